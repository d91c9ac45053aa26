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
:meth:`rectify.actions.workspace.Workspace.output` as well as standalone (atomic, via
:func:`rectify.atomic.atomic_write_text`).
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

from rectify.atomic import atomic_write_text, read_json
from rectify.errors import InvalidInputError, RasterIOError
from rectify.geometry.camera import Camera
from rectify.geometry.residuals import ResidualTable

__all__ = [
    "FORMAT_PREFIX", "CAMERA_VERSION", "TRANSFORM_VERSION", "REPORT_VERSION",
    "stamp", "check_format",
    "GcpTable", "Matches", "ControlTable",
    "read_gcps", "write_gcps", "gcps_text",
    "read_gcps_geojson", "gcps_geojson_text", "read_gcps_gpkg", "write_gcps_gpkg", "read_gcps_embedded",
    "has_embedded_gcps",
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
    By suffix: ``.geojson``/``.json`` (:func:`read_gcps_geojson`), ``.gpkg`` (:func:`read_gcps_gpkg`),
    ``.tif``/``.tiff`` (the GCPs embedded in the raster, :func:`read_gcps_embedded`).

    Returns
    -------
    GcpTable
        ``pixel`` (N, 2) source pixels, ``target`` (N, 2) in the ``crs`` units (or target pixels).
    """
    suffix = Path(path).suffix.lower()
    if suffix in GEOJSON_SUFFIXES:
        return read_gcps_geojson(path)
    if suffix in GPKG_SUFFIXES:
        return read_gcps_gpkg(path)
    if suffix in TIFF_SUFFIXES:
        return read_gcps_embedded(path)
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
    """Write a GCP CSV atomically (:func:`gcps_text`), or GeoJSON / GeoPackage by suffix; return the path."""
    suffix = Path(path).suffix.lower()
    if suffix in GEOJSON_SUFFIXES:
        return atomic_write_text(path, gcps_geojson_text(gcps), overwrite=overwrite)
    if suffix in GPKG_SUFFIXES:
        return write_gcps_gpkg(path, gcps, overwrite=overwrite)
    return atomic_write_text(path, gcps_text(gcps), overwrite=overwrite)


# --------------------------------------------------------------------------- GCPs: GeoJSON, GeoPackage, GeoTIFF
#: Suffixes read as GeoJSON, GeoPackage and GeoTIFF (embedded GCPs) by :func:`read_gcps`.
GEOJSON_SUFFIXES = (".geojson", ".json")
GPKG_SUFFIXES = (".gpkg",)
TIFF_SUFFIXES = (".tif", ".tiff", ".gtiff")
_COL_KEYS = (("col", "row", "centre"), ("pixelX", "pixelY", "corner"), ("sourceX", "sourceY", "corner"),
             ("px", "py", "corner"))


def _crs_name(value: Any) -> str | None:
    """A CRS given as ``EPSG:n``, ``urn:ogc:def:crs:EPSG::n``, an OGC URL, a GeoJSON 2008 ``crs`` member or WKT."""
    if value is None or value == "":
        return None
    if isinstance(value, Mapping):
        props = value.get("properties")
        return _crs_name(props.get("name") if isinstance(props, Mapping) else None)
    s = str(value).strip()
    m = re.search(r"EPSG[:/]+(?:[\d.]*[:/]+)?(\d+)$", s, flags=re.IGNORECASE)
    if m:
        return f"EPSG:{m[1]}"
    if re.search(r"CRS84$", s, flags=re.IGNORECASE):
        return "OGC:CRS84"
    return s


def _pixel_of(props: Mapping[str, Any], where: str, path: StrPath) -> tuple[float, float]:
    """(col, row) in the project's convention from a feature's properties (see docs/formats.md)."""
    for kx, ky, conv in _COL_KEYS:
        if kx in props and ky in props:
            x, y = _json_num(props[kx], kx, where, path), _json_num(props[ky], ky, where, path)
            if conv == "centre":
                return x, y
            # pixel-corner convention (QGIS, GDAL); a negative row is QGIS's upward row axis
            return x - 0.5, (-y if y < 0 else y) - 0.5
    raise InvalidInputError(f"{str(path)!r} {where}: no pixel coordinates; expected properties 'col'/'row', "
                            f"'pixelX'/'pixelY' or 'sourceX'/'sourceY'; got {sorted(props)}")


def _json_num(v: Any, key: str, where: str, path: StrPath) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise InvalidInputError(f"{str(path)!r} {where}: {key!r} is not a number: {v!r}")
    try:
        f = float(v)
    except ValueError:
        raise InvalidInputError(f"{str(path)!r} {where}: {key!r} is not a number: {v!r}") from None
    if not math.isfinite(f):
        raise InvalidInputError(f"{str(path)!r} {where}: {key!r} is not finite: {v!r}")
    return f


def _check_flag(props: Mapping[str, Any]) -> bool:
    """A check point: ``check`` true/1, or ``enable``/``enabled`` false/0 (QGIS)."""
    c = props.get("check")
    if c is not None:
        return str(c).strip().lower() in ("1", "true", "yes")
    e = props.get("enable", props.get("enabled"))
    return e is not None and str(e).strip().lower() in ("0", "false", "no")


def _gcp_rows_table(rows: list[tuple[str, float, float, float, float, float | None, bool]], crs: str | None,
                    path: StrPath) -> GcpTable:
    if not rows:
        raise InvalidInputError(f"{str(path)!r} holds no GCP points")
    ids = [r[0] for r in rows]
    _no_duplicates(ids, path, "GCP id(s)")
    zs = [r[5] for r in rows]
    z = np.array(zs, dtype=float) if all(v is not None for v in zs) else None
    return GcpTable(tuple(ids), np.array([r[1:3] for r in rows], dtype=float).reshape(-1, 2),
                    np.array([r[3:5] for r in rows], dtype=float).reshape(-1, 2), z,
                    np.array([r[6] for r in rows], dtype=bool), crs)


def _default_lonlat(rows: list, crs: str | None) -> str | None:
    """RFC 7946: GeoJSON without a CRS is WGS 84 longitude/latitude; kept unset when the values cannot be."""
    if crs is not None:
        return crs
    xy = np.array([r[3:5] for r in rows], dtype=float).reshape(-1, 2)
    ok = len(xy) and (np.abs(xy[:, 0]) <= 180).all() and (np.abs(xy[:, 1]) <= 90).all()
    return "EPSG:4326" if ok else None


def read_gcps_geojson(path: StrPath) -> GcpTable:
    """Read GCPs from a GeoJSON FeatureCollection of Point features (schema in ``docs/formats.md``).

    World coordinates come from the Point geometry (x, y[, z]), or from ``mapX``/``mapY`` (or ``x``/``y``)
    properties when the geometry is null; source pixels from ``col``/``row`` (pixel centres at integers)
    or ``pixelX``/``pixelY``/``sourceX``/``sourceY`` (pixel corners; negative rows as QGIS writes them).
    The CRS is the ``crs`` member, else a ``crs`` property, else EPSG:4326 (RFC 7946) when the values
    are longitudes/latitudes. Ids from ``id``/``name``/``gcp_id`` properties or the feature ``id``.
    """
    text = _read_text(path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise InvalidInputError(f"{str(path)!r} is not valid JSON: {err}") from None
    if not isinstance(doc, dict) or doc.get("type") not in ("FeatureCollection", "Feature"):
        got = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
        raise InvalidInputError(f"{str(path)!r}: expected a GeoJSON FeatureCollection of Point features; got {got!r}")
    feats = doc.get("features") if doc["type"] == "FeatureCollection" else [doc]
    if not isinstance(feats, list):
        raise InvalidInputError(f"{str(path)!r}: 'features' must be a list; got {type(feats).__name__}")
    crs = _crs_name(doc.get("crs"))
    rows: list[tuple[str, float, float, float, float, float | None, bool]] = []
    for k, f in enumerate(feats):
        where = f"feature {k}"
        if not isinstance(f, dict):
            raise InvalidInputError(f"{str(path)!r} {where}: not a GeoJSON Feature: {f!r:.60}")
        props = f.get("properties") or {}
        if not isinstance(props, dict):
            raise InvalidInputError(f"{str(path)!r} {where}: 'properties' must be an object")
        geom = f.get("geometry")
        z: float | None = None
        if geom is not None:
            if not isinstance(geom, dict) or geom.get("type") != "Point":
                got = geom.get("type") if isinstance(geom, dict) else geom
                raise InvalidInputError(f"{str(path)!r} {where}: geometry must be a Point; got {got!r}")
            c = geom.get("coordinates")
            if not isinstance(c, list) or len(c) < 2:
                raise InvalidInputError(f"{str(path)!r} {where}: Point coordinates must be [x, y(, z)]; got {c!r}")
            x, y = _json_num(c[0], "x", where, path), _json_num(c[1], "y", where, path)
            if len(c) > 2:
                z = _json_num(c[2], "z", where, path)
        else:
            kx, ky = ("mapX", "mapY") if "mapX" in props else ("x", "y")
            if kx not in props or ky not in props:
                raise InvalidInputError(f"{str(path)!r} {where}: no Point geometry and no mapX/mapY properties")
            x, y = _json_num(props[kx], kx, where, path), _json_num(props[ky], ky, where, path)
        if z is None and props.get("z") not in (None, ""):
            z = _json_num(props["z"], "z", where, path)
        col, row = _pixel_of(props, where, path)
        gid = next((props[key] for key in ("id", "name", "gcp_id", "label") if props.get(key) not in (None, "")),
                   f.get("id", k + 1))
        if crs is None and props.get("crs"):
            crs = _crs_name(props["crs"])
        rows.append((str(gid), col, row, x, y, z, _check_flag(props)))
    return _gcp_rows_table(rows, _default_lonlat(rows, crs), path)


def gcps_geojson_text(gcps: GcpTable) -> str:
    """GeoJSON text of a GCP table: Point features (world x, y[, z]) with ``id``, ``col``, ``row``
    (pixel centres at integers) and ``check`` properties, and a ``crs`` member when the table has one."""
    feats = []
    for i in range(len(gcps)):
        c = [float(v) for v in gcps.target[i]] + ([float(gcps.z[i])] if gcps.z is not None else [])
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": c},
                      "properties": {"id": gcps.ids[i], "col": float(gcps.pixel[i, 0]),
                                     "row": float(gcps.pixel[i, 1]), "check": int(bool(gcps.check[i]))}})
    doc: dict[str, Any] = {"type": "FeatureCollection"}
    if gcps.crs:
        doc["crs"] = {"type": "name", "properties": {"name": gcps.crs}}
    doc["features"] = feats
    return json.dumps(doc, indent=1) + "\n"


def _gpkg_point(blob: Any, where: str, path: StrPath) -> tuple[float, float, float | None]:
    """x, y[, z] of a GeoPackage geometry blob: the ``GP`` header (with its envelope) and a WKB Point."""
    b = bytes(blob) if blob is not None else b""
    if len(b) < 8 or b[:2] != b"GP":
        raise InvalidInputError(f"{str(path)!r} {where}: not a GeoPackage geometry")
    flags = b[3]
    env = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}.get((flags >> 1) & 7)
    if env is None:
        raise InvalidInputError(f"{str(path)!r} {where}: bad GeoPackage envelope flag {flags:#x}")
    w = b[8 + env:]
    if len(w) < 21:
        raise InvalidInputError(f"{str(path)!r} {where}: empty or truncated geometry")
    end = "<" if w[0] == 1 else ">"
    gtype = int(np.frombuffer(w[1:5], dtype=end + "u4")[0])
    has_z = bool(gtype & 0x80000000) or (gtype % 1000 == 1 and gtype // 1000 in (1, 3))
    base = (gtype & 0x0FFFFFFF) % 1000
    if base != 1:
        raise InvalidInputError(f"{str(path)!r} {where}: geometry must be a Point; got WKB type {gtype}")
    n = 3 if has_z else 2
    v = np.frombuffer(w[5:5 + 8 * n], dtype=end + "f8")
    if len(v) < n or not np.isfinite(v[:2]).all():
        raise InvalidInputError(f"{str(path)!r} {where}: empty or non-finite Point {v.tolist()}")
    return float(v[0]), float(v[1]), (float(v[2]) if has_z else None)


def read_gcps_gpkg(path: StrPath, layer: str | None = None) -> GcpTable:
    """Read GCPs from a GeoPackage point layer (the first feature layer, or ``layer``).

    Read with the standard library's ``sqlite3`` (a GeoPackage is an SQLite file): the geometry column
    (GeoPackage header + WKB Point) gives the world coordinates and the layer's ``srs_id`` the CRS;
    the attribute columns follow the GeoJSON property names (``col``/``row``, ``pixelX``/``pixelY`` or
    ``sourceX``/``sourceY``; ``id``/``name``; ``check`` or ``enable``).
    """
    import sqlite3

    p = Path(path)
    if not p.is_file():
        raise RasterIOError(f"file not found: {str(p)!r}")
    try:
        con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    except sqlite3.Error as err:
        raise RasterIOError(f"cannot read {str(p)!r}: {err}") from err
    try:
        try:
            layers = con.execute("SELECT c.table_name, g.column_name, g.srs_id FROM gpkg_contents c JOIN "
                                 "gpkg_geometry_columns g ON g.table_name = c.table_name "
                                 "WHERE c.data_type = 'features' ORDER BY c.table_name").fetchall()
        except sqlite3.DatabaseError as err:
            raise InvalidInputError(f"{str(p)!r} is not a GeoPackage: {err}") from None
        if not layers:
            raise InvalidInputError(f"{str(p)!r} has no feature layer")
        if layer is not None:
            layers = [t for t in layers if t[0] == layer]
            if not layers:
                raise InvalidInputError(f"{str(p)!r} has no feature layer {layer!r}")
        table, gcol, srs_id = layers[0]
        crs = None
        srs = con.execute("SELECT organization, organization_coordsys_id, definition FROM gpkg_spatial_ref_sys "
                          "WHERE srs_id = ?", (srs_id,)).fetchone()
        if srs is not None and srs_id not in (0, -1):
            org, code, definition = srs
            crs = f"{str(org).upper()}:{code}" if org and str(org).upper() == "EPSG" else (definition or None)
        cur = con.execute(f'SELECT * FROM "{table}"')
        names = [d[0] for d in cur.description]
        records = cur.fetchall()
    finally:
        con.close()
    rows: list[tuple[str, float, float, float, float, float | None, bool]] = []
    for k, rec in enumerate(records):
        props = {n: v for n, v in zip(names, rec, strict=True) if n != gcol}
        where = f"layer {table!r} row {k + 1}"
        x, y, z = _gpkg_point(rec[names.index(gcol)], where, p)
        if z is None and props.get("z") not in (None, ""):
            z = _json_num(props["z"], "z", where, p)
        col, row = _pixel_of(props, where, p)
        gid = next((props[key] for key in ("id", "name", "gcp_id", "label") if props.get(key) not in (None, "")),
                   props.get("fid", k + 1))
        rows.append((str(gid), col, row, x, y, z, _check_flag(props)))
    return _gcp_rows_table(rows, crs, p)


def _gpkg_blob(x: float, y: float, z: float | None, srs_id: int) -> bytes:
    """A GeoPackage geometry: the ``GP`` header (little-endian, no envelope) and a WKB Point (Z)."""
    head = b"GP\x00\x01" + np.array([srs_id], "<i4").tobytes()
    wkb = b"\x01" + np.array([1001 if z is not None else 1], "<u4").tobytes()
    return head + wkb + np.array([x, y] + ([z] if z is not None else []), "<f8").tobytes()


def write_gcps_gpkg(path: StrPath, gcps: GcpTable, *, overwrite: bool = False, layer: str = "gcps") -> Path:
    """Write a GCP table as a minimal GeoPackage point layer (``id``, ``col``, ``row``, ``check``; EPSG CRS
    or undefined), written beside the destination and renamed into place."""
    import sqlite3

    from rectify.atomic import atomic_output

    m = re.fullmatch(r"EPSG:(\d+)", gcps.crs or "")
    srs_id = int(m[1]) if m else 0
    with atomic_output(path, overwrite=overwrite) as tmp:
        con = sqlite3.connect(str(tmp))
        try:
            con.executescript(
                "PRAGMA application_id = 1196444487; PRAGMA user_version = 10300;"
                "CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY, "
                "organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL, "
                "description TEXT);"
                "CREATE TABLE gpkg_contents (table_name TEXT PRIMARY KEY, data_type TEXT NOT NULL, identifier TEXT, "
                "description TEXT DEFAULT '', last_change DATETIME, min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, "
                "max_y DOUBLE, srs_id INTEGER);"
                "CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL, "
                "geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL);")
            con.execute("INSERT INTO gpkg_spatial_ref_sys VALUES ('Undefined Cartesian SRS', 0, 'NONE', 0, "
                        "'undefined', NULL)")
            if srs_id:
                from rectify.geometry.crs import parse_crs

                con.execute("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, 'EPSG', ?, ?, NULL)",
                            (gcps.crs, srs_id, srs_id, parse_crs(gcps.crs).to_wkt()))
            con.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, srs_id) VALUES "
                        "(?, 'features', ?, ?)", (layer, layer, srs_id))
            con.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', 'POINT', ?, ?, 0)",
                        (layer, srs_id, int(gcps.z is not None)))
            con.execute(f'CREATE TABLE "{layer}" (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom BLOB, id TEXT, '
                        "col DOUBLE, row DOUBLE, \"check\" INTEGER)")
            for i in range(len(gcps)):
                z = float(gcps.z[i]) if gcps.z is not None else None
                con.execute(f'INSERT INTO "{layer}" (geom, id, col, row, "check") VALUES (?, ?, ?, ?, ?)',
                            (_gpkg_blob(float(gcps.target[i, 0]), float(gcps.target[i, 1]), z, srs_id),
                             gcps.ids[i], float(gcps.pixel[i, 0]), float(gcps.pixel[i, 1]), int(gcps.check[i])))
            con.commit()
        finally:
            con.close()
    return Path(path)


def read_gcps_embedded(path: StrPath) -> GcpTable:
    """The GCPs embedded in a raster (GeoTIFF tie points read by rasterio/GDAL, pixel corners converted to
    the project's centres) with their CRS; InvalidInputError when the raster carries none."""
    from rectify.raster.io import _crs_string, open_raster

    with open_raster(Path(path)) as ds:
        pts, crs = ds.gcps
    if not pts:
        raise InvalidInputError(f"{str(path)!r} carries no embedded GCPs")
    rows: list[tuple[str, float, float, float, float, float | None, bool]] = []
    for k, g in enumerate(pts):
        vals = [g.col, g.row, g.x, g.y]
        if not all(v is not None and math.isfinite(v) for v in vals):
            raise InvalidInputError(f"{str(path)!r} embedded GCP {k + 1}: non-finite value {vals}")
        z = float(g.z) if g.z is not None and math.isfinite(g.z) and g.z != 0 else None
        rows.append((str(g.id or k + 1), g.col - 0.5, g.row - 0.5, g.x, g.y, z, False))
    if any(r[5] is None for r in rows):
        rows = [(*r[:5], None, r[6]) for r in rows]
    return _gcp_rows_table(rows, _crs_string(crs), path)


def has_embedded_gcps(path: StrPath) -> bool:
    """Whether the raster ``path`` carries GCPs (False for unreadable files: their reader names the problem)."""
    from rectify.raster.io import open_raster

    try:
        with open_raster(Path(path)) as ds:
            return bool(ds.gcps[0])
    except RasterIOError:
        return False


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
    """The matches CSV text: positions with 6 decimals (1e-6 px), scores with 6 significant digits (empty
    for a NaN score: a match the refinement could not refine, kept at its raw position)."""
    buf = io.StringIO()
    cols = ["id", "col_left", "row_left", "col_right", "row_right"]
    if matches.score is not None:
        cols.append("score")
    buf.write(",".join(cols) + "\n")
    for i in range(len(matches)):
        vals = [matches.ids[i]] + [f"{v:.6f}" for v in (*matches.left[i], *matches.right[i])]
        if matches.score is not None:  # NaN (a match kept unrefined) is written empty
            vals.append(f"{matches.score[i]:.6g}" if math.isfinite(matches.score[i]) else "")
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
    from rectify.geometry.transforms import transform_to_dict

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
    from rectify.geometry.transforms import transform_from_dict

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
