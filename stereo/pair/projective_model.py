"""Affine and projective orientation of a pair's model to control (seed 003, sections 3.3.1-3.3.2).

A model is formed by linear intersection (:func:`stereo.pair.projective.triangulate_projective`) of
two cameras:

- a *projective model* from the canonical cameras of a fundamental matrix (no camera known): the
  scene up to a 3D projective transformation; only :class:`~stereo.pair.projective.Projective3D`
  (15 parameters, at least 5 control points not all on one plane) orients it;
- a *similar model* from a metric relative orientation (rotations and unit base, photo vectors of
  a known camera): the scene up to a similarity, oriented by
  :class:`~stereo.pair.projective.Affine3D` (12 parameters, at least 4 non-coplanar control points;
  seed 003, 3.3.1, "affine exterior orientation of a similar model") or by the projective
  transformation (3.3.2, which the seed applies to similar and projective models alike).

The transformation is fitted in the control's own frame (no topocentric reduction: the 12 or 15
parameters absorb a map projection's scale better than a similarity does). Control rows without
object coordinates are extra tie points; check points are intersected and transformed but not used
in the fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.points import ControlTable, as_ids, as_pair
from rectify.geometry.residuals import ResidualTable, rms
from stereo.pair.projective import Affine3D, Projective3D, triangulate_projective

__all__ = ["TRANSFORMS", "TransformedModel", "build_transformed_model", "metric_cameras"]

#: model-to-object transformations of ``stereo model --transform``
TRANSFORMS = ("similarity", "affine", "projective")


def metric_cameras(rotation_left: ArrayLike, rotation_right: ArrayLike, base: ArrayLike
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(3, 4) cameras of a metric relative orientation acting on normalised photo coordinates.

    A model point X (model frame, left centre at 0, right centre at the unit ``base``) is seen along
    the photo vector u = R^T (X - C) ~ (x, y, -f), i.e. at (-x / f, -y / f) in homogeneous form
    (u / -f); so P = R^T [I | -C] maps X to (-x / f, -y / f, 1).
    """
    R1 = np.asarray(rotation_left, dtype=np.float64).reshape(3, 3)
    R2 = np.asarray(rotation_right, dtype=np.float64).reshape(3, 3)
    b = np.asarray(base, dtype=np.float64).reshape(3)
    P1 = np.hstack([R1.T, np.zeros((3, 1))])
    P2 = np.hstack([R2.T, (-R2.T @ b).reshape(3, 1)])
    return P1, P2


def _reproject(P: NDArray, Xh: NDArray) -> NDArray:
    p = Xh @ P.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


@dataclass(frozen=True, eq=False)
class TransformedModel:
    """A pair's model oriented to control by a 3D affine or projective transformation.

    Attributes
    ----------
    ids : tuple of str
        Tie points, then the control rows (control, check and extra tie points).
    model : (N, 4) float64
        Homogeneous model points (unit rows).
    points : (N, 3) float64
        Object coordinates (the control's frame and units).
    std : (N, 3) float64
        Standard deviations of ``points`` propagated from the transformation's covariance (NaN
        without redundancy).
    transform : Affine3D or Projective3D
    transform_name : {"affine", "projective"}
    model_kind : {"projective", "similar"}
    is_control, is_check : (N,) bool
    image_residual_px : (N,) float64
        Rms over both images of each point's reprojection residual (how well its rays meet), pixels.
    crs : str or None
    units : str
        Object units label (``"m"`` unless the control says otherwise).
    """

    ids: tuple[str, ...]
    model: NDArray[np.float64]
    points: NDArray[np.float64]
    std: NDArray[np.float64]
    transform: Affine3D | Projective3D
    transform_name: str
    model_kind: str
    is_control: NDArray[np.bool_]
    is_check: NDArray[np.bool_]
    observed: NDArray[np.float64]
    image_residual_px: NDArray[np.float64]
    crs: str | None = None
    units: str = "m"

    @property
    def control_rms(self) -> float:
        """Rms of the control residuals (all three coordinates), object units."""
        v = self.points[self.is_control] - self.observed[self.is_control]
        return float(np.sqrt(np.mean(np.sum(v * v, axis=1))))

    @property
    def check_rms(self) -> float | None:
        """Rms 3D error at the check points, object units (``None`` without checks)."""
        if not self.is_check.any():
            return None
        v = self.points[self.is_check] - self.observed[self.is_check]
        return float(np.sqrt(np.mean(np.sum(v * v, axis=1))))

    def residual_table(self) -> ResidualTable:
        """Control and check residuals (adjusted - observed) as a :class:`ResidualTable`."""
        m = self.is_control | self.is_check
        return ResidualTable(
            step=f"{self.transform_name} orientation of the {self.model_kind} model",
            ids=[i for i, k in zip(self.ids, m, strict=True) if k], observed=self.observed[m],
            adjusted=self.points[m], units=self.units, components=("dx", "dy", "dz"),
            check=self.is_check[m], n_params=self.transform.n_params, sigma0=self.transform.sigma0,
            extra={"redundancy": self.transform.redundancy})

    def summary_lines(self) -> list[str]:
        t = self.transform
        nc, nk = int(self.is_control.sum()), int(self.is_check.sum())
        out = [f"{self.model_kind} model of {len(self.ids)} points; reprojection RMS "
               f"{rms(self.image_residual_px[np.isfinite(self.image_residual_px)]):.3f} px",
               f"{self.transform_name} orientation ({t.n_params} parameters) to {nc} control points "
               f"(at least {t.min_points}), redundancy {t.redundancy}: sigma0 "
               + ("n/a" if t.sigma0 is None else f"{t.sigma0:.4g} {self.units}")
               + f", control RMSE {self.control_rms:.4g} {self.units}"]
        if nk:
            out.append(f"check points: {nk}, RMSE {self.check_rms:.4g} {self.units}")
        if self.model_kind == "projective":
            out.append("no camera: projective model, no metric elements (rotations, base, focal length)")
        return out

    def to_dict(self) -> dict[str, Any]:
        """The orientation JSON body (``docs/formats.md``, model orientation)."""
        m = self.is_control | self.is_check
        pts = []
        for i in np.flatnonzero(m):
            v = self.points[i] - self.observed[i]
            pts.append({"id": self.ids[i], "check": bool(self.is_check[i]), "residual": v.tolist()})
        return {
            "transform": self.transform_name, "model": self.model_kind, "crs": self.crs, "units": self.units,
            "parameters": self.transform.to_dict(), "n_control": int(self.is_control.sum()),
            "n_check": int(self.is_check.sum()), "control_rmse": self.control_rms, "check_rmse": self.check_rms,
            "reprojection_rmse_px": rms(self.image_residual_px[np.isfinite(self.image_residual_px)]),
            "control": pts,
        }


def build_transformed_model(cameras: tuple[ArrayLike, ArrayLike], left: ArrayLike, right: ArrayLike, *,
                            transform: str, model_kind: str, ids: Sequence[str] | None = None,
                            control: ControlTable | None = None,
                            control_image: tuple[ArrayLike, ArrayLike] | None = None,
                            check_ids: Sequence[str] = (), px_per_unit: tuple[float, float] = (1.0, 1.0),
                            units: str = "m") -> TransformedModel:
    """Intersect, then orient the model to control by a 3D affine or projective transformation.

    Parameters
    ----------
    cameras : ((3, 4), (3, 4))
        Left and right cameras acting on the image coordinates given (pixels for a projective model,
        normalised photo coordinates for a similar one, see :func:`metric_cameras`).
    left, right : (N, 2) array_like
        Tie points in the cameras' image coordinates.
    transform : {"affine", "projective"}
    model_kind : {"projective", "similar"}
        A projective model accepts only the projective transformation.
    ids : (N,) str, optional
    control : ControlTable
        Object coordinates (rows with NaN are extra tie points).
    control_image : ((M, 2), (M, 2))
        The control points' image coordinates (as ``left``/``right``).
    check_ids : sequence of str
        Control ids used only as checks.
    px_per_unit : (float, float)
        Pixels per image-coordinate unit of the left and right image (reprojection figures).
    units : str

    Raises
    ------
    InvalidInputError
        No control, the affine transformation of a projective model, unknown check ids.
    EstimationError
        Too few control points (the minimum named), coplanar control, points at infinity.
    """
    if transform not in ("affine", "projective"):
        raise InvalidInputError(f"unknown transformation {transform!r}; expected 'affine' or 'projective'")
    if model_kind == "projective" and transform != "projective":
        raise InvalidInputError("a projective model (no camera) is oriented only by the 15-parameter projective "
                                f"transformation; got {transform!r} (use --transform projective)")
    if control is None or control_image is None:
        raise InvalidInputError(f"the {transform} orientation needs control (--control)")
    lt, rt = as_pair(left, right, names=("left", "right"))
    tie_ids = as_ids(ids, len(lt))
    cl, cr = as_pair(control_image[0], control_image[1], names=("control left", "control right"))
    cids = tuple(str(i) for i in control.ids)
    unknown = sorted(set(check_ids) - set(cids))
    if unknown:
        raise InvalidInputError(f"check id(s) {unknown} are not in the control file")
    all_ids = tie_ids + cids
    if len(set(all_ids)) != len(all_ids):
        dup = sorted({i for i in all_ids if all_ids.count(i) > 1})[:3]
        raise InvalidInputError(f"ids occur twice among tie and control points: {dup}")
    L = np.vstack([lt, cl])
    R = np.vstack([rt, cr])
    P1, P2 = (np.asarray(c, dtype=np.float64) for c in cameras)
    Xh = triangulate_projective([P1, P2], [L, R])
    if not np.isfinite(Xh).all():
        raise EstimationError("intersection failed for some points (rays not seen in both images)")
    e1 = (_reproject(P1, Xh) - L) * px_per_unit[0]
    e2 = (_reproject(P2, Xh) - R) * px_per_unit[1]
    img_res = np.sqrt((np.sum(e1 * e1, axis=1) + np.sum(e2 * e2, axis=1)) / 2)
    n_tie = len(lt)
    xyz = np.vstack([np.full((n_tie, 3), np.nan), np.asarray(control.xyz, dtype=np.float64)])
    known = np.isfinite(xyz).all(axis=1)
    is_check = np.array([i in set(check_ids) for i in all_ids]) & known
    is_ctrl = known & ~is_check
    src = Xh[is_ctrl]
    with np.errstate(divide="ignore", invalid="ignore"):
        src3 = Xh[:, :3] / Xh[:, 3:4]
    if transform == "affine":
        if not np.isfinite(src3[is_ctrl]).all():
            raise EstimationError("a control point is at infinity in the model (parallel rays)")
        T: Affine3D | Projective3D = Affine3D.from_points(src3[is_ctrl], xyz[is_ctrl])
        pts = T(np.where(np.isfinite(src3), src3, 0.0))
        pts[~np.isfinite(src3).all(axis=1)] = np.nan
        std = T.point_std(np.where(np.isfinite(src3), src3, 0.0))
    else:
        T = Projective3D.from_points(src, xyz[is_ctrl])
        pts = T(Xh)
        std = T.point_std(Xh)
    return TransformedModel(ids=all_ids, model=Xh, points=pts, std=std, transform=T, transform_name=transform,
                            model_kind=model_kind, is_control=is_ctrl, is_check=is_check, observed=xyz,
                            image_residual_px=img_res, crs=control.crs, units=units)
