"""Orthorectification with a DEM: frame cameras and RPC images, true orthophotos.

For every output pixel (a north-up grid in any CRS) the ground height comes
from the DEM (any CRS and resolution, bilinear, resampled on the fly through
:class:`rectify.raster.dem.Dem`), the ground point (x, y, h) is projected into the
image by the sensor model, and the image is resampled there (OpenCV remap on
the source window the tile needs). The horizontal CRS changes (output ->
model, output -> DEM) are smooth and are evaluated exactly on a sparse grid
(every ``map_step_px`` pixels) and interpolated bilinearly; heights and the
sensor projection are evaluated exactly at every output pixel.

True orthophoto (``true_ortho=True``): each ground point is tested for
visibility by marching along its line of sight towards the sensor over the
DEM (half-pixel steps, up to the highest DEM point of the tile's
neighbourhood); a point hidden by higher ground (a wall, a building, a ridge)
gets nodata instead of the occluder's pixels (no ghost image), and an extra
last band records the visibility: 0 outside the image, 1 occluded, 2 visible.

Output: tiled, compressed GeoTIFF (COG with ``cog=True``), written tile by
tile from a thread pool (bounded memory: at most ``2 x threads + 1`` tiles in
flight) to a temporary file renamed at the end. Nodata outside the image:
the source nodata, else 0 for integer rasters and NaN for float ones (valid
pixels equal to 0 in integer outputs are raised to 1 so they stay valid).

The sensor models (:class:`rectify.geometry.sensors.FrameModel`,
:class:`rectify.geometry.sensors.RPCModel`) live in :mod:`rectify.geometry.sensors`; the tile engine
runs on the shared base and output tail of :mod:`rectify.raster.engine`. The command's file step
(models from files, GCPs, the report) is :mod:`rectify.actions.ortho`.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from affine import Affine
from numpy.typing import NDArray
from threadpoolctl import ThreadpoolController

from rectify.atomic import check_output
from rectify.errors import CRSError, InvalidInputError, RasterIOError, SchedulerError
from rectify.geometry.crs import crs_to_string, same_crs, transform_xy, unit_label, utm_crs
from rectify.geometry.sensors import SensorModel
from rectify.raster.coverage import check_coverage
from rectify.raster.dem import Dem
from rectify.raster.distributed import Scheduler, resolve_scheduler
from rectify.raster.engine import (
    COMPRESSIONS,
    JPEG_QUALITY,
    TileEngine,
    check_output_format,
    tile_windows,
    worker_count,
    write_tiled,
)
from rectify.raster.georef import Grid, boundary_pixels, crs_label, pixel_from_world_matrix
from rectify.raster.io import MaskPolicy, raster_info
from rectify.raster.relief import ReliefShift, relief_shift, relief_stride
from rectify.raster.visibility import line_of_sight

__all__ = ["OrthoOptions", "OrthoResult", "ReliefShift", "orthorectify", "ortho_grid", "relief_shift",
           "relief_stride", "MIN_VALID_SHARE", "VISIBILITY_OUTSIDE",
           "VISIBILITY_OCCLUDED", "VISIBILITY_VISIBLE"]

logger = logging.getLogger(__name__)

VISIBILITY_OUTSIDE, VISIBILITY_OCCLUDED, VISIBILITY_VISIBLE = 0, 1, 2
#: default :attr:`OrthoOptions.min_valid_share`: an orthophoto with less than 1 % valid cells is refused
MIN_VALID_SHARE = 0.01


# =========================================================================== options / result
@dataclass(frozen=True)
class OrthoOptions:
    """Options of :func:`orthorectify`.

    Attributes
    ----------
    resampling : ``nearest``, ``bilinear`` or ``cubic``
    tile_px : output tile and block size (multiple of 16)
    threads : worker threads (None: all cores)
    compress : GeoTIFF compression, one of :data:`rectify.raster.engine.COMPRESSIONS`: lossless ``zstd``
        (default), ``deflate``, ``lzw``, ``none``; or ``jpeg`` (8-bit images only; JPEG-in-TIFF, YCbCr for
        RGB, invalid pixels in an internal mask band instead of a nodata value; not with ``true_ortho``,
        whose visibility band must stay exact)
    quality : JPEG quality 1..100 (``compress="jpeg"``)
    cog : write a Cloud Optimized GeoTIFF (internal overviews)
    true_ortho : z-buffer (line-of-sight) visibility and the visibility band
    map_step_px : spacing of the exactly transformed points for CRS changes
    max_window_px : largest source window read for one tile (bigger tiles are split)
    min_valid_share : an output grid of which a smaller share would get a value (a DEM height whose
        ground point the image sees; estimated before any tile, :func:`rectify.raster.coverage.ortho_coverage`)
        is refused with the numbers (the share, the DEM's extent, the image footprint); 0: never refused
    scheduler : where the tiles run: ``threads``, ``processes[:N]`` or ``tcp://HOST:PORT``; None:
        ``$RECTIFY_SCHEDULER``, else ``threads`` (:mod:`rectify.raster.distributed`; same output bytes on every one)
    """

    resampling: str = "bilinear"
    tile_px: int = 512
    threads: int | None = None
    compress: str = "zstd"
    cog: bool = False
    quality: int = JPEG_QUALITY
    true_ortho: bool = False
    map_step_px: int = 16
    max_window_px: int = 8192
    scheduler: Scheduler | str | None = None
    min_valid_share: float = MIN_VALID_SHARE

    def __post_init__(self) -> None:
        if self.scheduler is not None:
            resolve_scheduler(self.scheduler)  # a bad value fails here, before any work
        if str(self.compress).lower() not in COMPRESSIONS:
            raise InvalidInputError(f"unknown compression {self.compress!r}; expected one of {', '.join(COMPRESSIONS)}")
        q = self.quality
        if isinstance(q, bool) or not isinstance(q, (int, np.integer)) or not 1 <= int(q) <= 100:
            raise InvalidInputError(f"JPEG quality must be an integer in 1..100; got {q!r}")
        if str(self.compress).lower() == "jpeg" and self.true_ortho:
            raise InvalidInputError("--compress jpeg cannot keep the visibility band of --true-ortho exact; use a "
                                    "lossless compression (zstd, deflate, lzw)")
        if self.resampling not in ("nearest", "bilinear", "cubic"):
            raise InvalidInputError(f"unknown resampling {self.resampling!r}; expected nearest, bilinear or cubic")
        if self.tile_px < 16 or self.tile_px % 16 or self.tile_px > 4096:
            raise InvalidInputError(f"tile_px must be a multiple of 16 in 16..4096; got {self.tile_px}")
        if self.threads is not None and self.threads < 1:
            raise InvalidInputError(f"threads must be >= 1; got {self.threads}")
        if self.map_step_px < 1:
            raise InvalidInputError(f"map_step_px must be >= 1; got {self.map_step_px}")
        v = self.min_valid_share
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 1):
            raise InvalidInputError(f"min_valid_share must be a number in [0, 1]; got {v!r}")

    @property
    def n_threads(self) -> int:
        return worker_count(self.threads)


@dataclass(frozen=True)
class OrthoResult:
    """What :func:`orthorectify` wrote.

    Attributes
    ----------
    path, grid, seconds
    n_tiles, n_empty_tiles : int
    dem_path : str
    dem_range : (float, float)
        Lowest and highest ellipsoidal/model heights met on the output grid.
    max_relief_shift : float
        ``relief.max`` (m; 0 without valid cells): the largest relief displacement the DEM removed.
    n_occluded : int
        Output pixels found hidden (true ortho).
    nodata : float
    model : str
    extra : dict
        ``true_ortho``, ``visibility_band``, ``margin_px``, ``dem_datum`` (the DEM's height statement).
    relief : ReliefShift or None
        The relief displacement removed, over the written cells (:func:`relief_shift`).
    """

    path: Path
    grid: Grid
    seconds: float
    n_tiles: int
    n_empty_tiles: int
    dem_path: str
    dem_range: tuple[float, float]
    max_relief_shift: float
    n_occluded: int
    nodata: float
    model: str
    extra: dict[str, Any] = field(default_factory=dict)
    relief: ReliefShift | None = None

    def summary_lines(self) -> list[str]:
        g = self.grid
        u = unit_label(g.crs)
        lo, hi = self.dem_range
        share = self.extra.get("valid_share")
        about = f" (about {100 * share:.1f} % of the grid)" if share is not None else ""
        heights = (f"heights {lo:.2f} .. {hi:.2f} m on the valid output cells{about}"
                   if math.isfinite(lo) and math.isfinite(hi) else "no valid output cell")
        out = [f"wrote {self.path}: {g.width} x {g.height} px, {g.resolution[0]:.6g} {u}/px, CRS {crs_label(g.crs)}, "
               f"{self.model}, {self.seconds:.2f} s",
               f"DEM {self.dem_path}: {heights}"]
        if self.relief is not None:
            out.append(self.relief.summary_line())
        if self.extra.get("true_ortho"):
            out.append(f"true ortho: {self.n_occluded} occluded pixels set to nodata (visibility band "
                       f"{self.extra.get('visibility_band')}: 0 outside, 1 occluded, 2 visible)")
        return out


# =========================================================================== grids
def ortho_grid(model: SensorModel, dem: Dem, *, dst_crs: str | None = None, resolution: float | None = None,
               max_pixels: float = 4e10) -> Grid:
    """The north-up output grid covering the image footprint between the DEM's lowest and highest heights.

    Default CRS: the model's for frame cameras, the UTM zone of the image
    centre for RPC images. Default resolution: the ground distance of the
    image diagonal over its length in pixels (GDAL's suggestion), at the mean
    height. Bounds are aligned to multiples of the resolution.
    """

    hmin, hmax = dem.range()
    edge = boundary_pixels(model.width, model.height, 33)
    pts = []
    for h in (hmin, 0.5 * (hmin + hmax), hmax):
        g = model.ground_at_height(edge, h)
        pts.append(g[np.isfinite(g).all(axis=1), :2])
    world = np.vstack(pts)
    if len(world) < 3:
        raise InvalidInputError("the image footprint does not reach the ground at the DEM's heights "
                                f"({hmin:.1f} .. {hmax:.1f} m): check the orientation and the DEM")
    if dst_crs is None:
        if model.crs in ("EPSG:4326", "EPSG:4979"):
            c = world.mean(axis=0)
            dst_crs = utm_crs(float(c[0]), float(c[1]))
        else:
            dst_crs = model.crs
    dst = crs_to_string(dst_crs)
    w = transform_xy(model.crs, dst, world)
    if resolution is None:
        hm = 0.5 * (hmin + hmax)
        d = model.ground_at_height(np.array([[-0.5, -0.5], [model.width - 0.5, model.height - 0.5]]), hm)
        if not np.isfinite(d).all():
            raise InvalidInputError("cannot estimate an output resolution; pass one")
        dd = transform_xy(model.crs, dst, d[:, :2])
        resolution = float(np.hypot(*(dd[1] - dd[0]))) / math.hypot(model.width, model.height)
    res = float(resolution)
    if not math.isfinite(res) or res <= 0:
        raise InvalidInputError(f"resolution must be a positive number; got {resolution!r}")
    eps = 1e-9
    x0 = math.floor(w[:, 0].min() / res + eps) * res
    y0 = math.floor(w[:, 1].min() / res + eps) * res
    x1 = math.ceil(w[:, 0].max() / res - eps) * res
    y1 = math.ceil(w[:, 1].max() / res - eps) * res
    nx, ny = max(1, int(round((x1 - x0) / res))), max(1, int(round((y1 - y0) / res)))
    if float(nx) * float(ny) > max_pixels:
        raise InvalidInputError(f"output grid of {nx} x {ny} pixels at resolution {res!r} is too large; "
                                f"pass a coarser --resolution")
    return Grid(nx, ny, Affine(res, 0.0, x0, 0.0, -res, y1), dst)


# =========================================================================== tile engine
def _gt(transform: Any) -> tuple[float, ...]:
    """The six geotransform numbers (a, b, c, d, e, f) of a rasterio Affine."""
    return tuple(float(v) for v in tuple(transform)[:6])


def _interp_index(n: int, knots: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Left knot index and weight of 0..n-1 for linear interpolation between ``knots`` (ascending)."""
    x = np.arange(n, dtype=np.float64)
    k = len(knots)
    if k == 1:
        return np.zeros(n, np.intp), np.zeros(n)
    i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, k - 2)
    return i.astype(np.intp), (x - knots[i]) / (knots[i + 1] - knots[i])


def _densify(vals: NDArray[np.float64], kc: NDArray[np.float64], kr: NDArray[np.float64], w: int, h: int
             ) -> NDArray[np.float64]:
    """Bilinear interpolation of (nr, nc, ...) values at the knots to (h, w, ...)."""
    ir, tr = _interp_index(h, kr)
    ic, tc = _interp_index(w, kc)
    if len(kr) == 1:
        rows = np.repeat(vals[:1], h, axis=0)
    else:
        sh = (-1,) + (1,) * (vals.ndim - 1)
        rows = vals[ir] * (1 - tr).reshape(sh) + vals[ir + 1] * tr.reshape(sh)
    if len(kc) == 1:
        return np.repeat(rows[:, :1], w, axis=1)
    sh2 = (1, -1) + (1,) * (vals.ndim - 2)
    return rows[:, ic] * (1 - tc).reshape(sh2) + rows[:, ic + 1] * tc.reshape(sh2)


PROJECTION_TOLERANCE_PX = 1e-3
_NODES = np.array([0.0, 1 / 3, 2 / 3, 1.0])
#: power-basis coefficients from values at the 4 nodes: coef = _VANDER_INV @ values
_VANDER_INV = np.linalg.inv(np.vander(_NODES, 4, increasing=True))


def _lagrange4(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cubic Lagrange weights (N, 4) for nodes 0, 1/3, 2/3, 1 at t (N,)."""
    n = np.array([0.0, 1 / 3, 2 / 3, 1.0])
    out = np.ones((len(t), 4))
    for k in range(4):
        for j in range(4):
            if j != k:
                out[:, k] *= (t - n[j]) / (n[k] - n[j])
    return out


_BLAS: dict[str, ThreadpoolController] = {}
_BLAS_LOCK = threading.Lock()


def _blas_one_thread() -> Any:
    """A context holding BLAS to one thread while the tile threads run (the tiles' small matrix products
    would otherwise each start BLAS threads: 3x slower on 2 cores)."""
    with _BLAS_LOCK:
        ctl = _BLAS.get("c")
        if ctl is None:
            ctl = _BLAS["c"] = ThreadpoolController()
    return ctl.limit(limits=1, user_api="blas")


def _interp_matrix(n: int, knots: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, len(knots)) weights of linear interpolation between ``knots`` at 0..n-1 (:func:`_interp_index`)."""
    i, t = _interp_index(n, knots)
    m = np.zeros((n, len(knots)))
    r = np.arange(n)
    m[r, i] = 1 - t
    m[r, np.minimum(i + 1, len(knots) - 1)] += t
    return m


def _densify_matrix(vals: NDArray[np.float64], kc: NDArray[np.float64], kr: NDArray[np.float64], w: int, h: int
                    ) -> NDArray[np.float64]:
    """:func:`_densify` of (nr, nc, dim) values as two matrix products a channel, A (h, nr) @ V @ B (nc, w): the
    same values to rounding (two non-zero weights a row, ~1e-16 relative), 3x faster than the gathers."""
    A = _interp_matrix(h, kr)
    B = _interp_matrix(w, kc).T
    out = np.empty((h, w) + vals.shape[2:])
    for k in range(vals.shape[2]):
        out[..., k] = (A @ vals[:, :, k]) @ B
    return out


def _knots(n: int, step: int) -> NDArray[np.float64]:
    k = np.arange(0, n, step, dtype=np.float64)
    if k[-1] != n - 1:
        k = np.append(k, n - 1)
    return k


class _Engine(TileEngine):
    def __init__(self, src: str, model: SensorModel, dem: Dem, grid: Grid, opts: OrthoOptions, dtype: np.dtype,
                 count: int, nodata: float, margin_px: int, h_ref: float,
                 h_range: tuple[float, float] | None = None):

        self.src, self.model, self.dem, self.grid, self.opts = src, model, dem, grid, opts
        self.dtype, self.count, self.nodata = dtype, count, nodata
        self.margin = int(margin_px)
        self.h_ref = h_ref
        self.h_range = h_range
        self.interp = {"nearest": cv2.INTER_NEAREST, "bilinear": cv2.INTER_LINEAR,
                       "cubic": cv2.INTER_CUBIC}[opts.resampling]
        self._init_readers()
        self.stats_lock = threading.Lock()
        self.hmin, self.hmax, self.n_occluded = math.inf, -math.inf, 0
        self.stride = relief_stride(grid)
        self.samples: list[NDArray[np.float64]] = []  # (row, col, h) of written cells on the relief lattice

        self.same_model = same_crs(grid.crs, model.crs)
        self.same_dem = same_crs(grid.crs, dem.crs)

    # ---------------------------------------------------------------- shipping to Dask workers
    _TRANSIENT = {**TileEngine._TRANSIENT, "stats_lock": threading.Lock}

    def portable(self) -> _Engine:
        """A copy for Dask workers: image and DEM by absolute path, no open readers, statistics reset."""

        eng = copy.copy(self)
        eng.src = os.path.abspath(self.src)
        if self.dem.constant is None:
            eng.dem = dataclasses.replace(self.dem, path=os.path.abspath(self.dem.path))
        eng.hmin, eng.hmax, eng.n_occluded = math.inf, -math.inf, 0
        eng.samples = []
        return eng

    def stats(self) -> tuple[float, float, int, NDArray[np.float64]]:
        """Heights met, occluded pixels and relief-lattice samples of the tiles this engine computed."""
        return self.hmin, self.hmax, self.n_occluded, self.lattice_samples()

    def merge_stats(self, stats: tuple[float, float, int, NDArray[np.float64]]) -> None:
        """Add another copy's :meth:`stats` (a Dask task's) to this engine's."""
        lo, hi, occluded, samples = stats
        with self.stats_lock:
            self.hmin, self.hmax = min(self.hmin, lo), max(self.hmax, hi)
            self.n_occluded += int(occluded)
            if len(samples):
                self.samples.append(np.asarray(samples, dtype=np.float64))

    def lattice_samples(self) -> NDArray[np.float64]:
        """(M, 3) (row, col, h) of the written cells on the relief lattice, sorted (the same on every scheduler)."""
        if not self.samples:
            return np.zeros((0, 3))
        a = np.vstack(self.samples)
        return a[np.lexsort((a[:, 1], a[:, 0]))]

    # ---------------------------------------------------------------- geometry of a block
    def _world(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray]:
        t = _gt(self.grid.transform)
        xs = t[2] + t[0] * (np.arange(c0, c0 + w) + 0.5)
        ys = t[5] + t[4] * (np.arange(r0, r0 + h) + 0.5)
        return np.broadcast_to(xs, (h, w)), np.broadcast_to(ys[:, None], (h, w))

    def _sparse(self, c0: int, r0: int, w: int, h: int, fn: Callable[[NDArray], NDArray], dim: int,
                step: int | None = None, matrix: bool = False) -> NDArray:
        """fn evaluated on a sparse grid of the block's world points, interpolated to (h, w, dim) (``matrix``:
        by :func:`_densify_matrix`)."""
        step = step or self.opts.map_step_px
        kc, kr = _knots(w, step), _knots(h, step)
        t = _gt(self.grid.transform)
        X = t[2] + t[0] * (c0 + kc + 0.5)
        Y = t[5] + t[4] * (r0 + kr + 0.5)
        XX, YY = np.meshgrid(X, Y)
        vals = np.asarray(fn(np.column_stack([XX.ravel(), YY.ravel()])), dtype=np.float64)
        vals = vals.reshape(len(kr), len(kc), dim)
        return _densify_matrix(vals, kc, kr, w, h) if matrix else _densify(vals, kc, kr, w, h)

    def _heights(self, c0: int, r0: int, w: int, h: int) -> NDArray[np.float64]:
        if self.dem.constant is not None:
            return np.full((h, w), self.dem.constant)
        M = pixel_from_world_matrix(self.dem.transform)
        z = None
        if self.same_dem and M[0, 1] == 0 and M[1, 0] == 0:
            # north-up over north-up: the DEM columns depend on the output column only, the rows on the row
            # (separable sampling, bit-identical to the point-by-point one; None when the window has holes)
            t = _gt(self.grid.transform)
            if t[1] == 0 and t[3] == 0:
                xs = t[2] + t[0] * (np.arange(c0, c0 + w) + 0.5)
                ys = t[5] + t[4] * (np.arange(r0, r0 + h) + 0.5)
                z = self.dem.heights_on_lattice(M[0, 0] * xs + M[0, 2], M[1, 1] * ys + M[1, 2])
        if z is not None:
            pass
        elif self.same_dem:
            X, Y = self._world(c0, r0, w, h)
            dx = M[0, 0] * X + M[0, 1] * Y + M[0, 2]
            dy = M[1, 0] * X + M[1, 1] * Y + M[1, 2]
        else:
            def to_dem_px(p):
                q = transform_xy(self.grid.crs, self.dem.crs, p)
                return q @ M[:2, :2].T + M[:2, 2]
            d = self._sparse(c0, r0, w, h, to_dem_px, 2)
            dx, dy = d[..., 0], d[..., 1]
        if z is None:
            z = self.dem.heights_at_dem_pixels(dx, dy)
        if self.dem.geoid is None:
            return z + self.dem.undulation
        # the geoid undulation varies slowly: exact on the sparse grid, interpolated
        return z + self._sparse(c0, r0, w, h, lambda p: self.dem.offset(
            transform_xy(self.grid.crs, "EPSG:4326", p))[:, None], 1)[..., 0]

    def _model_xy(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray]:
        if self.same_model:
            return self._world(c0, r0, w, h)
        m = self._sparse(c0, r0, w, h, lambda p: transform_xy(self.grid.crs, self.model.crs, p), 2)
        return m[..., 0], m[..., 1]

    def _direction(self, c0: int, r0: int, w: int, h: int, hz: float, step: int | None = None
                   ) -> NDArray[np.float64]:
        """Horizontal displacement towards the sensor per metre of height, in output pixels (h, w, 2) (col, row)."""

        t = _gt(self.grid.transform)
        dz = 10.0

        def fn(p):
            g0 = transform_xy(self.grid.crs, self.model.crs, p) if not self.same_model else p
            pix = self.model.project(np.column_stack([g0, np.full(len(g0), hz)]))
            out = np.zeros((len(p), 2))
            ok = np.isfinite(pix).all(axis=1)
            if ok.any():
                g1 = self.model.ground_at_height(pix[ok], hz + dz)
                ok2 = np.isfinite(g1).all(axis=1)
                w1 = np.full((ok.sum(), 2), np.nan)
                if ok2.any():
                    w1[ok2] = transform_xy(self.model.crs, self.grid.crs, g1[ok2, :2]) if not self.same_model \
                        else g1[ok2, :2]
                d = (w1 - p[ok]) / dz
                out[ok] = np.where(np.isfinite(d), d, 0.0)
            return np.column_stack([out[:, 0] / t[0], out[:, 1] / t[4]])
        return self._sparse(c0, r0, w, h, fn, 2, step, matrix=True)

    def _project(self, c0: int, r0: int, w: int, h: int, z: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Image (col, row) of every output pixel at its DEM height, (h, w) each; NaN where unknown.

        The projection is evaluated exactly on the sparse grid at 4 heights spanning the tile's heights
        and interpolated (bilinear in x, y; cubic Lagrange in h). The interpolation is checked against
        the exact projection at the sparse cells' centres and intermediate heights; when it is off by
        more than ``PROJECTION_TOLERANCE_PX`` the tile is projected exactly, pixel by pixel.
        """
        fin = np.isfinite(z)
        all_fin = bool(fin.all())
        if not all_fin and not fin.any():
            return np.full((h, w), np.nan), np.full((h, w), np.nan)
        zlo, zhi = (float(z.min()), float(z.max())) if all_fin else (float(z[fin].min()), float(z[fin].max()))
        step = self.opts.map_step_px
        kc, kr = _knots(w, step), _knots(h, step)
        t = _gt(self.grid.transform)
        XX, YY = np.meshgrid(t[2] + t[0] * (c0 + kc + 0.5), t[5] + t[4] * (r0 + kr + 0.5))
        # cell centres, for the check
        xc = 0.5 * (kc[:-1] + kc[1:]) if len(kc) > 1 else kc
        yc = 0.5 * (kr[:-1] + kr[1:]) if len(kr) > 1 else kr
        XC, YC = np.meshgrid(t[2] + t[0] * (c0 + xc + 0.5), t[5] + t[4] * (r0 + yc + 0.5))
        pts = np.column_stack([np.concatenate([XX.ravel(), XC.ravel()]), np.concatenate([YY.ravel(), YC.ravel()])])
        if not self.same_model:
            pts = transform_xy(self.grid.crs, self.model.crs, pts)
        n_knot = XX.size
        span = zhi - zlo
        K = 1 if span < 1e-9 else 4
        hk = np.linspace(zlo, zhi, K) if K > 1 else np.array([zlo])
        vals = np.empty((len(kr), len(kc), K, 2))
        for k, hv in enumerate(hk):
            vals[:, :, k] = self.model.project(np.column_stack([pts[:n_knot], np.full(n_knot, hv)])
                                               ).reshape(len(kr), len(kc), 2)
        exact = not np.isfinite(vals).all()
        if not exact and len(kc) > 1 and len(kr) > 1:
            # check at the cell centres and at heights between the nodes
            tq = np.array([1 / 6, 1 / 2, 5 / 6])[np.arange(XC.size) % 3] if K > 1 else np.zeros(XC.size)
            centre = 0.25 * (vals[:-1, :-1] + vals[1:, :-1] + vals[:-1, 1:] + vals[1:, 1:]).reshape(-1, K, 2)
            est = np.einsum("nk,nkc->nc", _lagrange4(tq), centre) if K > 1 else centre[:, 0]
            ex = self.model.project(np.column_stack([pts[n_knot:], zlo + tq * span]))
            err = np.abs(est - ex).max() if np.isfinite(ex).all() else np.inf
            exact = not (err <= PROJECTION_TOLERANCE_PX)
        if exact:
            mx, my = self._model_xy(c0, r0, w, h)
            g = np.column_stack([mx.ravel(), my.ravel(), z.ravel()])
            okz = fin.ravel()
            pix = np.full((len(g), 2), np.nan)
            pix[okz] = self.model.project(g[okz])
            return pix[:, 0].reshape(h, w), pix[:, 1].reshape(h, w)
        # bilinear interpolation of the sparse planes as two small matrix products, A (h, nr) @ V @ B (nc, w)
        # (two non-zero weights a row: the same sums as the gather form, to rounding, ~1e-16 relative)
        A = _interp_matrix(h, kr)
        B = _interp_matrix(w, kc).T
        col = np.empty((h, w))
        row = np.empty((h, w))
        if K == 1:
            planes = (A @ vals[:, :, 0].reshape(len(kr), -1)).reshape(h, len(kc), 2)
            np.matmul(planes[:, :, 0], B, out=col)
            np.matmul(planes[:, :, 1], B, out=row)
        else:
            # cubic in t = (z - zlo) / span through the 4 nodes: coefficients per sparse point, Horner per pixel
            coef = np.einsum("jk,rskc->rsjc", _VANDER_INV, vals)
            left = (A @ coef.reshape(len(kr), -1)).reshape(h, len(kc), 4, 2)  # BLAS (einsum's own loop: 5x slower)
            tz = (z - zlo) / span
            if not all_fin:
                tz[~fin] = 0.0
            tmp = np.empty((h, w))
            for c, acc in ((0, col), (1, row)):
                np.matmul(left[:, :, 3, c], B, out=acc)
                for j in (2, 1, 0):
                    acc *= tz
                    acc += np.matmul(left[:, :, j, c], B, out=tmp)
        if not all_fin:
            col[~fin] = np.nan
            row[~fin] = np.nan
        return col, row

    # ---------------------------------------------------------------- one tile
    def _margins(self, c0: int, r0: int, w: int, h: int) -> tuple[int, int, int, int]:
        """Cells of the line-of-sight block beyond a tile (left, top, right, bottom): how far the ground points of
        the tile (a 5 x 5 lattice) move towards the sensor from the lowest to the highest height, x 1.5 + 4
        (the rule of :func:`_margin_px`, side by side), at most the grid's margin; that margin on every side
        when a point does not project."""
        m = self.margin
        if self.h_range is None:
            return m, m, m, m
        t = _gt(self.grid.transform)
        cc, rr = np.meshgrid(np.linspace(c0, c0 + w - 1, 5), np.linspace(r0, r0 + h - 1, 5))
        p = np.column_stack([t[2] + t[0] * (cc.ravel() + 0.5), t[5] + t[4] * (rr.ravel() + 0.5)])
        lo, hi = self.h_range
        g0 = p if self.same_model else transform_xy(self.grid.crs, self.model.crs, p)
        pix = self.model.project(np.column_stack([g0, np.full(len(g0), lo)]))
        g1 = self.model.ground_at_height(pix, hi) if np.isfinite(pix).all() else None
        if g1 is None or not np.isfinite(g1[:, :2]).all():
            return m, m, m, m
        p1 = g1[:, :2] if self.same_model else transform_xy(self.model.crs, self.grid.crs, g1[:, :2])
        dc, dr = (p1[:, 0] - p[:, 0]) / t[0], (p1[:, 1] - p[:, 1]) / t[4]
        if not (np.isfinite(dc).all() and np.isfinite(dr).all()):
            return m, m, m, m

        def side(v: float) -> int:
            return min(m, int(math.ceil(max(v, 0.0) * 1.5)) + 4)
        return side(-float(dc.min())), side(-float(dr.min())), side(float(dc.max())), side(float(dr.max()))

    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, bool]:
        ml, mt, mr, mb = self._margins(c0, r0, w, h) if self.opts.true_ortho else (0, 0, 0, 0)
        # the block with margins (for the line-of-sight test), clipped to nothing: heights outside the grid exist
        Z = self._heights(c0 - ml, r0 - mt, w + ml + mr, h + mt + mb)
        z = Z[mt:mt + h, ml:ml + w]
        col, row = self._project(c0, r0, w, h, z)
        W, H = self.model.width, self.model.height
        with np.errstate(invalid="ignore"):  # NaN compares False: outside
            inside = (col >= -0.5) & (col <= W - 0.5) & (row >= -0.5) & (row <= H - 0.5)
        vis = None
        if self.opts.true_ortho and inside.any():
            d = self._direction(c0, r0, w, h, float(np.nanmean(z[inside])))
            vis = self._visible(Z, (ml, mt), d, w, h, z, inside)
        out_bands = self.count + (1 if self.opts.true_ortho else 0)
        if not inside.any():
            out = np.full((h, w, out_bands), self.nodata, dtype=self.dtype)
            if self.opts.true_ortho:
                out[..., -1] = VISIBILITY_OUTSIDE
            return out, True
        use = inside if vis is None else (inside & vis)
        data = self._resample(col, row, use, h, w) if use.any() else None
        if (data is not None and not self.opts.true_ortho and self.nodata == 0 and self.dtype.kind in "ui"
                and data[0].dtype == self.dtype and data[0].shape == (h, w, self.count)):
            # the resampled tile itself, 0 (nodata) where nothing is written: the bytes of the general path below
            img, valid = data
            sel = use & valid
            np.multiply(img, sel[..., None], out=img)
            self._stats(c0, r0, z, sel)
            return img, False
        out = np.full((h, w, out_bands), self.nodata, dtype=self.dtype)
        if self.opts.true_ortho:
            out[..., -1] = np.where(inside, np.where(use, VISIBILITY_VISIBLE, VISIBILITY_OCCLUDED), VISIBILITY_OUTSIDE)
            with self.stats_lock:
                self.n_occluded += int((inside & ~use).sum())
        if data is not None:
            img, valid = data
            sel = use & valid
            np.copyto(out[..., :self.count], img, where=sel[..., None])
            self._stats(c0, r0, z, sel)
        return out, False

    def _stats(self, c0: int, r0: int, z: NDArray[np.float64], written: NDArray[np.bool_]) -> None:
        """Heights met on the written (valid) cells of a tile, and its cells on the relief lattice."""
        ok = written & np.isfinite(z)
        if not ok.any():
            return
        zk = z if ok.all() else z[ok]  # (a masked reduction, where=, is 4x slower than the gather)
        lo, hi = float(zk.min()), float(zk.max())
        s = self.stride
        h, w = z.shape
        rr = np.arange((s // 2 - r0) % s, h, s)
        cc = np.arange((s // 2 - c0) % s, w, s)
        sub = ok[np.ix_(rr, cc)]
        i, j = np.nonzero(sub)
        sample = np.column_stack([r0 + rr[i], c0 + cc[j], z[rr[i], cc[j]]])
        with self.stats_lock:
            self.hmin, self.hmax = min(self.hmin, lo), max(self.hmax, hi)
            if len(sample):
                self.samples.append(sample)

    def _visible(self, Z: NDArray, m: tuple[int, int], d: NDArray, w: int, h: int, z: NDArray,
                 inside: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Line-of-sight test over the DEM block ``Z`` (the tile from column, row ``m``): True where nothing
        hides the point.

        ``d`` (h, w, 2): output pixels per metre of height towards the sensor
        (:func:`rectify.raster.visibility.line_of_sight`).
        """
        return line_of_sight(Z, m, d, z, inside)

    def _resample(self, col: NDArray, row: NDArray, use: NDArray[np.bool_], h: int, w: int):
        W, H = self.model.width, self.model.height
        pad = 3
        cu, ru = (col, row) if use.all() else (col[use], row[use])  # (use has a pixel)
        c_lo, r_lo = max(int(math.floor(cu.min())) - pad, 0), max(int(math.floor(ru.min())) - pad, 0)
        c_hi, r_hi = min(int(math.ceil(cu.max())) + pad + 1, W), min(int(math.ceil(ru.max())) + pad + 1, H)
        if c_hi <= c_lo or r_hi <= r_lo:
            return None
        if c_hi - c_lo > self.opts.max_window_px or r_hi - r_lo > self.opts.max_window_px:
            if h <= 16 and w <= 16:
                raise InvalidInputError(f"the source window for one output tile exceeds {self.opts.max_window_px} px;"
                                        f" use a finer output resolution")
            # split the tile in four
            img = np.zeros((h, w, self.count), dtype=np.float64)
            valid = np.zeros((h, w), bool)
            hh, ww = max(h // 2, 1), max(w // 2, 1)
            for rs, re_ in ((0, hh), (hh, h)):
                for cs, ce in ((0, ww), (ww, w)):
                    if re_ <= rs or ce <= cs:
                        continue
                    u = use[rs:re_, cs:ce]
                    if not u.any():
                        continue
                    sub = self._resample(col[rs:re_, cs:ce], row[rs:re_, cs:ce], u, re_ - rs, ce - cs)
                    if sub is not None:
                        img[rs:re_, cs:ce] = sub[0]
                        valid[rs:re_, cs:ce] = sub[1]
            return img, valid
        data, vmask = self.reader().read(c_lo, r_lo, c_hi - c_lo, r_hi - r_lo)
        mx = np.subtract(col, c_lo, out=np.empty(col.shape, np.float32), casting="unsafe")
        my = np.subtract(row, r_lo, out=np.empty(row.shape, np.float32), casting="unsafe")
        if not use.all():
            off = ~use
            mx[off] = -10.0
            my[off] = -10.0
        src = data if data.dtype in (np.uint8, np.uint16, np.int16, np.float32) else data.astype(np.float32)
        chans = []
        for k0 in range(0, src.shape[2], 4):
            part = np.ascontiguousarray(src[..., k0:k0 + 4])
            if part.shape[2] == 2:
                r = cv2.remap(np.ascontiguousarray(part[..., :1]), mx, my, self.interp, borderMode=cv2.BORDER_REPLICATE)
                r2 = cv2.remap(np.ascontiguousarray(part[..., 1:]), mx, my, self.interp,
                               borderMode=cv2.BORDER_REPLICATE)
                r = np.dstack([r, r2])
            else:
                r = cv2.remap(part, mx, my, self.interp, borderMode=cv2.BORDER_REPLICATE)
            if r.ndim == 2:
                r = r[..., None]
            chans.append(r)
        img = chans[0] if len(chans) == 1 else np.concatenate(chans, axis=2)  # type: ignore[assignment]
        valid = np.ones((h, w), bool)
        if vmask is not None:
            v = cv2.remap(vmask.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
            valid = v > 0
        if self.dtype.kind in "ui":
            if img.dtype != self.dtype:  # OpenCV keeps an 8/16-bit source's type, rounded and saturated
                ii = np.iinfo(self.dtype)
                img = np.clip(np.rint(img), ii.min, ii.max).astype(self.dtype)
            if self.nodata == 0:
                img[img == 0] = 1
        return img.astype(self.dtype, copy=False), valid


def _margin_px(model: SensorModel, dem: Dem, grid: Grid, h_range: tuple[float, float]) -> int:
    """Output pixels a line of sight can travel over the DEM's height range (for the true-ortho margin)."""

    t = _gt(grid.transform)
    cc, rr = np.meshgrid(np.linspace(0, grid.width - 1, 9), np.linspace(0, grid.height - 1, 9))
    X = t[2] + t[0] * (cc.ravel() + 0.5)
    Y = t[5] + t[4] * (rr.ravel() + 0.5)
    g0 = transform_xy(grid.crs, model.crs, np.column_stack([X, Y]))
    lo, hi = h_range
    pix = model.project(np.column_stack([g0, np.full(len(g0), lo)]))
    ok = np.isfinite(pix).all(axis=1)
    if not ok.any():
        return 8
    g1 = model.ground_at_height(pix[ok], hi)
    ok1 = np.isfinite(g1).all(axis=1)
    if not ok1.any():
        return 8
    w1 = transform_xy(model.crs, grid.crs, g1[ok1, :2])
    w0 = np.column_stack([X, Y])[ok][ok1]
    dist = float(np.hypot(*(w1 - w0).T).max()) / grid.resolution[0]
    return int(min(math.ceil(dist * 1.5) + 4, 2048))


def orthorectify(src: str | Path, dst: str | Path, model: SensorModel, dem: Dem, *, grid: Grid | None = None,
                 dst_crs: str | None = None, resolution: float | None = None, options: OrthoOptions | None = None,
                 overwrite: bool = False, progress: Callable[[int, int], None] | None = None) -> OrthoResult:
    """Orthorectify ``src`` through a sensor model and a DEM into the GeoTIFF ``dst``.

    Parameters
    ----------
    src : path
        The image (any band count and dtype rasterio reads). Never modified.
    dst : path
        Output GeoTIFF (tiled; COG with ``options.cog``), written atomically.
    model : FrameModel or RPCModel
    dem : Dem
        Heights in the model's vertical frame (ellipsoidal for RPCs: use
        ``Dem(undulation=...)`` or ``geoid=`` for geoid heights).
    grid : Grid, optional
        Output grid; default :func:`ortho_grid` (``dst_crs``, ``resolution``).
    options : OrthoOptions

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        Unreadable inputs, existing output without ``overwrite``, output equal
        to an input, an image that does not match its model's size.
    """

    opts = options or OrthoOptions()
    sched = resolve_scheduler(opts.scheduler)
    t0 = time.perf_counter()
    src = str(src)
    for p in (src,) if dem.constant is not None else (src, dem.path):
        if Path(dst).resolve() == Path(p).resolve():
            raise InvalidInputError(f"output {str(dst)!r} is an input; inputs are never modified")
    check_output(dst, overwrite=overwrite)
    info = raster_info(src)
    if (info.width, info.height) != (model.width, model.height):
        raise InvalidInputError(f"image {src!r} is {info.width} x {info.height} px but its model expects "
                                f"{model.width} x {model.height}")
    if grid is None:
        grid = ortho_grid(model, dem, dst_crs=dst_crs, resolution=resolution)
    elif grid.crs is None:
        raise CRSError("the output grid needs a CRS")
    else:
        grid = Grid(grid.width, grid.height, grid.transform, crs_to_string(grid.crs))
    dtype = np.dtype(info.dtype)
    if info.nodata is not None:
        nodata = float(info.nodata)
    else:
        nodata = float("nan") if dtype.kind == "f" else 0.0
    check_output_format(opts.compress, dtype, info.count + (1 if opts.true_ortho else 0), opts.quality)
    # an orthophoto that would be empty or mostly nodata is refused before any tile (with the numbers)
    coverage = check_coverage(model, dem, grid, opts.min_valid_share) if opts.min_valid_share > 0 else None
    hr = dem.range()
    h_ref = 0.5 * (hr[0] + hr[1])
    margin = _margin_px(model, dem, grid, hr) if opts.true_ortho else 0
    engine = _Engine(src, model, dem, grid, opts, dtype, info.count, nodata, margin, h_ref, hr)
    windows = tile_windows(grid.width, grid.height, opts.tile_px)
    count = info.count + (1 if opts.true_ortho else 0)
    nad = _nadir_in(model, str(grid.crs))
    dem_name = dem.path if dem.constant is not None else Path(dem.path).name
    tags = {"ORTHO_MODEL": type(model).__name__, "ORTHO_DEM": dem_name,
            "ORTHO_NADIR_X": repr(float(nad[0])), "ORTHO_NADIR_Y": repr(float(nad[1]))}
    tags.update(_centre_tags(model, str(grid.crs)))  # issue 27: the mosaic's least-transformed seamlines
    if opts.true_ortho:
        tags["ORTHO_VISIBILITY_BAND"] = str(count)
    try:
        with _blas_one_thread():
            n_empty = _write(engine, dst, grid, windows, count, dtype, nodata, opts, sched, overwrite, progress, tags)
    except OSError as err:
        if isinstance(err, (RasterIOError, SchedulerError)):  # a Dask scheduler's failure is not a write failure
            raise
        raise RasterIOError(f"cannot write {str(dst)!r}: {err}") from err
    lo = engine.hmin if math.isfinite(engine.hmin) else float("nan")
    hi = engine.hmax if math.isfinite(engine.hmax) else float("nan")
    relief = relief_shift(model, grid, engine.lattice_samples(), engine.stride)
    dt = time.perf_counter() - t0
    logger.info("ortho %s -> %s: %d x %d, %d tiles in %.2f s", src, dst, grid.width, grid.height, len(windows), dt)
    max_shift = relief.max if math.isfinite(relief.max) else 0.0
    return OrthoResult(Path(dst), grid, dt, len(windows), n_empty, dem.path, (lo, hi), max_shift, engine.n_occluded,
                       nodata, type(model).__name__,
                       {"true_ortho": opts.true_ortho, "visibility_band": count if opts.true_ortho else None,
                        "margin_px": margin, "dem_datum": dem.datum,
                        "valid_share": None if coverage is None else coverage.valid_share}, relief)


#: tile windows a worker thread needs to pay back its start, reader and GIL hand-overs (see :func:`_write`)
TILES_PER_THREAD = 8
#: a true orthophoto's tile counts as this many plain tiles there (its line-of-sight march: ~2.5x the work)
TRUE_ORTHO_TILE_WORK = 2


def _write(engine: _Engine, dst: str | Path, grid: Grid, windows: list, count: int, dtype: np.dtype, nodata: float,
           opts: OrthoOptions, sched: Scheduler, overwrite: bool, progress: Callable[[int, int], None] | None,
           tags: dict[str, str]) -> int:
    """The engine's tiles into ``dst`` through the shared output tail; the empty tiles.

    A small grid (fewer than :data:`TILES_PER_THREAD` windows a thread) runs on fewer tile threads (the
    compression keeps ``threads``): each thread
    costs a start, its own source reader and GIL hand-overs, which a few tiles do not pay back (a 722 x 1274
    frame, 6 tiles: 0.19 s on one thread against 0.20-0.27 s on two). Its true orthophoto (about 2.5x the
    work a tile since the march skips from the first sample, docs/ortho.md) runs on one thread too: both NGI
    frames took 0.46 s CPU (0.51 s wall) on one against 0.55 s CPU (0.74 s wall) on two at load 5. The
    pixels do not depend on it.
    """
    work = len(windows) * (TRUE_ORTHO_TILE_WORK if opts.true_ortho else 1)
    workers = max(1, min(opts.n_threads, work // TILES_PER_THREAD))
    return write_tiled(engine, dst, grid, windows, count=count, dtype=dtype, policy=MaskPolicy("nodata", nodata),
                       tile=opts.tile_px, compress=opts.compress, cog=opts.cog, threads=opts.n_threads, workers=workers,
                       scheduler=sched, overwrite=overwrite, progress=progress, name="ortho",
                       cache_bytes=64 * 1024 * 1024, cog_resampling="nearest", tags=tags, quality=opts.quality,
                       band_descriptions={count: "visibility: 0 outside, 1 occluded, 2 visible"}
                       if opts.true_ortho else None)


def _nadir_in(model: SensorModel, crs: str) -> NDArray[np.float64]:
    try:
        return transform_xy(model.crs, crs, np.asarray(model.nadir).reshape(1, 2))[0]
    except Exception:  # noqa: BLE001 - the nadir is metadata only
        return np.array([np.nan, np.nan])


def _centre_tags(model: SensorModel, crs: str) -> dict[str, str]:
    """``ORTHO_CENTER_X/Y/Z`` (output CRS, metres up): a frame model's projection centre; for an RPC a point
    1000 km up along the line of sight of the image centre (``ORTHO_CENTER_KIND`` ``direction``)."""
    pos = getattr(model, "position", None)
    try:
        if pos is not None:
            c = transform_xy(model.crs, crs, np.asarray(pos, dtype=np.float64)[:2].reshape(1, 2))[0]
            xyz, kind = (float(c[0]), float(c[1]), float(pos[2])), "centre"
        else:
            vb = model.rpc.validity_box[2]  # type: ignore[attr-defined]
            h0, up = 0.5 * (vb[0] + vb[1]), 1.0e6
            mid = np.array([[(model.width - 1) / 2.0, (model.height - 1) / 2.0]])
            g = [transform_xy(model.crs, crs, model.ground_at_height(mid, h)[:, :2])[0] for h in (h0, h0 + 100.0)]
            d = (g[1] - g[0]) / 100.0  # horizontal move towards the sensor per metre up
            xyz, kind = (float(g[0][0] + up * d[0]), float(g[0][1] + up * d[1]), h0 + up), "direction"
        if not all(math.isfinite(v) for v in xyz):
            return {}
    except Exception:  # noqa: BLE001 - the centre is metadata only
        return {}
    return {"ORTHO_CENTER_X": repr(xyz[0]), "ORTHO_CENTER_Y": repr(xyz[1]), "ORTHO_CENTER_Z": repr(xyz[2]),
            "ORTHO_CENTER_KIND": kind}
