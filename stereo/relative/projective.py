"""The fundamental matrix of a pair: relative orientation by the 2D-2D projective relation (seed 003,
section 3.2.2), without interior orientation.

The fundamental matrix F (3, 3, rank 2, unit Frobenius norm) maps a left point to its epipolar line in
the right image: ``x_right^T F x_left = 0`` for homogeneous coordinates (x, y, 1) - pixels (x right,
y down) when no camera is known, or any affine image frame. Seven of its eight ratios are
independent (7 degrees of freedom); with a calibrated camera it reduces to the essential matrix of
the five elements of relative orientation (:func:`relative_from_fundamental`).

Estimation (:func:`fundamental_from_points`): Hartley's normalised eight-point solution, rank 2
enforced, then Levenberg-Marquardt on the Sampson distances (the first-order geometric distance of
each pair from the epipolar constraint, pixels) in the minimal orthonormal representation
F = U diag(1, s, 0) V^T (Bartoli and Sturm). A pair whose points lie on one plane, or that has no
base, is related by a homography and leaves F undetermined: it is refused (degenerate
configuration, a critical surface).

The canonical projective cameras and the projective model are in :mod:`stereo.pair.projective`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry import lsq
from rectify.geometry.points import as_pair

__all__ = ["MIN_POINTS_F", "FundamentalFit", "fundamental_from_points", "sampson_distances", "epipoles", "skew",
           "normaliser", "essential_candidates", "relative_from_fundamental"]

#: point pairs needed by the (normalised) 8-point fundamental matrix (7 is the algebraic minimum,
#: which has up to three solutions and no redundancy)
MIN_POINTS_F = 8
#: a homography explaining the pairs within this factor of the fundamental matrix's rms (or
#: within _PLANE_FLOOR of the image scale) leaves F undetermined (a plane or no base)
_PLANE_RATIO = 3.0
_PLANE_FLOOR = 1e-7


def skew(v: ArrayLike) -> NDArray[np.float64]:
    """[v]x (3, 3): the cross-product matrix, ``skew(a) @ b == cross(a, b)``."""
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def normaliser(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hartley's similarity (3, 3): centroid to 0, mean distance sqrt(2)."""
    c = xy.mean(axis=0)
    d = float(np.mean(np.linalg.norm(xy - c, axis=1)))
    s = math.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _h(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.column_stack([xy, np.ones(len(xy))])


def sampson_distances(F: ArrayLike, left_px: ArrayLike, right_px: ArrayLike) -> NDArray[np.float64]:
    """Signed Sampson distances (N,), pixels: the first-order distance of each pair (x, x') in R^4
    from the variety ``x'^T F x = 0``. With independent noise sigma on every coordinate of both
    images, E[d^2] = sigma^2."""
    Fm = np.asarray(F, dtype=np.float64).reshape(3, 3)
    a, b = _h(np.asarray(left_px, dtype=np.float64)), _h(np.asarray(right_px, dtype=np.float64))
    Fx = a @ Fm.T
    Ftx = b @ Fm
    num = np.einsum("ij,ij->i", b, Fx)
    den = np.sqrt(Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / den, np.inf)


def epipoles(F: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(e, e'): unit homogeneous epipoles (3,) of the left (``F e = 0``) and right (``F^T e' = 0``)
    images."""
    U, _, Vt = np.linalg.svd(np.asarray(F, dtype=np.float64).reshape(3, 3))
    return Vt[-1].copy(), U[:, -1].copy()


def _rank2(F: NDArray[np.float64]) -> NDArray[np.float64]:
    U, s, Vt = np.linalg.svd(F)
    G = U @ np.diag([s[0], s[1], 0.0]) @ Vt
    return G / np.linalg.norm(G)


def _linear_f(a: NDArray, b: NDArray) -> tuple[NDArray, NDArray]:
    """Eight-point F (3, 3) in normalised coordinates and the singular values (9,) of its design."""
    A = np.column_stack([b[:, [0]] * a, b[:, [1]] * a, a])  # rows: kron(x', x)
    _, s, Vt = np.linalg.svd(A, full_matrices=len(A) < 9)
    return _rank2(Vt[-1].reshape(3, 3)), s


def _homography_rms(a: NDArray, b: NDArray) -> float:
    """Rms one-sided transfer error of the best homography between normalised points."""
    rows = []
    for (x, y, _), (u, v, _) in zip(a, b, strict=True):
        rows.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
        rows.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
    _, _, Vt = np.linalg.svd(np.asarray(rows))
    H = Vt[-1].reshape(3, 3)
    p = a @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        d = p[:, :2] / p[:, 2:3] - b[:, :2]
    if not np.isfinite(d).all():
        return math.inf
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _orth(w: NDArray) -> NDArray[np.float64]:
    """Rotation exp([w]x) (Rodrigues) for a small vector (3,)."""
    t = float(np.linalg.norm(w))
    K = skew(w)
    if t < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(t) / t * K + (1 - math.cos(t)) / t**2 * K @ K


@dataclass(frozen=True)
class FundamentalFit:
    """How a fundamental matrix fits its point pairs.

    Attributes
    ----------
    sampson_px : (N,) float64
        Signed Sampson distance of every pair (pixels) under the final F.
    inliers : (N,) bool
        Pairs used in the final fit (all, unless ``outlier_px`` rejected some).
    rms_px : float
        Rms Sampson distance over the inliers.
    sigma0_px : float or None
        sqrt(sum d^2 / (n - 7)) over the inliers: the estimated standard deviation of one image
        coordinate (F has 7 degrees of freedom).
    redundancy : int
        n_inliers - 7.
    iterations : int
        Levenberg-Marquardt iterations of the Sampson refinement.
    condition : float
        sigma_1 / sigma_8 of the normalised eight-point design (large = weak geometry).
    """

    sampson_px: NDArray[np.float64]
    inliers: NDArray[np.bool_]
    rms_px: float
    sigma0_px: float | None
    redundancy: int
    iterations: int
    condition: float


def _sampson_refine(F0n: NDArray, a: NDArray, b: NDArray, Ta: NDArray, Tb: NDArray,
                    max_iterations: int = 50) -> tuple[NDArray, int]:
    """Minimise the pixel Sampson distances over rank-2 F in the orthonormal representation
    F = U diag(1, s, 0) V^T (7 parameters: two small rotations and s; Bartoli and Sturm)."""
    U, sv, Vt = np.linalg.svd(F0n)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    s = sv[1] / sv[0]
    ax, bx = a @ np.linalg.inv(Ta).T, b @ np.linalg.inv(Tb).T  # pixel homogeneous

    def build(U_, s_, Vt_):
        Fn = U_ @ np.diag([1.0, s_, 0.0]) @ Vt_
        return Tb.T @ Fn @ Ta

    def resid(Fp):
        Fx, Ftx = ax @ Fp.T, bx @ Fp
        num = np.einsum("ij,ij->i", bx, Fx)
        return num / np.sqrt(Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2)

    def step_params(U_, s_, Vt_, d):
        return U_ @ _orth(d[:3]), s_ + d[6], (Vt_.T @ _orth(d[3:6])).T

    r = resid(build(U, s, Vt))
    cost = float(r @ r)
    lam = 1e-3
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007
        J = np.empty((len(r), 7))
        for k in range(7):
            d = np.zeros(7)
            d[k] = 1e-6
            Up, sp, Vp = step_params(U, s, Vt, d)
            Um, sm, Vm = step_params(U, s, Vt, -d)
            J[:, k] = (resid(build(Up, sp, Vp)) - resid(build(Um, sm, Vm))) / 2e-6
        N = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(10):
            try:
                dx = -np.linalg.solve(N + lam * np.diag(np.diag(N) + 1e-12), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            Un, sn, Vn = step_params(U, s, Vt, dx)
            rn = resid(build(Un, sn, Vn))
            cn = float(rn @ rn)
            if np.isfinite(cn) and cn <= cost:
                U, s, Vt, r = Un, sn, Vn, rn
                done = cost - cn <= 1e-12 * max(cost, 1e-30)
                cost = cn
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        if not improved or done:
            break
    Fp = build(U, s, Vt)
    return Fp / np.linalg.norm(Fp), it


def fundamental_from_points(left_px: ArrayLike, right_px: ArrayLike, *, refine: bool = True,
                            outlier_px: float | None = None) -> tuple[NDArray[np.float64], FundamentalFit]:
    """Fundamental matrix of a pair: normalised eight-point, then Sampson refinement.

    Parameters
    ----------
    left_px, right_px : (N, 2) array_like
        Corresponding pixel coordinates (x right, y down), N >= 8.
    refine : bool
        Minimise the Sampson distances (pixels) after the linear solution (default).
    outlier_px : float, optional
        When given, the pairs farther than half the largest Sampson distance (and than
        ``outlier_px``) are dropped and F is fitted again, up to 10 times, until every remaining
        pair is within ``outlier_px``; pairs the final F puts within the threshold are taken back.
        At least 8 must remain. Not a RANSAC: meant for a few gross errors among good pairs.

    Returns
    -------
    F : (3, 3) float64
        Rank 2, unit Frobenius norm, sign fixed so that its largest-magnitude element is positive;
        ``x_right^T F x_left = 0`` for homogeneous pixel coordinates.
    fit : FundamentalFit

    Raises
    ------
    EstimationError
        Fewer than 8 pairs; a degenerate configuration (all scene points on one plane, or no base:
        a homography explains the pairs as well as F does, so F is not determined).
    """
    a_px, b_px = as_pair(left_px, right_px, names=("left_px", "right_px"))
    n = len(a_px)
    if n < MIN_POINTS_F:
        raise EstimationError(f"too few point pairs for the fundamental matrix: {n}; the eight-point "
                              f"method needs at least {MIN_POINTS_F} (7 is the algebraic minimum, with up "
                              f"to three solutions and no check)")
    inl = np.ones(n, dtype=bool)
    F, fit = _fit_f(a_px, b_px, inl, refine)
    if outlier_px is not None:
        if not outlier_px > 0:
            raise InvalidInputError(f"outlier threshold must be > 0 px; got {outlier_px}")
        for _ in range(10):  # drop the worst pair at a time until all remaining are within the threshold,
            d = np.where(inl, np.abs(fit.sampson_px), -1.0)  # then take back pairs the final F accepts
            if d.max() <= outlier_px:
                break
            inl = inl.copy()
            worst = d > max(outlier_px, 0.5 * float(d.max()))
            inl[worst] = False
            if inl.sum() < MIN_POINTS_F:
                raise EstimationError(f"only {int(inl.sum())} point pairs left within {outlier_px} px of the "
                                      f"fundamental matrix; at least {MIN_POINTS_F} needed")
            F, fit = _fit_f(a_px, b_px, inl, refine)
        back = np.abs(fit.sampson_px) <= outlier_px
        if (back & ~inl).any():
            F, fit = _fit_f(a_px, b_px, back | inl, refine)
    return F, fit


def _fit_f(a_px: NDArray, b_px: NDArray, inl: NDArray, refine: bool) -> tuple[NDArray, FundamentalFit]:
    Ta, Tb = normaliser(a_px[inl]), normaliser(b_px[inl])
    a, b = _h(a_px[inl]) @ Ta.T, _h(b_px[inl]) @ Tb.T
    Fn, s = _linear_f(a, b)
    cond = float(s[0] / s[7]) if s[7] > 0 else math.inf
    it = 0
    if refine:
        F, it = _sampson_refine(Fn, a, b, Ta, Tb)
    else:
        F = Tb.T @ Fn @ Ta
        F = F / np.linalg.norm(F)
    F = F * np.sign(F.flat[np.argmax(np.abs(F))])
    d = sampson_distances(F, a_px, b_px)
    k = int(inl.sum())
    rms = float(np.sqrt(np.mean(d[inl] ** 2)))
    # degeneracy: a plane (or no base) lets a homography map the left points onto the right ones;
    # compare its transfer rms (normalised units -> pixels of the right image) with F's
    scale_b = 1.0 / Tb[0, 0]
    h_rms = _homography_rms(a, b) * scale_b
    f_rms_pts = rms * math.sqrt(2.0)  # a one-sided transfer error carries the noise of both images
    extent = float(np.ptp(b_px[inl], axis=0).max())
    if h_rms <= max(_PLANE_RATIO * f_rms_pts, _PLANE_FLOOR * extent) or not np.isfinite(d[inl]).all():
        raise EstimationError(
            f"degenerate configuration for the fundamental matrix: one homography maps the {k} left points "
            f"onto the right ones within {h_rms:.3g} px (F fits within {rms:.3g} px): the scene points lie "
            f"on one plane or the pair has no base, so F is not determined")
    fit = FundamentalFit(sampson_px=d, inliers=inl.copy(), rms_px=rms,
                         sigma0_px=lsq.sigma0(float(np.sum(d[inl] ** 2)), k - 7), redundancy=k - 7,
                         iterations=it, condition=cond)
    return F, fit



def essential_candidates(F: ArrayLike, pixel_size_mm: float, focal_length_mm: tuple[float, float]
                         ) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """The four relative geometries (R_rel, base_left) of a fundamental matrix of photo coordinates.

    Parameters
    ----------
    F : (3, 3)
        Fundamental matrix of the photo coordinates divided by the pixel size (x right, y up, origin at
        the principal point, in pixels): ``h_right^T F h_left = 0`` with h = (x / pixel, y / pixel, 1).
    pixel_size_mm : float
    focal_length_mm : (float, float)
        Principal distances of the left and right camera.

    Returns
    -------
    list of 4 (R_rel (3, 3) right photo frame -> left photo frame, base_left (3,) unit base in the
    left photo frame); the essential matrix is ``E = R_rel^T [b]x`` (photo vectors (x, y, -f)), made
    essential (two equal singular values) before the decomposition. The caller keeps the one that
    puts the points in front of both cameras.
    """
    Fm = np.asarray(F, dtype=np.float64).reshape(3, 3)
    f1, f2 = focal_length_mm
    D1i = np.diag([1 / pixel_size_mm, 1 / pixel_size_mm, -1 / f1])
    D2i = np.diag([1 / pixel_size_mm, 1 / pixel_size_mm, -1 / f2])
    E = D2i @ Fm @ D1i   # u2^T E u1 = 0 for photo vectors u = (x, y, -f)
    U, _, Vt = np.linalg.svd(E.T)  # E^T = [t]x R_rel with t = -b
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    out = []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            out.append((R, -t / np.linalg.norm(t)))
    return out


def _in_front(R_rel: NDArray, b: NDArray, u1: NDArray, u2: NDArray) -> float:
    """Fraction of points whose rays (left photo frame = model frame) meet in front of both cameras."""
    r2 = u2 @ R_rel.T
    c = np.cross(u1, r2)
    cc = np.einsum("ij,ij->i", c, c)
    ok = cc > 0
    if not ok.any():
        return 0.0
    l1 = np.einsum("ij,ij->i", np.cross(b, r2), c)[ok] / cc[ok]
    l2 = np.einsum("ij,ij->i", np.cross(b, u1), c)[ok] / cc[ok]
    return float(np.mean((l1 > 0) & (l2 > 0)))


def relative_from_fundamental(left_mm: ArrayLike, right_mm: ArrayLike, focal_length_mm: tuple[float, float],
                              pixel_size_mm: float
                              ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], FundamentalFit]:
    """Relative orientation of a calibrated pair through its fundamental matrix (seed 003, 3.2.2).

    Parameters
    ----------
    left_mm, right_mm : (N, 2) float64
        Photo coordinates, mm (x right, y up, origin at the principal point), N >= 8.
    focal_length_mm : (float, float)
    pixel_size_mm : float
        Scales the photo coordinates to pixels, so that the Sampson distances are pixels.

    Returns
    -------
    R_rel : (3, 3)
        Right photo frame -> left photo frame.
    base_left : (3,)
        Unit base in the left photo frame.
    F : (3, 3)
        Fundamental matrix of the photo coordinates in pixels (see :func:`essential_candidates`).
    fit : FundamentalFit

    Raises
    ------
    EstimationError
        As :func:`fundamental_from_points`; no decomposition puts the points in front of both cameras.
    """
    lm, rm = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    F, fit = fundamental_from_points(lm / pixel_size_mm, rm / pixel_size_mm)
    f1, f2 = focal_length_mm
    u1 = np.column_stack([lm, np.full(len(lm), -f1)])
    u2 = np.column_stack([rm, np.full(len(rm), -f2)])
    best = max(essential_candidates(F, pixel_size_mm, (f1, f2)), key=lambda c: _in_front(c[0], c[1], u1, u2))
    if _in_front(best[0], best[1], u1, u2) < 0.5:
        raise EstimationError("no decomposition of the fundamental matrix puts most points in front of both cameras")
    return best[0], best[1], F, fit
