"""Tiles of a raster for the browser view (``rectify view``): PNG tiles of a pixel pyramid, read by window on demand.

The pyramid is in the raster's own pixels: at level ``max_level`` one tile pixel is one raster pixel; each
level below halves the resolution (scale ``2 ** (max_level - level)`` raster pixels per tile pixel), and level
0 is the first that fits the whole raster in one tile. A tile ``(level, tx, ty)`` covers the raster pixels
columns ``[tx * T * s, (tx + 1) * T * s)`` and rows ``[ty * T * s, (ty + 1) * T * s)`` with ``T`` = :data:`TILE`
and ``s`` the scale; edge tiles are smaller (the page places them by that rule).

Nothing is read when a source is opened except the header. A tile at scale ``s`` smaller than the preview's
reads its window decimated (GDAL uses the raster's overviews when it has them); coarser tiles are cut from one
*preview* of the whole raster (longest side at most :data:`PREVIEW_MAX` pixels), read once, on the first
request that needs it, in one decimated read that GDAL streams block by block. So memory stays at about one
preview plus one window per request thread, whatever the raster's size.

Kinds of rendering (:class:`TileSource` ``mode``):

- ``image``: bands 1-3 (or band 1 as grey); uint8 as is, other types stretched between the 2nd and 98th
  percentile of the preview.
- ``hillshade``: band 1 as heights, shaded (sun azimuth 315 deg, altitude 45 deg) with the cell size of the tile's
  scale; ``z_factor`` converts heights to ground units.
- ``ramp``: one band (e.g. a sigma_Z band) coloured from dark blue to yellow between its preview percentiles.

Invalid pixels (nodata, mask) are transparent (PNG RGBA).
"""

from __future__ import annotations

import math
import struct
import threading
import zlib
from dataclasses import dataclass

import numpy as np
import rasterio
from numpy.typing import NDArray
from rasterio.enums import Resampling
from rasterio.errors import RasterioError
from rasterio.io import DatasetReader
from rasterio.windows import Window

from rectify.errors import InvalidInputError, RasterIOError
from rectify.raster.io import ignore_not_georeferenced

#: tile side, pixels
TILE = 256
#: longest side of the preview a source keeps for its coarse levels, pixels
PREVIEW_MAX = 2048
#: threads reading a preview (each with its own dataset)
PREVIEW_THREADS = 2
MODES = ("image", "hillshade", "ramp")


@dataclass(frozen=True)
class RasterLayout:
    """What the page needs to place a raster's tiles.

    Attributes
    ----------
    width, height, count : int
        Columns, rows, bands of the raster.
    max_level : int
        The level of full resolution (one tile pixel = one raster pixel).
    tile : int
        Tile side, pixels.
    descriptions : tuple of str
        The bands' descriptions ("" where none).
    crs : str or None
    transform : tuple of 6 float
        rasterio's geotransform (a, b, c, d, e, f) of the pixel corners.
    """

    width: int
    height: int
    count: int
    max_level: int
    tile: int
    descriptions: tuple[str, ...]
    crs: str | None
    transform: tuple[float, float, float, float, float, float]


def max_level_for(width: int, height: int, tile: int = TILE) -> int:
    """The level of full resolution: the smallest L with ``tile * 2**L >= max(width, height)``.

    >>> max_level_for(10000, 8000), max_level_for(256, 10), max_level_for(257, 10)
    (6, 0, 1)
    """
    side = max(int(width), int(height), 1)
    return max(0, math.ceil(math.log2(side / tile))) if side > tile else 0


def encode_png(rgba: NDArray[np.uint8], *, level: int = 1) -> bytes:
    """PNG bytes of an (H, W, 4) uint8 RGBA array (or (H, W, 3) RGB), zlib ``level`` (1: fast).

    >>> encode_png(np.zeros((2, 3, 4), np.uint8))[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
    True
    """
    a = np.ascontiguousarray(rgba, dtype=np.uint8)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.shape[0] < 1 or a.shape[1] < 1:
        raise InvalidInputError(f"PNG tile must be (H, W, 3|4) uint8; got shape {a.shape}")
    h, w, c = a.shape
    raw = np.empty((h, 1 + w * c), np.uint8)
    raw[:, 0] = 0  # filter type None on every row
    raw[:, 1:] = a.reshape(h, w * c)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 6 if c == 4 else 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw.tobytes(), level))
            + chunk(b"IEND", b""))


def hillshade(z: NDArray, valid: NDArray[np.bool_], cell: float, *, azimuth_deg: float = 315.0,
              altitude_deg: float = 45.0) -> NDArray[np.uint8]:
    """Grey hillshade (H, W) uint8 of heights ``z`` (H, W) on a square grid of ``cell`` ground units.

    Slopes by central differences (one-sided at the edges and next to invalid cells); the sun from
    ``azimuth_deg`` (clockwise from up = north, rows down) at ``altitude_deg`` above the horizon. A flat
    surface gets ``255 * sin(altitude)``.

    >>> int(hillshade(np.zeros((3, 3)), np.ones((3, 3), bool), 1.0)[1, 1])
    180
    """
    zz = np.where(valid, z, np.nan).astype(np.float64)
    if zz.shape[0] < 2 or zz.shape[1] < 2:
        dzdx = np.zeros_like(zz)
        dzdy = np.zeros_like(zz)
    else:
        fill = np.where(np.isnan(zz), np.nanmean(zz) if np.isfinite(zz).any() else 0.0, zz)
        dzdy, dzdx = np.gradient(fill, cell)  # rows (down), columns (right)
    az = math.radians(azimuth_deg)
    alt = math.radians(altitude_deg)
    slope = np.arctan(np.hypot(dzdx, dzdy))
    aspect = np.arctan2(-dzdx, dzdy)  # direction of steepest descent, clockwise from north with rows down
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    out = np.clip(255.0 * shade, 0, 255)
    out[~valid] = 0
    return out.astype(np.uint8)


def _ramp(v: NDArray[np.float64]) -> NDArray[np.uint8]:
    """Colours (..., 3) uint8 of ``v`` in [0, 1]: dark blue - teal - yellow (a viridis-like ramp)."""
    stops = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64)
    t = np.clip(np.nan_to_num(v), 0, 1) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[..., None]
    return (stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


class TileSource:
    """One raster served as PNG tiles (see the module docstring); safe to use from several threads.

    Parameters
    ----------
    path : str
    mode : {"image", "hillshade", "ramp"}
    band : int
        The band of ``hillshade`` and ``ramp`` (1-based).
    z_factor : float
        Heights to ground units for ``hillshade`` (1 when both are metres).

    Raises
    ------
    RasterIOError
        The raster cannot be opened.
    InvalidInputError
        An unknown mode or a band out of range.
    """

    def __init__(self, path: str, *, mode: str = "image", band: int = 1, z_factor: float = 1.0) -> None:
        if mode not in MODES:
            raise InvalidInputError(f"tile mode must be one of {MODES}; got {mode!r}")
        self.path = str(path)
        self.mode = mode
        self._lock = threading.Lock()
        try:
            with ignore_not_georeferenced():
                self._ds = rasterio.open(self.path)
        except (RasterioError, OSError) as err:
            raise RasterIOError(f"cannot read raster {self.path!r}: {err}") from err
        ds = self._ds
        if not 1 <= band <= ds.count:
            ds.close()
            raise InvalidInputError(f"band {band} out of range 1..{ds.count} in {self.path!r}")
        self.band = band
        self.z_factor = float(z_factor)
        t = ds.transform
        self.layout = RasterLayout(ds.width, ds.height, ds.count, max_level_for(ds.width, ds.height), TILE,
                                   tuple(d or "" for d in ds.descriptions),
                                   ds.crs.to_string() if ds.crs else None,
                                   (t.a, t.b, t.c, t.d, t.e, t.f))
        self._preview: tuple[NDArray, NDArray[np.bool_]] | None = None
        self._preview_scale = 1
        while max(ds.width, ds.height) / self._preview_scale > PREVIEW_MAX:
            self._preview_scale *= 2
        self._limits: tuple[float, float] | None = None

    def close(self) -> None:
        """Close the raster."""
        with self._lock:
            self._ds.close()

    @property
    def dtype(self) -> str:
        """The data type of the rendered band(s)."""
        return str(self._ds.dtypes[self.bands[0] - 1])

    @property
    def bands(self) -> list[int]:
        """The bands read: 1-3 (or 1) for ``image``, the chosen band otherwise."""
        if self.mode == "image":
            return [1, 2, 3] if self._ds.count >= 3 else [1]
        return [self.band]

    def _read(self, col: int, row: int, w: int, h: int, out_h: int, out_w: int, ds: DatasetReader | None = None
              ) -> tuple[NDArray, NDArray[np.bool_]]:
        """The window decimated to (out_h, out_w): data (C, out_h, out_w), valid (out_h, out_w). Lock held (or
        ``ds``, a dataset of the calling thread's own)."""
        win = Window(col, row, w, h)
        ds = self._ds if ds is None else ds
        try:
            with ignore_not_georeferenced():
                data = ds.read(self.bands, window=win, out_shape=(len(self.bands), out_h, out_w),
                               resampling=Resampling.nearest)
                mask = ds.read_masks(self.bands[0], window=win, out_shape=(out_h, out_w),
                                     resampling=Resampling.nearest)
        except RasterioError as err:
            raise RasterIOError(f"cannot read raster {self.path!r}: {err}") from err
        valid = mask > 0
        if np.issubdtype(data.dtype, np.floating):
            valid &= np.all(np.isfinite(data), axis=0)
        return data, valid

    def preview(self) -> tuple[NDArray, NDArray[np.bool_], int]:
        """The whole raster decimated by ``scale`` (a power of two; longest side <= PREVIEW_MAX): data
        (C, h, w), valid (h, w), scale. Read once, on first use."""
        with self._lock:
            if self._preview is None:
                s = self._preview_scale
                lay = self.layout
                out_w = max(1, math.ceil(lay.width / s))
                # strips of whole block rows (a multiple of the scale): every block is read once, and
                # GDAL's cache needs to hold one block row only
                block_rows = self._ds.block_shapes[0][0] if self._ds.block_shapes else 256
                strip = max(s, math.lcm(int(block_rows), s))
                while strip < 256:
                    strip *= 2
                starts = list(range(0, lay.height, strip))
                parts: list[tuple[NDArray, NDArray[np.bool_]] | None] = [None] * len(starts)
                errors: list[BaseException] = []

                def work(first: int, ds: DatasetReader | None) -> None:
                    try:
                        for j in range(first, len(starts), PREVIEW_THREADS):
                            h = min(strip, lay.height - starts[j])
                            parts[j] = self._read(0, starts[j], lay.width, h, max(1, math.ceil(h / s)), out_w, ds)
                    except BaseException as err:  # handed to the caller below
                        errors.append(err)
                    finally:
                        if ds is not None:
                            ds.close()

                # the strips in PREVIEW_THREADS threads, each with its own dataset (GDAL reads release the GIL)
                helpers = []
                for first in range(1, min(PREVIEW_THREADS, len(starts))):
                    try:
                        with ignore_not_georeferenced():
                            own = rasterio.open(self.path)
                    except (RasterioError, OSError) as err:
                        raise RasterIOError(f"cannot read raster {self.path!r}: {err}") from err
                    helpers.append(threading.Thread(target=work, args=(first, own), daemon=True))
                for t in helpers:
                    t.start()
                work(0, None)
                for t in helpers:
                    t.join()
                if errors:
                    raise errors[0]
                done = [p for p in parts if p is not None]
                self._preview = (np.concatenate([d for d, _ in done], axis=1),
                                 np.concatenate([v for _, v in done], axis=0))
            data, valid = self._preview
            return data, valid, self._preview_scale

    def limits(self) -> tuple[float, float]:
        """The stretch of the rendering: 2nd and 98th percentile of the preview's valid values."""
        if self._limits is None:
            data, valid, _ = self.preview()
            vals = data[:, valid].astype(np.float64).ravel()
            vals = vals[np.isfinite(vals)]
            if vals.size == 0:
                lim = (0.0, 1.0)
            else:
                lo, hi = np.percentile(vals, [2.0, 98.0])
                lim = (float(lo), float(hi) if hi > lo else float(lo) + 1.0)
            self._limits = lim
        return self._limits

    def tile_window(self, level: int, tx: int, ty: int) -> tuple[int, int, int, int, int]:
        """(col, row, width, height, scale) of the raster pixels of tile ``(level, tx, ty)``.

        Raises
        ------
        InvalidInputError
            The tile lies outside the pyramid.
        """
        lay = self.layout
        if not 0 <= level <= lay.max_level:
            raise InvalidInputError(f"tile level {level} outside 0..{lay.max_level}")
        s = 2 ** (lay.max_level - level)
        span = TILE * s
        col, row = tx * span, ty * span
        if tx < 0 or ty < 0 or col >= lay.width or row >= lay.height:
            raise InvalidInputError(f"tile {level}/{tx}/{ty} outside the raster of {lay.width} x {lay.height} px")
        return col, row, min(span, lay.width - col), min(span, lay.height - row), s

    def tile_array(self, level: int, tx: int, ty: int) -> tuple[NDArray, NDArray[np.bool_], int]:
        """Data (C, h, w) and valid (h, w) of a tile, and its scale (raster pixels per tile pixel)."""
        col, row, w, h, s = self.tile_window(level, tx, ty)
        out_h, out_w = max(1, math.ceil(h / s)), max(1, math.ceil(w / s))
        if s > 1 and s >= self._preview_scale:
            data, valid, p = self.preview()
            k = s // p
            r0, c0 = row // p, col // p
            sl = (slice(r0, r0 + out_h * k, k), slice(c0, c0 + out_w * k, k))
            d, v = data[:, sl[0], sl[1]], valid[sl]
            return d, v, s
        with self._lock:
            d, v = self._read(col, row, w, h, out_h, out_w)
        return d, v, s

    def tile_png(self, level: int, tx: int, ty: int) -> bytes:
        """The PNG (RGBA) of tile ``(level, tx, ty)``."""
        data, valid, s = self.tile_array(level, tx, ty)
        return encode_png(self.render(data, valid, s))

    def render(self, data: NDArray, valid: NDArray[np.bool_], scale: int) -> NDArray[np.uint8]:
        """RGBA (h, w, 4) uint8 of a tile's data (C, h, w) by the source's mode."""
        h, w = valid.shape
        out = np.zeros((h, w, 4), np.uint8)
        if self.mode == "image":
            if data.dtype == np.uint8:
                img = data
            else:
                lo, hi = self.limits()
                img = np.clip((data.astype(np.float64) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
            out[..., :3] = np.moveaxis(img, 0, -1) if img.shape[0] == 3 else img[0][..., None]
        elif self.mode == "hillshade":
            t = self.layout.transform
            cell = math.hypot(t[0], t[3]) or 1.0
            g = hillshade(data[0].astype(np.float64) * self.z_factor, valid, cell * scale)
            out[..., :3] = g[..., None]
        else:
            lo, hi = self.limits()
            out[..., :3] = _ramp((data[0].astype(np.float64) - lo) / (hi - lo))
        out[..., 3] = np.where(valid, 255, 0)
        return out

    def __enter__(self) -> TileSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
