"""The collinearity model of the bundle adjustment and its analytic Jacobians (vectorised).

Model (identical to :func:`stereo.block.types.project_pixel`)::

    p = R^T (X - C)                         ground -> camera axes, metres
    n = (-p0 / p2, p1 / p2)                 OpenCV normalised frame (x right, y down)
    n_d = distort(n; k1, k2, k3, p1, p2)    Brown-Conrady, OpenCV's definition
    u = F A n_d + c                         F = f / pixel size = fx, c = principal point (pixels),
                                            A = [[1, shear], [0, aspect]]: K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]

with ``R = Rx(omega) Ry(phi) Rz(kappa)``. The interior parameters are held as one vector per camera:
the :data:`INTERIOR_NAMES` f (mm), x0, y0 (mm, offset of the principal point from the image centre,
photo axes), k1, k2, k3, p1, p2, aspect fy/fx and shear s/fx (:class:`rectify.geometry.camera.Camera`),
any of which a bundle can self-calibrate (a self-calibrated f alone scales fx, fy and s together;
with ``aspect`` and ``shear`` the block recovers the projective interior orientation fx, fy, skew of
seed 003, 1.2).

The derivative of ``R`` by an angle is ``[a]x R`` with the rotation axis ``a`` in the ground frame
(``e_x``, ``Rx e_y``, ``Rx Ry e_z`` for omega, phi, kappa), so ``d p / d angle = R^T (d x a)`` with
``d = X - C``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles, rot_x, rot_y

__all__ = ["INTERIOR_NAMES", "camera_from_interior", "interior_from_camera", "project", "rotation_axes",
           "rotations"]

#: the interior parameters a bundle can self-calibrate, in vector order
INTERIOR_NAMES: tuple[str, ...] = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "aspect", "shear")


def interior_from_camera(camera: Camera) -> NDArray[np.float64]:
    """(10,) vector f, x0, y0, k1, k2, k3, p1, p2, aspect, shear of a camera (mm and unitless)."""
    d = camera.distortion
    return np.array([camera.focal_length_mm, camera.principal_point_mm[0], camera.principal_point_mm[1],
                     d["k1"], d["k2"], d["k3"], d["p1"], d["p2"], camera.aspect, camera.shear], dtype=np.float64)


def camera_from_interior(camera: Camera, vec: NDArray[np.float64], std: dict[str, float] | None = None) -> Camera:
    """A copy of ``camera`` with the interior vector ``vec`` (10,) (and standard errors ``std``)."""
    se = dict(camera.std_errors)
    if std:
        se.update(std)
    return Camera(focal_length_mm=float(vec[0]), pixel_size_mm=camera.pixel_size_mm, width=camera.width,
                  height=camera.height, principal_point_mm=(float(vec[1]), float(vec[2])),
                  distortion={k: float(v) for k, v in zip(INTERIOR_NAMES[3:8], vec[3:8], strict=True)},
                  pixel_camera=camera.pixel_camera, std_errors=se, sigma0_px=camera.sigma0_px,
                  aspect=float(vec[8]), shear=float(vec[9]))


def rotations(angles: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3, 3) rotation matrices R = Rx(omega) Ry(phi) Rz(kappa) of angles (n, 3), rad."""
    return np.asarray(matrix_from_angles(angles[:, 0], angles[:, 1], angles[:, 2]), dtype=np.float64
                      ).reshape(-1, 3, 3)


def rotation_axes(angles: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3, 3) ground-frame rotation axes of omega, phi, kappa: ``axes[:, a]`` is the axis of angle a."""
    n = len(angles)
    Rx = rot_x(angles[:, 0]).reshape(n, 3, 3)
    Ry = rot_y(angles[:, 1]).reshape(n, 3, 3)
    out = np.empty((n, 3, 3))
    out[:, 0] = (1.0, 0.0, 0.0)
    out[:, 1] = Rx[:, :, 1]
    out[:, 2] = np.einsum("nij,nj->ni", Rx @ Ry, np.broadcast_to([0.0, 0.0, 1.0], (n, 3)))
    return out


def project(R: NDArray[np.float64], C: NDArray[np.float64], axes: NDArray[np.float64],
            interior: NDArray[np.float64], pixel_size: NDArray[np.float64], centre: NDArray[np.float64],
            X: NDArray[np.float64], *, jacobian: bool = True, pose: bool = True, intrinsic: bool = True
            ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
                       NDArray[np.float64]]:
    """Project M observations and differentiate.

    Parameters
    ----------
    R : (M, 3, 3)
        Rotation (photo -> ground) of each observation's image.
    C : (M, 3)
        Projection centre, ground frame, m.
    axes : (M, 3, 3)
        Rotation axes of the three angles (:func:`rotation_axes`), ground frame.
    interior : (M, 10)
        Interior vector of each observation's camera (:func:`interior_from_camera`: the
        :data:`INTERIOR_NAMES`).
    pixel_size : (M,)
        Pixel size, mm.
    centre : (M, 2)
        Image centre ((W - 1) / 2, (H - 1) / 2), pixels.
    X : (M, 3)
        Ground point, m.
    jacobian : bool
        Compute the derivatives.
    pose, intrinsic : bool
        With ``jacobian``: also the derivatives by the pose and by the interior vector (else those
        two are returned empty, (0, 2, 6) and (0, 2, 10); the point derivatives alone are what the
        intersection of the points with the cameras held needs).

    Returns
    -------
    pixel : (M, 2)
        Predicted pixels (x = column, y = row).
    depth : (M,)
        -p2, the distance in front of the camera along its axis, m (> 0 in front).
    J_pose : (M, 2, 6)
        d pixel / d (omega, phi, kappa, Cx, Cy, Cz).
    J_point : (M, 2, 3)
        d pixel / d X.
    J_int : (M, 2, 10)
        d pixel / d the :data:`INTERIOR_NAMES` (the interior vector).
    """
    m = len(X)
    # columns as contiguous rows: the elementwise work below is several times faster on them
    dT = np.ascontiguousarray((X - C).T)
    d0, d1, d2 = dT[0], dT[1], dT[2]
    RT = np.ascontiguousarray(R.reshape(m, 9).T)
    Rc = [[RT[3 * i + j] for j in range(3)] for i in range(3)]
    # p = R^T d, component by component (elementwise on columns is faster than batched 3x3 products)
    p0 = d0 * Rc[0][0] + d1 * Rc[1][0] + d2 * Rc[2][0]
    p1 = d0 * Rc[0][1] + d1 * Rc[1][1] + d2 * Rc[2][1]
    p2 = d0 * Rc[0][2] + d1 * Rc[1][2] + d2 * Rc[2][2]
    w = 1.0 / p2
    nx = -p0 * w
    ny = p1 * w
    f, x0, y0, k1, k2, k3, q1, q2 = (interior[:, i] for i in range(8))
    r2 = nx * nx + ny * ny
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    nxy = nx * ny
    xd = nx * rad + 2 * q1 * nxy + q2 * (r2 + 2 * nx * nx)
    yd = ny * rad + q1 * (r2 + 2 * ny * ny) + 2 * q2 * nxy
    F = f / pixel_size
    aspect, shear = interior[:, 8], interior[:, 9]
    square = bool(np.all(aspect == 1.0) and np.all(shear == 0.0))  # the single-f arithmetic, bit for bit
    Fy, Fs = (F, None) if square else (F * aspect, F * shear)
    pix = np.empty((m, 2))
    pix[:, 0] = (F * xd if Fs is None else F * xd + Fs * yd) + centre[:, 0] + x0 / pixel_size
    pix[:, 1] = Fy * yd + centre[:, 1] - y0 / pixel_size
    z6, z8 = np.zeros((0, 2, 6)), np.zeros((0, 2, 10))
    if not jacobian:
        return pix, -p2, z6, np.zeros((0, 2, 3)), z8
    # d n_d / d n  (2 x 2), times F
    drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    a00 = F * (rad + 2 * nx * nx * drad + 2 * q1 * ny + 6 * q2 * nx)
    a01 = F * (2 * nxy * drad + 2 * q1 * nx + 2 * q2 * ny)
    a11 = F * (rad + 2 * ny * ny * drad + 6 * q1 * ny + 2 * q2 * nx)
    # d pixel / d n = [[1, shear], [0, aspect]] @ (F d n_d / d n): rows (b00, b01), (b10, b11)
    if square:
        b00, b01, b10, b11 = a00, a01, a01, a11
    else:
        b00, b01 = a00 + shear * a01, a01 + shear * a11
        b10, b11 = aspect * a01, aspect * a11
    # q = d pixel / d p = dd @ dn, dn = [[-w, 0, p0 w^2], [0, w, -p1 w^2]]
    ww = w * w
    u0, u1 = p0 * ww, -p1 * ww
    q = ((-w * b00, w * b01, b00 * u0 + b01 * u1),
         (-w * b10, w * b11, b10 * u0 + b11 * u1))
    # d pixel / d X = q R^T (built as (2, 3, m) and returned as its (m, 2, 3) view)
    JpT = np.empty((2, 3, m))
    for r in range(2):
        qr = q[r]
        for j in range(3):
            np.add(qr[0] * Rc[j][0], qr[1] * Rc[j][1], out=JpT[r, j])
            JpT[r, j] += qr[2] * Rc[j][2]
    J_point = JpT.transpose(2, 0, 1)
    if not pose:
        return pix, -p2, z6, J_point, z8
    JcT = np.empty((2, 6, m))
    AT = np.ascontiguousarray(axes.reshape(m, 9).T)  # AT[3 a + k]: component k of the axis of angle a
    # d pixel / d angle_a = J_point . (d x a_a) = (J_point x d) . a_a, a_a the ground-frame axis of the angle
    for r in range(2):
        j0, j1, j2 = JpT[r]
        c0 = j1 * d2 - j2 * d1
        c1 = j2 * d0 - j0 * d2
        c2 = j0 * d1 - j1 * d0
        for a in range(3):
            np.add(c0 * AT[3 * a], c1 * AT[3 * a + 1], out=JcT[r, a])
            JcT[r, a] += c2 * AT[3 * a + 2]
    np.negative(JpT, out=JcT[:, 3:])
    J_pose = JcT.transpose(2, 0, 1)
    if not intrinsic:
        return pix, -p2, J_pose, J_point, z8
    J_int = np.empty((m, 2, 10))
    J_int[:, 0, 0] = (xd if square else xd + shear * yd) / pixel_size
    J_int[:, 1, 0] = (yd if square else aspect * yd) / pixel_size
    J_int[:, 0, 1] = 1.0 / pixel_size
    J_int[:, 1, 1] = 0.0
    J_int[:, 0, 2] = 0.0
    J_int[:, 1, 2] = -1.0 / pixel_size
    r4 = r2 * r2
    for col, rr in ((3, r2), (4, r4), (5, r4 * r2)):
        J_int[:, 0, col] = F * nx * rr
        J_int[:, 1, col] = F * ny * rr
    J_int[:, 0, 6] = F * 2 * nxy
    J_int[:, 1, 6] = F * (r2 + 2 * ny * ny)
    J_int[:, 0, 7] = F * (r2 + 2 * nx * nx)
    J_int[:, 1, 7] = F * 2 * nxy
    if not square:  # the distortion terms go through [[1, shear], [0, aspect]] too
        J_int[:, 0, 3:8] += shear[:, None] * J_int[:, 1, 3:8]
        J_int[:, 1, 3:8] *= aspect[:, None]
    J_int[:, 0, 8] = 0.0  # pixel x = F (xd + shear yd) + ..., pixel y = F aspect yd + ...
    J_int[:, 1, 8] = F * yd
    J_int[:, 0, 9] = F * yd
    J_int[:, 1, 9] = 0.0
    return pix, -p2, J_pose, J_point, J_int
