"""``stereo block --method independent-models``: the block adjusted by independent models (seed 002, 3.1-3.2).

Instead of the bundle adjustment, the block's pairs are formed into models
(:func:`stereo.block.independent.independent_models`; with ``--dependent-models`` partially
dependent ones, seed 002, 3.2) and then either

- adjusted together with the control and GNSS centres in one least-squares adjustment
  (:func:`stereo.block.model_adjust.adjust_models`, seed 002, 3.1.2; the default), or
- with ``--strip-polynomial DEGREE``: split into strips, each oriented by a similarity to its
  control and its polynomial deformation removed (:func:`stereo.block.strip_adjust.correct_strips`,
  seed 002, 3.1.1, eqs. 3.8-3.15).

The result is handed to :mod:`stereo.actions.block` as a
:class:`~stereo.block.bundle.result.BundleResult`, so the same files and report are written:
the image residuals are those of the adjusted points projected through the adjusted poses, the
standard errors those of the model adjustment (angles: of the models' rotations), the lines of
the summary name the method.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.camera import Camera
from stereo.block.bundle.adjust import BundleOptions
from stereo.block.bundle.result import BundleResult
from stereo.block.independent import independent_models, triangulate_tracks
from stereo.block.model_adjust import ModelAdjustOptions, adjust_models
from stereo.block.models import IndependentOptions
from stereo.block.strip_adjust import correct_strips
from stereo.block.strip_polynomial import STRIP_DEGREES
from stereo.block.types import BlockControl, GnssObservations, Pose, Tracks

__all__ = ["MODEL_METHOD", "ModelMethodOptions", "check_block_method", "run_models"]

#: the ``--method`` value of this module
MODEL_METHOD = "independent-models"
#: the methods ``stereo block`` runs through :func:`stereo.actions.block.run_block` (the bundle and this one)
CAMERA_METHODS = ("bundle", MODEL_METHOD)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ModelMethodOptions:
    """Options of ``--method independent-models``.

    Attributes
    ----------
    strip_polynomial : int or None
        Degree of the strip polynomial (:data:`stereo.block.strip_polynomial.STRIP_DEGREES`); None:
        the simultaneous adjustment with control.
    dependent : bool
        Partially dependent models (seed 002, 3.2).
    robust : bool
        Reject model points (adjustment) or refit with Huber weights (strip polynomial).
    """

    strip_polynomial: int | None = None
    dependent: bool = False
    robust: bool = True

    def __post_init__(self) -> None:
        if self.strip_polynomial is not None and self.strip_polynomial not in STRIP_DEGREES:
            raise InvalidInputError(f"--strip-polynomial must be one of {sorted(STRIP_DEGREES)}; got "
                                    f"{self.strip_polynomial!r}")


def check_block_method(method: str, models: ModelMethodOptions, bundle: BundleOptions | None = None) -> None:
    """Raise unless ``method`` is run by ``run_block`` and the model (and bundle) options go with it."""
    if method not in CAMERA_METHODS:
        raise InvalidInputError(f"unknown block method {method!r}; expected one of {list(CAMERA_METHODS)}")
    if method != MODEL_METHOD and (models.strip_polynomial is not None or models.dependent):
        raise InvalidInputError(f"--strip-polynomial and --dependent-models need --method {MODEL_METHOD}; got "
                                f"--method {method}")
    if method == MODEL_METHOD and bundle is not None and (bundle.self_calibrate or bundle.free_network):
        what = "--self-calibrate/--calibrate" if bundle.self_calibrate else "--free-network"
        raise InvalidInputError(f"{what} needs the bundle adjustment; --method {MODEL_METHOD} keeps the camera as "
                                "given and needs control or GNSS for its datum")


def run_models(cameras: Mapping[str, Camera], camera_of: Sequence[str], tracks: Tracks,
               control: BlockControl | None, gnss: GnssObservations | None, options: ModelMethodOptions,
               image_sigma_px: float, progress: Callable[[int, int], None] | None = None
               ) -> tuple[BundleResult, str, tuple[str, ...]]:
    """Orient the block by independent models; the result as a bundle result, its initial-orientation
    text and the summary lines of the method.

    Raises
    ------
    EstimationError
        Too little control for the method (the named minimum), a singular adjustment.
    StereoError
        A model with too few tie points (named), a failed relative orientation.
    """
    opts = options
    mb = independent_models(cameras, camera_of, tracks, options=IndependentOptions(dependent=opts.dependent),
                            progress=progress)
    kind = "partially dependent models (seed 002, 3.2)" if opts.dependent else "independent models"
    if opts.strip_polynomial is not None:
        if control is None:
            raise EstimationError(f"--strip-polynomial needs control: at least {STRIP_DEGREES[opts.strip_polynomial]} "
                                  f"control points per strip for degree {opts.strip_polynomial} (seed 002, eq. 3.12)")
        sc = correct_strips(mb, control, degree=opts.strip_polynomial, robust=opts.robust)
        poses, X, pstd = list(sc.poses), np.asarray(sc.points), np.asarray(sc.point_std)
        pose_std = np.full((len(poses), 6), np.nan)
        n_sigma = [np.asarray(p.residuals) for p in sc.polynomials]
        r = np.concatenate([v[np.isfinite(v)] for v in n_sigma]) if n_sigma else np.zeros(0)
        sigma0 = float(np.sqrt(np.mean(r ** 2))) if r.size else float("nan")
        ctrl_ids, ctrl_res = sc.control_ids, np.asarray(sc.control_residuals)
        chk_ids, chk_err, chk_std = sc.check_ids, np.asarray(sc.check_errors), np.asarray(sc.check_std)
        gres = np.zeros((0, 3))
        lines = (f"method: {kind} joined into strips, strip polynomial of degree {opts.strip_polynomial} "
                 "(seed 002, 3.1.1)", *sc.summary_lines())
        iters, conv, groups, red = 1, True, {"control": sigma0}, {}
        datum = (f"datum: each strip's control ({len(ctrl_ids)} control points in all; similarity and polynomial "
                 f"of degree {opts.strip_polynomial} per strip)",)
    else:
        ad = adjust_models(mb, control=control, gnss=gnss,
                           options=ModelAdjustOptions(image_sigma_px=image_sigma_px, robust=opts.robust))
        poses, X, pstd = list(ad.poses), np.asarray(ad.points), np.asarray(ad.point_std)
        pose_std = np.hstack([ad.angle_std, ad.position_std])
        sigma0 = ad.sigma0
        ctrl_ids, ctrl_res = ad.control_ids, np.asarray(ad.control_residuals)
        chk_ids, chk_err, chk_std = ad.check_ids, np.asarray(ad.check_errors), np.asarray(ad.check_std)
        gres = np.asarray(ad.gnss_residuals)
        lines = (f"method: {kind} adjusted together with the control (seed 002, 3.1.2)", *ad.summary_lines())
        iters, conv, groups, red = ad.iterations, ad.converged, {"model points": sigma0}, {"all": float(ad.redundancy)}
        datum = (f"datum: {len(ctrl_ids)} control points and {len(ad.gnss_images)} GNSS centres in the simultaneous "
                 "adjustment of the models",)
    res = _as_bundle(cameras, poses, tracks, X, pstd, pose_std, sigma0, groups, red, ctrl_ids, ctrl_res, chk_ids,
                     chk_err, chk_std, gres, iters, conv, datum)
    initial = (f"{kind} ({len(mb.models)} models)" + (f", strip polynomial of degree {opts.strip_polynomial}"
                                                      if opts.strip_polynomial is not None else
                                                      ", adjusted with control (no bundle adjustment)"))
    return res, initial, lines


def _as_bundle(cameras: Mapping[str, Camera], poses: list[Pose], tracks: Tracks, X: F64, pstd: F64, pose_std: F64,
               sigma0: float, groups: dict[str, float], red: dict[str, float], ctrl_ids: tuple[str, ...],
               ctrl_res: F64, chk_ids: tuple[str, ...], chk_err: F64, chk_std: F64, gres: F64, iters: int, conv: bool,
               datum: tuple[str, ...]) -> BundleResult:
    """The model method's result in the shape the block's writers and report take."""
    # tracks in no model: intersected through the adjusted poses
    miss = np.asarray(~np.isfinite(X).all(axis=1), dtype=bool)
    if miss.any():
        Xt, _used = triangulate_tracks(cameras, poses, tracks)
        X = np.where(miss[:, None], Xt, X)
        pstd = np.where(miss[:, None], np.nan, pstd)
    M = tracks.n_obs
    res_px = np.full((M, 2), np.nan)
    for i, p in enumerate(poses):
        rows = np.flatnonzero(tracks.obs_image == i)
        cam = cameras[p.camera]
        q = (X[tracks.obs_point[rows]] - p.position) @ p.rotation       # R^T (X - C) per row
        f = cam.focal_length_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            mm = np.column_stack([-f * q[:, 0] / q[:, 2], -f * q[:, 1] / q[:, 2]])
        ok = np.isfinite(mm).all(axis=1) & (q[:, 2] < 0)
        px = np.full((len(rows), 2), np.nan)
        if ok.any():
            px[ok] = cam.pixel_from_photo(mm[ok])
        res_px[rows] = tracks.obs_pixel[rows] - px
    bad = ~np.isfinite(res_px).all(axis=1)
    res_px[bad] = 0.0
    n_rays = np.bincount(tracks.obs_point[~bad], minlength=tracks.n_points)
    determined = np.isfinite(X).all(axis=1) & (n_rays >= 2)
    n = len(poses)
    pcov = np.zeros((n, 6, 6))
    pcov[:, np.arange(6), np.arange(6)] = pose_std ** 2
    warn = tuple(f"{int(bad.sum())} image observations could not be projected (points behind or at the camera)"
                 for _ in range(1) if bad.any())
    return BundleResult(
        cameras=dict(cameras), poses=tuple(poses), point_ids=tracks.point_ids, points=X, pose_std=pose_std,
        pose_covariance=pcov, correlation=np.zeros((0, 0)), correlation_names=(), interior_std={}, point_std=pstd,
        point_covariance=None, sigma0=sigma0 if math.isfinite(sigma0) else float("nan"), sigma0_groups=groups,
        variance_factors={}, redundancy_groups=red, residuals_px=res_px, weights=np.ones((M, 2)),
        standardized=np.full((M, 2), np.nan), redundancy_numbers=np.full((M, 2), np.nan),
        flagged=bad, control_ids=tuple(ctrl_ids), control_residuals=ctrl_res.reshape(-1, 3), flagged_control=(),
        check_ids=tuple(chk_ids), check_errors=chk_err.reshape(-1, 3), check_std=chk_std.reshape(-1, 3),
        gnss_residuals=gres.reshape(-1, 3), iterations=iters, converged=conv, datum=datum,
        datum_groups=("control",), condition_number=float("nan"), warnings=warn, points_determined=determined,
        iteration_limit=0)
