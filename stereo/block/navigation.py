"""GNSS/INS navigation angles <-> camera rotations: frames, roll conventions, boresight, lever arm.

The formulas behind the ``heading,pitch,roll`` columns of the position/angle CSV
(:func:`stereo.formats.poses.read_pose_csv`).

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
projection, grid north differs from true north by the meridian convergence. This module does not
apply it: the rotation it returns is in the local east-north-up frame of the camera when the angles
are an INS's, and ``stereo block`` turns it into its adjustment frame at each camera's position (the
meridian convergence and the deflection of the vertical, :mod:`stereo.block.frames`).

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

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.rotation import matrix_from_angles, rot_x, rot_y, rot_z

__all__ = [
    "NAVIGATION_CONVENTIONS",
    "body_rotation",
    "boresight_matrix",
    "check_convention",
    "lever_arm",
    "navigation_from_rotation",
    "rotation_from_navigation",
]

#: roll definitions of :func:`rotation_from_navigation`
NAVIGATION_CONVENTIONS = ("seed004", "euler")


def boresight_matrix(boresight_rad: ArrayLike | None) -> NDArray[np.float64] | None:
    """B = Rx Ry Rz of small boresight angles (omega, phi, kappa), rad: camera photo frame -> body frame (3, 3).

    None for None. Raises :class:`InvalidInputError` unless 3 finite angles under 10 deg each.
    """
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


def check_convention(convention: str) -> str:
    """``convention`` if it is one of :data:`NAVIGATION_CONVENTIONS`, else :class:`InvalidInputError`."""
    if convention not in NAVIGATION_CONVENTIONS:
        raise InvalidInputError(f"unknown navigation convention {convention!r}; expected one of "
                                f"{list(NAVIGATION_CONVENTIONS)}")
    return convention


def body_rotation(heading: ArrayLike, pitch: ArrayLike, roll: ArrayLike, *,
                  convention: str = "seed004") -> NDArray[np.float64]:
    """Rotation body (x right wing, y forward, z up) -> ground (east, north, up), S + (3, 3).

    See :func:`rotation_from_navigation`; this is the same without a boresight.
    """
    check_convention(convention)
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
    B = boresight_matrix(boresight_rad)
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
    check_convention(convention)
    m = np.asarray(R, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ShapeError(f"`R` must have shape (..., 3, 3); got {m.shape}", actual_shape=m.shape,
                         expected_shape=(3, 3))
    B = boresight_matrix(boresight_rad)
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


def lever_arm(lever_arm_m: ArrayLike | None) -> NDArray[np.float64] | None:
    """The lever arm as a (3,) float64 vector (metres, body frame), None for None.

    Raises :class:`InvalidInputError` unless 3 finite numbers.
    """
    if lever_arm_m is None:
        return None
    v = np.asarray(lever_arm_m, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise InvalidInputError(f"lever_arm_m must be 3 finite numbers (metres, body frame); "
                                f"got {np.asarray(lever_arm_m).tolist()}")
    return v
