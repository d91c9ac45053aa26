"""Agisoft Metashape's XML exports in: cameras (calibration and exterior orientation) and markers.

:func:`read_metashape_chunk` reads a ``cameras.xml`` (File > Export > Export Cameras, "Agisoft XML") or
a markers XML (Export Markers) into a :class:`MetashapeChunk`: cameras, exterior orientations of the
aligned images (:meth:`MetashapeChunk.exteriors`, what ``rectify ortho --exterior`` takes), and the
markers with their image measurements (:meth:`MetashapeChunk.gcp_table`, what ``--gcps`` takes);
``stereo.formats.metashape`` makes block poses and control of it. :func:`detect_metashape` recognises one.

Conventions, converted once here:

calibration
    ``<calibration type="frame">`` (the ``adjusted`` one when present): ``f``, ``cx``, ``cy``,
    ``b1``, ``b2`` in pixels, ``k1``-``k4``, ``p1``-``p4``. Metashape projects
    u = w/2 + cx + x'(f + b1) + y' b2, v = h/2 + cy + y' f with the image's top-left corner at
    (0, 0), so fx = f + b1, fy = f, skew = b2 and our principal point (centre of the top-left
    pixel at (0, 0)) is ((w - 1)/2 + cx, (h - 1)/2 + cy). Its tangential terms are OpenCV's
    swapped: x' gains P1 (r^2 + 2x^2) + 2 P2 x y, so OpenCV's p1 = Metashape's P2 and p2 = P1.
    k4, p3 and p4 are not in the frame camera model and must be 0; fisheye, spherical,
    cylindrical and RPC sensors are refused by name.
poses
    A camera's ``<transform>`` (4 x 4, row-major) takes camera coordinates (x right, y down,
    z forward) into the chunk's internal frame; the component's ``<transform>`` (Metashape 2) or
    else the chunk's (rotation, translation, scale) takes that into the world: geocentric
    coordinates on the datum of the chunk's ``<reference>`` CRS when it is geographic or
    projected, the local frame itself for a local CRS or none. Georeferenced poses are returned in
    a projected CRS (``crs``; default the chunk's own when projected, else the WGS 84 UTM zone of
    the cameras): positions through PROJ (heights ellipsoidal unless that CRS has a vertical
    datum), rotations through the local east-north-up frame and the grid convergence
    (:func:`rectify.geometry.mapframe.grid_from_enu`), the approximation behind any omega, phi,
    kappa in a projected CRS. The rotation of photo vectors (x right, y up, z back) is
    R = R_world diag(1, -1, -1).
markers
    Reference coordinates (``<reference x= y= z=>``) are in the chunk's CRS (longitude, latitude,
    height for a geographic one) and are transformed like the camera positions; image
    measurements (``<location camera_id= x= y=>``) lose 0.5 px (Metashape's corner origin).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError, RectifyError
from rectify.formats.camera import camera_from_focals
from rectify.formats.common import StrPath, finite_number, read_table_text
from rectify.geometry.camera import Camera
from rectify.geometry.crs import crs_to_string, parse_crs, transform_xyz, utm_crs
from rectify.geometry.geodesy import enu_rotation, geocentric_crs, geodetic_from_ecef
from rectify.geometry.mapframe import grid_from_enu
from rectify.geometry.points import GcpTable
from rectify.geometry.rotation import check_rotation

__all__ = ["MetashapeChunk", "read_metashape_chunk", "detect_metashape"]

_FLIP = np.diag([1.0, -1.0, -1.0])
_REFUSED_TYPES = ("fisheye", "spherical", "cylindrical", "rpc", "equirectangular")
_ZERO_TERMS = ("k4", "p3", "p4")


@dataclass(frozen=True, eq=False)
class MetashapeChunk:
    """One chunk of a Metashape XML export in the project's terms.

    Attributes
    ----------
    cameras : dict of str -> Camera
        Pixel cameras keyed by Metashape's sensor id; ``sensor_labels`` gives their labels.
    sensor_labels : dict of str -> str
    images : tuple of str
        The aligned images (camera ``label``), n.
    image_sensor : tuple of str
        The sensor id of each aligned image.
    positions : (n, 3) float64
        Projection centres in ``crs``.
    rotations : (n, 3, 3) float64
        Rotations of photo vectors (x right, y up, z back) into ``crs``'s frame.
    unaligned : tuple of str
        Labels of the cameras without a transform.
    crs : str or None
        The CRS of the poses and markers; None for a local frame.
    reference_crs : str or None
        The chunk's own ``<reference>`` CRS (None when absent or local).
    frame : str
        What the coordinates are.
    marker_ids : tuple of str
        Marker labels (K).
    marker_xyz : (K, 3) float64
        Their reference coordinates in ``crs`` (NaN rows: markers without reference, tie markers).
    meas_id, meas_image : tuple of str
        Marker label and image name of each measurement (L).
    meas_pixel : (L, 2) float64
        Pixels in our convention.
    """

    cameras: dict[str, Camera]
    sensor_labels: dict[str, str]
    images: tuple[str, ...]
    image_sensor: tuple[str, ...]
    positions: NDArray[np.float64]
    rotations: NDArray[np.float64]
    unaligned: tuple[str, ...]
    crs: str | None
    reference_crs: str | None
    frame: str
    marker_ids: tuple[str, ...]
    marker_xyz: NDArray[np.float64]
    meas_id: tuple[str, ...]
    meas_image: tuple[str, ...]
    meas_pixel: NDArray[np.float64]

    def exteriors(self) -> dict[str, dict[str, Any]]:
        """``{image: {"position", "rotation", "crs", "camera"}}`` of the aligned images (camera: the sensor id)."""
        return {n: {"position": p.copy(), "rotation": R.copy(), "crs": self.crs, "camera": s}
                for n, s, p, R in zip(self.images, self.image_sensor, self.positions, self.rotations, strict=True)}

    def gcp_table(self, image: str) -> GcpTable:
        """The markers with reference coordinates measured in ``image``.

        Raises
        ------
        InvalidInputError
            None is measured there.
        """
        index = {m: i for i, m in enumerate(self.marker_ids)}
        rows = [k for k, im in enumerate(self.meas_image)
                if im == image and np.isfinite(self.marker_xyz[index[self.meas_id[k]]]).all()]
        if not rows:
            raise InvalidInputError(f"no marker with reference coordinates is measured in image {image!r}")
        xyz = self.marker_xyz[[index[self.meas_id[k]] for k in rows]]
        return GcpTable(tuple(self.meas_id[k] for k in rows), self.meas_pixel[rows].copy(), xyz[:, :2].copy(),
                        xyz[:, 2].copy(), np.zeros(len(rows), dtype=bool), self.crs)


# --------------------------------------------------------------------------- XML helpers
def _num(text: str | None, label: str) -> float:
    if text is None:
        raise InvalidInputError(f"{label} is missing")
    return finite_number(text.strip(), label)


def _numbers(text: str | None, n: int, label: str) -> NDArray[np.float64]:
    cells = (text or "").split()
    if len(cells) != n:
        raise InvalidInputError(f"{label} must hold {n} numbers; got {len(cells)}: {(text or '').strip()[:80]!r}")
    return np.array([finite_number(c, label) for c in cells], dtype=np.float64)


def _cameras_in(el: ET.Element | None) -> Iterator[ET.Element]:
    """The ``<camera>`` elements of ``<cameras>``, groups included."""
    if el is None:
        return
    for child in el:
        if child.tag == "camera":
            yield child
        elif child.tag == "group":
            yield from (c for c in child if c.tag == "camera")


def _sensor_camera(sensor: ET.Element, where: str) -> Camera | None:
    stype = (sensor.get("type") or "frame").lower()
    if stype in _REFUSED_TYPES:
        raise InvalidInputError(f"{where} has type {stype!r}, which the frame camera model cannot represent")
    cals = sensor.findall("calibration")
    cal = next((c for c in cals if c.get("class") == "adjusted"), None) or next(iter(cals), None)
    if cal is None:
        return None
    ctype = (cal.get("type") or "frame").lower()
    if ctype != "frame":
        raise InvalidInputError(f"{where}: calibration type {ctype!r} is not a frame camera")
    where = f"{where} calibration ({cal.get('class') or 'unnamed'})"
    if cal.find("fx") is not None:
        raise InvalidInputError(f"{where} gives `fx`/`fy` (PhotoScan 1.2's form); export it from Metashape 1.5 or "
                                "later (f, cx, cy, b1, b2)")
    res = cal.find("resolution")
    if res is None:
        res = sensor.find("resolution")
    try:
        w, h = (int(res.get("width", "")), int(res.get("height", ""))) if res is not None else (0, 0)
    except ValueError:
        w = h = 0
    if w <= 0 or h <= 0:
        got = None if res is None else dict(res.attrib)
        raise InvalidInputError(f"{where}: `resolution` must give positive integer width and height; got {got!r}")
    v = {t: _num(cal.findtext(t), f"{where}: `{t}`") if cal.find(t) is not None else 0.0
         for t in ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2", "p3", "p4")}
    if cal.find("f") is None:
        raise InvalidInputError(f"{where} lacks `f`")
    bad = {k: v[k] for k in _ZERO_TERMS if v[k] != 0.0}
    if bad:
        raise InvalidInputError(f"{where} has {bad}; the frame camera model has only k1, k2, k3, p1, p2 (k4, p3, "
                                "p4 must be 0)")
    fx, fy, s = v["f"] + v["b1"], v["f"], v["b2"]
    d: dict[str, Any] = {"width": w, "height": h,
                         "principal_point_px": [(w - 1) / 2.0 + v["cx"], (h - 1) / 2.0 + v["cy"]],
                         "distortion": {"k1": v["k1"], "k2": v["k2"], "k3": v["k3"], "p1": v["p2"], "p2": v["p1"]}}
    return camera_from_focals(d, fx, fy, s, where=where)


def _similarity(el: ET.Element | None, label: str) -> NDArray[np.float64] | None:
    """A ``<transform>`` with rotation/translation/scale (or 16 numbers) as a 4 x 4 matrix; None when absent."""
    if el is None:
        return None
    if el.find("rotation") is None and el.find("translation") is None:
        text = (el.text or "").strip()
        return _numbers(text, 16, label).reshape(4, 4) if text else None
    R = _numbers(el.findtext("rotation"), 9, f"{label} `rotation`").reshape(3, 3) \
        if el.find("rotation") is not None else np.eye(3)
    t = _numbers(el.findtext("translation"), 3, f"{label} `translation`") \
        if el.find("translation") is not None else np.zeros(3)
    s = _num(el.findtext("scale"), f"{label} `scale`") if el.find("scale") is not None else 1.0
    if s <= 0:
        raise InvalidInputError(f"{label} `scale` must be > 0; got {s!r}")
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = t
    return M


def _split(M: NDArray[np.float64], label: str) -> tuple[float, NDArray[np.float64]]:
    """Scale and rotation of a similarity's 3 x 3 part (refused when not scale x rotation)."""
    A = M[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    if not s > 0:
        raise InvalidInputError(f"{label} is not a similarity (det {np.linalg.det(A)!r})")
    R = A / s
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6:
        raise InvalidInputError(f"{label} is not a rotation times a scale")
    return s, R


def _reference_crs(chunk: ET.Element, where: str) -> str | None:
    text = (chunk.findtext("reference") or "").strip()
    if not text or text.upper().startswith(("LOCAL_CS", "ENGCRS", "ENGINEERINGCRS")):
        return None
    try:
        c = parse_crs(text)
    except CRSError as err:
        raise CRSError(f"{where}: `reference`: {err}") from None
    if not (c.is_geographic or c.is_projected or c.is_geocentric):
        return None  # an engineering (local) CRS
    return crs_to_string(c)


# --------------------------------------------------------------------------- the reader
def read_metashape_chunk(path: StrPath, *, crs: str | None = None, chunk: int = 0) -> MetashapeChunk:
    """Read a Metashape cameras or markers XML (see the module docstring).

    Parameters
    ----------
    path : path
    crs : str, optional
        The projected CRS of the returned poses and markers of a georeferenced chunk (default:
        the chunk's own when projected, else the WGS 84 UTM zone of the cameras).
    chunk : int
        Which ``<chunk>`` of the document.

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Not XML or not a Metashape document, an element with a bad or missing value (file,
        element and value named), an aligned camera whose sensor has no calibration, a sensor
        type or distortion term outside the frame camera model.
    CRSError
        An unknown reference CRS, a geographic ``crs``.
    """
    where = repr(str(path))
    try:
        root = ET.fromstring(read_table_text(path))
    except ET.ParseError as err:
        raise InvalidInputError(f"{where} is not valid XML: {err}") from None
    chunks = [root] if root.tag == "chunk" else root.findall("chunk")
    if root.tag not in ("document", "chunk") or not chunks:
        raise InvalidInputError(f"{where} is not a Metashape XML export (<document><chunk>...); root is <{root.tag}>")
    if not 0 <= chunk < len(chunks):
        raise InvalidInputError(f"{where}: chunk {chunk} out of range 0..{len(chunks) - 1}")
    ch = chunks[chunk]
    cameras: dict[str, Camera] = {}
    labels: dict[str, str] = {}
    sensors = ch.find("sensors")
    for s in (sensors if sensors is not None else []):
        sid = s.get("id", "")
        labels[sid] = s.get("label", sid)
        cam = _sensor_camera(s, f"{where} sensor {sid} ({labels[sid]!r})")
        if cam is not None:
            cameras[sid] = cam
    ref = _reference_crs(ch, where)
    chunk_T = _similarity(ch.find("transform"), f"{where} chunk `transform`")
    comp_T: dict[str, NDArray[np.float64]] = {}
    comps = ch.find("components")
    for comp in (comps if comps is not None else []):
        M = _similarity(comp.find("transform"), f"{where} component {comp.get('id')}")
        if M is not None:
            comp_T[comp.get("id", "")] = M
    names: dict[str, str] = {}
    world: list[tuple[str, str, NDArray[np.float64], NDArray[np.float64]]] = []
    unaligned: list[str] = []
    for cam_el in _cameras_in(ch.find("cameras")):
        cid, label = cam_el.get("id", ""), cam_el.get("label", "")
        names[cid] = label or cid
        tr = cam_el.findtext("transform")
        if not tr or not tr.strip():
            unaligned.append(names[cid])
            continue
        cw = f"{where} camera {cid} ({names[cid]!r})"
        sid = cam_el.get("sensor_id", "")
        if sid not in cameras:
            raise InvalidInputError(f"{cw} is aligned but its sensor {sid!r} has no calibration")
        M = _numbers(tr, 16, f"{cw} `transform`").reshape(4, 4)
        T = comp_T.get(cam_el.get("component_id", ""), chunk_T)
        W = M if T is None else T @ M
        _, R = _split(W, f"{cw} `transform` (in the world)")
        world.append((names[cid], sid, W[:3, 3].copy(), R @ _FLIP))
    pos = np.array([w[2] for w in world], dtype=np.float64).reshape(-1, 3)
    rot = [w[3] for w in world]
    mk_ids, mk_ref, meas = _markers(ch, names, where)
    target: str | None = None
    if ref is not None:
        target, pos, rot, mk_ref = _georeference(ref, crs, pos, rot, mk_ref, where)
        frame = f"projected CRS {target} (positions through PROJ; rotations via local ENU and grid convergence)"
    else:
        if crs is not None:
            raise CRSError(f"{where}: the chunk has a local coordinate system; it cannot be given a CRS ({crs!r})")
        frame = "the chunk's local coordinate system (not georeferenced)"
    for (name, _, _, _), p, R in zip(world, pos, rot, strict=True):
        try:
            if not np.isfinite(p).all():
                raise InvalidInputError(f"position {p.tolist()} is not finite")
            check_rotation(R, "rotation")
        except RectifyError as err:
            raise InvalidInputError(f"{where} camera {name!r}: {err}") from None
    return MetashapeChunk(cameras=cameras, sensor_labels=labels, images=tuple(w[0] for w in world),
                          image_sensor=tuple(w[1] for w in world), positions=pos,
                          rotations=np.array(rot, dtype=np.float64).reshape(-1, 3, 3), unaligned=tuple(unaligned),
                          crs=target, reference_crs=ref, frame=frame, marker_ids=tuple(mk_ids),
                          marker_xyz=mk_ref, meas_id=tuple(m[0] for m in meas),
                          meas_image=tuple(m[1] for m in meas),
                          meas_pixel=np.array([m[2] for m in meas], dtype=np.float64).reshape(-1, 2))


def _markers(ch: ET.Element, names: dict[str, str], where: str
             ) -> tuple[list[str], NDArray[np.float64], list[tuple[str, str, tuple[float, float]]]]:
    ids: list[str] = []
    by_id: dict[str, str] = {}
    ref: list[list[float]] = []
    markers = ch.find("markers")
    for m in (markers if markers is not None else []):
        if m.tag != "marker":
            continue
        mid = m.get("id", "")
        label = m.get("label", mid)
        if label in ids:
            raise InvalidInputError(f"{where}: marker label {label!r} appears twice")
        ids.append(label)
        by_id[mid] = label
        r = m.find("reference")
        mw = f"{where} marker {label!r} `reference`"
        if r is not None and all(r.get(k) is not None for k in "xyz"):
            ref.append([_num(r.get(k), f"{mw} {k}") for k in "xyz"])
        else:
            ref.append([math.nan] * 3)
    meas: list[tuple[str, str, tuple[float, float]]] = []
    for frame in ch.iter("frame"):
        fm = frame.find("markers")
        for m in (fm if fm is not None else []):
            mid = m.get("marker_id", "")
            if mid not in by_id:
                raise InvalidInputError(f"{where}: frame measurements name marker_id {mid!r}, which <markers> lacks")
            for loc in m.findall("location"):
                if loc.get("valid", "true").lower() == "false" or loc.get("x") is None:
                    continue
                cid = loc.get("camera_id", "")
                if cid not in names:
                    raise InvalidInputError(f"{where}: marker {by_id[mid]!r} is measured in camera_id {cid!r}, "
                                            "which <cameras> lacks")
                lw = f"{where} marker {by_id[mid]!r} location in {names[cid]!r}"
                meas.append((by_id[mid], names[cid], (_num(loc.get("x"), f"{lw} x") - 0.5,
                                                      _num(loc.get("y"), f"{lw} y") - 0.5)))
    return ids, np.array(ref, dtype=np.float64).reshape(-1, 3), meas


def _georeference(ref: str, crs: str | None, pos: NDArray[np.float64], rot: list[NDArray[np.float64]],
                  mk_ref: NDArray[np.float64], where: str
                  ) -> tuple[str, NDArray[np.float64], list[NDArray[np.float64]], NDArray[np.float64]]:
    """Geocentric camera poses and reference-CRS markers -> a projected CRS."""
    lonlat = geodetic_from_ecef(pos, crs=ref) if len(pos) else np.zeros((0, 3))
    if crs is not None:
        target = crs_to_string(parse_crs(crs))
    elif parse_crs(ref).is_projected:
        target = ref
    elif len(lonlat):
        target = utm_crs(*np.mean(lonlat[:, :2], axis=0))
    else:
        good = mk_ref[np.isfinite(mk_ref).all(axis=1)]
        if not len(good):
            raise CRSError(f"{where}: nothing georeferenced to place a UTM zone; give crs=")
        target = utm_crs(*np.mean(transform_xyz(ref, "EPSG:4979", good)[:, :2], axis=0))
    if not parse_crs(target).is_projected:
        raise CRSError(f"{where}: poses need a projected CRS; got {target!r}")
    out = transform_xyz(geocentric_crs(ref), target, pos) if len(pos) else pos
    rot = [grid_from_enu(target, ll[0], ll[1]) @ enu_rotation(ll[0], ll[1]) @ R for ll, R in zip(lonlat, rot,
                                                                                                 strict=True)]
    ok = np.isfinite(mk_ref).all(axis=1)
    mk = mk_ref.copy()
    if ok.any():
        mk[ok] = transform_xyz(ref, target, mk_ref[ok])
    return target, out, rot, mk


def detect_metashape(path: StrPath) -> bool:
    """Whether ``path`` is an XML file whose root is a Metashape ``<document>`` with a ``<chunk>``."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = fh.read(1 << 12)
    except OSError:
        return False
    return "<document" in head and "<chunk" in head
