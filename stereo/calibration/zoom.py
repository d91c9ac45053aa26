"""Zoom cameras (seed 003, 1.6): the interior orientation as a function of the focal setting.

Each element ``e`` (``fx``, ``fy``, ``cx``, ``cy``, ``k1``, ...) calibrated at
settings ``z_1..z_m`` (a zoom ring reading, a nominal focal length, a lens
encoder count) is modelled by a polynomial of degree ``d`` in the normalised
setting ``u = (z - z_mid) / z_half``::

    e(z) = a_0 + a_1 u + ... + a_d u^d

fitted by weighted least squares with weights ``1 / se_i^2`` from each
calibration's standard errors. The coefficient covariance ``(A^T W A)^-1``
propagates to a standard error of the prediction at any setting. The fit's
``chi2 / dof`` per element says whether the polynomial explains the
calibrations within their standard errors (about 1) or not (much larger: raise
the degree or add settings).

:meth:`ZoomModel.zoom_camera` hands the fit to :class:`rectify.geometry.zoom.ZoomCamera`, the object
the commands evaluate at an image's focal setting (``stereo calibrate --zoom`` writes it as the zoom
camera JSON). Both refuse a setting outside the calibrated range (plus a margin of
:data:`rectify.geometry.zoom.ZOOM_MARGIN` of the span). :func:`held_out_checks` predicts each inner
setting from the others (leave one out) and compares with its own calibration.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.camera import zoom_camera_document
from rectify.geometry.zoom import ZoomCamera
from stereo.calibration.model import Intrinsics
from stereo.calibration.result import Calibration

logger = logging.getLogger(__name__)

__all__ = ["HeldOut", "ZoomModel", "held_out_checks", "min_settings"]

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ZoomModel:
    """Polynomial model of the interior orientation over the focal setting.

    Attributes
    ----------
    settings : (m,) float64
        Focal settings of the calibrations used.
    names : tuple of str
        Modelled elements.
    degree : int
    centre, half_range : float
        Normalisation of the setting.
    coefficients : dict name -> (degree + 1,) float64
    covariances : dict name -> (degree + 1, degree + 1) float64
    chi2_dof : dict name -> float
        Weighted residual sum of squares / (m - degree - 1); nan when m = degree + 1.
    width, height : int
    """

    settings: F64
    names: tuple[str, ...]
    degree: int
    centre: float
    half_range: float
    coefficients: dict[str, F64]
    covariances: dict[str, F64]
    chi2_dof: dict[str, float]
    width: int
    height: int

    @classmethod
    def from_calibrations(cls, settings: ArrayLike, calibrations: Sequence[Calibration], *, degree: int = 2,
                          names: Sequence[str] | None = None) -> ZoomModel:
        """Fit the model to calibrations at several focal settings.

        Raises
        ------
        InvalidInputError
            Mismatched lengths, repeated settings, a bad degree, different image sizes.
        CalibrationError
            Fewer calibrations than ``degree + 1``, or an element not estimated in every calibration.
        """
        z = np.asarray(settings, dtype=np.float64).reshape(-1)
        if len(z) != len(calibrations):
            raise InvalidInputError(f"{len(z)} settings for {len(calibrations)} calibrations")
        if not np.isfinite(z).all():
            raise InvalidInputError("focal settings must be finite")
        if len(np.unique(z)) != len(z):
            raise InvalidInputError(f"repeated focal settings: {z.tolist()}")
        if isinstance(degree, bool) or not isinstance(degree, int) or degree < 0:
            raise InvalidInputError(f"degree must be an integer >= 0; got {degree!r}")
        if len(z) < degree + 1:
            raise CalibrationError(f"too few focal settings for a degree-{degree} model: {len(z)} given, "
                                   f"at least {degree + 1} needed")
        sizes = {(c.intrinsics.width, c.intrinsics.height) for c in calibrations}
        if len(sizes) != 1:
            raise InvalidInputError(f"calibrations have different image sizes: {sorted(sizes)}")
        common = [n for n in calibrations[0].names if all(n in c.names for c in calibrations)]
        use = tuple(names) if names is not None else tuple(common)
        missing = [n for n in use if n not in common]
        if missing:
            raise CalibrationError(f"element(s) {missing} not estimated in every calibration")
        centre = float((z.max() + z.min()) / 2)
        half = float((z.max() - z.min()) / 2) or 1.0
        A = np.vander((z - centre) / half, degree + 1, increasing=True)
        coefs, covs, chi = {}, {}, {}
        for n in use:
            y = np.array([c.value(n) for c in calibrations])
            se = np.array([c.std_errors[n] for c in calibrations])
            if np.any(se <= 0):
                raise CalibrationError(f"element {n!r} has a zero standard error in some calibration")
            w = 1.0 / se ** 2
            N = A.T @ (A * w[:, None])
            C = np.linalg.inv(N)
            a = C @ (A.T @ (w * y))
            r = A @ a - y
            dof = len(z) - degree - 1
            coefs[n], covs[n] = a, C
            chi[n] = float(np.sum(w * r * r) / dof) if dof > 0 else math.nan
        sw, sh = next(iter(sizes))
        logger.info("zoom model: degree %d over %d settings; chi2/dof %s", degree, len(z), chi)
        return cls(z, use, degree, centre, half, coefs, covs, chi, sw, sh)

    def zoom_camera(self, unit: str = "") -> ZoomCamera:
        """The fit as a :class:`ZoomCamera` (``unit``: what the setting is, e.g. ``"mm"``)."""
        return ZoomCamera(self.settings, self.degree, self.centre, self.half_range, dict(self.coefficients),
                          dict(self.covariances), self.width, self.height, unit)

    def predict(self, setting: float) -> tuple[dict[str, float], dict[str, float]]:
        """Predicted elements and their standard errors at ``setting``.

        Raises
        ------
        InvalidInputError
            A setting that is not a finite number.
        CalibrationError
            A setting outside the calibrated range (:meth:`ZoomCamera.check_setting`).
        """
        return self.zoom_camera().predict(setting)

    def intrinsics(self, setting: float) -> Intrinsics:
        """The predicted interior orientation at ``setting`` (elements not modelled are 0)."""
        v, _ = self.predict(setting)
        f = v.get("f")
        fx = v.get("fx", f)
        fy = v.get("fy", f)
        if fx is None or fy is None or "cx" not in v or "cy" not in v:
            raise CalibrationError("the zoom model lacks the focal length or the principal point")
        return Intrinsics(fx=fx, fy=fy, cx=v["cx"], cy=v["cy"], width=self.width, height=self.height,
                          **{k: v.get(k, 0.0) for k in ("k1", "k2", "k3", "p1", "p2")})

    def to_dict(self, unit: str = "", **extra: Any) -> dict[str, Any]:
        """The zoom camera JSON (``rectify-stereo/zoom-camera``, ``docs/formats.md``), with each element's
        chi2/dof and ``extra`` keys (informative, not read back)."""
        return zoom_camera_document(self.zoom_camera(unit), chi2_dof=dict(self.chi2_dof), **extra)


def min_settings(degree: int) -> int:
    """Fewest focal settings a zoom model of ``degree`` needs (``degree + 1``)."""
    return degree + 1


@dataclass(frozen=True)
class HeldOut:
    """One setting predicted by the model of the others: the normalised differences per element,
    ``(predicted - calibrated) / sqrt(se_pred^2 + se_cal^2)``."""

    setting: float
    z: dict[str, float]

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(np.square(list(self.z.values())))))

    @property
    def worst(self) -> tuple[str, float]:
        n = max(self.z, key=lambda k: abs(self.z[k]))
        return n, self.z[n]


def held_out_checks(settings: ArrayLike, calibrations: Sequence[Calibration], *, degree: int = 2,
                    names: Sequence[str] | None = None) -> list[HeldOut]:
    """Leave one out: each inner setting (never the ends: that would extrapolate) predicted by the model
    fitted to the other settings. Empty when fewer than ``degree + 2`` settings."""
    z = np.asarray(settings, dtype=np.float64).reshape(-1)
    if len(z) < degree + 2:
        return []
    order = np.argsort(z)
    out = []
    for k in order[1:-1]:
        keep = [i for i in range(len(z)) if i != k]
        zm = ZoomModel.from_calibrations(z[keep], [calibrations[i] for i in keep], degree=degree, names=names)
        val, se = zm.predict(float(z[k]))
        cal = calibrations[k]
        out.append(HeldOut(float(z[k]), {n: (val[n] - cal.value(n)) / math.hypot(se[n], cal.std_errors[n])
                                         for n in zm.names}))
    return out
