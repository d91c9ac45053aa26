"""Projective starts with no initial guess: the 11-parameter DLT and plane-target homographies.

DLT (projective collinearity, seed 003, 1.2 and 1.7)
-----------------------------------------------------
For object points ``X`` (N, 3) and pixels ``(col, row)`` the direct linear
transformation is the 3 x 4 matrix ``P`` (11 independent elements)::

    col = (P0 . Xh) / (P2 . Xh),   row = (P1 . Xh) / (P2 . Xh),   Xh = (X, Y, Z, 1)

It is solved linearly after normalising both point sets (Hartley), then
refined by minimising the reprojection error. Its decomposition
``P ~ K [R_cv | t]`` (RQ of the left 3 x 3 block) gives the *projective
interior orientation*: ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with
principal distances along columns and rows, the skew ``s`` and the principal
point, and the exterior orientation: rotation ``R`` (camera -> object, the
project's photo frame: x right, y up, z back) and projection centre ``C``.
The classical interior orientation is the special case ``fx = fy = f``,
``s = 0``; ``fy / fx`` is the affinity and ``s / fy`` the shear of the image
axes.

Plane targets (seed 003, 1.5)
-----------------------------
A plane (object z = 0) maps to the image by a homography ``H ~ K [r1 r2 t]``.
Each view gives two linear equations in ``B = K^-T K^-1`` (zero skew); two or
more views give ``K`` (:func:`interior_from_homographies`); with one view, or
when that solution is not a camera, the principal point is held at the image
centre and only the principal distances are solved.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CalibrationError, EstimationError, InvalidInputError, ShapeError
from stereo.calibration.model import CV_FROM_PHOTO

logger = logging.getLogger(__name__)

__all__ = ["DLT", "ProjectiveInterior", "interior_from_homographies", "pose_from_homography",
           "perspective_strength"]

F64 = NDArray[np.float64]


def _as_array(a: ArrayLike, cols: int, name: str) -> F64:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != cols:
        raise ShapeError(f"`{name}` must have shape (N, {cols}); got {x.shape}", actual_shape=x.shape,
                         expected_shape=(None, cols))
    if not np.isfinite(x).all():
        raise InvalidInputError(f"`{name}` contains NaN or infinity")
    return x


def _similarity(p: F64) -> F64:
    """Normalising similarity (d+1, d+1): centroid to 0, mean distance sqrt(d)."""
    d = p.shape[1]
    c = p.mean(axis=0)
    s = math.sqrt(d) / max(float(np.mean(np.linalg.norm(p - c, axis=1))), 1e-300)
    t = np.eye(d + 1)
    t[:d, :d] *= s
    t[:d, d] = -s * c
    return t


@dataclass(frozen=True)
class ProjectiveInterior:
    """The decomposition of a DLT matrix.

    Attributes
    ----------
    fx, fy : float
        Principal distances along columns and rows, px.
    skew : float
        K[0, 1], px (0 for a classical camera).
    cx, cy : float
        Principal point, pixel frame, px.
    rotation : (3, 3) float64
        Camera -> object rotation in the project's photo frame (x right, y up, z back).
    centre : (3,) float64
        Projection centre, object frame and units.
    """

    fx: float
    fy: float
    skew: float
    cx: float
    cy: float
    rotation: F64
    centre: F64

    @property
    def K(self) -> F64:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def rotation_cv(self) -> F64:
        """Object -> OpenCV camera rotation ``R_cv = D R^T``."""
        return CV_FROM_PHOTO @ self.rotation.T

    @property
    def translation_cv(self) -> F64:
        """OpenCV translation ``t = -R_cv C``."""
        return -self.rotation_cv @ self.centre


@dataclass(frozen=True)
class DLT:
    """The 11-parameter direct linear transformation of one image.

    Parameters
    ----------
    matrix : (3, 4) float64
        Object (X, Y, Z, 1) -> homogeneous pixel (col, row, 1); normalised so
        that ``||matrix[2, :3]|| = 1`` and points in front have a positive third
        coordinate.
    rmse_px : float
        RMS reprojection error of the fit, px (0 for exactly 6 points).
    n_points : int
    """

    matrix: F64
    rmse_px: float = 0.0
    n_points: int = 0

    def __post_init__(self) -> None:
        m = np.array(self.matrix, dtype=np.float64, copy=True)
        if m.shape != (3, 4) or not np.isfinite(m).all():
            raise InvalidInputError(f"DLT matrix must be a finite (3, 4) array; got shape {m.shape}")
        m.flags.writeable = False
        object.__setattr__(self, "matrix", m)

    @classmethod
    def from_points(cls, object_xyz: ArrayLike, pixel: ArrayLike, *, refine: bool = True) -> DLT:
        """Solve the DLT from >= 6 points of a 3D (non-coplanar) field.

        Parameters
        ----------
        object_xyz : (N, 3) float64
            Object coordinates, any unit.
        pixel : (N, 2) float64
            Measured pixels (col, row).
        refine : bool
            Refine the linear solution by minimising the reprojection error.

        Raises
        ------
        EstimationError
            Fewer than 6 points, coplanar points, or a degenerate configuration.
        """
        X = _as_array(object_xyz, 3, "object_xyz")
        x = _as_array(pixel, 2, "pixel")
        if len(X) != len(x):
            raise ShapeError(f"{len(X)} object points but {len(x)} pixels", actual_shape=(len(X), len(x)))
        if len(X) < 6:
            raise EstimationError(f"too few points for the DLT: {len(X)} given, at least 6 needed")
        sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
        if sv[2] < 1e-6 * sv[0]:
            raise EstimationError(
                f"the DLT needs a 3D field, but the {len(X)} object points are coplanar "
                f"(thickness/extent {sv[2] / sv[0]:.1e}); use the plane-target start (homographies)")
        T3 = _similarity(X)
        T2 = _similarity(x)
        Xn = (T3[:3, :3] @ X.T).T + T3[:3, 3]
        xn = (T2[:2, :2] @ x.T).T + T2[:2, 2]
        n = len(X)
        A = np.zeros((2 * n, 12))
        Xh = np.column_stack([Xn, np.ones(n)])
        A[0::2, 0:4] = Xh
        A[0::2, 8:12] = -xn[:, :1] * Xh
        A[1::2, 4:8] = Xh
        A[1::2, 8:12] = -xn[:, 1:] * Xh
        _, s, vt = np.linalg.svd(A)
        if n > 6 and s[-2] < 1e-9 * s[0]:
            raise EstimationError("the DLT has no unique solution (points on a critical configuration)")
        Pn = vt[-1].reshape(3, 4)
        P = np.linalg.inv(T2) @ Pn @ T3
        P = cls._normalise(P, X)
        if refine and n > 6:
            p0 = P.reshape(-1)
            k = int(np.argmax(np.abs(p0)))

            def fun(q: F64) -> F64:
                m = np.insert(q, k, p0[k]).reshape(3, 4)
                h = X @ m[:, :3].T + m[:, 3]
                return (h[:, :2] / h[:, 2:] - x).ravel()

            sol = scipy.optimize.least_squares(fun, np.delete(p0, k), method="lm", xtol=1e-12, ftol=1e-12)
            if sol.success and np.all(np.isfinite(sol.x)):
                P = cls._normalise(np.insert(sol.x, k, p0[k]).reshape(3, 4), X)
        h = X @ P[:, :3].T + P[:, 3]
        if np.any(h[:, 2] <= 0):
            raise EstimationError("the DLT solution puts object points behind the camera")
        r = h[:, :2] / h[:, 2:] - x
        rmse = float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
        return cls(P, rmse, n)

    @staticmethod
    def _normalise(P: F64, X: F64) -> F64:
        P = P / np.linalg.norm(P[2, :3])
        if np.median(X @ P[2, :3] + P[2, 3]) < 0:
            P = -P
        return P

    @classmethod
    def from_elements(cls, K: ArrayLike, rotation: ArrayLike, centre: ArrayLike) -> DLT:
        """Build ``P = K [R_cv | -R_cv C]`` from a camera matrix, a rotation (camera -> object,
        photo frame) and a projection centre."""
        Km = np.asarray(K, dtype=np.float64)
        R = np.asarray(rotation, dtype=np.float64)
        C = np.asarray(centre, dtype=np.float64).reshape(3)
        Rcv = CV_FROM_PHOTO @ R.T
        P = Km @ np.column_stack([Rcv, -Rcv @ C])
        return cls(P / np.linalg.norm(P[2, :3]))

    def project(self, object_xyz: ArrayLike) -> F64:
        """Object points (N, 3) -> pixels (N, 2)."""
        X = _as_array(object_xyz, 3, "object_xyz")
        h = X @ self.matrix[:, :3].T + self.matrix[:, 3]
        return h[:, :2] / h[:, 2:]

    def decompose(self) -> ProjectiveInterior:
        """RQ-decompose into the projective interior and exterior orientation.

        Raises
        ------
        CalibrationError
            If the left 3 x 3 block is singular (not a central projection).
        """
        M = self.matrix[:, :3]
        if abs(np.linalg.det(M)) < 1e-12 * np.abs(M).max() ** 3:
            raise CalibrationError("the DLT matrix has a singular 3 x 3 block: not a central projection")
        K, Rcv = scipy.linalg.rq(M)
        S = np.diag(np.sign(np.diag(K)))
        K = K @ S
        Rcv = S @ Rcv
        scale = K[2, 2]
        if np.linalg.det(Rcv) < 0:  # P was defined up to sign; keep the camera in front
            Rcv = -Rcv
            scale = -scale
        K = K / K[2, 2]
        C = np.asarray(-np.linalg.solve(M, self.matrix[:, 3]), dtype=np.float64)
        R = Rcv.T @ CV_FROM_PHOTO
        del scale
        return ProjectiveInterior(fx=float(K[0, 0]), fy=float(K[1, 1]), skew=float(K[0, 1]), cx=float(K[0, 2]),
                                  cy=float(K[1, 2]), rotation=R, centre=C)


# ------------------------------------------------------------------ plane targets
def perspective_strength(H: ArrayLike, plane_xy: ArrayLike) -> float:
    """Relative depth variation over the target points seen through ``H``.

    ``max(w) / min(w) - 1`` for ``w = H[2] . (x, y, 1)``, which is proportional
    to the depth of each target point in the camera. About ``tan(tilt) *
    extent / distance``: 0 when the target is parallel to the image plane,
    where the principal distance cannot be observed.
    """
    m = np.asarray(H, dtype=np.float64)
    p = np.asarray(plane_xy, dtype=np.float64).reshape(-1, 2)
    w = p @ m[2, :2] + m[2, 2]
    w = w * np.sign(np.median(w))
    if np.min(w) <= 0:
        return math.inf
    return float(np.max(w) / np.min(w) - 1.0)


def _centring(width: int, height: int) -> F64:
    s = (width + height) / 2.0
    return np.array([[1 / s, 0.0, -(width - 1) / 2 / s], [0.0, 1 / s, -(height - 1) / 2 / s], [0.0, 0.0, 1.0]])


def interior_from_homographies(homographies: Sequence[ArrayLike], width: int, height: int, *,
                               equal_focal: bool = False) -> tuple[F64, str]:
    """Camera matrix ``K`` (3, 3), px, from plane -> pixel homographies (zero skew).

    Returns ``(K, how)`` with ``how`` = ``"homographies"`` (Zhang's closed form,
    principal point free, >= 2 views) or ``"homographies, principal point at the
    image centre"`` (the fallback).

    Raises
    ------
    CalibrationError
        When no positive principal distance solves the equations (focal length
        unobservable, e.g. all views parallel to the image plane).
    """
    T = _centring(width, height)
    Ti = np.linalg.inv(T)
    hs = []
    for h in homographies:
        m = T @ np.asarray(h, dtype=np.float64)
        hs.append(m / np.linalg.norm(m))
    if not hs:
        raise InvalidInputError("no homographies given")

    def row(h: F64, i: int, j: int) -> F64:
        a, b = h[:, i], h[:, j]
        return np.array([a[0] * b[0], a[1] * b[1], a[0] * b[2] + a[2] * b[0], a[1] * b[2] + a[2] * b[1],
                         a[2] * b[2]])

    if len(hs) >= 2 and not equal_focal:
        V = np.array([r for h in hs for r in (row(h, 0, 1), row(h, 0, 0) - row(h, 1, 1))])
        _, s, vt = np.linalg.svd(V)
        b = vt[-1]
        if b[0] < 0:
            b = -b
        if b[0] > 0 and b[1] > 0 and s[-2] > 1e-8 * s[0]:
            cx, cy = -b[2] / b[0], -b[3] / b[1]
            lam = b[4] - b[2] ** 2 / b[0] - b[3] ** 2 / b[1]
            if lam > 0 and abs(cx) < 0.5 and abs(cy) < 0.5:
                fx, fy = math.sqrt(lam / b[0]), math.sqrt(lam / b[1])
                if 0.05 < fx < 100 and 0.05 < fy < 100 and 0.5 < fx / fy < 2:
                    K = Ti @ np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
                    return K / K[2, 2], "homographies"
        logger.info("closed-form plane-target interior failed; principal point held at the image centre")
    # principal point at the centre: unknowns a = 1/fx^2, b = 1/fy^2
    rows, rhs = [], []
    for h in hs:
        h1, h2 = h[:, 0], h[:, 1]
        rows.append([h1[0] * h2[0], h1[1] * h2[1]])
        rhs.append(-h1[2] * h2[2])
        rows.append([h1[0] ** 2 - h2[0] ** 2, h1[1] ** 2 - h2[1] ** 2])
        rhs.append(-(h1[2] ** 2 - h2[2] ** 2))
    A, y = np.array(rows), np.array(rhs)
    if equal_focal or len(hs) == 1:
        A = A.sum(axis=1, keepdims=True)
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    sol = np.broadcast_to(sol, (2,)) if sol.size == 1 else sol
    if not np.all(sol > 1e-6) or np.linalg.norm(A) < 1e-9:
        raise CalibrationError(
            "the principal distance is unobservable from these plane views (no positive solution); "
            "views must be tilted against the image plane")
    fx, fy = 1 / math.sqrt(sol[0]), 1 / math.sqrt(sol[1])
    K = Ti @ np.diag([fx, fy, 1.0])
    return K / K[2, 2], "homographies, principal point at the image centre"


def pose_from_homography(K: ArrayLike, H: ArrayLike) -> tuple[F64, F64]:
    """Object (z = 0 plane) -> OpenCV camera pose ``(R_cv, t)`` from ``H ~ K [r1 r2 t]``."""
    A = np.linalg.solve(np.asarray(K, dtype=np.float64), np.asarray(H, dtype=np.float64))
    lam = 2.0 / (np.linalg.norm(A[:, 0]) + np.linalg.norm(A[:, 1]))
    if A[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * A[:, 0], lam * A[:, 1], lam * A[:, 2]
    R = np.column_stack([r1, r2, np.cross(r1, r2)])
    u, _, vt = np.linalg.svd(R)
    R = u @ vt
    if np.linalg.det(R) < 0:
        R = u @ np.diag([1, 1, -1.0]) @ vt
    return R, t
