"""The calibration result: a camera calibrated from target views, with its precision.

Its camera JSON (version 2, pixel or millimetre camera with standard errors and sigma0) is written by
:func:`rectify.formats.camera.intrinsics_document` (:meth:`Calibration.camera_dict`) and read back by
:func:`stereo.formats.calibration.camera_from_dict`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.camera import intrinsics_document
from rectify.geometry.rotation import angles_from_matrix, rodrigues
from stereo.calibration.adjust import Adjustment, Observations, adjust, free_parameters
from stereo.calibration.model import CV_FROM_PHOTO, Intrinsics
from stereo.calibration.start import Start, initial_orientation
from stereo.calibration.views import TargetView, check_inside

logger = logging.getLogger(__name__)

__all__ = ["Calibration", "ViewResult"]

F64 = NDArray[np.float64]


# ------------------------------------------------------------------- the result
@dataclass(frozen=True, eq=False)
class ViewResult:
    """One view of the target after the adjustment.

    Attributes
    ----------
    name : str
    ids : tuple of str
    pixel : (N, 2) float64
        Measured pixels.
    residuals : (N, 2) float64
        ``adjusted - observed``, px.
    weights : (N,) float64
        Robust weights.
    rotation : (3, 3) float64
        Camera -> object rotation, photo frame (x right, y up, z back).
    centre : (3,) float64
        Projection centre, object frame and units.
    angles : (3,) float64
        omega, phi, kappa of ``rotation``, rad.
    std_angles, std_centre : (3,) float64
        Their standard errors (rad; object units).
    """

    name: str
    ids: tuple[str, ...]
    pixel: F64
    residuals: F64
    weights: F64
    rotation: F64
    centre: F64
    angles: F64
    std_angles: F64
    std_centre: F64

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals ** 2, axis=1))))


def _eo(pose: F64) -> F64:
    Rcv = rodrigues(pose[:3])[0]
    R = Rcv.T @ CV_FROM_PHOTO
    C = -Rcv.T @ pose[3:]
    return np.concatenate([angles_from_matrix(R), C])


def _eo_std(pose: F64, cov: F64) -> F64:
    J = np.zeros((6, 6))
    for j in range(6):
        h = 1e-7 if j < 3 else 1e-7 * max(float(np.linalg.norm(pose[3:])), 1e-3)
        a, b = pose.copy(), pose.copy()
        a[j] += h
        b[j] -= h
        da = _eo(a) - _eo(b)
        da[:3] = (da[:3] + np.pi) % (2 * np.pi) - np.pi
        J[:, j] = da / (2 * h)
    return np.sqrt(np.clip(np.diag(J @ cov @ J.T), 0, None))


@dataclass(frozen=True, eq=False)
class Calibration:
    """A camera calibrated from target views (plane or 3D), with its precision.

    Build with :meth:`from_views` (any target) or :meth:`from_points` (one image
    of a 3D field).

    Attributes
    ----------
    intrinsics : Intrinsics
        Adjusted interior orientation, px.
    names : tuple of str
        Free interior unknowns (``f`` or ``fx, fy``, ``cx, cy``, distortion, ``sx, sy``).
    std_errors : dict name -> float
        Their standard errors (px; distortion unitless).
    correlation : (m, m) float64
        Correlations of the interior unknowns (in ``names`` order).
    sigma0_px : float
        A-posteriori standard deviation of unit weight (one image coordinate), px.
    rms_px : float
        RMS reprojection error as OpenCV reports it: sqrt(sum |v|^2 / N points), px.
    views : tuple of ViewResult
    start_method : str
    adjustment : Adjustment
        Full solution, covariance and residuals.
    """

    intrinsics: Intrinsics
    names: tuple[str, ...]
    std_errors: dict[str, float]
    correlation: F64
    sigma0_px: float
    rms_px: float
    views: tuple[ViewResult, ...]
    start_method: str
    robust: str | None
    adjustment: Adjustment
    start: Start | None = None

    # ----------------------------------------------------------------- builders
    @classmethod
    def from_views(cls, views: Sequence[TargetView], width: int, height: int, *, equal_focal: bool = False,
                   principal_point: bool = True, distortion: Sequence[str] = ("k1", "k2", "k3", "p1", "p2"),
                   symmetry: bool = False, robust: str | None = None,
                   start: tuple[F64, F64] | None = None) -> Calibration:
        """Calibrate one camera from views of a plane target or of a 3D test field.

        Parameters
        ----------
        views : sequence of TargetView
            Target points (object frame) and their measured pixels, one per image.
        width, height : int
            Image size, px.
        equal_focal : bool
            One principal distance (square pixels) instead of fx and fy.
        principal_point : bool
            Estimate the principal point (else it stays at the start: the image
            centre for plane targets with one view).
        distortion : sequence of str
            Free distortion coefficients (others fixed at 0).
        symmetry : bool
            Estimate the point of symmetry of distortion separately from the
            principal point (seed 003, 1.3).
        robust : str, optional
            M-estimator for robust weights (``huber``, ``tukey``, ``hampel``, ``andrews``).
        start : (interior (11,), poses (S, 6)), optional
            Start values (skips the search for a start, e.g. in Monte Carlo runs).

        Raises
        ------
        InvalidInputError
            Bad sizes, points outside the image (named), duplicate view names.
        CalibrationError
            Too few views or points, focal length unobservable, singular system.
        """
        views = list(views)
        if not views:
            raise CalibrationError("no views to calibrate from")
        for name, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or int(v) != v or v <= 0:
                raise InvalidInputError(f"image {name} must be a positive integer; got {v!r}")
        width, height = int(width), int(height)
        names = [v.name for v in views]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InvalidInputError(f"duplicate view name(s) {dup}")
        check_inside(views, width, height)
        planar = all(v.is_planar for v in views)
        if planar and principal_point and len(views) < 3:
            raise CalibrationError(f"too few views for a plane target: {len(views)} given, at least 3 needed "
                                   "(or fix the principal point)")
        free = free_parameters(equal_focal=equal_focal, principal_point=principal_point, distortion=distortion,
                               symmetry=symmetry)
        X = np.concatenate([v.object_xyz for v in views])
        obs = Observations(object_xyz=X, pixel=np.concatenate([v.pixel for v in views]),
                           camera=np.zeros(len(X), dtype=np.intp),
                           station=np.repeat(np.arange(len(views)), [v.n for v in views]))
        st: Start | None = None
        if start is None:
            st = initial_orientation(views, width, height, equal_focal=equal_focal)
            v0, p0 = st.interior, st.poses
            a = adjust(obs, [v0], [()], p0, tol=1e-8)  # exterior orientation only
            core = tuple(n for n in free if n in ("f", "fx", "fy", "cx", "cy", "cx*", "cy*"))
            a = adjust(obs, a.interiors, [core], a.poses, tol=1e-8)
            v0, p0 = a.interiors[0], a.poses
            method = st.method
        else:
            v0 = np.asarray(start[0], dtype=np.float64)
            p0 = np.asarray(start[1], dtype=np.float64)
            method = "given"
        a = adjust(obs, [v0], [free], p0, robust=robust, station_labels=names)
        intr = Intrinsics.from_vector(a.interiors[0], width, height, symmetry=symmetry)
        m = len(free)
        se = a.std_errors[:m]
        labels = tuple(n.rstrip("*") for n in free)
        std = dict(zip(labels, (float(s) for s in se), strict=True))
        fkey = "f" if equal_focal else "fx"
        if std[fkey] > 0.5 * intr.fx:
            raise CalibrationError(f"focal length unobservable: {intr.fx:.1f} +- {std[fkey]:.1f} px from these views "
                                   "(are they all parallel to the image plane?)")
        vres = []
        k0 = 0
        for s, tv in enumerate(views):
            sl = slice(k0, k0 + tv.n)
            k0 += tv.n
            pose = a.poses[s]
            eo = _eo(pose)
            o = m + 6 * s
            eos = _eo_std(pose, a.covariance[o:o + 6, o:o + 6])
            Rcv = rodrigues(pose[:3])[0]
            vres.append(ViewResult(tv.name, tv.ids, tv.pixel, a.residuals[sl], a.weights[sl], Rcv.T @ CV_FROM_PHOTO,
                                   eo[3:], eo[:3], eos[:3], eos[3:]))
        r = a.residuals
        rms = float(np.sqrt(np.sum(r * r) / len(r)))
        logger.info("calibration: %d views, rms %.4f px, sigma0 %.4f px", len(views), rms, a.sigma0)
        return cls(intr, labels, std, a.correlation[:m, :m].copy(), a.sigma0, rms, tuple(vres), method, robust, a,
                   st)

    @classmethod
    def from_points(cls, object_xyz: F64, pixel: F64, width: int, height: int, *, ids: Sequence[str] | None = None,
                    name: str = "image", **kwargs: Any) -> Calibration:
        """Calibrate from one image of a 3D test field (DLT start); keywords as :meth:`from_views`."""
        X = np.asarray(object_xyz, dtype=np.float64)
        ids_t = tuple(str(i) for i in ids) if ids is not None else tuple(f"p{i}" for i in range(len(X)))
        return cls.from_views([TargetView(name, X, np.asarray(pixel, dtype=np.float64), ids_t)], width, height,
                              **kwargs)

    # ----------------------------------------------------------------- derived
    @property
    def n_points(self) -> int:
        return sum(len(v.ids) for v in self.views)

    @property
    def pixel_error_std(self) -> F64:
        """Standard deviation of the x and y residuals (2,), px (the Bouguet toolbox's "pixel error")."""
        return np.std(self.adjustment.residuals, axis=0, ddof=1)

    @property
    def interior_covariance(self) -> F64:
        m = len(self.names)
        return self.adjustment.covariance[:m, :m].copy()

    def value(self, name: str) -> float:
        """Value of a named interior element (``f``, ``fx``, ``cx``, ``k1``, ...)."""
        i = self.intrinsics
        if name == "f":
            return i.fx
        v = getattr(i, name)
        if v is None:
            v = i.cx if name == "sx" else i.cy
        return float(v)

    def camera_dict(self, *, pixel_size_mm: float | None = None) -> dict[str, Any]:
        """The camera JSON (version 2) with standard errors and sigma0."""
        return intrinsics_document(self.intrinsics, std_errors=self.std_errors, sigma0_px=self.sigma0_px,
                                   pixel_size_mm=pixel_size_mm)

    def summary_lines(self) -> list[str]:
        """Human summary: counts, start, each interior element with its standard error, RMS, sigma0."""
        a = self.adjustment
        out = [f"calibration: {len(self.views)} view{'s' if len(self.views) != 1 else ''}, {self.n_points} points; "
               f"start: {self.start_method}; {a.iterations} iterations"
               + (f", {a.reweightings} reweightings ({self.robust})" if self.robust else "")]
        for n in self.names:
            unit = "" if n.startswith(("k", "p")) else " px"
            fmt = ".6f" if not unit else ".3f"
            out.append(f"  {n:>3} = {self.value(n):{fmt}}{unit} +- {self.std_errors[n]:{fmt}}")
        sx, sy = self.pixel_error_std
        out.append(f"RMS reprojection error {self.rms_px:.4f} px, sigma0 {self.sigma0_px:.4f} px "
                   f"(redundancy {a.redundancy}); residual std x {sx:.4f}, y {sy:.4f} px")
        corr = self.correlation.copy()
        np.fill_diagonal(corr, 0)
        if corr.size > 1:
            i, j = np.unravel_index(np.argmax(np.abs(corr)), corr.shape)
            out.append(f"largest correlation {self.names[i]}-{self.names[j]} {corr[i, j]:+.3f}; "
                       f"condition number {a.condition_number:.3g} (columns normalised)")
        worst = max(self.views, key=lambda v: v.rms_px)
        out.append(f"worst view {worst.name}: RMS {worst.rms_px:.4f} px")
        if self.robust:
            n_out = int(np.sum(a.weights < 0.05))
            out.append(f"robust ({self.robust}): {n_out} points with weight < 0.05")
        return out
