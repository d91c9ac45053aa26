"""Angle systems <-> rotation matrices.

Every matrix here takes a photo vector (x, y, -f) into the object (model or
ground) frame: X' = R @ (x, y, -f). With Rx, Ry, Rz the right-handed rotations
about the X, Y, Z axes (active, counter-clockwise for positive angles):

=====================  ==============================  ==========================
order                  matrix                          where
=====================  ==============================  ==========================
``omega-phi-kappa``    Rx(omega) @ Ry(phi) @ Rz(kappa)  Western textbooks, NGI data
``omega-alpha-chi``    Rx(omega) @ Ry(alpha) @ Rz(chi)  seed 000, eq. (1) (same matrix)
``phi-omega-kappa``    Ry(phi) @ Rx(omega) @ Rz(kappa)  classical Russian alpha-omega-kappa
``alpha-omega-kappa``  alias of ``phi-omega-kappa``
=====================  ==============================  ==========================

Angles are radians. Functions accept scalars or arrays of equal shape S and
return matrices of shape S + (3, 3) (:func:`rodrigues` always stacks: (M, 3) -> (M, 3, 3)).

Rotation vectors (axis-angle, Rodrigues): a vector r is the rotation by |r| rad
about the axis r / |r| (right-handed); :func:`rodrigues` gives its matrix
(OpenCV's ``cv2.Rodrigues``, SciPy's ``Rotation.from_rotvec``) and
:func:`rotvec_from_matrix` the inverse. These are the one implementation of
both directions in the project (the calibration, the OpenSfM reader and the
independent-model adjustment use them).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CalibrationError, InvalidInputError, ShapeError

__all__ = [
    "ORDERS",
    "rot_x",
    "rot_y",
    "rot_z",
    "matrix_from_angles",
    "angles_from_matrix",
    "check_rotation",
    "rodrigues",
    "rotvec_from_matrix",
]

#: order name -> axis sequence of the product (left to right)
ORDERS: dict[str, str] = {
    "omega-phi-kappa": "xyz",
    "omega-alpha-chi": "xyz",
    "phi-omega-kappa": "yxz",
    "alpha-omega-kappa": "yxz",
}


def _axis_rot(axis: str, angle: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "x":
        rows = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == "y":
        rows = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        rows = [[c, -s, z], [s, c, z], [z, z, o]]
    return np.moveaxis(np.array(rows), (0, 1), (-2, -1))


def rot_x(angle: ArrayLike) -> NDArray[np.float64]:
    """Rotation about X by ``angle`` rad, shape S + (3, 3)."""
    return _axis_rot("x", angle)


def rot_y(angle: ArrayLike) -> NDArray[np.float64]:
    """Rotation about Y by ``angle`` rad, shape S + (3, 3)."""
    return _axis_rot("y", angle)


def rot_z(angle: ArrayLike) -> NDArray[np.float64]:
    """Rotation about Z by ``angle`` rad, shape S + (3, 3)."""
    return _axis_rot("z", angle)


def _axes(order: str) -> str:
    try:
        return ORDERS[order]
    except KeyError:
        raise InvalidInputError(f"unknown rotation order {order!r}; expected one of {sorted(ORDERS)}") from None


def matrix_from_angles(a1: ArrayLike, a2: ArrayLike, a3: ArrayLike, order: str = "omega-phi-kappa"
                       ) -> NDArray[np.float64]:
    """Rotation matrix for three angles (rad) applied in the named ``order``.

    The angles are given in the order of the name: for ``"phi-omega-kappa"``,
    ``a1`` is phi, ``a2`` omega and ``a3`` kappa.

    Examples
    --------
    >>> R = matrix_from_angles(0.1, -0.2, 0.3, "omega-phi-kappa")
    >>> np.allclose(R @ R.T, np.eye(3))
    True
    >>> matrix_from_angles(0, 0, 0, "xyz")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    rectify.errors.InvalidInputError: unknown rotation order 'xyz'; expected one of ['alpha-omega-kappa', ...]
    """
    ax = _axes(order)
    m = _axis_rot(ax[0], a1)
    m = m @ _axis_rot(ax[1], a2)
    return m @ _axis_rot(ax[2], a3)


def angles_from_matrix(R: ArrayLike, order: str = "omega-phi-kappa") -> NDArray[np.float64]:
    """Angles (rad) of a rotation matrix in the named order, shape S + (3,).

    The middle angle is in [-pi/2, pi/2]; the others in (-pi, pi]. At the
    gimbal lock (middle angle = +-pi/2) the third angle is set to 0.
    """
    m = np.asarray(R, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ShapeError(f"`R` must have shape (..., 3, 3); got {m.shape}", actual_shape=m.shape,
                         expected_shape=(3, 3))
    ax = _axes(order)
    if ax == "xyz":
        # R02 = sin(b); R00 = cb cc; R01 = -cb sc; R12 = -sa cb; R22 = ca cb
        b = np.arcsin(np.clip(m[..., 0, 2], -1.0, 1.0))
        a = np.arctan2(-m[..., 1, 2], m[..., 2, 2])
        c = np.arctan2(-m[..., 0, 1], m[..., 0, 0])
        lock = np.hypot(m[..., 1, 2], m[..., 2, 2]) < 1e-12
        if np.any(lock):
            a = np.where(lock, np.arctan2(m[..., 2, 1], m[..., 1, 1]), a)
            c = np.where(lock, 0.0, c)
    else:  # "yxz": R = Ry(a) Rx(b) Rz(c)
        # R12 = -sin(b); R02 = sa cb; R22 = ca cb; R10 = cb sc; R11 = cb cc
        b = np.arcsin(np.clip(-m[..., 1, 2], -1.0, 1.0))
        a = np.arctan2(m[..., 0, 2], m[..., 2, 2])
        c = np.arctan2(m[..., 1, 0], m[..., 1, 1])
        lock = np.hypot(m[..., 0, 2], m[..., 2, 2]) < 1e-12
        if np.any(lock):
            a = np.where(lock, np.arctan2(-m[..., 2, 0], m[..., 0, 0]), a)
            c = np.where(lock, 0.0, c)
    return np.stack([a, b, c], axis=-1)


def check_rotation(R: ArrayLike, name: str = "R", *, atol: float = 1e-6) -> NDArray[np.float64]:
    """Return ``R`` as a (3, 3) float64 copy, or raise if it is not a proper rotation."""
    m = np.array(R, dtype=np.float64, copy=True)
    if m.shape != (3, 3):
        raise ShapeError(f"`{name}` must have shape (3, 3); got {m.shape}", actual_shape=m.shape,
                         expected_shape=(3, 3))
    if not np.isfinite(m).all():
        raise InvalidInputError(f"`{name}` has non-finite entries: {m.tolist()}")
    err = np.abs(m @ m.T - np.eye(3)).max()
    if err > atol or np.linalg.det(m) < 0:
        raise InvalidInputError(
            f"`{name}` is not a proper rotation (|R R^T - I| = {err:.3g}, det = {np.linalg.det(m):.6f})")
    return m


def rodrigues(rv: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrices of rotation vectors (Rodrigues' formula), (M, 3) -> (M, 3, 3).

    ``R = I + sin(t) K + (1 - cos(t)) K^2`` with ``t = |r|`` and ``K`` the cross-product matrix of
    the unit axis ``r / t``; below ``t = 1e-12`` the first order ``I + [r]x``. The convention of
    ``cv2.Rodrigues`` and ``scipy.spatial.transform.Rotation.from_rotvec``.

    Parameters
    ----------
    rv : array_like, (M, 3) or (3,)
        Rotation vectors, radians; a single vector is taken as M = 1.

    Returns
    -------
    (M, 3, 3) float64
        Always stacked: ``rodrigues(r)[0]`` is the matrix of one vector ``r``.

    Examples
    --------
    >>> np.round(rodrigues([0.0, 0.0, np.pi / 2])[0] @ [1.0, 0.0, 0.0], 12) + 0.0
    array([0., 1., 0.])
    """
    r = np.asarray(rv, dtype=np.float64).reshape(-1, 3)
    th = np.linalg.norm(r, axis=1)
    small = th < 1e-12
    k = r / np.where(small, 1.0, th)[:, None]
    kx = np.zeros((len(r), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s = np.sin(th)[:, None, None]
    c = (1 - np.cos(th))[:, None, None]
    out = np.eye(3)[None] + s * kx + c * (kx @ kx)
    if np.any(small):  # first order for tiny angles
        rx = np.zeros((int(small.sum()), 3, 3))
        rs = r[small]
        rx[:, 0, 1], rx[:, 0, 2], rx[:, 1, 2] = -rs[:, 2], rs[:, 1], -rs[:, 0]
        rx[:, 1, 0], rx[:, 2, 0], rx[:, 2, 1] = rs[:, 2], -rs[:, 1], rs[:, 0]
        out[small] = np.eye(3)[None] + rx
    return out


def rotvec_from_matrix(R: ArrayLike) -> NDArray[np.float64]:
    """Rotation vector (3,) of a rotation matrix (3, 3), angle in [0, pi]; the inverse of :func:`rodrigues`.

    The matrix is first made orthonormal (nearest rotation by SVD). Near pi the axis is taken
    from the symmetric part ``(R + I) / 2``.

    Raises
    ------
    CalibrationError
        The matrix is a reflection (determinant -1).
    """
    m = np.asarray(R, dtype=np.float64)
    u, _, vt = np.linalg.svd(m)
    m = u @ vt
    if np.linalg.det(m) < 0:
        raise CalibrationError("not a proper rotation (determinant -1)")
    c = np.clip((np.trace(m) - 1) / 2, -1.0, 1.0)
    th = math.acos(c)
    a = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    if th < 1e-8:
        return a / 2
    if math.pi - th < 1e-6:  # near pi: axis from the symmetric part
        b = (m + np.eye(3)) / 2
        i = int(np.argmax(np.diag(b)))
        axis = b[:, i] / math.sqrt(max(b[i, i], 1e-300))
        if np.dot(axis, a) < 0:
            axis = -axis
        return axis * th
    return a * th / (2 * math.sin(th))
