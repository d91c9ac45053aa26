"""Robust estimation: a generic RANSAC driver and IRLS M-estimation.

Two tools, independent of any particular model:

* :func:`ransac` -- random sample consensus for any model class that has a
  ``from_points(*data)`` classmethod and a ``residuals(*data) -> (N,)``
  method (the :class:`RansacModel` protocol). Minimal samples that cannot be
  estimated raise :class:`~rectify.errors.EstimationError` inside the model and
  are skipped. No consensus raises; the driver never returns ``None``.
* :func:`irls` -- iteratively reweighted least squares with the M-estimators
  of seed 002, section 2.2 (Huber, Tukey, Hampel, Andrews). The caller
  supplies a weighted solver and a residual function, so any least-squares
  estimator becomes robust; :func:`irls_linear` does it for a linear system
  ``A x ~ b``.

Scale
-----
The robust scale is the median of the absolute non-zero residuals divided by
0.6745 (the MAD of a zero-mean normal distribution), recomputed at every
iteration (seed 002, eq. 2.29). From the second iteration on the seed takes the
median with the weights of the previous iteration (found "by dichotomy"):
:func:`weighted_median` and :func:`weighted_scale`, whose divisor is the
weighted median of |u| at the standard normal for the psi function in use
(:func:`weighted_mad_constant`), so that the scale is consistent for normal errors.

Covariance of M-estimates
-------------------------
:func:`m_covariance_factor` is the factor of seed 002 eq. 2.28 (Huber's):
``K^2 [sum psi(u)^2 / (n - p)] / [sum psi'(u) / n]^2`` with
``K = 1 + (p / n) var(psi') / mean(psi')^2``, ``u = v sqrt(p_i) / s``; the
covariance of the estimate is ``factor s^2 (A^T P A)^-1`` (``P`` the a-priori
weights, not the robust ones). For least squares (psi(u) = u) it is
``v^T P v / (n - p) / s^2``: the usual ``sigma0^2``.

Tuning constants
----------------
All constants give 95 % asymptotic efficiency at the normal distribution
(checked numerically by :func:`efficiency` in the tests):
Huber c = 1.345; Tukey biweight c = 4.685; Andrews a = 1.339 (psi zero
beyond a*pi); Hampel (a, b, c) = 0.9014 * (1.5, 3.5, 8) =
(1.352, 3.155, 7.212).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError, ShapeError

logger = logging.getLogger(__name__)

__all__ = [
    "MAD_TO_SIGMA",
    "PSI_FUNCTIONS",
    "ROBUST_METHODS",
    "Andrews",
    "Hampel",
    "Huber",
    "IrlsResult",
    "PsiFunction",
    "RansacModel",
    "RansacResult",
    "Tukey",
    "efficiency",
    "get_psi",
    "irls",
    "irls_linear",
    "m_covariance_factor",
    "psi_covariance_factor",
    "ransac",
    "robust_scale",
    "weighted_mad_constant",
    "weighted_median",
    "weighted_scale",
]

#: median(|e|) / MAD_TO_SIGMA estimates sigma for zero-mean normal errors
MAD_TO_SIGMA = 0.6744897501960817


# ---------------------------------------------------------------- psi functions
class PsiFunction(Protocol):
    """An M-estimator: psi(u) and weight(u) = psi(u) / u on standardised residuals u."""

    @property
    def name(self) -> str: ...

    def psi(self, u: NDArray[np.float64]) -> NDArray[np.float64]: ...

    def weight(self, u: NDArray[np.float64]) -> NDArray[np.float64]: ...

    def dpsi(self, u: NDArray[np.float64]) -> NDArray[np.float64]: ...

    @property
    def rejection_point(self) -> float: ...


@dataclass(frozen=True)
class Huber:
    """Huber's psi: u for |u| <= c, c sign(u) beyond (monotone, never rejects)."""

    c: float = 1.345
    name: str = "huber"

    def psi(self, u):
        return np.clip(np.asarray(u, dtype=np.float64), -self.c, self.c)

    def dpsi(self, u):
        return (np.abs(np.asarray(u, dtype=np.float64)) <= self.c).astype(np.float64)

    def weight(self, u):
        a = np.abs(np.asarray(u, dtype=np.float64))
        with np.errstate(divide="ignore"):
            return np.where(a <= self.c, 1.0, self.c / np.maximum(a, 1e-300))

    @property
    def rejection_point(self) -> float:
        return math.inf


@dataclass(frozen=True)
class Tukey:
    """Tukey's biweight: u (1 - (u/c)^2)^2 for |u| <= c, 0 beyond (redescending)."""

    c: float = 4.685
    name: str = "tukey"

    def psi(self, u):
        u = np.asarray(u, dtype=np.float64)
        return u * self.weight(u)

    def dpsi(self, u):
        t = (np.asarray(u, dtype=np.float64) / self.c) ** 2
        return np.where(t <= 1.0, (1 - t) * (1 - 5 * t), 0.0)

    def weight(self, u):
        t = (np.asarray(u, dtype=np.float64) / self.c) ** 2
        return np.where(t <= 1.0, (1.0 - t) ** 2, 0.0)

    @property
    def rejection_point(self) -> float:
        return self.c


@dataclass(frozen=True)
class Hampel:
    """Hampel's three-part redescending psi with breakpoints a < b < c."""

    a: float = 1.352
    b: float = 3.155
    c: float = 7.212
    name: str = "hampel"

    def psi(self, u):
        u = np.asarray(u, dtype=np.float64)
        x, s = np.abs(u), np.sign(u)
        out = np.where(x <= self.a, u, s * self.a)
        out = np.where((x > self.b) & (x <= self.c), s * self.a * (self.c - x) / (self.c - self.b), out)
        return np.where(x > self.c, 0.0, out)

    def dpsi(self, u):
        x = np.abs(np.asarray(u, dtype=np.float64))
        out = np.where(x <= self.a, 1.0, 0.0)
        return np.where((x > self.b) & (x <= self.c), -self.a / (self.c - self.b), out)

    def weight(self, u):
        u = np.asarray(u, dtype=np.float64)
        x = np.abs(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.abs(self.psi(u)) / np.maximum(x, 1e-300)
        return np.where(x <= self.a, 1.0, w)

    @property
    def rejection_point(self) -> float:
        return self.c


@dataclass(frozen=True)
class Andrews:
    """Andrews' sine: a sin(u/a) for |u| <= a pi, 0 beyond (redescending)."""

    a: float = 1.339
    name: str = "andrews"

    def psi(self, u):
        u = np.asarray(u, dtype=np.float64)
        return np.where(np.abs(u) <= self.a * np.pi, self.a * np.sin(u / self.a), 0.0)

    def dpsi(self, u):
        u = np.asarray(u, dtype=np.float64)
        return np.where(np.abs(u) <= self.a * np.pi, np.cos(u / self.a), 0.0)

    def weight(self, u):
        u = np.asarray(u, dtype=np.float64)
        # sinc(x) = sin(pi x)/(pi x)
        return np.where(np.abs(u) <= self.a * np.pi, np.sinc(u / (self.a * np.pi)), 0.0)

    @property
    def rejection_point(self) -> float:
        return self.a * math.pi


#: name -> psi function with 95 %-efficiency constants (CLI choices come from here)
PSI_FUNCTIONS: dict[str, PsiFunction] = {
    "huber": Huber(), "tukey": Tukey(), "hampel": Hampel(), "andrews": Andrews(),
}

#: the choice list of every ``--robust`` option: "none" (plain least squares) or a psi function
ROBUST_METHODS: tuple[str, ...] = ("none", *PSI_FUNCTIONS)


def get_psi(psi: str | PsiFunction) -> PsiFunction:
    """Look a psi function up by name (or pass an object through).

    Raises
    ------
    InvalidInputError
        For an unknown name.
    """
    if isinstance(psi, str):
        try:
            return PSI_FUNCTIONS[psi.lower()]
        except KeyError:
            raise InvalidInputError(
                f"unknown psi function {psi!r}; expected one of {sorted(PSI_FUNCTIONS)}") from None
    if not all(hasattr(psi, m) for m in ("psi", "weight")):
        raise InvalidInputError(f"`psi` must be a name or have psi() and weight(); got {psi!r}")
    return psi


def efficiency(psi: str | PsiFunction) -> float:
    """Asymptotic efficiency at the standard normal: E[psi']^2 / E[psi^2].

    Computed by numerical integration on a fine grid over [-12, 12].
    """
    p = get_psi(psi)
    u = np.linspace(-12.0, 12.0, 480_001)
    phi = np.exp(-0.5 * u * u) / math.sqrt(2 * math.pi)
    du = u[1] - u[0]
    e_dpsi = float(np.sum(p.dpsi(u) * phi) * du)
    e_psi2 = float(np.sum(p.psi(u) ** 2 * phi) * du)
    return e_dpsi ** 2 / e_psi2


def robust_scale(residuals: ArrayLike, *, mask: ArrayLike | None = None) -> float:
    """Robust standard deviation: median of the absolute non-zero residuals / 0.6745.

    Parameters
    ----------
    residuals : (N,) float64
    mask : (N,) bool, optional
        Only these residuals take part (e.g. RANSAC inliers, positive weights).

    Returns
    -------
    float
        0.0 when every residual is zero (an exact fit).
    """
    r = np.abs(np.asarray(residuals, dtype=np.float64).reshape(-1))
    if mask is not None:
        r = r[np.asarray(mask, dtype=bool).reshape(-1)]
    if not np.isfinite(r).all():
        raise InvalidInputError("residuals contain NaN or infinity; cannot estimate a scale")
    scale_ref = float(r.max()) if r.size else 0.0
    r = r[r > 1e-14 * max(scale_ref, 1e-300)]
    if r.size == 0:
        return 0.0
    return float(np.median(r) / MAD_TO_SIGMA)


def weighted_median(values: ArrayLike, weights: ArrayLike) -> float:
    """Weighted median: the smallest value m with ``sum(w[v <= m]) >= sum(w) / 2``.

    Found by dichotomy (seed 002, the text after eq. 2.29): the interval [min, max] is halved
    until it holds one value; no sort.

    Parameters
    ----------
    values : (N,) float64
    weights : (N,) float64
        Non-negative, not all zero.

    Raises
    ------
    InvalidInputError
        Empty input, shapes that differ, non-finite numbers, a negative weight or only zero weights.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if v.shape != w.shape or v.size == 0:
        raise InvalidInputError(f"weighted median needs values and weights of one non-empty shape; got "
                                f"{v.shape} and {w.shape}")
    if not (np.isfinite(v).all() and np.isfinite(w).all()):
        raise InvalidInputError("weighted median: values or weights contain NaN or infinity")
    if (w < 0).any():
        raise InvalidInputError(f"weighted median: negative weight {float(w[w < 0][0])!r}")
    keep = w > 0
    if not keep.any():
        raise InvalidInputError("weighted median: every weight is zero")
    v, w = v[keep], w[keep]
    half = 0.5 * float(w.sum())
    lo, hi = float(v.min()), float(v.max())
    if float(w[v <= lo].sum()) >= half:
        return lo
    # invariant: W(v <= lo) < half <= W(v <= hi); the answer is the smallest value in (lo, hi]. The values
    # inside the interval are kept apart, so each halving works on fewer of them.
    below = float(w[v <= lo].sum())
    inside = v > lo
    cv, cw = v[inside], w[inside]
    for _ in range(200):
        if cv.size <= 1 or not lo < hi:
            break
        mid = lo + 0.5 * (hi - lo)
        if mid <= lo or mid >= hi:  # adjacent floats
            break
        low = cv <= mid
        wl = float(cw[low].sum())
        if below + wl >= half:
            hi, cv, cw = mid, cv[low], cw[low]
        else:
            lo, below, cv, cw = mid, below + wl, cv[~low], cw[~low]
    return float(cv.min())


_WMAD_CACHE: dict[tuple[str, tuple[float, ...]], float] = {}


def weighted_mad_constant(psi: str | PsiFunction) -> float:
    """The weighted median of |u| with weights ``psi(u) / u`` at the standard normal distribution.

    The divisor that makes :func:`weighted_scale` consistent for normal errors (0.6745, the MAD, for
    equal weights; smaller for down-weighting psi functions). Computed once per psi by numerical
    integration on [0, 12].
    """
    p = get_psi(psi)
    key = (p.name, tuple(float(getattr(p, k)) for k in ("a", "b", "c") if hasattr(p, k)))
    got = _WMAD_CACHE.get(key)
    if got is None:
        u = np.linspace(0.0, 12.0, 240_001)
        dens = p.weight(u) * np.exp(-0.5 * u * u)
        cum = np.cumsum(dens)
        got = float(np.interp(0.5 * cum[-1], cum, u))
        _WMAD_CACHE[key] = got
    return got


def weighted_scale(residuals: ArrayLike, weights: ArrayLike, psi: str | PsiFunction, *,
                   mask: ArrayLike | None = None) -> float:
    """Robust scale from the second iteration on (seed 002, eq. 2.29 with the weights ``P`` of eq. 2.24).

    ``weighted_median(|v|, w) / weighted_mad_constant(psi)`` over the non-zero residuals with positive
    weight, ``w`` the robust weights of the previous iteration (``psi(u) / u``).

    Parameters
    ----------
    residuals : (N,) float64
        Residuals (standardised by their a-priori sigma when the sigmas differ).
    weights : (N,) float64
        Robust weights in [0, 1].
    psi : str or PsiFunction
        The psi function the weights come from.
    mask : (N,) bool, optional
        Only these residuals take part.

    Returns
    -------
    float
        0.0 when every residual is zero.
    """
    r = np.abs(np.asarray(residuals, dtype=np.float64).reshape(-1))
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if r.shape != w.shape:
        raise ShapeError(f"`weights` must have the shape of `residuals` {r.shape}; got {w.shape}",
                         actual_shape=w.shape, expected_shape=r.shape)
    if mask is not None:
        m = np.asarray(mask, dtype=bool).reshape(-1)
        r, w = r[m], w[m]
    if not np.isfinite(r).all():
        raise InvalidInputError("residuals contain NaN or infinity; cannot estimate a scale")
    ref = float(r.max()) if r.size else 0.0
    keep = (r > 1e-14 * max(ref, 1e-300)) & (w > 0)
    if not keep.any():
        return 0.0
    return weighted_median(r[keep], w[keep]) / weighted_mad_constant(psi)


def m_covariance_factor(u: ArrayLike, psi: str | PsiFunction, n_unknowns: int, *,
                        mask: ArrayLike | None = None) -> float:
    """Factor of the covariance of an M-estimate (seed 002, eq. 2.28; Huber 1981, sec. 7.6).

    ``K^2 [sum psi(u)^2 / (n - p)] / [sum psi'(u) / n]^2`` with the correction
    ``K = 1 + (p / n) var(psi'(u)) / mean(psi'(u))^2``; the covariance of the estimate is
    ``factor * s^2 * (A^T P A)^-1`` (``s`` the robust scale, ``u = v sqrt(p_i) / s`` the standardised
    residuals at the solution, ``P`` the a-priori weights).

    Parameters
    ----------
    u : (N,) float64
        Standardised residuals at the solution.
    psi : str or PsiFunction
        ``"none"`` (least squares: psi(u) = u) is accepted too.
    n_unknowns : int
        p, the number of estimated parameters.
    mask : (N,) bool, optional
        The observations that take part (a-priori weight > 0).

    Raises
    ------
    InvalidInputError
        n <= p, non-finite residuals, or a psi whose derivative averages to zero or less
        (a redescending psi with most residuals beyond its rejection point).
    """
    uu = np.asarray(u, dtype=np.float64).reshape(-1)
    if mask is not None:
        uu = uu[np.asarray(mask, dtype=bool).reshape(-1)]
    if not np.isfinite(uu).all():
        raise InvalidInputError("standardised residuals contain NaN or infinity")
    if isinstance(psi, str) and psi.lower() == "none":
        return psi_covariance_factor(uu, np.ones_like(uu), n_unknowns)
    f = get_psi(psi)
    return psi_covariance_factor(f.psi(uu), f.dpsi(uu), n_unknowns, name=f.name)


def psi_covariance_factor(psi_values: ArrayLike, dpsi_values: ArrayLike, n_unknowns: int, *,
                          name: str = "psi") -> float:
    """Eq. 2.28's factor from the values psi(u_i) and psi'(u_i) of every observation (N,) each.

    The form :func:`m_covariance_factor` evaluates; used directly where observation groups differ
    (least-squares groups contribute psi = u, psi' = 1), e.g. by the bundle adjustment.
    """
    ps = np.asarray(psi_values, dtype=np.float64).reshape(-1)
    d = np.asarray(dpsi_values, dtype=np.float64).reshape(-1)
    n, p_ = ps.size, int(n_unknowns)
    if d.shape != ps.shape:
        raise ShapeError(f"psi and psi' values must have one shape; got {ps.shape} and {d.shape}",
                         actual_shape=d.shape, expected_shape=ps.shape)
    if p_ < 0 or n <= p_:
        raise InvalidInputError(f"the M-estimate covariance needs more observations ({n}) than unknowns ({p_})")
    if not (np.isfinite(ps).all() and np.isfinite(d).all()):
        raise InvalidInputError("psi values contain NaN or infinity")
    md = float(np.mean(d))
    if not md > 0:
        raise InvalidInputError(f"the mean derivative of psi ({name}) over the residuals is {md:.3g}: the "
                                "M-estimate has no covariance (most residuals beyond the rejection point)")
    k = 1.0 + (p_ / n) * float(np.var(d)) / md ** 2
    return float(k * k * (np.sum(ps * ps) / (n - p_)) / md ** 2)


# ------------------------------------------------------------------------ IRLS
@dataclass(frozen=True, eq=False)
class IrlsResult:
    """Outcome of :func:`irls`.

    Attributes
    ----------
    model : object
        Whatever the caller's ``fit`` returns, from the last reweighting.
    weights : (N,) float64
        Final robust weights (times the a-priori weights), in [0, 1] for unit a-priori weights.
    residuals : (N,) float64
        Residuals of ``model``.
    scale : float
        Final robust scale (units of the residuals).
    outlier_mask : (N,) bool
        |residual| > ``outlier_threshold`` * scale, or zero weight.
    iterations : int
        Reweightings performed.
    converged : bool
        The weights changed by less than ``tol`` in the last reweighting.
    psi : str
        Name of the psi function.
    """

    model: Any
    weights: NDArray[np.float64]
    residuals: NDArray[np.float64]
    scale: float
    outlier_mask: NDArray[np.bool_]
    iterations: int
    converged: bool
    psi: str


def irls(
    fit: Callable[[NDArray[np.float64], Any], Any],
    residuals: Callable[[Any], NDArray[np.float64]],
    n: int,
    *,
    psi: str | PsiFunction = "huber",
    initial: Any = None,
    prior_weights: ArrayLike | None = None,
    scale: float | None = None,
    min_used: int = 1,
    max_iterations: int = 50,
    tol: float = 1e-6,
    outlier_threshold: float = 3.0,
) -> IrlsResult:
    """Iteratively reweighted least squares (M-estimation, seed 002 section 2.2).

    Parameters
    ----------
    fit : callable ``fit(weights (N,), previous_model) -> model``
        Weighted least-squares solver; ``previous_model`` is ``None`` on the
        first call when no ``initial`` is given (a warm start otherwise). It
        may raise :class:`EstimationError`.
    residuals : callable ``residuals(model) -> (N,)``
        Signed residuals of every observation.
    n : int
        Number of observations N.
    psi : str or PsiFunction
        ``"huber"``, ``"tukey"``, ``"hampel"``, ``"andrews"`` or an object.
    initial : object, optional
        Starting model; when omitted, ``fit`` is called with the a-priori weights.
    prior_weights : (N,) float64, optional
        A-priori weights multiplied into the robust weights (0 excludes a point).
    scale : float, optional
        Fixed scale; by default re-estimated every iteration by :func:`robust_scale`.
    min_used : int
        Fewest observations with positive weight the solver needs.
    max_iterations : int
        Reweighting limit.
    tol : float
        Convergence: largest change of any weight.
    outlier_threshold : float
        Flag |r| > threshold * scale as an outlier.

    Returns
    -------
    IrlsResult

    Raises
    ------
    EstimationError
        When fewer than ``min_used`` observations keep a positive weight.
    InvalidInputError
        For a bad option.

    Examples
    --------
    >>> A = np.column_stack([np.ones(8), np.arange(8.0)])
    >>> b = 2 + 0.5 * np.arange(8.0) + 0.01 * np.array([1, -1, 1, -1, -1, 1, -1, 1])
    >>> b[3] += 40
    >>> res = irls_linear(A, b, psi="tukey")
    >>> np.round(res.model, 2).tolist(), res.outlier_mask.nonzero()[0].tolist()
    ([2.0, 0.5], [3])
    """
    p = get_psi(psi)
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise InvalidInputError(f"`n` must be a positive integer; got {n!r}")
    if max_iterations < 1:
        raise InvalidInputError(f"`max_iterations` must be >= 1; got {max_iterations!r}")
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"`scale` must be finite and > 0; got {scale!r}")
    w0 = np.ones(n) if prior_weights is None else np.array(prior_weights, dtype=np.float64).reshape(-1)
    if w0.shape != (n,):
        raise ShapeError(f"`prior_weights` must have shape ({n},); got {w0.shape}", actual_shape=w0.shape,
                         expected_shape=(n,))
    model = fit(w0.copy(), None) if initial is None else initial
    w = w0.copy()
    converged = False
    s = 0.0
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 (it is read after the loop: iterations done)
        r = np.asarray(residuals(model), dtype=np.float64).reshape(-1)
        s = scale if scale is not None else robust_scale(r, mask=w0 > 0)
        if s == 0.0:  # exact fit: nothing to reweight
            w_new = w0.copy()
        else:
            w_new = w0 * p.weight(r / s)
        used = int(np.count_nonzero(w_new > 0))
        if used < min_used:
            raise EstimationError(
                f"robust estimation ({p.name}) left {used} observation(s) with positive weight; "
                f"at least {min_used} needed (scale {s:.4g})")
        change = float(np.max(np.abs(w_new - w)))
        w = w_new
        model = fit(w.copy(), model)
        if change < tol:
            converged = True
            break
    r = np.asarray(residuals(model), dtype=np.float64).reshape(-1)
    s_final = scale if scale is not None else robust_scale(r, mask=w0 > 0)
    if s_final > 0:
        w = w0 * p.weight(r / s_final)
        outl = (np.abs(r) > outlier_threshold * s_final) | (w <= 0)
    else:
        outl = w0 <= 0
    if not converged:
        logger.info("IRLS (%s) stopped after %d reweightings without converging", p.name, it)
    return IrlsResult(model=model, weights=w, residuals=r, scale=float(s_final), outlier_mask=outl,
                      iterations=it, converged=converged, psi=p.name)


def irls_linear(
    A: ArrayLike, b: ArrayLike, *, psi: str | PsiFunction = "huber", prior_weights: ArrayLike | None = None,
    max_iterations: int = 50, tol: float = 1e-6, outlier_threshold: float = 3.0,
) -> IrlsResult:
    """Robust solution of the linear system ``A x ~ b`` by :func:`irls`.

    Parameters
    ----------
    A : (N, M) float64
    b : (N,) float64

    Returns
    -------
    IrlsResult
        ``model`` is x, shape (M,).

    Raises
    ------
    EstimationError
        If the weighted system becomes rank deficient.
    """
    A = np.array(A, dtype=np.float64, copy=True)
    b = np.array(b, dtype=np.float64, copy=True).reshape(-1)
    if A.ndim != 2 or A.shape[0] != b.shape[0]:
        raise ShapeError(f"`A` must have shape (N, M) with N = len(b) = {b.shape[0]}; got {A.shape}",
                         actual_shape=A.shape)
    if not (np.isfinite(A).all() and np.isfinite(b).all()):
        raise InvalidInputError("`A` or `b` has non-finite entries")
    m = A.shape[1]

    def fit(w, _prev):
        sw = np.sqrt(w)
        x, _, rank, _ = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)
        if rank < m:
            raise EstimationError(f"weighted system is rank deficient (rank {rank} < {m})")
        return x

    return irls(fit, lambda x: A @ x - b, A.shape[0], psi=psi, prior_weights=prior_weights, min_used=m,
                max_iterations=max_iterations, tol=tol, outlier_threshold=outlier_threshold)


# ---------------------------------------------------------------------- RANSAC
class RansacModel(Protocol):
    """What :func:`ransac` needs from a model class."""

    @classmethod
    def from_points(cls, *data: NDArray[np.float64]) -> RansacModel: ...

    def residuals(self, *data: NDArray[np.float64]) -> NDArray[np.float64]: ...


@dataclass(frozen=True, eq=False)
class RansacResult:
    """Outcome of :func:`ransac`.

    Attributes
    ----------
    model : object
        Refitted on all inliers of the best sample.
    inlier_mask : (N,) bool
    n_trials : int
        Minimal samples drawn.
    """

    model: Any
    inlier_mask: NDArray[np.bool_]
    n_trials: int

    @property
    def n_inliers(self) -> int:
        return int(self.inlier_mask.sum())


def _as_data(data: Any) -> tuple[NDArray[np.float64], ...]:
    arrs = tuple(np.asarray(d) for d in (data if isinstance(data, (tuple, list)) else (data,)))
    if not arrs:
        raise InvalidInputError("`data` is empty")
    n = arrs[0].shape[0] if arrs[0].ndim else 0
    for i, a in enumerate(arrs):
        if a.ndim == 0 or a.shape[0] != n:
            raise ShapeError(f"every array of `data` must have the same first dimension {n}; "
                             f"array {i} has shape {a.shape}", actual_shape=a.shape)
    return arrs


def ransac(
    data: NDArray[np.float64] | Sequence[NDArray[np.float64]],
    model_cls: Any,
    *,
    min_samples: int,
    residual_threshold_px: float,
    max_trials: int = 1000,
    confidence: float = 0.999,
    rng: np.random.Generator | int | None = None,
) -> RansacResult:
    """Random sample consensus for any model with ``from_points`` and ``residuals``.

    Parameters
    ----------
    data : (N, ...) array or sequence of (N, ...) arrays
        Passed (row-subset) as positional arguments to ``model_cls.from_points``
        and to ``model.residuals``.
    model_cls : type
        Satisfies :class:`RansacModel`; ``from_points`` raises
        :class:`EstimationError` for a degenerate sample (it is skipped).
    min_samples : int
        Size of a minimal sample.
    residual_threshold_px : float
        Inlier if residual < threshold (units of the model's residuals,
        normally pixels).
    max_trials : int
        Upper bound on samples; fewer are drawn once ``confidence`` is reached.
    confidence : float
        Probability in (0, 1) of drawing at least one outlier-free sample.
    rng : Generator, int or None
        Through :func:`numpy.random.default_rng`.

    Returns
    -------
    RansacResult

    Raises
    ------
    EstimationError
        When N < ``min_samples`` or no sample reaches a consensus of
        ``min_samples`` inliers.
    InvalidInputError
        For bad options.
    """
    arrs = _as_data(data)
    n = arrs[0].shape[0]
    if not isinstance(min_samples, (int, np.integer)) or min_samples < 1:
        raise InvalidInputError(f"`min_samples` must be a positive integer; got {min_samples!r}")
    if not (math.isfinite(residual_threshold_px) and residual_threshold_px > 0):
        raise InvalidInputError(f"`residual_threshold_px` must be finite and > 0; got {residual_threshold_px!r}")
    if not 0 < confidence < 1:
        raise InvalidInputError(f"`confidence` must lie in (0, 1); got {confidence!r}")
    if max_trials < 1:
        raise InvalidInputError(f"`max_trials` must be >= 1; got {max_trials!r}")
    if n < min_samples:
        raise EstimationError(f"too few points for RANSAC: {n} given, at least {min_samples} needed")
    gen = np.random.default_rng(rng)
    best_count, best_cost, best_mask = -1, math.inf, None
    needed = max_trials
    trials = 0
    while trials < min(needed, max_trials):
        trials += 1
        idx = gen.choice(n, min_samples, replace=False)
        try:
            model = model_cls.from_points(*(a[idx] for a in arrs))
            res = np.asarray(model.residuals(*arrs), dtype=np.float64).reshape(-1)
        except EstimationError:
            continue
        res = np.where(np.isfinite(res), res, np.inf)
        mask = res < residual_threshold_px
        count = int(mask.sum())
        cost = float(np.sum(np.minimum(res, residual_threshold_px) ** 2))
        if count > best_count or (count == best_count and cost < best_cost):
            best_count, best_cost, best_mask = count, cost, mask
            ratio = count / n
            if ratio >= 1.0:
                needed = trials
            elif ratio > 0:
                denom = math.log(max(1e-300, 1.0 - ratio ** min_samples))
                needed = int(math.ceil(math.log(1 - confidence) / denom)) if denom < 0 else max_trials
    if best_mask is None or best_count < min_samples:
        raise EstimationError(
            f"RANSAC found no consensus: best sample had {max(best_count, 0)} inlier(s) below "
            f"{residual_threshold_px} after {trials} trials; at least {min_samples} needed")
    try:
        model = model_cls.from_points(*(a[best_mask] for a in arrs))
        res = np.asarray(model.residuals(*arrs), dtype=np.float64).reshape(-1)
        mask = np.isfinite(res) & (res < residual_threshold_px)
        if mask.sum() >= min_samples and not np.array_equal(mask, best_mask):
            model = model_cls.from_points(*(a[mask] for a in arrs))
        else:
            mask = best_mask
    except EstimationError as err:
        raise EstimationError(f"RANSAC refit on {best_count} inliers failed: {err}") from err
    logger.debug("RANSAC: %d/%d inliers after %d trials", int(mask.sum()), n, trials)
    return RansacResult(model=model, inlier_mask=mask, n_trials=trials)
