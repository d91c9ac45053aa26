"""Point clouds: LAS, LAZ and COPC with per-point extra dimensions (issue 27).

=========================================  ===============================================================
file (suffix)                              layout
=========================================  ===============================================================
``*.las``                                  LAS 1.4, point format 7 (x, y, z, RGB), extra bytes, CRS (WKT)
``*.laz``                                  the same, LAZ-compressed (laspy with the ``lazrs`` backend)
``*.copc.laz``                             the same as a Cloud Optimized Point Cloud (COPC 1.0): an octree
                                           of LAZ chunks (``copclib``, the optional ``copc`` extra)
=========================================  ===============================================================

Coordinates are stored as int32 counts of ``scale`` (default 0.001: one millimetre in a metric CRS)
from ``offset`` (a point near the data), so a cloud may span +-2147 km around its offset at the
default scale; a point outside that range is refused. The CRS is an OGC WKT VLR (EVLR in COPC) with
the WKT bit of the global encoding set. RGB is 16 bits per channel (LAS): 8-bit colours are scaled by
257 (255 -> 65535, as PDAL and OpenDroneMap write them), 16-bit ones (``color_bits=16``) are stored as
given; points written without colours have 0.

Extra dimensions (LAS 1.4 "extra bytes", each with a name and a description in the file):

=========  ========  ==================================================================================
name       type      meaning
=========  ========  ==================================================================================
sigma_z    float32   standard error of the point's height, CRS vertical units (metres); NaN: unknown
pair       uint16    index of the stereo pair the point comes from (the run's pair list, from 0)
count      uint16    number of pairs that agree on the point's height (fused points)
=========  ========  ==================================================================================

Other dimensions may be declared with :class:`ExtraDim`. Every declared dimension must be given for
every chunk of points; integer values must be integral and within the type's range.

:class:`LasWriter` streams: ``write`` appends a chunk (LAS/LAZ go straight to the file through
laspy). A COPC octree needs all points, so for ``.copc.laz`` the chunks go to a hidden uncompressed
LAS beside the output first; ``close`` builds the octree from it (memory-mapped records; about 60
bytes per point of coordinates and indices in memory up to :data:`COPC_BATCH` points, beyond that by
batches of whole octree nodes: :func:`_octree_streamed`) and writes the COPC through ``copclib``. :func:`write_cloud`
writes a whole cloud (an (N, 3) array or an iterable of :class:`CloudChunk`) atomically.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import signal
import struct
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import cast

import laspy
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_output, make_temp, write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError, ShapeError
from rectify.geometry.crs import parse_crs

try:  # the optional ``copc`` extra: COPC output only
    import copclib
except ImportError:  # pragma: no cover - depends on the installation
    copclib = None

logger = logging.getLogger(__name__)

__all__ = ["CLOUD_FORMATS", "EXTRA_DIMS", "CloudChunk", "ExtraDim", "LasWriter", "cloud_format", "copc_available",
           "laz_available", "write_cloud"]

StrPath = str | os.PathLike[str]

#: the output formats, by suffix
CLOUD_FORMATS = ("las", "laz", "copc")
#: LAS point format of every cloud: 7 (x, y, z, RGB; the LAS 1.4 formats, as COPC requires)
POINT_FORMAT = 7
#: COPC octree: grid cells per node side (one point per cell is kept at each level above the leaves)
COPC_GRID = 128
#: COPC octree: a node with at most this many points is a leaf
COPC_MAX_NODE = 100_000
#: COPC octree: the deepest level (a node of a 2000 km cloud is still 30 m wide)
COPC_MAX_DEPTH = 16
#: COPC octree: points per chunk of the per-point arithmetic (bounds its temporaries)
OCTREE_CHUNK = 1 << 20
#: COPC octree: a cloud of more points is built by batches of whole nodes of one level of at most this many
#: points (:func:`_octree_streamed`), so that the build's memory does not grow with the cloud
COPC_BATCH = 4_000_000
#: COPC octree: the deepest level of those batch nodes (a cell of every level above lies inside one of them)
COPC_PARTITION_DEPTH = 7


@dataclass(frozen=True)
class ExtraDim:
    """One extra dimension (LAS 1.4 extra bytes): a name (<= 32 characters), a numpy type, a description."""

    name: str
    dtype: str
    description: str

    def __post_init__(self) -> None:
        if not self.name or len(self.name) > 32 or not self.name.isascii():
            raise InvalidInputError(f"extra dimension name {self.name!r} must be 1 to 32 ASCII characters")
        if np.dtype(self.dtype).kind not in "uif" or np.dtype(self.dtype).itemsize > 8:
            raise InvalidInputError(f"extra dimension {self.name!r}: unsupported type {self.dtype!r}")
        if len(self.description) > 32 or not self.description.isascii():
            raise InvalidInputError(f"extra dimension {self.name!r}: the description must be <= 32 ASCII characters")


#: the project's extra dimensions (module docstring)
EXTRA_DIMS: dict[str, ExtraDim] = {
    "sigma_z": ExtraDim("sigma_z", "float32", "height standard error (m)"),
    "pair": ExtraDim("pair", "uint16", "source stereo pair index"),
    "count": ExtraDim("count", "uint16", "pairs agreeing on the height"),
}


@dataclass(frozen=True, eq=False)
class CloudChunk:
    """A chunk of points for :func:`write_cloud`: ``xyz`` (N, 3), ``colors`` (N, 3) (0..255, or 0..65535 with
    ``color_bits=16``) or None,
    ``extra`` name -> (N,) values of each declared extra dimension."""

    xyz: ArrayLike
    colors: ArrayLike | None = None
    extra: Mapping[str, ArrayLike] | None = None


def laz_available() -> bool:
    """Whether laspy has a LAZ backend (``lazrs`` or ``laszip``)."""
    return bool(laspy.LazBackend.detect_available())


def copc_available() -> bool:
    """Whether COPC can be written (``copclib`` installed; it compresses the chunks itself)."""
    return copclib is not None


#: the temporary name :func:`rectify.atomic.make_temp` gives a file: ``.<name>.<8 random><suffix>.part``
_TEMP_NAME = re.compile(r"\.(?P<dest>.+)\.[a-z0-9_]{8}(?:\.[^.]+)?\.part")


def cloud_format(path: StrPath) -> str:
    """``las``, ``laz`` or ``copc`` from the name of ``path`` (``.copc.laz`` is COPC; the temporary name of
    :func:`rectify.atomic.atomic_output` stands for its destination's); else a one-line error."""
    name = Path(path).name.lower()
    m = _TEMP_NAME.fullmatch(name)
    if m:
        name = m["dest"]
    if name.endswith(".copc.laz"):
        return "copc"
    suffix = Path(name).suffix.lstrip(".")
    if suffix in ("las", "laz"):
        return suffix
    raise InvalidInputError(f"unknown point cloud format of {str(path)!r}: expected a name ending in .las, .laz "
                            "or .copc.laz")


def _resolve_dims(extra_dims: Sequence[str | ExtraDim]) -> tuple[ExtraDim, ...]:
    dims = []
    for d in extra_dims:
        if isinstance(d, ExtraDim):
            dims.append(d)
        elif d in EXTRA_DIMS:
            dims.append(EXTRA_DIMS[d])
        else:
            raise InvalidInputError(f"unknown extra dimension {d!r}: expected one of {sorted(EXTRA_DIMS)} "
                                    "or an ExtraDim")
    names = [d.name for d in dims]
    if len(set(names)) != len(names):
        raise InvalidInputError(f"extra dimensions named twice: {names}")
    return tuple(dims)


def _check_backend(path: Path, fmt: str) -> None:
    if fmt == "laz" and not laz_available():
        raise InvalidInputError(f"cannot write {str(path)!r}: LAZ needs a laspy LAZ backend, none is installed "
                                "(pip install lazrs); write .las")
    if fmt == "copc" and not copc_available():
        raise InvalidInputError(f"cannot write {str(path)!r}: COPC needs the copclib package, not installed "
                                "(pip install copclib, or the rectify-stereo[copc] extra); write .laz")


def _las_header(offset: ArrayLike, scale: float, crs_wkt: str | None, dims: tuple[ExtraDim, ...]) -> laspy.LasHeader:
    off = np.asarray(offset, dtype=np.float64).reshape(-1)
    if off.shape != (3,) or not np.isfinite(off).all():
        raise InvalidInputError(f"the LAS offset must be 3 finite numbers; got {off.tolist()}")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"the LAS scale must be a positive number; got {scale!r}")
    header = laspy.LasHeader(point_format=POINT_FORMAT, version="1.4")
    header.offsets = off
    header.scales = np.array([scale, scale, scale], dtype=np.float64)
    if dims:
        header.add_extra_dims([laspy.ExtraBytesParams(d.name, d.dtype, description=d.description) for d in dims])
    if crs_wkt:
        try:
            crs = parse_crs(crs_wkt)
            try:
                header.add_crs(crs)
            except Exception:  # noqa: BLE001 - laspy wants an EPSG code: store the OGC WKT VLR directly
                header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(crs.to_wkt()))
                header.global_encoding.wkt = True
        except Exception as err:  # noqa: BLE001 - a CRS that cannot be stored is logged, not fatal
            logger.warning("CRS not stored in the point cloud: %s", err)
    return header


class LasWriter:
    """Stream points into a LAS, LAZ or COPC file: LAS 1.4, point format 7 (x, y, z, RGB), extra bytes.

    Parameters
    ----------
    path : path
        Written as given (the caller stages it, e.g. with :func:`rectify.atomic.atomic_output`).
    offset : (3,) float
        LAS offsets (a point near the data, CRS units).
    scale : float
        LAS scale of x, y and z (default 0.001: millimetres in a metric CRS).
    crs_wkt : str, optional
        Stored as an OGC WKT (E)VLR when given; a CRS that cannot be stored is logged, not fatal.
    compress : bool, optional
        Legacy switch: True writes LAZ, False LAS, whatever the suffix (``fmt`` wins when given).
    fmt : {"las", "laz", "copc"}, optional
        Default: from the name of ``path`` (:func:`cloud_format`); give it when ``path`` is a temporary name.
    extra_dims : sequence of str or ExtraDim
        Extra dimensions (``"sigma_z"``, ``"pair"``, ``"count"`` or :class:`ExtraDim`), given to every
        :meth:`write`.
    color_bits : {8, 16}
        The depth of the colours given to :meth:`write`: 8 (0..255, scaled by 257 to LAS's 16-bit RGB, as
        PDAL and OpenDroneMap do: 255 -> 65535) or 16 (0..65535, stored as given).

    Raises
    ------
    InvalidInputError
        Unknown format or extra dimension, bad offset or scale, LAZ/COPC without its backend.
    RasterIOError
        The file cannot be written.
    """

    def __init__(self, path: StrPath, offset: ArrayLike, *, scale: float = 0.001, crs_wkt: str | None = None,
                 compress: bool | None = None, fmt: str | None = None,
                 extra_dims: Sequence[str | ExtraDim] = (), color_bits: int = 8):
        self.path = Path(path)
        if color_bits not in (8, 16):
            raise InvalidInputError(f"`color_bits` must be 8 or 16; got {color_bits!r}")
        self.color_bits = color_bits
        if fmt is None:
            fmt = ("laz" if compress else "las") if compress is not None else cloud_format(self.path)
        if fmt not in CLOUD_FORMATS:
            raise InvalidInputError(f"unknown point cloud format {fmt!r}: expected one of {list(CLOUD_FORMATS)}")
        self.fmt = fmt
        self.dims = _resolve_dims(extra_dims)
        _check_backend(self.path, fmt)
        self._header = _las_header(offset, scale, crs_wkt, self.dims)
        self._crs_wkt = crs_wkt
        self._stage: Path | None = make_temp(self.path, ".stage.las") if fmt == "copc" else None
        target = self._stage if self._stage is not None else self.path
        try:
            self._w = laspy.open(str(target), mode="w", header=self._header, do_compress=fmt == "laz")
        except OSError as err:
            self._drop_stage()
            raise RasterIOError(f"cannot write {str(self.path)!r}: {write_failure_reason(err, self.path)}") from err
        self.count = 0
        self._closed = False

    # ---------------------------------------------------------------- writing
    def write(self, xyz: ArrayLike, colors: ArrayLike | None = None,
              extra: Mapping[str, ArrayLike] | None = None) -> None:
        """Append points: ``xyz`` (N, 3) finite, ``colors`` (N, 3) 0..255 (``color_bits`` 8; x 257 to 16 bits)
        or 0..65535 (16), rounded and clipped to that range, ``extra`` name -> (N,)."""
        p = np.asarray(xyz, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ShapeError(f"points must have shape (N, 3); got {p.shape}", actual_shape=p.shape,
                             expected_shape=(None, 3))
        bad = ~np.isfinite(p).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidInputError(f"points must be finite: point {self.count + i} is {p[i].tolist()}")
        values = self._extra_values(len(p), extra)
        c = None
        if colors is not None:
            c = np.asarray(colors)
            if c.shape != (len(p), 3):
                raise ShapeError(f"colors must have shape ({len(p)}, 3); got {c.shape}", actual_shape=c.shape,
                                 expected_shape=(len(p), 3))
            top = 255 if self.color_bits == 8 else 65535
            c = np.clip(np.rint(np.nan_to_num(c.astype(np.float64))), 0, top).astype(np.uint16)
            c = c * np.uint16(65535 // top)
        if len(p) == 0:
            return
        h = self._header
        q = np.rint((p - h.offsets) / h.scales)
        lim = float(np.iinfo(np.int32).max)
        far = (np.abs(q) > lim).any(axis=1)
        if far.any():
            i = int(np.flatnonzero(far)[0])
            raise InvalidInputError(f"point {self.count + i} {p[i].tolist()} is out of the LAS range: more than "
                                    f"{lim * float(h.scales[0]):.0f} units from the offset {h.offsets.tolist()} "
                                    f"at scale {float(h.scales[0])}")
        rec = laspy.ScaleAwarePointRecord.zeros(len(p), header=h)
        rec.X, rec.Y, rec.Z = q[:, 0].astype(np.int32), q[:, 1].astype(np.int32), q[:, 2].astype(np.int32)
        if c is not None:
            rec.red, rec.green, rec.blue = c[:, 0], c[:, 1], c[:, 2]
        for name, v in values.items():
            rec[name] = v
        try:
            self._w.write_points(rec)
        except (OSError, RuntimeError) as err:  # RuntimeError: lazrs.LazrsError (e.g. "Failed to call write")
            raise RasterIOError(f"cannot write {str(self.path)!r}: {write_failure_reason(err, self.path)}") from err
        self.count += len(p)

    def _extra_values(self, n: int, extra: Mapping[str, ArrayLike] | None) -> dict[str, NDArray]:
        given = dict(extra or {})
        declared = {d.name: d for d in self.dims}
        unknown = sorted(set(given) - set(declared))
        if unknown:
            raise InvalidInputError(f"extra dimension(s) {unknown} not declared: this cloud has "
                                    f"{sorted(declared) or 'none'} (pass extra_dims=)")
        out = {}
        for name, d in declared.items():
            if name not in given:
                raise InvalidInputError(f"extra dimension {name!r} missing from the chunk (every chunk gives "
                                        f"{sorted(declared)})")
            v = np.asarray(given[name]).reshape(-1)
            if v.shape != (n,):
                raise ShapeError(f"extra dimension {name!r} has {v.shape[0]} values for {n} points",
                                 actual_shape=v.shape, expected_shape=(n,))
            t = np.dtype(d.dtype)
            if t.kind in "ui":
                vf = v.astype(np.float64)
                info = np.iinfo(t)
                bad = ~np.isfinite(vf) | (vf != np.round(vf)) | (vf < info.min) | (vf > info.max)
                if bad.any():
                    i = int(np.flatnonzero(bad)[0])
                    raise InvalidInputError(f"extra dimension {name!r} ({t.name}): value {v[i].item()!r} of point "
                                            f"{self.count + i} is not an integer in {info.min}..{info.max}")
                out[name] = vf.astype(t)
            else:
                vf = v.astype(np.float64)
                if np.isinf(vf).any() or (np.abs(vf[np.isfinite(vf)]) > np.finfo(t).max).any():
                    raise InvalidInputError(f"extra dimension {name!r} ({t.name}): infinite or out-of-range value")
                out[name] = vf.astype(t)
        return out

    # ---------------------------------------------------------------- closing
    def close(self) -> None:
        """Finish the file (COPC: build the octree and write it); the staging file is removed in any case."""
        if self._closed:
            return
        self._closed = True
        try:
            self._w.close()
        except (OSError, RuntimeError) as err:  # RuntimeError: lazrs.LazrsError
            self._release()
            self._drop_stage()
            raise RasterIOError(f"cannot write {str(self.path)!r}: {write_failure_reason(err, self.path)}") from err
        if self._stage is not None:
            try:
                _write_copc(self._stage, self.path, self._crs_wkt)
            finally:
                self._drop_stage()

    def abort(self) -> None:
        """Stop without finishing: the staging file is removed (the output path is the caller's to remove)."""
        if not self._closed:
            self._closed = True
            with contextlib.suppress(Exception):
                self._w.close()
            self._release()
        self._drop_stage()

    def _release(self) -> None:
        """Close the file laspy holds (its ``close`` stops before that when a flush fails, e.g. a full disk)."""
        dest = getattr(self._w, "dest", None)
        if dest is not None:
            with contextlib.suppress(Exception):
                dest.close()

    def _drop_stage(self) -> None:
        if self._stage is not None:
            self._stage.unlink(missing_ok=True)

    def __enter__(self) -> LasWriter:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is None:
            self.close()
        else:
            self.abort()


# ---------------------------------------------------------------------- COPC
def _octree(X: NDArray[np.int32], Y: NDArray[np.int32], Z: NDArray[np.int32]
            ) -> tuple[NDArray[np.float64], float, list[tuple[tuple[int, int, int, int], NDArray[np.integer]]]]:
    """The COPC octree of integer LAS coordinates: (cube centre in counts, half size in counts, nodes).

    Each level keeps one point per cell of a ``COPC_GRID``-cell grid of each node (the first in file
    order) and passes the rest down; a node of at most ``COPC_MAX_NODE`` points, or one at the
    deepest level (:data:`COPC_MAX_DEPTH`, or where a cell would be smaller than a count), keeps all of
    its points. Every node with points has a parent with points, and each point lies inside its node's cube.
    Memory: the point indices are int32 (below 2**31 points) and the per-point arithmetic runs by chunks of
    :data:`OCTREE_CHUNK` points: about 45 bytes per point besides the coordinates (measured on 4 million
    points of a grid; 57 on 1 million, where one chunk is the whole cloud).
    """
    lo = np.array([X.min(), Y.min(), Z.min()], dtype=np.float64)
    hi = np.array([X.max(), Y.max(), Z.max()], dtype=np.float64)
    centre, half, max_depth = _cube(lo, hi)
    return centre, half, _octree_nodes(X, Y, Z, centre - half, 2 * half, max_depth)


def _cube(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.float64], float, int]:
    """The octree's cube about the bounds ``lo``, ``hi`` (counts): centre, half size, deepest level."""
    centre = (lo + hi) / 2
    half = float((hi - lo).max()) / 2 + 1.0
    max_depth = max(0, min(COPC_MAX_DEPTH, math.ceil(math.log2(max(2 * half / COPC_GRID, 1.0)))))
    return centre, half, max_depth


def _octree_nodes(X: NDArray[np.int32], Y: NDArray[np.int32], Z: NDArray[np.int32], corner: NDArray[np.float64],
                  side: float, max_depth: int, sample_above: int = 0
                  ) -> list[tuple[tuple[int, int, int, int], NDArray[np.integer]]]:
    """The nodes of :func:`_octree` in the cube of ``corner`` and ``side`` (counts); the levels above
    ``sample_above`` keep one point per cell whatever their nodes' counts (:func:`_octree_streamed`)."""
    axes = ((X, corner[0]), (Y, corner[1]), (Z, corner[2]))
    itype = np.int32 if len(X) < np.iinfo(np.int32).max else np.int64
    rem = np.arange(len(X), dtype=itype)
    nodes: list[tuple[tuple[int, int, int, int], NDArray[np.integer]]] = []
    m19 = (1 << 19) - 1
    for d in range(max_depth + 1):
        if rem.size == 0:
            break
        n = 1 << d
        # node of each remaining point (x << 38 | y << 19 | z)
        nkey = np.zeros(len(rem), np.int64)
        for (A, c0), shift in zip(axes, (38, 19, 0), strict=True):
            _add_index(nkey, A, c0, rem, None, n / side, n, shift, 0)
        order = np.argsort(nkey, kind="stable")
        sk = nkey[order]
        new = np.empty(len(rem), bool)
        new[0] = True
        np.not_equal(sk[1:], sk[:-1], out=new[1:])
        del sk
        rank = np.empty(len(rem), itype)
        rank[order] = np.cumsum(new, dtype=itype) - 1       # node number of each point
        del order, new
        if d < sample_above:
            take = np.zeros(len(rem), bool)
        elif d < max_depth:
            take = (np.bincount(rank) <= COPC_MAX_NODE)[rank]
        else:
            take = np.ones(len(rem), bool)
        big = np.flatnonzero(~take).astype(itype)
        if big.size:
            # one point per cell of the node's COPC_GRID^3 grid: the first in file order
            cell = rank[big].astype(np.int64) << 21
            for (A, c0), shift in zip(axes, (14, 7, 0), strict=True):
                _add_index(cell, A, c0, rem, big, n * COPC_GRID / side, n, shift, COPC_GRID)
            o = np.argsort(cell, kind="stable")             # within a cell: file order
            sc = cell[o]
            del cell
            first = np.empty(len(o), bool)
            first[0] = True
            np.not_equal(sc[1:], sc[:-1], out=first[1:])
            del sc
            take[big[o[first]]] = True
            del o, first
        del big, rank
        tk, ti = nkey[take], rem[take]
        rem = rem[~take]
        del nkey, take
        o = np.argsort(tk, kind="stable")
        tk, ti = tk[o], ti[o]
        starts = np.flatnonzero(np.r_[True, tk[1:] != tk[:-1]])
        for s, e in zip(starts, np.r_[starts[1:], len(tk)], strict=True):
            k = int(tk[s])
            nodes.append(((d, (k >> 38) & m19, (k >> 19) & m19, k & m19), ti[s:e]))
    return nodes


def _octree_streamed(X: NDArray[np.int32], Y: NDArray[np.int32], Z: NDArray[np.int32], scratch: Path
                     ) -> tuple[NDArray[np.float64], float, NDArray[np.float64], NDArray[np.float64],
                                Iterator[tuple[tuple[int, int, int, int], NDArray[np.int64]]]]:
    """A COPC octree built by batches: (centre, half size, lo, hi (counts), nodes (key, point indices)).

    ``X``, ``Y``, ``Z``: the coordinates (counts), read by chunks and by index (e.g. the fields of a
    memory-mapped LAS). The cube is split into the nodes of the shallowest level P (at most
    :data:`COPC_PARTITION_DEPTH`) that holds at most :data:`COPC_BATCH` points per node; whole nodes are
    grouped into batches of at most that many points (a node of more is a batch of its own), whose point
    indices are written to the file ``<scratch>.octree``, grouped by batch, in one pass (8 bytes per
    point on disk) and read back one batch at a time. Each batch is built in memory as :func:`_octree`
    does; at the levels above P each keeps one point per cell of its node's grid (a cell of such a level
    lies inside one node of level P, so the first point of each cell in file order is the same as in one
    build), and those points are gathered over the batches and yielded last. Unlike :func:`_octree`, a
    node above P of at most :data:`COPC_MAX_NODE` points does not keep all of them. Memory: one batch
    (about 60 bytes per point) and the points of the levels above P. The file is removed after the last
    batch (and by the caller on an error: :func:`_drop_octree_files`).
    """
    n_pts = len(X)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(0, n_pts, OCTREE_CHUNK):
        for a, A in enumerate((X, Y, Z)):
            c = np.asarray(A[i:i + OCTREE_CHUNK])
            lo[a], hi[a] = min(lo[a], float(c.min())), max(hi[a], float(c.max()))
    centre, half, max_depth = _cube(lo, hi)
    corner, side = centre - half, 2 * half
    part, counts = 0, np.zeros(1, np.int64)
    first = max(1, math.ceil(math.log(max(n_pts / COPC_BATCH, 1.0), 8)))   # fewer nodes cannot hold the points
    for p in range(min(first, COPC_PARTITION_DEPTH, max_depth), min(COPC_PARTITION_DEPTH, max_depth) + 1):
        counts = np.zeros(8 ** p, np.int64)
        for i in range(0, n_pts, OCTREE_CHUNK):
            counts += np.bincount(_partition_keys(X, Y, Z, i, p, corner, side), minlength=8 ** p)
        part = p
        if counts.max() <= COPC_BATCH:
            break
    if part == 0:   # a cube of less than one grid: one node, built in memory
        nodes = _octree_nodes(np.asarray(X), np.asarray(Y), np.asarray(Z), corner, side, max_depth)
        return centre, half, lo, hi, iter([(k, np.asarray(v, np.int64)) for k, v in nodes])
    batch_of = np.zeros(len(counts), np.int64)
    b, acc = 0, 0
    for k in np.flatnonzero(counts):
        if acc and acc + counts[k] > COPC_BATCH:
            b, acc = b + 1, 0
        batch_of[k] = b
        acc += int(counts[k])
    # the point indices grouped by batch, in file order within each, in one file (8 bytes per point)
    size = np.bincount(batch_of, weights=counts, minlength=b + 1).astype(np.int64)
    start = np.r_[0, np.cumsum(size)[:-1]]
    pos = start.copy()
    index_file = Path(f"{scratch}.octree")
    with open(index_file, "wb") as fh:
        fh.truncate(8 * n_pts)
        for i in range(0, n_pts, OCTREE_CHUNK):
            bk = batch_of[_partition_keys(X, Y, Z, i, part, corner, side)]
            o = np.argsort(bk, kind="stable")
            sb = bk[o]
            starts = np.flatnonzero(np.r_[True, sb[1:] != sb[:-1]])
            for s, e in zip(starts, np.r_[starts[1:], len(sb)], strict=True):
                kb = int(sb[s])
                data = (i + o[s:e]).astype("<i8").tobytes()
                done = 0
                while done < len(data):   # pwrite may write less (a full disk: then it raises)
                    done += os.pwrite(fh.fileno(), data[done:], 8 * int(pos[kb]) + done)
                pos[kb] += e - s
    if not np.array_equal(pos, start + size):  # pragma: no cover - the two passes agree by construction
        raise RasterIOError(f"cannot write the COPC octree of {str(scratch)!r}: inconsistent batch sizes")

    def nodes_by_batch() -> Iterator[tuple[tuple[int, int, int, int], NDArray[np.int64]]]:
        upper: dict[tuple[int, int, int, int], list[NDArray[np.int64]]] = {}
        for k in range(b + 1):
            ids = np.fromfile(index_file, dtype="<i8", count=int(size[k]), offset=8 * int(start[k])).astype(np.int64)
            if k == b:
                index_file.unlink()
            for key, sel in _octree_nodes(np.asarray(X[ids]), np.asarray(Y[ids]), np.asarray(Z[ids]), corner, side,
                                          max_depth, sample_above=part):
                if key[0] < part:
                    upper.setdefault(key, []).append(ids[sel])
                else:
                    yield key, ids[sel]
        for key in sorted(upper):
            yield key, np.sort(np.concatenate(upper.pop(key)))

    return centre, half, lo, hi, nodes_by_batch()


def _partition_keys(X: NDArray[np.int32], Y: NDArray[np.int32], Z: NDArray[np.int32], i: int, p: int,
                    corner: NDArray[np.float64], side: float) -> NDArray[np.int64]:
    """The level-``p`` node (x 4^p + y 2^p + z) of the points ``i`` to ``i + OCTREE_CHUNK``, computed as
    :func:`_octree_nodes` computes it."""
    n = 1 << p
    key = np.zeros(len(X[i:i + OCTREE_CHUNK]), np.int64)
    for A, c0 in ((X, corner[0]), (Y, corner[1]), (Z, corner[2])):
        g = np.floor((np.asarray(A[i:i + OCTREE_CHUNK]) - c0) * (n / side)).astype(np.int64)
        key = key * n + np.clip(g, 0, n - 1)
    return key


def _drop_octree_files(scratch: Path) -> None:
    """Remove the index file of :func:`_octree_streamed` left by a failure."""
    Path(f"{scratch}.octree").unlink(missing_ok=True)


def _add_index(key: NDArray[np.int64], A: NDArray[np.int32], c0: float, rem: NDArray[np.integer],
               sel: NDArray[np.integer] | None, scale: float, n: int, shift: int, grid: int) -> None:
    """``key |= index << shift`` for the points ``rem`` (or ``rem[sel]``), by chunks of :data:`OCTREE_CHUNK`:
    the index ``floor((A - c0) scale)`` clipped to the ``n`` nodes of a level (``grid`` 0), or the cell in
    its node of a ``grid``-cell grid per node."""
    m = len(key)
    for i in range(0, m, OCTREE_CHUNK):
        idx = rem[i:i + OCTREE_CHUNK] if sel is None else rem[sel[i:i + OCTREE_CHUNK]]
        g = np.floor((A[idx] - c0) * scale).astype(np.int64)
        g = np.clip(g - np.clip(g // grid, 0, n - 1) * grid, 0, grid - 1) if grid else np.clip(g, 0, n - 1)
        key[i:i + OCTREE_CHUNK] |= g << shift


_VLR_HEADER = struct.Struct("<H16sHH32s")


def _fix_extra_bytes_vlr(path: Path, header: laspy.LasHeader) -> None:
    """Replace copclib's untyped extra-bytes VLR (one ``FIELD_k`` byte per extra byte) in place by the typed,
    named descriptors of ``header``; the spare bytes become a padding VLR so that no offset moves.

    copclib's own statistics VLR (user ``copc``, record 10000, not part of COPC 1.0) counts one entry per
    extra byte; it is renamed to a padding VLR too, so that no reader takes it for the new layout.
    """
    ebv = next((v for v in header.vlrs if isinstance(v, laspy.vlrs.known.ExtraBytesVlr)), None)
    if ebv is None:
        return
    ours = ebv.record_data_bytes()
    found = False
    with open(path, "r+b") as fh:
        head = fh.read(375)
        header_size, = struct.unpack_from("<H", head, 94)
        n_vlrs, = struct.unpack_from("<I", head, 100)
        added = 0
        pos = header_size
        for _ in range(n_vlrs):
            fh.seek(pos)
            _, user, rid, length, _ = _VLR_HEADER.unpack(fh.read(54))
            user = user.rstrip(b"\0")
            if user == b"copc" and rid == 10000:
                fh.seek(pos)
                fh.write(_VLR_HEADER.pack(0, b"rectify-stereo", 2, length, b"padding (copclib statistics)"))
            elif user == b"LASF_Spec" and rid == 4:
                spare = length - len(ours)
                if spare < 0 or 0 < spare < 54:
                    raise RasterIOError(f"cannot write {str(path)!r}: unexpected extra-bytes layout from copclib")
                fh.seek(pos)
                fh.write(_VLR_HEADER.pack(0, b"LASF_Spec", 4, len(ours), b"extra bytes"))
                fh.write(ours)
                if spare:
                    fh.write(_VLR_HEADER.pack(0, b"rectify-stereo", 1, spare - 54, b"padding"))
                    fh.write(b"\0" * (spare - 54))
                    added = 1
                found = True
            pos += 54 + length
        if added:
            fh.seek(100)
            fh.write(struct.pack("<I", n_vlrs + added))
    if not found:
        raise RasterIOError(f"cannot write {str(path)!r}: copclib wrote no extra-bytes VLR")


def _write_copc(stage: Path, path: Path, crs_wkt: str | None) -> None:
    """Build the COPC octree of the staged LAS ``stage`` and write it to ``path`` (copclib).

    copclib's writer throws from its C++ destructor when a write has failed (a full disk: "Chunk is
    too large!", then "LasHeader + VLRs are bigger than offset to point data"), which aborts the whole
    process. Where the system can fork, the copclib part therefore runs in a child process that
    reports a failure through a pipe and leaves with ``os._exit`` before any destructor runs.
    """
    with laspy.open(str(stage)) as rd:
        header = rd.header
    try:
        _copc_in_child(stage, path, crs_wkt, header)
    finally:
        _drop_octree_files(stage)
    if header.point_format.num_extra_bytes:
        _fix_extra_bytes_vlr(path, header)


def _copc_in_child(stage: Path, path: Path, crs_wkt: str | None, header: laspy.LasHeader) -> None:
    """:func:`_copc_body` in a forked child process where the system can fork (:func:`_write_copc`)."""
    if not hasattr(os, "fork"):  # pragma: no cover - not POSIX
        _copc_body(stage, path, crs_wkt, header)
    else:
        rfd, wfd = os.pipe()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child (its coverage is not collected)
            os.close(rfd)
            try:
                _copc_body(stage, path, crs_wkt, header)
            except BaseException as err:  # noqa: BLE001 - reported to the parent, then leave at once
                os.write(wfd, write_failure_reason(err, path).encode("utf-8", "replace")[:4000])
                os._exit(1)
            os._exit(0)
        os.close(wfd)
        try:
            with os.fdopen(rfd, "rb") as fh:
                reason = fh.read().decode("utf-8", "replace").strip()
            _, status = os.waitpid(pid, 0)
        except BaseException:   # SIGTERM or Ctrl-C while waiting: stop the child before the files are removed
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
            raise
        code = os.waitstatus_to_exitcode(status)
        if code != 0:
            reason = reason or f"copclib failed (exit status {code})"
            if "no space left" not in reason:
                reason = write_failure_reason(RuntimeError(reason), path)
            raise RasterIOError(f"cannot write {str(path)!r}: {reason}")


def _copc_body(stage: Path, path: Path, crs_wkt: str | None, header: laspy.LasHeader) -> None:
    """The copclib part of :func:`_write_copc` (raises on any failure)."""
    assert copclib is not None
    n = int(header.point_count)
    rec_dtype = header.point_format.dtype()
    scales, offsets = [float(s) for s in header.scales], [float(o) for o in header.offsets]
    wkt = ""
    if crs_wkt:
        with contextlib.suppress(Exception):  # as in the LAS: a CRS that cannot be stored is not fatal
            wkt = parse_crs(crs_wkt).to_wkt()
    cfg = copclib.CopcConfigWriter(POINT_FORMAT, copclib.Vector3(*scales), copclib.Vector3(*offsets), wkt,
                                   copclib.EbVlr(int(header.point_format.num_extra_bytes)))
    w = copclib.FileWriter(str(path), cfg)
    if n:
        recs = np.memmap(stage, dtype=rec_dtype, mode="r", offset=int(header.offset_to_point_data), shape=(n,))
        nodes: Iterable[tuple[tuple[int, int, int, int], NDArray[np.integer]]]
        if n <= COPC_BATCH:
            X, Y, Z = np.array(recs["X"]), np.array(recs["Y"]), np.array(recs["Z"])
            centre, half, nodes = _octree(X, Y, Z)
            lo = np.array([X.min(), Y.min(), Z.min()]) * scales + offsets
            hi = np.array([X.max(), Y.max(), Z.max()]) * scales + offsets
            del X, Y, Z
        else:   # by batches, in bounded memory
            centre, half, lo_c, hi_c, nodes = _octree_streamed(recs["X"], recs["Y"], recs["Z"], stage)
            lo, hi = lo_c * scales + offsets, hi_c * scales + offsets
        h = w.copc_config.las_header
        h.min, h.max = copclib.Vector3(*lo.tolist()), copclib.Vector3(*hi.tolist())
        info = w.copc_config.copc_info
        c = centre * scales + offsets
        info.center_x, info.center_y, info.center_z = (float(v) for v in c)
        info.halfsize = half * scales[0]
        info.spacing = 2 * half * scales[0] / COPC_GRID
        for (d, x, y, z), sel in nodes:
            data = np.ascontiguousarray(recs[np.sort(sel)]).view(np.int8)
            w.AddNode(copclib.VoxelKey(d, x, y, z), copclib.VectorChar(data))
        del recs
    w.Close()


# ---------------------------------------------------------------------- whole clouds
def write_cloud(path: StrPath, xyz: ArrayLike | Iterable[CloudChunk], *, colors: ArrayLike | None = None,
                extra: Mapping[str, ArrayLike] | None = None, extra_dims: Sequence[str | ExtraDim] | None = None,
                crs_wkt: str | None = None, offset: ArrayLike | None = None, scale: float = 0.001,
                fmt: str | None = None, overwrite: bool = False, color_bits: int = 8) -> Path:
    """Write a point cloud (LAS, LAZ or COPC by the name of ``path``) atomically; return ``path``.

    Parameters
    ----------
    path : path
        ``*.las``, ``*.laz`` or ``*.copc.laz`` (or give ``fmt``); replaced only with ``overwrite``.
    xyz : (N, 3) array_like, or iterable of CloudChunk
        The points (CRS units), whole or as chunks (streamed: only one chunk in memory at a time for
        LAS and LAZ).
    colors : (N, 3) array_like, optional
        0..255 per channel, stored x 257 as LAS's 16-bit RGB (whole clouds only; chunks carry their own);
        0..65535, stored as given, with ``color_bits=16``.
    extra : mapping name -> (N,) array_like, optional
        Extra dimension values (whole clouds only). Their names declare the dimensions unless
        ``extra_dims`` does (required with chunks that carry extra values).
    extra_dims : sequence of str or ExtraDim, optional
        The declared extra dimensions (:data:`EXTRA_DIMS` names or :class:`ExtraDim`).
    crs_wkt : str, optional
        The CRS (any form :func:`rectify.geometry.crs.parse_crs` reads), stored as OGC WKT.
    offset : (3,) array_like, optional
        Default: the minimum of a whole cloud rounded down to whole units, else the first point of the
        first chunk rounded.
    scale : float
        Default 0.001 (millimetres).

    Raises
    ------
    InvalidInputError, ShapeError
        Unknown format, non-finite points, extra values of the wrong length or type, a missing backend.
    RasterIOError
        The file cannot be written. Nothing is left at ``path`` on any error.
    """
    p = Path(path)
    f = fmt if fmt is not None else cloud_format(p)
    if f not in CLOUD_FORMATS:
        raise InvalidInputError(f"unknown point cloud format {f!r}: expected one of {list(CLOUD_FORMATS)}")
    _check_backend(p, f)
    if isinstance(xyz, np.ndarray) or (isinstance(xyz, (list, tuple)) and not any(isinstance(c, CloudChunk)
                                                                                  for c in xyz)):
        chunks: Iterable[CloudChunk] = [CloudChunk(xyz, colors, extra)]
        arr = np.asarray(xyz, dtype=np.float64)
        if offset is None and arr.ndim == 2 and arr.shape[1] == 3 and len(arr) and np.isfinite(arr).all():
            offset = np.floor(arr.min(axis=0))
        dims = extra_dims if extra_dims is not None else list(_names_as_dims(extra or {}))
    else:
        if colors is not None or extra is not None:
            raise InvalidInputError("with chunks, give colors and extra values in each CloudChunk")
        chunks = cast(Iterable[CloudChunk], xyz)
        dims = extra_dims if extra_dims is not None else ()
    with atomic_output(p, overwrite=overwrite, suffix=".part") as tmp:
        writer: LasWriter | None = None
        try:
            for ch in chunks:
                if not isinstance(ch, CloudChunk):
                    raise InvalidInputError(f"chunks must be CloudChunk objects; got {type(ch).__name__}")
                if writer is None:
                    if offset is None:
                        first = np.asarray(ch.xyz, dtype=np.float64).reshape(-1)[:3]
                        offset = np.round(first) if first.size == 3 and np.isfinite(first).all() else np.zeros(3)
                    writer = LasWriter(tmp, offset, scale=scale, crs_wkt=crs_wkt, fmt=f, extra_dims=dims,
                                       color_bits=color_bits)
                writer.write(ch.xyz, ch.colors, ch.extra)
            if writer is None:
                writer = LasWriter(tmp, np.zeros(3) if offset is None else offset, scale=scale, crs_wkt=crs_wkt, fmt=f,
                                   extra_dims=dims, color_bits=color_bits)
            writer.close()
        except BaseException:
            if writer is not None:
                writer.abort()
            raise
    return p


def _names_as_dims(extra: Mapping[str, ArrayLike]) -> Iterable[str | ExtraDim]:
    for name, v in extra.items():
        if name in EXTRA_DIMS:
            yield name
        else:
            kind = np.asarray(v).dtype
            yield ExtraDim(name, "float32" if kind.kind == "f" else kind.name, name[:32])
