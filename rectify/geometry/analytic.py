"""Analytic rectification of a tilted frame (seed 001, eq. 1).

From the interior orientation (principal distance f, principal point
(x0, y0)) and the angular elements of exterior orientation of a tilted
frame, eq. (1) gives the coordinates of a point on the *horizontal* image
(the image the same camera would take from the same centre with its axis
vertical):

    x0_h = -f X' / Z',    y0_h = -f Y' / Z',

    X' = a1 (x - x0) + a2 (y - y0) - a3 f
    Y' = b1 (x - x0) + b2 (y - y0) - b3 f
    Z' = c1 (x - x0) + c2 (y - y0) - c3 f

where (a1 a2 a3; b1 b2 b3; c1 c2 c3) = R are the direction cosines: the
rotation matrix of :mod:`rectify.geometry.rotation` that takes the photo vector
(x - x0, y - y0, -f) into the horizontal (object-parallel) frame.

Frames: photo coordinates in millimetres, x right, y up (the photo frame of
:mod:`rectify.geometry.camera`). The input coordinates are measured in the frame in
which the principal point is (x0, y0) (e.g. the fiducial frame); the output
is centred on the nadir point's image (the principal point of the horizontal image). An optional
``f_out`` gives the horizontal image another principal distance (scale).

Because eq. (1) is a ratio of linear functions of (x, y), it is a
homography, :attr:`TiltedFrame.homography`, equal to ``diag(-f_out, -f_out, 1)
@ R @ [[1, 0, -x0], [0, 1, -y0], [0, 0, -f]]``; the tests check it equals the
homography fitted to the same points.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.points import as_points
from rectify.geometry.rotation import check_rotation, matrix_from_angles
from rectify.geometry.transforms import AffineTransform, Homography

logger = logging.getLogger(__name__)

__all__ = ["TiltedFrame"]

F64 = NDArray[np.float64]


def _positive(v: float, name: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InvalidInputError(f"`{name}` must be a number; got {v!r}") from None
    if not math.isfinite(x) or x <= 0:
        raise InvalidInputError(f"`{name}` must be finite and > 0; got {v!r}")
    return x


@dataclass(frozen=True, eq=False)
class TiltedFrame:
    """A tilted frame and its analytic rectification to the horizontal image.

    Parameters
    ----------
    focal_length_mm : float
        Principal distance f of the tilted frame, mm.
    rotation : (3, 3) array_like
        Direction cosines R: photo vector (x - x0, y - y0, -f) -> horizontal
        frame (X', Y', Z').
    principal_point_mm : (2,) float
        (x0, y0) in the frame of the measured photo coordinates, mm.
    f_out_mm : float or None
        Principal distance of the horizontal image (default ``focal_length_mm``).

    Examples
    --------
    >>> fr = TiltedFrame.from_angles(1000.0, 0.05, 0.0, 0.0)   # omega = 0.05 rad
    >>> bool(np.isclose(fr([[0.0, 0.0]])[0, 1], 1000 * np.tan(0.05)))  # principal point -> f tan(omega)
    True
    >>> TiltedFrame(-5.0, np.eye(3))
    Traceback (most recent call last):
    ...
    rectify.errors.InvalidInputError: `focal_length_mm` must be finite and > 0; got -5.0
    """

    focal_length_mm: float
    rotation: F64
    principal_point_mm: tuple[float, float] = (0.0, 0.0)
    f_out_mm: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "focal_length_mm", _positive(self.focal_length_mm, "focal_length_mm"))
        R = check_rotation(self.rotation, "rotation")
        R.flags.writeable = False
        object.__setattr__(self, "rotation", R)
        pp = np.asarray(self.principal_point_mm, dtype=float).reshape(-1)
        if pp.shape != (2,) or not np.isfinite(pp).all():
            raise InvalidInputError(f"`principal_point_mm` must be two finite numbers; got "
                                    f"{self.principal_point_mm!r}")
        object.__setattr__(self, "principal_point_mm", (float(pp[0]), float(pp[1])))
        fo = self.focal_length_mm if self.f_out_mm is None else _positive(self.f_out_mm, "f_out_mm")
        object.__setattr__(self, "f_out_mm", fo)

    @classmethod
    def from_angles(cls, focal_length_mm: float, a1: float, a2: float, a3: float, *,
                    order: str = "omega-phi-kappa", principal_point_mm: tuple[float, float] = (0.0, 0.0),
                    f_out_mm: float | None = None) -> TiltedFrame:
        """Build from three angles (rad) in a named order of :mod:`rectify.geometry.rotation`
        (``omega-phi-kappa``, ``phi-omega-kappa`` = ``alpha-omega-kappa``,
        ``omega-alpha-chi``)."""
        for name, v in (("a1", a1), ("a2", a2), ("a3", a3)):
            if not math.isfinite(float(v)):
                raise InvalidInputError(f"angle `{name}` must be finite; got {v!r}")
        return cls(focal_length_mm, matrix_from_angles(a1, a2, a3, order), principal_point_mm, f_out_mm)

    @property
    def _f_out(self) -> float:
        """``f_out_mm`` as set by ``__post_init__`` (never None after construction)."""
        return self.focal_length_mm if self.f_out_mm is None else float(self.f_out_mm)

    @property
    def tilt(self) -> float:
        """Angle between the camera axis and the vertical, rad."""
        return float(math.acos(max(-1.0, min(1.0, self.rotation[2, 2]))))

    def __call__(self, photo_mm: ArrayLike) -> F64:
        """Eq. (1): tilted photo coordinates (N, 2) mm -> horizontal image (N, 2) mm.

        Points on the horizon of the tilted frame (Z' = 0) map to inf/NaN.
        """
        p = as_points(photo_mm, "photo_mm")
        f, (x0, y0) = self.focal_length_mm, self.principal_point_mm
        (a1, a2, a3), (b1, b2, b3), (c1, c2, c3) = self.rotation
        dx, dy = p[:, 0] - x0, p[:, 1] - y0
        Xp = a1 * dx + a2 * dy - a3 * f
        Yp = b1 * dx + b2 * dy - b3 * f
        Zp = c1 * dx + c2 * dy - c3 * f
        fo = self._f_out
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.column_stack([-fo * Xp / Zp, -fo * Yp / Zp])

    @property
    def homography(self) -> Homography:
        """Eq. (1) as a homography, tilted photo mm -> horizontal photo mm."""
        f, (x0, y0) = self.focal_length_mm, self.principal_point_mm
        A = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, -f]])
        m = np.diag([-self._f_out, -self._f_out, 1.0]) @ self.rotation @ A
        return Homography(m / m[2, 2] if abs(m[2, 2]) > 1e-300 else m)

    @property
    def inverse(self) -> Homography:
        """Horizontal image mm -> tilted photo mm (exact, as a homography)."""
        return self.homography.inverse

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error |eq1(src) - dst|, (N,), mm."""
        s = as_points(src, "src")
        d = as_points(dst, "dst")
        return np.linalg.norm(self(s) - d, axis=1)

    def pixel_homography(self, camera: Camera) -> Homography:
        """Tilted image pixels -> horizontal image photo mm, for a distortion-free camera.

        The camera's photo frame has its origin at the principal point, so this
        frame's ``principal_point_mm`` must be (0, 0).
        """
        if camera.has_distortion:
            raise InvalidInputError("pixel_homography needs a distortion-free camera; undistort first "
                                    f"(distortion {camera.distortion})")
        if self.principal_point_mm != (0.0, 0.0):
            raise InvalidInputError("with a Camera, photo coordinates are centred on the principal point; "
                                    f"set principal_point_mm=(0, 0), got {self.principal_point_mm}")
        px = np.array([[0.0, 0.0], [camera.width - 1.0, 0.0], [0.0, camera.height - 1.0]])
        A = AffineTransform.from_points(px, camera.photo_from_pixel(px))
        return cast(Homography, self.homography @ A)   # a homography composed with an affine map
