"""Dense-matching report: disparity and DSM pictures, coverage, height differences against a DEM."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.raster.io import reproject_band
from stereo.dense.dsm import DsmResult

logger = logging.getLogger(__name__)

__all__ = ["HeightComparison", "compare_with_dem", "height_stats", "save_picture"]

StrPath = str | Path


@dataclass(frozen=True)
class HeightComparison:
    """DSM minus reference heights over the cells where both exist.

    Attributes
    ----------
    n : int
        Cells compared.
    coverage : float
        Share of the overlap cells (inside the hull of the points) with a DSM height.
    rmse, mean, median, nmad : float
        Of the differences (ground units). NMAD = 1.4826 median |dz - median|.
    blunder_share : float
        Share of cells with |dz - median| > ``blunder_factor`` x max(NMAD, cell).
    rmse_without_blunders : float
    blunder_factor : float
    histogram : (counts, edges)
    """

    n: int
    coverage: float
    rmse: float
    mean: float
    median: float
    nmad: float
    blunder_share: float
    rmse_without_blunders: float
    blunder_factor: float
    histogram: tuple[tuple[int, ...], tuple[float, ...]]

    def summary_line(self, unit: str = "m", cell: float | None = None) -> str:
        px = f" ({self.rmse / cell:.2f} cells)" if cell else ""
        return (f"DSM vs reference DEM: {self.n} cells, coverage {100 * self.coverage:.1f}% of the overlap, RMSE "
                f"{self.rmse:.2f} {unit}{px}, mean {self.mean:+.2f} {unit}, median {self.median:+.2f} {unit}, NMAD "
                f"{self.nmad:.2f} {unit}, blunders {100 * self.blunder_share:.1f}% (|dz - median| > "
                f"{self.blunder_factor:g} x max(NMAD, cell)), RMSE without them "
                f"{self.rmse_without_blunders:.2f} {unit}")


def height_stats(dz: NDArray[np.float64], cell: float, *, coverage: float = float("nan"),
                 blunder_factor: float = 3.0) -> HeightComparison:
    """Statistics of height differences (see :class:`HeightComparison`)."""
    d = np.asarray(dz, dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise InvalidInputError("no height differences to compare (the DSM and the reference do not overlap)")
    med = float(np.median(d))
    nmad = float(1.4826 * np.median(np.abs(d - med)))
    bl = np.abs(d - med) > blunder_factor * max(nmad, cell)
    counts, edges = np.histogram(np.clip(d, med - 10 * max(nmad, cell), med + 10 * max(nmad, cell)), bins=60)
    return HeightComparison(
        n=int(d.size), coverage=coverage, rmse=float(np.sqrt(np.mean(d * d))), mean=float(np.mean(d)), median=med,
        nmad=nmad, blunder_share=float(bl.mean()),
        rmse_without_blunders=float(np.sqrt(np.mean(d[~bl] ** 2))) if (~bl).any() else float("nan"),
        blunder_factor=blunder_factor,
        histogram=(tuple(int(c) for c in counts), tuple(float(e) for e in edges)))


def _overlap_cells(dsm: DsmResult) -> NDArray[np.bool_]:
    """Cells inside the convex hull of the cells with points (the matched overlap)."""
    has = dsm.count > 0
    if not has.any():
        return has
    r, c = np.nonzero(has)
    hull = cv2.convexHull(np.column_stack([c, r]).astype(np.int32))
    m = np.zeros(has.shape, np.uint8)
    cv2.fillConvexPoly(m, hull, 1)
    return m > 0


def compare_with_dem(dsm: DsmResult, dem_path: StrPath, *, blunder_factor: float = 3.0
                     ) -> tuple[HeightComparison, NDArray[np.float64]]:
    """DSM minus the reference DEM (resampled bilinearly onto the DSM grid); returns the stats and dz grid."""
    p = Path(dem_path)
    if not p.exists():
        raise RasterIOError(f"reference DEM not found: {str(p)!r}")
    if dsm.crs is None:
        raise CRSError("the DSM has no CRS (model frame): a reference DEM needs ground control or exterior "
                       "orientations")
    ref = reproject_band(p, dsm.height.shape, dsm.transform, dsm.crs, what="reference DEM")
    h = np.where(dsm.valid & ~dsm.filled, dsm.height.astype(np.float64), np.nan)
    dz = h - ref
    overlap = _overlap_cells(dsm)
    cov = float((dsm.valid & overlap).sum() / max(1, overlap.sum()))
    cell = abs(dsm.transform.a)
    return height_stats(dz, cell, coverage=cov, blunder_factor=blunder_factor), dz


def save_picture(path: StrPath, grid: NDArray, *, title: str, cmap: str = "viridis", label: str = "",
                 nodata: float | None = None, symmetric: bool = False) -> Path:
    """A PNG picture of a grid (NaN or ``nodata`` transparent); ``symmetric``: colour limits +-v (0 in the middle)."""
    a = np.asarray(grid)
    step = max(1, int(math.ceil(max(a.shape) / 1500)))
    g = a[::step, ::step].astype(np.float64)  # decimated first: no full-size copy of a large grid
    if nodata is not None:
        g = np.where(g == nodata, np.nan, g)
    fig = Figure(figsize=(6, 6 * g.shape[0] / max(g.shape[1], 1) + 0.5))
    ax = fig.subplots()
    ok = np.isfinite(g)
    vmin, vmax = (np.percentile(g[ok], [1, 99]) if ok.any() else (0, 1))
    if symmetric:
        vmax = max(abs(float(vmin)), abs(float(vmax)), 1e-9)
        vmin = -vmax
    im = ax.imshow(g, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title(title)
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, label=label, shrink=0.8)
    fig.savefig(path, dpi=100, bbox_inches="tight", format="png")
    return Path(path)


def save_histogram(path: StrPath, cmp: HeightComparison, *, unit: str = "m") -> Path:
    """PNG histogram of the DSM - DEM differences."""
    counts, edges = cmp.histogram
    fig = Figure(figsize=(6, 3.5))
    ax = fig.subplots()
    ax.stairs(counts, edges, fill=True)
    ax.axvline(cmp.median, color="k", lw=1)
    ax.set_xlabel(f"DSM - reference ({unit})")
    ax.set_ylabel("cells")
    ax.set_title(f"RMSE {cmp.rmse:.2f} {unit}, NMAD {cmp.nmad:.2f} {unit}, n = {cmp.n}")
    fig.savefig(path, dpi=100, bbox_inches="tight", format="png")
    return Path(path)
