"""The camera model of the calibration: pinhole + Brown-Conrady distortion, pixel units.

Frames
------
object
    The target's frame (board: z = 0 plane, x along the rows of corners);
    any unit (the square size, mm, m).
camera (OpenCV)
    x right, y down, z forward (along the viewing direction), origin at the
    projection centre. A camera vector is ``Xc = R_cv @ X + t``. The project's
    photo frame (x right, y up, z backwards) is ``diag(1, -1, -1) @ Xc``.
pixel
    (N, 2) float64, x = column right, y = row down, pixel centres at integers.

Model
-----
With ``x = Xc / Zc``, ``y = Yc / Zc`` and the point of symmetry of distortion
``(sx, sy)`` (pixels; by default the principal point ``(cx, cy)``)::

    u = x - (sx - cx) / fx,   v = y - (sy - cy) / fy,   r^2 = u^2 + v^2
    du = u (k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 u v + p2 (r^2 + 2 u^2)
    dv = v (k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 v^2) + 2 p2 u v
    col = cx + fx (x + du),   row = cy + fy (y + dv)

This is OpenCV's model (``cv2.projectPoints``) when the point of symmetry is the
principal point, so the coefficients compare directly with OpenCV's and with
:class:`rectify.geometry.camera.Camera`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CalibrationError, InvalidInputError

__all__ = ["INTERIOR_NAMES", "Intrinsics", "CV_FROM_PHOTO", "project_vector"]

#: Order of the full interior vector used by the adjustment.
INTERIOR_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "sx", "sy")

#: diag(1, -1, -1): photo frame (y up, z back) <-> OpenCV camera frame (y down, z forward)
CV_FROM_PHOTO = np.diag([1.0, -1.0, -1.0])

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Intrinsics:
    """Interior orientation in pixels.

    Parameters
    ----------
    fx, fy : float
        Principal distance along columns and rows, px (> 0).
    cx, cy : float
        Principal point, pixel frame (column, row), px.
    k1, k2, k3, p1, p2 : float
        Brown-Conrady coefficients (OpenCV's definition, unitless).
    sx, sy : float or None
        Point of symmetry of distortion, pixel frame, px; ``None`` means the
        principal point.
    width, height : int
        Image size, px.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    sx: float | None = None
    sy: float | None = None

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not math.isfinite(v) or v <= 0:
                raise CalibrationError(f"`{name}` must be a finite number > 0; got {v!r}")
        for name in ("cx", "cy", "k1", "k2", "k3", "p1", "p2"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise CalibrationError(f"`{name}` must be finite; got {v!r}")
        if (self.sx is None) != (self.sy is None):
            raise CalibrationError(f"give both or neither of sx, sy; got {self.sx!r}, {self.sy!r}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v <= 0:
                raise CalibrationError(f"`{name}` must be a positive integer; got {v!r}")
            object.__setattr__(self, name, int(v))

    # ------------------------------------------------------------ conversions
    @property
    def vector(self) -> F64:
        """The full interior vector in :data:`INTERIOR_NAMES` order (11,)."""
        sx = self.cx if self.sx is None else self.sx
        sy = self.cy if self.sy is None else self.sy
        return np.array([self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.k3, self.p1, self.p2, sx, sy])

    @classmethod
    def from_vector(cls, v: ArrayLike, width: int, height: int, *, symmetry: bool = False) -> Intrinsics:
        """Inverse of :attr:`vector`; ``symmetry`` keeps (sx, sy) separate."""
        a = [float(x) for x in np.asarray(v, dtype=np.float64).reshape(-1)]
        if len(a) != len(INTERIOR_NAMES):
            raise InvalidInputError(f"interior vector must have {len(INTERIOR_NAMES)} entries; got {len(a)}")
        return cls(fx=a[0], fy=a[1], cx=a[2], cy=a[3], width=width, height=height, k1=a[4], k2=a[5], k3=a[6],
                   p1=a[7], p2=a[8], sx=a[9] if symmetry else None, sy=a[10] if symmetry else None)

    @property
    def K(self) -> F64:
        """OpenCV camera matrix (3, 3), px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> F64:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def distortion(self) -> dict[str, float]:
        return {"k1": self.k1, "k2": self.k2, "k3": self.k3, "p1": self.p1, "p2": self.p2}

    # ------------------------------------------------------------- projection
    def project(self, xc: ArrayLike) -> F64:
        """Camera-frame points (N, 3) (OpenCV frame) -> pixels (N, 2)."""
        return project_vector(self.vector, np.asarray(xc, dtype=np.float64))

    def distortion_px(self, pixel: ArrayLike) -> tuple[F64, F64]:
        """Radial and decentering displacement (each (N, 2), px) at distorted-free pixel positions.

        The positions are ideal (undistorted) pixels; the displacement is what
        the lens adds there: ``(radial, decentering)``.
        """
        p = np.asarray(pixel, dtype=np.float64).reshape(-1, 2)
        v = self.vector
        x = (p[:, 0] - v[2]) / v[0]
        y = (p[:, 1] - v[3]) / v[1]
        u = x - (v[9] - v[2]) / v[0]
        w = y - (v[10] - v[3]) / v[1]
        r2 = u * u + w * w
        rad = r2 * (v[4] + r2 * (v[5] + r2 * v[6]))
        radial = np.column_stack([u * rad * v[0], w * rad * v[1]])
        dec = np.column_stack([(2 * v[7] * u * w + v[8] * (r2 + 2 * u * u)) * v[0],
                               (v[7] * (r2 + 2 * w * w) + 2 * v[8] * u * w) * v[1]])
        return radial, dec


def project_vector(v: F64, xc: F64) -> F64:
    """Project camera-frame points (N, 3) with the interior vector ``v`` (11,) -> pixels (N, 2).

    Also accepts ``v`` of shape (N, 11) (one vector per point, used by the
    finite-difference Jacobian).
    """
    z = xc[:, 2]
    x = xc[:, 0] / z
    y = xc[:, 1] / z
    fx, fy, cx, cy, k1, k2, k3, p1, p2, sx, sy = (v[..., i] for i in range(11))
    u = x - (sx - cx) / fx
    w = y - (sy - cy) / fy
    r2 = u * u + w * w
    rad = r2 * (k1 + r2 * (k2 + r2 * k3))
    du = u * rad + 2 * p1 * u * w + p2 * (r2 + 2 * u * u)
    dv = w * rad + p1 * (r2 + 2 * w * w) + 2 * p2 * u * w
    return np.column_stack([cx + fx * (x + du), cy + fy * (y + dv)])
