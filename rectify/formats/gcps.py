"""Ground control points: the GCP CSV, QGIS ``.points``, GeoJSON, GeoPackage and the GCPs embedded in a GeoTIFF.

========================  ===============================================  ==============================
file                      reader / writer                                  identified by
========================  ===============================================  ==============================
GCP CSV, QGIS ``.points`` :func:`read_gcps` / :func:`write_gcps`           its header (``id,col,row,x,y``)
GeoJSON                   :func:`read_gcps_geojson` / :func:`gcps_geojson_text`  suffix ``.geojson``, ``.json``
GeoPackage                :func:`read_gcps_gpkg` / :func:`write_gcps_gpkg`  suffix ``.gpkg``
GeoTIFF (embedded GCPs)   :func:`read_gcps_embedded`                        suffix ``.tif``, ``.tiff``
========================  ===============================================  ==============================

:func:`read_gcps` reads any of them by suffix, and a matches CSV as GCPs of the right image on the left.
The table is a :class:`rectify.geometry.points.GcpTable`: source pixels in the project's convention
(x = column right, y = row down, pixel centres at integers; QGIS and GDAL pixel corners are converted on
reading), target coordinates in the table's CRS (``# crs=`` comment line). Layout in ``docs/formats.md``.
"""

from __future__ import annotations

import io
import json
import math
import re
import sqlite3
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rectify.atomic import atomic_output, atomic_write_text, read_json
from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.formats.common import (
    MAX_POINT_ROWS,
    StrPath,
    TableReader,
    finite_number,
    need_columns,
    no_duplicates,
)
from rectify.formats.tables import check_crs_comment, read_matches_table
from rectify.geometry.crs import parse_crs
from rectify.geometry.points import GcpTable
from rectify.raster.io import _crs_string, open_raster

__all__ = [
    "GEOJSON_SUFFIXES", "GPKG_SUFFIXES", "TIFF_SUFFIXES",
    "read_gcps", "write_gcps", "gcps_text",
    "read_gcps_geojson", "gcps_geojson_text", "read_gcps_gpkg", "write_gcps_gpkg", "read_gcps_embedded",
    "has_embedded_gcps",
]

#: Suffixes read as GeoJSON, GeoPackage and GeoTIFF (embedded GCPs) by :func:`read_gcps`.
GEOJSON_SUFFIXES = (".geojson", ".json")
GPKG_SUFFIXES = (".gpkg",)
TIFF_SUFFIXES = (".tif", ".tiff", ".gtiff")


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
    with TableReader(path) as t:
        fields = list(t.fields)
        if "col_left" in fields and "x" not in fields:  # a matches CSV: fit the right image to the left
            m, crs = read_matches_table(t, max_rows=MAX_POINT_ROWS)  # GCPs: the GCP table's limit
            return GcpTable(m.ids, m.right, m.left, None, np.zeros(len(m), dtype=bool), crs)
        if "mapX" in fields:
            sx = "sourceX" if "sourceX" in fields else "pixelX"
            sy = "sourceY" if "sourceY" in fields else "pixelY"
            need_columns(fields, ("mapX", "mapY", sx, sy), path)
            cols = t.read("GCP rows", numbers=("mapX", "mapY", sx, sy), texts=("enable",))
            n = len(cols)
            ids = tuple(str(k + 1) for k in range(n))
            # QGIS: corner convention, row axis negative
            pix = np.column_stack([cols.numbers[sx] - 0.5, -cols.numbers[sy] - 0.5])
            tgt = np.column_stack([cols.numbers["mapX"], cols.numbers["mapY"]])
            enable = cols.texts["enable"] if "enable" in fields else ["1"] * n
            chk = np.array([e in ("0", "false", "False") for e in enable], dtype=bool)
            z = None
        else:
            need_columns(fields, ("id", "col", "row", "x", "y"), path)
            has_z = "z" in fields
            cols = t.read("GCP rows", numbers=("col", "row", "x", "y") + (("z",) if has_z else ()),
                          texts=("id", "check") if "check" in fields else ("id",))
            ids = tuple(cols.texts.pop("id"))
            pix = np.column_stack([cols.numbers.pop("col"), cols.numbers.pop("row")])
            tgt = np.column_stack([cols.numbers.pop("x"), cols.numbers.pop("y")])
            z = cols.numbers.pop("z") if has_z else None
            flags = cols.texts.pop("check", None) or [""] * len(ids)
            bad = next((k for k, c in enumerate(flags) if c not in ("0", "1", "")), None)
            if bad is not None:
                raise InvalidInputError(f"{str(path)!r} line {int(cols.lines[bad])}: column 'check' must be 0 or 1; "
                                        f"got {flags[bad]!r}")
            chk = np.array([c == "1" for c in flags], dtype=bool)
            del flags
    check_crs_comment(cols)
    no_duplicates(ids, path, "GCP id(s)")
    return GcpTable(ids, pix.reshape(-1, 2), tgt.reshape(-1, 2), z, chk, cols.crs)


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


# --------------------------------------------------------------------------- GeoJSON, GeoPackage, GeoTIFF
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
    label = f"{str(path)!r} {where}: {key!r}"
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise InvalidInputError(f"{label} is not a number: {v!r}")
    return finite_number(v, label)


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
    no_duplicates(ids, path, "GCP id(s)")
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
    doc = read_json(path, "GeoJSON GCP file")
    if not isinstance(doc, dict) or doc.get("type") not in ("FeatureCollection", "Feature"):
        got = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
        raise InvalidInputError(f"{str(path)!r}: expected a GeoJSON FeatureCollection of Point features; got {got!r}")
    feats = doc.get("features") if doc["type"] == "FeatureCollection" else [doc]
    if not isinstance(feats, list):
        raise InvalidInputError(f"{str(path)!r}: 'features' must be a list; got {type(feats).__name__}")
    if len(feats) > MAX_POINT_ROWS:
        raise InvalidInputError(f"{str(path)!r} has {len(feats)} features, more than the {MAX_POINT_ROWS} GCPs a GCP "
                                "table may have")
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
    b = bytes(blob) if isinstance(blob, (bytes, bytearray, memoryview)) else b""
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
    p = Path(path)
    if not p.is_file():
        raise RasterIOError(f"file not found: {str(p)!r}")
    try:
        # a URI, percent-encoded: '?', '#' and '%' in the name stay part of it; mode=ro creates nothing
        con = sqlite3.connect(p.resolve().as_uri() + "?mode=ro", uri=True)
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
        cur = con.execute(f"SELECT * FROM {_sql_name(str(table))} LIMIT ?", (MAX_POINT_ROWS + 1,))
        names = [d[0] for d in cur.description]
        records = cur.fetchall()
        if len(records) > MAX_POINT_ROWS:
            raise InvalidInputError(f"{str(p)!r} layer {table!r} has more than {MAX_POINT_ROWS} features, the most "
                                    "GCPs a GCP table may have")
    except sqlite3.Error as err:
        raise InvalidInputError(f"{str(p)!r} is not a readable GeoPackage: {err}") from None
    finally:
        con.close()
    if gcol not in names:
        raise InvalidInputError(f"{str(p)!r} layer {table!r} has no geometry column {gcol!r}")
    if crs is not None:
        try:
            parse_crs(crs)
        except CRSError as err:
            raise CRSError(f"{str(p)!r} layer {table!r}: {err}") from None
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


def _sql_name(name: str) -> str:
    """An SQL identifier quoted for SQLite (double quotes, inner ones doubled)."""
    return '"' + name.replace('"', '""') + '"'


def _gpkg_blob(x: float, y: float, z: float | None, srs_id: int) -> bytes:
    """A GeoPackage geometry: the ``GP`` header (little-endian, no envelope) and a WKB Point (Z)."""
    head = b"GP\x00\x01" + np.array([srs_id], "<i4").tobytes()
    wkb = b"\x01" + np.array([1001 if z is not None else 1], "<u4").tobytes()
    return head + wkb + np.array([x, y] + ([z] if z is not None else []), "<f8").tobytes()


def write_gcps_gpkg(path: StrPath, gcps: GcpTable, *, overwrite: bool = False, layer: str = "gcps") -> Path:
    """Write a GCP table as a minimal GeoPackage point layer (``id``, ``col``, ``row``, ``check``; EPSG CRS
    or undefined), written beside the destination and renamed into place."""
    m = re.fullmatch(r"EPSG:(\d+)", gcps.crs or "")
    srs_id = int(m[1]) if m else 0
    with atomic_output(path, overwrite=overwrite) as tmp:
        try:
            con = sqlite3.connect(Path(tmp).resolve().as_uri() + "?mode=rw", uri=True)
        except sqlite3.Error as err:
            raise RasterIOError(f"cannot write {str(path)!r}: {err}") from err
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
                con.execute("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, 'EPSG', ?, ?, NULL)",
                            (gcps.crs, srs_id, srs_id, parse_crs(gcps.crs).to_wkt()))
            con.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, srs_id) VALUES "
                        "(?, 'features', ?, ?)", (layer, layer, srs_id))
            con.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', 'POINT', ?, ?, 0)",
                        (layer, srs_id, int(gcps.z is not None)))
            con.execute(f"CREATE TABLE {_sql_name(layer)} (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom BLOB, "
                        "id TEXT, col DOUBLE, row DOUBLE, \"check\" INTEGER)")
            for i in range(len(gcps)):
                z = float(gcps.z[i]) if gcps.z is not None else None
                con.execute(f'INSERT INTO {_sql_name(layer)} (geom, id, col, row, "check") VALUES (?, ?, ?, ?, ?)',
                            (_gpkg_blob(float(gcps.target[i, 0]), float(gcps.target[i, 1]), z, srs_id),
                             gcps.ids[i], float(gcps.pixel[i, 0]), float(gcps.pixel[i, 1]), int(gcps.check[i])))
            con.commit()
        except sqlite3.Error as err:
            raise RasterIOError(f"cannot write {str(path)!r}: {err}") from err
        finally:
            con.close()
    return Path(path)


def read_gcps_embedded(path: StrPath) -> GcpTable:
    """The GCPs embedded in a raster (GeoTIFF tie points read by rasterio/GDAL, pixel corners converted to
    the project's centres) with their CRS; InvalidInputError when the raster carries none."""
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
    try:
        with open_raster(Path(path)) as ds:
            return bool(ds.gcps[0])
    except RasterIOError:
        return False
