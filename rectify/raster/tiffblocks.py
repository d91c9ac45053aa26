"""Compressed GeoTIFF tiles made in one process and placed into a file by another.

The tiled steps on a Dask cluster (:mod:`rectify.raster.distributed`) compress their output tiles on the
workers; the calling process (the *driver*) only copies the compressed bytes into the output
GeoTIFF. Three pieces:

- :class:`TileEncoder`: built from the output's creation options (the profile of
  :class:`rectify.raster.io.TiledWriter`), it writes one output window into an in-memory GeoTIFF
  (``/vsimem/``) with exactly those options (tile size, compression, predictor, ZSTD level,
  interleave, dtype, bands, nodata, internal mask) and returns the compressed bytes of its tile (and
  of its internal-mask tile). GDAL compresses the tile, pads an edge tile and applies the predictor
  as it does when it writes the same window into the full-size file, so the bytes are the same.
- :func:`read_tiff_layout`: a small TIFF structure reader (classic TIFF and BigTIFF, little- and
  big-endian) that finds, for the image IFD and GDAL's internal-mask IFD, where the TileOffsets
  (tag 324) and TileByteCounts (tag 325) arrays lie and how wide their elements are (arrays short
  enough to fit in the IFD entry itself are found there).
- :class:`TileAppender` / :func:`append_tiles`: append tile bytes at the end of a GeoTIFF created
  without tiles (GDAL's ``SPARSE_OK=TRUE``) and write their offsets and byte counts into those
  arrays in place (an array whose element type is too narrow for the values is rewritten, wider, at
  the end of the file and its IFD entry pointed at it).

Output windows are aligned on the tile grid: their column and row offsets are multiples of the tile
size (windows at the right and bottom edges are smaller).
"""

from __future__ import annotations

import contextlib
import os
import struct
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO, NamedTuple

import numpy as np
import rasterio
from numpy.typing import NDArray
from rasterio.errors import NotGeoreferencedWarning, RasterioError
from rasterio.io import MemoryFile

from rectify.atomic import write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError, ShapeError

__all__ = ["RAW_COMPRESSIONS", "EncodedTile", "TileEncoder", "TileArray", "TiffIfd", "TiffLayout",
           "read_tiff_layout", "TileAppender", "append_tiles"]

#: compressions whose tiles are self-contained (no per-file tables such as JPEG's): tiles can be made elsewhere
RAW_COMPRESSIONS = ("none", "deflate", "lzw", "zstd", "packbits", "lzma")

TAG_NEW_SUBFILE_TYPE = 254
TAG_BITS_PER_SAMPLE = 258
TAG_COMPRESSION = 259
TAG_PHOTOMETRIC = 262
TAG_SAMPLES_PER_PIXEL = 277
TAG_PLANAR_CONFIG = 284
TAG_PREDICTOR = 317
TAG_TILE_WIDTH = 322
TAG_TILE_LENGTH = 323
TAG_TILE_OFFSETS = 324
TAG_TILE_BYTE_COUNTS = 325
TAG_SAMPLE_FORMAT = 339
#: NewSubfileType bit of a transparency mask (GDAL's internal mask IFD)
FILETYPE_MASK = 4
#: PhotometricInterpretation of a transparency mask
PHOTOMETRIC_MASK = 4

#: TIFF field type -> (bytes per element, struct code of an unsigned integer type, or "" if not one)
_TYPES = {1: (1, "B"), 2: (1, ""), 3: (2, "H"), 4: (4, "I"), 5: (8, ""), 6: (1, ""), 7: (1, ""), 8: (2, ""),
          9: (4, ""), 10: (8, ""), 11: (4, ""), 12: (8, ""), 13: (4, "I"), 16: (8, "Q"), 17: (8, ""), 18: (8, "Q")}
_SHORT, _LONG, _LONG8 = 3, 4, 16
#: tags whose values describe how a tile is encoded (must agree between an encoded tile and the file)
_LAYOUT_TAGS = (TAG_BITS_PER_SAMPLE, TAG_COMPRESSION, TAG_SAMPLES_PER_PIXEL, TAG_PLANAR_CONFIG, TAG_PREDICTOR,
                TAG_TILE_WIDTH, TAG_TILE_LENGTH, TAG_SAMPLE_FORMAT)
_MAX_IFDS = 1024


# =============================================================================
# The TIFF structure
# =============================================================================

@dataclass(frozen=True)
class TileArray:
    """Where one TileOffsets or TileByteCounts array lies in a TIFF file.

    Attributes
    ----------
    entry_pos : int
        File position (bytes) of its IFD entry (tag, type, count, value or offset).
    field_type : int
        TIFF field type of the elements (3 SHORT, 4 LONG, 16 LONG8; 13 IFD and 18 IFD8 are read too).
    count : int
        Number of elements (tiles of the IFD).
    pos : int
        File position of the first element: inside the IFD entry when the array fits there.
    inline : bool
        True when the array is stored in the entry's value field.
    """

    entry_pos: int
    field_type: int
    count: int
    pos: int
    inline: bool

    @property
    def item_size(self) -> int:
        """Bytes per element."""
        return _TYPES[self.field_type][0]


@dataclass(frozen=True)
class TiffIfd:
    """One image file directory of a tiled TIFF.

    Attributes
    ----------
    pos : int
        File position of the IFD.
    offsets, byte_counts : TileArray
        Its TileOffsets (324) and TileByteCounts (325) arrays.
    is_mask : bool
        A transparency mask (NewSubfileType bit 4 or PhotometricInterpretation 4): GDAL's internal mask.
    layout : tuple of (tag, values)
        The tags that say how a tile is encoded (bits per sample, compression, samples per pixel,
        planar configuration, predictor, tile width and length, sample format).
    """

    pos: int
    offsets: TileArray
    byte_counts: TileArray
    is_mask: bool
    layout: tuple[tuple[int, tuple[int, ...]], ...]


@dataclass(frozen=True)
class TiffLayout:
    """The structure of a tiled TIFF file: byte order, flavour and its tiled IFDs, in file order.

    Attributes
    ----------
    byte_order : str
        ``"<"`` (little-endian, ``II``) or ``">"`` (big-endian, ``MM``).
    bigtiff : bool
    ifds : tuple of TiffIfd
        Every tiled IFD of the main chain, the image first.
    """

    byte_order: str
    bigtiff: bool
    ifds: tuple[TiffIfd, ...]

    @property
    def image(self) -> TiffIfd:
        """The first IFD (the full-resolution image)."""
        return self.ifds[0]

    @property
    def mask(self) -> TiffIfd | None:
        """The internal-mask IFD of the full-resolution image (the first mask IFD), or None."""
        return next((d for d in self.ifds[1:] if d.is_mask), None)


class _Source:
    """Random access to the bytes of a file or of a buffer."""

    def __init__(self, src: BinaryIO | bytes | bytearray | memoryview, name: str):
        self.name = name
        self._fh: BinaryIO | None = None
        self._buf: memoryview | None = None
        if isinstance(src, (bytes, bytearray, memoryview)):
            self._buf = memoryview(src).cast("B")
        else:
            self._fh = src

    def read(self, pos: int, n: int) -> bytes:
        if self._fh is not None:
            self._fh.seek(pos)
            out = self._fh.read(n)
        else:
            out = bytes(self._buf[pos:pos + n]) if self._buf is not None else b""
        if len(out) != n:
            raise RasterIOError(f"cannot read the TIFF structure of {self.name!r}: it ends at byte {pos + len(out)} "
                                f"inside a structure that needs {n} bytes at {pos}")
        return out


def read_tiff_layout(src: str | os.PathLike[str] | BinaryIO | bytes | memoryview, *,
                     name: str | None = None) -> TiffLayout:
    """Find the tile arrays of a tiled TIFF (classic or BigTIFF, either byte order).

    Parameters
    ----------
    src : path, binary file opened for reading, or bytes
        The TIFF file (a file object is read from its start; its position is left anywhere).
    name : str, optional
        Name of the file in error messages (default: the path).

    Returns
    -------
    TiffLayout

    Raises
    ------
    RasterIOError
        Not a TIFF, a truncated structure, or a first IFD without tiles.

    Examples
    --------
    >>> read_tiff_layout(b"GIF89a..")
    Traceback (most recent call last):
    ...
    rectify.errors.RasterIOError: '<bytes>' is not a TIFF file (header b'GIF8')
    """
    if isinstance(src, (str, os.PathLike)):
        try:
            with open(src, "rb") as fh:
                return read_tiff_layout(fh, name=name or str(src))
        except OSError as err:
            raise RasterIOError(f"cannot read {str(src)!r}: {err.strerror or err}") from err
    label = name or ("<bytes>" if isinstance(src, (bytes, bytearray, memoryview)) else getattr(src, "name", "<file>"))
    s = _Source(src, str(label))
    try:
        head = s.read(0, 4)
    except RasterIOError:
        head = b""
    if head[:2] not in (b"II", b"MM"):
        raise RasterIOError(f"{s.name!r} is not a TIFF file (header {head!r})")
    bo = "<" if head[:2] == b"II" else ">"
    magic = struct.unpack(bo + "H", head[2:4])[0]
    if magic == 42:
        big = False
        first = struct.unpack(bo + "I", s.read(4, 4))[0]
    elif magic == 43:
        big = True
        size, _zero, first = struct.unpack(bo + "HHQ", s.read(4, 12))
        if size != 8:
            raise RasterIOError(f"{s.name!r}: BigTIFF offset size {size}, expected 8")
    else:
        raise RasterIOError(f"{s.name!r} is not a TIFF file (version {magic})")
    ifds: list[TiffIfd] = []
    seen: set[int] = set()
    pos = first
    while pos and len(seen) < _MAX_IFDS:
        if pos in seen:
            raise RasterIOError(f"{s.name!r}: the IFD chain loops back to byte {pos}")
        seen.add(pos)
        ifd, pos = _read_ifd(s, bo, big, pos)
        if ifd is not None:
            ifds.append(ifd)
    if not ifds or ifds[0].pos != first:
        raise RasterIOError(f"{s.name!r} is not a tiled TIFF (its first IFD has no TileOffsets/TileByteCounts)")
    return TiffLayout(bo, big, tuple(ifds))


def _read_ifd(s: _Source, bo: str, big: bool, pos: int) -> tuple[TiffIfd | None, int]:
    """One IFD at ``pos`` -> (the IFD if it is tiled, the position of the next IFD or 0)."""
    if big:
        n = struct.unpack(bo + "Q", s.read(pos, 8))[0]
        entries_pos, entry_size, inline_size = pos + 8, 20, 8
    else:
        n = struct.unpack(bo + "H", s.read(pos, 2))[0]
        entries_pos, entry_size, inline_size = pos + 2, 12, 4
    if n > 4096:
        raise RasterIOError(f"{s.name!r}: IFD at byte {pos} claims {n} entries")
    raw = s.read(entries_pos, n * entry_size + (8 if big else 4))
    arrays: dict[int, TileArray] = {}
    values: dict[int, tuple[int, ...]] = {}
    for k in range(n):
        e = raw[k * entry_size:(k + 1) * entry_size]
        if big:
            tag, typ, count = struct.unpack(bo + "HHQ", e[:12])
            field = e[12:20]
        else:
            tag, typ, count = struct.unpack(bo + "HHI", e[:8])
            field = e[8:12]
        size, code = _TYPES.get(typ, (0, ""))
        if not size:
            continue
        inline = count * size <= inline_size
        data_pos = entries_pos + k * entry_size + (12 if big else 8) if inline else \
            struct.unpack(bo + ("Q" if big else "I"), field)[0]
        if tag in (TAG_TILE_OFFSETS, TAG_TILE_BYTE_COUNTS):
            if not code:
                raise RasterIOError(f"{s.name!r}: tag {tag} of the IFD at byte {pos} has non-integer type {typ}")
            arrays[tag] = TileArray(entries_pos + k * entry_size, typ, int(count), int(data_pos), inline)
        elif tag in (TAG_NEW_SUBFILE_TYPE, TAG_PHOTOMETRIC) + _LAYOUT_TAGS and code and count <= 64:
            blob = field[:count * size] if inline else s.read(data_pos, count * size)
            values[tag] = struct.unpack(f"{bo}{count}{code}", blob)
    nxt = struct.unpack(bo + ("Q" if big else "I"), raw[n * entry_size:])[0]
    if TAG_TILE_OFFSETS not in arrays or TAG_TILE_BYTE_COUNTS not in arrays:
        return None, nxt
    off, cnt = arrays[TAG_TILE_OFFSETS], arrays[TAG_TILE_BYTE_COUNTS]
    if off.count != cnt.count:
        raise RasterIOError(f"{s.name!r}: the IFD at byte {pos} has {off.count} tile offsets but {cnt.count} "
                            "tile byte counts")
    is_mask = bool(values.get(TAG_NEW_SUBFILE_TYPE, (0,))[0] & FILETYPE_MASK) or \
        values.get(TAG_PHOTOMETRIC, (None,))[0] == PHOTOMETRIC_MASK
    layout = tuple((t, values[t]) for t in _LAYOUT_TAGS if t in values)
    return TiffIfd(pos, off, cnt, is_mask, layout), nxt


def _read_array(fh: BinaryIO, bo: str, arr: TileArray) -> NDArray[np.uint64]:
    """The values of a tile array, as uint64."""
    fh.seek(arr.pos)
    raw = fh.read(arr.count * arr.item_size)
    return np.frombuffer(raw, dtype=f"{bo}u{arr.item_size}").astype(np.uint64)


# =============================================================================
# Appending tiles
# =============================================================================

class TileAppender:
    """Append compressed tiles to a tiled GeoTIFF and fill its tile arrays.

    The file must have been created with its tile arrays in place and its tiles unwritten (GDAL's
    ``SPARSE_OK=TRUE``: every offset and byte count 0). Each :meth:`append` writes a tile's bytes at
    the end of the file; :meth:`close` writes the offsets and byte counts into the arrays, in place.
    A tile appended twice keeps its last bytes (the earlier ones stay in the file, unused).

    Parameters
    ----------
    path : path
        The GeoTIFF (opened read-write).

    Raises
    ------
    RasterIOError
        The file cannot be opened or is not a tiled TIFF.
    """

    def __init__(self, path: str | os.PathLike[str]):
        self.path = str(path)
        self.layout = read_tiff_layout(self.path)
        try:
            self._fh: BinaryIO = open(self.path, "r+b")  # noqa: SIM115 - closed by close()/abort()
        except OSError as err:
            raise RasterIOError(f"cannot write {self.path!r}: {write_failure_reason(err, self.path)}") from err
        self._end = self._fh.seek(0, os.SEEK_END)
        self._offsets = [np.zeros(d.offsets.count, np.uint64) for d in self.layout.ifds]
        self._counts = [np.zeros(d.offsets.count, np.uint64) for d in self.layout.ifds]
        for i, d in enumerate(self.layout.ifds):  # keep tiles the file already has (none after SPARSE_OK)
            self._offsets[i] = _read_array(self._fh, self.layout.byte_order, d.offsets)
            self._counts[i] = _read_array(self._fh, self.layout.byte_order, d.byte_counts)

    @property
    def closed(self) -> bool:
        return self._fh.closed

    def append(self, ifd: int, index: int, data: bytes | memoryview | NDArray[np.uint8]) -> None:
        """Write one tile's compressed bytes at the end of the file.

        Parameters
        ----------
        ifd : int
            Index into ``self.layout.ifds`` (0: the image; see :attr:`TiffLayout.mask`).
        index : int
            Tile index in the IFD (row-major: ``tile_row * tiles_across + tile_col``).
        data : bytes-like
            The tile as the file's compression encodes it.
        """
        n = len(self._offsets[ifd])
        if not 0 <= index < n:
            raise InvalidInputError(f"tile index {index} is outside 0..{n - 1} of IFD {ifd} of {self.path!r}")
        buf = (np.ascontiguousarray(data, dtype=np.uint8).data if isinstance(data, np.ndarray)
               else memoryview(data)).cast("B")
        try:
            self._fh.seek(self._end)
            self._fh.write(buf)
        except OSError as err:
            raise RasterIOError(f"cannot write {self.path!r}: {write_failure_reason(err, self.path)}") from err
        self._offsets[ifd][index] = self._end if buf.nbytes else 0
        self._counts[ifd][index] = buf.nbytes
        self._end += buf.nbytes

    def close(self) -> None:
        """Write the tile arrays and close the file.

        Raises
        ------
        RasterIOError
            A write failed ("no space left on device" when the disk is full), or an offset does not
            fit a classic TIFF (more than 4 GB: write a BigTIFF).
        """
        if self._fh.closed:
            return
        try:
            for i, d in enumerate(self.layout.ifds):
                self._patch(d.offsets, self._offsets[i])
                self._patch(d.byte_counts, self._counts[i])
            self._fh.flush()  # no fsync: as GDAL's own writer (a full disk fails the writes themselves)
        except OSError as err:
            self.abort()
            if isinstance(err, RasterIOError):
                raise
            raise RasterIOError(f"cannot write {self.path!r}: {write_failure_reason(err, self.path)}") from err
        self._fh.close()

    def abort(self) -> None:
        """Close the file without writing the tile arrays (the caller discards the file)."""
        if not self._fh.closed:
            try:
                self._fh.close()
            except OSError:  # a failed flush of a file that is discarded anyway
                pass

    def _patch(self, arr: TileArray, values: NDArray[np.uint64]) -> None:
        bo, big = self.layout.byte_order, self.layout.bigtiff
        top = int(values.max()) if values.size else 0
        typ = arr.field_type
        if top >= 1 << (8 * arr.item_size):  # too narrow for the values: a wider array at the end of the file
            if not big and top >= 1 << 32:
                raise RasterIOError(f"cannot write {self.path!r}: tile data end past 4 GB in a classic TIFF "
                                    "(write it as a BigTIFF)")
            typ = _LONG8 if big else _LONG
        size = _TYPES[typ][0]
        blob = values.astype(f"{bo}u{size}").tobytes()
        if typ == arr.field_type:
            self._fh.seek(arr.pos)
            self._fh.write(blob)
            return
        inline_size = 8 if big else 4
        field = blob.ljust(inline_size, b"\0") if len(blob) <= inline_size else None
        if field is None:
            self._end += self._end % 2  # TIFF offsets to values are word-aligned
            self._fh.seek(self._end)
            self._fh.write(blob)
            field = struct.pack(bo + ("Q" if big else "I"), self._end)
            self._end += len(blob)
        self._fh.seek(arr.entry_pos + 2)
        self._fh.write(struct.pack(bo + "H", typ))
        self._fh.seek(arr.entry_pos + (12 if big else 8))
        self._fh.write(field)


def append_tiles(path: str | os.PathLike[str], tiles: Iterable[tuple[int, int, bytes | NDArray[np.uint8]]]) -> None:
    """Append tiles at the end of a tiled GeoTIFF and write their offsets and byte counts in place.

    Parameters
    ----------
    path : path
        A GeoTIFF created without its tiles (GDAL's ``SPARSE_OK=TRUE``).
    tiles : iterable of (ifd, index, data)
        ``ifd`` 0 is the image, :attr:`TiffLayout.mask`'s index the internal mask; ``index`` is the
        row-major tile index; ``data`` the compressed tile.

    Raises
    ------
    RasterIOError
        Unreadable structure, a failed write.
    """
    app = TileAppender(path)
    try:
        for ifd, index, data in tiles:
            app.append(ifd, index, data)
    except BaseException:
        app.abort()
        raise
    app.close()


# =============================================================================
# Encoding tiles
# =============================================================================

class EncodedTile(NamedTuple):
    """One output window, compressed as the output GeoTIFF stores it.

    Attributes
    ----------
    data : (n,) uint8
        The image tile (all bands, as the file's interleave, compression and predictor encode it).
    mask : (m,) uint8 or None
        The internal-mask tile (mask policy only).
    """

    data: NDArray[np.uint8]
    mask: NDArray[np.uint8] | None


@contextlib.contextmanager
def _no_georef_warning() -> Iterator[None]:
    """Silence rasterio's NotGeoreferencedWarning for the in-memory one-tile files (on Dask workers it
    would reach the user's console once per tile)."""

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        yield


@dataclass(frozen=True, eq=False)
class TileEncoder:
    """Compress output windows as one GeoTIFF's tiles (picklable: shipped to Dask workers).

    Attributes
    ----------
    creation : dict
        The GeoTIFF creation profile of the output (rasterio keywords: ``count``, ``dtype``,
        ``blockxsize``, ``compress``, ``predictor``, ``ZSTD_LEVEL``, ``interleave``, ``nodata``,
        ``photometric``, ...) without its size, geotransform and CRS.
    tile : int
        Tile size (px).
    mask : bool
        The output stores validity as an internal mask (GDAL's per-dataset mask IFD).
    """

    creation: dict[str, Any] = field(repr=False)
    tile: int
    mask: bool

    @classmethod
    def from_profile(cls, profile: dict[str, Any], *, mask: bool) -> TileEncoder:
        """An encoder for the GeoTIFF that ``rasterio.open(path, "w", **profile)`` creates."""
        drop = {"width", "height", "transform", "crs", "driver", "sparse_ok", "num_threads", "bigtiff"}
        creation = {k: v for k, v in profile.items() if k.lower() not in drop}
        tile = int(profile["blockxsize"])
        if int(profile.get("blockysize", tile)) != tile:
            raise InvalidInputError(f"tile encoding needs square tiles; got {tile} x {profile['blockysize']}")
        comp = str(profile.get("compress", "none")).lower()
        if comp not in RAW_COMPRESSIONS:
            raise InvalidInputError(f"compression {comp!r} cannot be encoded tile by tile; expected one of "
                                    f"{list(RAW_COMPRESSIONS)}")
        return cls(creation, tile, bool(mask))

    @property
    def count(self) -> int:
        """Bands."""
        return int(self.creation["count"])

    @property
    def dtype(self) -> np.dtype:
        """Data type of the bands."""
        return np.dtype(self.creation["dtype"])

    def encode(self, data: NDArray, valid: NDArray[np.bool_] | None = None) -> EncodedTile:
        """Compress one output window (at most one tile) as the output GeoTIFF stores it.

        Parameters
        ----------
        data : (h, w, C) array
            The window, of the output's dtype and band count; h, w <= tile (smaller only at the
            right and bottom edges of the output).
        valid : (h, w) bool, optional
            With an internal-mask output: the mask (None: every pixel valid). Ignored otherwise
            (nodata and alpha outputs carry validity in ``data``).

        Returns
        -------
        EncodedTile

        Raises
        ------
        ShapeError
            A window larger than a tile or of the wrong band count.
        RasterIOError
            GDAL cannot encode it.
        """

        a = np.asarray(data)
        if a.ndim == 2:
            a = a[:, :, None]
        h, w = a.shape[:2]
        if a.ndim != 3 or a.shape[2] != self.count or not (0 < h <= self.tile and 0 < w <= self.tile):
            raise ShapeError(f"`data` must be (h, w, {self.count}) with h, w in 1..{self.tile}; got {np.shape(data)}",
                             actual_shape=np.shape(data), expected_shape=(None, None, self.count))
        try:
            with MemoryFile(ext=".tif") as mem, _no_georef_warning():
                # the window as a whole w x h GeoTIFF of one (partial) tile: GDAL pads and predicts an edge
                # tile exactly as in the full-size file (no geotransform: it only carries the tile's bytes)
                with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), \
                        mem.open(driver="GTiff", width=w, height=h, NUM_THREADS="1", **self.creation) as ds:
                    ds.write(np.moveaxis(a.astype(self.dtype, copy=False), -1, 0))
                    if self.mask:
                        m = np.full((h, w), 255, np.uint8) if valid is None else \
                            np.asarray(valid, dtype=bool).astype(np.uint8) * 255
                        ds.write_mask(m)
                return self._tiles(memoryview(mem.getbuffer()))
        except (RasterioError, OSError) as err:
            if isinstance(err, RasterIOError):
                raise
            raise RasterIOError(f"cannot encode a {w} x {h} tile in memory: {err}") from err

    def encode_window(self, result: tuple) -> tuple[NDArray[np.uint8], NDArray[np.uint8] | None, bool]:
        """Compress a window result of a tiled engine; runs where the window was computed.

        Parameters
        ----------
        result : tuple
            ``(data, valid, empty)`` (the warp engine) or ``(data, empty)`` (the orthophoto and mosaic
            engines): ``data`` (h, w, C), ``valid`` (h, w) bool or None, ``empty`` bool.

        Returns
        -------
        (tile, mask tile or None, empty)
            As :meth:`encode`, with the engine's ``empty`` flag.
        """
        if len(result) == 3:
            data, valid, empty = result
        elif len(result) == 2:
            (data, empty), valid = result, None
        else:
            raise InvalidInputError(f"a window result is (data, valid, empty) or (data, empty); got {len(result)} "
                                    "items")
        enc = self.encode(data, valid)
        return enc.data, enc.mask, bool(empty)

    def layout(self) -> tuple[tuple, tuple | None]:
        """The encoding tags (:attr:`TiffIfd.layout`) of the image IFD and the mask IFD (or None) of the
        GeoTIFFs this encoder makes, to compare with the output file's."""

        with MemoryFile(ext=".tif") as mem, _no_georef_warning():
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), \
                    mem.open(driver="GTiff", width=16, height=16, NUM_THREADS="1", SPARSE_OK="TRUE",
                             **self.creation) as ds:
                if self.mask:
                    ds.write_mask(np.zeros((16, 16), np.uint8))
            lay = read_tiff_layout(memoryview(mem.getbuffer()), name="encoder")
        return lay.image.layout, (lay.mask.layout if lay.mask is not None else None)

    def _tiles(self, buf: memoryview) -> EncodedTile:
        lay = read_tiff_layout(buf, name="encoded tile")
        mv = memoryview(buf).cast("B")

        def first_tile(d: TiffIfd) -> NDArray[np.uint8]:
            off = _first_value(mv, lay.byte_order, d.offsets)
            n = _first_value(mv, lay.byte_order, d.byte_counts)
            if n == 0:
                raise RasterIOError("GDAL wrote no tile for an encoded window")
            return np.frombuffer(bytes(mv[off:off + n]), dtype=np.uint8)

        mask = None
        if self.mask:
            if lay.mask is None:
                raise RasterIOError("GDAL wrote no internal mask for an encoded window")
            mask = first_tile(lay.mask)
        return EncodedTile(first_tile(lay.image), mask)


def _first_value(buf: memoryview, bo: str, arr: TileArray) -> int:
    return int(np.frombuffer(bytes(buf[arr.pos:arr.pos + arr.item_size]), dtype=f"{bo}u{arr.item_size}")[0])


def tile_index(col_off: int, row_off: int, tile: int, width: int) -> int:
    """Row-major index of the tile whose top-left pixel is (col_off, row_off) in a raster ``width`` px wide.

    Raises
    ------
    InvalidInputError
        The offsets are not on the tile grid.
    """
    if col_off % tile or row_off % tile or col_off < 0 or row_off < 0 or col_off >= width:
        raise InvalidInputError(f"window offset ({col_off}, {row_off}) is not on the {tile} px tile grid of a "
                                f"{width} px wide raster")
    return (row_off // tile) * -(-width // tile) + col_off // tile
