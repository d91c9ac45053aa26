"""Planar transforms for 2D rectification: projective, cotangent four-point,
affine and polynomial models, with one interface.

Every model maps **source** points to **target** points, both (N, 2) float64
arrays in the project's frames (source: pixel frame, x = column right,
y = row down, pixel centres at integers; target: target pixels or map
coordinates). All models share the interface of STYLE.md #6:

- ``Model.from_points(src, dst, *, weights=None)`` builds a new, immutable
  model (raises :class:`~rectify.errors.EstimationError` on degenerate data,
  :class:`~rectify.errors.InvalidInputError` on malformed data);
- ``model(points)`` maps (N, 2) -> (N, 2);
- ``model.inverse`` returns a new model for the opposite direction;
- ``model.residuals(src, dst)`` returns the (N,) **transfer error**
  ``|model(src) - dst|`` in target units;
- ``model.matrix`` (3, 3) where meaningful (homography, affine), and ``@``
  composition ``(a @ b)(p) == a(b(p))`` for matrix models.

The registry :data:`METHODS` (name -> class) drives dispatch and the CLI;
:func:`fit_gcps` fits a GCP table withholding check points;
:func:`save_transform` / :func:`load_transform` read and write the transform
JSON of DESIGN.md.

The cotangent four-point method (seed 001, eq. 2)
-------------------------------------------------
V. I. Kushtin's method maps a point without solving a linear system. Take
two control points a, b as the *base*. A point p defines the signed
cotangents of the angles at a and b between the base and the rays to p,

    cot B = (d . (p - a)) / (d x (p - a)),
    cot G = ((a - b) . (p - b)) / (d x (p - b)),      d = b - a,

where ``u . v`` is the dot and ``u x v = u_x v_y - u_y v_x`` the 2D cross
product. Each cotangent is an affine coordinate on the pencil of lines
through its vertex, with the base line at infinity. A projective map sends
the pencil at a to the pencil at a0 and the base line to the base line, so
it acts *affinely* on the cotangent: the cross-ratio of the four rays
(base, to c, to e, to p) is the ratio of cotangent differences

    (cot B_p - cot B_c) / (cot B_e - cot B_c),

and it is invariant. With the two remaining control points c, e this carries
the cotangents from the source to the target plane,

    cot B0_p = cot B0_c + (cot B_p - cot B_c) (cot B0_e - cot B0_c) / (cot B_e - cot B_c),

(likewise for G), and eq. (2) intersects the two rays in the target plane:

    x0 = xa0 + ((xb0 - xa0) cot B0 - (yb0 - ya0)) / (cot B0 + cot G0)
    y0 = ya0 + ((yb0 - ya0) cot B0 + (xb0 - xa0)) / (cot B0 + cot G0)

**Sign correction.** Seed 001 prints the y-line with ``- (x2 - x1)``. That is
inconsistent: the offset ``(-(y2-y1), -(x2-x1))`` is not perpendicular to the
base, so the printed formula misplaces every point not on the base line
(checked numerically against the homography in
``tests/rectify/test_projective.py::test_printed_eq2_is_wrong``). The
corrected y-line has ``+ (x2 - x1)``. The formula then holds in any
rectangular frame with the *signed* cotangents above (cross product
``x_u y_v - y_u x_v`` of that frame's axes): with positive angles it
describes a point that lies on the side of the base reached by turning the
base direction from the x axis towards the y axis, i.e. to the **right** of
a -> b in the pixel frame (x right, y down) and in the geodetic frame
(x north, y east), to the left in a mathematical frame (x right, y up).

Eq. (2) is singular for points on or near the base line (cot B -> inf).
For every point, :class:`CotangentFourPoint` uses, among the six pairs of
control points, the base pair whose source triangle (a, b, p) has the
largest relative height ``|h| / b = |sin B sin G / sin(B + G)|`` (distance
of p from the base line over the base length; eq. (2) divides by it), and
raises only when no pair reaches :data:`COT_MIN_REL_HEIGHT`. The whole
computation is vectorised in blocks of points: choose the pair (one small
matrix product and a 6-way tournament), gather the pair's 13 constants,
then cotangents, carriage and eq. (2) -- about 30 floating-point operations
per point and no linear system.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import EstimationError, InvalidInputError, RasterIOError, ShapeError
from .fileutil import atomic_write_text
from .points import (as_pair, as_points, as_weights, check_distinct, check_min_points,
                     check_no_three_collinear, check_not_collinear)
from .residuals import ResidualTable
from .tables import GcpTable

logger = logging.getLogger(__name__)

__all__ = [
    "Transform2D", "Homography", "AffineTransform", "PolynomialTransform", "CotangentFourPoint",
    "METHODS", "N_PARAMS", "FitResult", "fit_gcps", "transform_to_dict", "transform_from_dict",
    "save_transform", "load_transform", "COT_MIN_REL_HEIGHT", "PAIRS", "TRANSFORM_FORMAT_VERSION",
    "method_of", "base_cotangents", "printed_eq2", "corrected_eq2",
]

#: Smallest acceptable relative height |h| / b (distance of the point from the
#: base line over the base length) of the best base pair of the cotangent
#: method; below it a point is reported as unmappable.
COT_MIN_REL_HEIGHT = 1e-12

#: Version of the transform JSON written by :func:`save_transform`.
TRANSFORM_FORMAT_VERSION = 1

F64 = NDArray[np.float64]

_CHUNK = 1 << 15  # points per block: keeps the temporaries in cache


@runtime_checkable
class Transform2D(Protocol):
    """What every planar model offers (and what RANSAC needs)."""

    def __call__(self, points: ArrayLike) -> F64: ...

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64: ...


# --------------------------------------------------------------------------- helpers
def _frozen(a: ArrayLike) -> F64:
    m = np.array(a, dtype=np.float64, copy=True)
    m.flags.writeable = False
    return m


def _normalising_similarity(pts: F64, w: F64 | None = None) -> F64:
    """Hartley normalisation: (3, 3) T with T p centred, mean distance sqrt(2)."""
    if w is None:
        c = pts.mean(axis=0)
    else:
        c = (w[:, None] * pts).sum(axis=0) / w.sum()
    d = np.linalg.norm(pts - c, axis=1).mean()
    s = math.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _apply_h(m: F64, pts: F64) -> F64:
    """Apply a (3, 3) homography to validated (N, 2) points, in cache-sized blocks."""
    out = np.empty_like(pts)
    a = m[:2, :2].T.copy()
    t = m[:2, 2].copy()
    h = m[2, :2].copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        for s0 in range(0, len(pts), _CHUNK):
            pc = pts[s0:s0 + _CHUNK]
            w = pc @ h
            w += m[2, 2]
            np.divide(1.0, w, out=w)
            o = out[s0:s0 + _CHUNK]
            np.matmul(pc, a, out=o)
            o += t
            o *= w[:, None]
    return out


def _check_model_input(src: ArrayLike, dst: ArrayLike, n_min: int, what: str
                       ) -> tuple[F64, F64]:
    s, d = as_pair(src, dst)
    check_min_points(s, n_min, f"control points for the {what}")
    check_distinct(s, "src")
    check_distinct(d, "dst")
    return s, d


# --------------------------------------------------------------------------- matrix models
@dataclass(frozen=True, eq=False)
class _MatrixTransform:
    """Common part of the (3, 3) matrix models."""

    matrix: F64

    def __post_init__(self) -> None:
        m = np.array(self.matrix, dtype=np.float64, copy=True)
        if m.shape != (3, 3):
            raise ShapeError(f"`matrix` must have shape (3, 3); got {m.shape}", actual_shape=m.shape,
                             expected_shape=(3, 3))
        if not np.isfinite(m).all():
            raise InvalidInputError(f"`matrix` has non-finite entries: {m.tolist()}")
        # scale-invariant singularity test: rows and columns equilibrated first (map
        # coordinates make the translation column 1e6 times larger than the rest)
        e = np.abs(m)
        r = e.max(axis=1, keepdims=True)
        eq = m / np.where(r > 0, r, 1.0)
        c = np.abs(eq).max(axis=0, keepdims=True)
        eq = eq / np.where(c > 0, c, 1.0)
        det = np.linalg.det(eq)
        if not (r > 0).all() or abs(det) <= 1e-13:
            raise EstimationError(f"`matrix` is singular (equilibrated det = {det:.3g}): {m.tolist()}")
        self._validate_matrix(m)
        m.flags.writeable = False
        object.__setattr__(self, "matrix", m)

    def _validate_matrix(self, m: F64) -> None:  # overridden by AffineTransform
        return None

    def __array__(self, dtype=None, copy=None) -> F64:
        return np.array(self.matrix, dtype=dtype)

    def __call__(self, points: ArrayLike) -> F64:
        """Map (N, 2) source points to (N, 2) target points.

        Points on the vanishing line of a homography map to inf/NaN.
        """
        return _apply_h(self.matrix, as_points(points, "points"))

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error ``|T(src) - dst|``, (N,), target units."""
        s, d = as_pair(src, dst)
        return np.linalg.norm(_apply_h(self.matrix, s) - d, axis=1)

    def __matmul__(self, other: Any) -> "_MatrixTransform":
        if not isinstance(other, _MatrixTransform):
            return NotImplemented
        m = self.matrix @ other.matrix
        if isinstance(self, AffineTransform) and isinstance(other, AffineTransform):
            return AffineTransform(m)
        return Homography(m / m[2, 2] if abs(m[2, 2]) > 1e-300 else m)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(matrix={np.array2string(self.matrix, precision=6)})"


@dataclass(frozen=True, eq=False, repr=False)
class Homography(_MatrixTransform):
    """Planar projective map (8 parameters), source -> target.

    Parameters
    ----------
    matrix : (3, 3) array_like
        Acts on homogeneous source points (x, y, 1); the target point is
        ``(m @ p)[:2] / (m @ p)[2]``. Scale is irrelevant; non-singular.

    Examples
    --------
    >>> src = [[0, 0], [100, 0], [100, 80], [0, 80]]
    >>> dst = [[10, 12], [215, 5], [190, 170], [3, 160]]
    >>> H = Homography.from_points(src, dst)
    >>> np.allclose(H(src), dst), np.allclose(H.inverse(H(src)), src)
    (True, True)
    >>> Homography.from_points(src[:3], dst[:3])
    Traceback (most recent call last):
    ...
    rectify.errors.EstimationError: too few control points for the homography: 3 given, at least 4 needed
    """

    n_params: ClassVar[int] = 8
    min_points: ClassVar[int] = 4

    @classmethod
    def identity(cls) -> "Homography":
        return cls(np.eye(3))

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None,
                    refine: bool = True) -> "Homography":
        """Estimate the homography mapping ``src`` onto ``dst``.

        Parameters
        ----------
        src, dst : (N, 2) array_like
            Corresponding source and target points, N >= 4.
        weights : (N,) array_like, optional
            Non-negative weights (1 / variance of the target coordinates).
        refine : bool
            For N > 4, refine the normalised-DLT solution by minimising the
            weighted transfer error sum(w |H(src) - dst|^2) (Levenberg-Marquardt).

        Returns
        -------
        Homography
            Exact for 4 points (no three collinear).

        Raises
        ------
        EstimationError
            Fewer than 4 points, duplicates, three collinear points (N = 4),
            all points collinear or otherwise no unique solution.
        InvalidInputError
            NaN/inf, wrong shapes, bad weights.
        """
        s, d = _check_model_input(src, dst, 4, "homography")
        w = as_weights(weights, len(s))
        used = w > 0
        if used.sum() < 4:
            raise EstimationError(f"too few control points with non-zero weight: {int(used.sum())}, "
                                  "at least 4 needed")
        s_u, d_u, w_u = s[used], d[used], w[used]
        if len(s_u) == 4:
            check_no_three_collinear(s_u, "src")
            check_no_three_collinear(d_u, "dst")
        else:
            check_not_collinear(s_u, "src")
            check_not_collinear(d_u, "dst")
        m = _dlt(s_u, d_u, w_u)
        if refine and len(s_u) > 4:
            m = _refine_transfer(m, s_u, d_u, w_u)
        return cls(m / m[2, 2] if abs(m[2, 2]) > 1e-12 * np.abs(m).max() else m / np.abs(m).max())

    @property
    def inverse(self) -> "Homography":
        """The target -> source homography (exact)."""
        m = np.linalg.inv(self.matrix)
        return Homography(m / m[2, 2] if abs(m[2, 2]) > 1e-12 * np.abs(m).max() else m)


def _dlt(s: F64, d: F64, w: F64) -> F64:
    """Weighted normalised DLT (Hartley & Zisserman, alg. 4.2)."""
    ts, td = _normalising_similarity(s), _normalising_similarity(d)
    sn = s @ ts[:2, :2].T + ts[:2, 2]
    dn = d @ td[:2, :2].T + td[:2, 2]
    n = len(s)
    x, y, u, v = sn[:, 0], sn[:, 1], dn[:, 0], dn[:, 1]
    o, z = np.ones(n), np.zeros(n)
    a = np.empty((2 * n, 9))
    a[0::2] = np.stack([x, y, o, z, z, z, -u * x, -u * y, -u], axis=1)
    a[1::2] = np.stack([z, z, z, x, y, o, -v * x, -v * y, -v], axis=1)
    sw = np.sqrt(np.repeat(w, 2))
    a *= sw[:, None]
    _, sv, vt = np.linalg.svd(a)
    if len(sv) >= 9 and sv[7] <= 1e-10 * sv[0]:
        raise EstimationError(f"no unique homography: the points are degenerate (singular values "
                              f"{sv[6:].round(12).tolist()} relative to {sv[0]:.3g})")
    hn = vt[-1].reshape(3, 3)
    det = np.linalg.det(hn)  # normalised coordinates: well scaled, |hn| = 1
    if abs(det) < 1e-12:
        raise EstimationError(f"the estimated homography is singular (det {det:.3g} in normalised "
                              "coordinates): the points are degenerate")
    return np.linalg.inv(td) @ hn @ ts


def _refine_transfer(m0: F64, s: F64, d: F64, w: F64) -> F64:
    """Minimise sum w |H(s) - d|^2 over the 8 degrees of freedom of H."""
    from scipy.optimize import least_squares

    ts, td = _normalising_similarity(s), _normalising_similarity(d)
    sn = s @ ts[:2, :2].T + ts[:2, 2]
    dn = d @ td[:2, :2].T + td[:2, 2]
    hn = td @ m0 @ np.linalg.inv(ts)
    hn = hn / np.linalg.norm(hn)
    fix = int(np.argmax(np.abs(hn.ravel())))
    free = [k for k in range(9) if k != fix]
    sw = np.sqrt(w)
    x, y = sn[:, 0], sn[:, 1]

    def unpack(p: F64) -> F64:
        h = hn.ravel().copy()
        h[free] = p
        return h

    def fun(p: F64) -> F64:
        h = unpack(p)
        ww = h[6] * x + h[7] * y + h[8]
        r = np.empty((len(x), 2))
        r[:, 0] = (h[0] * x + h[1] * y + h[2]) / ww - dn[:, 0]
        r[:, 1] = (h[3] * x + h[4] * y + h[5]) / ww - dn[:, 1]
        return (r * sw[:, None]).ravel()

    def jac(p: F64) -> F64:
        h = unpack(p)
        ww = h[6] * x + h[7] * y + h[8]
        uu = (h[0] * x + h[1] * y + h[2]) / ww
        vv = (h[3] * x + h[4] * y + h[5]) / ww
        o, z = np.ones_like(x), np.zeros_like(x)
        ju = np.stack([x, y, o, z, z, z, -x * uu, -y * uu, -uu], axis=1) / ww[:, None]
        jv = np.stack([z, z, z, x, y, o, -x * vv, -y * vv, -vv], axis=1) / ww[:, None]
        j = np.empty((2 * len(x), 9))
        j[0::2], j[1::2] = ju * sw[:, None], jv * sw[:, None]
        return j[:, free]

    p0 = hn.ravel()[free]
    res = least_squares(fun, p0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        max_nfev=200)
    hr = unpack(res.x).reshape(3, 3)
    if not np.isfinite(hr).all():
        logger.warning("homography refinement diverged; keeping the DLT solution")
        return m0
    return np.linalg.inv(td) @ hr @ ts


@dataclass(frozen=True, eq=False, repr=False)
class AffineTransform(_MatrixTransform):
    """Affine map (6 parameters), source -> target; last matrix row (0, 0, 1).

    Examples
    --------
    >>> A = AffineTransform.from_points([[0, 0], [1, 0], [0, 1]], [[1, 1], [3, 1], [1, 4]])
    >>> A.matrix.round(12).tolist()
    [[2.0, 0.0, 1.0], [0.0, 3.0, 1.0], [0.0, 0.0, 1.0]]
    """

    n_params: ClassVar[int] = 6
    min_points: ClassVar[int] = 3

    def _validate_matrix(self, m: F64) -> None:
        if not np.allclose(m[2], [0.0, 0.0, 1.0], rtol=0, atol=1e-12):
            raise InvalidInputError(f"an affine matrix must end with the row (0, 0, 1); got {m[2].tolist()}")

    @classmethod
    def identity(cls) -> "AffineTransform":
        return cls(np.eye(3))

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None
                    ) -> "AffineTransform":
        """Weighted least-squares affine fit (exact for 3 non-collinear points).

        Raises
        ------
        EstimationError
            Fewer than 3 points, duplicates, collinear points.
        """
        s, d = _check_model_input(src, dst, 3, "affine transform")
        w = as_weights(weights, len(s))
        check_not_collinear(s[w > 0] if (w > 0).sum() >= 3 else s, "src")
        ts = _normalising_similarity(s)
        sn = s @ ts[:2, :2].T + ts[:2, 2]
        a = np.column_stack([sn, np.ones(len(s))]) * np.sqrt(w)[:, None]
        b = d * np.sqrt(w)[:, None]
        coef, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
        if rank < 3:
            raise EstimationError(f"affine fit is rank deficient (rank {rank}): points {s.tolist()}")
        m = np.eye(3)
        m[:2, :] = coef.T
        m = m @ ts
        m[2] = (0.0, 0.0, 1.0)
        return cls(m)

    @property
    def inverse(self) -> "AffineTransform":
        m = np.linalg.inv(self.matrix)
        m[2] = (0.0, 0.0, 1.0)
        return AffineTransform(m)


# --------------------------------------------------------------------------- polynomials
def _poly_terms(order: int) -> list[tuple[int, int]]:
    return [(i - j, j) for i in range(order + 1) for j in range(i + 1)]


def _poly_design(pn: F64, order: int) -> F64:
    x, y = pn[:, 0], pn[:, 1]
    return np.column_stack([x ** i * y ** j for i, j in _poly_terms(order)])


@dataclass(frozen=True, eq=False)
class PolynomialTransform:
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

    Notes
    -----
    A polynomial has no closed-form inverse. :attr:`inverse` returns a new
    polynomial of the same order fitted, by least squares, to a 41 x 41 grid
    mapped through this one over ``domain``; it is **approximate** (its error
    is reported in ``inverse_rmse``, target -> source units) and only valid
    near the image of ``domain``.
    """

    order: int
    coefficients: F64
    shift: F64 = field(default_factory=lambda: np.zeros(2))
    scale: float = 1.0
    domain: F64 = field(default_factory=lambda: np.array([[0.0, 0.0], [1.0, 1.0]]))
    inverse_rmse: float | None = None

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
                    order: int = 2) -> "PolynomialTransform":
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

    @classmethod
    def order2(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None
               ) -> "PolynomialTransform":
        return cls.from_points(src, dst, weights=weights, order=2)

    @classmethod
    def order3(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None
               ) -> "PolynomialTransform":
        return cls.from_points(src, dst, weights=weights, order=3)

    def __call__(self, points: ArrayLike) -> F64:
        p = as_points(points, "points")
        return _poly_design((p - self.shift) * self.scale, self.order) @ self.coefficients.T

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error ``|T(src) - dst|``, (N,), target units."""
        s, d = as_pair(src, dst)
        return np.linalg.norm(self(s) - d, axis=1)

    @property
    def inverse(self) -> "PolynomialTransform":
        """Approximate inverse polynomial (see Notes of the class)."""
        g = np.linspace(0.0, 1.0, 41)
        gx, gy = np.meshgrid(g, g)
        lo, hi = self.domain
        span = np.where(hi > lo, hi - lo, 1.0)
        src = np.column_stack([lo[0] + gx.ravel() * span[0], lo[1] + gy.ravel() * span[1]])
        dst = self(src)
        inv = PolynomialTransform.from_points(dst, src, order=self.order)
        err = float(np.sqrt(np.mean(np.sum((inv(dst) - src) ** 2, axis=1))))
        return PolynomialTransform(inv.order, inv.coefficients, inv.shift, inv.scale, inv.domain,
                                   inverse_rmse=err)


# --------------------------------------------------------------------------- cotangent method
_PAIRS: tuple[tuple[int, int, int, int], ...] = tuple(
    (a, b, *[k for k in range(4) if k not in (a, b)]) for a, b in combinations(range(4), 2))

#: The six base pairs (a, b) of the cotangent method, as indices of the control points.
PAIRS: tuple[tuple[int, int], ...] = tuple((a, b) for a, b, _, _ in _PAIRS)


_CONST_NAMES = ("dx", "dy", "e1", "e2", "b2", "kB", "mB", "kG", "mG", "xa0", "ya0", "dx0", "dy0")


def _cot_tables(src: F64, dst: F64) -> dict[str, Any]:
    """Per-base-pair constants of the cotangent method.

    Source coordinates are taken relative to ``centre`` (the centroid of the
    four source control points) for numerical range. For base pair
    k = (a, b) with carriers (c, e), d = b - a:

    - ``cross(d, p - a) = dx*y - dy*x + e1`` and ``dot(d, p - a) = dx*x + dy*y + e2``;
      ``dot(a - b, p - b) = b2 - dot(d, p - a)`` with ``b2 = |d|^2``, so
      ``cot B = dot / cross`` and ``cot G = (b2 - dot) / cross``;
    - the carriage ``cot0 = k * cot + m`` for B and G (through c and e);
    - the target base ``xa0, ya0, dx0, dy0`` for eq. (2);
    - ``sel_w`` (6, 2) and ``sel_c`` (6,): ``cross / b2`` as an affine form,
      the signed relative height h / b of the triangle (a, b, p), in float32
      (only used to choose the pair).
    """
    centre = src.mean(axis=0)
    sc = src - centre
    consts = []
    for a, b, c, e in _PAIRS:
        pa, pb = sc[a], sc[b]
        dx, dy = pb - pa
        b2 = dx * dx + dy * dy
        e1 = dy * pa[0] - dx * pa[1]
        e2 = -(dx * pa[0] + dy * pa[1])
        cot = {}
        for j in (c, e):
            cr = dx * sc[j, 1] - dy * sc[j, 0] + e1
            da = dx * sc[j, 0] + dy * sc[j, 1] + e2
            d0 = dst[b] - dst[a]
            q0 = dst[j] - dst[a]
            cr0 = d0[0] * q0[1] - d0[1] * q0[0]
            da0 = d0[0] * q0[0] + d0[1] * q0[1]
            b20 = d0[0] ** 2 + d0[1] ** 2
            cot[j] = (da / cr, (b2 - da) / cr, da0 / cr0, (b20 - da0) / cr0)
        (bc, gc, bc0, gc0), (be, ge, be0, ge0) = cot[c], cot[e]
        # cot0 = cot0_c + (cot - cot_c) (cot0_e - cot0_c) / (cot_e - cot_c)  ==  k cot + m
        kb = (be0 - bc0) / (be - bc)
        kg = (ge0 - gc0) / (ge - gc)
        consts.append((dx, dy, e1, e2, b2, kb, bc0 - kb * bc, kg, gc0 - kg * gc, dst[a, 0], dst[a, 1],
                       dst[b, 0] - dst[a, 0], dst[b, 1] - dst[a, 1]))
    arr = np.array(consts, dtype=np.float64)  # (6, 13)
    dx, dy, e1, b2 = arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 4]
    return {
        "centre": centre,
        "consts": tuple(tuple(float(v) for v in row) for row in arr),
        "packed": arr,
        "sel_w": np.column_stack([-dy / b2, dx / b2]).astype(np.float32),
        "sel_c": (e1 / b2).astype(np.float32),
    }


_ROWS = np.arange(len(_PAIRS), dtype=np.int32)[:, None]


def _select_pairs(x: F64, y: F64, t: dict[str, Any]) -> NDArray[np.int32]:
    """Per point, the index of the pair with the largest relative height |h| / b.

    ``x, y`` (n,) are centred source coordinates. The six |h| / b are
    evaluated in float32 (a (6, 2) @ (2, n) product); the pair index is
    stored in the 3 lowest mantissa bits of each value, so one integer
    maximum over the six rows yields the argmax (values are >= 0, whose
    float32 bit patterns order like the values; the 3 bits change them by
    < 1e-6 relative, irrelevant for choosing).
    """
    p32 = np.empty((2, len(x)), dtype=np.float32)
    p32[0] = x
    p32[1] = y
    sel = t["sel_w"] @ p32
    sel += t["sel_c"][:, None]
    np.abs(sel, out=sel)
    v = sel.view(np.int32)
    v &= ~7
    v |= _ROWS
    best = v.max(axis=0)
    best &= 7
    return best


@dataclass(frozen=True, eq=False)
class CotangentFourPoint:
    """Kushtin's cotangent four-point method (seed 001, corrected eq. 2).

    Maps source points to target points through four control points, no
    three collinear, by carrying the cotangents of the base angles through
    the cross-ratio of the pencil of rays (see the module docstring). It is
    the same projective map as :class:`Homography` fitted to the four points,
    computed without a linear system.

    Parameters
    ----------
    src, dst : (4, 2) array_like
        The control points in the source and the target plane.

    Examples
    --------
    >>> src = [[0, 0], [100, 0], [100, 80], [0, 80]]
    >>> dst = [[10, 12], [215, 5], [190, 170], [3, 160]]
    >>> C = CotangentFourPoint.from_points(src, dst)
    >>> p = [[50, 40], [0, 40], [120, -30]]
    >>> np.allclose(C(p), Homography.from_points(src, dst)(p))
    True
    """

    src: F64
    dst: F64
    _tables: dict[str, Any] = field(init=False, repr=False, compare=False)

    n_params: ClassVar[int] = 8
    min_points: ClassVar[int] = 4

    def __post_init__(self) -> None:
        s, d = as_pair(self.src, self.dst)
        if len(s) != 4:
            raise EstimationError(f"the cotangent method needs exactly 4 control points; got {len(s)}")
        check_distinct(s, "src")
        check_distinct(d, "dst")
        check_no_three_collinear(s, "src")
        check_no_three_collinear(d, "dst")
        tabs = _cot_tables(s, d)
        if not np.isfinite(tabs["packed"]).all():
            raise EstimationError(f"cotangent carriage is undefined for control points src={s.tolist()} "
                                  f"dst={d.tolist()}")
        for name, a in (("src", s), ("dst", d)):
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        for a in tabs.values():
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
        object.__setattr__(self, "_tables", tabs)

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None
                    ) -> "CotangentFourPoint":
        """Build the method from exactly four control points.

        ``weights`` is accepted for interface compatibility; four points
        determine the map exactly, so weights other than all-positive are
        rejected.

        Raises
        ------
        EstimationError
            Not exactly 4 points, duplicates, three collinear points.
        """
        s, d = as_pair(src, dst)
        if weights is not None:
            w = as_weights(weights, len(s))
            if (w <= 0).any():
                raise EstimationError("the cotangent method uses all four points; zero weights given: "
                                      f"{w.tolist()}")
        if len(s) < 4:
            raise EstimationError(f"too few control points for the cotangent method: {len(s)} given, "
                                  "exactly 4 needed")
        return cls(s, d)

    @property
    def inverse(self) -> "CotangentFourPoint":
        """The same method with the roles of the planes swapped (target -> source)."""
        return CotangentFourPoint(self.dst, self.src)

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error ``|T(src) - dst|``, (N,), target units."""
        s, d = as_pair(src, dst)
        return np.linalg.norm(self._map(s) - d, axis=1)

    def __call__(self, points: ArrayLike) -> F64:
        """Map (N, 2) source points to (N, 2) target points.

        Points on the vanishing line (mapped to infinity) give inf/NaN, as
        with :class:`Homography`.

        Raises
        ------
        EstimationError
            If some point has no base pair with ``|h| / b >=
            COT_MIN_REL_HEIGHT`` (cannot happen for finite points and four control
            points in general position; kept as a guard).
        """
        return self._map(as_points(points, "points"))

    def base_pairs(self, points: ArrayLike) -> tuple[NDArray[np.intp], F64]:
        """The base pair chosen for each point and its conditioning.

        Parameters
        ----------
        points : (N, 2) array_like
            Source points.

        Returns
        -------
        pair : (N,) int
            Index into :data:`PAIRS`, the six pairs ``(0,1), (0,2), (0,3),
            (1,2), (1,3), (2,3)`` of control points.
        rel_height : (N,) float
            ``|h| / b`` of the triangle (a, b, p) of the chosen pair:
            distance of the point from the base line over the base length,
            ``|sin B sin G / sin(B + G)|``. Eq. (2) is singular where it is 0.
        """
        p = as_points(points, "points")
        t = self._tables
        x = p[:, 0] - t["centre"][0]
        y = p[:, 1] - t["centre"][1]
        k = _select_pairs(x, y, t).astype(np.intp)
        c = t["packed"][k]
        rel = np.abs(c[:, 0] * y - c[:, 1] * x + c[:, 2]) / c[:, 4]
        return k, rel

    def _map(self, p: F64) -> F64:
        out = np.empty_like(p)
        for s0 in range(0, len(p), _CHUNK):
            self._map_block(p[s0:s0 + _CHUNK], out[s0:s0 + _CHUNK])
        return out

    def _map_block(self, pc: F64, out: F64) -> None:
        """Eq. (2) with carried cotangents on one block; writes ``out`` (n, 2).

        Points are grouped by their chosen base pair, so every group is
        computed with scalar constants.
        """
        t = self._tables
        x = pc[:, 0] - t["centre"][0]
        y = pc[:, 1] - t["centre"][1]
        k = _select_pairs(x, y, t)
        ox = np.empty_like(x)
        oy = np.empty_like(y)
        single = None
        for j, (dx, dy, e1, e2, b2, kb, mb, kg, mg, xa0, ya0, dx0, dy0) in enumerate(t["consts"]):
            if single is None:
                idx = np.flatnonzero(k == j)
                if idx.size == 0:
                    continue
                if idx.size == len(x):
                    single = True
                    xs, ys = x, y
                else:
                    xs, ys = x[idx], y[idx]
            else:
                break
            # signed cotangents of the base angles in the source plane
            cr = dx * ys
            cr -= dy * xs
            cr += e1                                   # cross(d, p - a) = b * h
            worst = float(np.abs(cr).min())
            if worst < COT_MIN_REL_HEIGHT * b2:
                i = int(np.argmin(np.abs(cr)))
                raise EstimationError(
                    f"point {[xs[i] + t['centre'][0], ys[i] + t['centre'][1]]} has no well-conditioned "
                    f"base pair: largest relative height |h|/b = {worst / b2:.3g} < {COT_MIN_REL_HEIGHT}")
            da = dx * xs
            da += dy * ys
            da += e2                                   # dot(d, p - a)
            inv_cr = 1.0 / cr
            cot_b = da * inv_cr                        # cot B
            cot_g = b2 - da
            cot_g *= inv_cr                            # cot G
            # carriage through the cross-ratio of the pencil (affine in the cotangent)
            cot_b *= kb
            cot_b += mb                                # cot B0
            cot_g *= kg
            cot_g += mg                                # cot G0
            # eq. (2), corrected y-line
            with np.errstate(divide="ignore", invalid="ignore"):
                inv_s = 1.0 / (cot_b + cot_g)
            gx = dx0 * cot_b
            gx -= dy0
            gx *= inv_s
            gx += xa0
            gy = dy0 * cot_b
            gy += dx0
            gy *= inv_s
            gy += ya0
            if single:
                ox, oy = gx, gy
            else:
                ox[idx] = gx
                oy[idx] = gy
        out[:, 0] = ox
        out[:, 1] = oy

    def to_homography(self) -> Homography:
        """The equivalent :class:`Homography` (exact fit to the four points)."""
        return Homography.from_points(self.src, self.dst)


def printed_eq2(p1: ArrayLike, p2: ArrayLike, cot_b: ArrayLike, cot_g: ArrayLike) -> F64:
    """Seed 001's eq. (2) **as printed** (with the sign error), for the record.

    Returns (N, 2). Used by the tests and the study to show the inconsistency;
    the corrected formula is what :class:`CotangentFourPoint` uses.
    """
    x1, y1 = np.asarray(p1, dtype=float)
    x2, y2 = np.asarray(p2, dtype=float)
    cb, cg = np.asarray(cot_b, dtype=float), np.asarray(cot_g, dtype=float)
    s = cb + cg
    return np.column_stack([x1 + ((x2 - x1) * cb - (y2 - y1)) / s, y1 + ((y2 - y1) * cb - (x2 - x1)) / s])


def corrected_eq2(p1: ArrayLike, p2: ArrayLike, cot_b: ArrayLike, cot_g: ArrayLike) -> F64:
    """Seed 001's eq. (2) with the corrected sign in the y-line, (N, 2)."""
    x1, y1 = np.asarray(p1, dtype=float)
    x2, y2 = np.asarray(p2, dtype=float)
    cb, cg = np.asarray(cot_b, dtype=float), np.asarray(cot_g, dtype=float)
    s = cb + cg
    return np.column_stack([x1 + ((x2 - x1) * cb - (y2 - y1)) / s, y1 + ((y2 - y1) * cb + (x2 - x1)) / s])


def base_cotangents(p1: ArrayLike, p2: ArrayLike, points: ArrayLike) -> tuple[F64, F64]:
    """Signed cotangents (cot B, cot G) of the base angles at p1 and p2, (N,) each."""
    a, b = np.asarray(p1, dtype=float), np.asarray(p2, dtype=float)
    p = as_points(points, "points")
    d = b - a
    cr = d[0] * (p[:, 1] - a[1]) - d[1] * (p[:, 0] - a[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        cb = (d[0] * (p[:, 0] - a[0]) + d[1] * (p[:, 1] - a[1])) / cr
        cg = (-d[0] * (p[:, 0] - b[0]) - d[1] * (p[:, 1] - b[1])) / cr
    return cb, cg


# --------------------------------------------------------------------------- registry
def _poly2(src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None) -> PolynomialTransform:
    return PolynomialTransform.from_points(src, dst, weights=weights, order=2)


def _poly3(src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None) -> PolynomialTransform:
    return PolynomialTransform.from_points(src, dst, weights=weights, order=3)


class _Method:
    """Registry entry: ``METHODS[name].from_points(src, dst, weights=...)``."""

    def __init__(self, name: str, cls: type, n_params: int, min_points: int, builder=None):
        self.name, self.cls, self.n_params, self.min_points = name, cls, n_params, min_points
        self._builder = builder or cls.from_points

    def from_points(self, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None):
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

#: name -> number of parameters (for redundancy / sigma0)
N_PARAMS: dict[str, int] = {k: m.n_params for k, m in METHODS.items()}


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

    model: Any
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
    units = "px" if gcps.crs is None else "map units"
    table = ResidualTable(step=f"GCP fit ({method})", ids=gcps.ids, observed=gcps.target,
                          adjusted=adjusted, units=units, weights=w_all, check=check,
                          position_px=gcps.pixel, n_params=m.n_params, extra=extra)
    return FitResult(model, table, method)


# --------------------------------------------------------------------------- JSON
def transform_to_dict(model: Any) -> dict[str, Any]:
    """The parameters of a model as a JSON-ready dict (``method`` + parameters)."""
    name = method_of(model)
    out: dict[str, Any] = {"format": "rectify-transform", "version": TRANSFORM_FORMAT_VERSION,
                           "method": name, "direction": "target_from_source"}
    if isinstance(model, _MatrixTransform):
        out["matrix"] = model.matrix.tolist()
    elif isinstance(model, CotangentFourPoint):
        out["src"] = model.src.tolist()
        out["dst"] = model.dst.tolist()
    elif isinstance(model, PolynomialTransform):
        out.update(order=model.order, coefficients=model.coefficients.tolist(), shift=model.shift.tolist(),
                   scale=model.scale, domain=model.domain.tolist())
    return out


def transform_from_dict(d: dict[str, Any]) -> Any:
    """Rebuild a model from :func:`transform_to_dict` output (extra keys ignored).

    Raises
    ------
    InvalidInputError
        Unknown method or missing/malformed parameters.
    """
    if not isinstance(d, dict) or "method" not in d:
        raise InvalidInputError(f"transform JSON must be an object with a 'method'; got {str(d)[:80]!r}")
    name = d["method"]
    _get_method(name)
    need = {"homography": ("matrix",), "affine": ("matrix",), "cotangent": ("src", "dst"),
            "poly2": ("coefficients", "shift", "scale"), "poly3": ("coefficients", "shift", "scale")}[name]
    missing = [k for k in need if k not in d]
    if missing:
        raise InvalidInputError(f"transform JSON for {name!r} misses key(s) {missing}")
    try:
        if name == "homography":
            return Homography(d["matrix"])
        if name == "affine":
            return AffineTransform(d["matrix"])
        if name == "cotangent":
            return CotangentFourPoint(d["src"], d["dst"])
        order = int(d.get("order", 2 if name == "poly2" else 3))
        return PolynomialTransform(order, d["coefficients"], d["shift"], float(d["scale"]),
                                   d.get("domain", [[0.0, 0.0], [1.0, 1.0]]))
    except (TypeError, ValueError) as err:
        if isinstance(err, InvalidInputError):
            raise
        raise InvalidInputError(f"malformed {name!r} transform JSON: {err}") from err


def save_transform(path: str | Path, model: Any, *, table: ResidualTable | None = None,
                   crs: str | None = None, overwrite: bool = False, extra: dict | None = None) -> Path:
    """Write the transform JSON of DESIGN.md atomically.

    Keys: ``method``, the parameters (:func:`transform_to_dict`), ``crs`` of
    the target (when known), and, with ``table``, ``rmse``,
    ``rmse_check``, ``summary`` and ``residuals`` (one object per GCP).
    """
    out = transform_to_dict(model)
    if crs:
        out["crs"] = crs
    if table is not None:
        s = table.summary()
        out["rmse"] = s["rmse"]
        out["rmse_check"] = s["rmse_check"]
        out["units"] = table.units
        out["summary"] = {k: v for k, v in s.items() if _jsonable(v)}
        res = table.residual
        out["residuals"] = [
            {"id": table.ids[i], "observed": table.observed[i].tolist(), "adjusted": table.adjusted[i].tolist(),
             "dx": float(res[i, 0]), "dy": float(res[i, 1]), "norm": float(table.norm[i]),
             "check": bool(table.check[i])} for i in range(table.n)]
    if extra:
        out.update(extra)
    text = json.dumps(out, indent=2, allow_nan=True) + "\n"
    return atomic_write_text(path, text, overwrite=overwrite)


def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except (TypeError, ValueError):
        return False


def load_transform(path: str | Path) -> Any:
    """Read a transform JSON written by :func:`save_transform` (or ``rectify fit``).

    Raises
    ------
    RasterIOError
        File missing or unreadable.
    InvalidInputError
        Not JSON, or not a valid transform.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError as err:
        raise RasterIOError(f"transform file not found: {str(p)!r}") from err
    except OSError as err:
        raise RasterIOError(f"cannot read {str(p)!r}: {err}") from err
    try:
        d = json.loads(text)
    except json.JSONDecodeError as err:
        raise InvalidInputError(f"{str(p)!r} is not valid JSON: {err}") from err
    return transform_from_dict(d)
