"""Every file the stereo side reads or writes: one reader and one writer per artefact.

=========================================  ==========================================  =======
artefact (default names)                   ``format`` key                              version
=========================================  ==========================================  =======
relative orientation JSON (``ro.json``,    ``rectify-stereo/relative-orientation``     1
``relative.json``)
exterior orientation JSON (``eo.json``)    ``rectify-stereo/exterior-orientation``     1
model orientation JSON                     ``rectify-stereo/model-orientation``        1
(``points.orientation.json``,
``orientation.json``)
points PLY (``points.ply``)                binary little-endian PLY, no key            --
points CSV (``points.csv``)                ``id,x,y,z,residual_mm[,std_x,std_y,std_z]``  --
=========================================  ==========================================  =======

JSON outputs carry ``"format"`` and ``"version"`` keys; readers accept the unversioned files of
release 0.1.0 and reject another format name or a newer version with a one-line error naming the
file and the value. Each writer comes in two forms: ``dump_*`` writes to a path as given (a
temporary path of :meth:`rectify.actions.workspace.Workspace.output`, inside a transaction), ``write_*``
writes atomically on its own (:func:`rectify.atomic.atomic_output`) and refuses to replace a file
without ``overwrite``. The fields, units and frames are documented in ``docs/formats.md``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_output, read_json, write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError
from rectify.report.builder import json_safe
from stereo.pair.resection import ExteriorOrientation
from stereo.relative import RelativeGeometry

if TYPE_CHECKING:  # type hints only: stereo.pair.model imports this module
    from stereo.pair.model import StereoModel

__all__ = [
    "EXTERIOR_FORMAT",
    "FORMAT_VERSION",
    "ORIENTATION_FORMAT",
    "RELATIVE_FORMAT",
    "PointCloud",
    "PointsTable",
    "check_format",
    "dump_exterior",
    "dump_orientation",
    "dump_ply",
    "dump_points_csv",
    "dump_relative",
    "exterior_dict",
    "orientation_dict",
    "read_exterior",
    "read_orientation",
    "read_ply",
    "read_ply_xyz",
    "read_points_csv",
    "read_relative",
    "relative_dict",
    "relative_json_text",
    "write_exterior",
    "write_orientation",
    "write_ply",
    "write_points_csv",
    "write_relative",
]

StrPath = str | os.PathLike[str]

RELATIVE_FORMAT = "rectify-stereo/relative-orientation"
EXTERIOR_FORMAT = "rectify-stereo/exterior-orientation"
ORIENTATION_FORMAT = "rectify-stereo/model-orientation"
#: current version of every stereo JSON format (release 0.1.0 files have no version: read as 1)
FORMAT_VERSION = 1


# ---------------------------------------------------------------------- helpers
def check_format(d: Any, path: StrPath, name: str, version: int = FORMAT_VERSION) -> dict[str, Any]:
    """Check the ``format``/``version`` keys of a parsed JSON file; return the dict.

    Files without the keys (release 0.1.0) are accepted.

    Raises
    ------
    InvalidInputError
        Not a JSON object, another ``format`` name, or a ``version`` that is not an integer or is newer
        than ``version``.
    """
    if not isinstance(d, dict):
        raise InvalidInputError(f"{str(path)!r} is not a {name} file: expected a JSON object, got "
                                f"{type(d).__name__}")
    fmt = d.get("format", name)
    if fmt != name:
        raise InvalidInputError(f"{str(path)!r} has format {fmt!r}; expected {name!r}")
    v = d.get("version", 1)
    if isinstance(v, bool) or not isinstance(v, int):
        raise InvalidInputError(f"{str(path)!r} has version {v!r}; expected an integer")
    if v > version:
        raise InvalidInputError(f"{str(path)!r} has {name} version {v}; this release reads versions up to "
                                f"{version}")
    return d


def _versioned(name: str, d: dict[str, Any]) -> dict[str, Any]:
    """``d`` with the ``format`` and ``version`` keys first."""
    rest = {k: v for k, v in d.items() if k not in ("format", "version")}
    return {"format": name, "version": FORMAT_VERSION, **rest}


def _write_text_file(tmp: StrPath, text: str) -> None:
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as err:
        raise RasterIOError(f"cannot write {str(tmp)!r}: {write_failure_reason(err, tmp)}") from err


def _atomic(path: StrPath, overwrite: bool, dump: Callable[[Path], None]) -> Path:
    with atomic_output(path, overwrite=overwrite) as tmp:
        dump(tmp)
    return Path(path)


# ---------------------------------------------------------- relative orientation
def relative_dict(ro: Any, *, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The relative orientation JSON as a dict: format, version, ``ro.to_dict()`` and ``extra`` (cameras).

    Parameters
    ----------
    ro : RelativeOrientation or dict
        The estimate, or its dict form.
    extra : dict, optional
        More keys, e.g. ``{"camera": camera.to_dict()}`` (``stereo orient`` stores the cameras).
    """
    d = ro if isinstance(ro, dict) else ro.to_dict()
    return _versioned(RELATIVE_FORMAT, {**d, **(extra or {})})


def relative_json_text(ro: Any, *, extra: dict[str, Any] | None = None) -> str:
    """The text of the relative orientation JSON (indented, no trailing newline)."""
    return json.dumps(relative_dict(ro, extra=extra), indent=2)


def dump_relative(path: StrPath, ro: Any, *, extra: dict[str, Any] | None = None) -> None:
    """Write the relative orientation JSON to ``path`` as given (no overwrite check)."""
    _write_text_file(path, relative_json_text(ro, extra=extra) + "\n")


def write_relative(path: StrPath, ro: Any, *, extra: dict[str, Any] | None = None,
                   overwrite: bool = False) -> Path:
    """Write the relative orientation JSON atomically (see :func:`relative_dict`)."""
    return _atomic(path, overwrite, lambda tmp: dump_relative(tmp, ro, extra=extra))


def read_relative(path: StrPath) -> RelativeGeometry:
    """Read a relative orientation JSON (``stereo orient``'s ``ro.json``, ``stereo run``'s ``relative.json``).

    Returns
    -------
    RelativeGeometry
        Rotations, base and focal lengths; ``raw`` holds the whole file (points, cameras).

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Not JSON, another format or a newer version, or a key intersection needs is missing.
    """
    p = Path(path)
    d = check_format(read_json(p, "relative orientation"), p, RELATIVE_FORMAT)
    missing = [k for k in ("rotation_left", "rotation_right", "base", "focal_length_mm") if k not in d]
    if missing:
        raise InvalidInputError(f"{str(p)!r} is not a relative orientation JSON: missing {missing}")
    _check_numbers(d, "rotation_left", (3, 3), p)
    _check_numbers(d, "rotation_right", (3, 3), p)
    _check_numbers(d, "base", (3,), p)
    f = d["focal_length_mm"]
    _check_numbers(d, "focal_length_mm", (2,) if isinstance(f, list) else (), p)
    for key in ("sigma0_mm", "pixel_size_mm"):
        if d.get(key) is not None:
            _check_numbers(d, key, (), p)
    try:
        return RelativeGeometry.from_dict(d, source=repr(str(p)))
    except (TypeError, ValueError, KeyError) as err:
        if isinstance(err, InvalidInputError):
            raise
        raise InvalidInputError(f"{str(p)!r}: bad relative orientation: {err}") from err


_JSON_SHAPE_NAMES = {(): "a number", (2,): "a list of 2 numbers", (3,): "a list of 3 numbers",
                     (3, 3): "a 3 x 3 list of numbers"}


def _is_json_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_numbers(d: dict[str, Any], key: str, shape: tuple[int, ...], path: Path) -> None:
    """Refuse ``d[key]`` unless it is finite numbers of ``shape`` (strings and bools are not numbers)."""
    v = d.get(key)

    def ok(x: Any, shp: tuple[int, ...]) -> bool:
        if not shp:
            return _is_json_number(x) and bool(np.isfinite(x))
        return isinstance(x, list) and len(x) == shp[0] and all(ok(e, shp[1:]) for e in x)

    if not ok(v, shape):
        raise InvalidInputError(f"{str(path)!r}: `{key}` must be {_JSON_SHAPE_NAMES.get(shape, 'numbers')}; "
                                f"got {v!r}")


# ---------------------------------------------------------- exterior orientation
def exterior_dict(eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None) -> dict[str, Any]:
    """The exterior orientation JSON as a dict: format, version, ``eo.to_dict()`` and the camera."""
    d = eo.to_dict()
    s0 = d.get("sigma0_mm")
    if s0 is not None and not math.isfinite(float(s0)):
        d["sigma0_mm"] = None  # not adjusted (no redundancy): JSON null, not NaN
    if camera is not None:
        d["camera"] = camera
    return _versioned(EXTERIOR_FORMAT, d)


def dump_exterior(path: StrPath, eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None) -> None:
    """Write the exterior orientation JSON to ``path`` as given."""
    _write_text_file(path, json.dumps(exterior_dict(eo, camera=camera), indent=2))


def write_exterior(path: StrPath, eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None,
                   overwrite: bool = False) -> Path:
    """Write the exterior orientation JSON (``stereo resect``'s ``eo.json``) atomically."""
    return _atomic(path, overwrite, lambda tmp: dump_exterior(tmp, eo, camera=camera))


def read_exterior(path: StrPath) -> ExteriorOrientation:
    """Read an exterior orientation JSON.

    Position, rotation (or omega-phi-kappa angles), focal length, principal point and CRS are read;
    the covariance is rebuilt from ``std_errors`` and ``correlation`` when both are present, and
    ``sigma0_mm``, ``iterations``, ``converged`` when present. Other keys (camera, points, residual
    summary) are kept in ``extra``.

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Not JSON, another format or a newer version, a missing or bad key.
    """
    p = Path(path)
    d = check_format(read_json(p, "exterior orientation file"), p, EXTERIOR_FORMAT)
    if "position" in d:
        _check_numbers(d, "position", (3,), p)
    if "rotation" in d:
        _check_numbers(d, "rotation", (3, 3), p)
    elif isinstance(d.get("angles"), dict):
        for k in ("omega", "phi", "kappa"):
            if k in d["angles"]:
                _check_numbers(d["angles"], k, (), p)
    if "focal_length_mm" in d:
        _check_numbers(d, "focal_length_mm", (), p)
    if d.get("principal_point_mm") is not None:
        _check_numbers(d, "principal_point_mm", (2,), p)
    for key in ("sigma0_mm", "iterations"):
        if d.get(key) is not None:
            _check_numbers(d, key, (), p)
    try:
        eo = ExteriorOrientation.from_dict(d)
    except (InvalidInputError, TypeError, ValueError) as err:
        raise InvalidInputError(f"{str(p)!r}: {err}") from err
    cov = None
    corr = d.get("correlation")
    std = d.get("std_errors")
    names: tuple[str, ...] = eo.param_names
    if isinstance(corr, dict) and isinstance(std, dict) and corr.get("matrix") is not None:
        names = tuple(corr.get("names") or names)
        try:
            s = np.array([float(std[k]) for k in names])
            cov = np.array(corr["matrix"], dtype=np.float64) * np.outer(s, s)
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"{str(p)!r}: bad std_errors/correlation: {err}") from err
    sigma0 = d.get("sigma0_mm")
    known = {"format", "version", "position", "rotation", "rotation_convention", "angles", "focal_length_mm",
             "principal_point_mm", "std_errors", "sigma0_mm", "iterations", "converged", "crs", "correlation",
             "residuals", "points"}
    return ExteriorOrientation(
        position=eo.position, rotation=eo.rotation, focal_length_mm=eo.focal_length_mm,
        principal_point_mm=eo.principal_point_mm, covariance=cov, param_names=names,
        sigma0=float("nan") if sigma0 is None else float(sigma0), iterations=int(d.get("iterations", 0)),
        converged=bool(d.get("converged", True)), crs=eo.crs,
        extra={k: v for k, v in d.items() if k not in known})


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


def _ply_bytes(xyz: ArrayLike, colors: ArrayLike | None, comment: str | None) -> bytes:
    p = np.asarray(xyz, dtype="<f8").reshape(-1, 3)
    n = len(p)
    dt = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        c = np.asarray(colors).reshape(n, -1)
        dt += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(n, dtype=dt)
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colors is not None:
        for k, name in enumerate(("red", "green", "blue")):
            rec[name] = np.clip(c[:, min(k, c.shape[1] - 1)], 0, 255).astype("u1")
    head = ["ply", "format binary_little_endian 1.0"]
    if comment:
        head.append(f"comment {comment}")
    head += [f"element vertex {n}", "property double x", "property double y", "property double z"]
    if colors is not None:
        head += ["property uchar red", "property uchar green", "property uchar blue"]
    head.append("end_header")
    return ("\n".join(head) + "\n").encode("ascii") + rec.tobytes()


def dump_ply(path: StrPath, xyz: ArrayLike, *, colors: ArrayLike | None = None, comment: str | None = None) -> None:
    """Write a binary little-endian PLY (float64 x, y, z; uchar red, green, blue) to ``path`` as given."""
    data = _ply_bytes(xyz, colors, comment)
    try:
        with open(path, "wb") as fh:
            fh.write(data)
    except OSError as err:
        raise RasterIOError(f"cannot write {str(path)!r}: {write_failure_reason(err, path)}") from err


def write_ply(path: StrPath, xyz: ArrayLike, *, colors: ArrayLike | None = None, overwrite: bool = False,
              comment: str | None = None) -> Path:
    """Binary little-endian PLY with float64 x, y, z (N, 3) (and uchar red, green, blue), atomically."""
    return _atomic(path, overwrite, lambda tmp: dump_ply(tmp, xyz, colors=colors, comment=comment))


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
    _write_text_file(path, points_csv_text(ids, xyz, residual_mm, std=std, crs=crs))


def write_points_csv(path: StrPath, ids: Sequence[str], xyz: ArrayLike, residual_mm: ArrayLike, *,
                     std: ArrayLike | None = None, crs: str | None = None, overwrite: bool = False) -> Path:
    """Write a points CSV ``id,x,y,z,residual_mm`` (plus ``std_x,std_y,std_z``) atomically."""
    return _atomic(path, overwrite,
                   lambda tmp: dump_points_csv(tmp, ids, xyz, residual_mm, std=std, crs=crs))


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


# --------------------------------------------------------- model orientation JSON
def orientation_dict(model: StereoModel, *, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The model orientation JSON as a dict: frame, CRS, summary, absolute orientation (NaN -> null)."""
    d: dict[str, Any] = {"frame": model.frame, "crs": model.crs, "summary": model.summary}
    if model.absolute is not None:
        d["absolute"] = model.absolute.to_dict()
    if extra:
        d.update(extra)
    return _versioned(ORIENTATION_FORMAT, json_safe(d))


def dump_orientation(path: StrPath, d: dict[str, Any]) -> None:
    """Write a model orientation dict (:func:`orientation_dict`) to ``path`` as given."""
    _write_text_file(path, json.dumps(json_safe(_versioned(ORIENTATION_FORMAT, d)), indent=2))


def write_orientation(path: StrPath, d: dict[str, Any], *, overwrite: bool = False) -> Path:
    """Write a model orientation dict (:func:`orientation_dict`) atomically."""
    return _atomic(path, overwrite, lambda tmp: dump_orientation(tmp, d))


def read_orientation(path: StrPath) -> dict[str, Any]:
    """Read a model orientation JSON (``points.orientation.json``, ``orientation.json``).

    Returns
    -------
    dict
        ``frame`` (``name``; ``origin_lon_lat_h`` for the topocentric frame), ``crs``, ``summary``
        and, when the model was oriented to control, ``absolute``.

    Raises
    ------
    RasterIOError, InvalidInputError
        Missing file, not JSON, another format or a newer version, no ``frame``/``summary``.
    """
    p = Path(path)
    d = check_format(read_json(p, "orientation file"), p, ORIENTATION_FORMAT)
    missing = [k for k in ("frame", "summary") if not isinstance(d.get(k), dict)]
    if missing:
        raise InvalidInputError(f"{str(p)!r} is not a model orientation JSON: missing {missing}")
    if not isinstance(d["frame"].get("name"), str):
        raise InvalidInputError(f"{str(p)!r}: the frame has no name")
    return d
