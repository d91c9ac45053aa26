"""Space intersection: corresponding rays of a stereo pair -> points.

Frames and units
----------------
photo
    (N, 2) float64 millimetres from the principal point, x right, y up; the
    image vector of a point is (x, y, -f).
object
    The frame of the orientation: the model frame of a relative orientation
    (left projection centre at the origin, arbitrary scale) or the ground frame
    of two exterior orientations. ``rotation_*`` take a photo vector into it:
    ``d = R @ (x, y, -f)``.

The rays are ``P = C1 + N1 d1`` and ``P = C2 + N2 d2`` with ``C2 = C1 + B``.
Eliminating ``N2`` with a cross product gives ``N1 (d1 x d2) = B x d2``: three
equations for one unknown. Every closed-form intersection formula projects
them on a direction ``u``::

    N1 = u . (B x d2) / u . (d1 x d2)

============== ======================= =========================================
method         u                       source
============== ======================= =========================================
``general-n``  (1, 1, 1)               seed 000: N = [B'x(Y'2 - Z'2) + B'y(Z'2 -
                                       X'2) + B'z(X'2 - Y'2)] / [X'1(Y'2 - Z'2)
                                       + Y'1(Z'2 - X'2) + Z'1(X'2 - Y'2)]
``aerial-n``   (0, 1, 0)               seed 001: N = (Bx + x2/f Bz) / (x1 - x2)
                                       on nadir photos; the general form is
                                       N = (Bx Z'2 - Bz X'2) / (X'1 Z'2 - Z'1 X'2)
``midpoint``   d1 x d2                 the centre of the common perpendicular
                                       (closest point to both rays in space)
``least-squares``                      minimises the image residuals in mm on
                                       both photos (Gauss-Newton from the
                                       midpoint): the closest point to both
                                       rays in the photo metric
============== ======================= =========================================

For the two N-formulas the point is ``C1 + N1 d1`` (on the left ray), as in
the seeds. Whatever the method, each point also gets the miss distance of the
rays (object units) and the residual vertical parallax ``q`` in mm at the left
photo's scale: the signed miss distance along ``d1 x d2`` divided by ``N1``;
in the normal case (R1 = R2 = I, B along +X) ``q = y2 - y1``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError, StereoError
from rectify.geometry.points import as_pair
from rectify.geometry.rotation import check_rotation

logger = logging.getLogger(__name__)

__all__ = ["METHODS", "Intersection", "intersect", "intersect_relative", "n_factor_seed001",
           "project"]

METHODS = ("least-squares", "midpoint", "general-n", "aerial-n")



@dataclass(frozen=True, eq=False)
class Intersection:
    """Intersected points and per-point diagnostics.

    Attributes
    ----------
    points : (N, 3) float64
        Object coordinates (the frame and units of the orientation).
    scale_left, scale_right : (N,) float64
        N1, N2: object units per mm of the image vectors (x, y, -f). Negative
        values put the point behind a camera.
    miss_distance : (N,) float64
        Length of the common perpendicular of the two rays, object units.
    vertical_parallax_mm : (N,) float64
        Signed residual vertical parallax at the left photo scale, mm.
    residuals_mm : (N, 4) float64
        Reprojected minus measured photo coordinates (dx1, dy1, dx2, dy2), mm.
    covariance : (N, 3, 3) float64 or None
        Covariance of each point from image noise ``sigma_mm`` (orientation
        taken as exact), object units squared; None without ``sigma_mm``.
    method : str
    """

    points: NDArray[np.float64]
    scale_left: NDArray[np.float64]
    scale_right: NDArray[np.float64]
    miss_distance: NDArray[np.float64]
    vertical_parallax_mm: NDArray[np.float64]
    residuals_mm: NDArray[np.float64]
    covariance: NDArray[np.float64] | None
    method: str

    def __post_init__(self) -> None:
        for name in ("points", "scale_left", "scale_right", "miss_distance", "vertical_parallax_mm",
                     "residuals_mm", "covariance"):
            a = getattr(self, name)
            if a is not None:
                a.flags.writeable = False

    def __len__(self) -> int:
        return len(self.points)

    @property
    def std(self) -> NDArray[np.float64] | None:
        """(N, 3) standard errors of the point coordinates, or None."""
        if self.covariance is None:
            return None
        return np.sqrt(np.einsum("nii->ni", self.covariance))


def project(points: ArrayLike, *, rotation: ArrayLike, centre: ArrayLike, focal_length_mm: float
            ) -> NDArray[np.float64]:
    """Collinearity: object points (N, 3) -> photo coordinates (N, 2), mm.

    ``p = R.T @ (P - C)``, ``x = -f p0 / p2``, ``y = -f p1 / p2``.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = (P - np.asarray(centre, dtype=np.float64)) @ np.asarray(rotation, dtype=np.float64)
    return np.column_stack([-focal_length_mm * p[:, 0] / p[:, 2], -focal_length_mm * p[:, 1] / p[:, 2]])


def n_factor_seed001(x1: ArrayLike, x2: ArrayLike, *, bx: float, bz: float, focal_length_mm: float
                     ) -> NDArray[np.float64]:
    """Seed 001's scale factor ``N = (Bx + x2/f Bz) / (x1 - x2)`` for nadir photos.

    Parameters
    ----------
    x1, x2 : (N,) array_like
        x photo coordinates (mm) of the point on the left and right photo,
        both photos brought to the nadir (rotation = identity).
    bx, bz : float
        Base components, object units.
    focal_length_mm : float

    Returns
    -------
    (N,) float64
        N such that X = N x1, Y = N y1, Z = -N f (object units, origin at the
        left projection centre).

    Raises
    ------
    StereoError
        Where the x-parallax x1 - x2 is zero (parallel rays).
    """
    a1 = np.asarray(x1, dtype=np.float64).reshape(-1)
    a2 = np.asarray(x2, dtype=np.float64).reshape(-1)
    if a1.shape != a2.shape:
        raise ShapeError(f"`x1` and `x2` must have equal shapes; got {a1.shape} and {a2.shape}",
                         actual_shape=(a1.shape, a2.shape))
    p = a1 - a2
    bad = np.abs(p) <= 1e-12 * max(1.0, float(np.abs(a1).max(initial=0.0)))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise StereoError(f"parallel rays: x-parallax x1 - x2 = {p[i]!r} mm at point {i} "
                          f"({int(bad.sum())} such points)")
    return (bx + a2 / focal_length_mm * bz) / p


def _as_f(focal_length_mm: Any) -> tuple[float, float]:
    f = np.asarray(focal_length_mm, dtype=np.float64).reshape(-1)
    if f.size == 1:
        f = np.repeat(f, 2)
    if f.size != 2 or not np.isfinite(f).all() or (f <= 0).any():
        raise InvalidInputError(f"`focal_length_mm` must be one or two numbers > 0; got {focal_length_mm!r}")
    return float(f[0]), float(f[1])


def intersect(
    left_mm: ArrayLike,
    right_mm: ArrayLike,
    *,
    rotation_left: ArrayLike,
    rotation_right: ArrayLike,
    base: ArrayLike,
    focal_length_mm: float | tuple[float, float],
    centre_left: ArrayLike = (0.0, 0.0, 0.0),
    method: str = "least-squares",
    sigma_mm: float | None = None,
    min_angle_rad: float = 1e-6,
    max_iterations: int = 10,
    step_tol: float = 1e-5,
    progress: Callable[[int, int], None] | None = None,
) -> Intersection:
    """Intersect corresponding rays of a stereo pair.

    Parameters
    ----------
    left_mm, right_mm : (N, 2) array_like
        Photo coordinates of the same points on the left and right photo, mm.
    rotation_left, rotation_right : (3, 3) array_like
        Rotations taking a photo vector (x, y, -f) into the object frame.
    base : (3,) array_like
        Right projection centre minus left, object frame and units.
    focal_length_mm : float or (float, float)
        Principal distance, or one per photo.
    centre_left : (3,) array_like
        Left projection centre in the object frame (0 for a model).
    method : {"least-squares", "midpoint", "general-n", "aerial-n"}
        See the module docstring.
    sigma_mm : float, optional
        Standard deviation of one photo coordinate; when given, each point's
        covariance is propagated (orientation taken as exact).
    min_angle_rad : float
        Rays meeting at a smaller angle count as parallel.
    max_iterations : int
        Most Gauss-Newton iterations for ``least-squares``.
    step_tol : float
        A point has converged when its last Gauss-Newton step is below
        ``step_tol`` times its distance from the left centre. The iteration
        converges linearly at a rate of about 1e-4 for aerial geometry
        (measured in ``scripts/intersection_study.py``), so the default leaves
        an error near 1e-9 of the distance (5 um at 5 km).

    Returns
    -------
    Intersection

    Raises
    ------
    StereoError
        If rays are parallel (angle < ``min_angle_rad``) or the chosen
        N-formula is singular for a point (its denominator vanishes); the
        message gives the count and the first offending point.
    InvalidInputError, ShapeError
        For malformed inputs or an unknown method.

    Examples
    --------
    >>> import numpy as np
    >>> I = np.eye(3)
    >>> r = intersect([[10.0, 5.0]], [[-10.0, 5.0]], rotation_left=I, rotation_right=I,
    ...               base=[200.0, 0, 0], focal_length_mm=100.0)
    >>> r.points.round(6).tolist()
    [[100.0, 50.0, -1000.0]]
    >>> intersect([[10.0, 5.0]], [[10.0, 5.0]], rotation_left=I, rotation_right=I,
    ...           base=[200.0, 0, 0], focal_length_mm=100.0)
    Traceback (most recent call last):
    ...
    rectify.errors.StereoError: parallel rays: 1 of 1 ray pairs meet at less than 1e-06 rad; first is point 0 ...
    """
    if method not in METHODS:
        raise InvalidInputError(f"unknown intersection method {method!r}; expected one of {list(METHODS)}")
    x1, x2 = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    R1 = check_rotation(rotation_left, "rotation_left")
    R2 = check_rotation(rotation_right, "rotation_right")
    B = np.array(base, dtype=np.float64).reshape(-1)
    C1 = np.array(centre_left, dtype=np.float64).reshape(-1)
    for name, v in (("base", B), ("centre_left", C1)):
        if v.shape != (3,) or not np.isfinite(v).all():
            raise ShapeError(f"`{name}` must be 3 finite numbers; got {v.tolist()}", actual_shape=v.shape,
                             expected_shape=(3,))
    if not np.linalg.norm(B) > 0:
        raise StereoError(f"the base is zero ({B.tolist()}): no intersection is possible")
    f1, f2 = _as_f(focal_length_mm)
    if sigma_mm is not None and not (np.isfinite(sigma_mm) and sigma_mm > 0):
        raise InvalidInputError(f"`sigma_mm` must be a finite number > 0; got {sigma_mm!r}")
    n = len(x1)
    P = np.empty((n, 3))
    N1 = np.empty(n)
    N2 = np.empty(n)
    miss = np.empty(n)
    q = np.empty(n)
    res = np.empty((n, 4))
    cov = np.empty((n, 3, 3)) if sigma_mm is not None else None
    iters = 0
    # chunks keep the temporaries in cache: about 2x faster than whole arrays
    for start in range(0, n, _CHUNK):
        sl = slice(start, min(start + _CHUNK, n))
        iters = max(iters, _intersect_chunk(
            x1[sl], x2[sl], R1, R2, B, f1, f2, method, sigma_mm, min_angle_rad, max_iterations, step_tol,
            start, n,
            P[sl], N1[sl], N2[sl], miss[sl], q[sl], res[sl], None if cov is None else cov[sl]))
        if progress is not None:
            progress(sl.stop, n)
    if method == "least-squares":
        logger.debug("least-squares intersection of %d points: at most %d iterations", n, iters)
    P += C1
    return Intersection(points=P, scale_left=N1, scale_right=N2, miss_distance=miss,
                        vertical_parallax_mm=q, residuals_mm=res, covariance=cov, method=method)


_CHUNK = 1 << 14


def _cam_terms(P, C, R, f, u, v, with_jac=True):
    """Photo residuals (measured - projected) and Jacobian rows of one camera.

    ``P`` is a tuple of three (n,) arrays; ``R`` a (3, 3) nested list. Works on
    separate coordinate arrays (not (n, 3)) because numpy is much faster on
    contiguous 1-D arrays than on reductions along a short last axis.
    """
    qx, qy, qz = P[0] - C[0], P[1] - C[1], P[2] - C[2]
    p0 = R[0][0] * qx + R[1][0] * qy + R[2][0] * qz
    p1 = R[0][1] * qx + R[1][1] * qy + R[2][1] * qz
    p2 = R[0][2] * qx + R[1][2] * qy + R[2][2] * qz
    w = 1.0 / p2
    a = p0 * w
    b = p1 * w
    rx = u + f * a  # measured - projected, projected x = -f a
    ry = v + f * b
    if not with_jac:
        return rx, ry, None, None
    s = -f * w
    jx = [s * (R[k][0] - a * R[k][2]) for k in range(3)]
    jy = [s * (R[k][1] - b * R[k][2]) for k in range(3)]
    return rx, ry, jx, jy


def _normal_soa(rows):
    """Upper triangle (a00, a01, a02, a11, a12, a22) of sum_r r r^T for SoA rows."""
    out = []
    for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        acc = rows[0][i] * rows[0][j]
        for r in rows[1:]:
            acc += r[i] * r[j]
        out.append(acc)
    return out


def _inv_sym_soa(A):
    """Cofactor inverse of symmetric 3x3 matrices given as 6 arrays; returns 6 arrays."""
    a, b, c, d, e, g = A
    c00 = d * g - e * e
    c01 = c * e - b * g
    c02 = b * e - c * d
    c11 = a * g - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    idet = 1.0 / (a * c00 + b * c01 + c * c02)
    return [c00 * idet, c01 * idet, c02 * idet, c11 * idet, c12 * idet, c22 * idet]


def _gn_soa(P, u1, v1, u2, v2, R1, R2, B, f1, f2):
    """One Gauss-Newton step of the photo-metric intersection; returns dP (3 arrays)."""
    zero = (0.0, 0.0, 0.0)
    rx1, ry1, jx1, jy1 = _cam_terms(P, zero, R1, f1, u1, v1)
    rx2, ry2, jx2, jy2 = _cam_terms(P, B, R2, f2, u2, v2)
    g = [jx1[k] * rx1 + jy1[k] * ry1 + jx2[k] * rx2 + jy2[k] * ry2 for k in range(3)]
    i00, i01, i02, i11, i12, i22 = _inv_sym_soa(_normal_soa([jx1, jy1, jx2, jy2]))
    return (i00 * g[0] + i01 * g[1] + i02 * g[2],
            i01 * g[0] + i11 * g[1] + i12 * g[2],
            i02 * g[0] + i12 * g[1] + i22 * g[2])


def _intersect_chunk(x1, x2, R1, R2, B, f1, f2, method, sigma_mm, min_angle_rad, max_iterations, step_tol,
                     offset, n_total, P_out, N1_out, N2_out, miss_out, q_out, res_out, cov_out) -> int:
    """Intersect one chunk of points into the given output views; returns the iterations used."""
    n = len(x1)
    R1l, R2l, Bt = R1.tolist(), R2.tolist(), tuple(float(b) for b in B)
    u1, v1 = x1[:, 0].copy(), x1[:, 1].copy()
    u2, v2 = x2[:, 0].copy(), x2[:, 1].copy()
    d1 = [R1l[k][0] * u1 + R1l[k][1] * v1 - f1 * R1l[k][2] for k in range(3)]
    d2 = [R2l[k][0] * u2 + R2l[k][1] * v2 - f2 * R2l[k][2] for k in range(3)]
    c = [d1[1] * d2[2] - d1[2] * d2[1], d1[2] * d2[0] - d1[0] * d2[2], d1[0] * d2[1] - d1[1] * d2[0]]
    nc = np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    n1s = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
    n2s = d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2]
    sin_angle = nc / np.sqrt(n1s * n2s)
    bad = ~(sin_angle >= min_angle_rad)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise StereoError(
            f"parallel rays: {int(bad.sum())} of {n_total} ray pairs meet at less than {min_angle_rad:g} rad"
            f"{' (in this chunk)' if n != n_total else ''}; first is point {offset + i} "
            f"(angle {float(np.arcsin(min(sin_angle[i], 1.0))):.3g} rad)")
    b0, b1, b2 = Bt
    # signed miss distance along the common perpendicular (the same for every method)
    signed_miss = (c[0] * b0 + c[1] * b1 + c[2] * b2) / nc
    iters = 0
    if method in ("general-n", "aerial-n"):
        if method == "general-n":
            den = c[0] + c[1] + c[2]
            # (B x d2) . (1,1,1) and (B x d1) . (1,1,1)
            num1 = (b1 * d2[2] - b2 * d2[1]) + (b2 * d2[0] - b0 * d2[2]) + (b0 * d2[1] - b1 * d2[0])
            num2 = (b1 * d1[2] - b2 * d1[1]) + (b2 * d1[0] - b0 * d1[2]) + (b0 * d1[1] - b1 * d1[0])
            u = [1.0, 1.0, 1.0]
        else:
            den = c[1]
            num1 = b2 * d2[0] - b0 * d2[2]
            num2 = b2 * d1[0] - b0 * d1[2]
            u = [0.0, 1.0, 0.0]
        tiny = np.abs(den) <= 1e-9 * nc
        if tiny.any():
            i = int(np.flatnonzero(tiny)[0])
            raise StereoError(
                f"the {method} formula is singular: its denominator u.(d1 x d2) vanishes for "
                f"{int(tiny.sum())} points (u = {u}); first is point {offset + i}, "
                f"left {x1[i].tolist()} mm, right {x2[i].tolist()} mm")
        N1 = num1 / den
        N2 = num2 / den
        P = [N1 * d1[k] for k in range(3)]
    else:
        # midpoint: minimise |N1 d1 - B - N2 d2|^2
        d12 = d1[0] * d2[0] + d1[1] * d2[1] + d1[2] * d2[2]
        e = d1[0] * b0 + d1[1] * b1 + d1[2] * b2
        g = d2[0] * b0 + d2[1] * b1 + d2[2] * b2
        idet = 1.0 / (n1s * n2s - d12 * d12)
        N1 = (n2s * e - d12 * g) * idet
        N2 = (d12 * e - n1s * g) * idet
        P = [0.5 * (N1 * d1[k] + Bt[k] + N2 * d2[k]) for k in range(3)]
        if method == "least-squares":
            idx = None  # all points active
            for iters in range(1, max_iterations + 1):  # noqa: B007 (returned: the iterations used)
                if idx is None:
                    Pa, a_uv = P, (u1, v1, u2, v2)
                else:
                    Pa, a_uv = [p[idx] for p in P], (u1[idx], v1[idx], u2[idx], v2[idx])
                dP = _gn_soa(Pa, *a_uv, R1l, R2l, Bt, f1, f2)
                Pn = [Pa[k] + dP[k] for k in range(3)]
                step2 = dP[0] * dP[0] + dP[1] * dP[1] + dP[2] * dP[2]
                dist2 = Pn[0] * Pn[0] + Pn[1] * Pn[1] + Pn[2] * Pn[2]
                big = step2 > (step_tol * step_tol) * dist2
                if idx is None:
                    P = Pn
                    idx = np.flatnonzero(big)
                else:
                    for k in range(3):
                        P[k][idx] = Pn[k]
                    idx = idx[big]
                if idx.size == 0:
                    break
            N1 = (P[0] * d1[0] + P[1] * d1[1] + P[2] * d1[2]) / n1s
            N2 = ((P[0] - b0) * d2[0] + (P[1] - b1) * d2[1] + (P[2] - b2) * d2[2]) / n2s
    zero = (0.0, 0.0, 0.0)
    need_jac = cov_out is not None
    rx1, ry1, jx1, jy1 = _cam_terms(P, zero, R1l, f1, u1, v1, with_jac=need_jac)
    rx2, ry2, jx2, jy2 = _cam_terms(P, Bt, R2l, f2, u2, v2, with_jac=need_jac)
    if need_jac:
        i00, i01, i02, i11, i12, i22 = _inv_sym_soa(_normal_soa([jx1, jy1, jx2, jy2]))
        s2 = float(sigma_mm) ** 2
        cov_out[:, 0, 0], cov_out[:, 0, 1], cov_out[:, 0, 2] = s2 * i00, s2 * i01, s2 * i02
        cov_out[:, 1, 0], cov_out[:, 1, 1], cov_out[:, 1, 2] = s2 * i01, s2 * i11, s2 * i12
        cov_out[:, 2, 0], cov_out[:, 2, 1], cov_out[:, 2, 2] = s2 * i02, s2 * i12, s2 * i22
    with np.errstate(divide="ignore", invalid="ignore"):
        q_out[...] = signed_miss / N1
    # residual = projected - measured
    res_out[:, 0], res_out[:, 1], res_out[:, 2], res_out[:, 3] = -rx1, -ry1, -rx2, -ry2
    P_out[:, 0], P_out[:, 1], P_out[:, 2] = P
    N1_out[...] = N1
    N2_out[...] = N2
    miss_out[...] = np.abs(signed_miss)
    return iters


def intersect_relative(ro: Any, left_mm: ArrayLike, right_mm: ArrayLike, **kwargs: Any) -> Intersection:
    """Intersect in the model frame of a relative orientation.

    Parameters
    ----------
    ro : RelativeOrientation-like
        Any object with ``rotation_left``, ``rotation_right`` (3, 3),
        ``base`` (3,) and ``focal_length_mm``.
    left_mm, right_mm : (N, 2) array_like
        Photo coordinates, mm.
    **kwargs
        Passed to :func:`intersect` (``method``, ``sigma_mm``, ...).
    """
    try:
        R1, R2, B, f = ro.rotation_left, ro.rotation_right, ro.base, ro.focal_length_mm
    except AttributeError as err:
        raise InvalidInputError(f"`ro` is not a relative orientation: {err}") from err
    return intersect(left_mm, right_mm, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=f,
                     **kwargs)
