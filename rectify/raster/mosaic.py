"""Mosaics of orthophotos: seamlines (nearest nadir, or the least-transformed image over a DSM), averaging,
radiometric balancing, feathering across seams, one GeoTIFF/COG and a provenance raster.

Seams (``MosaicOptions.seams``):

* ``nadir``: every output pixel takes the orthophoto whose nadir point (the ``ORTHO_NADIR_X/Y``
  tags written by :func:`rectify.raster.ortho.orthorectify`; the footprint centre for other GeoTIFFs) is
  nearest, among those with valid data there: the seamlines are the Voronoi edges of the nadir points.
* ``normal``: the least-transformed image per zone (seed 003, 4.2.1; :mod:`rectify.raster.seamlines`):
  the projection centres (``ORTHO_CENTER_X/Y/Z``) and a DSM give per zone of ``zone_px`` output pixels
  the angle of each image's ray to the vertical and to the surface normal; the zone takes the image with
  the smallest weighted sum among those valid (and visible) there, smoothed by a majority filter. The
  distance D_i of a pixel to image i's region is the bilinearly interpolated signed distance of the zones.

Across a seam the images are blended over ``feather_px`` output pixels:
``w_i = clip(1 - (D_i - D_min) / feather, 0, 1)`` with ``D_i`` the distance to nadir i (or to region i)
and ``D_min`` the smallest among valid images, normalised to sum 1. ``blend="average"`` averages every
valid image instead (seed 003, 4.2.1: "the final colours of the pixels may be the mean of the homologous
pixels of all overlapping orthophotos, defects excepted"), each weight ramping up from 0 at its footprint's
edge to 1 at ``feather_px`` inside. True orthophotos (a visibility band)
contribute only their visible pixels, so ground hidden in one image is filled by the next.
``balance`` corrects each image by a gain and offset per band estimated from the overlaps
(:mod:`rectify.raster.balance`) before blending.

Inputs must share the CRS and band count; the output grid is the union of their bounds at the finest
input resolution (or ``resolution``), aligned to multiples of it; an input of another resolution is
resampled bilinearly. Inputs are read by windows, tiles are processed by a thread pool and written
atomically (the shared engine base and output tail of :mod:`rectify.raster.engine`). The provenance
raster (``provenance=``) holds per pixel the 1-based number of the input with the largest weight there
(0: none), its tags ``MOSAIC_SOURCE_<k>`` the inputs' file names.
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
from rectify.raster.balance import Balance, estimate_balance
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
from rectify.raster.georef import Grid, crs_label, pixel_from_world_matrix
from rectify.raster.io import MaskPolicy, bound_gdal_cache, open_raster
from rectify.raster.seamlines import SeamPlan, mask_distance, plan_seams

__all__ = ["MAX_PIXELS", "SEAMS", "BLENDS", "BALANCES", "MosaicOptions", "MosaicResult", "mosaic"]

SEAMS = ("nadir", "normal")
BLENDS = ("seams", "average")
BALANCES = ("none", "mean", "reference")
#: most sample points of the zone lattice (seams and balancing)
MAX_SAMPLES = 4_000_000
#: most common samples kept for the balancing
MAX_BALANCE_SAMPLES = 200_000

#: the largest output grid :func:`mosaic` writes, pixels (that of ``rectify warp --max-pixels``)
MAX_PIXELS = 2e9

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MosaicOptions:
    """Options of :func:`mosaic`: feathering width (output pixels), tiles, threads, compression, COG, and the
    scheduler (``threads``, ``processes[:N]``, ``tcp://HOST:PORT``; None: ``$RECTIFY_SCHEDULER``, else threads).

    Seams and radiometry (module docstring): ``seams`` ``nadir`` or ``normal`` (None: ``normal`` when a
    ``dsm`` is given, else ``nadir``); ``dsm`` the surface (heights in the orthophotos' vertical datum) for
    the rays and normals; ``normal_weight`` w of the criterion (1 - w) nadir angle + w normal angle;
    ``zone_px`` the zone size (output pixels); ``smooth`` the smoothing of the choice (zones: the criterion's
    Gaussian sigma and the majority filter's radius; 0: none);
    ``blend`` ``seams`` or ``average``; ``balance`` ``none``, ``mean`` or ``reference`` (the first input kept).
    """

    feather_px: float = 16.0
    tile_px: int = 512
    threads: int | None = None
    compress: str = "zstd"
    cog: bool = False
    scheduler: Scheduler | str | None = None
    seams: str | None = None
    dsm: str | None = None
    normal_weight: float = 0.5
    zone_px: int = 8
    smooth: int = 2
    blend: str = "seams"
    balance: str = "none"
    quality: int = JPEG_QUALITY

    def __post_init__(self) -> None:
        if self.scheduler is not None:
            resolve_scheduler(self.scheduler)  # a bad value fails here, before any work
        if str(self.compress).lower() not in COMPRESSIONS:
            raise InvalidInputError(f"unknown compression {self.compress!r}; expected one of {', '.join(COMPRESSIONS)}")
        if self.seams is not None and self.seams not in SEAMS:
            raise InvalidInputError(f"seams must be one of {', '.join(SEAMS)}; got {self.seams!r}")
        if self.seam_mode == "normal" and self.dsm is None:
            raise InvalidInputError("seams 'normal' (the least-transformed image) needs a DSM: give --dsm FILE "
                                    "(or --seams nadir)")
        if self.blend not in BLENDS:
            raise InvalidInputError(f"blend must be one of {', '.join(BLENDS)}; got {self.blend!r}")
        if self.balance not in BALANCES:
            raise InvalidInputError(f"balance must be one of {', '.join(BALANCES)}; got {self.balance!r}")
        if not (math.isfinite(self.normal_weight) and 0.0 <= self.normal_weight <= 1.0):
            raise InvalidInputError(f"normal_weight must lie in 0..1; got {self.normal_weight!r}")
        if not 1 <= self.zone_px <= 4096:
            raise InvalidInputError(f"zone_px must lie in 1..4096; got {self.zone_px}")
        if not 0 <= self.smooth <= 64:
            raise InvalidInputError(f"smooth must lie in 0..64 zones; got {self.smooth}")
        if not math.isfinite(self.feather_px) or self.feather_px < 0:
            raise InvalidInputError(f"feather_px must be >= 0; got {self.feather_px!r}")
        if self.tile_px < 16 or self.tile_px % 16:
            raise InvalidInputError(f"tile_px must be a multiple of 16; got {self.tile_px}")
        if self.threads is not None and self.threads < 1:
            raise InvalidInputError(f"threads must be >= 1; got {self.threads}")

    @property
    def n_threads(self) -> int:
        return worker_count(self.threads)

    @property
    def seam_mode(self) -> str:
        """``nadir`` or ``normal`` (the default: ``normal`` with a DSM)."""
        return self.seams or ("normal" if self.dsm is not None else "nadir")


@dataclass(frozen=True)
class MosaicResult:
    path: Path
    grid: Grid
    inputs: tuple[str, ...]
    share: tuple[float, ...]  # fraction of the valid output pixels each input dominates
    seconds: float
    seams: str = "nadir"
    blend: str = "seams"
    plan: SeamPlan | None = None
    balance: Balance | None = None
    provenance: Path | None = None

    def summary_lines(self) -> list[str]:
        g = self.grid
        out = [f"wrote {self.path}: {g.width} x {g.height} px, {g.resolution[0]:.6g} {unit_label(g.crs)}/px, "
               f"CRS {crs_label(g.crs)}, "
               f"{len(self.inputs)} orthophotos, {self.seconds:.2f} s"]
        how = "average of all overlaps" if self.blend == "average" else (
            "seams of the least-transformed image (nadir and normal angles)" if self.seams == "normal"
            else "seams of the nearest nadir")
        out.append(f"  {how}" + (f": {self.plan.labels.shape[1]} x {self.plan.labels.shape[0]} zones of "
                                 f"{self.plan.zone} px, {self.plan.regions()} regions, seams "
                                 f"{self.plan.seam_edges() * self.plan.zone} px long, {self.plan.changed} zones "
                                 f"changed by smoothing" if self.plan is not None else ""))
        out += [f"  {Path(p).name}: {100 * s:.1f}% of the mosaic" for p, s in zip(self.inputs, self.share,
                                                                                  strict=True)]
        if self.balance is not None and self.balance.mode != "none":
            b = self.balance
            ref = f", {Path(self.inputs[b.reference]).name} kept" if b.reference is not None else ""
            out.append(f"  radiometric balance ({b.mode}{ref}): gain / offset per band")
            for p, gs, os_ in zip(self.inputs, b.gains, b.offsets, strict=True):
                out.append(f"    {Path(p).name}: " + ", ".join(f"{gv:.4f} / {ov:+.3f}" for gv, ov in zip(gs, os_,
                                                                                                      strict=True)))
            for ps in b.pairs:
                out.append(f"    overlap {Path(self.inputs[ps.i]).name} - {Path(self.inputs[ps.j]).name} "
                           f"({ps.samples} samples): RMS difference "
                           + ", ".join(f"{x0:.3f} -> {x1:.3f}" for x0, x1 in zip(ps.rms_before, ps.rms_after,
                                                                                  strict=True)))
        if self.provenance is not None:
            out.append(f"wrote {self.provenance} (provenance: 1-based input number per pixel, 0 none)")
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
    centre: tuple[float, float, float] | None = None  # projection centre (ORTHO_CENTER_X/Y/Z), CRS units, m


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
        centre: tuple[float, float, float] | None
        try:
            centre = (float(tags["ORTHO_CENTER_X"]), float(tags["ORTHO_CENTER_Y"]), float(tags["ORTHO_CENTER_Z"]))
            if not all(math.isfinite(v) for v in centre):
                raise ValueError
        except (KeyError, ValueError):
            centre = None
        return (_Input(path, ds.transform, ds.width, ds.height, count, vis, ds.nodata, nadir, centre),
                crs_to_string(ds.crs), ds.dtypes[0])


class _Datasets(list):
    """The open orthophotos of one thread (closed together)."""

    def close(self) -> None:
        for d in self:
            d.close()


class _Engine(TileEngine):
    """The mosaic's tiles; ``sources=True``: the provenance raster instead (input numbers, no pixel values)."""

    def __init__(self, inputs: list[_Input], grid: Grid, dtype: np.dtype, nodata: float, feather: float, *,
                 plan: SeamPlan | None = None, blend: str = "seams", balance: Balance | None = None,
                 sources: bool = False, edges: NDArray[np.float32] | None = None, zone: int = 8):
        self.inputs, self.grid, self.dtype, self.nodata, self.feather = inputs, grid, dtype, nodata, feather
        self.plan, self.blend, self.balance, self.sources = plan, blend, balance, sources
        self.edges, self.zone = edges, zone  # average blend: signed distances (zones) to each footprint's edge
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

    def _read(self, i: int, X: NDArray, Y: NDArray, data_too: bool = True
              ) -> tuple[NDArray | None, NDArray[np.bool_]] | None:
        """Input i resampled at world points (h, w): data (h, w, C) float64 (None without ``data_too``) and
        validity (nearest pixel valid, and visible in a true orthophoto)."""
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
        valid = ds.read_masks(1, window=win) > 0
        data = None
        if data_too or (inp.nodata is not None and isinstance(inp.nodata, float) and math.isnan(inp.nodata)):
            data = ds.read(list(range(1, inp.count + 1)), window=win).astype(np.float32)
        if data is not None and inp.nodata is not None and isinstance(inp.nodata, float) and math.isnan(inp.nodata):
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
        if not data_too or data is None:
            return None, v
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

    def _distance(self, i: int, X: NDArray, Y: NDArray, c0: int, r0: int) -> NDArray[np.float64]:
        """D_i (h, w), world units: the distance to nadir i, or (zone seams) minus the interpolated signed
        distance to image i's region."""
        plan = self.plan
        if plan is None:
            inp = self.inputs[i]
            return np.hypot(X - inp.nadir[0], Y - inp.nadir[1])
        return -self._zone_interp(plan.sdist[i], plan.zone, c0, r0, X.shape)

    def _zone_interp(self, a: NDArray[np.float32], z: int, c0: int, r0: int, shape: tuple[int, ...]
                     ) -> NDArray[np.float64]:
        """A zone grid's values (zones) interpolated bilinearly at the output pixels of a window, world units."""
        h, w = shape
        # zone (r, c) is centred on output pixel c * z + (z - 1) / 2; float32 maps from absolute pixel numbers
        mx = ((np.arange(c0, c0 + w, dtype=np.float64) - 0.5 * (z - 1)) / z).astype(np.float32)
        my = ((np.arange(r0, r0 + h, dtype=np.float64) - 0.5 * (z - 1)) / z).astype(np.float32)
        MX, MY = np.meshgrid(mx, my)
        sd = cv2.remap(a, MX, MY, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return sd.astype(np.float64) * z * abs(_gt(self.grid.transform)[0])

    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, bool]:
        t = _gt(self.grid.transform)
        xs = t[2] + t[0] * (np.arange(c0, c0 + w) + 0.5)
        ys = t[5] + t[4] * (np.arange(r0, r0 + h) + 0.5)
        X, Y = np.meshgrid(xs, ys)
        count = self.inputs[0].count
        reads = []
        for i in range(len(self.inputs)):
            r = self._read(i, X, Y, data_too=not self.sources)
            if r is None or not r[1].any():
                continue
            img = r[0]
            if img is not None and self.balance is not None and self.balance.mode != "none":
                img = self.balance.apply(i, img)
            reads.append((i, img, r[1], self._distance(i, X, Y, c0, r0)))
        if self.sources:
            out = np.zeros((h, w, 1), dtype=self.dtype)
        else:
            out = np.full((h, w, count), self.nodata, dtype=self.dtype)
        if not reads:
            return out, True
        big = np.inf
        dmin = np.min([np.where(v, d, big) for _, _, v, d in reads], axis=0)
        acc = np.zeros((h, w, count))
        wsum = np.zeros((h, w))
        best = np.full((h, w), -1)
        for i, img, v, d in reads:
            if self.blend == "average" and self.edges is not None and self.feather > 0:
                # ramps from 0 at the footprint's edge to 1 a feather inside; never 0, so a pixel only this input
                # fills keeps it
                inner = self._zone_interp(self.edges[i], self.zone, c0, r0, (h, w))
                wt = np.clip(inner / self.feather, 1e-3, 1.0)
            elif self.blend == "average":
                wt = np.ones((h, w))
            elif self.feather > 0:
                wt = np.clip(1.0 - (d - dmin) / self.feather, 0.0, 1.0)
            else:
                wt = (d <= dmin).astype(np.float64)
            wt = np.where(v, wt, 0.0)
            if img is not None:
                acc += wt[..., None] * img
            wsum += wt
            top = v & (d <= dmin)  # the input with the largest weight (ties: the first)
            best[top & (best < 0)] = i
        ok = wsum > 0
        if self.sources:
            out[..., 0] = np.where(ok, best + 1, 0).astype(self.dtype)
            return out, False
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


@dataclass(frozen=True, eq=False)
class _Samples:
    """The zone lattice: zone centres X, Y (rows, cols) world; each input's valid share per zone (n, rows, cols);
    values (n, m, C) and validity (n, m) at the lattice points valid in two inputs or more (for the balance)."""

    X: NDArray[np.float64]
    Y: NDArray[np.float64]
    share: NDArray[np.float64]
    values: NDArray[np.float64]
    valid: NDArray[np.bool_]


def _sample_zones(engine: _Engine, zone: int, with_values: bool) -> _Samples:
    """Sample every input on k x k points per zone (k <= 4, fewer when the lattice would pass MAX_SAMPLES)."""
    g = engine.grid
    t = _gt(g.transform)
    ncx, ncy = -(-g.width // zone), -(-g.height // zone)
    k = int(max(1, min(4, zone, math.floor(math.sqrt(MAX_SAMPLES / (ncx * ncy))))))
    step = zone / k
    n, nb = len(engine.inputs), engine.inputs[0].count
    share = np.zeros((n, ncy, ncx))
    vals: list[NDArray[np.float64]] = []
    vals_ok: list[NDArray[np.bool_]] = []
    blk = 64  # zones per block side
    for zr in range(0, ncy, blk):
        for zc in range(0, ncx, blk):
            nzr, nzc = min(blk, ncy - zr), min(blk, ncx - zc)
            cols = np.minimum(zc * zone + (np.arange(nzc * k) + 0.5) * step - 0.5, g.width - 1.0)
            rows = np.minimum(zr * zone + (np.arange(nzr * k) + 0.5) * step - 0.5, g.height - 1.0)
            X, Y = np.meshgrid(t[2] + t[0] * (cols + 0.5), t[5] + t[4] * (rows + 0.5))
            data = np.zeros((n,) + X.shape + (nb,))
            ok = np.zeros((n,) + X.shape, bool)
            for i in range(n):
                r = engine._read(i, X, Y, data_too=with_values)
                if r is None:
                    continue
                ok[i] = r[1]
                if r[0] is not None:
                    data[i] = r[0]
                share[i, zr:zr + nzr, zc:zc + nzc] = r[1].reshape(nzr, k, nzc, k).mean(axis=(1, 3))
            if with_values:
                two = ok.sum(axis=0) >= 2
                vals.append(data[:, two])
                vals_ok.append(ok[:, two])
    zx = t[2] + t[0] * (np.arange(ncx) + 0.5) * zone  # zone centres: output pixel c * zone + (zone - 1) / 2
    zy = t[5] + t[4] * (np.arange(ncy) + 0.5) * zone
    X, Y = np.meshgrid(zx, zy)
    values = np.concatenate(vals, axis=1) if vals else np.zeros((n, 0, nb))
    valid = np.concatenate(vals_ok, axis=1) if vals_ok else np.zeros((n, 0), bool)
    if values.shape[1] > MAX_BALANCE_SAMPLES:  # an even thinning, the same on every run
        keep = np.linspace(0, values.shape[1] - 1, MAX_BALANCE_SAMPLES).astype(np.intp)
        values, valid = values[:, keep], valid[:, keep]
    return _Samples(X, Y, share, values, valid)


def _plan(inputs: list[_Input], grid: Grid, samples: _Samples, opts: MosaicOptions) -> SeamPlan:
    """The least-transformed seams over ``opts.dsm``."""
    missing = [i.path for i in inputs if i.centre is None]
    if missing:
        raise InvalidInputError(f"orthophoto {missing[0]!r} has no projection centre (tags ORTHO_CENTER_X/Y/Z, "
                                f"written by `rectify ortho` for frame cameras); seams 'normal' need one per "
                                f"input: orthorectify it again, or use --seams nadir")
    dsm = Dem.from_path(str(opts.dsm), convert_declared=False)
    xy = np.column_stack([samples.X.ravel(), samples.Y.ravel()])
    Z = dsm.sample(xy, str(grid.crs)).reshape(samples.X.shape)
    if not np.isfinite(Z).any():
        raise InvalidInputError(f"DSM {str(opts.dsm)!r} has no height under the mosaic (x {samples.X.min():.10g} .. "
                                f"{samples.X.max():.10g}, y {samples.Y.min():.10g} .. {samples.Y.max():.10g})")
    centres = np.array([i.centre for i in inputs], dtype=np.float64)
    return plan_seams(centres, samples.X, samples.Y, Z, samples.share, zone=opts.zone_px,
                      spacing=opts.zone_px * abs(_gt(grid.transform)[0]), weight=opts.normal_weight,
                      radius=opts.smooth)


def mosaic(orthos: Sequence[str | Path], dst: str | Path, *, resolution: float | None = None,
           options: MosaicOptions | None = None, overwrite: bool = False,
           progress: Callable[[int, int], None] | None = None, max_pixels: float = MAX_PIXELS,
           provenance: str | Path | None = None) -> MosaicResult:
    """Mosaic orthophotos into one GeoTIFF (COG with ``options.cog``); with ``provenance`` also the provenance
    raster there (uint8, uint16 beyond 254 inputs: the 1-based input number per pixel, 0 none).

    Raises
    ------
    InvalidInputError
        Fewer than one input, an input given twice, the output among the
        inputs, different band counts, existing output without ``overwrite``;
        an output grid of more than ``max_pixels`` (orthophotos far apart, a tiny ``resolution``),
        refused before any tile with its size and the share the inputs cover.
        Seams ``normal`` with an input that has no projection centre, or a DSM with no height under the
        mosaic; ``balance`` with an input overlapping no other.
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
    if provenance is not None:
        if Path(provenance).resolve() in res_paths + [Path(dst).resolve()]:
            raise InvalidInputError(f"provenance output {str(provenance)!r} is an input or the mosaic")
        check_output(provenance, overwrite=overwrite)
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
    check_output_format(opts.compress, dtype, inputs[0].count, opts.quality)  # before any work
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
    seams = opts.seam_mode
    plan: SeamPlan | None = None
    balance: Balance | None = None
    feather_average = opts.blend == "average" and opts.feather_px > 0 and len(inputs) > 1
    edges = None
    if seams == "normal" or opts.balance != "none" or feather_average:
        probe = _Engine(inputs, grid, dtype, nodata, 0.0)
        try:
            samples = _sample_zones(probe, opts.zone_px, with_values=opts.balance != "none")
        finally:
            probe.close()
        if seams == "normal":
            plan = _plan(inputs, grid, samples, opts)
        if feather_average:
            edges = np.stack([mask_distance(s >= 0.5) for s in samples.share])
        if opts.balance != "none":
            balance = estimate_balance(samples.values, samples.valid, mode=opts.balance, reference=0,
                                       names=[Path(p).name for p in paths])
    engine = _Engine(inputs, grid, dtype, nodata, opts.feather_px * res, plan=plan, blend=opts.blend,
                     balance=balance, edges=edges, zone=opts.zone_px)
    windows = tile_windows(grid.width, grid.height, opts.tile_px)
    tags = {"MOSAIC_SEAMS": seams, "MOSAIC_BLEND": opts.blend, "MOSAIC_BALANCE": opts.balance}
    write_tiled(engine, dst, grid, windows, count=inputs[0].count, dtype=dtype, policy=MaskPolicy("nodata", nodata),
                tile=opts.tile_px, compress=opts.compress, cog=opts.cog, threads=opts.n_threads, scheduler=sched,
                overwrite=overwrite, progress=progress, name="mosaic", cache_bytes=64 * 1024 * 1024, tags=tags,
                quality=opts.quality)
    if provenance is not None:
        try:
            src_dtype = np.dtype(np.uint8 if len(inputs) < 255 else np.uint16)
            src_engine = _Engine(inputs, grid, src_dtype, 0.0, opts.feather_px * res, plan=plan, blend=opts.blend,
                                 sources=True)
            src_tags = {f"MOSAIC_SOURCE_{k + 1}": Path(p).name for k, p in enumerate(paths)}
            write_tiled(src_engine, provenance, grid, windows, count=1, dtype=src_dtype,
                        policy=MaskPolicy("nodata", 0.0), tile=opts.tile_px, compress="deflate", cog=opts.cog,
                        threads=opts.n_threads, scheduler=sched, overwrite=overwrite, progress=None,
                        name="mosaic-sources", cache_bytes=16 * 1024 * 1024, cog_resampling="nearest",
                        tags=src_tags, band_descriptions={1: "source: 1-based input number, 0 none"})
        except BaseException:
            Path(dst).unlink(missing_ok=True)  # nothing half-made is left
            raise
    total = max(int(engine.counts.sum()), 1)
    share = tuple(float(c) / total for c in engine.counts)
    seconds = time.perf_counter() - t0
    logger.info("mosaic of %d orthophotos -> %s in %.2f s", len(paths), dst, seconds)
    return MosaicResult(Path(dst), grid, tuple(paths), share, seconds, seams, opts.blend, plan, balance,
                        Path(provenance) if provenance is not None else None)
