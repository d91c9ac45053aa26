"""Validation of point arrays at the public boundary, and the point tables read from files.

Private functions trust their inputs; every public entry point validates once
with :func:`as_points` (and friends), which return C-contiguous float64 copies,
so callers' arrays are never modified.

The point tables :class:`GcpTable` (ground control), :class:`Matches` (tie points of two images)
and :class:`ControlTable` (stereo control) are what the readers of :mod:`rectify.formats.gcps` and
:mod:`rectify.formats.tables` build.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError, ShapeError

__all__ = [
    "as_points", "as_pair", "as_weights", "check_min_points", "check_distinct",
    "check_not_collinear", "check_no_three_collinear",
    "GcpTable", "Matches", "ControlTable",
]


def as_points(
    a: ArrayLike, name: str = "points", dim: int = 2, *, allow_empty: bool = True
) -> NDArray[np.float64]:
    """Return ``a`` as a new C-contiguous float64 array of shape (N, dim).

    A single point of shape (dim,) is accepted and returned as (1, dim).

    Raises
    ------
    ShapeError
        If the shape is not (N, dim).
    InvalidInputError
        If an entry is NaN or infinite, or if ``a`` is empty and
        ``allow_empty`` is false.
    """
    try:
        arr = np.array(a, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as err:
        raise InvalidInputError(f"`{name}` must be numeric of shape (N, {dim}); {err}") from err
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr.reshape(1, dim)
    if arr.ndim != 2 or arr.shape[1] != dim:
        if arr.ndim == 1 and arr.shape[0] == 0:
            arr = arr.reshape(0, dim)
        else:
            raise ShapeError(
                f"`{name}` must have shape (N, {dim}); got {arr.shape}",
                actual_shape=arr.shape,
                expected_shape=(None, dim),
            )
    if not allow_empty and arr.shape[0] == 0:
        raise InvalidInputError(f"`{name}` is empty; at least one point is needed")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidInputError(
            f"`{name}` has {int(bad.sum())} non-finite row(s); first is row {i}: {arr[i].tolist()}"
        )
    return np.ascontiguousarray(arr)


def as_pair(
    src: ArrayLike, dst: ArrayLike, *, dim_src: int = 2, dim_dst: int = 2,
    names: tuple[str, str] = ("src", "dst"),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate two corresponding point arrays of equal length."""
    s = as_points(src, names[0], dim_src)
    d = as_points(dst, names[1], dim_dst)
    if len(s) != len(d):
        raise ShapeError(
            f"`{names[0]}` and `{names[1]}` must have the same number of points; "
            f"got {len(s)} and {len(d)}",
            actual_shape=(len(s), len(d)),
        )
    return s, d


def as_weights(weights: ArrayLike | None, n: int, name: str = "weights") -> NDArray[np.float64]:
    """Validate per-point weights: (N,) finite, non-negative, not all zero."""
    if weights is None:
        return np.ones(n)
    w = np.array(weights, dtype=np.float64, copy=True).reshape(-1)
    if w.shape != (n,):
        raise ShapeError(f"`{name}` must have shape ({n},); got {w.shape}",
                         actual_shape=w.shape, expected_shape=(n,))
    if not np.isfinite(w).all() or (w < 0).any():
        raise InvalidInputError(f"`{name}` must be finite and >= 0; got min {np.nanmin(w)!r}")
    if not (w > 0).any():
        raise InvalidInputError(f"`{name}` are all zero")
    return w


def check_min_points(pts: NDArray[np.float64], n_min: int, what: str = "points") -> None:
    """Raise EstimationError if fewer than ``n_min`` points are given."""
    if len(pts) < n_min:
        raise EstimationError(f"too few {what}: {len(pts)} given, at least {n_min} needed")


def check_distinct(pts: NDArray[np.float64], name: str = "points", *, tol: float = 0.0) -> None:
    """Raise EstimationError if two points coincide (within ``tol``)."""
    n = len(pts)
    if n < 2:
        return
    scale = max(float(np.ptp(pts, axis=0).max()), 1.0)
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1) if n <= 2000 else None
    if d is None:
        _, idx, counts = np.unique(pts, axis=0, return_index=True, return_counts=True)
        if (counts > 1).any():
            j = int(idx[np.flatnonzero(counts > 1)[0]])
            raise EstimationError(f"duplicate point in `{name}`: {pts[j].tolist()}")
        return
    iu = np.triu_indices(n, 1)
    close = d[iu] <= max(tol, 1e-12 * scale)
    if close.any():
        k = int(np.flatnonzero(close)[0])
        i, j = int(iu[0][k]), int(iu[1][k])
        raise EstimationError(
            f"duplicate points in `{name}`: rows {i} and {j} are both {pts[i].tolist()}"
        )


def check_not_collinear(pts: NDArray[np.float64], name: str = "points", *, rtol: float = 1e-9) -> None:
    """Raise EstimationError if all points (N, 2) lie on one line (or coincide)."""
    c = pts - pts.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if len(s) < 2 or s[0] == 0 or s[1] <= rtol * s[0]:
        raise EstimationError(
            f"`{name}` are collinear (singular values {np.round(s, 6).tolist()}): "
            f"{pts.tolist() if len(pts) <= 8 else str(len(pts)) + ' points'}"
        )


def check_no_three_collinear(pts: NDArray[np.float64], name: str = "points", *, rtol: float = 1e-9) -> None:
    """Raise EstimationError if any three of a small point set (N <= 8) are collinear.

    The tolerance is relative: the triangle's doubled area over the squared
    longest side of the set.
    """

    scale2 = float(np.ptp(pts, axis=0).max()) ** 2 or 1.0
    for i, j, k in combinations(range(len(pts)), 3):
        a, b, c = pts[i], pts[j], pts[k]
        area2 = abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
        if area2 <= rtol * scale2:
            raise EstimationError(
                f"three of `{name}` are collinear: rows {i}, {j}, {k} = "
                f"{a.tolist()}, {b.tolist()}, {c.tolist()}"
            )


def as_ids(ids, n: int, name: str = "ids") -> tuple[str, ...]:
    """Point identifiers as a tuple of n strings; ``None`` gives "1".."n".

    Raises
    ------
    ShapeError
        If ``ids`` does not have n entries.
    """
    out = tuple(str(i) for i in (ids if ids is not None else range(1, n + 1)))
    if len(out) != n:
        raise ShapeError(f"`{name}` must have {n} entries (one per point); got {len(out)}",
                         actual_shape=(len(out),), expected_shape=(n,))
    return out


def as_mask(mask, n: int, name: str = "mask") -> NDArray[np.bool_]:
    """A per-point flag array (n,) bool (a new array); ``None`` gives all False.

    Raises
    ------
    ShapeError
        If ``mask`` does not have shape (n,).
    """
    out = np.zeros(n, bool) if mask is None else np.array(mask, dtype=bool, copy=True).reshape(-1)
    if out.shape != (n,):
        raise ShapeError(f"`{name}` must have shape ({n},); got {out.shape}", actual_shape=out.shape,
                         expected_shape=(n,))
    return out


# --------------------------------------------------------------------------- point tables
@dataclass(frozen=True, eq=False)
class GcpTable:
    """Ground control for 2D rectification.

    Attributes
    ----------
    ids : tuple of str
    pixel : (N, 2) float64
        Source pixels (col, row).
    target : (N, 2) float64
        Target coordinates (map units when ``crs`` is set, target pixels otherwise).
    z : (N,) float64 or None
        Heights, when the file has a ``z`` column.
    check : (N,) bool
        Rows withheld from the fit (``check`` column = 1).
    crs : str or None
    """

    ids: tuple[str, ...]
    pixel: NDArray[np.float64]
    target: NDArray[np.float64]
    z: NDArray[np.float64] | None
    check: NDArray[np.bool_]
    crs: str | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def fit(self) -> GcpTable:
        """The rows used for fitting (not check points)."""
        return self.subset(~self.check)

    def subset(self, mask: NDArray[np.bool_]) -> GcpTable:
        """The rows where ``mask`` (N,) is true."""
        m = np.asarray(mask, dtype=bool)
        return GcpTable(tuple(i for i, k in zip(self.ids, m, strict=False) if k), self.pixel[m], self.target[m],
                        None if self.z is None else self.z[m], self.check[m], self.crs)


#: Position std assumed for a match kept unrefined (raw keypoint) when its file gives no ``sigma_px``, px
#: (measured: about 0.5 px on the NGI aerial pair; ``MatchResult.sigma_px``).
ASSUMED_RAW_SIGMA_PX = 0.5
#: Position std assumed for a refined match when the file gives no ``sigma_px``, px (0.08 px measured there).
ASSUMED_REFINED_SIGMA_PX = 0.1
#: An unrefined match never weighs more than this against the refined median (its sigma at least twice theirs).
UNREFINED_MAX_WEIGHT = 0.25


@dataclass(frozen=True, eq=False)
class Matches:
    """Tie points between two images, pixel frame.

    Attributes
    ----------
    ids : tuple of str
    left, right : (N, 2) float64
        (col, row) in the left and right image.
    score : (N,) float64 or None
        The matcher's score: the least-squares position std (px) of a refined match, NaN for a match kept
        unrefined at its raw keypoint position.
    sigma : (N,) float64 or None
        Standard deviation of each right position, px (the matcher's ``sigma_px``: the LSM one for a refined
        match, the raw keypoints' measured one for an unrefined match), or None when unknown.
    """

    ids: tuple[str, ...]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    score: NDArray[np.float64] | None = None
    sigma: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.ids)

    def weights(self) -> NDArray[np.float64] | None:
        """(N,) relative weights of the matches for an adjustment, or None when all are equal.

        A refined match (finite score) weighs 1: the LSM standard deviations of single matches are too
        uncertain to weight the refined matches among themselves (weighting by them cost relative
        orientation precision on the NGI variants: 0.097 deg against 0.065 deg on the half-scale pair).
        An unrefined match weighs ``(s0 / sigma)**2``, s0 the median ``sigma`` of the refined matches, at
        most ``UNREFINED_MAX_WEIGHT`` (about (0.08 / 0.6)**2 on aerial frames); one without a sigma as a
        raw keypoint (``ASSUMED_RAW_SIGMA_PX``). Without ``sigma`` (a matches CSV of an older version):
        ``(ASSUMED_REFINED_SIGMA_PX / ASSUMED_RAW_SIGMA_PX)**2``. Without a score (nothing says which
        matches are refined), ``sigma`` alone weights each match: ``(s0 / sigma)**2`` with s0 their
        median. An unrefined match is never counted with the weight of a refined one.
        """
        refined = None if self.score is None else np.isfinite(self.score)
        sigma = None if self.sigma is None or len(self.sigma) != len(self.ids) else \
            np.asarray(self.sigma, dtype=np.float64)
        ok = np.zeros(len(self.ids), bool) if sigma is None else np.isfinite(sigma) & (sigma > 0)
        if refined is None:
            if not ok.any():
                return None
            assert sigma is not None
            s0 = float(np.median(sigma[ok]))
            floor = 0.1 * s0   # a degenerate std must not dominate the set
            unknown = min((s0 / ASSUMED_RAW_SIGMA_PX) ** 2, UNREFINED_MAX_WEIGHT)
            return np.where(ok, (s0 / np.maximum(np.where(ok, sigma, 1.0), floor)) ** 2, unknown)
        if refined.all():
            return None
        if sigma is not None and (refined & ok).any():
            s0 = float(np.median(sigma[refined & ok]))
            raw = np.where(ok, sigma, ASSUMED_RAW_SIGMA_PX)
            return np.where(refined, 1.0, np.minimum((s0 / raw) ** 2, UNREFINED_MAX_WEIGHT))
        return np.where(refined, 1.0, (ASSUMED_REFINED_SIGMA_PX / ASSUMED_RAW_SIGMA_PX) ** 2)


@dataclass(frozen=True, eq=False)
class ControlTable:
    """Stereo control: image points in both images (pixel frame) plus ground coordinates.

    ``xyz`` (N, 3) rows are NaN for tie points (empty x, y, z in the file); ``crs`` is that of x, y.
    """

    ids: tuple[str, ...]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    xyz: NDArray[np.float64]
    crs: str | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def is_control(self) -> NDArray[np.bool_]:
        """(N,) rows with full ground coordinates."""
        return np.asarray(np.isfinite(self.xyz).all(axis=1), dtype=bool)
