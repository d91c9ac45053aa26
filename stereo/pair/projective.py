"""Projective pair geometry: the fundamental matrix, projective cameras and models, 3D affine and
projective transformations (seed 003, sections 3.2.2 and 3.3.1-3.3.2).

Frames and conventions
----------------------
- Image points are pixel coordinates (N, 2), x = column right, y = row down; their homogeneous
  form is (x, y, 1).
- The fundamental matrix F (3, 3, rank 2, Frobenius norm 1) maps a left point to its epipolar line
  in the right image: ``x_right^T F x_left = 0``.
- Projective cameras are (3, 4) matrices mapping homogeneous model points X (4,) to homogeneous
  pixels; the canonical pair of a fundamental matrix is ``P1 = [I | 0]``,
  ``P2 = [[e']x F | e']`` with ``e'`` the right epipole (``F^T e' = 0``). The model they form is
  the true scene up to an unknown 3D projective transformation (15 parameters), which
  :class:`Projective3D` recovers from control points (seed 003, 3.3.2).
- :class:`Affine3D` (12 parameters, seed 003, 3.3.1) orients a model that is already affine or
  similar (e.g. formed with a camera whose interior orientation is approximate).

Residuals are ``v = adjusted - observed`` in the units of the observations (pixels for the
fundamental matrix, object units for the 3D transformations), as everywhere in the project.

The fundamental matrix itself is estimated in :mod:`stereo.relative.projective` (relative orientation
uses it, and ``relative`` ranks below ``pair``); its names are re-exported here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry import lsq
from rectify.geometry.points import as_pair, as_points, as_weights
from stereo.relative.projective import (
    MIN_POINTS_F,
    FundamentalFit,
    epipoles,
    fundamental_from_points,
    normaliser,
    sampson_distances,
    skew,
)

__all__ = [
    "MIN_POINTS_F", "MIN_CONTROL_AFFINE", "MIN_CONTROL_PROJECTIVE", "FundamentalFit", "Affine3D",
    "Projective3D", "fundamental_from_points", "cameras_from_fundamental", "triangulate_projective",
    "sampson_distances", "epipoles", "skew",
]

#: control points needed by the 3D affine transformation (12 parameters, 4 non-coplanar points)
MIN_CONTROL_AFFINE = 4
#: control points needed by the 3D projective transformation (15 parameters, 5 in general position)
MIN_CONTROL_PROJECTIVE = 5
#: smallest relative singular value of the point spread before the points count as one plane
_PLANAR_RTOL = 1e-6


def cameras_from_fundamental(F: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Canonical projective cameras (3, 4) of a fundamental matrix: ``P1 = [I | 0]``,
    ``P2 = [[e']x F | e']`` (Hartley and Zisserman, result 9.14), e' the unit right epipole.

    Raises
    ------
    EstimationError
        If F is not (numerically) of rank 2.
    """
    Fm = np.asarray(F, dtype=np.float64)
    if Fm.shape != (3, 3) or not np.isfinite(Fm).all():
        raise ShapeError(f"F must be a finite (3, 3) matrix; got shape {Fm.shape}", actual_shape=Fm.shape)
    s = np.linalg.svd(Fm, compute_uv=False)
    if s[0] == 0 or s[1] / s[0] < 1e-12 or s[2] / s[0] > 1e-6:
        raise EstimationError(f"F must have rank 2; singular values {s.tolist()}")
    _, e2 = epipoles(Fm)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([skew(e2) @ Fm, e2.reshape(3, 1)])
    return P1, P2


def triangulate_projective(cameras: Sequence[ArrayLike], points: Sequence[ArrayLike]) -> NDArray[np.float64]:
    """Linear (DLT) intersection of rays from any number of projective cameras.

    Parameters
    ----------
    cameras : sequence of K (3, 4) array_like
        Projective cameras, homogeneous model point -> homogeneous pixel.
    points : sequence of K (N, 2) array_like
        Pixel coordinates of the same N points in each camera; NaN rows mark points a camera does
        not see.

    Returns
    -------
    (N, 4) float64
        Homogeneous model points of unit norm, sign with the last coordinate >= 0; NaN rows for
        points seen by fewer than two cameras. Each camera's rows are scaled by its pixel spread so
        that the solution does not depend on the pixel origin's distance.
    """
    if len(cameras) != len(points) or len(cameras) < 2:
        raise InvalidInputError(f"need matching lists of at least 2 cameras and point arrays; got "
                                f"{len(cameras)} cameras and {len(points)} point arrays")
    Ps = []
    for k, P in enumerate(cameras):
        m = np.asarray(P, dtype=np.float64)
        if m.shape != (3, 4) or not np.isfinite(m).all():
            raise ShapeError(f"camera {k} must be a finite (3, 4) matrix; got shape {m.shape}",
                             actual_shape=m.shape)
        Ps.append(m)
    pts = []
    for k, p in enumerate(points):
        q = np.array(p, dtype=np.float64, copy=True)
        if q.ndim != 2 or q.shape[1] != 2:
            raise ShapeError(f"points of camera {k} must have shape (N, 2); got {q.shape}", actual_shape=q.shape)
        pts.append(q)
    n = len(pts[0])
    if any(len(q) != n for q in pts):
        raise ShapeError(f"every camera needs the same N points (NaN where unseen); got {[len(q) for q in pts]}")
    # conditioning: per camera, a similarity taking its observed pixels to unit spread
    Ts = []
    for q in pts:
        fin = np.isfinite(q).all(axis=1)
        Ts.append(normaliser(q[fin]) if int(np.sum(fin)) >= 2 else np.eye(3))
    CP = [T @ P for T, P in zip(Ts, Ps, strict=True)]
    # all points at once: (N, 2K, 4) rows, zero for an unseen point (a zero row leaves the null space alone)
    rows = np.zeros((n, 2 * len(CP), 4))
    seen = np.zeros(n, dtype=int)
    for k, (q, T, P) in enumerate(zip(pts, Ts, CP, strict=True)):
        ok = np.asarray(np.isfinite(q).all(axis=1), dtype=bool)
        u = np.column_stack([np.where(ok[:, None], q, 0.0), np.ones(n)]) @ T.T
        for j in (0, 1):
            r = u[:, [j]] * P[2] - u[:, [2]] * P[j]
            nr = np.linalg.norm(r, axis=1, keepdims=True)
            rows[:, 2 * k + j] = np.where(ok[:, None] & (nr > 0), r / np.where(nr > 0, nr, 1.0), 0.0)
        seen += ok
    out = np.full((n, 4), np.nan)
    good = seen >= 2
    if good.any():
        X = np.linalg.svd(rows[good])[2][:, -1]
        out[good] = X * np.where(X[:, 3:] >= 0, 1.0, -1.0)
    return out


# ------------------------------------------------------------------ 3D transformations
def _as_src(src: ArrayLike, allow_h: bool) -> NDArray[np.float64]:
    """(N, 4) homogeneous source points (rows of unit norm for homogeneous input)."""
    a = np.asarray(src, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 4 and allow_h:
        if not np.isfinite(a).all():
            raise InvalidInputError("`src` has NaN or infinite values")
        n = np.linalg.norm(a, axis=1, keepdims=True)
        if (n == 0).any():
            raise InvalidInputError("`src` has a zero homogeneous point")
        return a / n
    p = as_points(a, "src", 3)
    return np.column_stack([p, np.ones(len(p))])


def _spread_rank(h: NDArray[np.float64]) -> tuple[int, NDArray[np.float64]]:
    """Rank (of 4) of homogeneous points after Hartley normalisation, and the relative singular values."""
    finite = np.abs(h[:, 3]) > 1e-12 * np.linalg.norm(h, axis=1)
    if finite.all():
        e = h[:, :3] / h[:, 3:4]
        c = e.mean(axis=0)
        d = float(np.mean(np.linalg.norm(e - c, axis=1))) or 1.0
        g = np.column_stack([(e - c) / d, np.ones(len(e))])
    else:
        g = h
    s = np.linalg.svd(g, compute_uv=False)
    rel = s / s[0]
    return int(np.sum(rel > _PLANAR_RTOL)), rel


def _freeze(*arrays: NDArray) -> None:
    for a in arrays:
        a.setflags(write=False)



@dataclass(frozen=True)
class Affine3D:
    """3D affine transformation ``dst = A src + t`` (12 parameters; seed 003, 3.3.1).

    Build with :meth:`from_points`. Attributes: ``A`` (3, 3), ``t`` (3,), ``residuals`` (N, 3)
    adjusted minus observed in dst units, ``weights`` (N,), ``sigma0`` (dst units, ``None`` without
    redundancy), ``redundancy`` (3N - 12), ``covariance`` (12, 12) of the parameters ordered as
    ``parameters`` (rows of [A | t]).
    """

    A: NDArray[np.float64]
    t: NDArray[np.float64]
    residuals: NDArray[np.float64]
    weights: NDArray[np.float64]
    sigma0: float | None
    redundancy: int
    covariance: NDArray[np.float64]

    n_params = 12
    min_points = MIN_CONTROL_AFFINE

    @property
    def parameters(self) -> NDArray[np.float64]:
        """(12,): a11 a12 a13 t1 a21 a22 a23 t2 a31 a32 a33 t3."""
        return np.hstack([self.A, self.t.reshape(3, 1)]).reshape(-1)

    @property
    def std_errors(self) -> NDArray[np.float64]:
        """(12,) standard errors of ``parameters`` (NaN without redundancy)."""
        if self.sigma0 is None:
            return np.full(12, np.nan)
        return lsq.standard_errors(self.covariance)

    @property
    def matrix(self) -> NDArray[np.float64]:
        """(4, 4) homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.A, self.t
        return m

    def __call__(self, src: ArrayLike) -> NDArray[np.float64]:
        """Transform (N, 3) (or (3,)) points; returns (N, 3)."""
        p = as_points(src, "src", 3)
        return p @ self.A.T + self.t

    def point_std(self, src: ArrayLike) -> NDArray[np.float64]:
        """(N, 3) standard deviations of the transformed points from the parameters' covariance."""
        p = as_points(src, "src", 3)
        out = np.empty((len(p), 3))
        for i, x in enumerate(p):
            J = np.zeros((3, 12))
            for j in range(3):
                J[j, 4 * j:4 * j + 4] = [x[0], x[1], x[2], 1.0]
            out[i] = np.sqrt(np.clip(np.diag(J @ self.covariance @ J.T), 0, None))
        return out if self.sigma0 is not None else np.full_like(out, np.nan)

    def to_dict(self) -> dict[str, Any]:
        return {"model": "affine3d", "A": self.A.tolist(), "t": self.t.tolist(),
                "sigma0": self.sigma0, "redundancy": self.redundancy,
                "std_errors": [None if not np.isfinite(v) else float(v) for v in self.std_errors]}

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, weights: ArrayLike | None = None) -> Affine3D:
        """Least-squares fit to corresponding points.

        Parameters
        ----------
        src, dst : (N, 3) array_like
            Source (model) and destination (object) points, N >= 4, not all on one plane.
        weights : (N,) array_like, optional
            Point weights (same for the three coordinates); default 1.

        Raises
        ------
        EstimationError
            Fewer than 4 points, or the source points coplanar (or collinear).
        """
        s, d = as_pair(src, dst, dim_src=3, dim_dst=3)
        w = as_weights(weights, len(s))
        n = int((w > 0).sum())
        if n < MIN_CONTROL_AFFINE:
            raise EstimationError(f"too few control points for the 3D affine transformation (12 parameters): "
                                  f"{n}; at least {MIN_CONTROL_AFFINE} non-coplanar points needed")
        for what, pts in (("model", s), ("control", d)):
            rank, rel = _spread_rank(np.column_stack([pts, np.ones(len(pts))])[w > 0])
            if rank < 4:
                raise EstimationError(f"degenerate control for the 3D affine transformation: the {n} {what} points "
                                      f"are {'coplanar' if rank == 3 else 'collinear'} (relative spread "
                                      f"{rel[-1]:.2g}); at least {MIN_CONTROL_AFFINE} non-coplanar points needed")
        # centre and scale for conditioning; the design is the same for the three coordinates
        c = np.average(s, axis=0, weights=w)
        sc = float(np.sqrt(np.average(np.sum((s - c) ** 2, axis=1), weights=w))) or 1.0
        X = np.column_stack([(s - c) / sc, np.ones(len(s))])
        N, _ = lsq.normal_equations(X, None, w)
        Q = lsq.cofactor(N)
        B = Q @ (X * w[:, None]).T @ d  # (4, 3): columns per destination coordinate
        A = B[:3].T / sc
        t = B[3] - A @ c
        v = s @ A.T + t - d
        r = 3 * n - 12
        s0 = lsq.sigma0(float(np.sum(w[:, None] * v * v)), r)
        # covariance of (a_j1, a_j2, a_j3, t_j) per row j: back from the conditioned unknowns
        Tm = np.zeros((4, 4))
        Tm[:3, :3] = np.eye(3) / sc
        Tm[3, :3] = -c / sc
        Tm[3, 3] = 1.0
        Qj = Tm @ Q @ Tm.T
        cov = np.kron(np.eye(3), Qj) * (s0 ** 2 if s0 is not None else 1.0)
        _freeze(A, t, v, w, cov)
        return cls(A=A, t=t, residuals=v, weights=w, sigma0=s0, redundancy=r, covariance=cov)


@dataclass(frozen=True)
class Projective3D:
    """3D projective transformation ``dst ~ H src`` (4 x 4 up to scale, 15 parameters; seed 003,
    3.3.2): it turns a projective model into the object frame.

    Build with :meth:`from_points`. Attributes: ``H`` (4, 4) normalised to ``H[3, 3] = 1`` when
    possible (unit Frobenius norm otherwise), ``residuals`` (N, 3) adjusted minus observed in dst
    units, ``weights`` (N,), ``sigma0``, ``redundancy`` (3N - 15), ``covariance`` (15, 15) of the
    first 15 elements of H (row-major) with ``H[3, 3]`` held fixed.
    """

    H: NDArray[np.float64]
    residuals: NDArray[np.float64]
    weights: NDArray[np.float64]
    sigma0: float | None
    redundancy: int
    covariance: NDArray[np.float64]
    iterations: int = 0

    n_params = 15
    min_points = MIN_CONTROL_PROJECTIVE

    @property
    def parameters(self) -> NDArray[np.float64]:
        """(15,): h11 .. h43 (row-major, h44 excluded)."""
        return self.H.reshape(-1)[:15].copy()

    @property
    def std_errors(self) -> NDArray[np.float64]:
        """(15,) standard errors of ``parameters`` (NaN without redundancy)."""
        if self.sigma0 is None:
            return np.full(15, np.nan)
        return lsq.standard_errors(self.covariance)

    def __call__(self, src: ArrayLike) -> NDArray[np.float64]:
        """Transform (N, 3) or homogeneous (N, 4) points; returns (N, 3) (inf/NaN for points the
        transformation sends to infinity)."""
        h = _as_src(src, allow_h=True)
        p = h @ self.H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return p[:, :3] / p[:, 3:4]

    def point_std(self, src: ArrayLike) -> NDArray[np.float64]:
        """(N, 3) standard deviations of the transformed points from the parameters' covariance."""
        h = _as_src(src, allow_h=True)
        out = np.empty((len(h), 3))
        for i, x in enumerate(h):
            out[i] = np.sqrt(np.clip(np.diag((J := _point_jac(self.H, x)) @ self.covariance @ J.T), 0, None))
        return out if self.sigma0 is not None else np.full_like(out, np.nan)

    def to_dict(self) -> dict[str, Any]:
        return {"model": "projective3d", "H": self.H.tolist(), "sigma0": self.sigma0,
                "redundancy": self.redundancy,
                "std_errors": [None if not np.isfinite(v) else float(v) for v in self.std_errors]}

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, weights: ArrayLike | None = None,
                    max_iterations: int = 50) -> Projective3D:
        """Least-squares fit: linear DLT on normalised points, then Gauss-Newton on the object-space
        residuals.

        Parameters
        ----------
        src : (N, 3) or homogeneous (N, 4) array_like
            Model points (e.g. from :func:`triangulate_projective`).
        dst : (N, 3) array_like
            Object points, N >= 5 in general position: not all on one plane (refused by name), and
            with a unique linear solution (five points of which four are coplanar have none).
        weights : (N,) array_like, optional

        Raises
        ------
        EstimationError
            Fewer than 5 points, all model points on one plane (the projective model is then not
            determined in depth), or a singular adjustment.
        """
        h = _as_src(src, allow_h=True)
        d = as_points(dst, "dst", 3)
        if len(h) != len(d):
            raise ShapeError(f"`src` and `dst` must have the same number of points; got {len(h)} and {len(d)}")
        w = as_weights(weights, len(h))
        used = w > 0
        n = int(used.sum())
        if n < MIN_CONTROL_PROJECTIVE:
            raise EstimationError(f"too few control points for the 3D projective transformation (15 "
                                  f"parameters): {n}; at least {MIN_CONTROL_PROJECTIVE} in general position needed")
        for what, pts in (("model", h[used]), ("control", np.column_stack([d[used], np.ones(n)]))):
            rank, rel = _spread_rank(pts)
            if rank < 4:
                raise EstimationError(f"degenerate control for the 3D projective transformation: the {n} "
                                      f"{what} points are coplanar (relative spread {rel[-1]:.2g}); the "
                                      f"15-parameter model needs at least {MIN_CONTROL_PROJECTIVE} points "
                                      f"not all on one plane")
        Hn, it = _fit_projective(h[used], d[used], w[used], max_iterations)
        v = _apply(Hn, h) - d
        if not np.isfinite(v[used]).all():
            raise EstimationError("3D projective transformation sends a control point to infinity")
        r = 3 * n - 15
        s0 = lsq.sigma0(float(np.sum(w[:, None] * v * v)), r)
        # covariance in the gauge h44 = 1 (else unit norm with the largest element fixed)
        H = Hn / Hn[3, 3] if abs(Hn[3, 3]) > 1e-8 * np.abs(Hn).max() else Hn / np.linalg.norm(Hn)
        J = np.vstack([_point_jac(H, x) for x in h[used]])
        Wd = np.repeat(w[used], 3)
        N, _ = lsq.normal_equations(J, None, Wd)
        Dn = np.sqrt(np.diag(N))
        if not (Dn > 0).all():
            raise EstimationError("degenerate control for the 3D projective transformation: an element has "
                                  "no influence on the control points")
        try:
            Q = np.linalg.inv(N / np.outer(Dn, Dn)) / np.outer(Dn, Dn)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"singular 3D projective adjustment: {err}") from err
        cov = Q * (s0 ** 2 if s0 is not None else 1.0)
        H = np.array(H)
        _freeze(H, v, w, cov)
        return cls(H=H, residuals=v, weights=w, sigma0=s0, redundancy=r, covariance=cov, iterations=it)


def _apply(H: NDArray, h: NDArray) -> NDArray:
    p = h @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :3] / p[:, 3:4]


def _point_jac16(H: NDArray, x: NDArray) -> NDArray:
    """d(dst)/d(h11..h44) (3, 16) of one homogeneous source point x (4,)."""
    p = H @ x
    J = np.zeros((3, 16))
    for j in range(3):
        J[j, 4 * j:4 * j + 4] = x / p[3]
        J[j, 12:16] = -p[j] * x / p[3] ** 2
    return J


def _point_jac(H: NDArray, x: NDArray) -> NDArray:
    """d(dst)/d(h11..h43) (3, 15) of one homogeneous source point x (4,), h44 held fixed."""
    return _point_jac16(H, x)[:, :15]


def _fit_projective(h: NDArray, d: NDArray, w: NDArray, max_iterations: int) -> tuple[NDArray, int]:
    """H (4, 4) in original units: DLT on normalised points, then Gauss-Newton (minimum-norm steps
    over the 16 elements, the scale being free)."""
    # normalisers: source (homogeneous, may hold points at infinity) and destination
    finite = np.abs(h[:, 3]) > 1e-9
    e = h[finite, :3] / h[finite, 3:4] if finite.any() else np.zeros((1, 3))
    cs = e.mean(axis=0)
    ss = math.sqrt(3.0) / (float(np.mean(np.linalg.norm(e - cs, axis=1))) or 1.0)
    Ts = np.diag([ss, ss, ss, 1.0])
    Ts[:3, 3] = -ss * cs
    cd = d.mean(axis=0)
    sd = math.sqrt(3.0) / (float(np.mean(np.linalg.norm(d - cd, axis=1))) or 1.0)
    Td = np.diag([sd, sd, sd, 1.0])
    Td[:3, 3] = -sd * cd
    hs = h @ Ts.T
    hs /= np.linalg.norm(hs, axis=1, keepdims=True)
    dn = (d - cd) * sd
    rows = []
    sw = np.sqrt(w)
    for x, y, wi in zip(hs, dn, sw, strict=True):
        for j in range(3):
            r = np.zeros(16)
            r[4 * j:4 * j + 4] = x
            r[12:16] = -y[j] * x
            rows.append(wi * r)
    _, sv, Vt = np.linalg.svd(np.asarray(rows))
    s16 = np.zeros(16)
    s16[:len(sv)] = sv
    if s16[14] / s16[0] < 1e-10:  # more than one null vector
        raise EstimationError(f"degenerate control for the 3D projective transformation: the {len(h)} points are "
                              "not in general position (the linear solution is not unique; e.g. four of five "
                              "points on one plane)")
    hv = Vt[-1]
    it = 0
    wr = np.repeat(sw, 3)

    def res(hv_):
        return (_apply(hv_.reshape(4, 4), hs) - dn).reshape(-1) * wr

    r = res(hv)
    cost = float(r @ r)
    for it in range(1, max_iterations + 1):  # noqa: B007
        Hm = hv.reshape(4, 4)
        J = np.vstack([_point_jac16(Hm, x) for x in hs]) * wr[:, None]
        dx = -np.linalg.lstsq(J, r, rcond=1e-12)[0]
        hn = hv + dx
        hn /= np.linalg.norm(hn)
        rn = res(hn)
        cn = float(rn @ rn)
        if not np.isfinite(cn) or cn > cost:
            break
        hv, r = hn, rn
        done = cost - cn <= 1e-14 * max(cost, 1e-30) or cn < 1e-28
        cost = cn
        if done:
            break
    H = np.linalg.inv(Td) @ hv.reshape(4, 4) @ Ts
    return H, it
