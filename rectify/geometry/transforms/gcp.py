"""GCP fitting, the method registry and the transform parameters as a dict.

:data:`METHODS` (name -> method) is the one list of transform methods: the
CLIs take their choices from it. :func:`fit_gcps` fits a GCP table,
withholding check points; :func:`transform_to_dict` gives the body of the
transform JSON and :func:`transform_from_dict` rebuilds any model from it
(the file itself, with its ``format``/``version`` stamp and residual table,
is read and written by :func:`rectify.formats.transform.read_transform` /
:func:`rectify.formats.transform.write_transform`; see ``docs/formats.md``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.crs import unit_label
from rectify.geometry.points import GcpTable, as_weights
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.transforms.base import F64, Transform
from rectify.geometry.transforms.cotangent import CotangentFourPoint
from rectify.geometry.transforms.matrix import AffineTransform, Homography
from rectify.geometry.transforms.polynomial import PolynomialTransform

logger = logging.getLogger(__name__)

__all__ = ["METHODS", "FitResult", "fit_gcps", "method_of", "transform_to_dict", "transform_from_dict"]

def _poly2(src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None) -> PolynomialTransform:
    return PolynomialTransform.from_points(src, dst, weights=weights, order=2)


def _poly3(src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None) -> PolynomialTransform:
    return PolynomialTransform.from_points(src, dst, weights=weights, order=3)


class _Method:
    """Registry entry: ``METHODS[name].from_points(src, dst, weights=...)``."""

    def __init__(self, name: str, cls: type[Transform], n_params: int, min_points: int,
                 builder: Callable[..., Transform] | None = None):
        self.name, self.cls, self.n_params, self.min_points = name, cls, n_params, min_points
        self._builder = builder or cls.from_points

    def from_points(self, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None) -> Transform:
        return self._builder(src, dst, weights=weights)

    __call__ = from_points

    def __repr__(self) -> str:
        return f"<method {self.name}: {self.cls.__name__}>"


#: name -> method; ``METHODS[name].from_points(src, dst, weights=None)`` builds a model.
METHODS: dict[str, _Method] = {
    "homography": _Method("homography", Homography, 8, 4),
    "cotangent": _Method("cotangent", CotangentFourPoint, 8, 4),
    "affine": _Method("affine", AffineTransform, 6, 3),
    "poly2": _Method("poly2", PolynomialTransform, 12, 6, _poly2),
    "poly3": _Method("poly3", PolynomialTransform, 20, 10, _poly3),
}


def method_of(model: Any) -> str:
    """The registry name of a model instance."""
    if isinstance(model, PolynomialTransform):
        return {1: "affine", 2: "poly2", 3: "poly3"}[model.order]
    for name, m in METHODS.items():
        if type(model) is m.cls:
            return name
    raise InvalidInputError(f"not a known transform: {type(model).__name__}")


def _get_method(method: str) -> _Method:
    try:
        return METHODS[method]
    except KeyError:
        raise InvalidInputError(f"unknown method {method!r}; expected one of {sorted(METHODS)}") from None


# --------------------------------------------------------------------------- GCP fitting
@dataclass(frozen=True, eq=False)
class FitResult:
    """A fitted model and its residual table (fit and check points).

    Attributes
    ----------
    model : the fitted transform (source pixels -> target)
    table : ResidualTable
        One row per GCP; ``check`` marks withheld points; residuals in
        target units.
    method : str
    """

    model: Transform
    table: ResidualTable
    method: str


def _best_quad(s: F64, d: F64) -> NDArray[np.intp]:
    """Indices of the 4 points whose smallest triangle (of the 4) is largest in both planes."""
    n = len(s)
    if n > 40:  # keep it cheap: candidates from the convex-hull-ish extremes
        c = s - s.mean(axis=0)
        dirs = np.array([[1, 0], [0, 1], [1, 1], [1, -1], [-1, 0], [0, -1], [-1, -1], [-1, 1]])
        cand = np.unique(np.concatenate([np.argsort(c @ v)[-3:] for v in dirs]))
    else:
        cand = np.arange(n)
    best, best_idx = -1.0, None

    def tri(p: F64, i: int, j: int, k: int) -> float:
        return abs((p[j, 0] - p[i, 0]) * (p[k, 1] - p[i, 1]) - (p[j, 1] - p[i, 1]) * (p[k, 0] - p[i, 0]))

    ss = max(float(np.ptp(s, axis=0).max()), 1e-300) ** 2
    ds = max(float(np.ptp(d, axis=0).max()), 1e-300) ** 2
    for q in combinations(cand.tolist(), 4):
        m = min(min(tri(s, *t) for t in combinations(q, 3)) / ss,
                min(tri(d, *t) for t in combinations(q, 3)) / ds)
        if m > best:
            best, best_idx = m, q
    return np.array(best_idx)


def fit_gcps(gcps: GcpTable, method: str = "homography", *, weights: ArrayLike | None = None
             ) -> FitResult:
    """Fit a transform (source pixels -> target) to a GCP table.

    Rows with ``check`` set are withheld from the fit and reported as check
    points. The cotangent method uses exactly four control points: with more
    than four fit rows it takes the four spanning the best-conditioned
    quadrilateral and reports the others as check points (logged).

    Parameters
    ----------
    gcps : GcpTable
    method : str
        A key of :data:`METHODS`.
    weights : (N,) array_like, optional
        One weight per row of ``gcps`` (check rows ignored).

    Returns
    -------
    FitResult

    Raises
    ------
    InvalidInputError
        Unknown method, bad weights.
    EstimationError
        Too few fit points or degenerate geometry.
    """
    m = _get_method(method)
    if not isinstance(gcps, GcpTable):
        raise InvalidInputError(f"`gcps` must be a GcpTable; got {type(gcps).__name__}")
    n = len(gcps)
    w_all = as_weights(weights, n)
    check = np.array(gcps.check, dtype=bool, copy=True)
    fit = ~check
    if fit.sum() < m.min_points:
        raise EstimationError(f"too few fit points for {method}: {int(fit.sum())} "
                              f"({int(check.sum())} of {n} rows are check points), at least {m.min_points} needed")
    s, d = gcps.pixel[fit], gcps.target[fit]
    extra: dict[str, Any] = {"method": method}
    if method == "cotangent" and fit.sum() > 4:
        q = _best_quad(s, d)
        fit_idx = np.flatnonzero(fit)[q]
        demoted = np.setdiff1d(np.flatnonzero(fit), fit_idx)
        logger.info("cotangent method: control points %s; %d other fit rows reported as check points",
                    [gcps.ids[i] for i in fit_idx], len(demoted))
        check[demoted] = True
        fit = ~check
        s, d = gcps.pixel[fit], gcps.target[fit]
        extra["control_ids"] = [gcps.ids[i] for i in fit_idx]
    model = m.from_points(s, d, weights=None if weights is None else w_all[fit])
    adjusted = model(gcps.pixel)
    units = "px" if gcps.crs is None else unit_label(gcps.crs)
    table = ResidualTable(step=f"GCP fit ({method})", ids=gcps.ids, observed=gcps.target,
                          adjusted=adjusted, units=units, weights=w_all, check=check,
                          position_px=gcps.pixel, n_params=m.n_params, extra=extra)
    return FitResult(model, table, method)


# --------------------------------------------------------------------------- dict and JSON
def transform_to_dict(model: Transform) -> dict[str, Any]:
    """The parameters of a model of :data:`METHODS` as a JSON-ready dict (:meth:`Transform.to_dict`).

    This is the body of the transform JSON; :func:`rectify.formats.transform.write_transform`
    adds the ``format``/``version`` stamp and the residual table.

    Raises
    ------
    InvalidInputError
        Not a model of :data:`METHODS`.
    """
    method_of(model)
    return model.to_dict()


def transform_from_dict(d: dict[str, Any]) -> Transform:
    """Rebuild a model from :meth:`Transform.to_dict` (or :func:`transform_to_dict`) output.

    Extra keys are ignored. An order-1 polynomial (``method`` ``affine`` with
    ``coefficients`` instead of ``matrix``) is rebuilt as a polynomial.

    Raises
    ------
    InvalidInputError
        Unknown method or missing/malformed parameters.
    """
    if not isinstance(d, dict) or "method" not in d:
        raise InvalidInputError(f"transform JSON must be an object with a 'method'; got {str(d)[:80]!r}")
    name = d["method"]
    _get_method(name)
    poly = name in ("poly2", "poly3") or (name == "affine" and "matrix" not in d and "coefficients" in d)
    need = (("coefficients", "shift", "scale") if poly else
            {"homography": ("matrix",), "affine": ("matrix",), "cotangent": ("src", "dst")}[name])
    missing = [k for k in need if k not in d]
    if missing:
        raise InvalidInputError(f"transform JSON for {name!r} misses key(s) {missing}")
    try:
        if poly:
            order = int(d.get("order", {"affine": 1, "poly2": 2}.get(name, 3)))
            return PolynomialTransform(order, d["coefficients"], d["shift"], float(d["scale"]),
                                       d.get("domain", [[0.0, 0.0], [1.0, 1.0]]))
        if name == "homography":
            return Homography(d["matrix"])
        if name == "affine":
            return AffineTransform(d["matrix"])
        return CotangentFourPoint(d["src"], d["dst"])
    except (TypeError, ValueError) as err:
        if isinstance(err, InvalidInputError):
            raise
        raise InvalidInputError(f"malformed {name!r} transform JSON: {err}") from err
