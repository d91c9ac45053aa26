"""Polynomial models: 2D polynomials of total degree 1 to 3 (GDAL/QGIS
"polynomial 1/2/3"), fitted by weighted least squares on normalised source
coordinates, with an approximate inverse fitted over the model's domain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.points import as_pair, as_points, as_weights, check_not_collinear
from rectify.geometry.transforms.base import F64, Transform, _check_model_input

__all__ = ["PolynomialTransform"]


#: registry name of a polynomial of each order
_ORDER_METHOD = {1: "affine", 2: "poly2", 3: "poly3"}


def _poly_terms(order: int) -> list[tuple[int, int]]:
    return [(i - j, j) for i in range(order + 1) for j in range(i + 1)]


def _poly_design(pn: F64, order: int) -> F64:
    x, y = pn[:, 0], pn[:, 1]
    return np.column_stack([x ** i * y ** j for i, j in _poly_terms(order)])


@dataclass(frozen=True, eq=False)
class PolynomialTransform(Transform):
    """2D polynomial of total degree ``order`` (GDAL/QGIS "polynomial 2/3").

    ``T(p) = C @ terms((p - shift) * scale)`` with terms ``x^i y^j``,
    ``i + j <= order`` (1, x, y, x^2, xy, y^2, ...), evaluated on normalised
    source coordinates for conditioning.

    Parameters
    ----------
    order : int
        2 or 3 (1 is accepted and equals an affine map).
    coefficients : (2, n_terms) array_like
        Rows for the target x and y.
    shift : (2,) array_like
        Source-coordinate centre subtracted before evaluation.
    scale : float
        Factor applied after the shift.
    domain : (2, 2) array_like
        ``[[xmin, ymin], [xmax, ymax]]`` of the source points of the fit; the
        approximate :attr:`inverse` is fitted over it.
    inverse_rmse, inverse_max_error : float or None
        Set on a model returned by :attr:`inverse`: RMS and largest error of
        the fitted inverse on its fitting grid, source units of the forward
        model (None for a fitted forward model).

    Notes
    -----
    A polynomial has no closed-form inverse. :attr:`inverse` returns a new
    polynomial of the same order fitted, by least squares, to a 41 x 41 grid
    mapped through this one over ``domain``; it is **approximate**: its error
    ``|inverse(T(p)) - p|`` at the grid nodes is at most ``inverse_max_error``
    (RMS ``inverse_rmse``), and between the nodes of ``domain`` it is of the
    same order for a smooth map (the tests check ``inverse(T(p))`` against
    ``p`` at random points of ``domain``). Outside the image of ``domain``
    it is not valid. :attr:`inverse` raises EstimationError when the image
    of ``domain`` is degenerate (e.g. the forward map folds it onto a line).
    """

    order: int
    coefficients: F64
    shift: F64 = field(default_factory=lambda: np.zeros(2))
    scale: float = 1.0
    domain: F64 = field(default_factory=lambda: np.array([[0.0, 0.0], [1.0, 1.0]]))
    inverse_rmse: float | None = None
    inverse_max_error: float | None = None

    def __post_init__(self) -> None:
        if self.order not in (1, 2, 3):
            raise InvalidInputError(f"polynomial order must be 1, 2 or 3; got {self.order!r}")
        nt = len(_poly_terms(self.order))
        c = np.array(self.coefficients, dtype=np.float64, copy=True)
        if c.shape != (2, nt):
            raise ShapeError(f"`coefficients` of an order-{self.order} polynomial must have shape (2, {nt}); "
                             f"got {c.shape}", actual_shape=c.shape, expected_shape=(2, nt))
        if not np.isfinite(c).all():
            raise InvalidInputError("`coefficients` has non-finite entries")
        sh = np.array(self.shift, dtype=np.float64, copy=True).reshape(-1)
        if sh.shape != (2,):
            raise ShapeError(f"`shift` must have shape (2,); got {sh.shape}", actual_shape=sh.shape,
                             expected_shape=(2,))
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise InvalidInputError(f"`scale` must be finite and > 0; got {self.scale!r}")
        dom = np.array(self.domain, dtype=np.float64, copy=True)
        if dom.shape != (2, 2):
            raise ShapeError(f"`domain` must have shape (2, 2); got {dom.shape}", actual_shape=dom.shape,
                             expected_shape=(2, 2))
        for name, a in (("coefficients", c), ("shift", sh), ("domain", dom)):
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        object.__setattr__(self, "scale", float(self.scale))

    @property
    def n_params(self) -> int:
        return 2 * len(_poly_terms(self.order))

    @property
    def min_points(self) -> int:
        return len(_poly_terms(self.order))

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None,
                    order: int = 2) -> PolynomialTransform:
        """Weighted least-squares polynomial fit.

        Parameters
        ----------
        src, dst : (N, 2) array_like
            N >= 6 (order 2) or 10 (order 3) points, in general position.
        weights : (N,) array_like, optional
        order : int
            2 or 3.

        Raises
        ------
        EstimationError
            Too few points, duplicates, or a rank-deficient design (e.g. all
            points on a line or a conic for order 2).
        """
        if order not in (1, 2, 3):
            raise InvalidInputError(f"polynomial order must be 1, 2 or 3; got {order!r}")
        nt = len(_poly_terms(order))
        s, d = _check_model_input(src, dst, nt, f"order-{order} polynomial")
        w = as_weights(weights, len(s))
        check_not_collinear(s, "src")
        shift = s.mean(axis=0)
        rad = float(np.abs(s - shift).max()) or 1.0
        scale = 1.0 / rad
        a = _poly_design((s - shift) * scale, order) * np.sqrt(w)[:, None]
        b = d * np.sqrt(w)[:, None]
        coef, _, rank, sv = np.linalg.lstsq(a, b, rcond=None)
        if rank < nt or sv[-1] <= 1e-10 * sv[0]:
            raise EstimationError(f"order-{order} polynomial fit is rank deficient (rank {rank} of {nt}, "
                                  f"condition {sv[0] / max(sv[-1], 1e-300):.3g}); add better-spread points")
        dom = np.array([s.min(axis=0), s.max(axis=0)])
        return cls(order, coef.T, shift, scale, dom)

    def __call__(self, points: ArrayLike) -> F64:
        p = as_points(points, "points")
        return _poly_design((p - self.shift) * self.scale, self.order) @ self.coefficients.T

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error ``|T(src) - dst|``, (N,), target units."""
        s, d = as_pair(src, dst)
        return np.linalg.norm(self(s) - d, axis=1)

    def to_dict(self) -> dict[str, Any]:
        """``method`` (``poly2``/``poly3``; ``affine`` for order 1), ``direction``, ``order``,
        ``coefficients`` (2, n_terms), ``shift`` (2,), ``scale`` and ``domain`` (2, 2)."""
        return {"method": _ORDER_METHOD[self.order], "direction": "target_from_source", "order": self.order,
                "coefficients": self.coefficients.tolist(), "shift": self.shift.tolist(), "scale": self.scale,
                "domain": self.domain.tolist()}

    @property
    def inverse(self) -> PolynomialTransform:
        """Approximate inverse polynomial, target -> source (see Notes of the class).

        Raises
        ------
        EstimationError
            The image of ``domain`` is degenerate (no unique inverse fit).
        """
        g = np.linspace(0.0, 1.0, 41)
        gx, gy = np.meshgrid(g, g)
        lo, hi = self.domain
        span = np.where(hi > lo, hi - lo, 1.0)
        src = np.column_stack([lo[0] + gx.ravel() * span[0], lo[1] + gy.ravel() * span[1]])
        dst = self(src)
        inv = PolynomialTransform.from_points(dst, src, order=self.order)
        e2 = np.sum((inv(dst) - src) ** 2, axis=1)
        err = float(np.sqrt(np.mean(e2)))
        return PolynomialTransform(inv.order, inv.coefficients, inv.shift, inv.scale, inv.domain,
                                   inverse_rmse=err, inverse_max_error=float(np.sqrt(e2.max())))
