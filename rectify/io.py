"""Raster IO: the only module that opens rasters and swaps axes.

Arrays handed to the rest of the project are ``(H, W, C)`` (rows, columns,
bands), never rasterio's ``(bands, rows, cols)``. Large rasters are read by
windows; nothing here assumes an image fits in memory. Validity is a bool
mask ``(H, W)``: True where every band holds data (nodata, per-dataset masks
and alpha are respected through rasterio's dataset mask).
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from numpy.typing import NDArray

from .errors import InvalidInputError, RasterIOError

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
        :mod:`rectify.georef`).
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
    transform: object
    block_shape: tuple[int, int]

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.height, self.width, self.count)


@contextlib.contextmanager
def open_raster(path: str | Path) -> Iterator["rasterio.io.DatasetReader"]:  # noqa: F821
    """Open a raster for reading; rasterio errors become :class:`RasterIOError`."""
    import rasterio
    from rasterio.errors import RasterioError

    p = str(path)
    if not Path(p).exists():
        raise RasterIOError(f"raster not found: {p!r}")
    try:
        ds = rasterio.open(p)
    except RasterioError as err:
        raise RasterIOError(f"cannot read raster {p!r}: {err}") from err
    try:
        yield ds
    finally:
        ds.close()


def _crs_string(crs) -> str | None:
    if crs is None:
        return None
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
    from rasterio.errors import RasterioError
    from rasterio.windows import Window

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
    from rasterio.windows import Window

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
