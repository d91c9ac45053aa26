"""Files of a camera calibration: the camera JSON read back into the calibration's interior orientation,
and the observation and field CSV files (``stereo calibrate --points/--field``).

Camera JSON
-----------
Written by :func:`rectify.formats.camera.intrinsics_document` (the one writer of the camera JSON; layout
there and in ``docs/formats.md``); :func:`camera_from_dict` reads a version-2 pixel or millimetre camera,
or a version-1 file, into :class:`stereo.calibration.model.Intrinsics` with its standard errors and sigma0.

Observation CSV (``--points``)
------------------------------
One row per measured image point; ``#`` lines are comments::

    view,point,col,row
    img01,p1,1021.37,733.05

``col, row`` are pixels (x = column right, y = row down, pixel centres at
integers). Optional columns ``x, y, z`` give the object coordinates in the
row itself (then no field file is needed).

Field CSV (``--field``)
-----------------------
Object coordinates of the target points (plane or 3D), any unit::

    point,x,y,z
    p1,0.0,0.0,0.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.common import FORMAT_PREFIX, MAX_MATCH_ROWS, Columns, TableReader
from stereo.calibration.model import Intrinsics
from stereo.calibration.views import TargetView

__all__ = ["CameraFile", "camera_from_dict", "read_field_csv", "read_observations_csv", "views_from_csv"]

F64 = NDArray[np.float64]
CAMERA_FORMAT = FORMAT_PREFIX + "camera"
_DIST = ("k1", "k2", "k3", "p1", "p2")


# ------------------------------------------------------------------- camera JSON
@dataclass(frozen=True)
class CameraFile:
    """What a camera JSON holds: the interior orientation, its standard errors and sigma0."""

    intrinsics: Intrinsics
    std_errors: dict[str, float] = field(default_factory=dict)
    sigma0_px: float | None = None
    pixel_size_mm: float | None = None


def _camera_num(d: dict[str, Any], k: str) -> float:
    v = d[k]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise CalibrationError(f"camera JSON key {k!r} must be a finite number; got {v!r}")
    return float(v)


def _camera_pair(d: dict[str, Any], k: str) -> tuple[float, float]:
    v = d[k]
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise CalibrationError(f"camera JSON key {k!r} must be two numbers; got {v!r}")
    return _camera_num({k: v[0]}, k), _camera_num({k: v[1]}, k)


def camera_from_dict(d: dict[str, Any]) -> CameraFile:
    """Read a camera JSON object (version 2 pixel or millimetre camera, or a version-1 file).

    The calibration's interior orientation has fx and fy but no skew: a ``skew_px`` other than 0 is
    refused (:func:`rectify.formats.camera.read_camera` reads such a file as a ``Camera``).

    Raises
    ------
    CalibrationError
        Missing or unknown keys (named), bad values.
    """
    if not isinstance(d, dict):
        raise CalibrationError(f"camera JSON must be an object; got {type(d).__name__}")
    if "format" in d and d["format"] != CAMERA_FORMAT:
        raise CalibrationError(f"camera JSON format {d['format']!r} is not {CAMERA_FORMAT!r}")
    if d.get("version", 1) not in (1, 2):
        raise CalibrationError(f"camera JSON version {d.get('version')!r} is not supported (1 or 2)")
    known = {"format", "version", "width", "height", "focal_length_px", "fx_px", "fy_px", "skew_px",
             "principal_point_px",
             "distortion", "point_of_symmetry_px", "std_errors", "sigma0_px", "focal_length_mm", "pixel_size_mm",
             "principal_point_mm", "point_of_symmetry_mm", "name", "comment", "sigma0_mm"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise CalibrationError(f"camera JSON has unknown key(s) {unknown}")
    for k in ("width", "height"):
        if k not in d:
            raise CalibrationError(f"camera JSON lacks required key {k!r}")
    w, h = d["width"], d["height"]
    for k, v in (("width", w), ("height", h)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or int(v) != v or v <= 0:
            raise CalibrationError(f"camera JSON key {k!r} must be a positive whole number of pixels; got {v!r}")
    w, h = int(w), int(h)
    dist = d.get("distortion") or {}
    if not isinstance(dist, dict) or set(dist) - set(_DIST):
        raise CalibrationError(f"camera JSON `distortion` must map {list(_DIST)} to numbers; got {dist!r}")
    dd = {k: _camera_num(dist, k) if k in dist else 0.0 for k in _DIST}
    ps: float | None = None
    sym: tuple[float | None, float | None] = (None, None)
    if "pixel_size_mm" in d:
        ps = _camera_num(d, "pixel_size_mm")
        if ps <= 0 or "focal_length_mm" not in d:
            raise CalibrationError("a millimetre camera needs focal_length_mm and pixel_size_mm > 0")
        f = _camera_num(d, "focal_length_mm") / ps
        fx = fy = f
        x0, y0 = _camera_pair(d, "principal_point_mm") if "principal_point_mm" in d else (0.0, 0.0)
        cx, cy = (w - 1) / 2.0 + x0 / ps, (h - 1) / 2.0 - y0 / ps
        if "point_of_symmetry_mm" in d:
            xs, ys = _camera_pair(d, "point_of_symmetry_mm")
            sym = ((w - 1) / 2.0 + xs / ps, (h - 1) / 2.0 - ys / ps)
    else:
        if "focal_length_px" in d:
            fx = fy = _camera_num(d, "focal_length_px")
        elif "fx_px" in d and "fy_px" in d:
            fx, fy = _camera_num(d, "fx_px"), _camera_num(d, "fy_px")
        else:
            raise CalibrationError("camera JSON needs focal_length_px (or fx_px and fy_px), or focal_length_mm "
                                   "with pixel_size_mm")
        if "skew_px" in d and _camera_num(d, "skew_px") != 0.0:
            raise CalibrationError(f"camera JSON `skew_px` {d['skew_px']!r}: the calibration's camera model has no "
                                   "skew (the rest of the project reads it: rectify.formats.camera.read_camera)")
        if "principal_point_px" not in d:
            raise CalibrationError("a pixel camera JSON needs principal_point_px")
        cx, cy = _camera_pair(d, "principal_point_px")
        if "point_of_symmetry_px" in d:
            sym = _camera_pair(d, "point_of_symmetry_px")
    intr = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h, sx=sym[0], sy=sym[1], **dd)
    se = d.get("std_errors") or {}
    if not isinstance(se, dict):
        raise CalibrationError(f"camera JSON `std_errors` must be an object; got {se!r}")
    s0 = d.get("sigma0_px")
    return CameraFile(intr, {str(k): _camera_num(se, k) for k in se},
                      None if s0 is None else _camera_num(d, "sigma0_px"), ps)


# ---------------------------------------------------------------------- CSV files
def _open(path: str | Path, what: str, texts: tuple[str, ...], numbers: tuple[str, ...],
          optional: tuple[str, ...] = ()) -> tuple[Columns, str]:
    """The columns of a calibration CSV (header names lower-case): ``texts`` and ``numbers``, and the
    ``optional`` numbers when the header has them all."""
    label = f"{what} {str(path)!r}"
    need = [*texts, *numbers]
    try:
        with TableReader(path, lower=True) as t:
            miss = [c for c in need if c not in t.fields]
            if miss:
                raise InvalidInputError(f"{label} lacks column(s) {miss}; expected {','.join(need)}"
                                        f"{'[,' + ','.join(optional) + ']' if optional else ''}")
            extra = optional if optional and all(c in t.fields for c in optional) else ()
            cols = t.read("rows", numbers=(*numbers, *extra), texts=texts, max_rows=MAX_MATCH_ROWS)
    except InvalidInputError as err:
        msg = str(err)
        if "has no header and no rows" in msg:
            raise InvalidInputError(f"{label} is empty") from None
        raise
    return cols, label


def read_field_csv(path: str | Path) -> dict[str, F64]:
    """Read a field CSV ``point,x,y,z`` -> {point id: (3,) object coordinates}.

    Read as a stream; more than :data:`rectify.formats.common.MAX_MATCH_ROWS` rows are refused.

    Raises
    ------
    InvalidInputError
        Missing columns, bad numbers, duplicate point ids, too many rows.
    """
    cols, what = _open(path, "field file", ("point",), ("x", "y", "z"))
    xyz = np.column_stack([cols.numbers[c] for c in ("x", "y", "z")])
    out: dict[str, F64] = {}
    for k, pid in enumerate(cols.texts["point"]):
        if pid in out:
            raise InvalidInputError(f"{what} line {cols.lines[k]}: duplicate point {pid!r}")
        out[pid] = xyz[k]
    return out


def read_observations_csv(path: str | Path) -> tuple[list[tuple[str, str, float, float]], dict[str, F64]]:
    """Read an observation CSV -> ([(view, point, col, row), ...], {point: xyz} from optional x,y,z columns).

    Read as a stream; more than :data:`rectify.formats.common.MAX_MATCH_ROWS` rows are refused.
    """
    cols, what = _open(path, "observation file", ("view", "point"), ("col", "row"), ("x", "y", "z"))
    has_xyz = "x" in cols.numbers
    views, points, lines = cols.texts["view"], cols.texts["point"], cols.lines
    col, row = cols.numbers["col"].tolist(), cols.numbers["row"].tolist()
    xyz_rows = np.column_stack([cols.numbers[c] for c in ("x", "y", "z")]) if has_xyz else None
    obs: list[tuple[str, str, float, float]] = []
    xyz: dict[str, F64] = {}
    seen: set[tuple[str, str]] = set()
    for k, (view, pid) in enumerate(zip(views, points, strict=True)):
        if (view, pid) in seen:
            raise InvalidInputError(f"{what} line {lines[k]}: point {pid!r} measured twice in view {view!r}")
        seen.add((view, pid))
        obs.append((view, pid, col[k], row[k]))
        if xyz_rows is not None:
            q = xyz_rows[k]
            if pid in xyz and not np.allclose(xyz[pid], q):
                raise InvalidInputError(f"{what} line {lines[k]}: point {pid!r} has two different object coordinates")
            xyz[pid] = q
    return obs, xyz


def views_from_csv(points_path: str | Path, field_path: str | Path | None = None) -> list[TargetView]:
    """Build views from an observation CSV and (optionally) a field CSV.

    Raises
    ------
    InvalidInputError
        Points without object coordinates (named), or no object coordinates at all.
    """
    obs, xyz = read_observations_csv(points_path)
    if field_path is not None:
        field = read_field_csv(field_path)
        xyz = {**xyz, **field}
    if not xyz:
        raise InvalidInputError(f"no object coordinates: give a field file or x,y,z columns in {str(points_path)!r}")
    unknown = sorted({pid for _, pid, _, _ in obs if pid not in xyz})
    if unknown:
        raise CalibrationError(f"{len(unknown)} measured point(s) have no object coordinates: {unknown[:5]}")
    order: list[str] = []
    by_view: dict[str, list[tuple[str, float, float]]] = {}
    for view, pid, c, r in obs:
        if view not in by_view:
            order.append(view)
            by_view[view] = []
        by_view[view].append((pid, c, r))
    out = []
    for v in order:
        items = by_view[v]
        out.append(TargetView(v, np.array([xyz[p] for p, _, _ in items]), np.array([[c, r] for _, c, r in items]),
                              tuple(p for p, _, _ in items)))
    return out
