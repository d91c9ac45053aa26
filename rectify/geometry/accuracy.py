"""Accuracy statements of check points in the standard forms users hand to clients.

From the errors of N check points (product minus the surveyed truth, ground units, (N, 2) for a
planimetric product such as an orthophoto or (N, 3) with heights), :class:`AccuracyStatement` gives

- per-axis mean error, standard deviation and RMSE, ``RMSE_r = sqrt(RMSE_x^2 + RMSE_y^2)`` (the
  radial RMSE, ASPRS's ``RMSE_H``), ``RMSE_z`` (``RMSE_V``) and ``RMSE_3D = sqrt(RMSE_r^2 + RMSE_z^2)``;
- the two-sided confidence interval of each RMSE (default 95 %), from ``n RMSE^2 / sigma^2 ~ chi^2(n)``
  for one axis and the Welch-Satterthwaite degrees of freedom for the radial and 3D figures (errors
  taken as zero-mean normal; the interval says how far a figure from few check points can be from the
  product's true RMSE);
- ``CE90`` and ``LE90`` (FGDC NSSDA 1998 and the 90 % circular/linear error of the NGA/ISO use):
  ``LE90 = 1.6449 RMSE_z``; ``CE90`` is the radius holding 90 % of a zero-mean normal horizontal error
  with standard deviations ``RMSE_x`` and ``RMSE_y``, solved exactly (``1.5175 RMSE_r`` when the two are
  equal; up to ``1.6449 RMSE_r`` when one dominates); beside them the 90th percentiles of the observed
  radial and vertical errors;
- the ASPRS Positional Accuracy Standards for Digital Geospatial Data, Edition 2, Version 1.0 (2023)
  form: the product's ``RMSE_H = sqrt(RMSE_H1^2 + RMSE_H2^2)`` and ``RMSE_V = sqrt(RMSE_V1^2 +
  RMSE_V2^2)`` with ``H1``/``V1`` the check points' figures and ``H2``/``V2`` the accuracy of the check
  points' own survey (Edition 2 counts it), the "tested to meet" sentence, and the edition's minimum of
  30 check points (a statement from fewer says so: Edition 2 then allows only "produced to meet").

Units: those of the errors (metres for map CRSs); the ASPRS sentence is written in centimetres when the
unit is metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import chdtri, ndtr

from rectify.errors import InvalidInputError
from rectify.geometry.residuals import ResidualTable

__all__ = ["ASPRS_MIN_CHECKPOINTS", "AccuracyStatement", "ce90", "check_point_statement", "rmse_interval"]

#: Edition 2 (2023) of the ASPRS standards asks for at least 30 check points (at most 120 are needed)
ASPRS_MIN_CHECKPOINTS = 30
#: Two-sided 90 % factor of the standard normal (LE90 = LE90_FACTOR x RMSE_z)
LE90_FACTOR = 1.6448536269514722
_GL_X, _GL_W = np.polynomial.legendre.leggauss(96)


def _rms(a: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def rmse_interval(rmse: float, dof: float, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided confidence interval of a true RMSE from an observed one with ``dof`` degrees of freedom.

    ``dof * rmse^2 / sigma^2`` is chi-square with ``dof`` degrees of freedom for zero-mean normal errors,
    so ``sigma`` lies in ``[rmse sqrt(dof / chi2_hi), rmse sqrt(dof / chi2_lo)]`` with probability
    ``confidence``.
    """
    if not (0 < confidence < 1):
        raise InvalidInputError(f"the confidence level must lie in (0, 1); got {confidence!r}")
    if not (dof > 0 and math.isfinite(rmse)):
        return (float("nan"), float("nan"))
    a = (1.0 - confidence) / 2.0
    hi = float(chdtri(dof, a))        # upper quantile: P(X > hi) = a
    lo = float(chdtri(dof, 1.0 - a))  # lower quantile: P(X > lo) = 1 - a
    return (rmse * math.sqrt(dof / hi), rmse * math.sqrt(dof / lo))


def _radial_cdf(r: float, sx: float, sy: float) -> float:
    """P(sqrt(X^2 + Y^2) <= r) for independent X ~ N(0, sx^2), Y ~ N(0, sy^2) (Gauss-Legendre over x)."""
    if r <= 0:
        return 0.0
    x = r * _GL_X
    inner = 2.0 * ndtr(np.sqrt(np.maximum(r * r - x * x, 0.0)) / sy) - 1.0
    dens = np.exp(-0.5 * (x / sx) ** 2) / (sx * math.sqrt(2.0 * math.pi))
    return float(r * np.sum(_GL_W * dens * inner))


def ce90(sx: float, sy: float) -> float:
    """Radius of the 90 % circular error of independent zero-mean normal errors with standard deviations
    ``sx`` and ``sy`` (ground units); 2.1460 sx for sx = sy, 1.6449 max(sx, sy) when the other is 0."""
    sx, sy = float(sx), float(sy)
    if not (math.isfinite(sx) and math.isfinite(sy)) or sx < 0 or sy < 0:
        return float("nan")
    big, small = max(sx, sy), min(sx, sy)
    if big == 0:
        return 0.0
    if small < 1e-6 * big:
        return LE90_FACTOR * big
    lo, hi = LE90_FACTOR * big, 2.1460 * big * 1.001   # the radius lies between these
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if _radial_cdf(mid, big, small) < 0.9:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class AccuracyStatement:
    """Check-point accuracy of a product (see the module docstring for every figure).

    Attributes
    ----------
    n : int
        Number of check points.
    mean, std, rmse : (2,) or (3,) float64
        Per-axis mean error, standard deviation (n - 1) and RMSE (x, y[, z]), ground units.
    rmse_r, rmse_z, rmse_3d : float
        Radial (horizontal), vertical (NaN without heights) and 3D RMSE.
    interval_x, interval_y, interval_r, interval_z : (float, float)
        Confidence interval of each RMSE at ``confidence``.
    ce90, le90 : float
        90 % circular and linear errors from the RMSEs (normal errors).
    ce90_observed, le90_observed : float
        90th percentiles of the observed radial and vertical errors.
    survey_rmse_h, survey_rmse_v : float
        Accuracy of the check points' own survey (0 when not given).
    confidence : float
    units : str
    """

    n: int
    mean: NDArray[np.float64]
    std: NDArray[np.float64]
    rmse: NDArray[np.float64]
    rmse_r: float
    rmse_z: float
    rmse_3d: float
    interval_x: tuple[float, float]
    interval_y: tuple[float, float]
    interval_r: tuple[float, float]
    interval_z: tuple[float, float]
    ce90: float
    le90: float
    ce90_observed: float
    le90_observed: float
    survey_rmse_h: float = 0.0
    survey_rmse_v: float = 0.0
    confidence: float = 0.95
    units: str = "m"

    @classmethod
    def from_errors(cls, errors: ArrayLike, *, survey_rmse_h: float = 0.0, survey_rmse_v: float = 0.0,
                    confidence: float = 0.95, units: str = "m") -> AccuracyStatement:
        """The statement of check-point ``errors`` (N, 2) or (N, 3), product minus truth, ground units.

        ``survey_rmse_h`` / ``survey_rmse_v``: the RMSE_H / RMSE_V of the check points' own survey (ASPRS
        Edition 2 adds them to the product's figures). Raises :class:`InvalidInputError` for no check
        point, a wrong shape or a non-finite error.
        """
        e = np.asarray(errors, dtype=np.float64)
        if e.ndim != 2 or e.shape[1] not in (2, 3):
            raise InvalidInputError(f"check-point errors must be an (N, 2) or (N, 3) array; got shape {e.shape}")
        if len(e) == 0:
            raise InvalidInputError("an accuracy statement needs at least 1 check point; got 0")
        bad = np.flatnonzero(~np.isfinite(e).all(axis=1))
        if len(bad):
            raise InvalidInputError(f"check point {int(bad[0])} has a non-finite error {e[bad[0]].tolist()}")
        for name, v in (("survey_rmse_h", survey_rmse_h), ("survey_rmse_v", survey_rmse_v)):
            if not (math.isfinite(v) and v >= 0):
                raise InvalidInputError(f"{name} must be a finite number >= 0; got {v!r}")
        n = len(e)
        rmse = np.sqrt(np.mean(e * e, axis=0))
        std = e.std(axis=0, ddof=1) if n > 1 else np.full(e.shape[1], np.nan)
        rx, ry = float(rmse[0]), float(rmse[1])
        rr = math.hypot(rx, ry)
        rz = float(rmse[2]) if e.shape[1] == 3 else float("nan")
        r3 = math.hypot(rr, rz) if e.shape[1] == 3 else float("nan")

        def sat_dof(parts: list[float]) -> float:  # Welch-Satterthwaite: sum of n-dof chi-squares scaled by s^2
            den = sum(p ** 4 for p in parts) / n
            return (sum(p * p for p in parts) ** 2) / den if den > 0 else float(n * len(parts))

        radial = np.hypot(e[:, 0], e[:, 1])
        return cls(n=n, mean=e.mean(axis=0), std=std, rmse=rmse, rmse_r=rr, rmse_z=rz, rmse_3d=r3,
                   interval_x=rmse_interval(rx, n, confidence), interval_y=rmse_interval(ry, n, confidence),
                   interval_r=rmse_interval(rr, sat_dof([rx, ry]), confidence),
                   interval_z=rmse_interval(rz, n, confidence) if e.shape[1] == 3 else (float("nan"),) * 2,
                   ce90=ce90(rx, ry), le90=LE90_FACTOR * rz if e.shape[1] == 3 else float("nan"),
                   ce90_observed=float(np.percentile(radial, 90)),
                   le90_observed=float(np.percentile(np.abs(e[:, 2]), 90)) if e.shape[1] == 3 else float("nan"),
                   survey_rmse_h=float(survey_rmse_h), survey_rmse_v=float(survey_rmse_v), confidence=confidence,
                   units=units)

    @classmethod
    def vertical(cls, errors_z: ArrayLike, *, survey_rmse_v: float = 0.0, confidence: float = 0.95,
                 units: str = "m") -> AccuracyStatement:
        """The vertical-only statement of a height product (a DSM at check points): ``errors_z`` (N,) heights
        minus the surveyed heights; the horizontal figures are NaN and left out of :meth:`lines` and the ASPRS
        sentences (RMSE_z, its interval, LE90, the RMSE_V class)."""
        ez = np.asarray(errors_z, dtype=np.float64)
        if ez.ndim != 1:
            raise InvalidInputError(f"vertical check-point errors must be an (N,) array; got shape {ez.shape}")
        s = cls.from_errors(np.column_stack([np.zeros_like(ez), np.zeros_like(ez), ez]), survey_rmse_v=survey_rmse_v,
                            confidence=confidence, units=units)
        nan2 = (float("nan"), float("nan"))
        return replace(s, mean=np.array([np.nan, np.nan, s.mean[2]]), std=np.array([np.nan, np.nan, s.std[2]]),
                       rmse=np.array([np.nan, np.nan, s.rmse[2]]), rmse_r=float("nan"), rmse_3d=float("nan"),
                       interval_x=nan2, interval_y=nan2, interval_r=nan2, ce90=float("nan"),
                       ce90_observed=float("nan"))

    @property
    def has_heights(self) -> bool:
        return len(self.rmse) == 3

    @property
    def has_plan(self) -> bool:
        """False for a vertical-only statement (:meth:`vertical`)."""
        return math.isfinite(self.rmse_r)

    @property
    def asprs_rmse_h(self) -> float:
        """The product's RMSE_H by ASPRS Edition 2: sqrt(RMSE_H1^2 + RMSE_H2^2) (H2: the check points' survey)."""
        return math.hypot(self.rmse_r, self.survey_rmse_h)

    @property
    def asprs_rmse_v(self) -> float:
        """The product's RMSE_V by ASPRS Edition 2 (NaN without heights)."""
        return math.hypot(self.rmse_z, self.survey_rmse_v) if self.has_heights else float("nan")

    def _fmt(self, v: float) -> str:
        return f"{v:.3f} {self.units}"

    def _ci(self, iv: tuple[float, float]) -> str:
        return f"[{iv[0]:.3f}, {iv[1]:.3f}]"

    def asprs_sentences(self) -> list[str]:
        """The ASPRS Edition 2 accuracy statement (centimetres when the unit is metres)."""
        cm = self.units == "m"
        scale, unit = (100.0, "cm") if cm else (1.0, self.units)
        enough = self.n >= ASPRS_MIN_CHECKPOINTS
        verb = "was tested to meet" if enough else "was produced to meet"
        std = "ASPRS Positional Accuracy Standards for Digital Geospatial Data, Edition 2, Version 1.0 (2023)"
        h = self.asprs_rmse_h * scale
        out = [f"This data set {verb} the {std} for a {math.ceil(h * 10) / 10:g} ({unit}) RMSE_H horizontal "
               f"positional accuracy class. The tested horizontal positional accuracy was found to be RMSE_H = "
               f"{h:.1f} ({unit})."] if self.has_plan else []
        if self.has_heights:
            v = self.asprs_rmse_v * scale
            out.append(f"This data set {verb} the {std} for a {math.ceil(v * 10) / 10:g} ({unit}) RMSE_V vertical "
                       f"positional accuracy class. The tested vertical positional accuracy was found to be "
                       f"RMSE_V = {v:.1f} ({unit}).")
        if not enough:
            out.append(f"({self.n} check points: Edition 2 asks for at least {ASPRS_MIN_CHECKPOINTS} to state "
                       "\"tested to meet\".)")
        if self.survey_rmse_h or self.survey_rmse_v:
            out.append(f"(Check points' own survey accuracy included: RMSE_H2 {self.survey_rmse_h * scale:.1f} "
                       f"{unit}, RMSE_V2 {self.survey_rmse_v * scale:.1f} {unit}.)")
        return out

    def lines(self) -> list[str]:
        """The statement as report/console lines: per-axis figures, RMSE_r/RMSE_z with confidence
        intervals, CE90/LE90, the ASPRS form."""
        c = f"{self.confidence * 100:g} %"
        axes = ("xyz" if self.has_heights else "xy") if self.has_plan else "z"
        out = [f"accuracy statement from {self.n} check points ({self.units}; RMSE {c} confidence intervals "
               "in brackets):"]
        ivs = (self.interval_x, self.interval_y, self.interval_z)
        for a in axes:
            i = "xyz".index(a)
            out.append(f"  {a}: mean {self.mean[i]:+.3f}, std {self.std[i]:.3f}, RMSE {self.rmse[i]:.3f} "
                       f"{self._ci(ivs[i])}")
        if not self.has_plan:  # vertical only (a DSM)
            out += [f"  RMSE_z {self._fmt(self.rmse_z)} {self._ci(self.interval_z)}; LE90 {self._fmt(self.le90)} "
                    f"(observed {self.le90_observed:.3f})"]
            out.extend("  " + s for s in self.asprs_sentences())
            return out
        line = f"  RMSE_r {self._fmt(self.rmse_r)} {self._ci(self.interval_r)}"
        if self.has_heights:
            line += (f"; RMSE_z {self._fmt(self.rmse_z)} {self._ci(self.interval_z)}; "
                     f"RMSE_3D {self._fmt(self.rmse_3d)}")
        out.append(line)
        line = (f"  CE90 {self._fmt(self.ce90)} (NSSDA, from the RMSEs; observed 90th percentile "
                f"{self.ce90_observed:.3f})")
        if self.has_heights:
            line += f"; LE90 {self._fmt(self.le90)} (observed {self.le90_observed:.3f})"
        out.append(line)
        out.extend("  " + s for s in self.asprs_sentences())
        return out

    def to_dict(self) -> dict[str, object]:
        """JSON-ready figures (NaN as None)."""
        def f(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)

        d: dict[str, object] = {
            "n": self.n, "units": self.units, "confidence": self.confidence,
            "mean": [f(v) for v in self.mean], "std": [f(v) for v in self.std], "rmse": [f(v) for v in self.rmse],
            "rmse_r": f(self.rmse_r), "rmse_z": f(self.rmse_z), "rmse_3d": f(self.rmse_3d),
            "rmse_interval": {"x": [f(v) for v in self.interval_x], "y": [f(v) for v in self.interval_y],
                              "r": [f(v) for v in self.interval_r], "z": [f(v) for v in self.interval_z]},
            "ce90": f(self.ce90), "le90": f(self.le90), "ce90_observed": f(self.ce90_observed),
            "le90_observed": f(self.le90_observed),
            "asprs_2023": {"rmse_h": f(self.asprs_rmse_h), "rmse_v": f(self.asprs_rmse_v),
                           "survey_rmse_h": self.survey_rmse_h, "survey_rmse_v": self.survey_rmse_v,
                           "enough_checkpoints": self.n >= ASPRS_MIN_CHECKPOINTS,
                           "statement": " ".join(self.asprs_sentences())},
            "lines": self.lines(),
        }
        return d


def check_point_statement(table: ResidualTable, **kwargs: float) -> AccuracyStatement | None:
    """The statement of a residual table's check points (their residuals are the errors), or None when it
    has none or its units are not ground lengths (pixels, millimetres of the photo, degrees)."""
    if table.units in ("px", "mm", "pixel", "pixels") or table.units.startswith("deg") or table.check is None:
        return None
    chk = np.asarray(table.check, dtype=bool)
    if not chk.any() or table.residual.shape[1] not in (2, 3):
        return None
    return AccuracyStatement.from_errors(table.residual[chk], units=table.units, **kwargs)
