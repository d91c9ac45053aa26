"""Raster IO: the only module that opens rasters and swaps axes.

Arrays handed to the rest of the project are ``(H, W, C)`` (rows, columns,
bands), never rasterio's ``(bands, rows, cols)``. Large rasters are read by
windows; nothing here assumes an image fits in memory. Validity is a bool
mask ``(H, W)``: True where every band holds data (nodata, per-dataset masks
and alpha are respected through rasterio's dataset mask).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
import rasterio.shutil
import rasterio.warp
from affine import Affine
from numpy.typing import NDArray
from rasterio._err import CPLE_BaseError
from rasterio.enums import ColorInterp, MaskFlags, Resampling
from rasterio.errors import RasterioError
from rasterio.windows import Window

from rectify.atomic import atomic_output, write_failure_reason
from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.raster.tiffblocks import TileAppender, TileEncoder, tile_index

__all__ = ["RasterInfo", "open_raster", "raster_info", "read_window", "read_overview", "iter_windows",
           "to_uint8"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RasterInfo:
    """What a raster is, without its pixels.

    Attributes
    ----------
    path : str
    width, height, count : int
        Columns, rows, bands.
    dtype : str
        Data type of the first band (numpy name).
    nodata : float or None
    crs : str or None
        ``"EPSG:nnnn"`` when it has a code, WKT otherwise, None if absent.
    transform : affine.Affine
        rasterio's geotransform (pixel *corner* convention; convert only in
        :mod:`rectify.raster.georef`).
    block_shape : (int, int)
        (rows, cols) of the first band's internal blocks.
    """

    path: str
    width: int
    height: int
    count: int
    dtype: str
    nodata: float | None
    crs: str | None
    transform: Affine
    block_shape: tuple[int, int]

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.height, self.width, self.count)


def _open(path: str | Path):
    """rasterio dataset opened for reading; missing or unreadable files raise RasterIOError."""

    p = str(path)
    if not Path(p).exists():
        raise RasterIOError(f"raster not found: {p!r}")
    try:
        return rasterio.open(p)
    except RasterioError as err:
        raise RasterIOError(f"cannot read raster {p!r}: {err}") from err


@contextlib.contextmanager
def open_raster(path: str | Path) -> Iterator[rasterio.io.DatasetReader]:
    """Open a raster for reading; rasterio errors become :class:`RasterIOError`."""
    ds = _open(path)
    try:
        yield ds
    finally:
        ds.close()


def _crs_string(crs) -> str | None:
    if crs is None:
        return None
    return _crs_string_of_wkt(crs.to_wkt())


@functools.lru_cache(maxsize=128)
def _crs_string_of_wkt(wkt: str) -> str:
    """EPSG code or WKT of a rasterio CRS given as WKT (the EPSG lookup searches PROJ's database: once per CRS)."""
    crs = rasterio.crs.CRS.from_wkt(wkt)
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_wkt()


def raster_info(path: str | Path) -> RasterInfo:
    """Describe a raster (size, bands, dtype, nodata, CRS, geotransform, blocks)."""
    with open_raster(path) as ds:
        return RasterInfo(str(path), ds.width, ds.height, ds.count, ds.dtypes[0], ds.nodata,
                          _crs_string(ds.crs), ds.transform, tuple(ds.block_shapes[0]))


def _check_bands(bands, count: int, path) -> list[int]:
    if bands is None:
        return list(range(1, count + 1))
    b = [int(x) for x in bands]
    bad = [x for x in b if x < 1 or x > count]
    if bad:
        raise InvalidInputError(f"band(s) {bad} out of range 1..{count} in {str(path)!r}")
    return b


def read_window(path: str | Path, col_off: int, row_off: int, width: int, height: int, *,
                bands: list[int] | None = None, out_shape: tuple[int, int] | None = None,
                ) -> tuple[NDArray, NDArray[np.bool_]]:
    """Read a window of a raster.

    Parameters
    ----------
    path : path of any raster rasterio reads
    col_off, row_off, width, height : int
        The window in pixels; parts outside the raster read as invalid.
    bands : list of int, optional
        1-based band indices (default all).
    out_shape : (rows, cols), optional
        Decimated read (GDAL picks overviews when present; nearest resampling).

    Returns
    -------
    data : (h, w, C) array of the raster's dtype
    valid : (h, w) bool
        True where the dataset mask says the pixel holds data.
    """

    if width <= 0 or height <= 0:
        raise InvalidInputError(f"window size must be positive; got {width} x {height}")
    with open_raster(path) as ds:
        b = _check_bands(bands, ds.count, path)
        win = Window(col_off, row_off, width, height)
        kw = {}
        if out_shape is not None:
            kw["out_shape"] = (len(b), int(out_shape[0]), int(out_shape[1]))
        try:
            data = ds.read(b, window=win, boundless=True, fill_value=ds.nodata or 0, **kw)
            mkw = {"out_shape": (int(out_shape[0]), int(out_shape[1]))} if out_shape is not None else {}
            mask = ds.dataset_mask(window=win, boundless=True, **mkw) if _inside(ds, win) else \
                _boundless_mask(ds, win, out_shape)
        except RasterioError as err:
            raise RasterIOError(f"cannot read window {win} of {str(path)!r}: {err}") from err
    return np.moveaxis(data, 0, -1), mask.astype(bool)


def _inside(ds, win) -> bool:
    return win.col_off >= 0 and win.row_off >= 0 and win.col_off + win.width <= ds.width and \
        win.row_off + win.height <= ds.height


def _boundless_mask(ds, win, out_shape) -> NDArray[np.bool_]:
    """Dataset mask for a window reaching outside the raster (outside = invalid)."""

    h, w = int(win.height), int(win.width)
    full = np.zeros((h, w), dtype=bool)
    c0, r0 = max(int(win.col_off), 0), max(int(win.row_off), 0)
    c1, r1 = min(int(win.col_off + win.width), ds.width), min(int(win.row_off + win.height), ds.height)
    if c1 > c0 and r1 > r0:
        inner = ds.dataset_mask(window=Window(c0, r0, c1 - c0, r1 - r0))
        full[r0 - int(win.row_off):r1 - int(win.row_off), c0 - int(win.col_off):c1 - int(win.col_off)] = inner > 0
    if out_shape is not None:
        ri = (np.arange(out_shape[0]) * h / out_shape[0]).astype(int)
        ci = (np.arange(out_shape[1]) * w / out_shape[1]).astype(int)
        full = full[np.ix_(ri, ci)]
    return full


def read_overview(path: str | Path, max_size: int, *, bands: list[int] | None = None
                  ) -> tuple[NDArray, NDArray[np.bool_], float]:
    """Read the whole raster decimated so its longer side is at most ``max_size``.

    Returns
    -------
    data : (h, w, C) array
    valid : (h, w) bool
    scale : float
        Full-resolution pixels per overview pixel (>= 1). A full-resolution
        pixel centre x maps to overview (x + 0.5) / scale - 0.5.
    """
    if max_size < 16:
        raise InvalidInputError(f"max_size must be >= 16; got {max_size}")
    info = raster_info(path)
    scale = max(1.0, max(info.width, info.height) / max_size)
    h = max(1, int(round(info.height / scale)))
    w = max(1, int(round(info.width / scale)))
    data, valid = read_window(path, 0, 0, info.width, info.height, bands=bands,
                              out_shape=None if scale == 1.0 else (h, w))
    # exact scale per axis may differ slightly from the rounded size; report the mean
    scale = 0.5 * (info.width / data.shape[1] + info.height / data.shape[0])
    return data, valid, scale


def iter_windows(width: int, height: int, tile: int, overlap: int = 0
                 ) -> Iterator[tuple[int, int, int, int]]:
    """Tile a ``width`` x ``height`` raster into windows (col_off, row_off, w, h).

    Tiles are ``tile`` pixels plus ``overlap`` on each side (clipped to the
    raster); their cores cover the raster exactly once.
    """
    if tile <= 0 or overlap < 0:
        raise InvalidInputError(f"tile must be > 0 and overlap >= 0; got {tile}, {overlap}")
    for r in range(0, height, tile):
        for c in range(0, width, tile):
            c0, r0 = max(c - overlap, 0), max(r - overlap, 0)
            c1, r1 = min(c + tile + overlap, width), min(r + tile + overlap, height)
            yield c0, r0, c1 - c0, r1 - r0


def to_uint8(data: NDArray, valid: NDArray[np.bool_] | None = None, *,
             percentiles: tuple[float, float] = (2.0, 98.0),
             limits: tuple[float, float] | None = None) -> NDArray[np.uint8]:
    """Grey uint8 image for feature detection only (never for output pixels).

    Multi-band input is averaged; values are stretched linearly between the
    given ``percentiles`` of valid pixels (or fixed ``limits``, so tiles of one
    image share a stretch); invalid pixels become 0.

    Parameters
    ----------
    data : (H, W) or (H, W, C) array, any dtype
    valid : (H, W) bool, optional
    """
    a = np.asarray(data)
    if a.ndim == 2 and a.dtype in (np.uint8, np.uint16):
        return _to_uint8_lut(a, valid, percentiles, limits)
    if a.ndim == 3:
        a = a.astype(np.float32).mean(axis=2)
    else:
        a = a.astype(np.float32)
    if a.ndim != 2:
        raise InvalidInputError(f"image must be (H, W) or (H, W, C); got shape {np.shape(data)}")
    ok = np.isfinite(a) if valid is None else (valid & np.isfinite(a))
    if limits is None:
        if not ok.any():
            return np.zeros(a.shape, dtype=np.uint8)
        sample = a[ok]
        if sample.size > 1_000_000:
            sample = sample[:: math.ceil(sample.size / 1_000_000)]
        lo, hi = np.percentile(sample, percentiles)
    else:
        lo, hi = limits
    if not hi > lo:
        hi = lo + 1.0
    out = np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255)
    out[~ok] = 0
    return out.astype(np.uint8)


#: most pixels sampled for the stretch percentiles of :func:`to_uint8`
STRETCH_SAMPLE = 1_000_000


def _to_uint8_lut(a: NDArray, valid: NDArray[np.bool_] | None, percentiles: tuple[float, float],
                  limits: tuple[float, float] | None) -> NDArray[np.uint8]:
    """:func:`to_uint8` of one uint8/uint16 band: percentiles from a histogram, the stretch as a look-up table
    (the same values, about 10x faster than the float path)."""
    lo: float
    hi: float      # np.float64 (a float) from the percentiles, as np.percentile gives
    if limits is None:
        sample = a.ravel() if valid is None else a[valid]
        if sample.size == 0:
            return np.zeros(a.shape, dtype=np.uint8)
        if sample.size > STRETCH_SAMPLE:
            sample = sample[:: math.ceil(sample.size / STRETCH_SAMPLE)]
        lo, hi = _histogram_percentiles(sample, percentiles)
    else:
        lo, hi = limits
    if not hi > lo:
        hi = lo + 1.0
    levels = np.arange(256 if a.dtype == np.uint8 else 65536, dtype=np.float32)
    lut = np.clip((levels - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    out = lut[a]
    if valid is not None:
        out[~valid] = 0
    return out


def _histogram_percentiles(sample: NDArray, q: tuple[float, float]) -> tuple[np.float64, np.float64]:
    """``np.percentile(sample, q)`` of non-negative integers from their histogram: numpy's linear method
    step by step (virtual index (n - 1) q, and its two-sided interpolation), so the values agree."""
    cum = np.cumsum(np.bincount(sample))
    n = int(cum[-1])
    out = []
    for p in q:
        f = float(p) / 100.0
        pos = (n - 1) * f
        i0 = min(max(math.floor(pos), 0), n - 1)
        i1 = min(i0 + 1, n - 1)
        t = pos - math.floor(pos)
        a = float(np.searchsorted(cum, i0, side="right"))
        b = float(np.searchsorted(cum, i1, side="right"))
        out.append(np.float64(b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t))
    return out[0], out[1]    # numpy scalars, as np.percentile gives: the stretch then computes in float64


# =============================================================================
# Writing, fast windowed reading for the warper, COG layout checks
# (appended by the warp engine, issue 4)
# =============================================================================

@dataclass(frozen=True)
class MaskPolicy:
    """How validity is stored in a raster.

    Attributes
    ----------
    kind : str
        ``"nodata"`` (a nodata value), ``"mask"`` (a per-dataset internal
        mask), ``"alpha"`` (an alpha band; invalid pixels get alpha 0) or
        ``"none"`` (every pixel valid).
    nodata : float or None
        The nodata value when ``kind == "nodata"``.
    alpha_band : int or None
        0-based index of the alpha band when ``kind == "alpha"``.
    """

    kind: str
    nodata: float | None = None
    alpha_band: int | None = None


def mask_policy(path: str | Path) -> MaskPolicy:
    """How a raster on disk stores validity (nodata, internal mask, alpha or none)."""

    with open_raster(path) as ds:
        return _mask_policy_of(ds)


def _mask_policy_of(ds) -> MaskPolicy:
    """:func:`mask_policy` of an open dataset."""
    flags = ds.mask_flag_enums
    if ds.nodata is not None:
        return MaskPolicy("nodata", float(ds.nodata))
    if any(MaskFlags.alpha in f for f in flags):
        ci = list(ds.colorinterp)
        idx = ci.index(ColorInterp.alpha) if ColorInterp.alpha in ci else ds.count - 1
        return MaskPolicy("alpha", None, idx)
    if any(MaskFlags.per_dataset in f for f in flags):
        return MaskPolicy("mask")
    return MaskPolicy("none")


class WindowReader:
    """Keep one dataset open and read windows inside it, as ``(h, w, C)``.

    Not thread-safe: give each thread its own reader. Windows must lie inside
    the raster (the warper clips them); use :func:`read_window` for boundless
    reads.

    Parameters
    ----------
    path : path of any raster rasterio reads
    """

    def __init__(self, path: str | Path):
        self.path = str(path)
        self._ds = _open(self.path)
        self.policy = _mask_policy_of(self._ds)  # (the open dataset's: no second open)
        self.width, self.height, self.count = self._ds.width, self._ds.height, self._ds.count
        self.dtype = np.dtype(self._ds.dtypes[0])

    def close(self) -> None:
        self._ds.close()

    def __enter__(self) -> WindowReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def read(self, col_off: int, row_off: int, width: int, height: int
             ) -> tuple[NDArray, NDArray[np.bool_] | None]:
        """Read a window inside the raster.

        Returns
        -------
        data : (h, w, C) array of the raster's dtype (C-contiguous, pixel-interleaved)
        valid : (h, w) bool, or None when every pixel of the window is valid.
            Nodata: a pixel is invalid when all its bands equal nodata (as
            rasterio's dataset mask); NaN counts as nodata for float rasters.
        """

        if col_off < 0 or row_off < 0 or width <= 0 or height <= 0 or col_off + width > self.width \
                or row_off + height > self.height:
            raise InvalidInputError(f"window ({col_off}, {row_off}, {width}, {height}) is not inside the "
                                    f"{self.width} x {self.height} raster {self.path!r}")
        win = Window(col_off, row_off, width, height)
        try:
            # GDAL writes the pixel-interleaved (h, w, C) layout itself through a band-first view (3-4x
            # faster than reading (C, h, w) and transposing)
            data = np.empty((height, width, self.count), dtype=self.dtype)
            self._ds.read(window=win, out=data.transpose(2, 0, 1))
            pol = self.policy
            valid = None
            if pol.kind == "nodata":
                nd = pol.nodata
                if isinstance(nd, float) and math.isnan(nd):
                    bad = _all_bands(data, np.isnan)
                else:
                    v = np.asarray(nd).astype(data.dtype)
                    bad = _all_bands(data, lambda b: b == v)
                    if data.dtype.kind == "f":
                        bad |= _all_bands(data, np.isnan)
                valid = None if not bad.any() else ~bad
            elif pol.kind in ("mask", "alpha"):
                m = self._ds.dataset_mask(window=win) > 0
                valid = None if m.all() else m
        except RasterioError as err:
            raise RasterIOError(f"cannot read window {win} of {self.path!r}: {err}") from err
        return data, valid


def _all_bands(data: NDArray, test: Callable[[NDArray], NDArray[np.bool_]]) -> NDArray[np.bool_]:
    """(h, w) True where ``test`` holds in every band of ``data`` (h, w, C), band by band (numpy's
    reduction over a short last axis is ten times slower)."""
    out = np.array(test(data[..., 0]), dtype=bool)
    for k in range(1, data.shape[2]):
        out &= test(data[..., k])
    return out


def _gtiff_profile(width: int, height: int, count: int, dtype: str, transform, crs: str | None,
                   nodata: float | None, *, tile: int, compress: str, threads: int,
                   bigtiff: str = "IF_SAFER") -> dict:
    prof = {"driver": "GTiff", "width": int(width), "height": int(height), "count": int(count),
            "dtype": dtype, "transform": transform, "crs": crs, "nodata": nodata,
            "tiled": True, "blockxsize": int(tile), "blockysize": int(tile),
            "compress": compress, "interleave": "pixel", "BIGTIFF": bigtiff,
            "NUM_THREADS": str(max(1, int(threads)))}
    if compress.lower() in ("deflate", "lzw", "zstd") and np.dtype(dtype).kind in "ui":
        prof["predictor"] = 2
    if compress.lower() == "zstd":
        prof["ZSTD_LEVEL"] = "1"
    return prof


class TiledWriter:
    """A tiled, compressed GeoTIFF opened for writing, fed tile by tile.

    Parameters
    ----------
    path : path
        The file to create (the caller handles atomic renaming).
    width, height, count : int
    dtype : str
    transform : affine.Affine
        rasterio geotransform.
    crs : str or None
    policy : MaskPolicy
        How invalid pixels are stored (nodata value, internal mask, alpha band).
    tile : int
        Internal block size (multiple of 16).
    compress : str
        GDAL compression (``deflate``, ``lzw``, ``zstd``, ``none``).
    threads : int
        Compression threads.
    colorinterp : sequence, optional
        Band colour interpretation to record.
    descriptions : sequence of str, optional
        One description per band (GDAL band description: what the band holds).
    raw : bool
        Take tiles already compressed elsewhere (:meth:`write_encoded`, tiles made by
        :attr:`encoder`, e.g. on Dask workers) instead of pixels: GDAL creates the file without tiles
        (``SPARSE_OK=TRUE``, and the internal-mask IFD when the policy is ``"mask"``) and is closed at
        once; each tile's bytes are appended to the file as they come and the tile arrays are filled
        at :meth:`close`. The file holds the same pixels and masks as the default mode's. Needs a
        compression of :data:`rectify.raster.tiffblocks.RAW_COMPRESSIONS`.
    """

    def __init__(self, path: str | Path, width: int, height: int, count: int, dtype: str, transform,
                 crs: str | None, policy: MaskPolicy, *, tile: int = 512, compress: str = "deflate",
                 threads: int = 1, colorinterp=None, raw: bool = False, descriptions=None):

        if tile % 16:
            raise InvalidInputError(f"tile size must be a multiple of 16; got {tile}")
        self.policy = policy
        self.crs = crs
        self.path = str(path)
        self.raw = bool(raw)
        self.width, self.tile = int(width), int(tile)
        prof = _gtiff_profile(width, height, count, dtype, transform, crs,
                              policy.nodata if policy.kind == "nodata" else None,
                              tile=tile, compress=compress, threads=threads)
        if policy.kind == "alpha" and count == 4 and dtype == "uint8":
            prof["photometric"] = "RGB"
        if descriptions is not None and len(descriptions) != count:
            raise InvalidInputError(f"{len(descriptions)} band descriptions for {count} bands")
        self.descriptions = None if descriptions is None else [str(d) for d in descriptions]
        if self.raw:
            self._open_raw(prof, colorinterp)
            return
        try:
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
                self._ds = rasterio.open(self.path, "w", **prof)
            if colorinterp is not None and len(colorinterp) == count:
                self._ds.colorinterp = list(colorinterp)
            for band, text in enumerate(self.descriptions or (), start=1):
                self._ds.set_band_description(band, text)
        except (RasterioError, OSError) as err:
            raise RasterIOError(f"cannot create {self.path!r}: {err}") from err

    def _open_raw(self, prof: dict, colorinterp) -> None:
        """Raw mode: the file without tiles, the encoder of its tiles, and the appender."""

        mask = self.policy.kind == "mask"
        self._encoder = TileEncoder.from_profile(prof, mask=mask)
        try:
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), \
                    rasterio.open(self.path, "w", SPARSE_OK="TRUE", **prof) as ds:
                if colorinterp is not None and len(colorinterp) == ds.count:
                    ds.colorinterp = list(colorinterp)
                for band, text in enumerate(self.descriptions or (), start=1):
                    ds.set_band_description(band, text)
                if mask:
                    # creates the internal-mask IFD; an all-invalid block is never written under SPARSE_OK
                    ds.write_mask(np.zeros((1, 1), np.uint8), window=Window(0, 0, 1, 1))
        except (RasterioError, OSError) as err:
            raise RasterIOError(f"cannot create {self.path!r}: {write_failure_reason(err, self.path)}") from err
        self._appender = TileAppender(self.path)
        lay = self._appender.layout
        self._mask_ifd = None if lay.mask is None else lay.ifds.index(lay.mask)
        image_tags, mask_tags = self._encoder.layout()
        if lay.image.layout != image_tags or (mask and (lay.mask is None or lay.mask.layout != mask_tags)):
            self._appender.abort()
            raise RasterIOError(f"cannot write {self.path!r} from encoded tiles: GDAL created it with another tile "
                                "layout than its encoder's")

    @property
    def encoder(self):
        """The :class:`rectify.raster.tiffblocks.TileEncoder` of this file's tiles (raw mode only; picklable)."""
        if not self.raw:
            raise InvalidInputError(f"{self.path!r} is not written in raw mode: it has no tile encoder")
        return self._encoder

    def write_encoded(self, col_off: int, row_off: int, encoded) -> None:
        """Write a tile compressed by :attr:`encoder` (raw mode): its bytes are copied, not decoded.

        Parameters
        ----------
        col_off, row_off : int
            Top-left pixel of the window; multiples of the tile size.
        encoded : EncodedTile or tuple
            ``(tile bytes, mask tile bytes or None, ...)`` as :meth:`TileEncoder.encode` or
            :meth:`TileEncoder.encode_window` return them ((n,) uint8 arrays or bytes).
        """

        if not self.raw:
            raise InvalidInputError(f"{self.path!r} is not written in raw mode: write pixels with write()")
        data, mask = encoded[0], encoded[1]
        i = tile_index(col_off, row_off, self.tile, self.width)
        self._appender.append(0, i, data)
        if self._mask_ifd is not None:
            if mask is None:
                raise InvalidInputError(f"an encoded tile of {self.path!r} needs its mask tile (the policy is mask)")
            self._appender.append(self._mask_ifd, i, mask)

    def write(self, data: NDArray, col_off: int, row_off: int, valid: NDArray[np.bool_] | None = None) -> None:
        """Write a tile ``(h, w, C)`` at (col_off, row_off); ``valid`` (h, w) for masks.

        With a nodata or alpha policy the caller has already filled invalid
        pixels; with an internal mask ``valid`` becomes the mask (None = all valid).
        """

        if self.raw:
            self.write_encoded(col_off, row_off, self._encoder.encode(data, valid))
            return
        h, w = data.shape[:2]
        win = Window(col_off, row_off, w, h)
        try:
            self._ds.write(np.moveaxis(data, -1, 0), window=win)
            if self.policy.kind == "mask":
                m = np.full((h, w), 255, np.uint8) if valid is None else valid.astype(np.uint8) * 255
                self._ds.write_mask(m, window=win)
        except (RasterioError, OSError) as err:
            raise RasterIOError(f"cannot write {self.path!r}: {write_failure_reason(err, self.path)} "
                                f"(window {win})") from err

    def close(self) -> None:
        """Close the file and check that it was written whole.

        GDAL reports a failed flush (a full disk, most often) only on its own stderr, so the closed
        file is opened again and every block of it must lie inside the file. In raw mode the tile
        arrays are written first.
        """
        if self.raw:
            if self._appender.closed:
                return
            self._appender.close()
            verify_geotiff(self.path, crs=self.crs)
            return
        if self._ds.closed:
            return
        try:
            self._ds.close()
        except (RasterioError, OSError) as err:
            raise RasterIOError(f"cannot write {self.path!r}: {write_failure_reason(err, self.path)}") from err
        verify_geotiff(self.path, crs=self.crs)

    def __enter__(self) -> TiledWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
            return
        with contextlib.suppress(Exception):  # failing already: close without masking the error
            if self.raw:
                self._appender.abort()
            else:
                self._ds.close()


def build_overviews(path: str | Path, tile: int, resampling: str) -> None:
    """Add internal overviews to the raster ``path`` (opened for update): factors 2, 4, ... while the
    reduced raster's long side is at least ``tile`` pixels; none for a raster smaller than two tiles."""
    with rasterio.open(path, "r+") as ds:
        levels, n = [], 2
        while max(ds.width, ds.height) / n >= tile:
            levels.append(n)
            n *= 2
        if levels:
            ds.build_overviews(levels, Resampling[resampling])


def verify_geotiff(path: str | Path, *, crs: str | None = None) -> None:
    """Raise :class:`RasterIOError` unless the GeoTIFF ``path`` opens and holds every block it indexes, and
    :class:`CRSError` when it was written with ``crs`` but records none.

    Catches files left truncated by a write failure GDAL did not raise (a full disk at close); the
    reason names "no space left on device" when the file system is (nearly) full. GDAL drops a CRS that
    GeoTIFF keys cannot express (a topocentric frame, for instance) without an error: such a raster would
    lose its georeferencing silently.
    """
    p = str(path)
    try:
        size = os.path.getsize(p)
        with rasterio.Env(GDAL_PAM_ENABLED=False), rasterio.open(p) as ds:   # the file's own keys, no sidecar
            if crs is not None and ds.crs is None:
                with contextlib.suppress(OSError):   # where GDAL put the CRS instead: beside a temporary name
                    os.unlink(p + ".aux.xml")
                short = crs if len(crs) <= 80 else crs[:77] + "..."
                raise CRSError(f"cannot write {p!r}: a GeoTIFF cannot record its CRS {short!r} (convert to a map "
                               "projection such as UTM)")
            bh, bw = ds.block_shapes[0]
            nbx, nby = math.ceil(ds.width / bw), math.ceil(ds.height / bh)
            for j in range(nby):
                for i in range(nbx):
                    off = ds.get_tag_item(f"BLOCK_OFFSET_{i}_{j}", "TIFF", bidx=1)
                    n = ds.get_tag_item(f"BLOCK_SIZE_{i}_{j}", "TIFF", bidx=1)
                    if off is not None and n is not None and int(off) + int(n) > size:
                        raise RasterIOError(f"cannot write {p!r}: {write_failure_reason(None, p)} "
                                            f"(block {i},{j} ends past the end of the file)")
    except (RasterIOError, CRSError):
        raise
    except (RasterioError, OSError) as err:
        raise RasterIOError(f"cannot write {p!r}: {write_failure_reason(err, p)} (the written file does not "
                            "open)") from err


def write_raster(path: str | Path, data: NDArray, transform, crs: str | None, *,
                 nodata: float | None = None, valid: NDArray[np.bool_] | None = None,
                 overwrite: bool = False, compress: str = "deflate", tile: int = 256) -> Path:
    """Write an in-memory ``(H, W)`` or ``(H, W, C)`` array as a tiled GeoTIFF, atomically.

    Parameters
    ----------
    data : (H, W) or (H, W, C) array
    transform : affine.Affine
    crs : str or None
    nodata : float, optional
        Stored nodata value; with ``valid`` given, invalid pixels are set to it.
    valid : (H, W) bool, optional
        Without ``nodata``, stored as an internal mask.
    overwrite : bool
        Replace an existing file.
    """

    a = np.asarray(data)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3:
        raise InvalidInputError(f"`data` must be (H, W) or (H, W, C); got shape {np.shape(data)}")
    if valid is not None and valid.shape != a.shape[:2]:
        raise InvalidInputError(f"`valid` must have shape {a.shape[:2]}; got {valid.shape}")
    policy = MaskPolicy("nodata", float(nodata)) if nodata is not None else \
        (MaskPolicy("mask") if valid is not None else MaskPolicy("none"))
    if nodata is not None and valid is not None:
        a = a.copy()
        a[~valid] = np.asarray(nodata).astype(a.dtype)
    with atomic_output(path, overwrite=overwrite) as tmp:
        with TiledWriter(tmp, a.shape[1], a.shape[0], a.shape[2], a.dtype.name, transform, crs, policy,
                         tile=tile, compress=compress) as w:
            w.write(a, 0, 0, valid)
    return Path(path)


def cog_driver_available() -> bool:
    """True when GDAL's COG driver is registered (GDAL >= 3.1)."""

    with rasterio.Env() as env:
        return "COG" in env.drivers()


def translate_to_cog(src: str | Path, dst: str | Path, *, compress: str = "deflate", threads: int = 1,
                     tile: int = 512, resampling: str = "average") -> None:
    """Copy a GeoTIFF into a Cloud Optimized GeoTIFF (tiled, overviews, COG IFD layout).

    Uses GDAL's COG driver when available; otherwise builds overviews on a
    copy and writes it with ``COPY_SRC_OVERVIEWS=YES``. ``dst`` is written in
    place (wrap in :func:`rectify.atomic.atomic_output`).
    """

    try:
        if cog_driver_available():
            opts = {"COMPRESS": compress.upper(), "BLOCKSIZE": str(tile), "NUM_THREADS": str(max(1, threads)),
                    "OVERVIEWS": "AUTO", "OVERVIEW_RESAMPLING": resampling.upper(), "BIGTIFF": "IF_SAFER"}
            if compress.lower() in ("deflate", "lzw", "zstd"):
                with rasterio.open(src) as ds:
                    if np.dtype(ds.dtypes[0]).kind in "ui":
                        opts["PREDICTOR"] = "YES"
            rasterio.shutil.copy(str(src), str(dst), driver="COG", **opts)
            verify_geotiff(dst)
            return

        build_overviews(src, tile, resampling)
        rasterio.shutil.copy(str(src), str(dst), driver="GTiff", COPY_SRC_OVERVIEWS="YES", TILED="YES",
                             BLOCKXSIZE=str(tile), BLOCKYSIZE=str(tile), COMPRESS=compress.upper(),
                             BIGTIFF="IF_SAFER")
        verify_geotiff(dst)
    except RasterIOError:
        raise
    except (RasterioError, CPLE_BaseError, OSError) as err:  # CPLE_*: GDAL's own, e.g. a full disk in the COG copy
        raise RasterIOError(f"cannot write COG {str(dst)!r}: {write_failure_reason(err, dst)}") from err


def read_overview_average(path: str | Path, max_size: int, *, bands: list[int] | None = None,
                          max_source_px: int = 16_000_000) -> tuple[NDArray[np.float32], NDArray[np.bool_], float]:
    """Area-averaged overview of a whole raster, streamed by strips (bounded memory).

    Like :func:`read_overview` but with average resampling (no aliasing, so it
    suits feature detection) and reading at most about ``max_source_px``
    source pixels at a time, whatever the raster size.

    Returns
    -------
    data : (h, w, C) float32
    valid : (h, w) bool
        True where at least half of the averaged source pixels hold data.
    scale : float
        Mean full-resolution pixels per overview pixel; the exact per-axis
        scales are ``width / w`` and ``height / h``.
    """

    if max_size < 16:
        raise InvalidInputError(f"max_size must be >= 16; got {max_size}")
    with open_raster(path) as ds:
        b = _check_bands(bands, ds.count, path)
        scale = max(1.0, max(ds.width, ds.height) / max_size)
        h = max(1, int(round(ds.height / scale)))
        w = max(1, int(round(ds.width / scale)))
        sy = ds.height / h
        data = np.empty((h, w, len(b)), dtype=np.float32)
        valid = np.empty((h, w), dtype=bool)
        strip = max(1, int(max_source_px / max(ds.width * sy, 1)))
        try:
            for i0 in range(0, h, strip):
                i1 = min(h, i0 + strip)
                r0 = int(round(i0 * sy))
                r1 = ds.height if i1 == h else int(round(i1 * sy))
                win = Window(0, r0, ds.width, r1 - r0)
                part = ds.read(b, window=win, out_shape=(len(b), i1 - i0, w), resampling=Resampling.average,
                               out_dtype=np.float32)
                m = ds.dataset_mask(window=win, out_shape=(i1 - i0, w), resampling=Resampling.average)
                data[i0:i1] = np.moveaxis(part, 0, -1)
                valid[i0:i1] = m >= 128
        except RasterioError as err:
            raise RasterIOError(f"cannot read overview of {str(path)!r}: {err}") from err
    return data, valid, 0.5 * (ds.width / w + ds.height / h)


def bound_gdal_cache(mb: int = 64) -> None:
    """Bound GDAL's block cache (``GDAL_CACHEMAX``, MB) unless the user set it.

    GDAL reads the setting once, at its first block access, so long tiled jobs call this before
    any pixel IO; it keeps their memory bounded by the tiles rather than by the cache.
    """
    os.environ.setdefault("GDAL_CACHEMAX", str(int(mb)))


@contextlib.contextmanager
def ignore_not_georeferenced() -> Iterator[None]:
    """Silence rasterio's ``NotGeoreferencedWarning`` inside the block (plain photos and normal-case
    images have no geotransform, as expected)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        yield


@contextlib.contextmanager
def gdal_cache_limit(mb: int) -> Iterator[None]:
    """GDAL's block cache bounded to ``mb`` MB inside the block (``GDAL_CACHEMAX`` of a ``rasterio.Env``):
    long tiled jobs keep their memory that of the tiles whatever the raster size."""
    with rasterio.Env(GDAL_CACHEMAX=mb * 1024 * 1024):
        yield


def gdal_wkt(crs: str) -> str:
    """The WKT that GDAL (rasterio) gives a CRS (``"EPSG:nnnn"``, PROJ string or WKT)."""
    return str(rasterio.crs.CRS.from_string(crs).to_wkt())


def reproject_band(path: str | Path, shape: tuple[int, int], transform: Affine, crs: str, *,
                   what: str = "raster") -> NDArray[np.float64]:
    """Band 1 of a georeferenced raster resampled bilinearly onto a grid; NaN where it has no data.

    Parameters
    ----------
    shape : (rows, cols)
        Of the target grid.
    transform, crs
        The target grid's geotransform (cell corners) and CRS.
    what : str
        The raster's name in error messages (``"reference DEM"``).

    Returns
    -------
    (rows, cols) float64

    Raises
    ------
    CRSError
        The raster has no CRS.
    RasterIOError
        It cannot be read.
    """
    p = str(path)
    out = np.full(shape, np.nan, np.float64)
    try:
        with rasterio.open(p) as src:
            if src.crs is None:
                raise CRSError(f"{what} {p!r} has no CRS")
            rasterio.warp.reproject(rasterio.band(src, 1), out, dst_transform=transform, dst_crs=crs,
                                    resampling=Resampling.bilinear, dst_nodata=np.nan)
    except RasterioError as err:
        raise RasterIOError(f"cannot read {what} {p!r}: {err}") from err
    return out


def raster_rpc_tags(path: str | Path) -> dict | None:
    """The RPC of a raster as a plain dict (rasterio's ``RPC.to_dict()`` keys: ``line_off``, ...,
    ``*_coeff`` lists of 20, ``err_bias``, ``err_rand``), from its GeoTIFF RPC tags or a sidecar
    ``_RPC.TXT``/``.RPB`` GDAL finds; None when it has none.

    Raises
    ------
    RasterIOError
        The raster cannot be read.
    """
    with open_raster(path) as ds:
        rpcs = ds.rpcs
    return None if rpcs is None else dict(rpcs.to_dict())
