"""Fusion of several pairs' heights into one surface: robust, precision-weighted, with sigma_Z.

The pairs' heights and standard errors lie on one common grid (cells on whole multiples of the
cell, :class:`stereo.dense.dsm.DsmGrid`); :class:`SigmaGrid` grids one pair's points with their
standard errors onto it, :func:`fuse_heights` fuses a block of cells of all pairs at once (the
caller streams row blocks: memory is that of the block).

Per cell, with the pairs' heights ``h_i`` and standard errors ``s_i`` (weights ``w_i = 1 / s_i^2``):

1. the weighted median ``m`` of the heights (the lower weighted median when the weight is split);
2. a height is *consistent* when ``|h_i - m| <= k sqrt(s_i^2 + s_m^2)`` (``s_m``: the smallest
   ``s_i`` of the cell, the median's standard error at best); the others are rejected;
3. the weighted mean of the consistent heights, ``z = sum(w_i h_i) / sum(w_i)``, and the test of
   step 2 once more against ``z`` (with ``s_z`` in place of ``s_m``); the final ``z`` from those kept;
4. its standard error ``s_z = 1 / sqrt(sum w_i)``, inflated by the scatter when that is larger:
   ``s_z * max(1, sqrt(chi2 / (n - 1)))`` with ``chi2 = sum w_i (h_i - z)^2`` (``n >= 2``), and a
   standard error common to all pairs at the cell, when given, added in quadrature;
5. the count of consistent pairs and the provenance: the index of the consistent pair with the
   smallest ``s_i`` (-1 where no height).

Over a whole surface, :func:`variance_factor` turns the cells' ``chi2`` into the a-posteriori
variance factor of the pairs' sigmas (a first pass), by which they are scaled in the final pass
when it exceeds 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.points import as_points
from stereo.dense.dsm import DSM_NODATA, DsmGrid

__all__ = ["FUSED_BANDS", "FusedHeights", "SigmaGrid", "fuse_heights", "fused_band_descriptions", "nodata_of",
           "variance_factor"]

#: names of the fused DSM's bands, in order
FUSED_BANDS = ("height", "sigma_z", "count", "provenance")


def fused_band_descriptions(heights: str = "ground units", k: float = 3.0) -> tuple[str, str, str, str]:
    """The band descriptions of a fused DSM GeoTIFF (:data:`FUSED_BANDS`)."""
    return (f"height: robust precision-weighted mean of the pairs' heights ({heights}); nodata -9999",
            f"sigma_z: standard error of the height ({heights}; the weighted mean's, inflated by the pairs' "
            "scatter when larger); nodata -9999",
            f"count: pairs whose heights agree within {k:g} sigma and made the height (0 where none)",
            "provenance: index of the agreeing pair with the smallest sigma_z (the pairs sidecar JSON lists them); "
            "-1 where none")


@dataclass(frozen=True, eq=False)
class FusedHeights:
    """A block of fused cells.

    Attributes
    ----------
    height, sigma : (H, W) float64
        Fused height and its standard error; NaN where no pair has a height.
    count : (H, W) int32
        Consistent pairs per cell.
    provenance : (H, W) int32
        Index (into the pair axis) of the consistent pair with the smallest standard error; -1 where none.
    rejected : (H, W) int32
        Heights rejected as inconsistent per cell.
    chi2 : (H, W) float64
        ``sum w_i (h_i - z)^2`` of the consistent heights (0 where fewer than two); with
        ``count - 1`` degrees of freedom it gives the variance factor (:func:`variance_factor`).
    """

    height: NDArray[np.float64]
    sigma: NDArray[np.float64]
    count: NDArray[np.int32]
    provenance: NDArray[np.int32]
    rejected: NDArray[np.int32]
    chi2: NDArray[np.float64]

    @property
    def dof(self) -> NDArray[np.int32]:
        """Degrees of freedom of each cell's ``chi2``: ``count - 1`` (0 where no height)."""
        return np.maximum(self.count - 1, 0).astype(np.int32)


def variance_factor(chi2_sum: float, dof_sum: int) -> float:
    """The a-posteriori variance factor of the pairs' sigmas, ``sqrt(sum chi2 / sum dof)``, at least 1.

    The pairs' standard errors are scaled by it before the final fusion when the pairs disagree more
    than their sigmas say (never made smaller: pairs that share an image have correlated errors, so
    their agreement overstates their precision). 1 when there is no redundancy (``dof_sum`` 0).
    """
    if dof_sum <= 0 or not math.isfinite(chi2_sum):
        return 1.0
    return max(1.0, math.sqrt(chi2_sum / dof_sum))


def _weighted_median(h: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Lower weighted median along axis 0 (w = 0 where no height)."""
    key = np.where(w > 0, h, np.inf)
    order = np.argsort(key, axis=0, kind="stable")
    hs = np.take_along_axis(key, order, axis=0)
    ws = np.take_along_axis(w, order, axis=0)
    cw = np.cumsum(ws, axis=0)
    half = 0.5 * cw[-1]
    idx = np.argmax(cw >= half[None] - 1e-12 * np.maximum(half[None], 1e-300), axis=0)
    return np.take_along_axis(hs, idx[None], axis=0)[0]


def fuse_heights(heights: ArrayLike, sigmas: ArrayLike, *, k: float = 3.0, common: ArrayLike | None = None
                 ) -> FusedHeights:
    """Fuse the heights of P pairs on a common grid (module docstring).

    Parameters
    ----------
    heights : (P, H, W) array_like
        Each pair's heights on the grid; NaN where the pair has none.
    sigmas : (P, H, W) array_like
        Their standard errors (> 0; a cell without a finite positive sigma is not used).
    k : float
        Rejection threshold, standard errors.
    common : (H, W) array_like, optional
        A standard error shared by all pairs at each cell (e.g. the orientation's, as the bundle
        propagated it to its points): it neither weights nor rejects, and is added in quadrature to
        the fused standard error (NaN: 0).

    Returns
    -------
    FusedHeights

    Raises
    ------
    ShapeError, InvalidInputError
        Shapes differ or are not 3-D, or ``k`` is not a number > 0.
    """
    h = np.asarray(heights, dtype=np.float64)
    s = np.asarray(sigmas, dtype=np.float64)
    if h.ndim != 3 or s.shape != h.shape:
        raise ShapeError(f"`heights` and `sigmas` must be (P, H, W) arrays of one shape; got {h.shape} and {s.shape}",
                         actual_shape=(h.shape, s.shape))
    if isinstance(k, bool) or not (isinstance(k, (int, float)) and math.isfinite(k) and k > 0):
        raise InvalidInputError(f"`k` must be a finite number > 0; got {k!r}")
    ok = np.isfinite(h) & np.isfinite(s) & (s > 0)
    s = np.where(ok, s, np.inf)
    h = np.where(ok, h, 0.0)
    w = np.where(ok, 1.0 / (s * s), 0.0)
    any_ok = ok.any(axis=0)
    m = _weighted_median(h, w)
    s_min = s.min(axis=0)
    keep = ok & (np.abs(h - m[None]) <= k * np.sqrt(s * s + s_min[None] ** 2))
    for _ in range(2):
        wk = np.where(keep, w, 0.0)
        sw = wk.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = (wk * h).sum(axis=0) / sw
            sz = 1.0 / np.sqrt(sw)
        if _ == 0:
            keep2 = ok & (np.abs(h - z[None]) <= k * np.sqrt(s * s + sz[None] ** 2))
            # a cell whose second test would leave no height keeps its first choice
            keep = np.where(keep2.any(axis=0)[None], keep2, keep)
    n = keep.sum(axis=0).astype(np.int32)
    with np.errstate(invalid="ignore", divide="ignore"):
        chi2 = (np.where(keep, w, 0.0) * (h - z[None]) ** 2).sum(axis=0)
        infl = np.where(n >= 2, np.sqrt(chi2 / np.maximum(n - 1, 1)), 1.0)
    sigma = sz * np.maximum(1.0, infl)
    if common is not None:
        c = np.asarray(common, dtype=np.float64)
        if c.shape != h.shape[1:]:
            raise ShapeError(f"`common` must have the grid's shape {h.shape[1:]}; got {c.shape}",
                             actual_shape=c.shape, expected_shape=h.shape[1:])
        sigma = np.sqrt(sigma * sigma + np.where(np.isfinite(c), c, 0.0) ** 2)
    has = any_ok & (n > 0)
    z = np.where(has, z, np.nan)
    sigma = np.where(has, sigma, np.nan)
    prov = np.argmin(np.where(keep, s, np.inf), axis=0).astype(np.int32)
    prov[~has] = -1
    rejected = (ok.sum(axis=0) - n).astype(np.int32)
    return FusedHeights(z, sigma, n, prov, rejected, np.where(has & (n >= 2), chi2, 0.0))


class SigmaGrid:
    """One pair's points with their height standard errors, gridded on a common DSM grid.

    The heights go into a :class:`DsmGrid` (``radius``, ``max_spread`` as there); the variances
    ``sigma^2`` into a second one (the same Gaussian weights, no spread test): a cell's standard
    error is the root of the weighted mean variance of its points (neighbouring disparities are
    strongly correlated, so the mean of n points is taken as no more precise than one of them).

    Parameters
    ----------
    bounds, cell, crs, radius, max_spread :
        As :class:`DsmGrid`; grids of the same cell share their cells.
    edge_cells : int
        Cells within this many cells of the pair's coverage edge (or of a hole in it) are dropped:
        their heights come from points on one side only and from disparities next to occlusions
        and photo borders, whose errors the disparity sigma does not see (on the synthetic block of
        ``docs/surface.md`` the cells within 2 cells of an edge had RMS(error / sigma_Z) of 3.1
        and 1.8 against 1.05 inside).
    """

    def __init__(self, bounds: tuple[float, float, float, float], cell: float, *, crs: str | None = None,
                 radius: float = 1.0, max_spread: float = 2.0, edge_cells: int = 2):
        if isinstance(edge_cells, bool) or not isinstance(edge_cells, int) or not 0 <= edge_cells <= 20:
            raise InvalidInputError(f"`edge_cells` must be an integer in 0..20; got {edge_cells!r}")
        self.edge_cells = edge_cells
        self.heights = DsmGrid(bounds, cell, crs=crs, radius=radius, max_spread=max_spread)
        self.variances = DsmGrid(bounds, cell, crs=crs, radius=radius, max_spread=0.0)
        self.shape = (self.heights.height, self.heights.width)

    @property
    def transform(self):  # noqa: ANN201 - affine.Affine
        return self.heights.transform

    def add(self, xyz: ArrayLike, sigma: ArrayLike) -> int:
        """Add points (N, 3) with their height standard errors (N,); returns how many fell inside."""
        p = as_points(xyz, "points", 3)
        s = np.asarray(sigma, dtype=np.float64).reshape(-1)
        if s.shape != (len(p),):
            raise ShapeError(f"`sigma` must have one value per point ({len(p)}); got {s.shape}",
                             actual_shape=s.shape, expected_shape=(len(p),))
        good = np.isfinite(p).all(axis=1) & np.isfinite(s) & (s > 0)
        if not good.any():
            return 0
        self.variances.add(np.column_stack([p[good, :2], s[good] ** 2]))
        return self.heights.add(p[good])

    def result(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(height, sigma) grids (H, W) float64, NaN where no height."""
        dh = self.heights.result()
        dv = self.variances.result()
        valid = dh.valid & dv.valid
        if self.edge_cells > 0:
            valid = ndimage.binary_erosion(valid, iterations=self.edge_cells, border_value=0)
        h = np.where(valid, dh.height.astype(np.float64), np.nan)
        var = np.where(valid, dv.height.astype(np.float64), np.nan)
        return h, np.sqrt(np.maximum(var, 0.0))


def nodata_of(a: NDArray[np.float64]) -> NDArray[np.float32]:
    """NaN -> the DSM nodata value, as float32."""
    return np.where(np.isfinite(a), a, DSM_NODATA).astype(np.float32)
