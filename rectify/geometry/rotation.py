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
return matrices of shape S + (3, 3).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError

__all__ = [
    "ORDERS",
    "rot_x",
    "rot_y",
    "rot_z",
    "matrix_from_angles",
    "angles_from_matrix",
    "check_rotation",
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
