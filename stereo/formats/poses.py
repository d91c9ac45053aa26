"""Known poses in: the position/angle CSV, OpenSfM's ``reconstruction.json``, GNSS/INS angles.

Frames
------
ground
    A right-handed map frame: X east (easting), Y north (northing, "grid north"), Z up; metres.
    Poses, antenna positions and lever arms end up in it.
photo
    x right, y up in the image, z backwards (out of the lens towards the sky for a nadir
    camera); an image point is the vector (x, y, -f) (:mod:`rectify.geometry.camera`). A pose's
    ``rotation`` R takes photo vectors into the ground frame, R = Rx(omega) Ry(phi) Rz(kappa)
    (:func:`rectify.geometry.rotation.matrix_from_angles`). A nadir camera with zero angles looks straight
    down with the top of the image towards north and its x axis towards east.
body (GNSS/INS platform)
    x towards the right wing, y forward (the flight direction), z up; right-handed. It is the
    photo frame of a camera mounted without boresight: image x along the right wing, the top of
    the image forward, the camera looking down (along -z).

Navigation angles
-----------------
``heading`` is the azimuth of the body's forward axis, clockwise from grid north (the map Y
axis) towards east; ``pitch`` is the elevation of the forward axis above the horizontal plane
(nose up positive); ``roll`` is the depression of the right-wing axis below the horizontal plane
(right wing down positive), the sign of Applanix POS and of most aerial GNSS/INS exports.
An INS measures heading from true north and tilts from the local vertical (seed 004); in a map
projection, grid north differs from true north by the meridian convergence, which must be
subtracted from the heading before it is given here (this module does not do it).

Two definitions of the roll angle are offered (``convention``):

``"seed004"`` (default)
    Seed 004, eqs. (6)-(10): pitch and roll are both measured in the vertical plane (the great
    circle through the normal) of their own axis: e_fwd = (cos p sin h, cos p cos h, sin p),
    gamma = arccos(tan p tan r) is the horizontal angle from the forward to the right-wing axis,
    e_right = (cos r sin(h + gamma), cos r cos(h + gamma), -sin r), e_up = e_right x e_fwd
    (components east, north, up). The seed's frame is (north, east, up) and its roll phi raises
    the Y' axis; here phi = -roll, so that right wing down is positive. The rotation is defined
    while |tan p tan r| <= 1 and the body's up axis is above the horizon.
``"euler"``
    Tait-Bryan angles (yaw about the vertical, then pitch about the new right-wing axis, then
    roll about the new forward axis): R_body = Rz(-h) Rx(p) Ry(r). The two agree when pitch or
    roll is zero; in general sin(roll_seed004) = cos(pitch) sin(roll_euler).

With a boresight B = Rx(b_omega) Ry(b_phi) Rz(b_kappa) (camera photo frame -> body frame), the
camera's rotation is R = R_body @ B. With a lever arm l (the vector from the camera's projection
centre to the GNSS antenna phase centre, in the body frame, metres), the projection centre is
C = A - R_body @ l, with A the antenna position.
"""

from __future__ import annotations

import io
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_write_text, read_json
from rectify.errors import CRSError, InvalidInputError, RectifyError, ShapeError
from rectify.formats.common import _need, _no_duplicates, _num, _read_text, _rows
from rectify.geometry.camera import Camera
from rectify.geometry.crs import parse_crs
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles, rot_x, rot_y, rot_z
from stereo.block.types import Pose

__all__ = [
    "ANGLE_UNITS",
    "DEFAULT_CAMERA_ID",
    "NAVIGATION_CONVENTIONS",
    "OPENSFM_PROJECTIONS",
    "OpenSfMReconstruction",
    "PoseTable",
    "body_rotation",
    "navigation_from_rotation",
    "pose_csv_text",
    "read_opensfm",
    "read_pose_csv",
    "rotation_from_navigation",
    "rotation_from_rodrigues",
    "write_pose_csv",
]

logger = logging.getLogger(__name__)

StrPath = str | os.PathLike[str]

#: angle units of the position/angle CSV (``# angles=deg|rad``; ``deg`` when the line is absent)
ANGLE_UNITS = ("deg", "rad")
#: roll definitions of :func:`rotation_from_navigation`
NAVIGATION_CONVENTIONS = ("seed004", "euler")
#: camera id of the rows of a pose CSV that name none (no ``camera`` column, empty cell, no ``camera=``)
DEFAULT_CAMERA_ID = "camera"

_OPK = ("omega", "phi", "kappa")
_NAV = ("heading", "pitch", "roll")
_POS = ("x", "y", "z")
_POS_SIGMA = ("sx", "sy", "sz")
_OPK_SIGMA = ("somega", "sphi", "skappa")
_NAV_SIGMA = ("sheading", "spitch", "sroll")


# =========================================================================== navigation angles
def _boresight(boresight_rad: ArrayLike | None) -> NDArray[np.float64] | None:
    if boresight_rad is None:
        return None
    b = np.asarray(boresight_rad, dtype=np.float64).reshape(-1)
    if b.shape != (3,) or not np.isfinite(b).all():
        raise InvalidInputError(f"boresight_rad must be 3 finite angles (omega, phi, kappa) in radians; "
                                f"got {np.asarray(boresight_rad).tolist()}")
    if np.abs(b).max() > math.radians(10.0):
        raise InvalidInputError(f"boresight_rad must be small angles (< 10 deg each, radians); got {b.tolist()}: "
                                "were degrees given?")
    return matrix_from_angles(b[0], b[1], b[2], "omega-phi-kappa")


def _convention(convention: str) -> str:
    if convention not in NAVIGATION_CONVENTIONS:
        raise InvalidInputError(f"unknown navigation convention {convention!r}; expected one of "
                                f"{list(NAVIGATION_CONVENTIONS)}")
    return convention


def body_rotation(heading: ArrayLike, pitch: ArrayLike, roll: ArrayLike, *,
                  convention: str = "seed004") -> NDArray[np.float64]:
    """Rotation body (x right wing, y forward, z up) -> ground (east, north, up), S + (3, 3).

    See :func:`rotation_from_navigation`; this is the same without a boresight.
    """
    _convention(convention)
    h, p, r = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (heading, pitch, roll)))
    if not (np.isfinite(h).all() and np.isfinite(p).all() and np.isfinite(r).all()):
        raise InvalidInputError(f"navigation angles must be finite; got heading {h.tolist()}, pitch {p.tolist()}, "
                                f"roll {r.tolist()}")
    if convention == "euler":
        return np.asarray(rot_z(-h) @ rot_x(p) @ rot_y(r), dtype=np.float64)
    half = math.pi / 2
    with np.errstate(invalid="ignore", over="ignore"):
        c = np.tan(p) * np.tan(r)
    bad = (np.abs(p) >= half) | (np.abs(r) >= half) | ~(np.abs(c) <= 1.0)
    if np.any(bad):
        i = np.flatnonzero(bad.reshape(-1))[0]
        raise InvalidInputError(
            f"pitch {float(p.reshape(-1)[i])!r} and roll {float(r.reshape(-1)[i])!r} rad admit no orthogonal "
            "platform axes (seed 004 needs |pitch|, |roll| < 90 deg and |tan(pitch) tan(roll)| <= 1)")
    g = np.arccos(c)  # horizontal angle from the forward axis to the right-wing axis, clockwise
    fwd = np.stack([np.cos(p) * np.sin(h), np.cos(p) * np.cos(h), np.sin(p)], axis=-1)
    right = np.stack([np.cos(r) * np.sin(h + g), np.cos(r) * np.cos(h + g), -np.sin(r)], axis=-1)
    up = np.cross(right, fwd)
    return np.stack([right, fwd, up], axis=-1)


def rotation_from_navigation(heading: ArrayLike, pitch: ArrayLike, roll: ArrayLike, *,
                             boresight_rad: ArrayLike | None = None,
                             convention: str = "seed004") -> NDArray[np.float64]:
    """Camera rotation (photo vector (x, y, -f) -> ground) from GNSS/INS navigation angles.

    Parameters
    ----------
    heading, pitch, roll : array_like, radians, broadcast to a common shape S
        Azimuth of the forward axis clockwise from grid north; elevation of the forward axis (nose
        up positive); depression of the right-wing axis (right wing down positive). See the module
        docstring for the exact definitions.
    boresight_rad : (3,) array_like, radians, optional
        Small angles (omega, phi, kappa) of the camera in the body frame: B = Rx Ry Rz of them takes
        camera photo vectors into the body frame (x right wing, y forward, z up). Default: none
        (image x along the right wing, image top forward, looking down).
    convention : {"seed004", "euler"}
        Definition of the roll angle (seed 004's great-circle angles, or Tait-Bryan angles).

    Returns
    -------
    S + (3, 3) float64
        R = R_body @ B.

    Raises
    ------
    InvalidInputError
        Non-finite angles, a boresight that is not 3 small angles, an unknown convention, or (seed
        004) pitch and roll that admit no orthogonal axes.

    Examples
    --------
    Flying east (heading 90 deg), level: the top of the image points east, image x south.

    >>> R = rotation_from_navigation(np.pi / 2, 0.0, 0.0)
    >>> np.round(R @ [0.0, 1.0, 0.0], 12) + 0.0, np.round(R @ [1.0, 0.0, 0.0], 12) + 0.0
    (array([1., 0., 0.]), array([ 0., -1.,  0.]))
    >>> rotation_from_navigation(0.0, 1.2, 1.2)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    rectify.errors.InvalidInputError: pitch 1.2 and roll 1.2 rad admit no orthogonal platform axes ...
    """
    Rb = body_rotation(heading, pitch, roll, convention=convention)
    B = _boresight(boresight_rad)
    return Rb if B is None else np.asarray(Rb @ B, dtype=np.float64)


def navigation_from_rotation(R: ArrayLike, *, boresight_rad: ArrayLike | None = None,
                             convention: str = "seed004") -> NDArray[np.float64]:
    """Navigation angles (heading, pitch, roll), radians, of camera rotations R, shape S + (3,).

    The inverse of :func:`rotation_from_navigation` with the same ``boresight_rad`` and
    ``convention``. Heading is in [0, 2 pi), pitch in [-pi/2, pi/2]; roll in [-pi/2, pi/2]
    (``"seed004"``) or (-pi, pi] (``"euler"``). At pitch +-90 deg the heading is 0.

    Parameters
    ----------
    R : (..., 3, 3) array_like
        Photo vector (x, y, -f) -> ground (east, north, up).

    Examples
    --------
    >>> navigation_from_rotation(rotation_from_navigation(0.3, 0.02, -0.01)).round(12)
    array([ 0.3 ,  0.02, -0.01])
    """
    _convention(convention)
    m = np.asarray(R, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ShapeError(f"`R` must have shape (..., 3, 3); got {m.shape}", actual_shape=m.shape,
                         expected_shape=(3, 3))
    B = _boresight(boresight_rad)
    Rb = m if B is None else m @ B.T
    fwd = Rb[..., :, 1]
    heading = np.mod(np.arctan2(fwd[..., 0], fwd[..., 1]), 2 * np.pi)
    heading = np.where(heading >= 2 * np.pi, 0.0, heading)
    pitch = np.arcsin(np.clip(fwd[..., 2], -1.0, 1.0))
    if convention == "euler":
        roll = np.arctan2(-Rb[..., 2, 0], Rb[..., 2, 2])
    else:
        roll = -np.arcsin(np.clip(Rb[..., 2, 0], -1.0, 1.0))
    return np.stack([heading, pitch, roll], axis=-1)


def _lever(lever_arm_m: ArrayLike | None) -> NDArray[np.float64] | None:
    if lever_arm_m is None:
        return None
    v = np.asarray(lever_arm_m, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise InvalidInputError(f"lever_arm_m must be 3 finite numbers (metres, body frame); "
                                f"got {np.asarray(lever_arm_m).tolist()}")
    return v


# =========================================================================== position/angle CSV
@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses read from a position/angle CSV.

    Parameters
    ----------
    poses : tuple of Pose
        One per row, in file order: projection centre (ground frame, metres; lever arm applied) and
        rotation (photo vector -> ground; boresight applied).
    crs : str or None
        The ``# crs=`` value (validated by :mod:`rectify.geometry.crs`), or None.
    sigma : (n, 6) float64 or None
        A-priori standard deviations of x, y, z (metres) and of the three angles (radians) in the
        file's angle system (``angle_system``); NaN where a cell or column is absent; None when
        the file has no standard-deviation column.
    angle_unit : {"deg", "rad"}
        The unit of the angles in the file.
    angle_system : {"omega-phi-kappa", "navigation"}
        ``omega,phi,kappa`` or ``heading,pitch,roll`` columns.
    source : Path or None
        The file read.
    """

    poses: tuple[Pose, ...]
    crs: str | None
    sigma: NDArray[np.float64] | None
    angle_unit: str
    angle_system: str
    source: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "poses", tuple(self.poses))
        if self.sigma is not None:
            s = np.array(self.sigma, dtype=np.float64, copy=True).reshape(-1, 6)
            if len(s) != len(self.poses):
                raise ShapeError(f"sigma must have shape ({len(self.poses)}, 6); got {s.shape}",
                                 actual_shape=s.shape, expected_shape=(len(self.poses), 6))
            s.flags.writeable = False
            object.__setattr__(self, "sigma", s)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def images(self) -> tuple[str, ...]:
        """Image names, in file order."""
        return tuple(p.image for p in self.poses)


def _comment_settings(text: str, path: StrPath) -> tuple[str, str | None, int | None]:
    """The ``# angles=`` unit (default ``deg``), the ``# crs=`` value and its line."""
    unit: str | None = None
    unit_line: int | None = None
    crs: str | None = None
    crs_line: int | None = None
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s.startswith("#"):
            continue
        body = s.lstrip("#").strip()
        key, sep, value = body.partition("=")
        key = key.strip().lower()
        if not sep:
            continue
        value = value.strip()
        if key == "angles":
            u = value.lower()
            if u not in ANGLE_UNITS:
                raise InvalidInputError(f"{str(path)!r} line {no}: unknown angle unit {value!r}; "
                                        f"expected one of {list(ANGLE_UNITS)}")
            if unit is not None and u != unit:
                raise InvalidInputError(f"{str(path)!r} line {no}: second angle unit {value!r} contradicts "
                                        f"{unit!r} of line {unit_line}")
            unit, unit_line = u, no
        elif key == "crs":
            crs, crs_line = value, no
    return unit or "deg", crs, crs_line


def read_pose_csv(path: StrPath, *, camera: str | None = None, boresight_rad: ArrayLike | None = None,
                  lever_arm_m: ArrayLike | None = None, convention: str = "seed004") -> PoseTable:
    """Read a position/angle CSV (``docs/formats.md``) into poses.

    Header ``image,x,y,z,omega,phi,kappa`` or ``image,x,y,z,heading,pitch,roll``, optional
    ``camera`` and standard deviations ``sx,sy,sz`` and ``somega,sphi,skappa`` (or
    ``sheading,spitch,sroll``), in the units of the values. Comment lines ``# crs=EPSG:nnnn`` and
    ``# angles=deg|rad`` (``deg`` when absent). A byte-order mark is accepted.

    Parameters
    ----------
    path : str or path-like
        The CSV file.
    camera : str, optional
        Camera id of the rows that name none (no ``camera`` column, or an empty cell); default
        :data:`DEFAULT_CAMERA_ID`.
    boresight_rad : (3,) array_like, optional
        Boresight angles (radians) of the camera in the GNSS/INS body frame; navigation files only.
    lever_arm_m : (3,) array_like, optional
        Vector from the projection centre to the antenna phase centre, metres, in the body frame
        (navigation files) or the camera's photo frame (omega-phi-kappa files); the file's
        positions are then antenna positions and C = A - R_body @ lever_arm_m.
    convention : {"seed004", "euler"}
        Roll definition of navigation files (:func:`rotation_from_navigation`).

    Returns
    -------
    PoseTable

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Missing or unknown columns, both angle systems, non-numeric or non-finite values (naming the
        line and value), negative standard deviations, duplicate or empty image names, an unknown
        angle unit, a boresight with omega-phi-kappa angles.
    CRSError
        The ``# crs=`` value is not a CRS (naming the line).
    """
    p = Path(path)
    conv = _convention(convention)
    if camera is not None and (not isinstance(camera, str) or not camera):
        raise InvalidInputError(f"camera must be a non-empty camera id; got {camera!r}")
    default_camera = camera or DEFAULT_CAMERA_ID
    text = _read_text(p)
    unit, crs, crs_line = _comment_settings(text, p)
    if crs is not None:
        try:
            parse_crs(crs)
        except CRSError as err:
            raise CRSError(f"{str(p)!r} line {crs_line}: {err}") from err
    rows, lines, _ = _rows(text, p)
    if not rows:
        raise InvalidInputError(f"{str(p)!r} has a header but no pose rows")
    fields = list(rows[0].keys())
    has_opk = any(f in fields for f in _OPK)
    has_nav = any(f in fields for f in _NAV)
    if has_opk and has_nav:
        raise InvalidInputError(f"{str(p)!r}: give either omega,phi,kappa or heading,pitch,roll, not both; "
                                f"header is {fields}")
    nav = has_nav
    angle_cols = _NAV if nav else _OPK
    angle_sigma_cols = _NAV_SIGMA if nav else _OPK_SIGMA
    _need(fields, ("image", *_POS, *angle_cols), p)
    allowed = {"image", "camera", *_POS, *angle_cols, *_POS_SIGMA, *angle_sigma_cols}
    unknown = [f for f in fields if f not in allowed]
    if unknown:
        raise InvalidInputError(f"{str(p)!r}: unknown column(s) {unknown}; allowed are {sorted(allowed)}")
    if boresight_rad is not None and not nav:
        raise InvalidInputError(f"{str(p)!r}: boresight_rad applies to heading,pitch,roll files only; this file "
                                "has omega,phi,kappa (the camera's own angles)")
    lever = _lever(lever_arm_m)
    sigma_cols = (*_POS_SIGMA, *angle_sigma_cols)
    has_sigma = any(f in fields for f in sigma_cols)
    scale = math.pi / 180.0 if unit == "deg" else 1.0

    images: list[str] = []
    cams: list[str] = []
    pos = np.empty((len(rows), 3))
    ang = np.empty((len(rows), 3))
    sig = np.full((len(rows), 6), np.nan)
    for i, (r, ln) in enumerate(zip(rows, lines, strict=False)):
        name = r.get("image", "")
        if not name:
            raise InvalidInputError(f"{str(p)!r} line {ln}: empty image name")
        images.append(name)
        cams.append(r.get("camera", "") or default_camera)
        pos[i] = [_num(r, k, ln, p) for k in _POS]
        ang[i] = [_num(r, k, ln, p) * scale for k in angle_cols]
        for j, k in enumerate(sigma_cols):
            if k in fields:
                v = _num(r, k, ln, p, allow_empty=True)
                if v < 0:
                    raise InvalidInputError(f"{str(p)!r} line {ln}: standard deviation {k!r} must be >= 0; "
                                            f"got {r[k]!r}")
                sig[i, j] = v * (scale if j >= 3 else 1.0)
    _no_duplicates(images, p, "image name(s)")

    if nav:
        try:
            Rb = body_rotation(ang[:, 0], ang[:, 1], ang[:, 2], convention=conv)
        except InvalidInputError:
            for i, ln in enumerate(lines):  # name the line
                try:
                    body_rotation(ang[i, 0], ang[i, 1], ang[i, 2], convention=conv)
                except InvalidInputError as err:
                    raise InvalidInputError(f"{str(p)!r} line {ln}: {err}") from err
            raise
        B = _boresight(boresight_rad)
        R = Rb if B is None else Rb @ B
    else:
        R = matrix_from_angles(ang[:, 0], ang[:, 1], ang[:, 2], "omega-phi-kappa")
        Rb = R
    if lever is not None:
        pos = pos - Rb @ lever
    poses = tuple(Pose(images[i], cams[i], pos[i], R[i]) for i in range(len(rows)))
    return PoseTable(poses, crs, sig if has_sigma else None, unit, "navigation" if nav else "omega-phi-kappa", p)


def _fmt(v: float) -> str:
    return repr(float(v) + 0.0)  # + 0.0: no "-0.0"


def pose_csv_text(poses: Sequence[Pose], *, crs: str | None, angles: str = "deg",
                  std: ArrayLike | None = None) -> str:
    """The position/angle CSV text of ``poses`` (omega-phi-kappa; see :func:`write_pose_csv`)."""
    if angles not in ANGLE_UNITS:
        raise InvalidInputError(f"unknown angle unit {angles!r}; expected one of {list(ANGLE_UNITS)}")
    if crs is not None:
        parse_crs(crs)
    poses = list(poses)
    if not all(isinstance(q, Pose) for q in poses):
        raise InvalidInputError("poses must be a sequence of stereo.block.types.Pose")
    _no_duplicates([q.image for q in poses], "poses", "image name(s)")
    for q in poses:
        if any(c in q.image + q.camera for c in ",\"\n\r") or q.image != q.image.strip() \
                or q.camera != q.camera.strip():
            raise InvalidInputError(f"image name {q.image!r} / camera id {q.camera!r} cannot be written to a CSV "
                                    "cell (comma, quote, line break or surrounding spaces)")
    s: NDArray[np.float64] | None = None
    if std is not None:
        s = np.asarray(std, dtype=np.float64)
        if s.shape != (len(poses), 6):
            raise ShapeError(f"std must have shape ({len(poses)}, 6); got {s.shape}", actual_shape=s.shape,
                             expected_shape=(len(poses), 6))
        if np.any(s < 0) or np.any(np.isinf(s)):
            raise InvalidInputError(f"std must be >= 0 and finite (NaN for unknown); got {s.tolist()}")
    to_unit = 180.0 / math.pi if angles == "deg" else 1.0
    buf = io.StringIO()
    if crs is not None:
        buf.write(f"# crs={crs}\n")
    buf.write(f"# angles={angles}\n")
    buf.write("# R = Rx(omega) Ry(phi) Rz(kappa) takes the photo vector (x, y, -f) into the ground frame\n")
    cols = ["image", "camera", *_POS, *_OPK] + ([*_POS_SIGMA, *_OPK_SIGMA] if s is not None else [])
    buf.write(",".join(cols) + "\n")
    for i, q in enumerate(poses):
        a = angles_from_matrix(q.rotation, "omega-phi-kappa") * to_unit
        vals = [q.image, q.camera, *(_fmt(v) for v in q.position), *(_fmt(v) for v in a)]
        if s is not None:
            vals += ["" if math.isnan(v) else _fmt(v * (to_unit if j >= 3 else 1.0)) for j, v in enumerate(s[i])]
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_pose_csv(path: StrPath, poses: Sequence[Pose], *, crs: str | None, angles: str = "deg",
                   std: ArrayLike | None = None, overwrite: bool = False) -> Path:
    """Write poses as a position/angle CSV (omega, phi, kappa), atomically; return the path.

    Parameters
    ----------
    path : str or path-like
        The output; an existing file is replaced only with ``overwrite``.
    poses : sequence of Pose
        Projection centres (ground, metres) and rotations (photo -> ground).
    crs : str or None
        Written as the ``# crs=`` line (validated); None writes none.
    angles : {"deg", "rad"}
        Unit of the angle columns (written as the ``# angles=`` line).
    std : (n, 6) array_like, optional
        Standard deviations of x, y, z (metres) and omega, phi, kappa (radians); NaN cells are left
        empty. Written as ``sx,sy,sz,somega,sphi,skappa`` in the file's units.

    Numbers are written with :func:`repr` (17 significant digits), so they read back exactly.

    Raises
    ------
    InvalidInputError
        Unknown angle unit, duplicate image names, names a CSV cell cannot hold, a bad ``std``, an
        existing output without ``overwrite``.
    CRSError
        ``crs`` is not a CRS.
    RasterIOError
        The file cannot be written (nothing is left behind).
    """
    text = pose_csv_text(poses, crs=crs, angles=angles, std=std)
    return atomic_write_text(path, text, overwrite=overwrite)


# =========================================================================== OpenSfM
#: OpenSfM projection types this reader converts (others are refused by name)
OPENSFM_PROJECTIONS = ("perspective", "brown", "radial", "simple_radial")
#: relative difference of OpenSfM's focal_x and focal_y below which their mean is used (above: refused)
FOCAL_ASPECT_TOLERANCE = 1e-3


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
        Origin of the topocentric world frame: longitude, latitude (degrees, WGS 84) and
        ellipsoidal height (metres), from the reconstruction's ``reference_lla`` or from
        ``reference_lla.json`` beside the file; None when neither exists.
    frame : str
        A description of the world frame.
    gps_position : (n, 3) float64
        Each shot's ``gps_position`` (world frame), NaN rows where absent.
    gps_dop : (n,) float64
        Each shot's ``gps_dop`` (metres), NaN where absent.
    index : int
        Position of this reconstruction in the file's list.
    n_reconstructions : int
        Number of reconstructions in the file.
    source : Path or None
        The file read.
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

    def __post_init__(self) -> None:
        object.__setattr__(self, "poses", tuple(self.poses))
        object.__setattr__(self, "point_ids", tuple(self.point_ids))
        for name in ("points", "colors", "reference_lonlat_h", "gps_position", "gps_dop"):
            a = getattr(self, name)
            if a is not None:
                a = np.array(a, copy=True)
                a.flags.writeable = False
                object.__setattr__(self, name, a)


def rotation_from_rodrigues(r: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) of an axis-angle (Rodrigues) vector r: axis r/|r|, angle |r| rad."""
    v = np.asarray(r, dtype=np.float64).reshape(3)
    th = float(np.linalg.norm(v))
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    K /= th
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


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

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Not valid JSON, not a list of reconstructions, no reconstruction at ``index``, an
        unsupported camera, a shot naming an unknown camera, malformed numbers (naming the value).
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
        R_cw = rotation_from_rodrigues(_vec3(shot["rotation"], f"shot {name!r} rotation", p))
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
    frame = ("topocentric east-north-up frame, metres, about reference_lonlat_h (WGS 84)" if ref is not None
             else "OpenSfM's arbitrary world frame (no reference_lla: not georeferenced; z roughly up)")
    return OpenSfMReconstruction(cameras=cameras, poses=tuple(poses), point_ids=tuple(str(k) for k in ids),
                                 points=xyz, colors=colors, reference_lonlat_h=ref, frame=frame,
                                 gps_position=np.array(gps, dtype=float).reshape(-1, 3),
                                 gps_dop=np.array(dop, dtype=float), index=index, n_reconstructions=len(doc),
                                 source=p)
