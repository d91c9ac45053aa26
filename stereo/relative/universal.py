"""Universal relative orientation by linear iterations (seed 003, section 3.2.1).

The seed's method ("взаимное ориентирование путем линейных итераций") replaces the angles of the
traditional adjustment by the parameters p, q, r of the direction-cosine matrices (analogues of
omega, alpha, kappa), simplified with Delta = 1 so that the correction equations are linear and are
solved directly, without approximate values of the angles:

1. the photo vectors u = (x, y, -f) of both images are first transformed by the resulting matrices
   C1, C2 of the previous iterations (identity at the first);
2. the linear correction equations of the coplanarity condition of the first scheme (fixed base
   along the model X axis, b = (1, 0, 0); p1 = omega1 = 0) are formed and solved for the five
   parameters q1, r1 (left image) and p2, q2, r2 (right image) - weighted least squares with the
   weights of the coplanarity adjustment (:mod:`stereo.relative`), so each equation is a
   normalised residual in mm;
3. the affine matrix I + [d]x of the corrections d = (p, q, r) of each image (the seed's matrix
   (3.3) with Delta = 1) is orthogonalised by Gram-Schmidt (the seed's choice of the two
   orthogonalisations it cites);
4. the resulting matrices are updated, C <- C_m C (the seed's C = prod C_m, recomputed every
   iteration so that errors do not accumulate), and the loop returns to 1 until the correction
   matrices equal the identity within the tolerance.

Each iteration is a direct linear solution about the current transformed coordinates, so the start
needs no approximate angles (large convergence and tilt, seed: up to 70 and 10 degrees). The
result is expressed in the elements of the ``basis`` system (alpha1, kappa1, alpha2, omega2, kappa2;
the seed's first scheme), which is how :mod:`stereo.relative.solver` reports its precision.

The seed's formulas (3.2)-(3.13) are images missing from the text extract; the steps above follow
its prose (see docs/universal.md).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from rectify.errors import ConvergenceError, EstimationError
from stereo.relative.systems import _cross, get_system

logger = logging.getLogger(__name__)

__all__ = ["gram_schmidt", "affine_matrix", "solve_universal"]

_B = np.array([1.0, 0.0, 0.0])


def affine_matrix(pqr: NDArray[np.float64]) -> NDArray[np.float64]:
    """The seed's linearised direction-cosine matrix with Delta = 1: I + [d]x, d = (p, q, r)
    (rotations about x, y and z), (3, 3); not orthogonal."""
    p, q, r = (float(v) for v in pqr)
    return np.array([[1.0, -r, q], [r, 1.0, -p], [-q, p, 1.0]])


def gram_schmidt(A: NDArray[np.float64]) -> NDArray[np.float64]:
    """Orthonormalise the columns of A (3, 3) in the order x, y, z (classical Gram-Schmidt); the
    result is a rotation when det A > 0."""
    cols: list[NDArray[np.float64]] = []
    for k in range(3):
        v = A[:, k].astype(np.float64).copy()
        for c in cols:
            v -= (c @ v) * c
        n = float(np.linalg.norm(v))
        if n < 1e-12:
            raise EstimationError("Gram-Schmidt: the matrix of direction-cosine parameters is singular")
        cols.append(v / n)
    return np.column_stack(cols)


def _front(C1: NDArray, C2: NDArray, u1: NDArray, u2: NDArray, used: NDArray) -> float:
    """Fraction of the used points whose rays meet in front of both cameras (base b = +X)."""
    r1, r2 = u1[used] @ C1.T, u2[used] @ C2.T
    c = _cross(r1, r2)
    cc = np.einsum("ij,ij->i", c, c)
    ok = cc > 0
    if not ok.any():
        return 0.0
    l1 = np.einsum("ij,ij->i", _cross(_B, r2), c)[ok] / cc[ok]
    l2 = np.einsum("ij,ij->i", _cross(_B, r1), c)[ok] / cc[ok]
    return float(np.mean((l1 > 0) & (l2 > 0)))


def solve_universal(u1: NDArray[np.float64], u2: NDArray[np.float64], w: NDArray[np.float64], *,
                    max_iterations: int = 100, tol: float = 1e-11
                    ) -> tuple[NDArray[np.float64], int]:
    """Linear iterations of seed 003, 3.2.1, from the identity; when that solution puts the points
    behind the cameras (the base not along +x of the photos, or the right image turned by about
    180 degrees in its plane - cases the seed excludes by measuring both images along their initial
    directions), again from the photo frames turned in their plane by 180, 90 or 270 degrees (and the
    right one by 180 more), keeping the solution with most points in front of both cameras.

    Parameters
    ----------
    u1, u2 : (N, 3) float64
        Photo vectors (x, y, -f) of the left and right image, mm.
    w : (N,) float64
        A-priori weights (0 excludes a point); at least 5 positive.
    max_iterations : int
    tol : float
        Stop when the largest element of every correction matrix minus I is below this.

    Returns
    -------
    elements : (5,) float64
        Elements of the ``basis`` system (radians) of the resulting relative geometry.
    iterations : int

    Raises
    ------
    EstimationError
        Fewer than 5 weighted points, singular correction equations (no parallax, points on one
        line).
    ConvergenceError
        No convergence within ``max_iterations``.
    """
    used = w > 0
    if int(used.sum()) < 5:
        raise EstimationError(f"only {int(used.sum())} tie point(s) with positive weight; at least 5 needed")
    best: tuple[float, NDArray, NDArray] | None = None
    total = 0
    last_err: Exception | None = None
    for turn1, turn2 in _TURNS:
        try:
            C1, C2, it = _iterate(u1, u2, w, _rz(turn1), _rz(turn2), max_iterations, tol)
        except ConvergenceError as err:
            last_err = err
            continue
        total += it
        front = _front(C1, C2, u1, u2, used)
        if best is None or front > best[0]:
            best = (front, C1, C2)
        if front > 0.9:
            break
    if best is None:
        assert last_err is not None
        raise last_err
    _, C1, C2 = best
    return get_system("basis").elements_from_relative(C1.T @ C2, C1.T @ _B), total


#: in-plane turns (degrees) of the left and right photo frames tried in turn: the identity first (the
#: seed's case), then the base along -x, +-y of the photos, each with the right image also turned by 180
_TURNS = [(t, t + r) for t in (0, 180, 90, 270) for r in (0, 180)]


def _rz(deg: float) -> NDArray[np.float64]:
    c, s = round(math.cos(math.radians(deg))), round(math.sin(math.radians(deg)))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _iterate(u1: NDArray, u2: NDArray, w: NDArray, C1_start: NDArray, C2_start: NDArray, max_iterations: int,
             tol: float) -> tuple[NDArray, NDArray, int]:
    """The linear iterations from the resulting matrices C1_start, C2_start; returns (C1, C2, iterations)."""
    used = w > 0
    C1, C2 = C1_start.copy(), C2_start.copy()
    last = math.inf
    for it in range(1, max_iterations + 1):
        r1, r2 = u1 @ C1.T, u2 @ C2.T                      # step 1: pre-transformed coordinates
        F = _cross(r1, r2) @ _B
        a1 = _cross(r2, _B)                                 # dF/dr1
        a2 = _cross(_B, r1)                                 # dF/dr2
        g1, g2 = a1 @ C1, a2 @ C2                           # dF/du (photo coordinates)
        gn2 = g1[:, 0] ** 2 + g1[:, 1] ** 2 + g2[:, 0] ** 2 + g2[:, 1] ** 2
        j1 = _cross(r1, a1)                                 # dF/d(d1): d(r1) = d1 x r1
        j2 = _cross(r2, a2)
        A = np.column_stack([j1[:, 1], j1[:, 2], j2[:, 0], j2[:, 1], j2[:, 2]])  # q1 r1 p2 q2 r2
        ww = np.where(used, w / np.where(gn2 > 0, gn2, np.inf), 0.0)
        sw = np.sqrt(ww)
        N = (A * ww[:, None]).T @ A
        d = np.sqrt(np.diag(N))
        if not (d > 0).all() or np.linalg.cond(N / np.outer(d, d)) > 1e12:
            raise EstimationError("degenerate configuration for universal relative orientation: the correction "
                                  "equations are singular (no parallax, or the points on one line)")
        x = -np.linalg.lstsq(A * sw[:, None], F * sw, rcond=None)[0]  # step 2: direct linear solution
        d1 = np.array([0.0, x[0], x[1]])
        d2 = x[2:]
        Cm1, Cm2 = gram_schmidt(affine_matrix(d1)), gram_schmidt(affine_matrix(d2))  # step 3
        C1, C2 = Cm1 @ C1, Cm2 @ C2                         # step 4: resulting matrices
        step = max(float(np.abs(Cm1 - np.eye(3)).max()), float(np.abs(Cm2 - np.eye(3)).max()))
        logger.debug("universal RO iteration %d: largest correction %.3g", it, step)
        if not np.isfinite(step):
            raise ConvergenceError(f"universal relative orientation: non-finite correction at iteration {it}",
                                   iterations=it)
        if step < tol:
            return C1, C2, it
        if it > 20 and step > 0.5 and step >= last:
            raise ConvergenceError(f"universal relative orientation diverges: correction {step:.3g} at "
                                   f"iteration {it}", iterations=it)
        last = step
    raise ConvergenceError(f"universal relative orientation did not converge in {max_iterations} linear "
                           f"iterations (last correction {last:.3g})", iterations=max_iterations)
