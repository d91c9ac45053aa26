"""Partially dependent models (seed 002, 3.2).

The models of a chain are built one after the other in one photogrammetric frame: the angular
elements of the left image of each next pair are not chosen freely, as for independent models,
but are those the previous pair gave to that image (its right image). Only the right image's
elements and the base direction are solved (relative orientation in the "left-image" system,
with the left image fixed), so every model's axes are the block's; the models differ only in
scale (each base has an arbitrary length) and origin. Each next model is brought to the scale of
the block by its tie points, its origin at the shared projection centre (seed 002, 3.2: "the next
model is brought to the scale of the previous one by tie points", eqs. 3.3-3.7 with the rotation
fixed). The joined strip is then oriented by control and its deformation removed as for
independent models (3.1.1, eqs. 3.8-3.15: :mod:`stereo.block.strip_polynomial`), or adjusted with
control (:mod:`stereo.block.model_adjust`).

Frames: block = the first model's frame; the left image's photo vectors (x, y, -f) are turned by
its block rotation into virtual photo coordinates of a camera with the block's axes, so that the
"left-image" system's model frame is the block frame.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from numpy.typing import NDArray

from rectify.errors import RectifyError, StereoError, WeakGeometryWarning
from rectify.geometry.camera import Camera
from rectify.geometry.residuals import rms
from rectify.geometry.robust import robust_scale
from stereo.block.models import IndependentOptions, Model, ModelJoin, _BlockPoints
from stereo.block.types import Tracks
from stereo.pair.intersection import intersect
from stereo.relative import RelativeOrientation

__all__ = ["dependent_model", "join_dependent"]

F64 = NDArray[np.float64]


def _virtual(mm: F64, R: F64, f: float) -> F64:
    """Photo coordinates (N, 2) of the vectors R (x, y, -f): a camera with the block's axes, mm."""
    v = np.column_stack([mm, np.full(len(mm), -f)]) @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.column_stack([-f * v[:, 0] / v[:, 2], -f * v[:, 1] / v[:, 2]])


def dependent_model(a: int, b: int, rotation_a: F64, cams: list[Camera], tracks: Tracks, obs_mm: F64,
                    per_image: list[tuple[NDArray[np.int64], NDArray[np.int64]]], opts: IndependentOptions) -> Model:
    """The model of pair (a, b) with image a's block rotation ``rotation_a`` kept (seed 002, 3.2).

    Returns a :class:`~stereo.block.models.Model` whose frame has the block's axes (origin at the
    left centre, unit base): ``rotation_left`` is ``rotation_a``.

    Raises
    ------
    StereoError
        Too few common points, a failed relative orientation or intersection (the pair named).
    """
    names = tracks.images
    pa, ra = per_image[a]
    pb, rb = per_image[b]
    common, ia, ib = np.intersect1d(pa, pb, assume_unique=True, return_indices=True)
    label = f"{names[a]!r}-{names[b]!r}"
    if len(common) < opts.min_common:
        raise StereoError(f"pair {label} has {len(common)} common points; at least {opts.min_common} are needed "
                          "for a model")
    left, right = obs_mm[ra[ia]], obs_mm[rb[ib]]
    ca, cb = cams[a], cams[b]
    f = (ca.focal_length_mm, cb.focal_length_mm)
    Ra = np.asarray(rotation_a, dtype=np.float64)
    lv, rv = _virtual(left, Ra, f[0]), _virtual(right, Ra, f[1])
    ok_v = np.isfinite(lv).all(axis=1) & np.isfinite(rv).all(axis=1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", WeakGeometryWarning)
            ro = RelativeOrientation.from_points(lv[ok_v], rv[ok_v], focal_length_mm=f, system="left-image",
                                                 robust=opts.robust, initial="auto",
                                                 ids=[tracks.point_ids[t] for t in common[ok_v]],
                                                 pixel_size_mm=ca.pixel_size_mm, options=opts.relative)
    except RectifyError as err:
        raise StereoError(f"relative orientation of the dependent pair {label} failed: {err}") from err
    floor = opts.outlier_floor_px * ca.pixel_size_mm
    good_ro = (ro.weights > 0) & ~(ro.outlier & (np.abs(ro.residual_mm) > floor))
    rows = np.flatnonzero(ok_v)[good_ro]
    # the virtual left camera is the block's axes (R1 = I): the true rotations are R1 Ra and R2 Ra
    R_left = ro.rotation_left @ Ra
    R_right = ro.rotation_right @ Ra
    B = np.asarray(ro.base, dtype=np.float64)
    try:
        inter = intersect(left[rows], right[rows], rotation_left=R_left, rotation_right=R_right, base=B,
                          focal_length_mm=f, min_angle_rad=1e-9, sigma_mm=ca.pixel_size_mm)
    except RectifyError as err:
        raise StereoError(f"intersection of the dependent model of pair {label} failed: {err}") from err
    good = (inter.scale_left > 0) & (inter.scale_right > 0) & np.isfinite(inter.points).all(axis=1)
    cov = inter.covariance if inter.covariance is not None else np.zeros((len(inter), 3, 3))
    return Model(common[rows][good], inter.points[good], R_left, R_right, B, cov[good], len(common),
                 int(len(common) - len(rows)), ro.sigma0_mm, ro.condition_number)


def join_dependent(model: Model, left: str, right: str, centre: F64, block: _BlockPoints, opts: IndependentOptions
                   ) -> tuple[float, F64, F64, NDArray[np.bool_], ModelJoin]:
    """Bring a dependent model to the block's scale by its tie points, its origin at the shared centre.

    ``X = s m + C`` (no rotation: the model has the block's axes); ``s`` is the least-squares
    scale of the tie points' offsets from the centre, after trimming those beyond ``join_trim``
    robust scales of the median ratio.

    Returns
    -------
    scale, rotation (identity), translation (the centre), keep (model points kept), join record

    Raises
    ------
    StereoError
        Fewer than ``min_join_points`` tie points shared with the block (named).
    """
    have = block.count[model.tracks] > 0
    nj = int(have.sum())
    if nj < opts.min_join_points:
        raise StereoError(f"dependent model {left!r}-{right!r} shares {nj} tie points with the block so far; at least "
                          f"{opts.min_join_points} are needed to bring it to scale (add points in the triple overlap)")
    X, _cov = block.get(model.tracks[have])
    m = model.points[have]
    d = X - centre
    ratio = np.linalg.norm(d, axis=1) / np.maximum(np.linalg.norm(m, axis=1), 1e-300)
    use = np.ones(nj, dtype=bool)
    s = float(np.median(ratio))
    for _ in range(3):
        s = float(np.sum(m[use] * d[use]) / max(float(np.sum(m[use] ** 2)), 1e-300))
        r = np.linalg.norm(s * m - d, axis=1)
        sc = robust_scale(r[use])
        new = (r <= opts.join_trim * max(sc, 1e-300)) | (r <= opts.join_floor * s)
        if new.sum() < opts.min_join_points or np.array_equal(new, use):
            break
        use = new
    r = np.linalg.norm(s * m - d, axis=1)
    keep = np.ones(len(model.tracks), dtype=bool)
    keep[np.flatnonzero(have)[~use]] = False
    rms_ = rms(r[use]) if use.any() else float("nan")
    join = ModelJoin(left, right, model.n_relative, model.n_relative_outliers, model.sigma0_mm, model.condition_number,
                     nj, int((~use).sum()), s, rms_, rms_ / s if s > 0 else math.nan, 0.0)
    return s, np.eye(3), np.asarray(centre, dtype=np.float64).copy(), keep, join
