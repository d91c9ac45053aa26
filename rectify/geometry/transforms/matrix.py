"""Matrix models: the 8-parameter :class:`Homography` and the 6-parameter
:class:`AffineTransform`, both a (3, 3) matrix acting on homogeneous source
points; ``@`` composes them, ``(a @ b)(p) == a(b(p))``.

The homography is estimated by the weighted normalised DLT and, for more
than four points, refined by minimising the weighted transfer error; the
affine map by weighted linear least squares on normalised coordinates.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.points import as_pair, as_points, as_weights, check_no_three_collinear, check_not_collinear
from rectify.geometry.transforms.base import _CHUNK, F64, Transform, _check_model_input, _normalising_similarity

logger = logging.getLogger(__name__)

__all__ = ["Homography", "AffineTransform"]


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



@dataclass(frozen=True, eq=False)
class _MatrixTransform(Transform):
    """Common part of the (3, 3) matrix models."""

    matrix: F64

    #: registry name of the model (a key of :data:`rectify.geometry.transforms.METHODS`)
    method: ClassVar[str]

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

    def __matmul__(self, other: Any) -> _MatrixTransform:
        if not isinstance(other, _MatrixTransform):
            return NotImplemented
        m = self.matrix @ other.matrix
        if isinstance(self, AffineTransform) and isinstance(other, AffineTransform):
            return AffineTransform(m)
        return Homography(m / m[2, 2] if abs(m[2, 2]) > 1e-300 else m)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(matrix={np.array2string(self.matrix, precision=6)})"

    def to_dict(self) -> dict[str, Any]:
        """``{"method", "direction": "target_from_source", "matrix": (3, 3) nested list}``."""
        return {"method": self.method, "direction": "target_from_source", "matrix": self.matrix.tolist()}


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

    method: ClassVar[str] = "homography"
    n_params: ClassVar[int] = 8
    min_points: ClassVar[int] = 4

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None,
                    refine: bool = True) -> Homography:
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
    def inverse(self) -> Homography:
        """The target -> source homography (exact)."""
        m = np.asarray(np.linalg.inv(self.matrix), dtype=np.float64)
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
    # local import: scipy.optimize takes about 1 s to import and only the refinement needs it
    # (the CLIs import this module for the list of methods)
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

    method: ClassVar[str] = "affine"
    n_params: ClassVar[int] = 6
    min_points: ClassVar[int] = 3

    def _validate_matrix(self, m: F64) -> None:
        if not np.allclose(m[2], [0.0, 0.0, 1.0], rtol=0, atol=1e-12):
            raise InvalidInputError(f"an affine matrix must end with the row (0, 0, 1); got {m[2].tolist()}")

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None
                    ) -> AffineTransform:
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
    def inverse(self) -> AffineTransform:
        """The target -> source affine map (exact)."""
        m = np.asarray(np.linalg.inv(self.matrix), dtype=np.float64)
        m[2] = (0.0, 0.0, 1.0)
        return AffineTransform(m)
