"""The resampling engine: tile-by-tile inverse mapping into a GeoTIFF.

For every output tile (512 x 512 by default) the engine computes where its
pixels come from in the source, reads only the source window they need
(through :mod:`rectify.raster.io`), resamples it with OpenCV and writes the tile.
Memory is bounded by the tile and window sizes, not by the image: rasters
wider than OpenCV's 32767-pixel limit work because every OpenCV call sees
only a tile and its window. Tiles are computed on a thread pool (OpenCV and
GDAL release the GIL) and written by the calling thread.

Mappings (output pixel -> source pixel):

- a model with a ``(3, 3)`` ``matrix`` (affine, homography) is composed
  analytically with the output grid and evaluated exactly at every pixel;
- any other callable (polynomials, the cotangent method, a change of CRS
  through pyproj) is evaluated exactly on a sparse lattice of the output grid
  (every ``WarpOptions.map_step_px`` pixels) and interpolated bilinearly --
  like GDAL's approximate transformer.

Either way a pixel's source position is computed from its position in the
output grid alone (float64, stored as float32) and applied by ``cv2.remap``
on a window starting at an even column and row: the output does not depend
on the tile size (``cv2.warpAffine`` on a tile-relative transform moved some
pixels by OpenCV's 1/32 px step from one tiling to another, and OpenCV rounds
a half-way position to the window's even pixel).

Validity: an output pixel is valid when the source pixel nearest to its
source position is valid (so the footprint reaches the outer pixel edges, as
GDAL's); near invalid source pixels and the source's edge, the kernel weights
are renormalised over the valid neighbours. Invalid pixels receive the nodata value, alpha 0 or an
internal mask, following the source (:class:`rectify.raster.io.MaskPolicy`).

The tile engine runs on the shared base and output tail of :mod:`rectify.raster.engine`;
georectification by GCPs or a saved transform (fit, output grid, then this engine) is
:mod:`rectify.raster.georectify`.
"""

from __future__ import annotations

import copy
import logging
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import check_output
from rectify.errors import EstimationError, InvalidInputError, RasterIOError
from rectify.geometry.crs import get_transformer, same_crs
from rectify.raster.distributed import Scheduler, resolve_scheduler
from rectify.raster.engine import TileEngine, tile_windows, worker_count, write_tiled
from rectify.raster.georef import Grid, world_from_pixel, world_from_pixel_matrix
from rectify.raster.io import MaskPolicy, mask_policy, open_raster, raster_info

__all__ = ["RESAMPLING", "WarpOptions", "WarpResult", "warp_raster", "warp_array", "check_free_space",
           "DEFAULT_MAX_PIXELS"]

logger = logging.getLogger(__name__)

#: resampling name -> (OpenCV flag, kernel radius in source pixels)
RESAMPLING: dict[str, tuple[int, int]] = {}


def _resampling_table() -> dict[str, tuple[int, int]]:

    if not RESAMPLING:
        RESAMPLING.update({"nearest": (cv2.INTER_NEAREST, 1), "bilinear": (cv2.INTER_LINEAR, 1),
                           "cubic": (cv2.INTER_CUBIC, 2), "lanczos": (cv2.INTER_LANCZOS4, 4)})
    return RESAMPLING


RESAMPLING_NAMES = ("nearest", "bilinear", "cubic", "lanczos")
_CV_LIMIT = 32767  # OpenCV's SHRT_MAX limit on remap/warp sizes
#: default limit on the pixels of an output grid (``rectify warp --max-pixels``): 2e9, a 44721 px square
DEFAULT_MAX_PIXELS = 2e9
#: GDAL block cache per warp thread, MB (:attr:`WarpOptions.block_cache_mb`)
CACHE_MB_PER_THREAD = 64
#: compression ratio assumed when checking that an output fits on the disk
ASSUMED_COMPRESSION = 4.0


@dataclass(frozen=True)
class WarpOptions:
    """Options of the resampling engine.

    Attributes
    ----------
    resampling : str
        ``nearest``, ``bilinear``, ``cubic`` or ``lanczos``.
    tile_px : int
        Output tile (and GeoTIFF block) size, a multiple of 16.
    threads : int or None
        Worker threads; None = all cores (``os.cpu_count()``).
    compress : str
        GeoTIFF compression: ``zstd`` (default: fast, supported by GDAL >= 2.3
        and so by QGIS), ``deflate``, ``lzw`` or ``none``.
    cog : bool
        Write a Cloud Optimized GeoTIFF (overviews, COG layout).
    nodata : float or None
        Force this nodata value for the output (default: follow the source:
        its nodata, alpha band or mask; NaN for float rasters without any;
        an internal mask for integer rasters without any).
    map_step_px : int
        Spacing of the exactly-evaluated points for non-matrix mappings.
    max_window_px : int
        Largest source window side read for one tile; bigger needs split the tile.
    cache_mb : int or None
        GDAL block cache limit while warping, MB (default: :data:`CACHE_MB_PER_THREAD` per worker
        thread: each thread reads through its own dataset, and its neighbouring tiles reuse the source
        blocks it decoded only if they stay cached; with 64 MB for two threads a 10 000 px warp decoded
        a fifth of its source twice).
    max_pixels : float
        Refuse an output grid with more pixels than this (``rectify warp --max-pixels``), before
        any pixel is written: a degenerate transform or a tiny resolution can ask for billions.
    scheduler : rectify.raster.distributed.Scheduler, str or None
        Where the tiles run: ``threads`` (a local thread pool), ``processes[:N]`` (a local Dask
        cluster), ``tcp://HOST:PORT`` (an existing Dask cluster); None: ``$RECTIFY_SCHEDULER``, else
        ``threads``. Every scheduler writes the same bytes (:mod:`rectify.raster.distributed`).
    """

    resampling: str = "bilinear"
    tile_px: int = 512
    threads: int | None = None
    compress: str = "zstd"
    cog: bool = False
    nodata: float | None = None
    map_step_px: int = 16
    max_window_px: int = 8192
    cache_mb: int | None = None
    max_pixels: float = DEFAULT_MAX_PIXELS
    scheduler: Scheduler | str | None = None

    def __post_init__(self) -> None:
        if self.scheduler is not None:
            resolve_scheduler(self.scheduler)  # a bad value fails here, before any work
        if not self.max_pixels > 0:
            raise InvalidInputError(f"max_pixels must be > 0; got {self.max_pixels!r}")
        if self.resampling not in RESAMPLING_NAMES:
            raise InvalidInputError(f"unknown resampling {self.resampling!r}; expected one of {list(RESAMPLING_NAMES)}")
        if self.tile_px < 16 or self.tile_px % 16 or self.tile_px > 4096:
            raise InvalidInputError(f"tile_px must be a multiple of 16 in 16..4096; got {self.tile_px}")
        if self.cache_mb is not None and not self.cache_mb >= 1:
            raise InvalidInputError(f"cache_mb must be >= 1; got {self.cache_mb!r}")
        if self.threads is not None and self.threads < 1:
            raise InvalidInputError(f"threads must be >= 1; got {self.threads}")
        if self.compress.lower() not in ("deflate", "lzw", "zstd", "none", "packbits", "lzma"):
            raise InvalidInputError(f"unknown compression {self.compress!r}")
        if self.map_step_px < 1 or self.max_window_px < 64 or self.max_window_px > _CV_LIMIT:
            raise InvalidInputError(f"bad map_step_px {self.map_step_px} or max_window_px {self.max_window_px}")

    @property
    def n_threads(self) -> int:
        return worker_count(self.threads)

    @property
    def block_cache_mb(self) -> int:
        """GDAL's block cache while warping, MB (``cache_mb``, or :data:`CACHE_MB_PER_THREAD` per thread)."""
        return int(self.cache_mb) if self.cache_mb is not None else CACHE_MB_PER_THREAD * self.n_threads


@dataclass(frozen=True)
class WarpResult:
    """What :func:`warp_raster` wrote.

    Attributes
    ----------
    path : Path
    grid : Grid
    n_tiles : int
    n_empty_tiles : int
        Tiles entirely outside the footprint.
    seconds : float
    policy : str
        How invalid pixels are stored (``nodata``, ``mask``, ``alpha``).
    nodata : float or None
    """

    path: Path
    grid: Grid
    n_tiles: int
    n_empty_tiles: int
    seconds: float
    policy: str
    nodata: float | None


# --------------------------------------------------------------------------- mappings
class _Mapping:
    """Output pixel (col, row) -> source pixel, per tile."""

    def __init__(self, grid: Grid, source_from_world: Callable, world_crs: str | None, step: int):
        self.step = step
        m = getattr(source_from_world, "matrix", None)
        same = world_crs is None or grid.crs is None or same_crs(world_crs, grid.crs)
        self.matrix = None
        if m is not None and same:
            mm = np.asarray(m, dtype=np.float64)
            if mm.shape == (3, 3):
                self.matrix = mm @ world_from_pixel_matrix(grid.transform)
                self.matrix = self.matrix / self.matrix[2, 2] if abs(self.matrix[2, 2]) > 1e-300 else self.matrix
        self.affine = self.matrix is not None and np.allclose(self.matrix[2, :2], 0.0, atol=1e-15)
        self._grid = grid
        self._f = source_from_world
        self._crs = (grid.crs, world_crs) if not same else None

    def points(self, pix: NDArray[np.float64]) -> NDArray[np.float64]:
        """Exact source positions (N, 2) of output pixels (N, 2); NaN where undefined."""
        if self.matrix is not None:
            h = pix @ self.matrix[:, :2].T + self.matrix[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                out = h[:, :2] / h[:, 2:3]
            out[~(h[:, 2] > 0)] = np.nan  # behind the horizon
            return out
        world = world_from_pixel(self._grid.transform, pix)
        if self._crs is not None:
            t = get_transformer(self._crs[0], self._crs[1])
            x, y = t.transform(world[:, 0], world[:, 1])
            world = np.column_stack([x, y])
        ok = np.isfinite(world).all(axis=1)
        out = np.full_like(world, np.nan)
        if ok.any():
            try:
                out[ok] = np.asarray(self._f(world[ok]), dtype=np.float64)
            except (EstimationError, InvalidInputError, FloatingPointError, ZeroDivisionError) as err:
                raise InvalidInputError(f"the transform cannot map output pixels back to the source: {err}") \
                    from err
        return out

    def matrix_maps(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Exact source x, y maps (h, w) float32 of a tile for a matrix mapping; NaN behind the horizon.

        Each pixel's value is computed from its grid position alone (float64, then rounded to float32), so
        it is the same whatever tile holds the pixel: OpenCV's own warpAffine/warpPerspective round a
        tile-relative transform and move some pixels by 1/32 px from one tiling to another.
        """
        M = self.matrix
        assert M is not None
        x = np.arange(c0, c0 + w, dtype=np.float64)[None, :]
        y = np.arange(r0, r0 + h, dtype=np.float64)[:, None]
        if self.affine:  # float64 sums stored as float32 in one pass each
            X = np.add(M[0, 0] * x, M[0, 1] * y + M[0, 2], out=np.empty((h, w), np.float32), casting="same_kind")
            Y = np.add(M[1, 0] * x, M[1, 1] * y + M[1, 2], out=np.empty((h, w), np.float32), casting="same_kind")
            return X, Y
        Z = M[2, 0] * x + (M[2, 1] * y + M[2, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            X = (M[0, 0] * x + (M[0, 1] * y + M[0, 2])) / Z
            Y = (M[1, 0] * x + (M[1, 1] * y + M[1, 2])) / Z
        behind = ~(Z > 0)
        X[behind] = np.nan
        Y[behind] = np.nan
        return X.astype(np.float32), Y.astype(np.float32)

    def knots(self, lo: int, hi: int, n: int) -> NDArray[np.float64]:
        """The exactly evaluated columns (or rows) of the sparse lattice from ``lo`` to ``hi`` (grid pixels):
        whole multiples of the step and the grid's last pixel ``n - 1``, from the last knot at or before ``lo``
        to the first at or after ``hi``. The lattice is the grid's, not the tile's: every tiling interpolates
        every pixel between the same two knots."""
        s = self.step
        first = (lo // s) * s
        last = min(-(-hi // s) * s, n - 1)
        k = np.arange(first, last + 1, s, dtype=np.float64)
        if k[-1] < last:
            k = np.r_[k, float(last)]
        return k

    def dense(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Source x, y maps (h, w) float32 for a tile, by sparse exact points + bilinear interpolation.

        The exact points lie on the grid's lattice (:meth:`knots`), so a pixel's value does not depend on
        the tile that holds it.
        """
        xs = self.knots(c0, c0 + w - 1, self._grid.width)
        ys = self.knots(r0, r0 + h - 1, self._grid.height)
        gx, gy = np.meshgrid(xs, ys)
        src = self.points(np.column_stack([gx.ravel(), gy.ravel()])).reshape(len(ys), len(xs), 2)
        cols = np.arange(c0, c0 + w, dtype=np.float64)
        rows = np.arange(r0, r0 + h, dtype=np.float64)
        ix = np.clip(np.searchsorted(xs, cols, side="right") - 1, 0, max(len(xs) - 2, 0))
        iy = np.clip(np.searchsorted(ys, rows, side="right") - 1, 0, max(len(ys) - 2, 0))
        # separable linear interpolation onto every pixel
        out = []
        for k in range(2):
            v = src[:, :, k]
            if len(xs) > 1:
                fx = (cols - xs[ix]) / (xs[ix + 1] - xs[ix])
                vx = v[:, ix] * (1 - fx) + v[:, ix + 1] * fx
            else:
                vx = np.repeat(v[:, :1], w, axis=1)
            if len(ys) > 1:
                fy = (rows - ys[iy]) / (ys[iy + 1] - ys[iy])
                vv = vx[iy, :] * (1 - fy)[:, None] + vx[iy + 1, :] * fy[:, None]
            else:
                vv = np.repeat(vx[:1, :], h, axis=0)
            out.append(vv.astype(np.float32))
        return out[0], out[1]


# --------------------------------------------------------------------------- tile kernel
def _fill_value(policy_kind: str, nodata: float | None, dtype: np.dtype) -> Any:
    if policy_kind == "nodata" and nodata is not None:
        return np.asarray(nodata).astype(dtype)[()]
    return np.zeros((), dtype=dtype)[()]


def _cv_dtype(a: NDArray) -> NDArray:
    """OpenCV warps uint8, uint16, int16, float32, float64; others go through float64."""
    if a.dtype in (np.uint8, np.uint16, np.int16, np.float32, np.float64):
        return a
    return a.astype(np.float64)


Maps = tuple[NDArray[np.float32], NDArray[np.float32]]


def _apply(img: NDArray, *, maps: Maps, interp: int, border: int) -> NDArray:
    """Resample ``img`` (h, w[, C<=4]) at the window positions ``maps`` (each (h', w') float32)."""
    return cv2.remap(img, maps[0], maps[1], interp, borderMode=border, borderValue=0)


def _warp_channels(data: NDArray, *, maps: Maps, interp: int, border: int) -> NDArray:
    """Resample (h, w, C) in chunks of at most 4 channels (OpenCV's limit for some kernels)."""
    c = data.shape[2]
    if c <= 4:
        out = _apply(data if c > 1 else data[:, :, 0], maps=maps, interp=interp, border=border)
        return out.reshape(out.shape[0], out.shape[1], c)
    parts = [_apply(np.ascontiguousarray(data[:, :, i:i + 4]), maps=maps, interp=interp, border=border)
             for i in range(0, c, 4)]
    parts = [p[:, :, None] if p.ndim == 2 else p for p in parts]
    return np.concatenate(parts, axis=2)


class _Engine(TileEngine):
    def __init__(self, src: str, mapping: _Mapping, grid: Grid, opts: WarpOptions, out_dtype: np.dtype,
                 count: int, fill: Any):
        info = raster_info(src)
        self.src, self.mapping, self.grid, self.opts = src, mapping, grid, opts
        self.W, self.H = info.width, info.height
        self.interp, self.radius = _resampling_table()[opts.resampling]
        self.dtype, self.count, self.fill = out_dtype, count, fill
        self._init_readers()

    # ----------------------------------------------------------------- shipping to Dask workers
    def portable(self) -> _Engine:
        """A copy for Dask workers: the source by absolute path, no open readers."""
        eng = copy.copy(self)
        eng.src = os.path.abspath(self.src)
        return eng

    # ----------------------------------------------------------------- one tile
    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray[np.bool_] | None, bool]:
        """Compute one output tile -> (data (h, w, C), valid or None, empty)."""
        m = self.mapping
        # per-pixel maps computed from grid positions: the tiling does not change a pixel's source position
        maps = m.matrix_maps(c0, r0, w, h) if m.matrix is not None else m.dense(c0, r0, w, h)
        mx, my = maps
        # NaN compares False: finite and within the source (plus the kernel) in one pass each
        ok = (mx >= -0.5 - self.radius) & (mx <= self.W - 0.5 + self.radius) & \
            (my >= -0.5 - self.radius) & (my <= self.H - 0.5 + self.radius)
        if not ok.any():
            return self._empty(w, h), np.zeros((h, w), bool), True
        if ok.all():
            bx, by = (float(mx.min()), float(mx.max())), (float(my.min()), float(my.max()))
        else:
            sx, sy = mx[ok], my[ok]
            bx, by = (float(sx.min()), float(sx.max())), (float(sy.min()), float(sy.max()))
        # the window starts at an even column and row: OpenCV rounds a position half-way between two pixels to
        # the even one of the window, so an even origin makes it the same pixel whatever the tiling
        x0 = max(math.floor(bx[0]) - self.radius, 0) // 2 * 2
        y0 = max(math.floor(by[0]) - self.radius, 0) // 2 * 2
        x1 = min(math.ceil(bx[1]) + self.radius + 1, self.W)
        y1 = min(math.ceil(by[1]) + self.radius + 1, self.H)
        if x1 <= x0 or y1 <= y0:
            return self._empty(w, h), np.zeros((h, w), bool), True
        if (x1 - x0 > self.opts.max_window_px or y1 - y0 > self.opts.max_window_px) and max(w, h) > 16:
            return self._split(c0, r0, w, h)
        data, valid = self.reader().read(x0, y0, x1 - x0, y1 - y0)
        # every output pixel maps inside the source raster (not just the window): no footprint edge in the tile
        full_inside = bool(ok.all() and bx[0] >= 0 and by[0] >= 0 and bx[1] <= self.W - 1 and by[1] <= self.H - 1)
        return self._resample(data, valid, x0, y0, w, h, maps, full_inside)

    def _empty(self, w: int, h: int) -> NDArray:
        return np.full((h, w, self.count), self.fill, dtype=self.dtype)

    def _split(self, c0, r0, w, h):
        out = self._empty(w, h)
        valid = np.zeros((h, w), bool)
        hw, hh = max(w // 2, 1), max(h // 2, 1)
        for cc, ww in ((c0, hw), (c0 + hw, w - hw)):
            for rr, hgt in ((r0, hh), (r0 + hh, h - hh)):
                if ww <= 0 or hgt <= 0:
                    continue
                d, v, empty = self.tile(cc, rr, ww, hgt)
                out[rr - r0:rr - r0 + hgt, cc - c0:cc - c0 + ww] = d
                valid[rr - r0:rr - r0 + hgt, cc - c0:cc - c0 + ww] = True if v is None else v
        return out, (None if valid.all() else valid), not valid.any()

    def _resample(self, data, valid, x0, y0, w, h, maps, full_inside):

        # window-relative maps: float32 minus a whole number is exact, so the shift changes no value
        wm = (maps[0] - np.float32(x0), maps[1] - np.float32(y0))
        src = _cv_dtype(data)
        out = _warp_channels(src, maps=wm, interp=self.interp, border=cv2.BORDER_REPLICATE)
        # footprint: nearest source pixel inside the window and valid
        win_h, win_w = data.shape[:2]
        if valid is None and self.opts.resampling != "nearest" and \
                (x0 == 0 or y0 == 0 or x0 + win_w == self.W or y0 + win_h == self.H):
            # at the source's edge the kernel is renormalised over the source pixels, as in a window with nodata:
            # whether the window also holds nodata must not change an edge pixel (it depends on the tiling)
            valid = np.ones((win_h, win_w), bool)
        if valid is None and full_inside:
            out_valid = None
        else:
            vm = np.full((win_h, win_w), 255, np.uint8) if valid is None else valid.astype(np.uint8) * 255
            near = _apply(vm, maps=wm, interp=cv2.INTER_NEAREST, border=cv2.BORDER_CONSTANT)
            out_valid = near > 0
            if valid is not None and self.opts.resampling != "nearest":
                # renormalise the kernel over valid neighbours near invalid source pixels
                lin = _apply(valid.astype(np.float32), maps=wm, interp=self.interp, border=cv2.BORDER_CONSTANT)
                edge = out_valid & (lin < 1.0 - 1e-6)
                if edge.any():
                    src0 = src.astype(np.float32) if src.dtype.kind in "ui" else src.copy()
                    src0[~valid] = 0
                    part = _warp_channels(src0, maps=wm, interp=self.interp, border=cv2.BORDER_CONSTANT)
                    wgt = lin[edge].astype(np.float64)[:, None]
                    vals = part[edge].astype(np.float64) / np.maximum(wgt, 1e-6)
                    out = out.copy() if not out.flags.writeable else out
                    out[edge] = _cast(vals, out.dtype)
            if not out_valid.any():
                return self._empty(w, h), out_valid, True
        if out.dtype != self.dtype:
            out = _cast(out, self.dtype)
        if out_valid is not None:
            out[~out_valid] = self.fill
            if out_valid.all():
                out_valid = None
        return out, out_valid, False


def _cast(a: NDArray, dtype: np.dtype) -> NDArray:
    dt = np.dtype(dtype)
    if dt.kind in "ui":
        info = np.iinfo(dt)
        return np.clip(np.rint(a), info.min, info.max).astype(dt)
    return a.astype(dt)


# --------------------------------------------------------------------------- public API
def _output_policy(src: str, opts: WarpOptions):

    info = raster_info(src)
    dtype = np.dtype(info.dtype)
    if opts.nodata is not None:
        return MaskPolicy("nodata", float(opts.nodata)), dtype
    pol = mask_policy(src)
    if pol.kind != "none":
        if pol.kind == "nodata" and pol.nodata is not None and dtype.kind in "ui":
            ii = np.iinfo(dtype)
            if not (ii.min <= pol.nodata <= ii.max):
                return MaskPolicy("mask"), dtype
        return pol, dtype
    if dtype.kind == "f":
        return MaskPolicy("nodata", float("nan")), dtype
    return MaskPolicy("mask"), dtype


def warp_raster(src: str | Path, dst: str | Path, source_from_world: Callable[[NDArray], NDArray],
                grid: Grid, *, world_crs: str | None = None, options: WarpOptions | None = None,
                overwrite: bool = False, progress: Callable[[int, int], None] | None = None) -> WarpResult:
    """Resample a raster onto ``grid`` through an inverse mapping, tile by tile.

    Parameters
    ----------
    src : path
        Any raster rasterio reads (any band count; uint8, uint16, int16,
        float32, ...). Never modified.
    dst : path
        Output GeoTIFF (tiled, compressed; COG with ``options.cog``). Written to
        a temporary file renamed at the end: no partial file on error.
    source_from_world : callable (N, 2) -> (N, 2)
        Output world coordinates (x, y in ``world_crs``, or in the grid's CRS)
        -> source pixels (col, row; centres at integers). A model with a
        ``(3, 3)`` ``matrix`` attribute (affine, homography) is used
        analytically.
    grid : Grid
        Output grid (size, geotransform, CRS).
    world_crs : str, optional
        CRS of the coordinates ``source_from_world`` expects, when it differs
        from ``grid.crs`` (each output pixel then goes through pyproj).
    options : WarpOptions
    overwrite : bool
        Replace an existing ``dst``.
    progress : callable(done, total), optional
        Called after each tile.

    Returns
    -------
    WarpResult

    Raises
    ------
    RasterIOError
        Unreadable source, unwritable output.
    InvalidInputError
        Existing output without ``overwrite``, ``dst`` equal to ``src``, bad options.
    """

    opts = options or WarpOptions()
    sched = resolve_scheduler(opts.scheduler)
    t0 = time.perf_counter()
    src = str(src)
    if Path(dst).resolve() == Path(src).resolve():
        raise InvalidInputError(f"output {str(dst)!r} is the input; the input is never modified")
    check_output(dst, overwrite=overwrite)
    with open_raster(src) as ds:
        count, colorinterp = ds.count, list(ds.colorinterp)
    policy, dtype = _output_policy(src, opts)
    check_free_space(dst, grid, count + (1 if policy.kind == "mask" else 0), dtype, opts)
    fill = _fill_value(policy.kind, policy.nodata, dtype)
    mapping = _Mapping(grid, source_from_world, world_crs, opts.map_step_px)
    engine = _Engine(src, mapping, grid, opts, dtype, count, fill)
    windows = tile_windows(grid.width, grid.height, opts.tile_px)
    # bound GDAL's block cache (its default is 5% of RAM): tiles are written once, whole
    n_empty = write_tiled(engine, dst, grid, windows, count=count, dtype=dtype, policy=policy, tile=opts.tile_px,
                          compress=opts.compress, cog=opts.cog, threads=opts.n_threads, scheduler=sched,
                          overwrite=overwrite, progress=progress, name="warp",
                          cache_bytes=opts.block_cache_mb * 1024 * 1024, colorinterp=colorinterp)
    dt = time.perf_counter() - t0
    logger.info("warped %s -> %s: %d x %d, %d tiles (%d empty) in %.2f s", src, dst, grid.width, grid.height,
                len(windows), n_empty, dt)
    return WarpResult(Path(dst), grid, len(windows), n_empty, dt, policy.kind, policy.nodata)


def check_free_space(dst: str | Path, grid: Grid, bands: int, dtype: np.dtype, opts: WarpOptions) -> None:
    """Refuse an output that cannot fit on the destination's file system, before any work.

    The bound is the uncompressed size divided by :data:`ASSUMED_COMPRESSION` (a compressed output
    may turn out smaller; one that needs more than this fails when written, and is cleaned up). A
    COG is first written uncompressed beside the destination, so it needs its full size in addition.
    """
    raw = float(grid.width) * float(grid.height) * bands * np.dtype(dtype).itemsize
    compressed = raw if opts.compress.lower() == "none" else raw / ASSUMED_COMPRESSION
    need = compressed + (raw if opts.cog else 0.0)
    folder = Path(dst).parent if str(Path(dst).parent) else Path(".")
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if need > free:
        raise RasterIOError(
            f"not enough space left on device for {str(dst)!r}: the output grid of {grid.width} x {grid.height} px "
            f"x {bands} band(s) {np.dtype(dtype).name} is {raw / 1e6:,.1f} MB uncompressed and needs about "
            f"{need / 1e6:,.1f} MB{' (COG: uncompressed body + copy)' if opts.cog else ''}; "
            f"{free / 1e6:,.1f} MB are free in {str(folder)!r}")


def warp_array(image: ArrayLike, source_from_target: Callable[[NDArray], NDArray] | ArrayLike,
               out_shape: tuple[int, int], *, resampling: str = "bilinear", fill: float = 0
               ) -> NDArray:
    """Warp an in-memory image (small; for demos and tests) by an inverse pixel mapping.

    Parameters
    ----------
    image : (H, W) or (H, W, C)
    source_from_target : (3, 3) matrix or callable (N, 2) -> (N, 2)
        Target pixel -> source pixel.
    out_shape : (rows, cols)
        At most 32767 each.

    Returns
    -------
    (rows, cols[, C]) array of the image's dtype; ``fill`` outside the source.
    """

    a = np.asarray(image)
    if a.ndim not in (2, 3):
        raise InvalidInputError(f"`image` must be (H, W) or (H, W, C); got {a.shape}")
    h, w = int(out_shape[0]), int(out_shape[1])
    if not (0 < h <= _CV_LIMIT and 0 < w <= _CV_LIMIT) or max(a.shape[:2]) > _CV_LIMIT:
        raise InvalidInputError(f"warp_array handles images up to {_CV_LIMIT} px; use warp_raster")
    interp = _resampling_table()[resampling][0] if resampling in RESAMPLING_NAMES else None
    if interp is None:
        raise InvalidInputError(f"unknown resampling {resampling!r}")
    if callable(source_from_target) and not hasattr(source_from_target, "matrix"):
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        p = np.asarray(source_from_target(np.column_stack([gx.ravel(), gy.ravel()])))
        mx, my = p[:, 0].reshape(h, w).astype(np.float32), p[:, 1].reshape(h, w).astype(np.float32)
        return cv2.remap(_cv_dtype(a), mx, my, interp, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=fill).astype(a.dtype)
    M = np.asarray(getattr(source_from_target, "matrix", source_from_target), dtype=np.float64)
    if M.shape != (3, 3):
        raise InvalidInputError(f"matrix must be (3, 3); got {M.shape}")
    return cv2.warpPerspective(_cv_dtype(a), M, (w, h), flags=interp | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=fill).astype(a.dtype)
