"""Residual tables: the one structure every estimator hands to reports.

A :class:`ResidualTable` holds, per observation, the observed and adjusted
values, the residual ``v = adjusted - observed`` (the least-squares
correction), the weight, the outlier flag and whether the point was a check
point withheld from the fit. Its summary separates the RMSE (plain root mean
square of |v| over fit points, with units) from sigma0 (the a-posteriori
standard deviation of unit weight, sqrt(v'Pv / (n - u))).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_write_text
from rectify.errors import InvalidInputError, ShapeError

__all__ = ["ResidualTable", "rms"]


def rms(a: ArrayLike) -> float:
    """Root mean square of all entries; NaN for an empty array."""
    x = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def _col(a: ArrayLike | None, n: int, default: Any, name: str, dtype=np.float64) -> NDArray:
    if a is None:
        return np.full(n, default, dtype=dtype)
    out = np.array(a, dtype=dtype, copy=True).reshape(-1)
    if out.shape != (n,):
        raise ShapeError(f"`{name}` must have shape ({n},); got {out.shape}", actual_shape=out.shape,
                         expected_shape=(n,))
    return out


@dataclass(frozen=True, eq=False)
class ResidualTable:
    """Per-observation residuals of one estimation step.

    Parameters
    ----------
    step : str
        Human name of the step, e.g. ``"GCP fit (homography)"``.
    ids : (N,) sequence of str
        Point identifiers.
    observed, adjusted : (N, k) float64
        Observed and adjusted (model-predicted) values, ``units``.
    units : str
        Units of observed/adjusted/residuals, e.g. ``"px"``, ``"m"``, ``"mm"``.
    components : tuple of str
        Names of the k residual components, e.g. ``("dx", "dy")``.
    weights : (N,) float64, optional
        Final weights (robust estimation lowers them); default 1.
    outlier : (N,) bool, optional
        Flagged outliers (excluded or down-weighted); default False.
    check : (N,) bool, optional
        Check points, withheld from the fit; default False.
    std : (N,) float64, optional
        Standard deviation of each residual's norm, ``units``; when given, the
        normalised residual is |v| / std, otherwise |v| / sigma0.
    position_px : (N, 2) float64, optional
        Where to draw each residual over the image (pixel frame).
    sigma0 : float, optional
        A-posteriori standard deviation of unit weight; computed from the fit
        points and ``n_params`` when omitted.
    n_params : int
        Number of estimated parameters (for the redundancy n*k - u).
    extra : dict
        Step-specific figures (iterations, condition number, ...).
    """

    step: str
    ids: Sequence[str]
    observed: NDArray[np.float64]
    adjusted: NDArray[np.float64]
    units: str
    components: tuple[str, ...] = ("dx", "dy")
    weights: NDArray[np.float64] | None = None
    outlier: NDArray[np.bool_] | None = None
    check: NDArray[np.bool_] | None = None
    std: NDArray[np.float64] | None = None
    position_px: NDArray[np.float64] | None = None
    sigma0: float | None = None
    n_params: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        obs = np.array(self.observed, dtype=np.float64, copy=True)
        adj = np.array(self.adjusted, dtype=np.float64, copy=True)
        if obs.ndim == 1:
            obs, adj = obs[:, None], adj.reshape(-1, 1)
        if obs.shape != adj.shape or obs.ndim != 2:
            raise ShapeError(f"`observed` and `adjusted` must share shape (N, k); got {obs.shape} and "
                             f"{adj.shape}", actual_shape=(obs.shape, adj.shape))
        n, k = obs.shape
        if len(self.components) != k:
            raise InvalidInputError(f"{k} residual components but names {self.components!r}")
        ids = [str(i) for i in self.ids]
        if len(ids) != n:
            raise ShapeError(f"`ids` must have {n} entries; got {len(ids)}", actual_shape=(len(ids),))
        set_ = object.__setattr__
        set_(self, "ids", tuple(ids))
        set_(self, "observed", obs)
        set_(self, "adjusted", adj)
        set_(self, "weights", _col(self.weights, n, 1.0, "weights"))
        set_(self, "outlier", _col(self.outlier, n, False, "outlier", bool))
        set_(self, "check", _col(self.check, n, False, "check", bool))
        if self.std is not None:
            set_(self, "std", _col(self.std, n, 1.0, "std"))
        if self.position_px is not None:
            pos = np.array(self.position_px, dtype=np.float64, copy=True)
            if pos.shape != (n, 2):
                raise ShapeError(f"`position_px` must have shape ({n}, 2); got {pos.shape}",
                                 actual_shape=pos.shape, expected_shape=(n, 2))
            set_(self, "position_px", pos)
        if self.sigma0 is None:
            set_(self, "sigma0", self._sigma0())
        for a in (self.observed, self.adjusted, self.weights, self.outlier, self.check, self.std,
                  self.position_px):
            if a is not None:
                a.flags.writeable = False

    # ----------------------------------------------------------------- derived
    # weights, outlier and check are arrays once __post_init__ has run (None only as constructor defaults)
    @property
    def _weights(self) -> NDArray[np.float64]:
        return cast(NDArray[np.float64], self.weights)

    @property
    def _outlier(self) -> NDArray[np.bool_]:
        return cast(NDArray[np.bool_], self.outlier)

    @property
    def _check(self) -> NDArray[np.bool_]:
        return cast(NDArray[np.bool_], self.check)

    @property
    def n(self) -> int:
        return len(self.ids)

    @property
    def residual(self) -> NDArray[np.float64]:
        """v = adjusted - observed, (N, k)."""
        return self.adjusted - self.observed

    @property
    def norm(self) -> NDArray[np.float64]:
        """|v| per point, (N,), ``units``."""
        return np.linalg.norm(self.residual, axis=1)

    @property
    def fit_mask(self) -> NDArray[np.bool_]:
        """Points that took part in the fit: not check points, not outliers."""
        return ~self._check & ~self._outlier

    def _sigma0(self) -> float:
        m = self.fit_mask
        v = self.residual[m]
        w = self._weights[m]
        dof = v.size - self.n_params
        if dof <= 0:
            return float("nan")
        return float(math.sqrt(float(np.sum(w[:, None] * v * v)) / dof))

    @property
    def normalised(self) -> NDArray[np.float64]:
        """|v| / std (or / sigma0 when no std is given), (N,), unitless."""
        if self.std is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                return self.norm / self.std
        s = self.sigma0 if self.sigma0 and math.isfinite(self.sigma0) else float("nan")
        return self.norm / s

    def summary(self) -> dict[str, Any]:
        """Counts, RMSE (fit and check points, per component) and sigma0."""
        fit, chk = self.fit_mask, self._check
        v = self.residual
        out: dict[str, Any] = {
            "step": self.step,
            "units": self.units,
            "n_points": self.n,
            "n_fit": int(fit.sum()),
            "n_check": int(chk.sum()),
            "n_outliers": int(self._outlier.sum()),
            "n_params": int(self.n_params),
            "rmse": rms(self.norm[fit]),
            "rmse_check": rms(self.norm[chk]) if chk.any() else None,
            "max_abs": float(self.norm[fit].max()) if fit.any() else None,
            "sigma0": self.sigma0,
        }
        for j, c in enumerate(self.components):
            out[f"rmse_{c}"] = rms(v[fit, j])
        out.update(self.extra)
        return out

    def rows(self) -> list[dict[str, Any]]:
        """One dict per point, in the CSV column order."""
        v, nrm, nz = self.residual, self.norm, self.normalised
        rows = []
        for i in range(self.n):
            r: dict[str, Any] = {"id": self.ids[i]}
            for j in range(len(self.components)):
                r[f"observed_{j}"] = self.observed[i, j]
            for j in range(len(self.components)):
                r[f"adjusted_{j}"] = self.adjusted[i, j]
            for j, c in enumerate(self.components):
                r[c] = v[i, j]
            r["norm"] = nrm[i]
            r["normalised"] = nz[i]
            r["weight"] = self._weights[i]
            r["outlier"] = int(self._outlier[i])
            r["check"] = int(self._check[i])
            rows.append(r)
        return rows

    def to_csv(self, path: str | Path | None = None) -> str:
        """Write the table as CSV (to ``path`` if given); return the text.

        Columns: id, observed_*, adjusted_*, residual components, norm (|v|),
        normalised, weight, outlier, check. A leading comment line states the
        step and units.
        """
        buf = io.StringIO()
        buf.write(f"# step={self.step}; units={self.units}; residual = adjusted - observed\n")
        rows = self.rows()
        fields = list(rows[0]) if rows else ["id", "norm"]
        w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})
        text = buf.getvalue()
        if path is not None:
            atomic_write_text(path, text, overwrite=True)
        return text

    def format_text(self, *, max_rows: int = 50, precision: int = 3) -> str:
        """A fixed-width residual table plus summary lines, for the terminal."""
        comps = list(self.components)
        head = f"{'id':>10} " + " ".join(f"{c:>10}" for c in comps) + f" {'|v|':>10}  flag"
        lines = [f"{self.step}: residuals in {self.units} (v = adjusted - observed)", head]
        v, nrm = self.residual, self.norm
        idx = range(self.n) if self.n <= max_rows else list(range(max_rows))
        for i in idx:
            flag = "check" if self._check[i] else ("OUTLIER" if self._outlier[i] else "")
            lines.append(f"{self.ids[i]:>10} " + " ".join(f"{x:>10.{precision}f}" for x in v[i])
                         + f" {nrm[i]:>10.{precision}f}  {flag}")
        if self.n > max_rows:
            lines.append(f"... {self.n - max_rows} more rows (full table with --report)")
        lines.append(self.summary_line())
        return "\n".join(lines)

    def summary_line(self) -> str:
        s = self.summary()
        sig = s["sigma0"]
        if sig is not None and math.isfinite(sig):
            sig_txt = f"sigma0 {sig:.4g} {self.units}"
        else:  # zero redundancy: sigma0 = sqrt(v'Pv / (n - u)) is undefined
            sig_txt = (f"sigma0 undefined (no redundancy: {s['n_fit'] * len(self.components)} "
                       f"observations, {s['n_params']} parameters)")
        txt = f"{s['n_fit']} fit points, RMSE {s['rmse']:.4g} {self.units}, {sig_txt}"
        if s["n_check"]:
            txt += f"; {s['n_check']} check points, RMSE {s['rmse_check']:.4g} {self.units}"
        if s["n_outliers"]:
            txt += f"; {s['n_outliers']} outliers"
        return txt
