"""How well GCPs determine a transform over the whole image (issue 12).

:func:`judge_gcp_geometry` measures the share of the image covered by the fit GCPs' convex hull and
predicts the 1-sigma error of the fitted model at the four image corners (and at the GCPs), by
first-order propagation of the observation noise through the fit: with targets ``t`` of standard
deviation sigma0 per coordinate, cov(model(p)) = sigma0^2 J J^T, J = d model(p) / d t. J is found by
refitting with perturbed targets (exactly, one coordinate at a time, up to 40 fit points; by random
+-1 probes beyond, E[(J r)(J r)^T] = J J^T). This works for every method of :data:`METHODS` and
shows what the residuals at the GCPs cannot: the error of an extrapolated output.

:func:`geographic_lines` shows residuals of a geographic CRS in degrees (8 decimals) and in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.points import GcpTable
from rectify.geometry.residuals import ResidualTable, rms
from rectify.geometry.transforms.gcp import METHODS, fit_gcps

__all__ = ["GcpGeometry", "judge_gcp_geometry", "hull_area", "geographic_lines", "metres_per_degree",
           "EXTRAPOLATION_HULL_SHARE"]

#: Below this share of the image covered by the GCPs' convex hull, the output is mostly extrapolation.
EXTRAPOLATION_HULL_SHARE = 0.30
_EXACT_MAX = 40
_PROBES = 40


def hull_area(points: NDArray[np.float64]) -> float:
    """Area of the convex hull of (N, 2) points (0 for fewer than 3 or collinear points)."""
    p = np.unique(np.asarray(points, dtype=np.float64).reshape(-1, 2), axis=0)
    if len(p) < 3:
        return 0.0
    p = p[np.lexsort((p[:, 1], p[:, 0]))]

    def cross(o, a, b) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    lower: list = []
    upper: list = []
    for q in p:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    for q in p[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    h = np.array(lower[:-1] + upper[:-1])
    if len(h) < 3:
        return 0.0
    x, y = h[:, 0], h[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def metres_per_degree(lat_deg: float) -> tuple[float, float]:
    """(east, north) metres per degree of longitude and latitude at ``lat_deg`` on the WGS 84 ellipsoid."""
    a, e2 = 6378137.0, 6.69437999014e-3
    s = math.sin(math.radians(lat_deg))
    w = math.sqrt(1 - e2 * s * s)
    return (a / w * math.cos(math.radians(lat_deg)) * math.pi / 180, a * (1 - e2) / w ** 3 * math.pi / 180)


@dataclass(frozen=True)
class GcpGeometry:
    """The GCP geometry of a fit over a ``width`` x ``height`` source image.

    Attributes
    ----------
    hull_share : float
        Area of the fit GCPs' convex hull / image area (0..1).
    corner_sigma : (4,) float64 or None
        Predicted 1-sigma radial error of the model at the corners (top-left, top-right, bottom-right,
        bottom-left), target units; None without redundancy.
    gcp_sigma : float or None
        The same, RMS over the fit GCPs.
    sigma0 : float or None
        The observation sigma used (the fit's sigma0 per coordinate).
    redundancy : int
        Observations minus parameters.
    n_fit, n_params : int
    units : str
    method : str
    metres : (float, float) or None
        Metres per unit (east, north) when the units are degrees.
    """

    hull_share: float
    corner_sigma: NDArray[np.float64] | None
    gcp_sigma: float | None
    sigma0: float | None
    redundancy: int
    n_fit: int
    n_params: int
    units: str
    method: str
    width: int
    height: int
    metres: tuple[float, float] | None = None

    @property
    def extrapolation(self) -> bool:
        """The GCPs cover less than :data:`EXTRAPOLATION_HULL_SHARE` of the image."""
        return self.hull_share < EXTRAPOLATION_HULL_SHARE

    def _len(self, v: float) -> str:
        if self.metres is not None:
            return f"{v:.3g} {self.units} ({v * min(self.metres):.3g} m)"
        return f"{v:.3g} {self.units}"

    def summary_lines(self) -> list[str]:
        """Hull share, predicted corner errors, the no-redundancy statement and the extrapolation warning."""
        lines = [f"GCP geometry: the {self.n_fit} fit GCPs' convex hull covers {100 * self.hull_share:.0f}% of the "
                 f"{self.width} x {self.height} image"]
        if self.redundancy <= 0:
            lines.append(f"no redundancy: {self.n_fit} GCPs determine the {self.n_params} {self.method} parameters "
                         "exactly; the residuals are zero by construction and no error can be estimated "
                         "(add GCPs, or check points)")
        elif self.corner_sigma is not None:
            cs = self.corner_sigma
            txt = ", ".join(f"{v:.3g}" for v in cs) + f" {self.units}"
            if self.metres is not None:
                k = min(self.metres)
                txt += " (" + ", ".join(f"{v * k:.3g}" for v in cs) + " m)"
            lines.append(f"predicted error (1 sigma, from sigma0 {self._len(self.sigma0 or 0.0)}) at the corners "
                         f"TL, TR, BR, BL: {txt}; at the GCPs: {self._len(self.gcp_sigma or 0.0)}")
        if self.extrapolation:
            worst = ("" if self.corner_sigma is None or self.redundancy <= 0
                     else f"; predicted error up to {self._len(float(np.max(self.corner_sigma)))} at the corners")
            lines.append(f"warning: the GCPs cover only {100 * self.hull_share:.0f}% of the image: most of the "
                         f"output is extrapolation{worst}; spread GCPs over the whole image")
        return lines

    def to_dict(self) -> dict:
        return {"hull_share": self.hull_share, "redundancy": self.redundancy, "sigma0": self.sigma0,
                "corner_sigma": None if self.corner_sigma is None else self.corner_sigma.tolist(),
                "gcp_sigma": self.gcp_sigma, "extrapolation": self.extrapolation}


def judge_gcp_geometry(gcps: GcpTable, method: str, width: int, height: int, *, units: str = "px",
                       seed: int = 0) -> GcpGeometry:
    """Judge how well the fit rows of ``gcps`` determine ``method`` over a ``width`` x ``height`` image.

    Parameters
    ----------
    gcps : GcpTable
        As fitted (check rows are withheld, as by :func:`fit_gcps`).
    method : str
        A key of :data:`METHODS`.
    width, height : int
        Source image size, px.
    units : str
        Target units (``degree`` adds metres).

    Returns
    -------
    GcpGeometry
    """
    base = fit_gcps(gcps, method)
    t = base.table
    fit = t.fit_mask
    n_fit = int(fit.sum())
    n_params = METHODS[method].n_params
    redundancy = 2 * n_fit - n_params
    share = hull_area(gcps.pixel[fit]) / max(float(width * height), 1.0)
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    metres = None
    if units.startswith("degree"):
        metres = metres_per_degree(float(np.mean(gcps.target[fit, 1])))
    sig = t.sigma0
    if redundancy <= 0 or sig is None or not math.isfinite(sig):
        return GcpGeometry(min(share, 1.0), None, None, None, redundancy, n_fit, n_params, units, method,
                           width, height, metres)
    # the fit rows only, in a local target frame (conditioning), perturbed and refitted
    sub = gcps.subset(fit)
    offset = np.round(sub.target.mean(axis=0))
    local = GcpTable(sub.ids, sub.pixel, sub.target - offset, None, np.zeros(len(sub), bool), None)
    probe_at = np.r_[corners, sub.pixel]
    p0 = np.asarray(fit_gcps(local, method).model(probe_at))
    eps = 1e-6 * max(float(np.ptp(local.target, axis=0).max()), 1e-9)
    n = len(sub)
    if n <= _EXACT_MAX:
        dirs = np.zeros((2 * n, n, 2))
        for k in range(n):
            dirs[2 * k, k, 0] = 1.0
            dirs[2 * k + 1, k, 1] = 1.0
        scale = 1.0
    else:
        rng = np.random.default_rng(seed)
        dirs = rng.choice([-1.0, 1.0], size=(_PROBES, n, 2))
        scale = 1.0 / _PROBES
    cov = np.zeros((len(probe_at), 2, 2))
    for d in dirs:
        pert = GcpTable(local.ids, local.pixel, local.target + eps * d, None, local.check, None)
        g = (np.asarray(fit_gcps(pert, method).model(probe_at)) - p0) / eps
        cov += g[:, :, None] * g[:, None, :]
    cov *= scale * sig ** 2  # sigma0 = sqrt(v'v / (2 n - u)) is per coordinate
    radial = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    return GcpGeometry(min(share, 1.0), radial[:4], rms(radial[4:]), float(sig), redundancy,
                       n_fit, n_params, units, method, width, height, metres)


def geographic_lines(table: ResidualTable, *, max_rows: int = 50) -> list[str]:
    """Residuals of a geographic CRS (x = longitude, y = latitude, degrees): degrees with 8 decimals and
    east/north metres at the GCPs' mean latitude, and the RMSE in both units."""
    fit = table.fit_mask
    lat = float(np.mean(table.observed[fit if fit.any() else slice(None), 1]))
    me, mn = metres_per_degree(lat)
    v = table.residual
    vm = v * [me, mn]
    nm = np.linalg.norm(vm, axis=1)
    lines = [f"{table.step}: residuals in degrees and metres (at latitude {lat:.4f}; v = adjusted - observed)",
             f"{'id':>10} {'dlon deg':>13} {'dlat deg':>13} {'dE m':>10} {'dN m':>10} {'|v| m':>10}  flag"]
    chk = np.asarray(table.check, dtype=bool)
    for i in range(min(table.n, max_rows)):
        lines.append(f"{table.ids[i]:>10} {v[i, 0]:>13.8f} {v[i, 1]:>13.8f} {vm[i, 0]:>10.3f} {vm[i, 1]:>10.3f} "
                     f"{nm[i]:>10.3f}  {'check' if chk[i] else ''}")
    if table.n > max_rows:
        lines.append(f"... {table.n - max_rows} more rows (full table with --report)")
    txt = f"{int(fit.sum())} fit points, RMSE {rms(table.norm[fit]):.3g} degree = {rms(nm[fit]):.4g} m"
    if chk.any():
        txt += f"; {int(chk.sum())} check points, RMSE {rms(table.norm[chk]):.3g} degree = {rms(nm[chk]):.4g} m"
    lines.append(txt)
    return lines
