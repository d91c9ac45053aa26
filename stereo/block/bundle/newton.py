"""One step of the bundle adjustment: the robust algorithm and the Newton-Raphson variant (seed 002, 2.2).

:func:`step` assembles the normal equations (:func:`stereo.block.bundle.solve.normal`) and solves them:

* ``modified_residuals`` (seed 002, eqs. 2.25-2.27): the normal matrix carries the a-priori weights only;
  the residuals are replaced by the modified residuals ``v* = w v`` (``w = psi(u) / u`` the robust weight,
  so ``v* = s psi(v / s)`` in standardised units) -- the right-hand side of the reweighted normal
  equations, the matrix of the unweighted ones. Its fixed point is the same M-estimate.
* ``modified_newton`` (seed 002, the text after eq. 2.14): the reduced camera matrix ``S`` is factorised
  at the first step and kept (:class:`Frozen`); later steps only assemble the right-hand side of the
  reduced system at the current point (the per-point blocks and the Schur terms are recomputed, they
  are cheap and exact) and solve with the kept factor. Convergence becomes linear; a rejected step (the
  cost rose) drops the factor and the next one is built at the current point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from rectify.errors import EstimationError
from stereo.block.bundle import solve as bs

__all__ = ["MODIFIED_RESIDUALS_STAGE_ITERATIONS", "Frozen", "factorise", "modified_residuals", "step"]

F64 = NDArray[np.float64]

#: reweightings per robust stage with the modified residuals: they converge linearly, slowly where the
#: robust weights leave a point few accepted rays (a 32-image block with 3 % blunders: 108 iterations
#: against 22 by reweighting; with the reweighting's 12 per stage, five points went wrong by 15 m)
MODIFIED_RESIDUALS_STAGE_ITERATIONS = 100


@dataclass
class Frozen:
    """A factorised reduced camera system ``S`` (Jacobi-scaled): dense Cholesky, banded Cholesky or sparse LU."""

    kind: str                    # "dense", "banded", "sparse"
    factor: object
    scale: F64                   # (n_c,) 1 / sqrt(diag S)
    order: NDArray[np.int64] | None = None   # banded: the reordered unknowns

    def solve(self, rhs_c: F64) -> F64:
        """xc = S^-1 rhs_c (n_c,)."""
        s = self.scale
        if self.kind == "banded":
            assert self.order is not None
            xo = scipy.linalg.cho_solve_banded(self.factor, (rhs_c * s)[self.order], check_finite=False)
            xc = np.empty_like(xo)
            xc[self.order] = xo
            out = xc * s
        elif self.kind == "sparse":
            out = self.factor.solve(rhs_c * s) * s  # type: ignore[attr-defined]
        else:
            out = scipy.linalg.cho_solve(self.factor, rhs_c * s, check_finite=False) * s
        if not np.isfinite(out).all():
            raise EstimationError("reduced camera system gave a non-finite solution; the datum is not defined")
        return np.asarray(out, dtype=np.float64)


def factorise(ne: bs.Normal, *, blas_threads: int = 1) -> Frozen:
    """Factorise the reduced camera system of ``ne`` (as :func:`stereo.block.bundle.solve.solve_reduced` does)
    and keep the factor."""
    S = ne.S
    dg = S.diagonal() if sp.issparse(S) or isinstance(S, bs.Banded) else np.diag(S)
    if not (dg > 0).all():
        k = int(np.flatnonzero(~(dg > 0))[0])
        raise EstimationError(f"camera-side unknown {k} has no influence on the observations (diagonal {dg[k]!r})")
    s = 1.0 / np.sqrt(dg)
    try:
        if isinstance(S, bs.Banded):
            so = s[S.order]
            b = S.ab.shape[0] - 1
            ab = S.ab * so[None, :]
            for k in range(1, b + 1):
                ab[k, :-k] *= so[k:]
            ab[0] *= so
            cb = scipy.linalg.cholesky_banded(ab, lower=True, overwrite_ab=True, check_finite=False)
            return Frozen("banded", (cb, True), s, S.order)
        if sp.issparse(S):
            try:
                lu = spla.splu(sp.csc_matrix(sp.diags(s) @ S @ sp.diags(s)))
            except RuntimeError as err:
                raise EstimationError(f"reduced camera system is singular ({err}); the datum is not defined") from err
            return Frozen("sparse", lu, s)
        Ss = np.asarray(S, dtype=np.float64) * s[:, None] * s[None, :]
        with bs.blas(blas_threads, len(s)):
            cf = scipy.linalg.cho_factor(Ss, lower=True, overwrite_a=True, check_finite=False)
        return Frozen("dense", cf, s)
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"reduced camera system is not positive definite ({err}); "
                              "the datum is not defined or an image is not determined") from err


def modified_residuals(lin: bs.Linear, robust_w: bs.Weights) -> bs.Linear:
    """The linearisation with the residuals of every group replaced by ``w v`` (seed 002, eq. 2.27)."""
    r = lin.res
    return replace(lin, res=replace(r, image=robust_w.image * r.image, gnss=robust_w.gnss * r.gnss,
                                    ins=robust_w.ins * r.ins, control=robust_w.control * r.control))


def step(prob: bs.Problem, lin: bs.Linear, w: bs.Weights, base: bs.Weights, robust_w: bs.Weights, mu: float, *,
         dense: bool, banded: bool, modified_residuals_: bool, modified_newton: bool, frozen: Frozen | None
         ) -> tuple[F64, F64, float, Frozen | None]:
    """Camera step (n_c,), point step (P, 3), the largest correction in a-priori standard deviations, and the
    kept factor (``modified_newton``; None otherwise).

    Parameters
    ----------
    w : Weights
        The a-priori weights times the robust weights (reweighting).
    base, robust_w : Weights
        The a-priori weights and the robust weights apart (modified residuals).
    frozen : Frozen or None
        The factor kept from an earlier step (``modified_newton``); None builds one.
    """
    if modified_residuals_:
        ne = bs.normal(prob, modified_residuals(lin, robust_w), base, mu, dense=dense, banded=banded)
    else:
        ne = bs.normal(prob, lin, w, mu, dense=dense, banded=banded)
    if modified_newton:
        if frozen is None:
            frozen = factorise(ne, blas_threads=prob.blas_threads)
        xc = frozen.solve(ne.rhs_c)
        xp = bs.back_substitute(ne, xc)
    else:
        xc, xp = bs.solve_reduced(ne, blas_threads=prob.blas_threads)
    nstep = max(float(np.max(np.abs(xc) * np.sqrt(ne.diag_c), initial=0.0)),
                float(np.max(np.abs(xp) * np.sqrt(ne.diag_p), initial=0.0)))
    return xc, xp, nstep, frozen
