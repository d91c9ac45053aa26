"""Mosaics of orthophotos: nearest-nadir seamlines, feathering across seams, one GeoTIFF/COG.

Every output pixel takes the orthophoto whose nadir point (the ``ORTHO_NADIR_X/Y``
tags written by :func:`rectify.raster.ortho.orthorectify`; the footprint centre for
other GeoTIFFs) is nearest, among those with valid data there: the seamlines
are the Voronoi edges of the nadir points, which keeps every pixel as close to
its image's nadir as possible (least relief displacement and building lean).
Across a seam the images are blended over ``feather_px`` output pixels:
``w_i = clip(1 - (d_i - d_min) / feather, 0, 1)`` with ``d_i`` the distance to
nadir i and ``d_min`` the smallest among valid images, normalised to sum 1.
True orthophotos (a visibility band) contribute only their visible pixels, so
ground hidden in one image is filled by the next.

Inputs must share the CRS and band count; the output grid is the union of
their bounds at the finest input resolution (or ``resolution``), aligned to
multiples of it. Inputs are read by windows (bilinear where grids differ),
tiles are processed by a thread pool and written atomically (the shared engine base and output
tail of :mod:`rectify.raster.engine`).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from affine import Affine
from numpy.typing import NDArray
from rasterio.windows import Window

from rectify.atomic import check_output
from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.crs import crs_to_string, same_crs, unit_label
from rectify.raster.distributed import Scheduler, resolve_scheduler
from rectify.raster.engine import TileEngine, tile_windows, worker_count, write_tiled
from rectify.raster.georef import Grid, crs_label, pixel_from_world_matrix
from rectify.raster.io import MaskPolicy, bound_gdal_cache, open_raster

__all__ = ["MAX_PIXELS", "MosaicOptions", "MosaicResult", "mosaic"]

#: the largest output grid :func:`mosaic` writes, pixels (that of ``rectify warp --max-pixels``)
MAX_PIXELS = 2e9

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MosaicOptions:
    """Options of :func:`mosaic`: feathering width (output pixels), tiles, threads, compression, COG, and the
    scheduler (``threads``, ``processes[:N]``, ``tcp://HOST:PORT``; None: ``$RECTIFY_SCHEDULER``, else threads)."""

    feather_px: float = 16.0
    tile_px: int = 512
    threads: int | None = None
    compress: str = "zstd"
    cog: bool = False
    scheduler: Scheduler | str | None = None

    def __post_init__(self) -> None:
        if self.scheduler is not None:
            resolve_scheduler(self.scheduler)  # a bad value fails here, before any work
        if not math.isfinite(self.feather_px) or self.feather_px < 0:
            raise InvalidInputError(f"feather_px must be >= 0; got {self.feather_px!r}")
        if self.tile_px < 16 or self.tile_px % 16:
            raise InvalidInputError(f"tile_px must be a multiple of 16; got {self.tile_px}")
        if self.threads is not None and self.threads < 1:
            raise InvalidInputError(f"threads must be >= 1; got {self.threads}")

    @property
    def n_threads(self) -> int:
        return worker_count(self.threads)


@dataclass(frozen=True)
class MosaicResult:
    path: Path
    grid: Grid
    inputs: tuple[str, ...]
    share: tuple[float, ...]  # fraction of the valid output pixels each input dominates
    seconds: float

    def summary_lines(self) -> list[str]:
        g = self.grid
        out = [f"wrote {self.path}: {g.width} x {g.height} px, {g.resolution[0]:.6g} {unit_label(g.crs)}/px, "
               f"CRS {crs_label(g.crs)}, "
               f"{len(self.inputs)} orthophotos, {self.seconds:.2f} s"]
        out += [f"  {Path(p).name}: {100 * s:.1f}% of the mosaic" for p, s in zip(self.inputs, self.share,
                                                                                  strict=True)]
        return out


def _gt(transform: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in tuple(transform)[:6])


@dataclass(frozen=True)
class _Input:
    path: str
    transform: object
    width: int
    height: int
    count: int  # image bands (without the visibility band)
    vis_band: int | None
    nodata: float | None
    nadir: tuple[float, float]


def _describe(path: str) -> tuple[_Input, str, str]:
    with open_raster(path) as ds:
        if ds.crs is None:
            raise CRSError(f"orthophoto {path!r} has no CRS")
        tags = ds.tags()
        vis = int(tags["ORTHO_VISIBILITY_BAND"]) if "ORTHO_VISIBILITY_BAND" in tags else None
        count = ds.count - (1 if vis is not None else 0)
        b = ds.bounds
        try:
            nadir = (float(tags["ORTHO_NADIR_X"]), float(tags["ORTHO_NADIR_Y"]))
            if not all(math.isfinite(v) for v in nadir):
                raise ValueError
        except (KeyError, ValueError):
            nadir = (0.5 * (b.left + b.right), 0.5 * (b.bottom + b.top))
        return (_Input(path, ds.transform, ds.width, ds.height, count, vis, ds.nodata, nadir),
                crs_to_string(ds.crs), ds.dtypes[0])


class _Datasets(list):
    """The open orthophotos of one thread (closed together)."""

    def close(self) -> None:
        for d in self:
            d.close()


class _Engine(TileEngine):
    def __init__(self, inputs: list[_Input], grid: Grid, dtype: np.dtype, nodata: float, feather: float):
        self.inputs, self.grid, self.dtype, self.nodata, self.feather = inputs, grid, dtype, nodata, feather
        self._init_readers()
        self.counts = np.zeros(len(inputs), np.int64)

    # ---------------------------------------------------------------- shipping to Dask workers
    def portable(self) -> _Engine:
        """A copy for Dask workers: orthophotos by absolute path, no open files, counts reset."""
        eng = copy.copy(self)
        eng.inputs = [dataclasses.replace(i, path=os.path.abspath(i.path)) for i in self.inputs]
        eng.counts = np.zeros(len(self.inputs), np.int64)
        return eng

    def stats(self) -> NDArray[np.int64]:
        """Output pixels each input dominated in the tiles this engine computed."""
        return self.counts.copy()

    def merge_stats(self, stats: NDArray[np.int64]) -> None:
        """Add another copy's :meth:`stats` (a Dask task's) to this engine's."""
        with self._lock:
            self.counts += np.asarray(stats, dtype=np.int64)

    def _ds(self, i: int):
        return self._thread_reader(lambda: _Datasets(rasterio.open(inp.path) for inp in self.inputs))[i]

    def _read(self, i: int, X: NDArray, Y: NDArray) -> tuple[NDArray, NDArray[np.bool_]] | None:
        """Input i resampled at world points (h, w): data (h, w, C) float64 and validity."""
        inp = self.inputs[i]
        M = pixel_from_world_matrix(inp.transform)
        px = M[0, 0] * X + M[0, 1] * Y + M[0, 2]
        py = M[1, 0] * X + M[1, 1] * Y + M[1, 2]
        # even window origins: np.rint rounds half-way positions to the even pixel of the window, the same pixel
        # whatever the tiling only when the origin is even
        c0 = max(int(math.floor(px.min())) - 1, 0) // 2 * 2
        r0 = max(int(math.floor(py.min())) - 1, 0) // 2 * 2
        c1 = min(int(math.ceil(px.max())) + 2, inp.width)
        r1 = min(int(math.ceil(py.max())) + 2, inp.height)
        if c1 <= c0 or r1 <= r0:
            return None
        ds = self._ds(i)
        win = Window(c0, r0, c1 - c0, r1 - r0)
        data = ds.read(list(range(1, inp.count + 1)), window=win).astype(np.float32)
        valid = ds.read_masks(1, window=win) > 0
        if inp.nodata is not None and isinstance(inp.nodata, float) and math.isnan(inp.nodata):
            valid &= ~np.isnan(data).all(axis=0)
        if inp.vis_band is not None:
            valid &= ds.read(inp.vis_band, window=win) == 2
        # window-relative positions from float32 raster positions (exact: a whole number subtracted), so that a
        # pixel's position, and OpenCV's 1/32 px rounding of it, does not depend on the tile's window
        mx = px.astype(np.float32) - np.float32(c0)
        my = py.astype(np.float32) - np.float32(r0)
        near_c, near_r = np.rint(mx).astype(int), np.rint(my).astype(int)
        inside = (near_c >= 0) & (near_r >= 0) & (near_c < c1 - c0) & (near_r < r1 - r0)
        v = np.zeros(X.shape, bool)
        v[inside] = valid[near_r[inside], near_c[inside]]
        img = np.moveaxis(data, 0, -1)
        img = np.where(valid[..., None], img, 0.0).astype(np.float32)
        # zero outside the raster as at invalid pixels, so that the division by the weights of the valid
        # neighbours below renormalises there too (a replicated edge divided by them came out up to 2x too large)
        out = np.stack([cv2.remap(np.ascontiguousarray(img[..., k]), mx, my, cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0) for k in range(inp.count)], axis=-1)
        # renormalise bilinear weights over valid neighbours
        wv = cv2.remap(valid.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.where(wv[..., None] > 1e-6, out / wv[..., None], 0.0)
        return out.astype(np.float64), v

    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, bool]:
        t = _gt(self.grid.transform)
        xs = t[2] + t[0] * (np.arange(c0, c0 + w) + 0.5)
        ys = t[5] + t[4] * (np.arange(r0, r0 + h) + 0.5)
        X, Y = np.meshgrid(xs, ys)
        count = self.inputs[0].count
        acc = np.zeros((h, w, count))
        reads = []
        for i, inp in enumerate(self.inputs):
            r = self._read(i, X, Y)
            if r is None or not r[1].any():
                continue
            d = np.hypot(X - inp.nadir[0], Y - inp.nadir[1])
            reads.append((i, r[0], r[1], d))
        out = np.full((h, w, count), self.nodata, dtype=self.dtype)
        if not reads:
            return out, True
        big = np.inf
        dmin = np.min([np.where(v, d, big) for _, _, v, d in reads], axis=0)
        wsum = np.zeros((h, w))
        best = np.full((h, w), -1)
        for i, img, v, d in reads:
            if self.feather > 0:
                wt = np.clip(1.0 - (d - dmin) / self.feather, 0.0, 1.0)
            else:
                wt = (d <= dmin).astype(np.float64)
            wt = np.where(v, wt, 0.0)
            acc += wt[..., None] * img
            wsum += wt
            best[v & (d <= dmin)] = i
        ok = wsum > 0
        res = np.zeros_like(acc)
        res[ok] = acc[ok] / wsum[ok, None]
        if self.dtype.kind in "ui":
            ii = np.iinfo(self.dtype)
            res = np.clip(np.rint(res), ii.min, ii.max)
            if self.nodata == 0:
                res = np.where(res == 0, 1, res)
        out[ok] = res[ok].astype(self.dtype)
        with self._lock:
            for i in range(len(self.inputs)):
                self.counts[i] += int((best == i).sum())
        return out, False


def mosaic(orthos: Sequence[str | Path], dst: str | Path, *, resolution: float | None = None,
           options: MosaicOptions | None = None, overwrite: bool = False,
           progress: Callable[[int, int], None] | None = None, max_pixels: float = MAX_PIXELS) -> MosaicResult:
    """Mosaic orthophotos into one GeoTIFF (COG with ``options.cog``).

    Raises
    ------
    InvalidInputError
        Fewer than one input, an input given twice, the output among the
        inputs, different band counts, existing output without ``overwrite``;
        an output grid of more than ``max_pixels`` (orthophotos far apart, a tiny ``resolution``),
        refused before any tile with its size and the share the inputs cover.
    CRSError
        Inputs in different CRSs (reproject them first) or without a CRS.
    """
    bound_gdal_cache()  # before any pixel IO
    opts = options or MosaicOptions()
    sched = resolve_scheduler(opts.scheduler)
    t0 = time.perf_counter()
    paths = [str(p) for p in orthos]
    if not paths:
        raise InvalidInputError("mosaic needs at least one orthophoto")
    res_paths = [Path(p).resolve() for p in paths]
    if len(set(res_paths)) != len(res_paths):
        raise InvalidInputError("an orthophoto is given twice")
    if Path(dst).resolve() in res_paths:
        raise InvalidInputError(f"output {str(dst)!r} is an input; inputs are never modified")
    check_output(dst, overwrite=overwrite)
    described = [_describe(p) for p in paths]
    inputs = [d[0] for d in described]
    crs, dtype_name = described[0][1], described[0][2]
    for inp, c, dt in described[1:]:
        if dt != dtype_name:
            raise InvalidInputError(f"orthophoto {inp.path!r} is {dt}, {inputs[0].path!r} {dtype_name}; mosaic "
                                    f"inputs must share one data type")
        if not same_crs(c, crs):
            raise CRSError(f"orthophoto {inp.path!r} is in {c}, not {crs}; mosaic inputs must share one CRS")
        if inp.count != inputs[0].count:
            raise InvalidInputError(f"orthophoto {inp.path!r} has {inp.count} bands, {inputs[0].path!r} "
                                    f"{inputs[0].count}")
    dtype = np.dtype(dtype_name)
    res = float(resolution) if resolution is not None else min(abs(_gt(i.transform)[0]) for i in inputs)
    if not math.isfinite(res) or res <= 0:
        raise InvalidInputError(f"resolution must be a positive number; got {resolution!r}")
    lefts: list[float] = []
    bottoms: list[float] = []
    rights: list[float] = []
    tops: list[float] = []
    for i in inputs:
        a, _b, c0, _d, e, f = _gt(i.transform)
        lefts.append(c0)
        rights.append(c0 + a * i.width)
        tops.append(f)
        bottoms.append(f + e * i.height)
    # a resolution so fine that the grid's size overflows a float: refused before any integer arithmetic
    cols, rows = (max(rights) - min(lefts)) / res, (max(tops) - min(bottoms)) / res
    if not all(math.isfinite(v) for v in (cols * rows, min(lefts) / res, max(rights) / res, min(bottoms) / res,
                                          max(tops) / res)):
        raise InvalidInputError(f"the mosaic's output grid at {res:.6g} {unit_label(crs)}/px would be {cols:.6g} x "
                                f"{rows:.6g} px, above the limit of {max_pixels:.3g} px; give a coarser --resolution "
                                f"(the finest orthophoto's is {min(abs(_gt(i.transform)[0]) for i in inputs):.6g})")
    eps = 1e-9
    x0 = math.floor(min(lefts) / res + eps) * res
    y0 = math.floor(min(bottoms) / res + eps) * res
    x1 = math.ceil(max(rights) / res - eps) * res
    y1 = math.ceil(max(tops) / res - eps) * res
    nx, ny = max(1, int(round((x1 - x0) / res))), max(1, int(round((y1 - y0) / res)))
    if float(nx) * float(ny) > max_pixels:
        covered = sum((r - left) * (t - b) for left, b, r, t in zip(lefts, bottoms, rights, tops, strict=True))
        cover = covered / ((x1 - x0) * (y1 - y0))
        fix = ("the orthophotos lie far apart: mosaic those that lie together, or give a coarser --resolution"
               if cover < 0.1 else "give a coarser --resolution")
        raise InvalidInputError(
            f"the mosaic's output grid would be {nx} x {ny} px ({float(nx) * float(ny):.3g} px at {res:.6g} "
            f"{unit_label(crs)}/px), above the limit of {max_pixels:.3g} px; the {len(paths)} orthophoto(s) cover at "
            f"most {100 * cover:.3g} % of it (x {x0:.10g} .. {x1:.10g}, y {y0:.10g} .. {y1:.10g}): {fix}")
    grid = Grid(nx, ny, Affine(res, 0.0, x0, 0.0, -res, y1), crs)
    nd0 = inputs[0].nodata
    nodata = float(nd0) if nd0 is not None else (float("nan") if dtype.kind == "f" else 0.0)
    engine = _Engine(inputs, grid, dtype, nodata, opts.feather_px * res)
    windows = tile_windows(grid.width, grid.height, opts.tile_px)
    write_tiled(engine, dst, grid, windows, count=inputs[0].count, dtype=dtype, policy=MaskPolicy("nodata", nodata),
                tile=opts.tile_px, compress=opts.compress, cog=opts.cog, threads=opts.n_threads, scheduler=sched,
                overwrite=overwrite, progress=progress, name="mosaic", cache_bytes=64 * 1024 * 1024)
    total = max(int(engine.counts.sum()), 1)
    share = tuple(float(c) / total for c in engine.counts)
    seconds = time.perf_counter() - t0
    logger.info("mosaic of %d orthophotos -> %s in %.2f s", len(paths), dst, seconds)
    return MosaicResult(Path(dst), grid, tuple(paths), share, seconds)
