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
from stereo.calibration.model import Intrinsics
from stereo.calibration.result import Calibration

logger = logging.getLogger(__name__)

__all__ = ["ZoomModel"]

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

    def predict(self, setting: float) -> tuple[dict[str, float], dict[str, float]]:
        """Predicted elements and their standard errors at ``setting``.

        Extrapolation beyond the calibrated settings is logged as a warning.
        """
        z = float(setting)
        if not math.isfinite(z):
            raise InvalidInputError(f"setting must be finite; got {setting!r}")
        if z < self.settings.min() or z > self.settings.max():
            logger.warning("zoom model extrapolated to setting %g (calibrated %g..%g)", z, self.settings.min(),
                           self.settings.max())
        a = np.vander([(z - self.centre) / self.half_range], self.degree + 1, increasing=True)[0]
        val = {n: float(a @ self.coefficients[n]) for n in self.names}
        se = {n: float(math.sqrt(max(a @ self.covariances[n] @ a, 0.0))) for n in self.names}
        return val, se

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

    def to_dict(self) -> dict[str, Any]:
        return {"format": "rectify-stereo/zoom-model", "version": 1, "degree": self.degree,
                "settings": self.settings.tolist(), "centre": self.centre, "half_range": self.half_range,
                "width": self.width, "height": self.height,
                "elements": {n: {"coefficients": self.coefficients[n].tolist(),
                                 "covariance": self.covariances[n].tolist(), "chi2_dof": self.chi2_dof[n]}
                             for n in self.names}}
