"""OpenSfM / OpenDroneMap ``reconstruction.json`` in, and ``reconstruction.json`` / ``camera_models.json`` out.

:func:`read_opensfm` reads cameras, poses and points (``docs/formats.md``); :func:`opensfm_texts` and
:func:`write_opensfm` write a block (cameras, poses, points) as OpenSfM reads it: the frame of a block
with a CRS becomes OpenSfM's topocentric frame about a ``reference_lla`` (the mean projection centre,
or the one given), through :meth:`OpenSfMReconstruction.to_crs`; a block without a CRS is written in
its own frame without ``reference_lla``. Cameras are written as ``brown`` (``focal_x``, ``focal_y``,
``c_x``, ``c_y`` normalised by the larger image side, k1, k2, k3, p1, p2); a camera with skew is
refused (OpenSfM has none).

Frames
------
OpenSfM's world frame is topocentric east-north-up about ``reference_lla`` (when the file or a
``reference_lla.json`` beside it gives one), else arbitrary; a georeferenced frame is returned with
its CRS (:attr:`OpenSfMReconstruction.crs`): the topocentric frame as a WKT2 projected CRS
(:func:`topocentric_crs_wkt`, EPSG method 9837, which PROJ transforms exactly).

OpenDroneMap replaces ``opensfm/reconstruction.json`` by a georeferenced copy (OpenSfM's
``export_geocoords --reconstruction --proj ... --offset-x E --offset-y N``) and keeps the
topocentric one as ``reconstruction.topocentric.json`` beside it. The copy's poses and points are in
ODM's projected CRS (UTM) *minus* the offset (E, N), mapped by the affine map tangent to the
projection at ``reference_lla`` (:func:`odm_affine`) -- its ``reference_lla`` stays, but no longer
describes the frame -- and its shots' ``gps_position`` stay topocentric. The CRS and the offset are
the two lines of ``odm_georeferencing/coords.txt`` of the ODM project (``WGS84 UTM 32N`` or
``EPSG:n`` or a PROJ string; ``E N``). Such a file is read in that CRS with the offset added back
(the coordinates of ODM's orthophoto and DSM); the GPS positions are mapped into it by the same
affine map.

Camera axes are OpenCV's (x right, y down, z forward); poses are returned in the project's
convention: projection centre in the world frame and rotation photo vector (x, y, -f) -> world
(:class:`stereo.block.types.Pose`). Rotation vectors are read with
:func:`rectify.geometry.rotation.rodrigues`.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from rectify.atomic import atomic_write_text, read_json, read_text
from rectify.errors import CRSError, InvalidInputError, RectifyError
from rectify.geometry.camera import Camera
from rectify.geometry.crs import crs_to_string, is_geographic, parse_crs, same_crs, transform_xyz
from rectify.geometry.rotation import rodrigues
from stereo.block.types import Pose
from stereo.formats.odm import odm_crs

__all__ = ["FOCAL_ASPECT_TOLERANCE", "ODM_COORDS", "ODM_TOPOCENTRIC", "OPENSFM_PROJECTIONS", "OPENSFM_FILES",
           "OpenSfMReconstruction", "crs_label", "odm_affine", "read_odm_coords", "read_opensfm", "topocentric_crs_wkt",
           "opensfm_camera", "opensfm_texts", "write_opensfm"]

logger = logging.getLogger(__name__)

StrPath = str | os.PathLike[str]

#: OpenSfM projection types this reader converts (others are refused by name)
OPENSFM_PROJECTIONS = ("perspective", "brown", "radial", "simple_radial")
#: relative difference of OpenSfM's focal_x and focal_y below which their mean is used (above: refused)
FOCAL_ASPECT_TOLERANCE = 1e-3
#: the topocentric reconstruction OpenDroneMap keeps beside its georeferenced ``reconstruction.json``
ODM_TOPOCENTRIC = "reconstruction.topocentric.json"
#: ODM's CRS and offset of the georeferenced reconstruction, relative to the ODM project folder
ODM_COORDS = Path("odm_georeferencing") / "coords.txt"


@dataclass(frozen=True, eq=False)
class OpenSfMReconstruction:
    """One reconstruction of an OpenSfM / OpenDroneMap ``reconstruction.json``.

    Parameters
    ----------
    cameras : dict of str -> Camera
        Pixel cameras (:attr:`Camera.pixel_camera`) keyed by OpenSfM's camera id.
    poses : tuple of Pose
        One per shot (sorted by image name): projection centre in the reconstruction's world frame
        and rotation photo vector (x, y, -f) -> world; ``camera`` is the OpenSfM camera id.
    point_ids : tuple of str
        Ids of the reconstructed points (P).
    points : (P, 3) float64
        Their world coordinates.
    colors : (P, 3) uint8 or None
        Their colours (red, green, blue), None when the file has none.
    reference_lonlat_h : (3,) float64 or None
        Origin of OpenSfM's topocentric frame: longitude, latitude (degrees, WGS 84) and
        ellipsoidal height (metres), from the reconstruction's ``reference_lla`` or from
        ``reference_lla.json`` beside the file; None when neither exists.
    frame : str
        A description of the world frame.
    gps_position : (n, 3) float64
        Each shot's ``gps_position`` in the world frame (converted from OpenSfM's topocentric
        frame when the world frame is another), NaN rows where absent or not convertible.
    gps_dop : (n,) float64
        Each shot's ``gps_dop`` (metres), NaN where absent.
    index : int
        Position of this reconstruction in the file's list.
    n_reconstructions : int
        Number of reconstructions in the file.
    source : Path or None
        The file read.
    crs : str or None
        The world frame as a CRS: ``"EPSG:n"`` or WKT2 (:func:`topocentric_crs_wkt` for OpenSfM's
        topocentric frame); None when the file is not georeferenced.
    offset : (3,) float64 or None
        What was added to the file's coordinates to give ``crs`` coordinates (ODM's georeferenced
        reconstruction: its easting and northing offset); None otherwise.
    """

    cameras: dict[str, Camera]
    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8] | None
    reference_lonlat_h: NDArray[np.float64] | None
    frame: str
    gps_position: NDArray[np.float64]
    gps_dop: NDArray[np.float64]
    index: int = 0
    n_reconstructions: int = 1
    source: Path | None = None
    crs: str | None = None
    offset: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "poses", tuple(self.poses))
        object.__setattr__(self, "point_ids", tuple(self.point_ids))
        for name in ("points", "colors", "reference_lonlat_h", "gps_position", "gps_dop", "offset"):
            a = getattr(self, name)
            if a is not None:
                a = np.array(a, copy=True)
                a.flags.writeable = False
                object.__setattr__(self, name, a)


    def to_crs(self, crs: str) -> OpenSfMReconstruction:
        """The reconstruction in another CRS: positions, points and GPS positions through pyproj, each
        rotation turned by the local rotation of the frame at its camera (the orthonormal part of the
        transformation's Jacobian, from central differences of 1 m: the meridian convergence of a map
        projection, for instance).

        Raises
        ------
        CRSError
            The reconstruction has no CRS (not georeferenced), or no transformation exists.
        """
        if self.crs is None:
            raise CRSError(f"the reconstruction {str(self.source)!r} is not georeferenced (no reference_lla): it "
                           f"cannot be converted into {crs!r}")
        if same_crs(self.crs, crs):
            return self
        C = np.array([p.position for p in self.poses]).reshape(-1, 3)
        C2 = transform_xyz(self.crs, crs, C)
        J = np.empty((len(C), 3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            J[:, :, k] = (transform_xyz(self.crs, crs, C + e) - transform_xyz(self.crs, crs, C - e)) / 2.0
        U, _, Vt = np.linalg.svd(J)
        Q = U @ Vt
        poses = tuple(Pose(p.image, p.camera, C2[i], Q[i] @ p.rotation) for i, p in enumerate(self.poses))
        pts = transform_xyz(self.crs, crs, self.points) if len(self.points) else self.points
        g = np.array(self.gps_position, dtype=np.float64)
        have = np.isfinite(g).all(axis=1)
        if have.any():
            g[have] = transform_xyz(self.crs, crs, g[have])
        q = float(np.degrees(np.arctan2(Q[:, 1, 0], Q[:, 0, 0])).mean()) if len(Q) else 0.0
        frame = (f"{crs_label(crs)}, converted from {self.frame} (positions and points through pyproj; rotations "
                 f"turned by the local rotation of the frame, {q:+.4f} deg about the vertical on average)")
        return OpenSfMReconstruction(cameras=self.cameras, poses=poses, point_ids=self.point_ids, points=pts,
                                     colors=self.colors, reference_lonlat_h=self.reference_lonlat_h, frame=frame,
                                     gps_position=g, gps_dop=self.gps_dop, index=self.index,
                                     n_reconstructions=self.n_reconstructions, source=self.source, crs=crs,
                                     offset=None)


def crs_label(crs: str) -> str:
    """A short name of a CRS for messages: the ``EPSG:n`` code, else the CRS's name."""
    code = crs_to_string(crs)
    return code if code.upper().startswith("EPSG:") else parse_crs(crs).name


def topocentric_crs_wkt(lonlat_h: Any) -> str:
    """WKT2 of OpenSfM's topocentric frame: east-north-up, metres, about the WGS 84 point (lon, lat, h).

    A projected CRS with the conversion EPSG 9837 (Geographic/topocentric conversions) from WGS 84's 3D
    geographic CRS: PROJ transforms it exactly (x east along the tangent plane, z up along the
    ellipsoid normal at the origin), as :func:`rectify.geometry.geodesy.enu_from_ecef` does.
    """
    lon, lat, h = (float(v) for v in np.asarray(lonlat_h, dtype=np.float64).reshape(3))
    deg = 'ANGLEUNIT["degree",0.0174532925199433]'
    m = 'LENGTHUNIT["metre",1]'
    return (f'PROJCRS["Topocentric ENU about lon {lon!r} lat {lat!r} h {h!r} (WGS 84)",'
            f'BASEGEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563,{m}]],'
            f'PRIMEM["Greenwich",0,{deg}]],'
            f'CONVERSION["Topocentric",METHOD["Geographic/topocentric conversions",ID["EPSG",9837]],'
            f'PARAMETER["Latitude of topocentric origin",{lat!r},{deg},ID["EPSG",8834]],'
            f'PARAMETER["Longitude of topocentric origin",{lon!r},{deg},ID["EPSG",8835]],'
            f'PARAMETER["Ellipsoidal height of topocentric origin",{h!r},{m},ID["EPSG",8836]]],'
            f'CS[Cartesian,3],AXIS["topocentric East (U)",east,ORDER[1],{m}],'
            f'AXIS["topocentric North (V)",north,ORDER[2],{m}],AXIS["topocentric Up (W)",up,ORDER[3],{m}]]')


def odm_affine(lonlat_h: Any, crs: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The affine map (A, b) of OpenSfM's ``export_geocoords`` (ODM's default): topocentric x -> A x + b in ``crs``.

    A's columns are the images of the three unit vectors at the topocentric origin minus the image of the
    origin, b that image (through pyproj, as OpenSfM does through its reference and PROJ). It departs from
    the exact conversion by the earth's curvature in height (d^2 / 2R: 0.7 cm at 300 m, 7.8 cm at 1 km
    from the origin; in plan by about 1 mm at 1 km).
    """
    q = transform_xyz(topocentric_crs_wkt(lonlat_h), crs, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                                                                     [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]))
    return (q[:3] - q[3]).T, q[3].copy()


def read_odm_coords(path: StrPath) -> tuple[str, NDArray[np.float64]]:
    """ODM's ``odm_georeferencing/coords.txt``: the CRS (``"EPSG:n"`` or a PROJ string) and the offset (E, N).

    Line 1 is ``WGS84 UTM <zone><N|S>``, ``EPSG:<n>`` or a PROJ string; line 2 the easting and northing
    offset. Further lines (camera positions) are not read.

    Raises
    ------
    CRSError
        A first line ODM would not read (:func:`stereo.formats.odm.odm_crs`).
    InvalidInputError
        A second line of another form (named with its value).
    RasterIOError
        The file cannot be read.
    """
    text = read_text(Path(path), "ODM coordinates file")
    lines = [ln.strip() for ln in text.splitlines()]
    if len(lines) < 2:
        raise InvalidInputError(f"{str(path)!r}: an ODM coordinates file has a CRS line and an offset line; got "
                                f"{len(lines)} line(s)")
    crs = odm_crs(lines[0], path)  # ODM's own header syntax, read as ODM reads it
    try:
        off = [float(v) for v in lines[1].split()]
    except ValueError:
        off = []
    if len(off) != 2 or not all(math.isfinite(v) for v in off):
        raise InvalidInputError(f"{str(path)!r} line 2: the offset must be two numbers 'easting northing'; got "
                                f"{lines[1]!r}")
    return crs, np.array([off[0], off[1], 0.0])


def _odm_georeferenced(path: Path) -> tuple[str, NDArray[np.float64]] | None:
    """The CRS and offset of ODM's georeferenced ``reconstruction.json`` (None: not one)."""
    if path.name == ODM_TOPOCENTRIC or not (path.parent / ODM_TOPOCENTRIC).is_file():
        return None
    coords = path.parent.parent / ODM_COORDS
    if not coords.is_file():
        raise InvalidInputError(
            f"{str(path)!r} is OpenDroneMap's georeferenced reconstruction ({ODM_TOPOCENTRIC} is beside it): its "
            f"coordinates are a projected CRS minus an offset, both given by {str(coords)!r}, which is missing; keep "
            f"the ODM project's layout, or give {str(path.parent / ODM_TOPOCENTRIC)!r} (topocentric about "
            "reference_lla)")
    return read_odm_coords(coords)


def _num_of(v: Any, what: str, path: Path) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InvalidInputError(f"{str(path)!r}: {what} must be a finite number; got {v!r}")
    return float(v)


def _vec3(v: Any, what: str, path: Path) -> NDArray[np.float64]:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise InvalidInputError(f"{str(path)!r}: {what} must be a list of 3 numbers; got {v!r}")
    return np.array([_num_of(c, what, path) for c in v])


def _opensfm_camera(key: str, obj: Any, path: Path) -> Camera:
    where = f"camera {key!r}"
    if not isinstance(obj, dict):
        raise InvalidInputError(f"{str(path)!r}: {where} must be an object; got {obj!r}")
    pt = obj.get("projection_type", "perspective")
    if pt not in OPENSFM_PROJECTIONS:
        raise InvalidInputError(f"{str(path)!r}: {where} has projection_type {pt!r}, which the frame camera model "
                                f"cannot represent; supported: {list(OPENSFM_PROJECTIONS)}")
    w, h = obj.get("width"), obj.get("height")
    if isinstance(w, bool) or isinstance(h, bool) or not isinstance(w, int) or not isinstance(h, int) \
            or w <= 0 or h <= 0:
        raise InvalidInputError(f"{str(path)!r}: {where} needs positive integer width and height (the "
                                f"normalised coordinates depend on them); got {w!r}, {h!r}")
    size = float(max(w, h))
    if pt == "perspective":
        if "focal" not in obj:
            raise InvalidInputError(f"{str(path)!r}: {where} ({pt}) lacks 'focal'")
        f = _num_of(obj["focal"], f"{where} focal", path)
        if f <= 0:
            raise InvalidInputError(f"{str(path)!r}: {where} focal must be > 0; got {f!r}")
        cx = cy = 0.0
    else:
        missing = [k for k in ("focal_x", "focal_y") if k not in obj]
        if missing:
            raise InvalidInputError(f"{str(path)!r}: {where} ({pt}) lacks {missing}")
        fx = _num_of(obj["focal_x"], f"{where} focal_x", path)
        fy = _num_of(obj["focal_y"], f"{where} focal_y", path)
        if fx <= 0 or fy <= 0:
            raise InvalidInputError(f"{str(path)!r}: {where} focal_x and focal_y must be > 0; got {fx!r}, {fy!r}")
        if abs(fx - fy) > FOCAL_ASPECT_TOLERANCE * max(fx, fy):
            raise InvalidInputError(f"{str(path)!r}: {where} has focal_x {fx!r} and focal_y {fy!r}; the frame camera "
                                    f"model needs square pixels (one focal length, within "
                                    f"{FOCAL_ASPECT_TOLERANCE:.1%})")
        if fx != fy:
            logger.info("%s: %s: focal_x %r and focal_y %r differ by %.2g; their mean is used", path, where, fx, fy,
                        abs(fx - fy) / max(fx, fy))
        f = 0.5 * (fx + fy)
        cx = _num_of(obj.get("c_x", 0.0), f"{where} c_x", path)
        cy = _num_of(obj.get("c_y", 0.0), f"{where} c_y", path)
    keys = {"perspective": ("k1", "k2"), "brown": ("k1", "k2", "k3", "p1", "p2"), "radial": ("k1", "k2"),
            "simple_radial": ("k1",)}[pt]
    dist = {k: _num_of(obj.get(k, 0.0), f"{where} {k}", path) for k in keys}
    doc = {"focal_length_px": f * size,
           "principal_point_px": [cx * size + (w - 1) / 2.0, cy * size + (h - 1) / 2.0],
           "width": w, "height": h, "distortion": {k: v for k, v in dist.items() if v != 0.0}}
    return Camera.from_dict(doc)


def _reference(rec: dict[str, Any], path: Path) -> NDArray[np.float64] | None:
    lla = rec.get("reference_lla")
    where = "reference_lla"
    src = path
    if lla is None:
        side = path.with_name("reference_lla.json")
        if not side.is_file():
            return None
        lla = read_json(side, "OpenSfM reference_lla.json")
        src = side
        where = "the reference"
    if not isinstance(lla, dict) or any(k not in lla for k in ("latitude", "longitude", "altitude")):
        raise InvalidInputError(f"{str(src)!r}: {where} must hold latitude, longitude and altitude; got {lla!r}")
    lon = _num_of(lla["longitude"], f"{where} longitude", src)
    lat = _num_of(lla["latitude"], f"{where} latitude", src)
    alt = _num_of(lla["altitude"], f"{where} altitude", src)
    if abs(lat) > 90 or abs(lon) > 360:
        raise InvalidInputError(f"{str(src)!r}: {where} latitude {lat!r} / longitude {lon!r} out of range")
    return np.array([lon, lat, alt])


def read_opensfm(path: StrPath, *, index: int | None = None) -> OpenSfMReconstruction:
    """Read cameras, poses and points of an OpenSfM / OpenDroneMap ``reconstruction.json``.

    Parameters
    ----------
    path : str or path-like
        The file: a JSON list of reconstructions.
    index : int, optional
        Which reconstruction; default the one with the most shots (the first of equals).

    Returns
    -------
    OpenSfMReconstruction

    Notes
    -----
    OpenSfM's shot ``rotation`` r is the axis-angle vector of R_cw (world -> camera) and
    ``translation`` t gives x_cam = R_cw X + t in camera axes x right, y down, z forward, so the
    projection centre is C = -R_cw^T t and the pose rotation (photo axes x right, y up, z back)
    is R = R_cw^T diag(1, -1, -1).

    OpenSfM's normalised image coordinates are u = (col + 0.5 - w/2) / s, v = (row + 0.5 - h/2) / s
    with s = max(w, h) and pixel centres at integer col, row (its pixel coordinates are OpenCV's,
    like ours), so pixel = s u + (w - 1) / 2. A camera becomes a pixel camera with
    f_px = s f, principal point (s c_x + (w - 1)/2, s c_y + (h - 1)/2), and OpenSfM's k1, k2, k3,
    p1, p2, which have OpenCV's definition on x/z, y/z. ``perspective`` (focal, k1, k2),
    ``brown`` (focal_x, focal_y, c_x, c_y, k1, k2, k3, p1, p2), ``radial`` (k1, k2) and
    ``simple_radial`` (k1) are read; fisheye, dual and spherical cameras are refused by name.
    ``focal_x`` and ``focal_y`` that differ by up to 0.1 % are replaced by their mean (a scale error
    of at most half the difference across the image); larger differences are refused.

    The frame (module docstring): with ``reference_lla`` OpenSfM's topocentric frame, ``crs`` its WKT2;
    OpenDroneMap's georeferenced ``reconstruction.json`` (``reconstruction.topocentric.json`` beside
    it) in the CRS of ``../odm_georeferencing/coords.txt`` with the offset added back.

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Not valid JSON, not a list of reconstructions, no reconstruction at ``index``, an
        unsupported camera, a shot naming an unknown camera, malformed numbers (naming the value);
        ODM's georeferenced reconstruction without its ``odm_georeferencing/coords.txt``, or a
        coordinates file of another form.
    """
    p = Path(path)
    doc = read_json(p, "OpenSfM reconstruction")
    if isinstance(doc, dict) and "shots" in doc:
        doc = [doc]
    if not isinstance(doc, list) or not doc or not all(isinstance(r, dict) for r in doc):
        raise InvalidInputError(f"{str(p)!r} is not an OpenSfM reconstruction file (a non-empty JSON list of "
                                f"reconstructions); got {type(doc).__name__}")
    if index is None:
        index = max(range(len(doc)), key=lambda i: (len(doc[i].get("shots") or {}), -i))
    elif isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(doc):
        raise InvalidInputError(f"{str(p)!r}: reconstruction index {index!r} out of range 0..{len(doc) - 1}")
    rec = doc[index]
    for key in ("cameras", "shots"):
        if not isinstance(rec.get(key), dict):
            raise InvalidInputError(f"{str(p)!r}: reconstruction {index} lacks the {key!r} object")
    cameras = {str(k): _opensfm_camera(str(k), v, p) for k, v in rec["cameras"].items()}
    poses: list[Pose] = []
    gps = []
    dop = []
    flip = np.diag([1.0, -1.0, -1.0])
    for name in sorted(rec["shots"]):
        shot = rec["shots"][name]
        if not isinstance(shot, dict) or "rotation" not in shot or "translation" not in shot:
            raise InvalidInputError(f"{str(p)!r}: shot {name!r} lacks rotation/translation")
        cam = shot.get("camera")
        if cam not in cameras:
            raise InvalidInputError(f"{str(p)!r}: shot {name!r} names camera {cam!r}, which is not in the "
                                    f"reconstruction (cameras: {sorted(cameras)})")
        R_cw = rodrigues(_vec3(shot["rotation"], f"shot {name!r} rotation", p))[0]
        t = _vec3(shot["translation"], f"shot {name!r} translation", p)
        try:
            poses.append(Pose(str(name), str(cam), -R_cw.T @ t, R_cw.T @ flip))
        except RectifyError as err:
            raise InvalidInputError(f"{str(p)!r}: shot {name!r}: {err}") from err
        g = shot.get("gps_position")
        gps.append(_vec3(g, f"shot {name!r} gps_position", p) if g is not None else np.full(3, np.nan))
        d = shot.get("gps_dop")
        dop.append(_num_of(d, f"shot {name!r} gps_dop", p) if d is not None else np.nan)
    pts = rec.get("points") or {}
    if not isinstance(pts, dict):
        raise InvalidInputError(f"{str(p)!r}: reconstruction {index} 'points' must be an object")
    ids = sorted(pts)
    xyz = np.empty((len(ids), 3))
    rgb = np.empty((len(ids), 3))
    all_colours = True
    for i, k in enumerate(ids):
        v = pts[k]
        if not isinstance(v, dict) or "coordinates" not in v:
            raise InvalidInputError(f"{str(p)!r}: point {k!r} lacks coordinates")
        xyz[i] = _vec3(v["coordinates"], f"point {k!r} coordinates", p)
        if "color" in v and all_colours:
            rgb[i] = _vec3(v["color"], f"point {k!r} color", p)
        else:
            all_colours = False
    colors = np.clip(np.rint(rgb), 0, 255).astype(np.uint8) if all_colours and ids else None
    ref = _reference(rec, p)
    g = np.array(gps, dtype=float).reshape(-1, 3)
    odm = _odm_georeferenced(p)
    crs: str | None = None
    offset = None
    if odm is not None:
        crs, offset = odm
        poses = [Pose(q.image, q.camera, q.position + offset, q.rotation) for q in poses]
        xyz = xyz + offset
        have = np.isfinite(g).all(axis=1)
        if have.any() and ref is not None:  # OpenSfM's gps_position stays topocentric in ODM's copy
            A, b = odm_affine(ref, crs)
            g[have] = g[have] @ A.T + b
        elif have.any():
            logger.warning("%s: gps_position without reference_lla cannot be put into %s; not used", p, crs)
            g[:] = np.nan
        frame = (f"OpenDroneMap's georeferenced frame {crs} (from {str(p.parent.parent / ODM_COORDS)!r}; the "
                 f"file's coordinates plus its offset E {offset[0]:.3f} m, N {offset[1]:.3f} m; heights as ODM's)")
    elif ref is not None:
        crs = topocentric_crs_wkt(ref)
        frame = (f"topocentric east-north-up frame of OpenSfM (x east, y north, z up along the ellipsoid normal, "
                 f"m) about reference_lla lon {ref[0]:.8f} deg, lat {ref[1]:.8f} deg, h {ref[2]:.3f} m (WGS 84)")
    else:
        frame = "OpenSfM's arbitrary world frame (no reference_lla: not georeferenced; z roughly up)"
    return OpenSfMReconstruction(cameras=cameras, poses=tuple(poses), point_ids=tuple(str(k) for k in ids),
                                 points=xyz, colors=colors, reference_lonlat_h=ref, frame=frame,
                                 gps_position=g, gps_dop=np.array(dop, dtype=float), index=index,
                                 n_reconstructions=len(doc), source=p, crs=crs, offset=offset)


# --------------------------------------------------------------------------- writing
#: the files :func:`write_opensfm` writes
OPENSFM_FILES = ("reconstruction.json", "camera_models.json")


def opensfm_camera(camera: Camera, name: str = "camera") -> dict[str, Any]:
    """OpenSfM's ``brown`` camera of ``camera`` (focal lengths and principal point normalised by max(w, h)).

    Raises
    ------
    InvalidInputError
        A camera with skew (OpenSfM has none).
    """
    K = np.asarray(camera.K, dtype=np.float64)
    if K[0, 1] != 0.0:
        raise InvalidInputError(f"camera {name!r} has skew {float(K[0, 1])!r} px, which OpenSfM's cameras cannot hold")
    w, h = camera.width, camera.height
    s = float(max(w, h))
    d = camera.distortion
    return {"projection_type": "brown", "width": int(w), "height": int(h),
            "focal_x": float(K[0, 0]) / s, "focal_y": float(K[1, 1]) / s,
            "c_x": (float(K[0, 2]) - (w - 1) / 2.0) / s, "c_y": (float(K[1, 2]) - (h - 1) / 2.0) / s,
            "k1": float(d["k1"]), "k2": float(d["k2"]), "k3": float(d["k3"]), "p1": float(d["p1"]),
            "p2": float(d["p2"])}


def opensfm_texts(cameras: Mapping[str, Camera], poses: Sequence[Pose], *, crs: str | None = None,
                  points: ArrayLike | None = None, point_ids: Sequence[str] | None = None,
                  colors: ArrayLike | None = None, reference_lonlat_h: ArrayLike | None = None) -> dict[str, str]:
    """``reconstruction.json`` and ``camera_models.json`` of a block (name -> text), as OpenSfM reads them.

    Parameters
    ----------
    cameras : dict of str -> Camera
    poses : sequence of Pose
        In the frame of ``crs``.
    crs : str, optional
        The block's CRS: the poses and points are converted into OpenSfM's topocentric frame about
        ``reference_lonlat_h`` (default: the mean projection centre, on the ellipsoid's normal) and
        ``reference_lla`` is written. None: written in their own frame, no ``reference_lla``.
    points : (P, 3) array_like, optional
    point_ids : sequence of str, optional
        Default ``1 .. P``.
    colors : (P, 3) array_like of 0..255, optional
    reference_lonlat_h : (3,) array_like, optional

    Raises
    ------
    InvalidInputError
        A camera with skew, a pose naming an unknown camera, points and ids of different lengths.
    CRSError
        A CRS PROJ cannot convert.
    """
    for p in poses:
        if p.camera not in cameras:
            raise InvalidInputError(f"image {p.image!r} names camera {p.camera!r}, which is not given "
                                    f"(cameras: {sorted(cameras)})")
    xyz = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ids = [str(i + 1) for i in range(len(xyz))] if point_ids is None else [str(i) for i in point_ids]
    if len(ids) != len(xyz):
        raise InvalidInputError(f"{len(ids)} point ids for {len(xyz)} points")
    rgb = None if colors is None else np.clip(np.rint(np.asarray(colors, dtype=np.float64)), 0, 255).reshape(-1, 3)
    if rgb is not None and len(rgb) != len(xyz):
        raise InvalidInputError(f"{len(rgb)} colours for {len(xyz)} points")
    rec = OpenSfMReconstruction(cameras=dict(cameras), poses=tuple(poses), point_ids=tuple(ids), points=xyz,
                                colors=None, reference_lonlat_h=None, frame="the block's", gps_position=np.full(
                                    (len(poses), 3), np.nan), gps_dop=np.full(len(poses), np.nan), crs=crs)
    ref = None
    if crs is not None:
        if reference_lonlat_h is not None:
            ref = np.asarray(reference_lonlat_h, dtype=np.float64).reshape(3)
        else:
            if is_geographic(crs):
                raise CRSError(f"the block's CRS must be projected to write OpenSfM's topocentric frame; got {crs!r}")
            C = np.array([p.position for p in poses]).reshape(-1, 3)
            ref = transform_xyz(crs, "EPSG:4979", C.mean(axis=0, keepdims=True))[0]
        rec = rec.to_crs(topocentric_crs_wkt(ref))
    flip = np.diag([1.0, -1.0, -1.0])
    shots = {}
    for q in rec.poses:
        R_cw = flip @ q.rotation.T
        shots[q.image] = {"camera": q.camera, "rotation": [float(v) for v in Rotation.from_matrix(R_cw).as_rotvec()],
                          "translation": [float(v) for v in -R_cw @ q.position]}
    pts = {}
    for k, pid in enumerate(rec.point_ids):
        pt: dict[str, Any] = {"coordinates": [float(v) for v in rec.points[k]]}
        if rgb is not None:
            pt["color"] = [float(v) for v in rgb[k]]
        pts[pid] = pt
    cams = {str(k): opensfm_camera(c, str(k)) for k, c in cameras.items()}
    body: dict[str, Any] = {"cameras": cams, "shots": shots, "points": pts}
    if ref is not None:
        body["reference_lla"] = {"latitude": float(ref[1]), "longitude": float(ref[0]), "altitude": float(ref[2])}
    return {"reconstruction.json": json.dumps([body], indent=1) + "\n",
            "camera_models.json": json.dumps(cams, indent=1) + "\n"}


def write_opensfm(folder: StrPath, cameras: Mapping[str, Camera], poses: Sequence[Pose], *, crs: str | None = None,
                  points: ArrayLike | None = None, point_ids: Sequence[str] | None = None,
                  colors: ArrayLike | None = None, overwrite: bool = False) -> tuple[Path, ...]:
    """Write :func:`opensfm_texts` into the existing ``folder`` (each file atomically); return the paths."""
    d = Path(folder)
    if not d.is_dir():
        raise InvalidInputError(f"OpenSfM folder {str(d)!r} does not exist")
    texts = opensfm_texts(cameras, poses, crs=crs, points=points, point_ids=point_ids, colors=colors)
    return tuple(atomic_write_text(d / n, t, overwrite=overwrite) for n, t in texts.items())
