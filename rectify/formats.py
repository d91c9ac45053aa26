"""Every file of the image side, each with a reader and a writer (documented in ``docs/formats.md``).

========================  ===========================================  ==============================
artefact                  reader / writer                              JSON ``format`` (``version``)
========================  ===========================================  ==============================
GCP CSV, QGIS ``.points`` :func:`read_gcps` / :func:`write_gcps`       (CSV, identified by its header)
matches CSV               :func:`read_matches` / :func:`write_matches` (CSV)
stereo control CSV        :func:`read_control` / :func:`write_control` (CSV)
camera JSON               :func:`read_camera` / :func:`write_camera`   ``rectify-stereo/camera`` (1)
transform JSON            :func:`read_transform` / :func:`write_transform`  ``rectify-stereo/transform`` (2)
report JSON               :func:`read_report` / :func:`report_json_text`    ``rectify-stereo/report`` (2)
residual table CSV        :func:`read_residuals` / :func:`write_residuals`  (CSV, ``# step=...`` line)
========================  ===========================================  ==============================

Tables use the project's pixel convention (x = column right, y = row down, pixel centres at
integers). Lines starting with ``#`` are comments; a comment ``# crs=EPSG:32618`` sets the CRS.
Readers raise :class:`~rectify.errors.RasterIOError` for unreadable files and
:class:`~rectify.errors.InvalidInputError` naming the file and line for malformed content.

Every JSON output carries ``"format": "rectify-stereo/<name>"`` and an integer ``"version"``
(:func:`stamp`); readers (:func:`check_format`) accept the unversioned files of release 0.1.0 and
reject a wrong format name or a version newer than this release reads, naming the file and value.

Each writer has a pure serialiser (``*_text`` or ``*_document``) so that it can be written through
:meth:`rectify.workspace.Workspace.output` as well as standalone (atomic, via
:func:`rectify.fileutil.atomic_write_text`).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera import Camera
from .errors import InvalidInputError, RasterIOError
from .fileutil import atomic_write_text, read_json
from .residuals import ResidualTable

__all__ = [
    "FORMAT_PREFIX", "CAMERA_VERSION", "TRANSFORM_VERSION", "REPORT_VERSION",
    "stamp", "check_format",
    "GcpTable", "Matches", "ControlTable",
    "read_gcps", "write_gcps", "gcps_text",
    "read_matches", "write_matches", "matches_text",
    "read_control", "write_control", "control_text",
    "read_camera", "write_camera", "camera_document",
    "TransformFile", "read_transform", "write_transform", "transform_document", "transform_text",
    "read_report", "report_json_text",
    "read_residuals", "write_residuals",
]

#: Prefix of every ``format`` value written by this project.
FORMAT_PREFIX = "rectify-stereo/"
#: Version of the camera JSON (1: the 0.1.0 keys plus ``format``/``version``).
CAMERA_VERSION = 2  # 2: pixel cameras, std_errors, sigma0_px (1: millimetre cameras)
#: Version of the transform JSON (1: 0.1.0, ``format: rectify-transform``; 2: ``rectify-stereo/transform``).
TRANSFORM_VERSION = 2
#: Version of ``report.json`` (1: 0.1.0, ``report_version: 1``; 2: ``format``/``version`` keys).
REPORT_VERSION = 2

StrPath = str | os.PathLike[str]


# --------------------------------------------------------------------------- versioning
def stamp(name: str, version: int, body: Mapping[str, Any]) -> dict[str, Any]:
    """``{"format": "rectify-stereo/<name>", "version": version, **body}`` (the stamp comes first).

    >>> stamp("camera", 1, {"width": 4})
    {'format': 'rectify-stereo/camera', 'version': 1, 'width': 4}
    """
    out: dict[str, Any] = {"format": FORMAT_PREFIX + name, "version": int(version)}
    out.update({k: v for k, v in body.items() if k not in ("format", "version")})
    return out


def check_format(doc: Any, name: str, version: int, path: StrPath | None = None, *, what: str | None = None,
                 legacy: Mapping[str, int] | None = None, version_key: str = "version") -> int:
    """Check the ``format``/``version`` keys of a JSON document; return the version it was written with.

    Parameters
    ----------
    doc : object
        The parsed JSON.
    name : str
        Format name without the prefix (``"camera"``).
    version : int
        Newest version this release reads.
    path : path, optional
        The file, named in errors.
    what : str, optional
        Human name of the file in errors (default ``"<name> file"``).
    legacy : dict format value -> version, optional
        Older ``format`` values accepted, with the version they stand for when the file has none
        (e.g. ``{"rectify-transform": 1}``).
    version_key : str
        Key holding the version in unstamped files of release 0.1.0 (``"report_version"``).

    Returns
    -------
    int
        The file's version; 0 for an unversioned file of release 0.1.0.

    Raises
    ------
    InvalidInputError
        Not a JSON object, a different format, or a version newer than ``version``.
    """
    label = f"{what or name + ' file'}{'' if path is None else ' ' + repr(str(path))}"
    if not isinstance(doc, dict):
        raise InvalidInputError(f"{label} must hold a JSON object; got {type(doc).__name__}")
    legacy = dict(legacy or {})
    fmt = doc.get("format")
    if fmt is None:
        found = doc.get(version_key, doc.get("version", 0))
    elif fmt == FORMAT_PREFIX + name or fmt in legacy:
        found = doc.get("version", legacy.get(fmt, 0))
    else:
        raise InvalidInputError(f"{label} has format {fmt!r}; expected {FORMAT_PREFIX + name!r}")
    if isinstance(found, bool) or not isinstance(found, int) or found < 0:
        raise InvalidInputError(f"{label} has version {found!r}; expected an integer <= {version}")
    if found > version:
        raise InvalidInputError(f"{label} has version {found}, newer than this release reads (<= {version})")
    return found


def _unstamped(doc: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in doc.items() if k not in ("format", "version")}


# --------------------------------------------------------------------------- point tables
@dataclass(frozen=True, eq=False)
class GcpTable:
    """Ground control for 2D rectification.

    Attributes
    ----------
    ids : tuple of str
    pixel : (N, 2) float64
        Source pixels (col, row).
    target : (N, 2) float64
        Target coordinates (map units when ``crs`` is set, target pixels otherwise).
    z : (N,) float64 or None
        Heights, when the file has a ``z`` column.
    check : (N,) bool
        Rows withheld from the fit (``check`` column = 1).
    crs : str or None
    """

    ids: tuple[str, ...]
    pixel: NDArray[np.float64]
    target: NDArray[np.float64]
    z: NDArray[np.float64] | None
    check: NDArray[np.bool_]
    crs: str | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def fit(self) -> GcpTable:
        """The rows used for fitting (not check points)."""
        return self.subset(~self.check)

    def subset(self, mask: NDArray[np.bool_]) -> GcpTable:
        """The rows where ``mask`` (N,) is true."""
        m = np.asarray(mask, dtype=bool)
        return GcpTable(tuple(i for i, k in zip(self.ids, m, strict=False) if k), self.pixel[m], self.target[m],
                        None if self.z is None else self.z[m], self.check[m], self.crs)


@dataclass(frozen=True, eq=False)
class Matches:
    """Tie points between two images, pixel frame.

    Attributes
    ----------
    ids : tuple of str
    left, right : (N, 2) float64
        (col, row) in the left and right image.
    score : (N,) float64 or None
    """

    ids: tuple[str, ...]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    score: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True, eq=False)
class ControlTable:
    """Stereo control: image points in both images (pixel frame) plus ground coordinates.

    ``xyz`` (N, 3) rows are NaN for tie points (empty x, y, z in the file); ``crs`` is that of x, y.
    """

    ids: tuple[str, ...]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    xyz: NDArray[np.float64]
    crs: str | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def is_control(self) -> NDArray[np.bool_]:
        """(N,) rows with full ground coordinates."""
        return np.asarray(np.isfinite(self.xyz).all(axis=1), dtype=bool)


def _read_text(path: StrPath) -> str:
    p = Path(path)
    try:
        # utf-8-sig: spreadsheets write a byte-order mark before the header or the '# crs=' line
        return p.read_text(encoding="utf-8-sig").replace("\ufeff", "")
    except FileNotFoundError as err:
        raise RasterIOError(f"file not found: {str(p)!r}") from err
    except (OSError, UnicodeDecodeError) as err:
        raise RasterIOError(f"cannot read {str(p)!r}: {err}") from err


def _rows(text: str, path: StrPath) -> tuple[list[dict[str, str]], list[int], str | None]:
    """Parse CSV text with comment lines; return rows, their line numbers and the crs comment."""
    crs = None
    data_lines: list[tuple[int, str]] = []
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            if body.lower().startswith("crs="):
                crs = body[4:].strip()
            elif body.upper().startswith("CRS:"):  # QGIS .points header
                crs = body[4:].strip() or None
            continue
        data_lines.append((no, line))
    if not data_lines:
        raise InvalidInputError(f"{str(path)!r} has no header and no rows")
    reader = csv.DictReader(io.StringIO("\n".join(text for _, text in data_lines)))
    reader.fieldnames = [f.strip() for f in (reader.fieldnames or [])]
    rows = [{k: (v or "").strip() for k, v in r.items() if k is not None} for r in reader]
    return rows, [no for no, _ in data_lines[1:]], crs


def _load(path: StrPath, what: str) -> tuple[list[dict[str, str]], list[int], str | None, list[str]]:
    """Read a point table: its rows, their line numbers, the ``# crs=`` value and the header;
    raise when the file has a header but no ``what``."""
    rows, lines, crs = _rows(_read_text(path), path)
    if not rows:
        raise InvalidInputError(f"{str(path)!r} has a header but no {what}")
    return rows, lines, crs, list(rows[0].keys())


def _need(fields: list[str], required: tuple[str, ...], path: StrPath) -> None:
    missing = [f for f in required if f not in fields]
    if missing:
        raise InvalidInputError(f"{str(path)!r}: missing column(s) {missing}; header is {fields}")


def _num(row: dict[str, str], key: str, line: int, path: StrPath, *, allow_empty: bool = False) -> float:
    s = row.get(key, "")
    if s == "" and allow_empty:
        return math.nan
    try:
        v = float(s)
    except ValueError:
        raise InvalidInputError(f"{str(path)!r} line {line}: column {key!r} is not a number: {s!r}") from None
    if not math.isfinite(v):
        raise InvalidInputError(f"{str(path)!r} line {line}: column {key!r} is not finite: {s!r}")
    return v


def _no_duplicates(ids: list[str], path: StrPath, what: str) -> None:
    counts = Counter(ids)
    dup = {i for i, n in counts.items() if n > 1}
    if dup:
        raise InvalidInputError(f"{str(path)!r}: duplicate {what} {sorted(dup)}")


def read_gcps(path: StrPath) -> GcpTable:
    """Read a GCP CSV (``id,col,row,x,y[,z][,check]``), a QGIS ``.points`` file or a matches CSV.

    QGIS files (``mapX,mapY,sourceX,sourceY,enable,...``, pixel corners, rows
    negative) are converted to the project's convention; disabled rows become
    check points. A matches CSV (``id,col_left,row_left,col_right,row_right[,score]``) gives
    GCPs that map the right image onto the left one: ``pixel`` = right, ``target`` = left pixels.

    Returns
    -------
    GcpTable
        ``pixel`` (N, 2) source pixels, ``target`` (N, 2) in the ``crs`` units (or target pixels).
    """
    rows, lines, crs, fields = _load(path, "GCP rows")
    ids: list[str] = []
    pix: list[tuple[float, float]] = []
    tgt: list[tuple[float, float]] = []
    zs: list[float] = []
    chk: list[bool] = []
    if "col_left" in fields and "x" not in fields:  # a matches CSV: fit the right image to the left
        m = read_matches(path)
        return GcpTable(m.ids, m.right.copy(), m.left.copy(), None, np.zeros(len(m), dtype=bool), crs)
    if "mapX" in fields:
        sx = "sourceX" if "sourceX" in fields else "pixelX"
        sy = "sourceY" if "sourceY" in fields else "pixelY"
        _need(fields, ("mapX", "mapY", sx, sy), path)
        for k, (r, ln) in enumerate(zip(rows, lines, strict=False)):
            ids.append(str(k + 1))
            # QGIS: corner convention, row axis negative
            pix.append((_num(r, sx, ln, path) - 0.5, -_num(r, sy, ln, path) - 0.5))
            tgt.append((_num(r, "mapX", ln, path), _num(r, "mapY", ln, path)))
            chk.append(r.get("enable", "1") in ("0", "false", "False"))
        z = None
    else:
        _need(fields, ("id", "col", "row", "x", "y"), path)
        has_z = "z" in fields
        for r, ln in zip(rows, lines, strict=False):
            ids.append(r["id"])
            pix.append((_num(r, "col", ln, path), _num(r, "row", ln, path)))
            tgt.append((_num(r, "x", ln, path), _num(r, "y", ln, path)))
            if has_z:
                zs.append(_num(r, "z", ln, path))
            c = r.get("check", "0") or "0"
            if c not in ("0", "1"):
                raise InvalidInputError(f"{str(path)!r} line {ln}: column 'check' must be 0 or 1; got {c!r}")
            chk.append(c == "1")
        z = np.array(zs) if has_z else None
    _no_duplicates(ids, path, "GCP id(s)")
    return GcpTable(tuple(ids), np.array(pix, dtype=float).reshape(-1, 2),
                    np.array(tgt, dtype=float).reshape(-1, 2), z, np.array(chk, dtype=bool), crs)


def gcps_text(gcps: GcpTable) -> str:
    """The GCP CSV text (``# crs=`` line when set; numbers as ``repr`` so they read back exactly)."""
    buf = io.StringIO()
    if gcps.crs:
        buf.write(f"# crs={gcps.crs}\n")
    cols = ["id", "col", "row", "x", "y"] + (["z"] if gcps.z is not None else []) + ["check"]
    buf.write(",".join(cols) + "\n")
    for i in range(len(gcps)):
        vals = [gcps.ids[i], *map(repr, map(float, gcps.pixel[i])), *map(repr, map(float, gcps.target[i]))]
        if gcps.z is not None:
            vals.append(repr(float(gcps.z[i])))
        vals.append("1" if gcps.check[i] else "0")
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_gcps(path: StrPath, gcps: GcpTable, *, overwrite: bool = False) -> Path:
    """Write a GCP CSV atomically (:func:`gcps_text`); return the path."""
    return atomic_write_text(path, gcps_text(gcps), overwrite=overwrite)


def read_matches(path: StrPath) -> Matches:
    """Read a matches CSV (``id,col_left,row_left,col_right,row_right[,score]``), pixel frame."""
    rows, lines, _, fields = _load(path, "matches")
    _need(fields, ("id", "col_left", "row_left", "col_right", "row_right"), path)
    has_score = "score" in fields
    ids, left, right, score = [], [], [], []
    for r, ln in zip(rows, lines, strict=False):
        ids.append(r["id"])
        left.append((_num(r, "col_left", ln, path), _num(r, "row_left", ln, path)))
        right.append((_num(r, "col_right", ln, path), _num(r, "row_right", ln, path)))
        if has_score:
            score.append(_num(r, "score", ln, path, allow_empty=True))
    _no_duplicates(ids, path, "match id(s)")
    return Matches(tuple(ids), np.array(left).reshape(-1, 2), np.array(right).reshape(-1, 2),
                   np.array(score) if has_score else None)


def matches_text(matches: Matches) -> str:
    """The matches CSV text: positions with 6 decimals (1e-6 px), scores with 6 significant digits."""
    buf = io.StringIO()
    cols = ["id", "col_left", "row_left", "col_right", "row_right"]
    if matches.score is not None:
        cols.append("score")
    buf.write(",".join(cols) + "\n")
    for i in range(len(matches)):
        vals = [matches.ids[i]] + [f"{v:.6f}" for v in (*matches.left[i], *matches.right[i])]
        if matches.score is not None:
            vals.append(f"{matches.score[i]:.6g}")
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_matches(path: StrPath, matches: Matches, *, overwrite: bool = False) -> Path:
    """Write a matches CSV atomically (:func:`matches_text`); return the path."""
    return atomic_write_text(path, matches_text(matches), overwrite=overwrite)


def read_control(path: StrPath) -> ControlTable:
    """Read a stereo control CSV (``id,col_left,row_left,col_right,row_right,x,y,z``).

    Empty ``x, y, z`` make a tie point (NaN in ``xyz``); partly empty rows are refused.
    """
    rows, lines, crs, fields = _load(path, "rows")
    _need(fields, ("id", "col_left", "row_left", "col_right", "row_right", "x", "y", "z"), path)
    ids, left, right, xyz = [], [], [], []
    for r, ln in zip(rows, lines, strict=False):
        ids.append(r["id"])
        left.append((_num(r, "col_left", ln, path), _num(r, "row_left", ln, path)))
        right.append((_num(r, "col_right", ln, path), _num(r, "row_right", ln, path)))
        p = [_num(r, k, ln, path, allow_empty=True) for k in ("x", "y", "z")]
        if any(math.isnan(v) for v in p) and not all(math.isnan(v) for v in p):
            raise InvalidInputError(f"{str(path)!r} line {ln}: x, y, z must be all given or all empty")
        xyz.append(p)
    _no_duplicates(ids, path, "id(s)")
    return ControlTable(tuple(ids), np.array(left).reshape(-1, 2), np.array(right).reshape(-1, 2),
                        np.array(xyz, dtype=float).reshape(-1, 3), crs)


def control_text(control: ControlTable) -> str:
    """The stereo control CSV text (``# crs=`` line when set; numbers as ``repr``, tie rows empty)."""
    buf = io.StringIO()
    if control.crs:
        buf.write(f"# crs={control.crs}\n")
    buf.write("id,col_left,row_left,col_right,row_right,x,y,z\n")
    for i in range(len(control)):
        g = control.xyz[i]
        ground = [repr(float(v)) for v in g] if np.isfinite(g).all() else ["", "", ""]
        vals = [control.ids[i], *(repr(float(v)) for v in (*control.left[i], *control.right[i])), *ground]
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_control(path: StrPath, control: ControlTable, *, overwrite: bool = False) -> Path:
    """Write a stereo control CSV atomically (:func:`control_text`); return the path."""
    return atomic_write_text(path, control_text(control), overwrite=overwrite)


# --------------------------------------------------------------------------- camera JSON
def read_camera(path: StrPath) -> Camera:
    """Read a camera JSON file (:meth:`Camera.from_dict` keys; ``rectify-stereo/camera``)."""
    doc = read_json(path, "camera file")
    check_format(doc, "camera", CAMERA_VERSION, path)
    return Camera.from_dict(_unstamped(doc))


def camera_document(camera: Camera) -> dict[str, Any]:
    """The camera JSON object: the format stamp and :meth:`Camera.to_dict`."""
    return stamp("camera", CAMERA_VERSION, camera.to_dict())


def write_camera(path: StrPath, camera: Camera, *, overwrite: bool = False) -> Path:
    """Write a camera JSON file atomically; return the path."""
    return atomic_write_text(path, json.dumps(camera_document(camera), indent=2) + "\n", overwrite=overwrite)


# --------------------------------------------------------------------------- transform JSON
@dataclass(frozen=True, eq=False)
class TransformFile:
    """A transform JSON file read back.

    Attributes
    ----------
    model : transform
        The model (source pixels -> target), rebuilt by the transforms' ``transform_from_dict``.
    method : str
        Registry name (``homography``, ``cotangent``, ``affine``, ``poly2``, ``poly3``).
    crs : str or None
        CRS of the target coordinates.
    units : str or None
        Units of the residuals.
    rmse, rmse_check : float or None
        Fit and check-point RMSE, ``units``.
    summary : dict
        The residual table's summary (JSON-able entries).
    residuals : list of dict
        One per GCP: ``id``, ``observed``, ``adjusted`` (target), ``dx``, ``dy``, ``norm``, ``check``.
    version : int
        Version the file was written with (1 for release 0.1.0).
    extra : dict
        Other keys (a caller's ``extra``).
    """

    model: Any
    method: str
    crs: str | None = None
    units: str | None = None
    rmse: float | None = None
    rmse_check: float | None = None
    summary: dict[str, Any] = field(default_factory=dict)
    residuals: list[dict[str, Any]] = field(default_factory=list)
    version: int = TRANSFORM_VERSION
    extra: dict[str, Any] = field(default_factory=dict)


_TRANSFORM_KEYS = {"format", "version", "method", "direction", "matrix", "src", "dst", "order", "coefficients",
                   "shift", "scale", "domain", "crs", "rmse", "rmse_check", "units", "summary", "residuals"}


def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except (TypeError, ValueError):
        return False


def transform_document(model: Any, *, table: ResidualTable | None = None, crs: str | None = None,
                       extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The transform JSON object.

    Keys: the stamp, ``method``, ``direction`` and the model's parameters (the transforms'
    ``transform_to_dict``), ``crs`` of the target (when known), and, with ``table``, ``rmse``,
    ``rmse_check``, ``units``, ``summary`` and ``residuals`` (one object per GCP), then ``extra``.
    """
    # import cycle: the transforms' GCP fitting imports GcpTable from this module
    from .transforms import transform_to_dict

    out = stamp("transform", TRANSFORM_VERSION, transform_to_dict(model))
    if crs:
        out["crs"] = crs
    if table is not None:
        s = table.summary()
        out["rmse"] = s["rmse"]
        out["rmse_check"] = s["rmse_check"]
        out["units"] = table.units
        out["summary"] = {k: v for k, v in s.items() if _jsonable(v)}
        res, check = table.residual, np.asarray(table.check, dtype=bool)
        out["residuals"] = [
            {"id": table.ids[i], "observed": table.observed[i].tolist(), "adjusted": table.adjusted[i].tolist(),
             "dx": float(res[i, 0]), "dy": float(res[i, 1]), "norm": float(table.norm[i]),
             "check": bool(check[i])} for i in range(table.n)]
    if extra:
        out.update(extra)
    return out


def transform_text(model: Any, *, table: ResidualTable | None = None, crs: str | None = None,
                   extra: Mapping[str, Any] | None = None) -> str:
    """:func:`transform_document` as indented JSON text (NaN kept as ``NaN``, as in release 0.1.0)."""
    return json.dumps(transform_document(model, table=table, crs=crs, extra=extra), indent=2, allow_nan=True) + "\n"


def write_transform(path: StrPath, model: Any, *, table: ResidualTable | None = None, crs: str | None = None,
                    extra: Mapping[str, Any] | None = None, overwrite: bool = False) -> Path:
    """Write a transform JSON file atomically (:func:`transform_document`); return the path."""
    return atomic_write_text(path, transform_text(model, table=table, crs=crs, extra=extra), overwrite=overwrite)


def read_transform(path: StrPath) -> TransformFile:
    """Read a transform JSON written by ``rectify fit`` (this release or 0.1.0).

    Raises
    ------
    RasterIOError
        File missing or unreadable.
    InvalidInputError
        Not JSON, another format, a newer version, or not a valid transform.
    """
    # import cycle: the transforms' GCP fitting imports GcpTable from this module
    from .transforms import transform_from_dict

    doc = read_json(path, "transform file")
    version = check_format(doc, "transform", TRANSFORM_VERSION, path, legacy={"rectify-transform": 1})
    model = transform_from_dict(doc)
    return TransformFile(model=model, method=str(doc["method"]), crs=doc.get("crs"), units=doc.get("units"),
                         rmse=doc.get("rmse"), rmse_check=doc.get("rmse_check"), summary=dict(doc.get("summary") or {}),
                         residuals=list(doc.get("residuals") or []), version=version or 1,
                         extra={k: v for k, v in doc.items() if k not in _TRANSFORM_KEYS})


# --------------------------------------------------------------------------- report JSON
def report_json_text(doc: Mapping[str, Any]) -> str:
    """``report.json`` text: the stamp, then ``doc`` (already JSON-safe: no NaN)."""
    return json.dumps(stamp("report", REPORT_VERSION, doc), indent=2, allow_nan=False)


def read_report(path: StrPath) -> dict[str, Any]:
    """Read ``report.json`` (give the file or the report folder); release 0.1.0's ``report_version: 1``
    is accepted.

    Returns
    -------
    dict
        ``title``, ``created_utc``, ``crs``, ``tables`` (step, slug, units, components, summary, files),
        ``figures``, ``summary``, ``files``, and ``version``.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "report.json"
    doc = read_json(p, "report file")
    version = check_format(doc, "report", REPORT_VERSION, p, version_key="report_version")
    out = _unstamped(doc)
    out.pop("report_version", None)
    out["version"] = version
    return out


# --------------------------------------------------------------------------- residual CSV
_STEP_LINE = re.compile(r"#\s*step=(?P<step>.*); units=(?P<units>[^;]*)(;|$)")


def read_residuals(path: StrPath) -> ResidualTable:
    """Read a residual table CSV of a report (``ResidualTable.to_csv``).

    The CSV keeps ids, observed, adjusted, components, weights and the outlier/check flags; the
    parameter count is not stored, so ``sigma0`` of the result is the one of the file's rows with
    ``n_params = 0``.
    """
    text = _read_text(path)
    first = text.splitlines()[0] if text else ""
    m = _STEP_LINE.match(first)
    if m is None:
        raise InvalidInputError(f"{str(path)!r}: first line must be '# step=...; units=...'; got {first[:60]!r}")
    rows, lines, _, fields = _load(path, "residual rows")
    k = sum(1 for f in fields if f.startswith("observed_"))
    adj = [f"adjusted_{j}" for j in range(k)]
    comps = tuple(fields[1 + 2 * k: 1 + 3 * k])
    _need(fields, ("id", *(f"observed_{j}" for j in range(k)), *adj, "norm", "weight", "outlier", "check"), path)

    def val(r: dict[str, str], key: str, ln: int) -> float:
        return math.nan if r[key] == "nan" else _num(r, key, ln, path)

    obs = [[val(r, f"observed_{j}", ln) for j in range(k)] for r, ln in zip(rows, lines, strict=False)]
    adjusted = [[val(r, a, ln) for a in adj] for r, ln in zip(rows, lines, strict=False)]
    return ResidualTable(step=m["step"], ids=[r["id"] for r in rows], observed=np.array(obs).reshape(-1, k),
                         adjusted=np.array(adjusted).reshape(-1, k), units=m["units"].strip(), components=comps,
                         weights=np.array([_num(r, "weight", ln, path) for r, ln in zip(rows, lines, strict=False)]),
                         outlier=np.array([r["outlier"] == "1" for r in rows]),
                         check=np.array([r["check"] == "1" for r in rows]))


def write_residuals(path: StrPath, table: ResidualTable, *, overwrite: bool = False) -> Path:
    """Write a residual table CSV atomically (``ResidualTable.to_csv`` text); return the path."""
    return atomic_write_text(path, table.to_csv(), overwrite=overwrite)
