"""The DSM of dense matching: the grid of cell statistics and its GeoTIFF.

Points arrive by tiles (the point-cloud writers that stream them beside the DSM are in
:mod:`stereo.formats.points`):

- :class:`DsmGrid`: cell statistics on a regular grid in the ground frame: the Gaussian-weighted
  mean (default), minimum or maximum height of the points within ``radius`` cells of each cell
  centre, and the count of points in the cell. Cells whose points spread by more than
  ``max_spread`` cell sides are dropped, optionally cells far from their 5 x 5 median
  (``despike_cells``). Cells without points are nodata (``-9999``). Optional hole filling
  interpolates holes of at most ``max_hole_cells`` cells from their rim and marks them in a mask
  band. The grid itself is held in memory: 14 bytes per cell.

Every grid is aligned on whole multiples of its cell (GDAL's "target aligned pixels"): the cell
edges lie at ``k x cell`` in both axes, so DSMs of the same place with the same cell stack without
resampling; :func:`default_cell` rounds a ground sampling distance to two significant digits for
the default cell, so that runs on the same images agree on it too.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from affine import Affine
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from rectify.atomic import atomic_output
from rectify.errors import InvalidInputError
from rectify.geometry.points import as_points
from rectify.raster.io import MaskPolicy, TiledWriter

logger = logging.getLogger(__name__)

__all__ = ["DSM_NODATA", "STATISTICS", "DsmGrid", "DsmResult", "band_descriptions", "default_cell", "fill_holes"]

StrPath = str | Path

DSM_NODATA = -9999.0
STATISTICS = ("mean", "min", "max")


def default_cell(gsd: float) -> float:
    """The default DSM cell of a ground sampling distance: rounded to two significant digits (0.5069 -> 0.51).

    Raises
    ------
    InvalidInputError
        ``gsd`` is not a finite number > 0.
    """
    if isinstance(gsd, bool) or not (isinstance(gsd, (int, float)) and math.isfinite(gsd) and gsd > 0):
        raise InvalidInputError(f"cannot derive a DSM cell from the ground sampling distance {gsd!r}")
    return float(f"{float(gsd):.2g}")


def band_descriptions(statistic: str = "mean", heights: str = "ground units") -> tuple[str, str, str]:
    """The descriptions of the three bands of a DSM GeoTIFF (recorded in the file by :meth:`DsmResult.write`)."""
    how = {"mean": "Gaussian-weighted mean", "min": "minimum", "max": "maximum"}.get(statistic, statistic)
    return (f"height: {how} of the points' heights near the cell centre ({heights}); nodata -9999",
            "count: points that made the cell's height (0 where none)",
            "filled: 1 where the height was interpolated over a hole (fill holes), else 0")


@dataclass(frozen=True, eq=False)
class DsmResult:
    """A finished DSM grid.

    Attributes
    ----------
    height : (H, W) float32
        Heights; ``DSM_NODATA`` where no points (and not filled).
    count : (H, W) uint16
        Points that made each cell (within the grid's radius of its centre; 0 where no height).
    filled : (H, W) bool
        Cells filled by interpolation.
    transform : affine.Affine
        rasterio geotransform (cell corners).
    crs : str or None
    statistic : str
        The cell statistic of ``height`` (band descriptions).
    heights : str
        What the heights are (e.g. ``"m above the WGS 84 ellipsoid"``; band descriptions).
    """

    height: NDArray[np.float32]
    count: NDArray[np.uint16]
    filled: NDArray[np.bool_]
    transform: Affine
    crs: str | None
    statistic: str = "mean"
    heights: str = "ground units"

    def __post_init__(self) -> None:
        for a in (self.height, self.count, self.filled):
            a.flags.writeable = False

    @property
    def valid(self) -> NDArray[np.bool_]:
        return np.asarray(self.height != DSM_NODATA)

    @property
    def coverage(self) -> float:
        """Share of cells with points (before filling)."""
        return float((self.count > 0).mean()) if self.count.size else 0.0

    def write(self, path: StrPath, *, overwrite: bool = False) -> Path:
        """Write the DSM GeoTIFF: band 1 height (nodata -9999), band 2 point count, band 3 fill mask (1 filled);
        each band carries its description (:func:`band_descriptions`)."""
        H, W = self.height.shape
        with atomic_output(path, overwrite=overwrite) as tmp, \
                TiledWriter(tmp, W, H, 3, "float32", self.transform, self.crs, MaskPolicy("nodata", DSM_NODATA),
                            tile=256, descriptions=band_descriptions(self.statistic, self.heights)) as w:
            for r0 in range(0, H, 512):
                r1 = min(r0 + 512, H)
                w.write(np.dstack([self.height[r0:r1].astype(np.float32), self.count[r0:r1].astype(np.float32),
                                   self.filled[r0:r1].astype(np.float32)]), 0, r0)
        return Path(path)


class DsmGrid:
    """Accumulate points into DSM cells.

    Parameters
    ----------
    bounds : (xmin, ymin, xmax, ymax)
        Ground extent.
    cell : float
        Cell side, ground units.
    statistic : {"mean", "min", "max"}
    crs : str, optional
    heights : str
        What the heights are (band description of the GeoTIFF), e.g. ``"m above the WGS 84 ellipsoid"``.
    radius : float
        Each point counts in every cell whose centre lies within ``radius`` cells of it (Gaussian
        weight, sigma ``radius / 2``, for the mean): with points about one per cell, as a disparity
        map gives at a cell of one ground pixel, this leaves no empty cells between the points'
        rows. 0: a point counts in its own cell only.
    max_spread : float
        Cells whose points' (weighted) height standard deviation exceeds ``max_spread`` cell sides
        are dropped (points of two surfaces, or blunders, in one cell; 0: no test).

    The cell edges lie on whole multiples of ``cell`` (the grid covers ``bounds``): grids with the
    same cell in the same CRS share their cells.

    Memory: 14 bytes per cell (float32 weight, weighted sums of z and z^2 about a reference height,
    uint16 count); points are added by batches over the cells they touch only.
    """

    def __init__(self, bounds: tuple[float, float, float, float], cell: float, *, statistic: str = "mean",
                 crs: str | None = None, max_cells: int = 400_000_000, radius: float = 1.0,
                 max_spread: float = 2.0, heights: str = "ground units"):
        if statistic not in STATISTICS:
            raise InvalidInputError(f"unknown DSM statistic {statistic!r}; expected one of {list(STATISTICS)}")
        if not (isinstance(cell, (int, float)) and math.isfinite(cell) and cell > 0):
            raise InvalidInputError(f"DSM cell must be a finite number > 0; got {cell!r}")
        for name, v in (("radius", radius), ("max_spread", max_spread)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 5):
                raise InvalidInputError(f"`{name}` must be a number in [0, 5]; got {v!r}")
        x0, y0, x1, y1 = (float(b) for b in bounds)
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)) or x1 <= x0 or y1 <= y0:
            raise InvalidInputError(f"DSM bounds must be finite with xmin < xmax, ymin < ymax; got {bounds!r}")
        self.cell = float(cell)
        # cell edges on whole multiples of the cell: the left and top edges, then the first cell centre
        left = math.floor(x0 / cell) * cell
        top = math.ceil(y1 / cell) * cell
        self.x0 = left + cell / 2
        self.y1 = top - cell / 2
        self.width = int(math.floor((x1 - left) / cell)) + 1
        self.height = int(math.floor((top - y0) / cell)) + 1
        if self.width * self.height > max_cells:
            raise InvalidInputError(f"the DSM would have {self.width} x {self.height} cells (more than {max_cells}); "
                                    f"choose a larger cell than {cell!r}")
        self.statistic = statistic
        self.crs = crs
        self.heights = str(heights)
        self.radius = float(radius)
        self.max_spread = float(max_spread)
        self.n_despiked = 0
        self.n_spread = 0
        self._done = False
        self._z0: float | None = None
        shape = (self.height, self.width)
        self._count = np.zeros(shape, np.uint16)
        self._w = np.zeros(shape, np.float32)
        self._wz = np.zeros(shape, np.float32)
        self._wzz = np.zeros(shape, np.float32)
        if statistic != "mean":
            self._acc = np.full(shape, np.inf if statistic == "min" else -np.inf, np.float32)

    @property
    def transform(self) -> Affine:
        """rasterio geotransform: the top-left corner on whole multiples of the cell."""
        k_left = round((self.x0 - self.cell / 2) / self.cell)
        k_top = round((self.y1 + self.cell / 2) / self.cell)
        return Affine(self.cell, 0.0, k_left * self.cell, 0.0, -self.cell, k_top * self.cell)

    def cell_of(self, xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        c = np.rint((xy[:, 0] - self.x0) / self.cell).astype(np.int64)
        r = np.rint((self.y1 - xy[:, 1]) / self.cell).astype(np.int64)
        return r, c

    def add(self, xyz: ArrayLike) -> int:
        """Add points (N, 3); returns how many fell inside the grid."""
        p = as_points(xyz, "points", 3)
        if self._done:
            raise InvalidInputError("this DsmGrid already gave its result: it takes no more points")
        fc = (p[:, 0] - self.x0) / self.cell
        fr = (self.y1 - p[:, 1]) / self.cell
        r0, c0 = np.rint(fr).astype(np.int64), np.rint(fc).astype(np.int64)
        own = (r0 >= 0) & (c0 >= 0) & (r0 < self.height) & (c0 < self.width)
        if not own.any():
            return 0
        if self._z0 is None:
            self._z0 = float(np.median(p[own, 2]))
        z = (p[:, 2] - self._z0).astype(np.float32)
        k = int(math.ceil(self.radius))
        lo_r, hi_r = max(int(r0[own].min()) - k, 0), min(int(r0[own].max()) + k, self.height - 1)
        lo_c, hi_c = max(int(c0[own].min()) - k, 0), min(int(c0[own].max()) + k, self.width - 1)
        h, w = hi_r - lo_r + 1, hi_c - lo_c + 1
        sl = (slice(lo_r, hi_r + 1), slice(lo_c, hi_c + 1))
        cnt = self._count[sl].astype(np.int64)
        sigma = max(self.radius / 2.0, 1e-6)
        for dr in range(-k, k + 1):
            for dc in range(-k, k + 1):
                rr, cc = r0 + dr, c0 + dc
                dist2 = (rr - fr) ** 2 + (cc - fc) ** 2
                m = (rr >= lo_r) & (cc >= lo_c) & (rr <= hi_r) & (cc <= hi_c)
                if self.radius > 0:
                    m &= dist2 <= self.radius ** 2
                elif dr or dc:
                    continue
                if not m.any():
                    continue
                j = (rr[m] - lo_r) * w + (cc[m] - lo_c)
                wt = np.exp(-0.5 * dist2[m] / sigma ** 2) if self.radius > 0 else np.ones(int(m.sum()))
                zm = z[m].astype(np.float64)
                cnt += np.bincount(j, minlength=h * w).reshape(h, w)
                self._w[sl] += np.bincount(j, weights=wt, minlength=h * w).reshape(h, w).astype(np.float32)
                self._wz[sl] += np.bincount(j, weights=wt * zm, minlength=h * w).reshape(h, w).astype(np.float32)
                self._wzz[sl] += np.bincount(j, weights=wt * zm * zm, minlength=h * w).reshape(h, w).astype(
                    np.float32)
                if self.statistic != "mean":
                    flat = self._acc[sl].reshape(-1).copy()
                    (np.minimum if self.statistic == "min" else np.maximum).at(flat, j, z[m])
                    self._acc[sl] = flat.reshape(h, w)
        self._count[sl] = np.minimum(cnt, 65535).astype(np.uint16)
        return int(own.sum())

    def result(self, *, max_hole_cells: int = 0, despike_cells: float = 0.0) -> DsmResult:
        """The DSM; holes of at most ``max_hole_cells`` cells are interpolated from their rim and flagged.

        Cells whose points spread by more than ``max_spread`` cell sides are dropped (counted in
        :attr:`n_spread`). With ``despike_cells`` > 0, cells whose height differs from the median of
        their 5 x 5 neighbourhood by more than ``despike_cells`` cell sides are removed next
        (matching blunders); the removed count is in :attr:`n_despiked`.

        The result is computed in the grid's own buffers (about 1 extra byte per cell), so the grid
        is consumed: it takes no more points afterwards.
        """
        if isinstance(max_hole_cells, bool) or not isinstance(max_hole_cells, int) or max_hole_cells < 0:
            raise InvalidInputError(f"`max_hole_cells` must be an integer >= 0; got {max_hole_cells!r}")
        if self._done:
            raise InvalidInputError("this DsmGrid already gave its result")
        self._done = True
        z0 = np.float32(self._z0 if self._z0 is not None else 0.0)
        has = self._w > 0
        h = self._wz  # becomes the height, in place
        wide_n = 0
        for r0 in range(0, self.height, 1024):  # by row blocks: small temporaries
            sl = slice(r0, r0 + 1024)
            w, m = self._w[sl], has[sl]
            np.divide(h[sl], w, out=h[sl], where=m)
            if self.max_spread > 0:
                var = np.divide(self._wzz[sl], w, out=np.zeros_like(w), where=m) - h[sl] * h[sl]
                wide = m & (var > np.float32((self.max_spread * self.cell) ** 2))
                wide_n += int(wide.sum())
                m &= ~wide
            if self.statistic != "mean":
                h[sl] = self._acc[sl]
            h[sl] += z0
            h[sl][~m] = np.nan
        self.n_spread = wide_n
        del self._w, self._wzz
        if self.statistic != "mean":
            del self._acc
        self.n_despiked = 0
        if despike_cells > 0 and has.any():
            idx = ndimage.distance_transform_edt(~has, return_distances=False, return_indices=True)
            med = ndimage.median_filter(h[idx[0], idx[1]], size=5, mode="nearest")
            del idx
            spike = has & (np.abs(h - med) > despike_cells * self.cell)
            self.n_despiked = int(spike.sum())
            h[spike] = np.nan
            has &= ~spike
        filled = np.zeros(h.shape, bool)
        if max_hole_cells > 0 and has.any() and not has.all():
            hf, filled = fill_holes(h.astype(np.float64), has, max_hole_cells)
            h[filled] = hf[filled]
            del hf
        h[~(has | filled)] = DSM_NODATA
        count = self._count
        count[~(has | filled)] = 0
        return DsmResult(h, count, filled, self.transform, self.crs, self.statistic, self.heights)


def fill_holes(h: NDArray[np.float64], has: NDArray[np.bool_], max_cells: int
               ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Fill the enclosed holes of a height grid (harmonic fill from their rim).

    ``h`` (rows, cols) heights in metres, read only where ``has`` (same shape, bool) is True. A hole is a
    4-connected region of missing cells of at most ``max_cells`` cells that does not touch the grid's border
    (a region touching it is outside the data). Each hole starts from its nearest valid height and is
    smoothed by 50 rounds of 4-neighbour averaging, so every filled height lies between its rim's extremes.
    Returns ``(heights, filled)``: the heights (NaN where neither valid nor filled) and the mask of the
    filled cells.
    """
    lab, n = ndimage.label(~has)
    if n == 0:
        return h, np.zeros(h.shape, bool)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    # a hole touching the border is outside the data, not a hole
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    small = sizes <= max_cells
    small[0] = False
    small[border] = False
    target = small[lab]
    if not target.any():
        return h, np.zeros(h.shape, bool)
    # nearest-valid value, then smoothed inside the hole by repeated averaging (harmonic fill)
    idx = ndimage.distance_transform_edt(~has, return_distances=False, return_indices=True)
    out = h[idx[0], idx[1]]
    for _ in range(50):
        pad = np.pad(out, 1, mode="edge")
        avg = 0.25 * (pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:])
        out[target] = avg[target]
    return np.where(has | target, out, np.nan), target
