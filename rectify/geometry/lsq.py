"""Least-squares helpers shared by the estimators: normal equations, sigma0, covariance, correlation.

The estimators (relative and absolute orientation, resection, the GCP fits) solve their own
linearised problems; what they share is the precision stage, written once here:

- :func:`normal_equations`: N = A^T P A and n = A^T P l for a design matrix A (m, u), weights P
  (diagonal (m,) or none) and misclosures l (m,);
- :func:`condition_numbers`: the condition number of N and of N with its columns scaled to a unit
  diagonal (the correlation structure; it does not depend on the units of the unknowns);
- :func:`sigma0`: the a-posteriori standard deviation of unit weight sqrt(v^T P v / r) with the
  redundancy r = n - u named by the caller, ``None`` without redundancy;
- :func:`cofactor`: Q = N^-1 (an :class:`~rectify.errors.EstimationError` when N is singular);
- :func:`standard_errors` and :func:`correlation` of a covariance matrix sigma0^2 Q.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError

__all__ = ["condition_numbers", "correlation", "cofactor", "normal_equations", "sigma0", "standard_errors"]


def normal_equations(A: ArrayLike, l: ArrayLike | None = None, weights: ArrayLike | None = None  # noqa: E741
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Normal matrix N = A^T P A (u, u) and right-hand side A^T P l (u,) (``None`` without ``l``).

    Parameters
    ----------
    A : (m, u) array_like
        Design matrix (partial derivatives of the m observations by the u unknowns).
    l : (m,) array_like, optional
        Misclosures (observed minus computed).
    weights : (m,) array_like, optional
        Diagonal weights P (default 1).
    """
    a = np.asarray(A, dtype=np.float64)
    if a.ndim != 2:
        raise InvalidInputError(f"design matrix must be 2-D (m, u); got shape {a.shape}")
    aw = a if weights is None else a * np.asarray(weights, dtype=np.float64).reshape(-1, 1)
    N = aw.T @ a
    rhs = None if l is None else aw.T @ np.asarray(l, dtype=np.float64).reshape(-1)
    return N, rhs


def condition_numbers(N: ArrayLike) -> tuple[float, float]:
    """(condition number of N with columns scaled to a unit diagonal, condition number of N).

    Raises
    ------
    EstimationError
        When a diagonal element is not positive (an unknown without influence).
    """
    n = np.asarray(N, dtype=np.float64)
    d = np.sqrt(np.diag(n))
    if not (d > 0).all():
        raise EstimationError("degenerate configuration: an unknown has no influence on the observations")
    return float(np.linalg.cond(n / np.outer(d, d))), float(np.linalg.cond(n))


def sigma0(vtpv: float, redundancy: int) -> float | None:
    """A-posteriori standard deviation of unit weight sqrt(v^T P v / r); ``None`` when r <= 0.

    Parameters
    ----------
    vtpv : float
        Weighted sum of squared residuals v^T P v.
    redundancy : int
        r = number of observations (with positive weight) minus number of unknowns.
    """
    if redundancy <= 0:
        return None
    return float(math.sqrt(float(vtpv) / redundancy))


def cofactor(N: ArrayLike) -> NDArray[np.float64]:
    """Q = N^-1, the cofactor matrix of the unknowns (their covariance is sigma0^2 Q).

    Raises
    ------
    EstimationError
        When N is singular.
    """
    try:
        return np.linalg.inv(np.asarray(N, dtype=np.float64))
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"singular normal equations: {err}") from err


def standard_errors(covariance: ArrayLike) -> NDArray[np.float64]:
    """Square roots of the diagonal of a covariance matrix (u,)."""
    return np.sqrt(np.diag(np.asarray(covariance, dtype=np.float64)))


def correlation(covariance: ArrayLike) -> NDArray[np.float64]:
    """Correlation matrix C_ij / (s_i s_j) (u, u); NaN where a standard error is 0."""
    c = np.asarray(covariance, dtype=np.float64)
    s = np.sqrt(np.diag(c))
    with np.errstate(divide="ignore", invalid="ignore"):
        return c / np.outer(s, s)
