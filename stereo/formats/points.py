"""Point files: the one PLY writer and reader, the LAS/LAZ writer, the points CSV.

=========================================  ==============================================  =======
artefact (default names)                   layout                                          version
=========================================  ==============================================  =======
points PLY (``points.ply``,                binary little-endian PLY: float64 x, y, z         --
``model_points.ply``, dense ``points.ply``) (+ uchar red, green, blue), comment = frame
dense point cloud (``points.las/.laz``)    LAS 1.4 point format 7 (x, y, z, RGB), extra      --
                                           bytes, CRS (:mod:`stereo.formats.cloud`)
points CSV (``points.csv``)                ``id,x,y,z,residual_mm[,std_x,std_y,std_z]``     --
=========================================  ==============================================  =======

A PLY is written whole (:func:`dump_ply`, :func:`write_ply`: the points in memory) or streamed by
tiles (:class:`PlyWriter`: the body goes to a temporary file first, the header, which needs the
count, is written at the end); both give the same bytes for the same points. :class:`LasWriter`
(LAS, LAZ and COPC with extra dimensions) lives in :mod:`stereo.formats.cloud` and is re-exported
here. :func:`point_writer` picks the streaming writer from the format.

As in :mod:`stereo.formats.orientation`, ``dump_*`` writes to a path as given (a temporary path of a
workspace transaction) and ``write_*`` writes atomically on its own, refusing to replace a file
without ``overwrite``. The fields, units and frames are documented in ``docs/formats.md``.
"""

from __future__ import annotations

import csv
import io
import logging
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_output, write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError, ShapeError
from stereo.formats.cloud import CLOUD_FORMATS, ExtraDim, LasWriter, cloud_format

logger = logging.getLogger(__name__)

__all__ = [
    "LasWriter",
    "PlyWriter",
    "PointCloud",
    "PointsTable",
    "dump_ply",
    "dump_points_csv",
    "point_writer",
    "points_csv_text",
    "read_ply",
    "read_ply_xyz",
    "read_points_csv",
    "write_ply",
    "write_points_csv",
]

StrPath = str | os.PathLike[str]


def _write_file(path: StrPath, data: str | bytes) -> None:
    """Write text (UTF-8) or bytes to ``path`` as given; failures become :class:`RasterIOError`."""
    try:
        if isinstance(data, str):
            with open(path, "w", encoding="utf-8") as fh:
                fh.write(data)
        else:
            with open(path, "wb") as fh:
                fh.write(data)
    except OSError as err:
        raise RasterIOError(f"cannot write {str(path)!r}: {write_failure_reason(err, path)}") from err


def _check_xyz(xyz: ArrayLike, colors: ArrayLike | None) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None]:
    p = np.asarray(xyz, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError(f"points must have shape (N, 3); got {p.shape}", actual_shape=p.shape,
                         expected_shape=(None, 3))
    if not np.isfinite(p).all():
        raise InvalidInputError("points must be finite (NaN or inf given)")
    c = None
    if colors is not None:
        c = np.asarray(colors)
        if c.shape != (len(p), 3):
            raise ShapeError(f"colors must have shape ({len(p)}, 3); got {c.shape}", actual_shape=c.shape,
                             expected_shape=(len(p), 3))
        c = np.clip(c, 0, 255).astype(np.uint8)
    return p, c


# ---------------------------------------------------------------------- PLY
@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points read from a PLY file.

    Attributes
    ----------
    xyz : (N, 3) float64
        Ground coordinates (map CRS of the control, or the model frame, as ``comment`` says).
    colors : (N, 3) uint8 or None
    comments : tuple of str
        The header's comment lines (``"ground"`` or ``"model frame"`` for this project's files).
    """

    xyz: NDArray[np.float64]
    colors: NDArray[np.uint8] | None = None
    comments: tuple[str, ...] = ()


def _ply_header(n: int, comment: str | None, colors: bool) -> bytes:
    """The header of a binary little-endian PLY of ``n`` vertices (float64 x, y, z; uchar red, green, blue)."""
    head = ["ply", "format binary_little_endian 1.0"]
    if comment:
        head.append(f"comment {comment}")
    head += [f"element vertex {n}", "property double x", "property double y", "property double z"]
    if colors:
        head += ["property uchar red", "property uchar green", "property uchar blue"]
    head.append("end_header")
    return ("\n".join(head) + "\n").encode("ascii")


def _ply_body(xyz: NDArray[np.float64], rgb: NDArray[np.uint8] | None, colors: bool) -> bytes:
    """The vertex records of :func:`_ply_header` (with ``colors``: ``rgb`` (N, 3), zeros when None)."""
    dt = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors:
        dt += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.zeros(len(xyz), dtype=dt)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if colors and rgb is not None:
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    return rec.tobytes()


def dump_ply(path: StrPath, xyz: ArrayLike, *, colors: ArrayLike | None = None, comment: str | None = None) -> None:
    """Write a binary little-endian PLY (float64 x, y, z; uchar red, green, blue) to ``path`` as given.

    ``colors`` (N, k): the first three columns, clipped to 0..255 (one column: grey); without it the
    file has no colour properties.
    """
    p = np.asarray(xyz, dtype="<f8").reshape(-1, 3)
    rgb = None
    if colors is not None:
        c = np.asarray(colors).reshape(len(p), -1)
        rgb = np.column_stack([np.clip(c[:, min(k, c.shape[1] - 1)], 0, 255).astype("u1") for k in range(3)])
    _write_file(path, _ply_header(len(p), comment, colors is not None) + _ply_body(p, rgb, colors is not None))


def write_ply(path: StrPath, xyz: ArrayLike, *, colors: ArrayLike | None = None, overwrite: bool = False,
              comment: str | None = None) -> Path:
    """Binary little-endian PLY with float64 x, y, z (N, 3) (and uchar red, green, blue), atomically."""
    with atomic_output(path, overwrite=overwrite) as tmp:
        dump_ply(tmp, xyz, colors=colors, comment=comment)
    return Path(path)


class PlyWriter:
    """Stream points into a binary little-endian PLY (x, y, z double; red, green, blue uchar).

    The records go to ``<path>.body`` first; :meth:`close` writes the header (which needs the count)
    and the body into ``path`` and removes the body file. Points without colours are black.
    """

    def __init__(self, path: StrPath, *, comment: str | None = None):
        self.path = Path(path)
        self.comment = comment
        self._body_path = self.path.with_name(self.path.name + ".body")
        try:
            self._body = open(self._body_path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as err:
            raise RasterIOError(f"cannot write {str(self.path)!r}: {err.strerror}") from err
        self.count = 0

    def write(self, xyz: ArrayLike, colors: ArrayLike | None = None) -> None:
        p, c = _check_xyz(xyz, colors)
        self._body.write(_ply_body(p, c, True))
        self.count += len(p)

    def close(self) -> None:
        self._body.close()
        try:
            with open(self.path, "wb") as out, open(self._body_path, "rb") as body:
                out.write(_ply_header(self.count, self.comment, True))
                shutil.copyfileobj(body, out, 1 << 22)
        finally:
            self._body_path.unlink(missing_ok=True)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def read_ply(path: StrPath) -> PointCloud:
    """Read a binary little-endian PLY with one ``vertex`` element (as :func:`write_ply` writes).

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Not a PLY, another encoding (ASCII, big-endian), list properties, no x/y/z, or a truncated body.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as err:
        raise RasterIOError(f"cannot read PLY {str(p)!r}: {err.strerror or err}") from err
    marker = b"end_header\n"
    end = data.find(marker)
    if not data.startswith(b"ply\n") or end < 0:
        raise InvalidInputError(f"{str(p)!r} is not a PLY file (no 'ply' ... 'end_header' header)")
    end += len(marker)
    head = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in head:
        fmt = next((h for h in head if h.startswith("format")), "no format line")
        raise InvalidInputError(f"{str(p)!r}: unsupported PLY {fmt!r}; expected binary_little_endian 1.0")
    n, fields, comments, in_vertex = None, [], [], False
    for h in head:
        parts = h.split()
        if parts[:1] == ["comment"]:
            comments.append(h[len("comment "):])
        elif parts[:1] == ["element"]:
            in_vertex = parts[1:2] == ["vertex"]
            if in_vertex:
                n = int(parts[2])
            elif n is not None or len(parts) < 3 or int(parts[2]) != 0:
                raise InvalidInputError(f"{str(p)!r}: only a PLY with one vertex element is supported")
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise InvalidInputError(f"{str(p)!r}: unsupported PLY property {h!r}")
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    names = [f[0] for f in fields]
    if n is None or not {"x", "y", "z"} <= set(names):
        raise InvalidInputError(f"{str(p)!r}: PLY without a vertex element with x, y, z")
    dt = np.dtype(fields)
    if len(data) - end < n * dt.itemsize:
        raise InvalidInputError(f"{str(p)!r}: PLY body too short for {n} vertices")
    rec = np.frombuffer(data, dtype=dt, count=n, offset=end)
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    colors = None
    if {"red", "green", "blue"} <= set(names):
        colors = np.column_stack([rec["red"], rec["green"], rec["blue"]]).astype(np.uint8)
    return PointCloud(xyz, colors, tuple(comments))


def read_ply_xyz(path: StrPath) -> NDArray[np.float64]:
    """The x, y, z (N, 3) of a PLY written by :func:`write_ply`."""
    return read_ply(path).xyz


def point_writer(path: StrPath, fmt: str | None = None, *, offset: ArrayLike, crs_wkt: str | None = None,
                 comment: str | None = None, extra_dims: Sequence[str | ExtraDim] = ()) -> LasWriter | PlyWriter:
    """A streaming writer: ``fmt`` ``las``, ``laz``, ``copc`` or ``ply`` (default: from the name of ``path``).

    ``extra_dims``: the extra dimensions of a LAS/LAZ/COPC cloud (:mod:`stereo.formats.cloud`).
    """
    if fmt is None:
        fmt = "ply" if Path(path).suffix.lower() == ".ply" else cloud_format(path)
    if fmt in CLOUD_FORMATS:
        return LasWriter(path, offset, crs_wkt=crs_wkt, fmt=fmt, extra_dims=extra_dims)
    if fmt == "ply":
        if extra_dims:
            raise InvalidInputError(f"{str(path)!r}: a PLY carries no extra dimensions {list(extra_dims)}; "
                                    "write .las, .laz or .copc.laz")
        return PlyWriter(path, comment=comment)
    raise InvalidInputError(f"unknown point cloud format {fmt!r} of {str(path)!r}; expected las, laz, copc or ply")


# ---------------------------------------------------------------- points CSV
@dataclass(frozen=True, eq=False)
class PointsTable:
    """A points CSV.

    Attributes
    ----------
    ids : tuple of str
    xyz : (N, 3) float64
        Ground coordinates (map CRS units), or model coordinates without control.
    residual_mm : (N,) float64
        RMS photo residual of the intersection per point, mm.
    std : (N, 3) float64 or None
        Predicted standard errors of x, y, z (ground units).
    crs : str or None
        From the ``# crs=`` line; ``None`` when absent or when the CRS is a WKT kept in the
        orientation JSON (``# crs=WKT (see orientation.json)``).
    """

    ids: tuple[str, ...]
    xyz: NDArray[np.float64]
    residual_mm: NDArray[np.float64]
    std: NDArray[np.float64] | None = None
    crs: str | None = None


def points_csv_text(ids: Sequence[str], xyz: ArrayLike, residual_mm: ArrayLike, *, std: ArrayLike | None = None,
                    crs: str | None = None) -> str:
    """The text of a points CSV: ``id,x,y,z,residual_mm[,std_x,std_y,std_z]`` (x, y, z to 0.1 mm)."""
    p = np.asarray(xyz, float).reshape(-1, 3)
    rr = np.asarray(residual_mm, float).reshape(-1)
    lines = []
    if crs:
        lines.append(f"# crs={crs}" if "\n" not in crs and len(crs) < 200 else "# crs=WKT (see orientation.json)")
    head = "id,x,y,z,residual_mm" + (",std_x,std_y,std_z" if std is not None else "")
    lines.append(head)
    s = None if std is None else np.asarray(std, float).reshape(-1, 3)
    for i, pid in enumerate(ids):
        row = f"{pid},{p[i, 0]:.4f},{p[i, 1]:.4f},{p[i, 2]:.4f},{rr[i]:.5f}"
        if s is not None:
            row += f",{s[i, 0]:.4f},{s[i, 1]:.4f},{s[i, 2]:.4f}"
        lines.append(row)
    return "\n".join(lines) + "\n"


def dump_points_csv(path: StrPath, ids: Sequence[str], xyz: ArrayLike, residual_mm: ArrayLike, *,
                    std: ArrayLike | None = None, crs: str | None = None) -> None:
    """Write a points CSV to ``path`` as given (see :func:`points_csv_text`)."""
    _write_file(path, points_csv_text(ids, xyz, residual_mm, std=std, crs=crs))


def write_points_csv(path: StrPath, ids: Sequence[str], xyz: ArrayLike, residual_mm: ArrayLike, *,
                     std: ArrayLike | None = None, crs: str | None = None, overwrite: bool = False) -> Path:
    """Write a points CSV ``id,x,y,z,residual_mm`` (plus ``std_x,std_y,std_z``) atomically."""
    with atomic_output(path, overwrite=overwrite) as tmp:
        dump_points_csv(tmp, ids, xyz, residual_mm, std=std, crs=crs)
    return Path(path)


def read_points_csv(path: StrPath) -> PointsTable:
    """Read a points CSV written by ``stereo model`` / ``stereo run``.

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Missing columns, a non-numeric value (the message names the line), no rows.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise RasterIOError(f"cannot read points CSV {str(p)!r}: {err}") from err
    crs: str | None = None
    rows: list[tuple[int, list[str]]] = []
    header: list[str] | None = None
    for k, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            c = s[1:].strip()
            if c.startswith("crs=") and c != "crs=WKT (see orientation.json)":
                crs = c[4:].strip() or None
            continue
        fields = next(csv.reader(io.StringIO(s)))
        if header is None:
            header = [f.strip() for f in fields]
        else:
            rows.append((k, fields))
    need = ["id", "x", "y", "z", "residual_mm"]
    if header is None or any(c not in header for c in need):
        raise InvalidInputError(f"{str(p)!r} is not a points CSV: expected the columns {','.join(need)}")
    if not rows:
        raise InvalidInputError(f"points CSV {str(p)!r} has no rows")
    has_std = all(c in header for c in ("std_x", "std_y", "std_z"))
    num = ["x", "y", "z", "residual_mm"] + (["std_x", "std_y", "std_z"] if has_std else [])
    col = {c: header.index(c) for c in need + num}
    vals = np.empty((len(rows), len(num)))
    ids = []
    for r, (k, f) in enumerate(rows):
        try:
            ids.append(f[col["id"]].strip())
            vals[r] = [float(f[col[c]]) for c in num]
        except (IndexError, ValueError) as err:
            raise InvalidInputError(f"{str(p)!r} line {k}: bad row {','.join(f)!r} ({err})") from err
    return PointsTable(tuple(ids), vals[:, :3].copy(), vals[:, 3].copy(),
                       vals[:, 4:7].copy() if has_std else None, crs)
