"""``run_dense_rpc``: an RPC (pushbroom satellite) pair -> DSM, point cloud and report, tile by tile.

Per tile of the region of interest of the left image (as satellite stereo pipelines do, s2p):

1. tie points (:mod:`rectify.features`: SIFT, verification, least-squares matching) between the
   tile's window of the left image and the window of the right image where the RPCs put it over
   the height prior (the validity box of the left RPC unless ``height_range`` is given);
2. their heights by RPC triangulation give the tile's height range;
3. the affine camera approximation of both RPCs over the tile's footprint, the affine epipolar
   geometry and the rectifying similarities; the relative pointing error of the RPCs is corrected
   by a row shift of the right image (the median vertical parallax of the tie points), and the
   residual vertical parallax of the tie points is reported
   (:mod:`stereo.dense.rpc_epipolar`);
4. both windows resampled into the rectified frame and matched by SGBM
   (:func:`stereo.dense.matching.match_pair`) over the disparity range of the tie points;
5. every disparity of the tile's core -> the two original pixels -> ground by least squares on
   (lon, lat, h) with both RPC projections (Gauss-Newton from the affine cameras' solution);
   points whose reprojection residual exceeds ``max_residual_px`` are dropped.

Outputs in ``out_dir`` (written together at the end, or none on an error; a folder the run
created is removed again on an error):

=====================  ==================================================================
``dsm.tif``            DSM in the scene's UTM zone (WGS 84 ellipsoidal heights), its cell
                       edges on whole multiples of the cell: band 1 height (nodata -9999),
                       band 2 points per cell, band 3: 1 filled (band descriptions in the
                       file)
``points.las``         the point cloud (UTM, ellipsoidal heights) with the left intensity
(``.laz``, ``.ply``)
``dense_rpc.json``     the summary: per-tile vertical parallax, affine fit, disparity range,
                       points; ROI coverage of the DSM; the comparison with a reference DEM
``item.stac.json``     the STAC Item of the DSM and the point cloud (``--no-stac``: none)
``report/``            with a reference DEM: ``dsm.png``, ``dz.png`` (DSM - DEM) and
                       ``dz_histogram.png``
=====================  ==================================================================

Tiles: the region of interest is cut into ``round(width / tile) x round(height / tile)`` tiles of
equal size (at least one a side), so a tile's side is ``tile`` rounded to split the ROI evenly: a
700 px ROI with the default 300 gives two tiles of 350 px a side.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.actions.products import FOLDER_ITEM, options_of, raster_grid, stac_text
from rectify.actions.workspace import Workspace
from rectify.errors import EstimationError, InvalidInputError, ShapeError, StereoError
from rectify.features import MatcherConfig
from rectify.features.match import match_arrays
from rectify.formats.rpc import rpc_from_raster
from rectify.formats.stac import StacAsset
from rectify.geometry.crs import transform_xy, utm_crs
from rectify.geometry.rpc import RPC
from rectify.raster.io import gdal_cache_limit, gdal_wkt, raster_info, read_window
from rectify.report.builder import json_safe
from stereo.dense.dsm import DSM_NODATA, STATISTICS, DsmGrid, DsmResult, default_cell
from stereo.dense.fusion import SigmaGrid
from stereo.dense.matching import MatchOptions, match_pair
from stereo.dense.precision import disparity_sigma
from stereo.dense.rpc_epipolar import (
    AffineCamera,
    AffineRectification,
    LocalFrame,
    TileParallax,
    fit_affine_pair,
    rectify_affine,
    resample_rectified,
)
from stereo.formats.points import point_writer
from stereo.report.dense import HeightComparison, compare_with_dem, save_histogram, save_picture

logger = logging.getLogger(__name__)

__all__ = ["RpcDenseOptions", "RpcDenseResult", "RpcTile", "roi_statistics", "run_dense_rpc", "triangulate_rpc"]

StrPath = str | Path
Progress = Callable[[str, int, int], None]

#: GDAL block cache while the tiles are read, MB
GDAL_CACHE_MB = 64


@dataclass(frozen=True)
class RpcDenseOptions:
    """Options of :func:`run_dense_rpc`.

    Attributes
    ----------
    tile : int
        Nominal side of the tiles of the region of interest (left image pixels); each has its own
        affine approximation and pointing correction. The ROI is cut into ``round(w / tile)`` x
        ``round(h / tile)`` equal tiles (at least one), so the tiles' side is ``tile`` rounded to
        split the ROI evenly (a 700 px ROI: two tiles of 350 px with 300).
    margin_px : int
        Rectified pixels added around a tile's core for matching (the disparities of the core only
        become points).
    disparity_margin_px : float
        Added on both sides of the tie points' disparity range of a tile.
    height_margin_m : float
        Added on both sides of the tie points' height range of a tile (affine fit range).
    height_range : (float, float) or None
        Height prior for the tie-point search windows; default the left RPC's validity box.
    min_ties : int
        A tile with fewer tie points borrows the nearest ones of the other tiles.
    max_residual_px : float
        Points whose RPC reprojection residual (RMS over the four coordinates) exceeds this are
        dropped.
    matching : MatchOptions
        The SGBM options (default: no coarse pass, the range comes from the tie points).
    dsm_cell : float or None
        DSM cell side, metres; default the median ground sampling distance of the left image rounded
        to two significant digits (:func:`stereo.dense.dsm.default_cell`).
    dsm_statistic, dsm_radius, dsm_max_spread, fill_holes, despike_cells
        As in :class:`stereo.actions.dense.DenseOptions`.
    cloud_format : {"las", "laz", "ply", "none"}
    interpolation : {"nearest", "linear", "cubic"}
    reference_dem : path or None
        Compare the DSM with this DEM (any CRS; resampled bilinearly onto the DSM grid; its heights
        are taken as they are: the DSM's are ellipsoidal). Statistics in the summary, pictures in
        ``report/``.
    stac : bool
        Write the STAC Item of the DSM and the point cloud, ``OUTDIR/item.stac.json``.
    pair_sigma : bool
        Also grid every point with its height standard error (the disparity's, from its sub-pixel fit,
        :func:`stereo.dense.precision.disparity_sigma`, over the tile's disparity per metre of height) on
        the DSM grid (:class:`stereo.dense.fusion.SigmaGrid`): :attr:`RpcDenseResult.sigma`, what the
        multi-view fusion of ``stereo dense-rpc IMG1 IMG2 IMG3 ...`` takes from each pair.
    sigma_edge_cells : int
        With ``pair_sigma``: cells within this many cells of the pair's coverage edge are left out of the
        sigma grids (:class:`stereo.dense.fusion.SigmaGrid`'s ``edge_cells``). Default 0: on the Pleiades
        triplet 1 cell took the fused DSM's ROI coverage from 99.2 % to 94.4 % (the pairs' holes are many
        and small) and changed the pairs' agreement by 0.04 m.
    """

    tile: int = 300
    margin_px: int = 24
    disparity_margin_px: float = 6.0
    height_margin_m: float = 15.0
    height_range: tuple[float, float] | None = None
    min_ties: int = 12
    max_residual_px: float = 1.5
    matching: MatchOptions = field(default_factory=lambda: MatchOptions(coarse_max_px=0, tile=1024))
    dsm_cell: float | None = None
    dsm_statistic: str = "mean"
    dsm_radius: float = 1.0
    dsm_max_spread: float = 2.0
    fill_holes: int = 0
    despike_cells: float = 0.0
    cloud_format: str = "las"
    interpolation: str = "cubic"
    reference_dem: str | None = None
    stac: bool = True
    pair_sigma: bool = False
    sigma_edge_cells: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.tile, bool) or not isinstance(self.tile, int) or not 64 <= self.tile <= 4096:
            raise InvalidInputError(f"`tile` must be an integer in 64..4096; got {self.tile!r}")
        for name, lo in (("margin_px", 0), ("min_ties", 3), ("fill_holes", 0), ("sigma_edge_cells", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise InvalidInputError(f"`{name}` must be an integer >= {lo}; got {v!r}")
        for name in ("disparity_margin_px", "height_margin_m", "max_residual_px", "despike_cells"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InvalidInputError(f"`{name}` must be a finite number >= 0; got {v!r}")
        if self.max_residual_px <= 0:
            raise InvalidInputError(f"`max_residual_px` must be > 0; got {self.max_residual_px!r}")
        if self.height_range is not None:
            try:
                lo_h, hi_h = (float(v) for v in self.height_range)
            except (TypeError, ValueError):
                raise InvalidInputError(f"`height_range` must be two numbers; got {self.height_range!r}") from None
            if not (math.isfinite(lo_h) and math.isfinite(hi_h) and lo_h < hi_h):
                raise InvalidInputError(f"`height_range` must be finite with min < max; got {self.height_range!r}")
        if not isinstance(self.matching, MatchOptions):
            raise InvalidInputError(f"`matching` must be a MatchOptions; got {type(self.matching).__name__}")
        if self.dsm_cell is not None and not (isinstance(self.dsm_cell, (int, float)) and math.isfinite(self.dsm_cell)
                                              and self.dsm_cell > 0):
            raise InvalidInputError(f"`dsm_cell` must be a finite number > 0; got {self.dsm_cell!r}")
        if self.dsm_statistic not in STATISTICS:
            raise InvalidInputError(f"unknown DSM statistic {self.dsm_statistic!r}; expected one of "
                                    f"{list(STATISTICS)}")
        for name in ("dsm_radius", "dsm_max_spread"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and 0 <= v <= 5):
                raise InvalidInputError(f"`{name}` must be a number in [0, 5]; got {v!r}")
        if self.cloud_format not in ("las", "laz", "ply", "none"):
            raise InvalidInputError(f"unknown point cloud format {self.cloud_format!r}; expected las, laz, ply or "
                                    "none")
        if self.interpolation not in ("nearest", "linear", "cubic"):
            raise InvalidInputError(f"unknown interpolation {self.interpolation!r}; expected nearest, linear or "
                                    "cubic")


@dataclass(frozen=True, eq=False)
class RpcTile:
    """What happened in one tile: its window, rectification, tie-point parallax, range, points."""

    window: tuple[int, int, int, int]
    n_ties: int
    borrowed_ties: bool
    height_range: tuple[float, float]
    rectification: AffineRectification | None
    parallax: TileParallax | None
    disparity_range: tuple[float, float] | None
    n_points: int
    density: float
    error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"window": list(self.window), "n_ties": self.n_ties, "borrowed_ties": self.borrowed_ties,
                "height_range": list(self.height_range),
                "parallax": None if self.parallax is None else self.parallax.to_dict(),
                "rectification": None if self.rectification is None else self.rectification.to_dict(),
                "disparity_range": None if self.disparity_range is None else list(self.disparity_range),
                "n_points": self.n_points, "density": self.density, "error": self.error}


@dataclass(frozen=True, eq=False)
class RpcDenseResult:
    """What :func:`run_dense_rpc` did and wrote.

    ``parallax_rms_px``: RMS vertical parallax of the tie points of every tile after local epipolar
    resampling and pointing correction; ``parallax_max_tile_rms_px``: the worst tile's RMS;
    ``parallax_before_rms_px``: the same before the correction (RPCs alone). ``roi``: statistics of
    the DSM cells that fall in the region of interest (:func:`roi_statistics`). ``sigma`` (with
    ``RpcDenseOptions.pair_sigma``): the pair's heights and their standard errors, (H, W) float64 each
    (metres, NaN where none), on the grid of the affine geotransform (the third item; the DSM's cells).
    """

    out_dir: Path
    files: tuple[Path, ...]
    tiles: tuple[RpcTile, ...]
    n_points: int
    dsm: DsmResult
    dsm_cell: float
    crs: str
    roi: tuple[int, int, int, int]
    roi_stats: dict[str, float]
    parallax_rms_px: float
    parallax_max_tile_rms_px: float
    parallax_before_rms_px: float
    seconds: float
    comparison: HeightComparison | None = None
    tile_option: int | None = None
    gsd: float | None = None
    sigma: tuple[NDArray[np.float64], NDArray[np.float64], Any] | None = None

    def summary_lines(self) -> list[str]:
        ok = [t for t in self.tiles if t.error is None]
        sides = sorted({(t.window[2], t.window[3]) for t in self.tiles})
        size = ", ".join(f"{w} x {h}" for w, h in sides)
        nx = len({t.window[0] for t in self.tiles})
        ny = len({t.window[1] for t in self.tiles})
        how = "" if self.tile_option is None else (
            f"; --tile {self.tile_option} cuts the {self.roi[2]} x {self.roi[3]} px ROI into {nx} x {ny} equal tiles")
        cell = f"{self.dsm_cell:g} m"
        if self.gsd is not None:
            cell += f" (the ground pixel {self.gsd:.4g} m, rounded to 2 significant digits)"
        lines = [
            f"tiles: {len(ok)} of {len(self.tiles)} matched ({size} px{how})",
            f"vertical parallax of the tie points after local epipolar resampling: RMS {self.parallax_rms_px:.3f} "
            f"px, worst tile {self.parallax_max_tile_rms_px:.3f} px (RPCs alone: {self.parallax_before_rms_px:.3f} "
            "px)",
            f"points: {self.n_points}",
            f"DSM: {self.dsm.height.shape[1]} x {self.dsm.height.shape[0]} cells of {cell} ({self.crs}, heights above "
            f"the WGS 84 ellipsoid), origin on whole multiples of the cell, {100 * self.roi_stats['coverage']:.1f}% of "
            f"the ROI cells have a height, median {self.roi_stats['median_m']:.1f} m",
        ]
        if self.comparison is not None:
            lines.append(self.comparison.summary_line(cell=self.dsm_cell)
                         + " (the reference DEM's heights taken as they are: the DSM's are ellipsoidal)")
        lines += [f"outputs in {self.out_dir}: " + ", ".join(
                      p.relative_to(self.out_dir).as_posix() if p.is_relative_to(self.out_dir) else str(p)
                      for p in self.files),
                  f"time {self.seconds:.1f} s"]
        return lines


# ---------------------------------------------------------------------------- triangulation
def triangulate_rpc(left_rpc: Any, right_rpc: Any, left: ArrayLike, right: ArrayLike, *,
                    cameras: tuple[AffineCamera, AffineCamera] | None = None, height: float | None = None,
                    iterations: int = 4) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ground points (lon, lat, h) (N, 3) of corresponding pixels, and their residuals (N,) px.

    Least squares on (lon, lat, h) with both RPC projections (Gauss-Newton, numerical Jacobian in
    a local metric frame), started from the affine cameras' linear solution (``cameras``) or, without
    them, from the left pixel localised at ``height`` (default: the left RPC's height offset). The
    residual is the RMS of the four image residuals.

    Raises
    ------
    ShapeError
        ``left`` and ``right`` are not (N, 2) of one length.
    """
    pl = np.asarray(left, dtype=np.float64).reshape(-1, 2) if np.size(left) else np.zeros((0, 2))
    pr = np.asarray(right, dtype=np.float64).reshape(-1, 2) if np.size(right) else np.zeros((0, 2))
    if np.shape(left)[-1:] != (2,) or pl.shape != pr.shape:
        raise ShapeError(f"`left` and `right` must be (N, 2) of one length; got {np.shape(left)} and "
                         f"{np.shape(right)}", actual_shape=np.shape(right), expected_shape=np.shape(left))
    n = len(pl)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0)
    obs = np.hstack([pl, pr])
    if cameras is not None:
        cl, cr = cameras
        frame = cl.frame
        A = np.vstack([cl.matrix, cr.matrix])
        b = obs - np.concatenate([cl.offset, cr.offset])
        X = b @ np.linalg.pinv(A).T
    else:
        h0 = float(left_rpc.height_off if height is None else height) if hasattr(left_rpc, "height_off") \
            else float(height if height is not None else 0.0)
        g0 = left_rpc.localize(pl, h0, on_failure="nan")
        ok = np.isfinite(g0).all(axis=1)
        c = g0[ok].mean(axis=0) if ok.any() else np.array([0.0, 0.0, h0])
        frame = LocalFrame(float(c[0]), float(c[1]), h0)
        X = frame.to_local(np.where(np.isfinite(g0), g0, c))

    def proj(Xl: NDArray[np.float64]) -> NDArray[np.float64]:
        g = frame.to_ground(Xl)
        return np.hstack([left_rpc._project(g), right_rpc._project(g)])

    step = 0.5
    for _ in range(iterations):
        r = proj(X) - obs
        J = np.empty((n, 4, 3))
        for k in range(3):
            dX = np.zeros(3)
            dX[k] = step
            J[:, :, k] = (proj(X + dX) - proj(X - dX)) / (2 * step)
        JtJ = np.einsum("nik,nil->nkl", J, J)
        Jtr = np.einsum("nik,ni->nk", J, r)
        with np.errstate(invalid="ignore"):
            try:
                dx = np.linalg.solve(JtJ, -Jtr[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:
                dx = np.einsum("nkl,nl->nk", np.linalg.pinv(JtJ), -Jtr)
        X = X + dx
        if np.nanmax(np.abs(dx)) < 1e-4:
            break
    r = proj(X) - obs
    res = np.sqrt(np.mean(r ** 2, axis=1))
    return frame.to_ground(X), res


# ---------------------------------------------------------------------------- helpers
def _check_roi(roi: Any, width: int, height: int) -> tuple[int, int, int, int]:
    if roi is None:
        return 0, 0, width, height
    try:
        x, y, w, h = (int(v) for v in roi)
        if any(float(v) != int(v) for v in roi):
            raise ValueError
    except (TypeError, ValueError):
        raise InvalidInputError(f"`roi` must be four integers (x, y, width, height); got {roi!r}") from None
    if w < 32 or h < 32 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise InvalidInputError(f"`roi` {roi!r} must lie inside the left image ({width} x {height} px) and be at "
                                "least 32 x 32 px")
    return x, y, w, h


def _tiles(roi: tuple[int, int, int, int], tile: int) -> list[tuple[int, int, int, int]]:
    x, y, w, h = roi
    nx, ny = max(1, round(w / tile)), max(1, round(h / tile))
    xs = np.linspace(x, x + w, nx + 1).round().astype(int)
    ys = np.linspace(y, y + h, ny + 1).round().astype(int)
    return [(int(xs[i]), int(ys[j]), int(xs[i + 1] - xs[i]), int(ys[j + 1] - ys[j]))
            for j in range(ny) for i in range(nx)]


def _tile_ties(left: StrPath, right: StrPath, left_rpc: Any, right_rpc: Any, window: tuple[int, int, int, int],
               heights: tuple[float, float], right_size: tuple[int, int], margin: int = 16
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Tie points of one tile: its left window (plus ``margin``) against the right window the RPCs
    give for the height prior. Empty arrays when nothing matches."""
    c0, r0, w, h = window
    lc0, lr0, lw, lh = c0 - margin, r0 - margin, w + 2 * margin, h + 2 * margin
    cc, rr = np.meshgrid(np.linspace(lc0, lc0 + lw - 1, 5), np.linspace(lr0, lr0 + lh - 1, 5))
    px = np.column_stack([cc.ravel(), rr.ravel()])
    g = np.vstack([left_rpc.localize(px, hh, on_failure="nan") for hh in np.linspace(*heights, 5)])
    g = g[np.isfinite(g).all(axis=1)]
    empty = np.zeros((0, 2))
    if len(g) == 0:
        return empty, empty
    q = right_rpc.project(g)
    W, H = right_size
    rc0, rr0 = max(int(math.floor(q[:, 0].min())) - 32, 0), max(int(math.floor(q[:, 1].min())) - 32, 0)
    rc1, rr1 = min(int(math.ceil(q[:, 0].max())) + 32, W), min(int(math.ceil(q[:, 1].max())) + 32, H)
    if rc1 - rc0 < 16 or rr1 - rr0 < 16:
        return empty, empty
    L, lv = read_window(left, lc0, lr0, lw, lh, bands=[1])
    R, rv = read_window(right, rc0, rr0, rc1 - rc0, rr1 - rr0, bands=[1])
    cfg = MatcherConfig(verify="fundamental", keep_unrefined=False, min_inliers=8, max_keypoints=8000)
    try:
        m = match_arrays(L[:, :, 0], R[:, :, 0], left_valid=lv, right_valid=rv, config=cfg).matches
    except EstimationError as err:
        logger.info("tile %s: no tie points (%s)", window, err)
        return empty, empty
    return m.left + [lc0, lr0], m.right + [rc0, rr0]


def _robust(v: NDArray[np.float64], k: float = 5.0) -> NDArray[np.bool_]:
    med = np.median(v)
    s = 1.4826 * np.median(np.abs(v - med))
    return np.asarray(np.abs(v - med) <= max(k * s, 1e-9), bool)


def roi_statistics(dsm: DsmResult, rpc: Any, roi: tuple[int, int, int, int], crs: str,
                   height_range: tuple[float, float] | None = None) -> dict[str, float]:
    """Statistics of the DSM cells inside the region of interest of the image of ``rpc``.

    A cell is in the ROI when its centre, at its height (or at the median height where it has
    none), projects into the ROI. Returns ``n_cells``, ``coverage`` (share with a height),
    ``median_m``, ``p01_m``, ``p99_m`` and, with ``height_range``, ``in_range`` (share of all the
    ROI cells whose height lies in the range).
    """
    H, W = dsm.height.shape
    rr, cc = np.mgrid[0:H, 0:W]
    t = dsm.transform
    x = t.c + (cc.ravel() + 0.5) * t.a
    y = t.f + (rr.ravel() + 0.5) * t.e
    z = dsm.height.ravel().astype(np.float64)
    has = z != DSM_NODATA
    med = float(np.median(z[has])) if has.any() else float(rpc.height_off)
    ll = transform_xy(crs, "EPSG:4326", np.column_stack([x, y]))
    p = rpc.project(np.column_stack([ll, np.where(has, z, med)]))
    x0, y0, w, h = roi
    inside = (p[:, 0] >= x0 - 0.5) & (p[:, 0] < x0 + w - 0.5) & (p[:, 1] >= y0 - 0.5) & (p[:, 1] < y0 + h - 0.5)
    n = int(inside.sum())
    zi = z[inside & has]
    out = {"n_cells": float(n), "coverage": float(len(zi) / n) if n else 0.0,
           "median_m": float(np.median(zi)) if len(zi) else float("nan"),
           "p01_m": float(np.percentile(zi, 1)) if len(zi) else float("nan"),
           "p99_m": float(np.percentile(zi, 99)) if len(zi) else float("nan")}
    if height_range is not None:
        lo, hi = height_range
        out["in_range"] = float(((zi >= lo) & (zi <= hi)).sum() / n) if n else 0.0
    return out


# ---------------------------------------------------------------------------- the chain
def run_dense_rpc(
    left: StrPath,
    right: StrPath,
    out_dir: StrPath,
    *,
    roi: tuple[int, int, int, int] | None = None,
    left_rpc: RPC | None = None,
    right_rpc: RPC | None = None,
    options: RpcDenseOptions | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> RpcDenseResult:
    """The dense chain of an RPC pair over a region of interest of the left image.

    Parameters
    ----------
    left, right : path
        The two images (GeoTIFF with RPC tags, or any raster GDAL finds an RPC for); band 1 is used.
    out_dir : path
        Output folder (see the module docstring for its files).
    roi : (x, y, width, height), optional
        Region of interest of the left image, pixels; default the whole image.
    left_rpc, right_rpc : RPC, optional
        Models to use instead of the images' own.
    options : RpcDenseOptions, optional
    overwrite : bool
    progress : callable(stage, done, total), optional

    Raises
    ------
    InvalidInputError
        Bad ROI or options, an image without RPC.
    RasterIOError
        Unreadable image or reference DEM, or the outputs cannot be written.
    StereoError
        No tie points anywhere, or no 3D point.

    On any error nothing is left in ``out_dir``, and the folder is removed again when the run created it.
    """
    t0 = time.perf_counter()
    opts = options or RpcDenseOptions()
    if not isinstance(opts, RpcDenseOptions):
        raise InvalidInputError(f"`options` must be an RpcDenseOptions; got {type(opts).__name__}")
    if opts.reference_dem is not None and not Path(opts.reference_dem).is_file():
        raise InvalidInputError(f"reference DEM file not found: {str(opts.reference_dem)!r}")
    il, ir = raster_info(left), raster_info(right)
    rl = left_rpc if left_rpc is not None else rpc_from_raster(left)
    rr = right_rpc if right_rpc is not None else rpc_from_raster(right)
    box = _check_roi(roi, il.width, il.height)
    prior = opts.height_range if opts.height_range is not None else rl.validity_box[2]
    suffix = None if opts.cloud_format == "none" else "." + opts.cloud_format
    names = ["dsm.tif", "dense_rpc.json"] + ([f"points{suffix}"] if suffix else []) + ([FOLDER_ITEM] if opts.stac
                                                                                       else [])
    ws = Workspace(out_dir, overwrite=overwrite, inputs=[left, right] + ([opts.reference_dem]
                                                                       if opts.reference_dem else []))
    ws.prepare(*names)
    try:
        return _run(left, right, Path(out_dir), ws, names, suffix, rl, rr, ir, box, prior, opts, progress, t0)
    except BaseException:
        ws.discard_root()  # a folder this run created goes again (the outputs were never renamed into it)
        raise


def _run(left: StrPath, right: StrPath, out: Path, ws: Workspace, names: list[str], suffix: str | None, rl: Any,
         rr: Any, ir: Any, box: tuple[int, int, int, int], prior: Any, opts: RpcDenseOptions,
         progress: Progress | None, t0: float) -> RpcDenseResult:
    """The chain of :func:`run_dense_rpc` after its inputs are checked and its folder prepared."""

    def prog(stage: str, done: int, total: int) -> None:
        if progress is not None:
            progress(stage, done, total)

    tiles = _tiles(box, opts.tile)
    with gdal_cache_limit(GDAL_CACHE_MB):
        # 1. tie points per tile, their heights
        ties_l, ties_r, ties_t = [], [], []
        for i, win in enumerate(tiles):
            a, b = _tile_ties(left, right, rl, rr, win, (float(prior[0]), float(prior[1])), (ir.width, ir.height))
            ties_l.append(a)
            ties_r.append(b)
            ties_t.append(np.full(len(a), i))
            prog("tie points", i + 1, len(tiles))
        TL, TR, TT = np.vstack(ties_l), np.vstack(ties_r), np.concatenate(ties_t)
        if len(TL) < opts.min_ties:
            raise StereoError(f"only {len(TL)} tie points over the region of interest {box}: do the images overlap "
                              f"there (height prior {prior[0]:.0f}..{prior[1]:.0f} m)?")
        TG, tres = triangulate_rpc(rl, rr, TL, TR)
        good = np.isfinite(TG).all(axis=1) & np.isfinite(tres)
        good[good] &= _robust(tres[good], 5.0) | (tres[good] < opts.max_residual_px)
        good[good] &= _robust(TG[good, 2], 6.0)
        TL, TR, TT, TG = TL[good], TR[good], TT[good], TG[good]
        if len(TL) < opts.min_ties:
            raise StereoError(f"only {len(TL)} consistent tie points over the region of interest {box}")
        centre = np.median(TG, axis=0)
        crs = utm_crs(float(centre[0]), float(centre[1]))
        # 2. the DSM grid: the ROI's footprint over the tie points' heights
        hl, hh = float(TG[:, 2].min()) - 2 * opts.height_margin_m, float(TG[:, 2].max()) + 2 * opts.height_margin_m
        x, y, w, h = box
        edge = np.linspace(0, 1, 9)
        rim = np.vstack([np.column_stack([x + edge * (w - 1), np.full(9, y)]),
                         np.column_stack([x + edge * (w - 1), np.full(9, y + h - 1)]),
                         np.column_stack([np.full(9, x), y + edge * (h - 1)]),
                         np.column_stack([np.full(9, x + w - 1), y + edge * (h - 1)])])
        foot = np.vstack([rl.localize(rim, z) for z in (hl, hh)])
        fxy = transform_xy("EPSG:4326", crs, foot[:, :2])
        plan: list[tuple[int, NDArray[np.bool_], bool]] = []
        gsds = []
        for i, win in enumerate(tiles):
            sel = TT == i
            borrowed = False
            if sel.sum() < opts.min_ties:
                c = np.array([win[0] + win[2] / 2, win[1] + win[3] / 2])
                near = np.argsort(np.hypot(*(TL - c).T))[:opts.min_ties]
                sel = np.zeros(len(TL), bool)
                sel[near] = True
                borrowed = True
            plan.append((i, sel, borrowed))
        for i, sel, _ in plan[:: max(1, len(plan) // 5)]:
            hz = TG[sel, 2]
            cams = fit_affine_pair(rl, rr, tiles[i], (float(hz.min()), float(hz.max())))
            gsds.append(cams[0].gsd_m)
        gsd = float(np.median(gsds))
        cell = float(opts.dsm_cell) if opts.dsm_cell is not None else default_cell(gsd)
        bounds = (float(fxy[:, 0].min()) - 2 * cell, float(fxy[:, 1].min()) - 2 * cell,
                  float(fxy[:, 0].max()) + 2 * cell, float(fxy[:, 1].max()) + 2 * cell)
        grid = DsmGrid(bounds, cell, statistic=opts.dsm_statistic, crs=crs, radius=opts.dsm_radius,
                       max_spread=opts.dsm_max_spread, heights="m above the WGS 84 ellipsoid")
        sgrid = (SigmaGrid(bounds, cell, crs=crs, radius=opts.dsm_radius, max_spread=opts.dsm_max_spread,
                           edge_cells=opts.sigma_edge_cells) if opts.pair_sigma else None)

        files: list[Path] = []
        results: list[RpcTile] = []
        n_total = 0
        comparison = None
        rep = out / "report"
        made_rep = False
        try:
            with ws.transaction(), contextlib.ExitStack() as stack:
                paths = {n: stack.enter_context(ws.output(out / n)) for n in names}
                files = [out / n for n in names]
                writer = None
                if suffix is not None:
                    writer = point_writer(paths[f"points{suffix}"], suffix[1:],
                                          offset=np.round(np.append(transform_xy("EPSG:4326", crs, centre[None, :2])[0],
                                                                    centre[2]), 0),
                                          crs_wkt=gdal_wkt(crs),
                                          comment=f"UTM {crs}, ellipsoidal heights")
                for i, sel, borrowed in plan:
                    tile = _dense_tile(left, right, rl, rr, tiles[i], TL[sel], TR[sel], TG[sel], borrowed, opts,
                                       grid, writer, crs, sgrid)
                    results.append(tile)
                    n_total += tile.n_points
                    prog("tiles", i + 1, len(tiles))
                if writer is not None:
                    writer.close()
                if n_total == 0:
                    errs = "; ".join(sorted({t.error for t in results if t.error}))
                    raise StereoError(f"no 3D point in the region of interest {box}" + (f": {errs}" if errs else ""))
                dsm = grid.result(max_hole_cells=opts.fill_holes, despike_cells=opts.despike_cells)
                dsm.write(paths["dsm.tif"], overwrite=True)
                stats = roi_statistics(dsm, rl, box, crs)
                dz = None
                if opts.reference_dem is not None:
                    comparison, dz = compare_with_dem(dsm, opts.reference_dem)
                pars = [t.parallax for t in results if t.parallax is not None and t.parallax.n]
                after = np.concatenate([p.after_px[p.keep] for p in pars]) if pars else np.zeros(0)
                before = np.concatenate([p.before_px[p.keep] for p in pars]) if pars else np.zeros(0)

                def rms(a: NDArray[np.float64]) -> float:
                    return float(np.sqrt(np.mean(a ** 2))) if len(a) else float("nan")

                worst = max((p.rms_after_px for p in pars), default=float("nan"))
                summary = {
                    "left": str(left), "right": str(right), "roi": list(box), "crs": crs, "dsm_cell": cell,
                    "n_points": n_total, "tile": opts.tile,
                    "vertical_parallax_px": {"rms_after": rms(after), "worst_tile_rms_after": worst,
                                             "rms_before": rms(before), "n": len(after)},
                    "dsm": {"width": int(dsm.height.shape[1]), "height": int(dsm.height.shape[0]),
                            "coverage": dsm.coverage, "roi": stats, "cell_m": cell,
                            "ground_sampling_distance_m": gsd, "transform": list(dsm.transform)[:6],
                            "heights": "m above the WGS 84 ellipsoid",
                            "bands": ["height (nodata -9999)", "count: points per cell", "filled: 1 interpolated"]},
                    "comparison": None if comparison is None else {
                        "reference_dem": str(opts.reference_dem),
                        **{k: v for k, v in comparison.__dict__.items() if k != "histogram"}},
                    "tiles": [t.to_dict() for t in results],
                }
                with open(paths["dense_rpc.json"], "w", encoding="utf-8") as fh:
                    json.dump(json_safe(summary), fh, indent=2)
                if comparison is not None and dz is not None:
                    if not rep.exists():
                        rep.mkdir()
                        made_rep = True
                    for name, draw in (
                            ("dsm.png", lambda t: save_picture(t, dsm.height, title="DSM", cmap="terrain",
                                                               label="height (m)", nodata=DSM_NODATA)),
                            ("dz.png", lambda t: save_picture(t, dz, title="DSM - reference DEM", cmap="RdBu_r",
                                                              label="dz (m)", symmetric=True)),
                            ("dz_histogram.png", lambda t: save_histogram(t, comparison))):
                        with ws.output(rep / name) as tmp:
                            draw(tmp)
                        files.append(rep / name)
                if opts.stac:  # the STAC Item of the DSM and the point cloud, committed with them
                    acc = {"vertical_parallax_rms_px": rms(after), "dsm_coverage": dsm.coverage}
                    if comparison is not None:
                        acc.update({f"reference_dem_{k}": v for k, v in comparison.__dict__.items()
                                    if isinstance(v, (int, float)) and not isinstance(v, bool)})
                    assets = {"dsm": StacAsset(out / "dsm.tif", ("data",), "DSM (ellipsoidal heights)",
                                               source=paths["dsm.tif"]),
                              "metadata": StacAsset(out / "dense_rpc.json", ("metadata",), "summary",
                                                    source=paths["dense_rpc.json"])}
                    if suffix:
                        assets["points"] = StacAsset(out / f"points{suffix}", ("data",), "point cloud",
                                                     source=paths[f"points{suffix}"])
                    Path(paths[FOLDER_ITEM]).write_text(stac_text(
                        out / FOLDER_ITEM, item_id=out.name or "dense-rpc", assets=assets, command="stereo dense-rpc",
                        grid=raster_grid(paths["dsm.tif"]), accuracy=acc,
                        options=options_of(opts, roi=list(box)), inputs=[left, right, opts.reference_dem]),
                        encoding="utf-8")
        except BaseException:
            if made_rep:
                with contextlib.suppress(OSError):
                    rep.rmdir()
            raise
    sig = None
    if sgrid is not None:
        sh, ss = sgrid.result()
        sig = (sh, ss, sgrid.transform)
    return RpcDenseResult(out, tuple(files), tuple(results), n_total, dsm, cell, crs, box, stats, rms(after), worst,
                          rms(before), time.perf_counter() - t0, comparison, opts.tile,
                          gsd if opts.dsm_cell is None else None, sig)


def _dense_tile(left: StrPath, right: StrPath, rl: Any, rr: Any, win: tuple[int, int, int, int],
                tl: NDArray[np.float64], tr: NDArray[np.float64], tg: NDArray[np.float64], borrowed: bool,
                opts: RpcDenseOptions, grid: DsmGrid, writer: Any, crs: str, sgrid: SigmaGrid | None = None
                ) -> RpcTile:
    """Rectify, match and triangulate one tile; add its points to the grid and the cloud (and, with
    ``sgrid``, with their height standard errors to that grid)."""
    hz = tg[:, 2]
    hr = (float(np.percentile(hz, 1)) - opts.height_margin_m, float(np.percentile(hz, 99)) + opts.height_margin_m)
    try:
        cams = fit_affine_pair(rl, rr, win, hr)
        rect0 = rectify_affine(*cams)
    except EstimationError as err:
        return RpcTile(win, len(tl), borrowed, hr, None, None, None, 0, 0.0, str(err))
    rect, par = rect0.with_tie_points(tl, tr)
    d = rect.disparity(tl[par.keep], tr[par.keep])
    # the disparity range: the tie points', widened to the tile's height range
    d_h = (np.array(hr) - cams[0].frame.h0) * rect.disparity_per_m
    dmin = min(float(d.min()) if len(d) else d_h[0], float(d_h[0])) - opts.disparity_margin_px
    dmax = max(float(d.max()) if len(d) else d_h[1], float(d_h[1])) + opts.disparity_margin_px
    c0, r0, w, h = win
    corners = np.array([[c0, r0], [c0 + w - 1, r0], [c0, r0 + h - 1], [c0 + w - 1, r0 + h - 1]], float)
    q = rect.rectified_from_original("left", corners)
    m = opts.margin_px
    x0 = int(math.floor(q[:, 0].min())) - m + int(math.floor(min(0.0, -dmax)))
    x1 = int(math.ceil(q[:, 0].max())) + m + int(math.ceil(max(0.0, -dmin)))
    y0, y1 = int(math.floor(q[:, 1].min())) - m, int(math.ceil(q[:, 1].max())) + m
    W, H = x1 - x0 + 1, y1 - y0 + 1
    L, lv = resample_rectified(left, rect.left, x0, y0, W, H, interpolation=opts.interpolation)
    R, rv = resample_rectified(right, rect.right, x0, y0, W, H, interpolation=opts.interpolation)
    if not lv.any() or not rv.any():
        return RpcTile(win, len(tl), borrowed, hr, rect, par, (dmin, dmax), 0, 0.0, "no image data in the window")
    try:
        dm = match_pair(L, R, left_valid=lv, right_valid=rv, disparity_range=(dmin, dmax), options=opts.matching)
    except StereoError as err:
        return RpcTile(win, len(tl), borrowed, hr, rect, par, (dmin, dmax), 0, 0.0, str(err))
    disp = np.asarray(dm.disparity, dtype=np.float64)
    ok = np.isfinite(disp) & ~dm.filled
    yy, xx = np.nonzero(ok)
    xr = xx.astype(np.float64) + x0
    yr = yy.astype(np.float64) + y0
    dd = disp[yy, xx]
    pl = rect.original_from_rectified("left", np.column_stack([xr, yr]))
    core = (pl[:, 0] >= c0 - 0.5) & (pl[:, 0] < c0 + w - 0.5) & (pl[:, 1] >= r0 - 0.5) & (pl[:, 1] < r0 + h - 0.5)
    n_core = int(core.sum())
    pl, xr, yr, dd, yy, xx = pl[core], xr[core], yr[core], dd[core], yy[core], xx[core]
    pr = rect.original_from_rectified("right", np.column_stack([xr - dd, yr]))
    g, res = triangulate_rpc(rl, rr, pl, pr, cameras=cams, iterations=3)
    keep = np.isfinite(g).all(axis=1) & (res <= opts.max_residual_px)
    g, yy, xx = g[keep], yy[keep], xx[keep]
    n = len(g)
    if n:
        xy = transform_xy("EPSG:4326", crs, g[:, :2])
        xyz = np.column_stack([xy, g[:, 2]])
        grid.add(xyz)
        if sgrid is not None:
            # the disparity's standard error (px) over the disparity per metre of height: sigma_Z (m)
            sd = disparity_sigma(L, R, np.where(ok, disp, np.nan))[yy, xx].astype(np.float64)
            sgrid.add(xyz, sd / max(abs(float(rect.disparity_per_m)), 1e-9))
        if writer is not None:
            v = L[yy, xx].astype(np.float64)
            lo, hi = np.percentile(L[lv], [1, 99]) if lv.any() else (0.0, 1.0)
            grey = np.clip((v - lo) / max(hi - lo, 1e-9) * 255, 0, 255)
            writer.write(xyz, np.repeat(grey[:, None], 3, axis=1))
    # density: points per core pixel of the left tile
    return RpcTile(win, len(tl), borrowed, hr, rect, par, (dmin, dmax), n, n / max(1, w * h),
                   None if n else f"no disparity survived in tile {win} ({n_core} matched in the core)")
