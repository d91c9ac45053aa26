"""M-estimation with the precision of seed 002 (section 2.2, eqs. 2.24-2.29) and the modified Newton-Raphson.

:func:`m_estimate` solves a (linearised) least-squares problem ``l(x) = observed - computed ~ 0`` robustly
and gives the covariance of the M-estimate:

Algorithms (``algorithm``)
    ``"reweighting"`` -- the seed's algorithm (after eq. 2.29): iteration 1 is least squares (P = E);
    every iteration solves the normal equations with the diagonal weights P = psi(u) / u of eq. 2.24,
    takes the residuals, the robust scale (eq. 2.29) and the new weights.
    ``"modified-residuals"`` -- eqs. 2.25-2.27: the observations keep their a-priori weights in the
    normal matrix; the residuals are replaced by the modified residuals ``v* = s psi(v / s)``, the
    step is ``dx = (A^T P A)^-1 A^T P v*``. The normal matrix does not depend on the robust weights:
    for a linear problem it is factorised once.
Newton-Raphson (``newton``)
    ``"full"`` -- the Jacobian, hence the normal matrix, is recomputed at every iteration (quadratic
    convergence near the solution). ``"modified"`` -- the normal matrix is built from the Jacobian at
    the start and not recomputed (seed 002, the text after eq. 2.14: "the matrix of the normal
    equations is inverted only once"); convergence is linear. The right-hand side uses the current
    Jacobian, so the fixed point is the same solution (with the Jacobian frozen in the right-hand side
    too, the solution would move by about ``|dB| |v|``).
Scale (``scale``)
    ``"weighted-median"`` -- the seed's: iteration 1 the median of the absolute non-zero residuals, from
    iteration 2 on the weighted median with the weights of the iteration before
    (:func:`rectify.geometry.robust.weighted_scale`). ``"median"`` -- the unweighted median every
    iteration. Residuals are standardised by their a-priori sigma (``sqrt(prior_weights)``) first.
Covariance
    ``factor * s^2 * (A^T P A)^-1`` with the factor of eq. 2.28
    (:func:`rectify.geometry.robust.m_covariance_factor`), ``A`` the Jacobian at the solution and
    ``P`` the a-priori weights. ``psi="none"`` gives least squares and ``sigma0^2 (A^T P A)^-1``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.lsq import cofactor, standard_errors
from rectify.geometry.robust import PsiFunction, get_psi, m_covariance_factor, robust_scale, weighted_scale

__all__ = ["M_ALGORITHMS", "M_SCALES", "NEWTON_METHODS", "MEstimate", "m_estimate", "m_estimate_linear"]

F64 = NDArray[np.float64]

#: robust algorithms: iteratively reweighted least squares (eq. 2.24) or modified residuals (eqs. 2.25-2.27)
M_ALGORITHMS: tuple[str, ...] = ("reweighting", "modified-residuals")
#: Newton-Raphson: the normal matrix recomputed every iteration, or frozen at the start
NEWTON_METHODS: tuple[str, ...] = ("full", "modified")
#: robust scale from iteration 2 on: weighted median (eq. 2.29 as the seed uses it) or plain median
M_SCALES: tuple[str, ...] = ("weighted-median", "median")


@dataclass(frozen=True, eq=False)
class MEstimate:
    """Result of :func:`m_estimate`.

    Attributes
    ----------
    x : (u,) float64
        The estimate.
    covariance : (u, u) float64
        ``factor * scale^2 * (A^T P A)^-1`` (eq. 2.28).
    std_errors : (u,) float64
    scale : float
        Robust scale s of the standardised residuals (units of ``sqrt(prior_weights) * residual``).
    factor : float
        The eq. 2.28 factor ``K^2 mean(psi^2) / mean(psi')^2`` (n - p in the mean of psi^2).
    residuals : (N,) float64
        ``l(x)`` at the solution (observed minus computed).
    weights : (N,) float64
        Robust weights ``psi(u) / u`` at the solution (1 for least squares).
    iterations : int
    converged : bool
    algorithm, newton, scale_method, psi : str
    normal_factorisations : int
        How often a normal matrix was factorised (the cost the modified Newton-Raphson saves).
    """

    x: F64
    covariance: F64
    std_errors: F64
    scale: float
    factor: float
    residuals: F64
    weights: F64
    iterations: int
    converged: bool
    algorithm: str
    newton: str
    scale_method: str
    psi: str
    normal_factorisations: int


def _factor(N: F64) -> tuple[F64, bool]:
    try:
        return scipy.linalg.cho_factor(N, lower=True, check_finite=False)
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"normal matrix is not positive definite ({err}): the unknowns are not determined "
                              "(or every observation of one was rejected)") from err


def m_estimate(
    residual_fn: Callable[[F64], ArrayLike],
    jacobian_fn: Callable[[F64], ArrayLike],
    x0: ArrayLike,
    *,
    psi: str | PsiFunction = "huber",
    algorithm: str = "reweighting",
    newton: str = "full",
    scale: str = "weighted-median",
    prior_weights: ArrayLike | None = None,
    max_iterations: int = 100,
    tol: float = 1e-8,
) -> MEstimate:
    """Robust (M-) estimation of a nonlinear least-squares problem with its covariance (seed 002, 2.24-2.29).

    Parameters
    ----------
    residual_fn : callable ``x (u,) -> l (N,)``
        Observed minus computed.
    jacobian_fn : callable ``x (u,) -> A (N, u)``
        d(computed)/dx, so that the step of least squares is ``(A^T P A)^-1 A^T P l``.
    x0 : (u,) float64
        Starting values (for a linear problem any, e.g. zeros).
    psi : str or PsiFunction
        ``"huber"``, ``"tukey"``, ``"hampel"``, ``"andrews"`` or ``"none"`` (least squares).
    algorithm : str
        :data:`M_ALGORITHMS`.
    newton : str
        :data:`NEWTON_METHODS`.
    scale : str
        :data:`M_SCALES`.
    prior_weights : (N,) float64, optional
        A-priori weights (1 / sigma^2, relative); 0 excludes an observation.
    max_iterations : int
    tol : float
        Converged when every correction is below ``tol`` times the unknown's a-priori standard
        deviation and the robust weights changed by less than ``sqrt(tol)``.

    Returns
    -------
    MEstimate

    Raises
    ------
    InvalidInputError
        Bad options or shapes; non-finite residuals or Jacobian.
    EstimationError
        Singular normal matrix; no redundancy.
    """
    if algorithm not in M_ALGORITHMS:
        raise InvalidInputError(f"unknown robust algorithm {algorithm!r}; expected one of {list(M_ALGORITHMS)}")
    if newton not in NEWTON_METHODS:
        raise InvalidInputError(f"unknown Newton-Raphson variant {newton!r}; expected one of {list(NEWTON_METHODS)}")
    if scale not in M_SCALES:
        raise InvalidInputError(f"unknown robust scale {scale!r}; expected one of {list(M_SCALES)}")
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
        raise InvalidInputError(f"`max_iterations` must be an integer >= 1; got {max_iterations!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise InvalidInputError(f"`tol` must be a finite number > 0; got {tol!r}")
    ls = isinstance(psi, str) and psi.lower() == "none"
    p = None if ls else get_psi(psi)
    x = np.array(x0, dtype=np.float64).reshape(-1)
    u_n = x.size

    def lvec(xx: F64) -> F64:
        v = np.asarray(residual_fn(xx), dtype=np.float64).reshape(-1)
        if not np.isfinite(v).all():
            raise InvalidInputError("the residuals contain NaN or infinity")
        return v

    def jmat(xx: F64, n: int) -> F64:
        a = np.asarray(jacobian_fn(xx), dtype=np.float64)
        if a.shape != (n, u_n):
            raise ShapeError(f"the Jacobian must have shape ({n}, {u_n}); got {a.shape}", actual_shape=a.shape,
                             expected_shape=(n, u_n))
        if not np.isfinite(a).all():
            raise InvalidInputError("the Jacobian contains NaN or infinity")
        return a

    v = lvec(x)
    n = v.size
    pw = np.ones(n) if prior_weights is None else np.array(prior_weights, dtype=np.float64).reshape(-1)
    if pw.shape != (n,):
        raise ShapeError(f"`prior_weights` must have shape ({n},); got {pw.shape}", actual_shape=pw.shape,
                         expected_shape=(n,))
    if not (np.isfinite(pw).all() and (pw >= 0).all()):
        raise InvalidInputError("`prior_weights` must be finite and >= 0")
    used = pw > 0
    if int(used.sum()) <= u_n:
        raise EstimationError(f"no redundancy: {int(used.sum())} observations for {u_n} unknowns")
    sp_ = np.sqrt(pw)
    w = np.ones(n)              # robust weights
    s = 0.0
    frozen: tuple[F64, bool] | None = None
    factorisations = 0
    converged = False
    it = 0
    A0: F64 | None = None       # the Jacobian the frozen normal matrix was built from
    sd = np.ones(u_n)
    for it in range(1, max_iterations + 1):  # noqa: B007 (read after the loop)
        A = jmat(x, n) * sp_[:, None]
        e = v * sp_
        if ls or it == 1:          # least squares, P = E (iteration 1 of the seed's algorithm)
            g, nw = A.T @ e, None
        elif algorithm == "reweighting":
            g, nw = A.T @ (w * e), w
        else:  # modified residuals v* = s psi(v / s) (eq. 2.27); the a-priori weights in the normal matrix
            assert p is not None
            g, nw = A.T @ (s * p.psi(e / s) if s > 0 else e), None
        if frozen is None or newton == "full" or nw is not None:
            if newton == "full" or A0 is None:
                A0 = A
            N = A0.T @ A0 if nw is None else A0.T @ (A0 * nw[:, None])
            frozen = _factor(N)
            factorisations += 1
            sd = 1.0 / np.sqrt(np.maximum(np.diag(N), 1e-300))
        dx = scipy.linalg.cho_solve(frozen, g, check_finite=False)
        x = x + dx
        v = lvec(x)
        e = v * sp_
        # robust scale (eq. 2.29) and weights (eq. 2.24)
        if ls:
            w_new = np.ones(n)
        else:
            assert p is not None
            if scale == "median" or it == 1:
                s = robust_scale(e, mask=used)
            else:
                s = weighted_scale(e, w, p, mask=used)
            w_new = np.ones(n) if s == 0.0 else p.weight(e / s)
        w_new = np.where(used, w_new, 0.0)
        dw = float(np.max(np.abs(w_new - w)))
        w = w_new
        step = float(np.max(np.abs(dx) / sd))
        if step < tol and (ls or dw < math.sqrt(tol)) and it > 1:
            converged = True
            break
    # precision at the solution (eq. 2.28): the a-priori normal matrix, the factor of the standardised residuals
    A = jmat(x, n) * sp_[:, None]
    e = v * sp_
    if ls:
        s_out, factor = 1.0, m_covariance_factor(e, "none", u_n, mask=used)
        w = np.where(used, 1.0, 0.0)
    else:
        assert p is not None
        s_out = s if s > 0 else robust_scale(e, mask=used)
        if s_out == 0.0:
            factor = 0.0
        else:
            factor = m_covariance_factor(e / s_out, p, u_n, mask=used)
            w = np.where(used, p.weight(e / s_out), 0.0)
    Q = cofactor(A[used].T @ A[used])
    cov = factor * s_out ** 2 * Q
    return MEstimate(x=x, covariance=cov, std_errors=standard_errors(cov), scale=float(s_out), factor=float(factor),
                     residuals=v, weights=w, iterations=it, converged=converged, algorithm=algorithm, newton=newton,
                     scale_method=scale, psi="none" if ls else p.name,  # type: ignore[union-attr]
                     normal_factorisations=factorisations)


def m_estimate_linear(A: ArrayLike, b: ArrayLike, **kwargs: object) -> MEstimate:
    """:func:`m_estimate` of the linear model ``A x ~ b`` (A (N, u), b (N,)), started at x = 0.

    Keyword arguments are those of :func:`m_estimate`. The modified residuals algorithm then factorises
    the normal matrix once (the Newton variant makes no difference for a linear model).
    """
    a = np.array(A, dtype=np.float64, copy=True)
    bb = np.array(b, dtype=np.float64, copy=True).reshape(-1)
    if a.ndim != 2 or a.shape[0] != bb.size:
        raise ShapeError(f"`A` must have shape (N, u) with N = len(b) = {bb.size}; got {a.shape}",
                         actual_shape=a.shape)
    if not (np.isfinite(a).all() and np.isfinite(bb).all()):
        raise InvalidInputError("`A` or `b` has non-finite entries")
    kwargs.setdefault("newton", "modified")
    return m_estimate(lambda x: bb - a @ x, lambda x: a, np.zeros(a.shape[1]), **kwargs)  # type: ignore[arg-type]
