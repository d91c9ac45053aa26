"""orthority's own files in and out: interior parameters, exterior parameters (GeoJSON and CSV) and GCPs.

==================================  ===========================================  ==================================
file (orthority's name)             reader / writer                              identified by
==================================  ===========================================  ==================================
interior parameters (YAML or JSON)  :func:`read_int_param` / :func:`int_param_text`  :func:`detect_int_param`: cameras
                                                                                 with ``type``, ``im_size``,
                                                                                 ``focal_len``
exterior parameters (GeoJSON)       :func:`read_ext_param` / :func:`ext_param_text`  :func:`detect_ext_param`:
                                                                                 ``world_crs``, ``xyz``, ``opk``
CSV ``xyz_opk``, ``xyz_rpy``,       :func:`read_frame_csv` / :func:`frame_csv_text`  :func:`detect_frame_csv`: a
``lla_opk``, ``lla_rpy`` (+ .prj)                                                ``filename`` column (or none:
                                                                                 the legacy order)
GCPs (GeoJSON with ``ji``)          :func:`read_oty_gcps` / :func:`oty_gcps_text`    :func:`detect_oty_gcps`: a ``ji``
                                                                                 property
GCPs embedded in a TIFF             :func:`read_embedded_gcps_centre`            (the caller's choice)
==================================  ===========================================  ==================================

Conventions, converted once here (layouts and examples in ``docs/formats.md``, "Users' files of other tools"):

pixels
    orthority's pixel coordinates (``ji``, and its principal point) are ours: x = column right,
    y = row down, the centre of the top-left pixel at (0, 0). GDAL leaves the convention of GCPs
    embedded in a raster to the application: orthority reads them as pixel centres, so
    :func:`read_embedded_gcps_centre` keeps them (``rectify.formats.gcps.read_gcps_embedded`` reads
    GDAL's corner convention and subtracts 0.5).
interior parameters
    ``focal_len`` and ``sensor_size`` share a unit (taken as millimetres, as in orthority's
    examples; only their ratio reaches the geometry): f_px = focal_len * width / sensor_width.
    Without ``sensor_size`` orthority multiplies a normalised ``focal_len`` by the image
    **width** (its code; its documentation says the larger side); that is followed.
    ``cx``, ``cy`` are offsets of the principal point from the image centre in units of the
    larger image side: principal point = ((w - 1)/2 + cx max(w, h), (h - 1)/2 + cy max(w, h)) px.
    ``brown`` (k1, k2, p1, p2, k3) and ``opencv`` (the same five; the others must be 0) use
    OpenCV's distortion definition, which is ours; ``pinhole`` has none; ``fisheye`` (and any other
    type) is refused by name.
angles
    ``opk`` (and the CSV's ``omega, phi, kappa``) rotate camera vectors (PATB axes: x right,
    y up, z back) into the world: R = Rx(omega) Ry(phi) Rz(kappa), our convention and matrix. The
    GeoJSON gives radians; the CSV degrees unless ``radians`` (orthority's ``--radians``) or a
    ``# angles=rad`` line says otherwise. ``roll, pitch, yaw`` (Pix4D's definition: body x forward,
    y right, z down, rotated into north-east-down by Rz(yaw) Ry(pitch) Rx(roll); camera x = body
    y, camera y = body x, camera z = -body z) are turned into the world CRS's grid through
    :func:`rectify.geometry.mapframe.grid_from_enu` at the camera.
CRS and heights
    The GeoJSON's ``world_crs``; for the CSV a ``# crs=`` line and/or the ``.prj`` sidecar (they
    must agree), else the ``crs`` argument; ``lla_rpy`` files without either get the WGS 84 UTM
    zone of their mean position (orthority's choice). ``latitude, longitude, altitude`` are in
    ``lla_crs`` (default EPSG:4979, ellipsoidal heights) and are transformed into the world CRS
    by PROJ: heights stay ellipsoidal in a 2D world CRS and are converted when the world CRS
    carries a vertical datum. orthority's GCP coordinates are WGS 84 longitude, latitude and
    ellipsoidal height: the table's CRS is EPSG:4979.

Exterior orientations are returned as ``{image: {"position": (3,), "rotation": (3, 3), "crs": str or
None, "camera": str or None}}``, the geometry of :func:`rectify.formats.exterior.exterior_fields`
plus orthority's camera id; images are keyed by file name as orthority writes it (with or without
extension: :func:`match_image` finds an image either way).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_write_text, check_nesting, parse_json
from rectify.errors import CalibrationError, CRSError, InvalidInputError, RasterIOError
from rectify.formats.common import StrPath, finite_number, read_table_text
from rectify.geometry.camera import Camera
from rectify.geometry.crs import crs_to_string, parse_crs, same_crs, transform_xyz, utm_crs
from rectify.geometry.mapframe import grid_from_enu
from rectify.geometry.points import GcpTable
from rectify.geometry.rotation import angles_from_matrix, check_rotation, matrix_from_angles, rot_x, rot_y, rot_z
from rectify.raster.io import open_raster

__all__ = [
    "CAMERA_TYPES", "REFUSED_CAMERA_TYPES", "EMBEDDED_CONVENTIONS", "LLA_CRS",
    "read_int_param", "int_param_text", "write_int_param", "detect_int_param", "single_camera",
    "read_ext_param", "ext_param_text", "write_ext_param", "detect_ext_param",
    "read_frame_csv", "frame_csv_text", "write_frame_csv", "detect_frame_csv",
    "read_oty_gcps", "oty_gcps_text", "detect_oty_gcps",
    "pixel_from_embedded", "read_embedded_gcps_centre", "match_image",
]

#: orthority camera types read here, with the distortion coefficients each may carry (nonzero)
CAMERA_TYPES: dict[str, tuple[str, ...]] = {
    "pinhole": (),
    "brown": ("k1", "k2", "p1", "p2", "k3"),
    "opencv": ("k1", "k2", "p1", "p2", "k3"),
}
#: orthority camera types the frame camera model cannot represent (refused by name)
REFUSED_CAMERA_TYPES = ("fisheye", "rpc")
#: keys an ``opencv`` camera may carry that must be 0 here (rational, thin-prism and tilt terms)
_OPENCV_ZERO = ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")
_COMMON_KEYS = ("type", "im_size", "focal_len", "sensor_size", "cx", "cy", "name")
#: pixel conventions of GCPs embedded in a raster -> what is added to (col, row) to reach ours
EMBEDDED_CONVENTIONS: dict[str, float] = {"corner": -0.5, "centre": 0.0}
#: orthority's geographic CRS of ``latitude, longitude, altitude`` and of GCP coordinates
LLA_CRS = "EPSG:4979"
#: body (x forward, y right, z down) <- camera (x right, y up, z back), Pix4D's mounting
_BODY_FROM_CAMERA = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: ENU <- NED
_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_LEGACY_FIELDS = ("filename", "x", "y", "z", "omega", "phi", "kappa")
_SNIFF_BYTES = 1 << 16


def _where(path: StrPath) -> str:
    return repr(str(path))


def _number(v: Any, label: str) -> float:
    """A finite JSON/YAML number (bools and strings refused); ``label`` names file, key and owner."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InvalidInputError(f"{label} must be a finite number; got {v!r}")
    return float(v)


def _numbers(v: Any, n: int, label: str) -> list[float]:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise InvalidInputError(f"{label} must be a list of {n} numbers; got {v!r}")
    return [_number(c, label) for c in v]


def _load_yaml(path: StrPath) -> Any:
    text = read_table_text(path)
    check_nesting(text, _where(path))  # bounded before the recursive parser (rectify.atomic)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        reason = str(err).replace("\n", " ")
        raise InvalidInputError(f"{_where(path)} is not valid YAML or JSON: {reason}") from None
    except RecursionError:  # block-style nesting (by indentation) deeper than the parser's recursion
        raise InvalidInputError(f"{_where(path)} nests mappings or lists too deeply to be read") from None


def _load_json(path: StrPath) -> Any:
    return parse_json(read_table_text(path), _where(path))  # bounded size of nesting, one-line errors


def _head(path: StrPath) -> str:
    """The first 64 KiB of a text file ('' when unreadable: the reader then names the problem)."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            return fh.read(_SNIFF_BYTES)
    except OSError:
        return ""


# --------------------------------------------------------------------------- interior parameters
def _camera_sections(doc: Any, path: StrPath) -> dict[str, Any]:
    """``{camera id: parameters}`` of an int_param document (nested, flat or legacy ``camera:`` form)."""
    if not isinstance(doc, dict) or not doc:
        got = type(doc).__name__ if not isinstance(doc, dict) else "an empty mapping"
        raise InvalidInputError(f"{_where(path)}: orthority interior parameters must be a mapping of camera id "
                                f"-> parameters; got {got}")
    if isinstance(doc.get("camera"), dict) and "type" in doc["camera"]:  # legacy simple-ortho config.yaml
        # (or a camera whose id is "camera": the same camera either way, the id "camera" unless named)
        return {str(doc["camera"].get("name", "camera")): doc["camera"]}
    if "type" in doc and not isinstance(doc["type"], dict):  # flat form: one camera
        return {str(doc.get("name", "unknown")): doc}
    return {str(k): v for k, v in doc.items()}


def _camera_from_oty(cam_id: str, p: Any, path: StrPath) -> Camera:
    where = f"{_where(path)}: camera {cam_id!r}"
    if not isinstance(p, dict):
        raise InvalidInputError(f"{where} must be a mapping of parameters; got {p!r}")
    missing = [k for k in ("type", "im_size", "focal_len") if k not in p]
    if missing:
        raise InvalidInputError(f"{where} lacks {missing}")
    ctype = p["type"]
    if not isinstance(ctype, str):
        raise InvalidInputError(f"{where}: `type` must be a string; got {ctype!r}")
    ctype = ctype.lower()
    if ctype in REFUSED_CAMERA_TYPES:
        raise InvalidInputError(f"{where}: `type` {ctype!r} is not a frame camera this project models; "
                                f"supported: {list(CAMERA_TYPES)}")
    if ctype not in CAMERA_TYPES:
        raise InvalidInputError(f"{where}: unknown `type` {ctype!r}; expected one of {list(CAMERA_TYPES)}")
    allowed = set(_COMMON_KEYS) | set(CAMERA_TYPES[ctype]) | (set(_OPENCV_ZERO) if ctype == "opencv" else set())
    unknown = sorted(set(map(str, p)) - allowed)
    if unknown:
        raise InvalidInputError(f"{where}: unknown parameter(s) {unknown} for `type` {ctype!r}")
    size = p["im_size"]
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
        raise InvalidInputError(f"{where}: `im_size` must be [width, height], positive integers; got {size!r}")
    w, h = int(size[0]), int(size[1])
    fl = p["focal_len"]
    flx, fly = (_numbers(fl, 2, f"{where}: `focal_len`") if isinstance(fl, (list, tuple))
                else [_number(fl, f"{where}: `focal_len`")] * 2)
    if flx <= 0 or fly <= 0:
        raise InvalidInputError(f"{where}: `focal_len` must be > 0; got {fl!r}")
    cx = _number(p.get("cx", 0.0), f"{where}: `cx`")
    cy = _number(p.get("cy", 0.0), f"{where}: `cy`")
    for k in _OPENCV_ZERO:
        if k in p and _number(p[k], f"{where}: `{k}`") != 0.0:
            raise InvalidInputError(f"{where}: `{k}` = {p[k]!r}; the frame camera model has only k1, k2, k3, p1, p2 "
                                    "(the rational, thin-prism and tilt terms of OpenCV's model must be 0)")
    dist = {k: _number(p[k], f"{where}: `{k}`") for k in CAMERA_TYPES[ctype] if k in p}
    dist = {k: v for k, v in dist.items() if v != 0.0}
    m = float(max(w, h))
    pp = [(w - 1) / 2.0 + m * cx, (h - 1) / 2.0 + m * cy]
    d: dict[str, Any] = {"width": w, "height": h, "distortion": dist}
    sensor = p.get("sensor_size")
    if sensor is not None:
        sw, sh = _numbers(sensor, 2, f"{where}: `sensor_size`")
        if sw <= 0 or sh <= 0:
            raise InvalidInputError(f"{where}: `sensor_size` must be > 0; got {sensor!r}")
        fx, fy = flx * w / sw, fly * h / sh
        ps = sw / w
        if (sw, sh) != (float(w), float(h)) and flx == fly and abs(sh / h - ps) <= 1e-9 * ps:
            d.update(focal_length_mm=flx, pixel_size_mm=ps,
                     principal_point_mm=[m * cx * ps, -m * cy * ps])
            return _camera(d, where)
    else:
        fx, fy = flx * w, fly * w
    if fx == fy:
        d["focal_length_px"] = fx
    else:
        d["fx_px"], d["fy_px"] = fx, fy
    d["principal_point_px"] = pp
    return _camera(d, where)


def _camera(d: dict[str, Any], where: str) -> Camera:
    try:
        return Camera.from_dict(d)
    except CalibrationError as err:
        raise CalibrationError(f"{where}: {err}") from None


def read_int_param(path: StrPath) -> dict[str, Camera]:
    """Read orthority interior parameters (YAML, or JSON) into cameras keyed by orthority's camera id.

    Millimetre cameras when ``sensor_size`` gives square pixels in a unit other than pixels;
    pixel cameras otherwise (see the module docstring for the conversion).

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Not YAML/JSON, not a mapping of cameras, a missing or malformed key, an unknown parameter,
        a camera ``type`` the frame camera model cannot represent (``fisheye``), nonzero
        higher-order OpenCV terms (each named with the file, the camera id and the value).
    CalibrationError
        A camera the project's model refuses (named by the camera model).
    """
    sections = _camera_sections(_load_yaml(path), path)
    return {cam_id: _camera_from_oty(cam_id, p, path) for cam_id, p in sections.items()}


def _oty_camera_dict(cam: Camera, cam_id: str) -> dict[str, Any]:
    w, h = cam.width, cam.height
    m = float(max(w, h))
    K = np.asarray(cam.K, dtype=np.float64)
    if K[0, 1] != 0.0:
        raise InvalidInputError(f"camera {cam_id!r} has skew {float(K[0, 1])!r} px, which orthority's cameras "
                                "cannot hold")
    d: dict[str, Any] = {"type": "brown" if cam.has_distortion else "pinhole", "im_size": [w, h]}
    if cam.pixel_camera:  # a sensor in pixels: focal_len in pixels, no normalisation
        fx, fy = float(K[0, 0]), float(K[1, 1])
        d.update(focal_len=fx if fx == fy else [fx, fy], sensor_size=[float(w), float(h)],
                 cx=float((K[0, 2] - (w - 1) / 2.0) / m), cy=float((K[1, 2] - (h - 1) / 2.0) / m))
    else:
        ps = cam.pixel_size_mm
        x0, y0 = cam.principal_point_mm
        d.update(focal_len=cam.focal_length_mm, sensor_size=[w * ps, h * ps], cx=x0 / ps / m, cy=-y0 / ps / m)
    if cam.has_distortion:
        d.update({k: cam.distortion[k] for k in CAMERA_TYPES["brown"]})
    return d


def int_param_text(cameras: Mapping[str, Camera]) -> str:
    """orthority interior parameters (YAML) of ``cameras`` (id -> Camera), read back by :func:`read_int_param`.

    ``brown`` when a camera has distortion, else ``pinhole``; millimetre cameras with their sensor
    size in millimetres, pixel cameras with ``sensor_size`` = ``im_size`` (focal length in pixels).

    Raises
    ------
    InvalidInputError
        A camera with skew (orthority has none).
    """
    body = {str(k): _oty_camera_dict(c, str(k)) for k, c in cameras.items()}
    return yaml.safe_dump(body, sort_keys=False, default_flow_style=None)


def write_int_param(path: StrPath, cameras: Mapping[str, Camera], *, overwrite: bool = False) -> Path:
    """Write :func:`int_param_text` atomically; return the path."""
    return atomic_write_text(path, int_param_text(cameras), overwrite=overwrite)


def detect_int_param(path: StrPath) -> bool:
    """Whether ``path`` holds orthority interior parameters (a mapping of cameras with ``im_size``, ``focal_len``)."""
    if Path(path).suffix.lower() not in (".yaml", ".yml", ".json"):
        return False
    try:
        head = _head(path)
        check_nesting(head, _where(path))
        doc = yaml.safe_load(head)
    except (yaml.YAMLError, RecursionError, InvalidInputError):  # not orthority's: the reader names the problem
        return False
    try:
        sections = _camera_sections(doc, path)
    except InvalidInputError:
        return False
    return any(isinstance(p, dict) and "im_size" in p and "focal_len" in p for p in sections.values())


def single_camera(cameras: Mapping[str, Camera], path: StrPath, camera_id: str | None = None) -> Camera:
    """The one camera of a file, or the one named ``camera_id``; a choice is refused with the ids named."""
    if camera_id is not None:
        if camera_id not in cameras:
            raise InvalidInputError(f"{_where(path)} has no camera {camera_id!r}; it has {sorted(cameras)}")
        return cameras[camera_id]
    if len(cameras) != 1:
        raise InvalidInputError(f"{_where(path)} holds {len(cameras)} cameras {sorted(cameras)}; name one")
    return next(iter(cameras.values()))


# --------------------------------------------------------------------------- exterior parameters
def _exterior(position: ArrayLike, R: ArrayLike, crs: str | None, camera: str | None, label: str) -> dict[str, Any]:
    try:
        rot = check_rotation(R, "rotation")
    except InvalidInputError as err:
        raise InvalidInputError(f"{label}: {err}") from None
    return {"position": np.asarray(position, dtype=np.float64).reshape(3), "rotation": rot, "crs": crs,
            "camera": camera}


def _world_crs(value: Any, label: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InvalidInputError(f"{label} must be a CRS string (EPSG code, WKT or PROJ); got {value!r}")
    try:
        c = parse_crs(value)
    except CRSError as err:
        raise CRSError(f"{label}: {err}") from None
    if not c.is_projected:
        raise CRSError(f"{label} must be a projected CRS (a Cartesian world frame); got {c.name!r}")
    return crs_to_string(c)


def read_ext_param(path: StrPath) -> dict[str, dict[str, Any]]:
    """Read orthority exterior parameters (GeoJSON ``FeatureCollection`` with ``world_crs``).

    Returns
    -------
    dict
        ``{filename: {"position": (3,), "rotation": (3, 3), "crs": str, "camera": str or None}}``:
        ``xyz`` in the world CRS, R = Rx(omega) Ry(phi) Rz(kappa) from ``opk`` (radians). The Point
        geometry (the position in WGS 84, derived by orthority) is not used.

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        Missing file, bad JSON, a missing key, a value of the wrong type (file, key and value named),
        a duplicated filename, a world CRS that is not projected.
    """
    doc = _load_json(path)
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        got = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
        raise InvalidInputError(f"{_where(path)}: expected a GeoJSON FeatureCollection of orthority exterior "
                                f"parameters; got type {got!r}")
    if "world_crs" not in doc:
        raise InvalidInputError(f"{_where(path)} lacks 'world_crs' (orthority exterior parameters name their CRS)")
    crs = _world_crs(doc["world_crs"], f"{_where(path)}: `world_crs`")
    feats = doc.get("features")
    if not isinstance(feats, list) or not feats:
        raise InvalidInputError(f"{_where(path)}: `features` must be a non-empty list; got {feats!r:.80}")
    out: dict[str, dict[str, Any]] = {}
    for k, f in enumerate(feats):
        props = f.get("properties") if isinstance(f, dict) else None
        if not isinstance(props, dict):
            raise InvalidInputError(f"{_where(path)} feature {k}: `properties` must be an object; got {f!r:.80}")
        name = props.get("filename")
        if not isinstance(name, str) or not name:
            raise InvalidInputError(f"{_where(path)} feature {k}: `filename` must be a non-empty string; got {name!r}")
        where = f"{_where(path)} feature {k} ({name!r})"
        for key in ("xyz", "opk"):
            if key not in props:
                raise InvalidInputError(f"{where} lacks `{key}`")
        xyz = _numbers(props["xyz"], 3, f"{where}: `xyz`")
        opk = _numbers(props["opk"], 3, f"{where}: `opk`")
        cam = props.get("camera")
        if cam is not None and not isinstance(cam, str):
            raise InvalidInputError(f"{where}: `camera` must be a string or null; got {cam!r}")
        if name in out:
            raise InvalidInputError(f"{_where(path)}: filename {name!r} appears twice")
        out[name] = _exterior(xyz, matrix_from_angles(opk[0], opk[1], opk[2], "omega-phi-kappa"), crs, cam, where)
    return out


def ext_param_text(exteriors: Mapping[str, Mapping[str, Any]], crs: str) -> str:
    """orthority exterior parameters (GeoJSON) of ``{image: {"position", "rotation"[, "camera"]}}`` in ``crs``.

    The Point geometry is the position in WGS 84 (EPSG:4979) as orthority writes it.
    """
    world = _world_crs(crs, "`crs`")
    feats = []
    for name, eo in exteriors.items():
        pos = [float(v) for v in np.asarray(eo["position"], dtype=np.float64).reshape(3)]
        opk = [float(v) for v in angles_from_matrix(check_rotation(eo["rotation"], f"rotation of {name!r}"))]
        lla = transform_xyz(world, LLA_CRS, [pos])[0]
        feats.append({"type": "Feature",
                      "properties": {"filename": str(name), "camera": eo.get("camera"), "xyz": pos, "opk": opk},
                      "geometry": {"type": "Point", "coordinates": [float(v) for v in lla]}})
    return json.dumps({"type": "FeatureCollection", "world_crs": crs, "features": feats}, indent=4) + "\n"


def write_ext_param(path: StrPath, exteriors: Mapping[str, Mapping[str, Any]], crs: str, *,
                    overwrite: bool = False) -> Path:
    """Write :func:`ext_param_text` atomically; return the path."""
    return atomic_write_text(path, ext_param_text(exteriors, crs), overwrite=overwrite)


def detect_ext_param(path: StrPath) -> bool:
    """Whether ``path`` is a GeoJSON ``FeatureCollection`` with orthority's ``world_crs`` (its features carry ``xyz``
    and ``opk``: the reader names what is missing)."""
    head = _head(path)
    return '"world_crs"' in head and '"FeatureCollection"' in head


# --------------------------------------------------------------------------- CSV exterior parameters
def _comment_settings(lines: list[str], path: StrPath) -> tuple[str | None, str | None]:
    """The ``# crs=`` and ``# angles=`` values of a CSV's comment lines."""
    crs = unit = None
    for no, line in enumerate(lines, start=1):
        s = line.strip()
        if not s.startswith("#"):
            continue
        key, sep, value = s.lstrip("#").strip().partition("=")
        key, value = key.strip().lower(), value.strip()
        if sep and key == "crs":
            crs = value
        elif sep and key == "angles":
            if value.lower() not in ("deg", "rad"):
                raise InvalidInputError(f"{_where(path)} line {no}: `angles` must be 'deg' or 'rad'; got {value!r}")
            unit = value.lower()
    return crs, unit


def _dialect(sample: str) -> type[csv.Dialect] | csv.Dialect:
    try:
        d = csv.Sniffer().sniff(sample, delimiters=",;\t ")
    except csv.Error:
        first = sample.splitlines()[0] if sample else ""
        delim = next((c for c in ",;\t" if c in first), " ")

        class _D(csv.excel):
            delimiter = delim
        d = _D
    d.skipinitialspace = True
    return d


def _csv_crs(path: Path, line_crs: str | None, crs: str | None) -> tuple[str | None, str | None]:
    """The CRS of a CSV's positions from the ``crs`` argument, the ``# crs=`` line and the ``.prj`` sidecar;
    refuse any two that disagree. Returns (crs, where it came from)."""
    given: list[tuple[str, str]] = []
    if crs is not None:
        given.append((crs, "the `crs` argument"))
    if line_crs:
        given.append((line_crs, f"the '# crs=' line of {str(path)!r}"))
    prj = path.with_suffix(".prj")
    if prj.is_file():
        try:
            text = prj.read_text(encoding="utf-8-sig").strip()
        except (OSError, UnicodeDecodeError) as err:
            raise RasterIOError(f"cannot read {str(prj)!r}: {err}") from err
        if not text:
            raise InvalidInputError(f"{str(prj)!r} is empty; it should hold the CRS of {str(path)!r}")
        given.append((text, repr(str(prj))))
    for value, where in given:
        try:
            parse_crs(value)
        except CRSError as err:
            raise CRSError(f"{where}: {err}") from None
    for value, where in given[1:]:
        if not same_crs(given[0][0], value):
            raise CRSError(f"{where} gives CRS {value[:80]!r}, which contradicts {given[0][1]} "
                           f"({given[0][0][:80]!r})")
    return (given[0][0], given[0][1]) if given else (None, None)


def _rotation_from_rpy(rpy_rad: Sequence[float], crs: str, lonlat: Sequence[float]) -> NDArray[np.float64]:
    roll, pitch, yaw = rpy_rad
    ned_from_body = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
    return np.asarray(grid_from_enu(crs, lonlat[0], lonlat[1]) @ _ENU_FROM_NED @ ned_from_body @ _BODY_FROM_CAMERA)


def read_frame_csv(path: StrPath, *, crs: str | None = None, radians: bool | None = None,
                   lla_crs: str = LLA_CRS) -> dict[str, dict[str, Any]]:
    """Read an orthority CSV of exterior parameters (``xyz_opk``, ``xyz_rpy``, ``lla_opk``, ``lla_rpy``).

    Parameters
    ----------
    path : path
        The CSV: a header naming ``filename``, ``x, y, z`` or ``latitude, longitude, altitude``,
        ``omega, phi, kappa`` or ``roll, pitch, yaw`` and optionally ``camera`` (other columns
        ignored), or no header and orthority's legacy order ``filename x y z omega phi kappa``.
        Comma, semicolon, tab or space separated; cells may be quoted; ``#`` lines are comments
        (``# crs=``, ``# angles=deg|rad`` are read).
    crs : str, optional
        The world CRS (projected). Needed for ``lla_opk`` and ``xyz_rpy`` files without a
        ``.prj`` or ``# crs=`` line; must agree with them when they exist.
    radians : bool, optional
        Angles in radians (orthority's ``--radians``); default: the ``# angles=`` line, else degrees.
    lla_crs : str
        The geographic CRS of latitude, longitude, altitude (default EPSG:4979).

    Returns
    -------
    dict
        ``{filename: {"position", "rotation", "crs", "camera"}}`` (module docstring); ``crs`` None
        for an ``xyz_opk`` file that names no CRS.

    Raises
    ------
    InvalidInputError
        Missing columns, a cell that is not a number (file, line, column and value named), a
        duplicated filename, an ``angles`` setting that contradicts ``radians``.
    CRSError
        A ``.prj``, ``# crs=`` line and ``crs`` argument that contradict each other; an unknown or
        non-projected world CRS; no CRS where the file's angles or positions need one.
    """
    p = Path(path)
    all_lines = read_table_text(p).splitlines()
    line_crs, unit = _comment_settings(all_lines, p)
    if radians is not None and unit is not None and radians != (unit == "rad"):
        raise InvalidInputError(f"{_where(p)}: '# angles={unit}' contradicts radians={radians}")
    in_radians = radians if radians is not None else unit == "rad"
    data = [(no, ln) for no, ln in enumerate(all_lines, start=1) if ln.strip() and not ln.strip().startswith("#")]
    if not data:
        raise InvalidInputError(f"{_where(p)} has no rows")
    dialect = _dialect("\n".join(ln for _, ln in data[:50]))
    rows = list(csv.reader([ln for _, ln in data], dialect))
    first = [c.strip().lower() for c in rows[0]]
    if "filename" in first:
        fields, body, numbers = first, rows[1:], [no for no, _ in data[1:]]
    else:
        fields, body, numbers = list(_LEGACY_FIELDS), rows, [no for no, _ in data]
    has = set(fields)
    xyz_cols = ("x", "y", "z") if {"x", "y", "z"} <= has else None
    lla_cols = ("longitude", "latitude", "altitude") if {"latitude", "longitude", "altitude"} <= has else None
    ang_cols = ("omega", "phi", "kappa") if {"omega", "phi", "kappa"} <= has else None
    rpy_cols = ("roll", "pitch", "yaw") if {"roll", "pitch", "yaw"} <= has else None
    if "filename" not in has or not (xyz_cols or lla_cols) or not (ang_cols or rpy_cols):
        raise InvalidInputError(f"{_where(p)}: orthority CSV needs columns filename, x/y/z or latitude/longitude/"
                                f"altitude, and omega/phi/kappa or roll/pitch/yaw; header is {fields}")
    if not body:
        raise InvalidInputError(f"{_where(p)} has a header but no rows")
    names: list[str] = []
    pos, ang, cams = [], [], []
    for no, r in zip(numbers, body, strict=True):
        if len(r) < len(fields):
            raise InvalidInputError(f"{_where(p)} line {no}: {len(r)} cells for {len(fields)} columns {fields}")
        cell = dict(zip(fields, (c.strip() for c in r), strict=False))
        names.append(Path(cell["filename"]).name)
        if not names[-1]:
            raise InvalidInputError(f"{_where(p)} line {no}: empty filename")
        num = [finite_number(cell[k], f"{_where(p)} line {no}: column {k!r}")
               for k in (xyz_cols or lla_cols or ()) + (ang_cols or rpy_cols or ())]
        pos.append(num[:3])
        ang.append(num[3:])
        cams.append(cell.get("camera") or None)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InvalidInputError(f"{_where(p)}: duplicate filename(s) {dup}")
    pos_a = np.array(pos, dtype=np.float64)
    ang_a = np.array(ang, dtype=np.float64) if in_radians else np.radians(np.array(ang, dtype=np.float64))
    world, source = _csv_crs(p, line_crs, crs)
    kind = f"{'xyz' if xyz_cols else 'lla'}_{'opk' if ang_cols else 'rpy'}"
    if world is None and kind == "lla_rpy":
        world, source = utm_crs(*np.mean(pos_a[:, :2], axis=0)), "the UTM zone of the positions"
    if world is None and kind != "xyz_opk":
        raise CRSError(f"{_where(p)} ({kind}) needs the world CRS: give a .prj beside it, a '# crs=' line or crs=")
    if world is not None:
        world = _world_crs(world, f"the world CRS from {source}")
    if lla_cols:
        pos_a = transform_xyz(lla_crs, world, pos_a)
        lonlat = np.array(pos)[:, :2]
    elif rpy_cols:
        lonlat = transform_xyz(world, lla_crs, pos_a)[:, :2]
    out: dict[str, dict[str, Any]] = {}
    for i, name in enumerate(names):
        if ang_cols:
            R = matrix_from_angles(ang_a[i, 0], ang_a[i, 1], ang_a[i, 2], "omega-phi-kappa")
        else:
            R = _rotation_from_rpy(ang_a[i], str(world), lonlat[i])
        out[name] = _exterior(pos_a[i], R, world, cams[i], f"{_where(p)} line {numbers[i]}")
    return out


def frame_csv_text(exteriors: Mapping[str, Mapping[str, Any]], *, radians: bool = False) -> str:
    """orthority ``xyz_opk`` CSV text (``filename,x,y,z,omega,phi,kappa[,camera]``); angles in degrees
    unless ``radians`` (then read it back with ``radians=True``). Numbers as ``repr`` (exact)."""
    with_cam = any(eo.get("camera") for eo in exteriors.values())
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(list(_LEGACY_FIELDS) + (["camera"] if with_cam else []))
    for name, eo in exteriors.items():
        a = angles_from_matrix(check_rotation(eo["rotation"], f"rotation of {name!r}"))
        a = a if radians else np.degrees(a)
        pos = np.asarray(eo["position"], dtype=np.float64).reshape(3)
        row = [str(name), *map(repr, map(float, pos)), *map(repr, map(float, a))]
        w.writerow(row + ([eo.get("camera") or ""] if with_cam else []))
    return buf.getvalue()


def write_frame_csv(path: StrPath, exteriors: Mapping[str, Mapping[str, Any]], *, crs: str, radians: bool = False,
                    overwrite: bool = False) -> Path:
    """Write :func:`frame_csv_text` and its ``.prj`` sidecar (the CRS as WKT) atomically; return the CSV path."""
    world = _world_crs(crs, "`crs`")
    p = Path(path)
    atomic_write_text(p.with_suffix(".prj"), parse_crs(world).to_wkt() + "\n", overwrite=overwrite)
    return atomic_write_text(p, frame_csv_text(exteriors, radians=radians), overwrite=overwrite)


def detect_frame_csv(path: StrPath) -> bool:
    """Whether ``path`` is an orthority CSV: a ``filename`` column with positions and angles (or the legacy
    order: a name and six numbers on every line)."""
    lines = [ln for ln in _head(path).splitlines() if ln.strip() and not ln.strip().startswith("#")]
    if not lines:
        return False
    first = lines[0].lower()
    if "filename" in first:
        return ("omega" in first or "roll" in first) and ("x" in first or "latitude" in first)
    cells = [c for c in lines[0].replace(",", " ").replace("\t", " ").split(" ") if c]
    try:
        [float(c) for c in cells[1:7]]
    except ValueError:
        return False
    return len(cells) == 7


# --------------------------------------------------------------------------- GCPs
def read_oty_gcps(path: StrPath) -> dict[str, GcpTable]:
    """Read orthority GCPs (GeoJSON Point features with ``filename`` and ``ji``) into one table per image.

    Pixels ``ji`` are ours (pixel centres at integers); the target is WGS 84 longitude, latitude
    and the height (``z``), CRS EPSG:4979. Ids from ``id`` (else the feature's position in the file).

    Raises
    ------
    RasterIOError, InvalidInputError
        Missing file, bad JSON, a feature without ``filename``/``ji``/a 3D Point, a value that is
        not a number (file, feature, key and value named), an id repeated within one image.
    """
    doc = _load_json(path)
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        got = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
        raise InvalidInputError(f"{_where(path)}: expected a GeoJSON FeatureCollection of orthority GCPs; "
                                f"got type {got!r}")
    feats = doc.get("features")
    if not isinstance(feats, list) or not feats:
        raise InvalidInputError(f"{_where(path)}: `features` must be a non-empty list; got {feats!r:.80}")
    rows: dict[str, list[tuple[str, list[float], list[float]]]] = {}
    for k, f in enumerate(feats):
        where = f"{_where(path)} feature {k}"
        props = f.get("properties") if isinstance(f, dict) else None
        geom = f.get("geometry") if isinstance(f, dict) else None
        if not isinstance(props, dict):
            raise InvalidInputError(f"{where}: `properties` must be an object; got {f!r:.80}")
        name = props.get("filename")
        if not isinstance(name, str) or not name:
            raise InvalidInputError(f"{where}: `filename` must be a non-empty string; got {name!r}")
        if "ji" not in props:
            raise InvalidInputError(f"{where}: lacks `ji` (pixel coordinates)")
        ji = _numbers(props["ji"], 2, f"{where}: `ji`")
        if not isinstance(geom, dict) or geom.get("type") != "Point":
            raise InvalidInputError(f"{where}: geometry must be a Point; got {geom!r:.80}")
        xyz = _numbers(geom.get("coordinates"), 3, f"{where}: Point `coordinates` [lon, lat, h]")
        gid = props.get("id")
        rows.setdefault(Path(name).name, []).append((str(gid) if gid not in (None, "") else str(k + 1), ji, xyz))
    out = {}
    for name, rs in rows.items():
        ids = [r[0] for r in rs]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise InvalidInputError(f"{_where(path)}: GCP id(s) {dup} repeated in image {name!r}")
        lla = np.array([r[2] for r in rs], dtype=np.float64)
        out[name] = GcpTable(tuple(ids), np.array([r[1] for r in rs], dtype=np.float64), lla[:, :2].copy(),
                             lla[:, 2].copy(), np.zeros(len(rs), dtype=bool), LLA_CRS)
    return out


def oty_gcps_text(gcps: Mapping[str, GcpTable]) -> str:
    """orthority GCP GeoJSON of ``{image: GcpTable}``: targets are transformed to EPSG:4979 (lon, lat, h).

    Raises
    ------
    InvalidInputError
        A table without heights or without a CRS.
    """
    feats = []
    for name, t in gcps.items():
        if t.z is None or t.crs is None:
            raise InvalidInputError(f"GCPs of {name!r} need heights and a CRS for orthority's 3D WGS 84 points")
        xyz = np.column_stack([t.target, t.z])
        lla = xyz if same_crs(t.crs, LLA_CRS) else transform_xyz(t.crs, LLA_CRS, xyz)
        for i in range(len(t)):
            feats.append({"type": "Feature",
                          "properties": {"filename": str(name), "ji": [float(v) for v in t.pixel[i]],
                                         "id": t.ids[i], "info": t.ids[i]},
                          "geometry": {"type": "Point", "coordinates": [float(v) for v in lla[i]]}})
    return json.dumps({"type": "FeatureCollection", "features": feats}, indent=4) + "\n"


def detect_oty_gcps(path: StrPath) -> bool:
    """Whether ``path`` is a GeoJSON of orthority GCPs (features with ``filename`` and ``ji``)."""
    head = _head(path)
    return '"FeatureCollection"' in head and '"ji"' in head and '"filename"' in head


def pixel_from_embedded(col_row: ArrayLike, convention: str) -> NDArray[np.float64]:
    """Pixels (N, 2) in our convention from the (col, row) of GCPs embedded in a raster.

    Parameters
    ----------
    col_row : (N, 2) array_like
        The GCPs' pixel/line values as GDAL reports them.
    convention : {"corner", "centre"}
        ``"corner"``: GDAL's usual reading (the top-left corner of the image at (0, 0)): 0.5 is
        subtracted. ``"centre"``: orthority's reading (the centre of the top-left pixel at (0, 0)):
        unchanged.

    Examples
    --------
    >>> pixel_from_embedded([[10.5, 20.5]], "corner").tolist()
    [[10.0, 20.0]]
    >>> pixel_from_embedded([[10.5, 20.5]], "middle")
    Traceback (most recent call last):
    ...
    rectify.errors.InvalidInputError: unknown embedded GCP convention 'middle'; expected one of ['corner', 'centre']
    """
    if convention not in EMBEDDED_CONVENTIONS:
        raise InvalidInputError(f"unknown embedded GCP convention {convention!r}; expected one of "
                                f"{list(EMBEDDED_CONVENTIONS)}")
    return np.asarray(col_row, dtype=np.float64).reshape(-1, 2) + EMBEDDED_CONVENTIONS[convention]


def read_embedded_gcps_centre(path: StrPath) -> GcpTable:
    """The GCPs embedded in a raster read with orthority's convention (pixel centres at integers, kept).

    Heights are kept when every GCP has a nonzero one (GDAL reports 0 for none).

    Raises
    ------
    RasterIOError
        The raster cannot be opened.
    InvalidInputError
        It carries no GCPs, or a GCP has a non-finite value (named).
    """
    with open_raster(Path(path)) as ds:
        pts, crs = ds.gcps
    if not pts:
        raise InvalidInputError(f"{_where(path)} carries no embedded GCPs")
    vals = np.array([[g.col, g.row, g.x, g.y, g.z if g.z is not None else 0.0] for g in pts], dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(vals).all(axis=1))
    if len(bad):
        raise InvalidInputError(f"{_where(path)} embedded GCP {int(bad[0]) + 1}: non-finite value "
                                f"{vals[bad[0]].tolist()}")
    ids = tuple(str(g.id or k + 1) for k, g in enumerate(pts))
    z = vals[:, 4].copy() if np.all(vals[:, 4] != 0.0) else None
    return GcpTable(ids, pixel_from_embedded(vals[:, :2], "centre"), vals[:, 2:4].copy(), z,
                    np.zeros(len(pts), dtype=bool), crs_to_string(crs) if crs is not None else None)


def match_image(mapping: Mapping[str, Any], image: StrPath) -> Any:
    """The entry of ``mapping`` (keyed by file name, with or without extension) for the image file ``image``.

    Raises
    ------
    InvalidInputError
        No entry, or two entries match (the names are listed).
    """
    p = Path(image)
    for key in (p.name, p.stem):
        if key in mapping:
            return mapping[key]
    hits = [k for k in mapping if Path(k).stem == p.stem]
    if len(hits) == 1:
        return mapping[hits[0]]
    listed = sorted(mapping)[:10]
    if hits:
        raise InvalidInputError(f"image {p.name!r} matches several entries {sorted(hits)}")
    raise InvalidInputError(f"image {p.name!r} has no entry; the file names {listed}"
                            f"{' ...' if len(mapping) > 10 else ''}")
