"""Dense matching of a normal-case pair: semi-global matching (OpenCV StereoSGBM), tiled.

Per tile: a disparity range (from the tie points and a coarse pass), StereoSGBM (three-way
mode, 3 x 3 blocks, BT cost on the colour bands) with its left-right consistency check
(``disp12MaxDiff``) and uniqueness test, its sub-pixel (1/16 px) parabola, speckle removal, the
occlusion (collision) test and border rule, optionally a half-resolution pass over the holes
(``MatchOptions.hole_p2``), then the pixels next to depth edges classified between the near and
far surface by their grey value (``MatchOptions.edge_radius``), a 3 x 3 median of the valid
disparities, a Lucas-Kanade sub-pixel step (:mod:`stereo.dense.refine`), a fill of small holes by
the background (the smaller of the nearest valid disparities left and right on the row: holes are
mostly occlusions, which belong to the farther surface), and a per-pixel confidence. The tests
after SGBM and the post-processing run by strips of rows (:mod:`stereo.dense.checks`).

Disparity convention: ``d = col_left - col_right`` (rectified photos); NaN where no disparity.

Tiling: the left photo is cut into ``tile`` x ``tile`` cores with ``overlap`` pixels on each side;
the right window of a tile is the left window moved by the tile's disparity range. Memory holds one
tile pair, its SGBM buffers and the coarse (overview) disparity, whatever the photo size.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from affine import Affine
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError, StereoError
from rectify.raster.distributed import Scheduler, resolve_scheduler, run_windows
from rectify.raster.io import (
    MaskPolicy,
    TiledWriter,
    WindowReader,
    ignore_not_georeferenced,
    iter_windows,
    raster_info,
    read_overview,
)
from stereo.dense.checks import erode_valid as _erode
from stereo.dense.checks import noise_fill as _noise_fill
from stereo.dense.checks import row_tests as _tests
from stereo.dense.checks import strip_rows as _strip_rows
from stereo.dense.checks import strips as _strips
from stereo.dense.holes import fill_holes_half
from stereo.dense.refine import confidence as _confidence
from stereo.dense.refine import edge_classify, fill_background, refine_subpixel
from stereo.dense.refine import median_valid as _median_valid

logger = logging.getLogger(__name__)

__all__ = ["DisparityMap", "MatchOptions", "MatchStats", "NODATA", "fill_background", "match_pair",
           "match_rasters", "refine_subpixel", "sgbm_baseline"]

StrPath = str | Path

#: nodata value of the disparity and confidence rasters
NODATA = -9999.0


@dataclass(frozen=True)
class MatchOptions:
    """Options of the dense matcher.

    Attributes
    ----------
    block_size : int
        SGBM block side (odd, 1..11).
    p1, p2 : float
        SGBM smoothness penalties per ``channels * block_size**2`` (OpenCV's sample uses 8 and 32).
    uniqueness : int
        SGBM uniqueness ratio, percent.
    lr_max_diff : int
        Left-right consistency tolerance, pixels (negative: no check).
    speckle_window, speckle_range : int
        Speckle removal: regions of at most ``speckle_window`` pixels differing by more than
        ``speckle_range`` from their surroundings are removed (0: off).
    median : bool
        3 x 3 median of the valid disparities.
    edge_radius : int
        0: off. Else pixels next to a depth edge are classified by their grey value between the
        near and the far surface of their ``(2 edge_radius + 1)^2`` window and take that surface's
        mean disparity (:func:`stereo.dense.refine.edge_classify`, before the median; issue 30:
        Motorcycle bad-2.0 2.60 -> 2.29 %, Cones bad-1.0 2.26 -> 2.11 % at the previous density).
    fill_max_px : int
        Holes of at most this many pixels are filled by the background (0, the default: no fill);
        filled pixels are flagged and get confidence 0. For a disparity product only: the dense
        pipeline never turns filled disparities into points.
    tile, overlap : int
        Tile core side and the overlap on each side, pixels (arrays larger than ``tile + 2 overlap``
        and every raster are matched by tiles).
    margin_px : float
        Added on both sides of a tile's disparity range.
    coarse_max_px : int
        Longest side of the coarse pass (coarse-to-fine disparity ranges); 0 disables it.
    max_disparities : int
        Largest disparity search width of a tile (bounds memory and time).
    refine_iterations, refine_radius : int
        Least-squares sub-pixel refinement along the rows (iterations, 0: off; Gaussian window of
        radius ``refine_radius``, sigma ``refine_radius / 2``). The default radius 6 (3 before
        issue 30) gives smoother surfaces: NGI DSM roughness 1.67 -> 1.13 m, NMAD against the DEM
        4.14 -> 3.59 m, with Motorcycle and Cones unchanged.
    colour : bool
        Match the colour bands (BT cost per band) rather than the grey image (default: grey, which
        is faster and as accurate on the benchmarks).
    border_px : int
        Disparities whose left or right pixel lies within this many pixels of nodata are dropped
        (in a window that holds nodata, its left and right edges count as nodata too, columns
        outside the right photo are nodata). The top and bottom edges of a window do not: before
        issue 30 they did whenever the window held any nodata, which dropped a 4-row frame then.
    right_check : {"collision", "sgbm"}
        The left-right test besides SGBM's own: ``collision`` drops a pixel whose right pixel is
        also the match of a left pixel with a larger disparity (by more than ``lr_max_diff``: the
        nearer surface hides it); ``sgbm`` runs a second SGBM with the right photo as reference
        and keeps disparities that agree within ``lr_max_diff`` (twice the time).
    hole_p2 : float
        0 (the default): off. Else the large holes left by the tests above (at least
        :data:`stereo.dense.holes.MIN_HOLE` half-resolution pixels that can be matched) are matched
        again at half resolution, each on a box around it over the range of the disparities around
        it, with ``P2 = hole_p2`` (per ``channels * block_size**2``; a stronger smoothness penalty
        fills low-texture and steep areas) and the same tests at half resolution; a hole pixel takes
        the doubled half-resolution disparity when the 7 x 7 ZNCC of the half-resolution left photo
        and right photo warped by the box's disparities is at least ``hole_zncc`` and its right
        pixel passes the full-resolution border rule; the sub-pixel step then refines it at full
        resolution (:func:`stereo.dense.holes.fill_holes_half`). :class:`stereo.actions.dense.
        DenseOptions` uses 128 (NGI strip DSM coverage 87.3 -> 91.6 % of the overlap); on
        Middlebury, with its higher density, :func:`match_pair` leaves it off.
    hole_zncc : float
        The ZNCC a hole pixel's half-resolution disparity must reach, in [-1, 1] (default 0.7; 0.5
        with the full-resolution window of the whole-window pass before).
    """

    block_size: int = 3
    p1: float = 8.0
    p2: float = 32.0
    uniqueness: int = 10
    lr_max_diff: int = 1
    speckle_window: int = 400
    speckle_range: int = 2
    median: bool = True
    edge_radius: int = 4
    fill_max_px: int = 0
    tile: int = 1024
    overlap: int = 48
    margin_px: float = 8.0
    coarse_max_px: int = 320
    max_disparities: int = 512
    refine_iterations: int = 1
    refine_radius: int = 6
    colour: bool = False
    border_px: int = 4
    right_check: str = "collision"
    hole_p2: float = 0.0
    hole_zncc: float = 0.7

    def __post_init__(self) -> None:
        if not isinstance(self.block_size, int) or self.block_size < 1 or self.block_size > 11 \
                or self.block_size % 2 == 0:
            raise InvalidInputError(f"`block_size` must be an odd integer in 1..11; got {self.block_size!r}")
        for name in ("p1", "p2", "margin_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InvalidInputError(f"`{name}` must be a finite number >= 0; got {v!r}")
        if self.p2 <= self.p1:
            raise InvalidInputError(f"`p2` must exceed `p1`; got p1={self.p1!r}, p2={self.p2!r}")
        for name, lo in (("uniqueness", 0), ("speckle_window", 0), ("speckle_range", 0), ("fill_max_px", 0),
                         ("overlap", 0), ("coarse_max_px", 0), ("tile", 64), ("max_disparities", 16)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise InvalidInputError(f"`{name}` must be an integer >= {lo}; got {v!r}")
        if isinstance(self.lr_max_diff, bool) or not isinstance(self.lr_max_diff, int):
            raise InvalidInputError(f"`lr_max_diff` must be an integer; got {self.lr_max_diff!r}")
        if self.right_check not in ("collision", "sgbm"):
            raise InvalidInputError(f"`right_check` must be 'collision' or 'sgbm'; got {self.right_check!r}")
        if not isinstance(self.colour, bool):
            raise InvalidInputError(f"`colour` must be a bool; got {self.colour!r}")
        for name, lo in (("refine_iterations", 0), ("refine_radius", 1), ("border_px", 0), ("edge_radius", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise InvalidInputError(f"`{name}` must be an integer >= {lo}; got {v!r}")
        if not (isinstance(self.hole_p2, (int, float)) and not isinstance(self.hole_p2, bool)
                and math.isfinite(self.hole_p2) and self.hole_p2 >= 0):
            raise InvalidInputError(f"`hole_p2` must be a finite number >= 0 (0: off); got {self.hole_p2!r}")
        if self.hole_p2 and self.hole_p2 <= self.p1:
            raise InvalidInputError(f"`hole_p2` must exceed `p1`; got p1={self.p1!r}, hole_p2={self.hole_p2!r}")
        if not (isinstance(self.hole_zncc, (int, float)) and not isinstance(self.hole_zncc, bool)
                and -1.0 <= self.hole_zncc <= 1.0):
            raise InvalidInputError(f"`hole_zncc` must be a number in [-1, 1]; got {self.hole_zncc!r}")
        if self.tile % 16:
            raise InvalidInputError(f"`tile` must be a multiple of 16; got {self.tile}")


@dataclass(frozen=True, eq=False)
class DisparityMap:
    """A disparity map of the left rectified photo.

    Attributes
    ----------
    disparity : (H, W) float32
        ``col_left - col_right``, px; NaN where there is none.
    confidence : (H, W) float32
        In [0, 1]; 0 where there is no disparity or it was filled.
    filled : (H, W) bool
        Disparities filled by the background rather than matched.
    """

    disparity: NDArray[np.float32]
    confidence: NDArray[np.float32]
    filled: NDArray[np.bool_]
    options: MatchOptions = field(default_factory=MatchOptions)

    def __post_init__(self) -> None:
        for a in (self.disparity, self.confidence, self.filled):
            a.flags.writeable = False

    @property
    def valid(self) -> NDArray[np.bool_]:
        return np.isfinite(self.disparity)

    @property
    def density(self) -> float:
        """Share of pixels with a disparity."""
        return float(self.valid.mean()) if self.disparity.size else 0.0


@dataclass(frozen=True)
class MatchStats:
    """What :func:`match_rasters` did: pixels, valid share, filled share, tiles, range."""

    width: int
    height: int
    n_valid: int
    n_filled: int
    n_tiles: int
    disparity_min: float
    disparity_max: float

    @property
    def density(self) -> float:
        return self.n_valid / max(1, self.width * self.height)


# ---------------------------------------------------------------- helpers
def _as_image(a: ArrayLike, name: str) -> NDArray:
    img = np.asarray(a)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)) or min(img.shape[:2]) < 8:
        raise ShapeError(f"`{name}` must be an (H, W) or (H, W, 3) image of at least 8 x 8 px; got {img.shape}",
                         actual_shape=img.shape)
    if img.dtype.kind not in "uif":
        raise InvalidInputError(f"`{name}` must be numeric; got dtype {img.dtype}")
    if img.ndim == 3:
        img = img[:, :, :3]
    return img


def _to_uint8(img: NDArray, valid: NDArray[np.bool_] | None) -> NDArray[np.uint8]:
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    f = img.astype(np.float32)
    m = np.isfinite(f) if valid is None else (valid[..., None] if f.ndim == 3 else valid) & np.isfinite(f)
    if not m.any():
        return np.zeros(img.shape, np.uint8)
    lo, hi = np.percentile(f[np.broadcast_to(m, f.shape)], [0.5, 99.5])
    scale = 255.0 / max(float(hi - lo), 1e-6)
    return np.clip(np.nan_to_num((f - lo) * scale), 0, 255).astype(np.uint8)


def _sgbm(opts: MatchOptions, channels: int, min_disp: int, num_disp: int) -> cv2.StereoSGBM:
    bs = opts.block_size
    return cv2.StereoSGBM.create(
        minDisparity=int(min_disp), numDisparities=int(num_disp), blockSize=bs,
        P1=int(round(opts.p1 * channels * bs * bs)), P2=int(round(opts.p2 * channels * bs * bs)),
        disp12MaxDiff=int(opts.lr_max_diff), uniquenessRatio=int(opts.uniqueness),
        speckleWindowSize=int(opts.speckle_window), speckleRange=int(opts.speckle_range),
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def _match_window(L: NDArray[np.uint8], R: NDArray[np.uint8], lv: NDArray[np.bool_], rv: NDArray[np.bool_],
                  dmin: int, dmax: int, opts: MatchOptions, *, lr_check: bool = True, pad: int | None = None
                  ) -> NDArray[np.float32]:
    """SGBM of one window pair whose columns coincide; d in [dmin, dmax]; NaN where none.

    The caller passes the right window already moved by ``dmin`` (``R[:, x] = right[:, x - dmin]``),
    so that SGBM searches [0, dmax - dmin]. Invalid pixels are replaced by noise first (they match
    nothing). Then, besides SGBM's own uniqueness and consistency tests:

    - with ``lr_check`` (and ``opts.lr_max_diff >= 0``), a left-right test (``opts.right_check``):
      the collision test (a right pixel matched by two left pixels belongs to the nearer one) or a
      second SGBM with the right photo as reference (both windows mirrored) and a consistency check
      within ``opts.lr_max_diff`` px. This removes the matches of pixels that are hidden in, or
      outside of, the right photo, which SGBM's built-in check lets through next to image borders;
    - disparities whose left pixel or right pixel lies within ``opts.border_px`` of an invalid pixel
      are dropped (the window's left and right edges count as invalid, its top and bottom ones not).

    ``pad``: columns reflected onto the left of both windows before SGBM (default ``num + 1``: SGBM
    leaves its first ``num`` columns unmatched); fewer when the windows' first columns are context.
    """
    if L.ndim == 3 and not opts.colour:
        L = np.asarray(cv2.cvtColor(np.ascontiguousarray(L), cv2.COLOR_RGB2GRAY), dtype=np.uint8)
        R = np.asarray(cv2.cvtColor(np.ascontiguousarray(R), cv2.COLOR_RGB2GRAY), dtype=np.uint8)
    H, W = L.shape[:2]
    num = int(math.ceil((dmax - dmin + 1) / 16.0)) * 16
    rve = _erode(rv, opts.border_px)
    L = _noise_fill(L, lv, 1)
    R = _noise_fill(R, rv, 2)
    pad = num + 1 if pad is None else max(0, int(pad))
    # SGBM leaves the first ``num`` columns of its reference photo unmatched: padded on the left, and
    # on the right too for the mirrored (right-reference) pass
    two_pass = lr_check and opts.lr_max_diff >= 0 and opts.right_check == "sgbm"
    Lp = cv2.copyMakeBorder(L, 0, 0, pad, num + 1 if two_pass else 0, cv2.BORDER_REFLECT_101)
    Rp = cv2.copyMakeBorder(R, 0, 0, pad, num + 1 if two_pass else 0, cv2.BORDER_REFLECT_101)
    ch = 1 if L.ndim == 2 else L.shape[2]
    sgbm = _sgbm(opts, ch, 0, num)
    raw = sgbm.compute(Lp, Rp)[:, pad:pad + W]
    raw_r = None
    if two_pass:
        raw_r = sgbm.compute(np.ascontiguousarray(Rp[:, ::-1]), np.ascontiguousarray(Lp[:, ::-1]))
        raw_r = raw_r[:, ::-1][:, pad:pad + W]
    lve = _erode(lv, opts.border_px)
    collide = lr_check and opts.lr_max_diff >= 0 and opts.right_check == "collision"
    # the right window's valid columns: when they are one run of whole columns (nodata only beyond
    # the photo's left and right edges, the usual case), the border rule is a column interval
    cols = None
    if raw_r is None:
        full = rve.all(axis=0)
        idx = np.flatnonzero(full)
        if len(idx) and idx[-1] - idx[0] + 1 == len(idx) and not (rve.any(axis=0) & ~full).any():
            cols = (int(idx[0]), int(idx[-1]))
        elif not len(idx) and not rve.any():
            cols = (0, -1)  # no valid right pixel
    d = np.empty((H, W), np.float32)
    for r0, r1, _, _ in _strips(H, 0, W):  # row by row tests: by strips (small, reused temporaries)
        d[r0:r1] = _tests(raw[r0:r1], lve[r0:r1], rve[r0:r1], None if raw_r is None else raw_r[r0:r1],
                          float(opts.lr_max_diff) if collide else None, opts.lr_max_diff, cols)
    d += float(dmin)
    return d


def _fill_holes_half(d: NDArray[np.float32], L: NDArray[np.uint8], R: NDArray[np.uint8], lv: NDArray[np.bool_],
                     rv: NDArray[np.bool_], lo: int, hi: int, opts: MatchOptions) -> NDArray[np.float32]:
    """Holes of ``d`` matched again at half resolution with a stronger smoothness penalty, in place
    (:func:`stereo.dense.holes.fill_holes_half`: on boxes around the large holes only); ``R`` is the
    right window moved by ``lo`` (as for :func:`_match_window`)."""
    return fill_holes_half(d, L, R, lv, rv, lo, hi, opts, _match_window)


#: the coarse pass of :func:`match_pair` is at most 1/4 of the resolution
_COARSE_MIN_SCALE = 4


def _post(d: NDArray[np.float32], grey: NDArray, opts: MatchOptions, right_grey: NDArray | None = None,
          shift: int = 0) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Edge classification, median, sub-pixel refinement (``right_grey``: the right window moved by
    ``shift``), fill, confidence.

    ``grey``/``right_grey``: (H, W) grey windows (uint8 or float). Computed by strips of rows with
    enough overlap (``halo``) that every core row sees what it would see in the whole window.
    """
    H, W = d.shape
    refine = right_grey is not None and opts.refine_iterations > 0
    halo = int(opts.median) + (opts.refine_iterations * opts.refine_radius + 1 if refine else 0)
    if opts.edge_radius > 0:
        d = edge_classify(d, grey, radius=opts.edge_radius, strip=3 * _strip_rows(W) // 2)  # its halo: 3 radii
    out = np.empty(d.shape, np.float32)
    for r0, r1, a0, a1 in _strips(H, halo, W):
        ds = d[a0:a1]
        if opts.median:
            ds = _median_valid(ds)
        if refine:
            assert right_grey is not None
            ds = refine_subpixel(grey[a0:a1], right_grey[a0:a1], ds - shift, radius=opts.refine_radius,
                                 iterations=opts.refine_iterations) + shift
        out[r0:r1] = ds[r0 - a0:r1 - a0]
    out, filled = fill_background(out, opts.fill_max_px)
    conf = np.empty(d.shape, np.float32)
    for r0, r1, a0, a1 in _strips(H, 2, W):  # the confidence's windows: 5 x 5 grey, 3 x 3 disparity
        conf[r0:r1] = _confidence(grey[a0:a1], out[a0:a1], filled[a0:a1])[r0 - a0:r1 - a0]
    return out, conf, filled


def _range_of(values: NDArray, opts: MatchOptions) -> tuple[int, int] | None:
    v = values[np.isfinite(values)]
    if v.size < 10:
        return None
    lo, hi = np.percentile(v, [0.5, 99.5])
    return int(math.floor(lo - opts.margin_px)), int(math.ceil(hi + opts.margin_px))


def _clip_range(r: tuple[int, int], opts: MatchOptions) -> tuple[int, int]:
    lo, hi = r
    if hi - lo + 1 > opts.max_disparities:
        mid = 0.5 * (lo + hi)
        lo, hi = int(mid - opts.max_disparities / 2), int(mid + opts.max_disparities / 2) - 1
    return lo, hi


def _shifted_window(img: NDArray, valid: NDArray[np.bool_], r0: int, r1: int, c0: int, c1: int
                    ) -> tuple[NDArray, NDArray[np.bool_]]:
    """img[r0:r1, c0:c1] with columns outside the image as zeros (invalid)."""
    H, W = img.shape[:2]
    shape = (r1 - r0, c1 - c0) + img.shape[2:]
    out = np.zeros(shape, img.dtype)
    ov = np.zeros((r1 - r0, c1 - c0), bool)
    a, b = max(c0, 0), min(c1, W)
    if b > a:
        out[:, a - c0:b - c0] = img[r0:r1, a:b]
        ov[:, a - c0:b - c0] = valid[r0:r1, a:b]
    return out, ov


def _coarse(L8: NDArray[np.uint8], R8: NDArray[np.uint8], lv, rv, rng: tuple[int, int] | None,
            opts: MatchOptions) -> tuple[NDArray[np.float32] | None, float]:
    """Disparity of a downsampled pair (in full-resolution pixels) and the scale."""
    H, W = L8.shape[:2]
    if opts.coarse_max_px <= 0:
        return None, 1.0
    s = max(H, W) / opts.coarse_max_px
    k = 2 ** max(0, int(math.ceil(math.log2(s)))) if s > 1 else 1
    k = max(k, _COARSE_MIN_SCALE)
    size = (max(8, W // k), max(8, H // k))
    # whole blocks of k x k pixels (OpenCV's fast path: 10 times faster than a fractional scale)
    cw, chh = min(W, size[0] * k), min(H, size[1] * k)
    Lc = np.asarray(cv2.resize(L8[:chh, :cw], size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    Rc = np.asarray(cv2.resize(R8[:chh, :cw], size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    lvc = cv2.resize(lv.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    rvc = cv2.resize(rv.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    if rng is None:
        lo, hi = 0, max(16, size[0] // 3)
    else:
        lo, hi = int(math.floor(rng[0] / k)) - 2, int(math.ceil(rng[1] / k)) + 2
    Rs, rvs = _shifted_window(Rc, rvc, 0, size[1], -lo, size[0] - lo)
    d = _match_window(Lc, Rs, lvc, rvs, lo, hi, opts, lr_check=False) * k
    return d, float(k)


def _grey8(img: NDArray) -> NDArray:
    """Grey values of a window: uint8 for a uint8 window (4 times smaller than :func:`_grey`'s), else float32."""
    if img.dtype != np.uint8:
        return _grey(img)
    if img.ndim == 2:
        return img
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def _grey(img: NDArray) -> NDArray[np.float32]:
    if img.ndim == 2:
        return img.astype(np.float32)
    if img.dtype == np.uint8:
        return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY).astype(np.float32)
    return img.astype(np.float32).mean(axis=2)


def match_pair(
    left: ArrayLike,
    right: ArrayLike,
    *,
    left_valid: ArrayLike | None = None,
    right_valid: ArrayLike | None = None,
    disparity_range: tuple[float, float] | None = None,
    options: MatchOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> DisparityMap:
    """Dense disparity of an in-memory normal-case pair (tiles when larger than one tile).

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) arrays
        Rectified photos of equal height (uint8, or any numeric dtype: stretched to uint8).
    left_valid, right_valid : (H, W) bool, optional
    disparity_range : (float, float), optional
        Expected ``col_left - col_right`` range (e.g. from tie points); without it a coarse pass
        searches ``0 .. width / 3``.
    options : MatchOptions, optional
    progress : callable(done, total), optional

    Returns
    -------
    DisparityMap

    Raises
    ------
    ShapeError, InvalidInputError
        Bad images, masks or range.
    StereoError
        No disparity found anywhere.
    """
    opts = options or MatchOptions()
    if not isinstance(opts, MatchOptions):
        raise InvalidInputError(f"`options` must be a MatchOptions; got {type(opts).__name__}")
    Li, Ri = _as_image(left, "left"), _as_image(right, "right")
    if Li.shape[0] != Ri.shape[0] or Li.ndim != Ri.ndim:
        raise ShapeError(f"`left` and `right` must have equal heights and bands; got {Li.shape} and {Ri.shape}",
                         actual_shape=(Li.shape, Ri.shape))
    lv = _as_mask(left_valid, Li.shape[:2], "left_valid")
    rv = _as_mask(right_valid, Ri.shape[:2], "right_valid")
    rng = _check_range(disparity_range)
    L8, R8 = _to_uint8(Li, lv), _to_uint8(Ri, rv)
    if L8.ndim == 3 and not opts.colour:  # grey once here, not per tile and step
        L8, R8 = _grey8(L8), _grey8(R8)
    coarse, k = _coarse(L8, R8, lv, rv, rng, opts)
    H, W = L8.shape[:2]
    windows = list(iter_windows(W, H, opts.tile, opts.overlap))
    if windows == [(0, 0, W, H)]:  # one window: its results are the map (no copies)
        out, conf, filled = _tile(L8, R8, lv, rv, 0, 0, W, H, coarse, k, rng, opts)
        if progress is not None:
            progress(1, 1)
        windows = []
    else:
        out = np.full((H, W), np.nan, np.float32)
        conf = np.zeros((H, W), np.float32)
        filled = np.zeros((H, W), bool)
    for i, (c0, r0, w, h) in enumerate(windows):
        d, cf, fl = _tile(L8, R8, lv, rv, c0, r0, w, h, coarse, k, rng, opts)
        cc0, cr0 = c0 if c0 == 0 else c0 + opts.overlap, r0 if r0 == 0 else r0 + opts.overlap
        cc1, cr1 = min(cc0 + opts.tile, W), min(cr0 + opts.tile, H)
        sl = (slice(cr0 - r0, cr1 - r0), slice(cc0 - c0, cc1 - c0))
        out[cr0:cr1, cc0:cc1] = d[sl]
        conf[cr0:cr1, cc0:cc1] = cf[sl]
        filled[cr0:cr1, cc0:cc1] = fl[sl]
        if progress is not None:
            progress(i + 1, len(windows))
    if not np.isfinite(out).any():
        raise StereoError("dense matching found no disparity: no texture, no overlap, or a wrong disparity range "
                          f"({disparity_range!r})")
    return DisparityMap(out, conf, filled, opts)


def _as_mask(m: ArrayLike | None, shape: tuple[int, ...], name: str) -> NDArray[np.bool_]:
    if m is None:
        return np.ones(shape, bool)
    a = np.asarray(m)
    if a.shape != shape:
        raise ShapeError(f"`{name}` must have shape {shape}; got {a.shape}", actual_shape=a.shape,
                         expected_shape=shape)
    return a.astype(bool)


def _check_range(r: tuple[float, float] | None) -> tuple[int, int] | None:
    if r is None:
        return None
    try:
        lo, hi = float(r[0]), float(r[1])
    except (TypeError, ValueError, IndexError) as err:
        raise InvalidInputError(f"`disparity_range` must be two numbers; got {r!r}") from err
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise InvalidInputError(f"`disparity_range` must be two finite numbers, low <= high; got {r!r}")
    return int(math.floor(lo)), int(math.ceil(hi))


def _tile(L8, R8, lv, rv, c0, r0, w, h, coarse, k, rng, opts: MatchOptions, col_shift: int = 0):
    """Match one left window (c0, r0, w, h) of in-memory photos; returns disparity, confidence, filled."""
    tr = None
    if coarse is not None:
        sub = coarse[int(r0 // k):int(math.ceil((r0 + h) / k)), int(c0 // k):int(math.ceil((c0 + w) / k))]
        tr = _range_of(sub, opts)
    if tr is None:
        tr = rng if rng is not None else (0, max(16, L8.shape[1] // 3))
        tr = (int(tr[0] - opts.margin_px), int(tr[1] + opts.margin_px))
    lo, hi = _clip_range(tr, opts)
    L, lvw = L8[r0:r0 + h, c0:c0 + w], lv[r0:r0 + h, c0:c0 + w]
    Rs, rvs = _shifted_window(R8, rv, r0, r0 + h, c0 - lo - col_shift, c0 + w - lo - col_shift)
    d = _fill_holes_half(_match_window(L, Rs, lvw, rvs, lo, hi, opts), L, Rs, lvw, rvs, lo, hi, opts)
    return _post(d, _grey8(L), opts, _grey8(Rs), lo)


def sgbm_baseline(left: ArrayLike, right: ArrayLike, num_disparities: int = 64, block_size: int = 5
                  ) -> NDArray[np.float32]:
    """OpenCV StereoSGBM with the settings of OpenCV's sample (the benchmark's peer); NaN where invalid."""
    Li, Ri = _as_image(left, "left"), _as_image(right, "right")
    ch = 1 if Li.ndim == 2 else 3
    bs = block_size
    s = cv2.StereoSGBM.create(minDisparity=0, numDisparities=num_disparities, blockSize=bs, P1=8 * ch * bs * bs,
                              P2=32 * ch * bs * bs, disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                              speckleRange=2)
    raw = s.compute(_to_uint8(Li, None), _to_uint8(Ri, None))
    d = raw.astype(np.float32) / 16.0
    d[raw < 0] = np.nan
    return d


# ---------------------------------------------------------------- rasters
def _read(rd: WindowReader, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray[np.bool_]]:
    """Window (clipped reads, zeros and invalid outside) of a rectified photo, 1 or 3 bands."""
    H, W = rd.height, rd.width
    bands = 3 if rd.count >= 3 else 1
    out = np.zeros((h, w, bands), np.uint8)
    ov = np.zeros((h, w), bool)
    x0, y0, x1, y1 = max(c0, 0), max(r0, 0), min(c0 + w, W), min(r0 + h, H)
    if x1 > x0 and y1 > y0:
        data, valid = rd.read(x0, y0, x1 - x0, y1 - y0)
        data = data[:, :, :bands]
        out[y0 - r0:y1 - r0, x0 - c0:x1 - c0] = data if data.dtype == np.uint8 else _to_uint8(data, valid)
        ov[y0 - r0:y1 - r0, x0 - c0:x1 - c0] = True if valid is None else valid
    return (out[:, :, 0] if bands == 1 else out), ov


class _DenseTiles:
    """The matcher of one tile of two rectified rasters, for :func:`rectify.raster.distributed.run_windows`.

    ``tile(c0, r0, w, h)`` matches the left window (with its overlap) against the right window moved
    by the tile's disparity range and returns the disparity, confidence and filled flags of the
    tile's core. It holds the photos' absolute paths (each copy opens them itself), the coarse
    disparity, the tie points and the options: a copy pickles to a Dask worker whole.
    """

    def __init__(self, left_path: str, right_path: str, width: int, height: int, coarse: NDArray | None,
                 k: float, ties: NDArray[np.float64] | None, rng: tuple[int, int] | None, opts: MatchOptions):
        self.left_path, self.right_path = left_path, right_path
        self.width, self.height = width, height
        self.coarse, self.k, self.ties, self.rng, self.opts = coarse, k, ties, rng, opts
        self._rl: WindowReader | None = None
        self._rr: WindowReader | None = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_rl"] = state["_rr"] = None  # never open files
        return state

    def portable(self) -> _DenseTiles:
        return self  # paths are absolute; open readers are dropped when pickled

    def close(self) -> None:
        for name in ("_rl", "_rr"):
            rd = getattr(self, name)
            if rd is not None:
                rd.close()
                setattr(self, name, None)

    def core_origin(self, c0: int, r0: int) -> tuple[int, int]:
        o = self.opts.overlap
        return (c0 if c0 == 0 else c0 + o), (r0 if r0 == 0 else r0 + o)

    def _range(self, c0: int, r0: int, w: int, h: int) -> tuple[int, int]:
        opts, k, ties = self.opts, self.k, self.ties
        tr = None
        if self.coarse is not None:
            sub = self.coarse[int(r0 // k):int(math.ceil((r0 + h) / k)), int(c0 // k):int(math.ceil((c0 + w) / k))]
            tr = _range_of(sub, opts)
        if tr is None and ties is not None and len(ties):
            inside = (ties[:, 0] >= c0) & (ties[:, 0] < c0 + w) & (ties[:, 1] >= r0) & (ties[:, 1] < r0 + h)
            if inside.sum() >= 3:
                tr = (int(math.floor(ties[inside, 2].min() - opts.margin_px)),
                      int(math.ceil(ties[inside, 2].max() + opts.margin_px)))
        if tr is None:
            g = self.rng if self.rng is not None else (0, max(16, self.width // 3))
            tr = (int(g[0] - opts.margin_px), int(g[1] + opts.margin_px))
        return _clip_range(tr, opts)

    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray[np.float32], NDArray[np.float32],
                                                               NDArray[np.bool_]]:
        opts = self.opts
        if self._rl is None:
            self._rl = WindowReader(self.left_path)
        if self._rr is None:
            self._rr = WindowReader(self.right_path)
        lo, hi = self._range(c0, r0, w, h)
        with ignore_not_georeferenced():
            L, lv = _read(self._rl, c0, r0, w, h)
            R, rv = _read(self._rr, c0 - lo, r0, w, h)
        if lv.any() and rv.any():
            d = _fill_holes_half(_match_window(L, R, lv, rv, lo, hi, opts), L, R, lv, rv, lo, hi, opts)
            d, cf, fl = _post(d, _grey8(L), opts, _grey8(R), lo)
        else:
            d = np.full((h, w), np.nan, np.float32)
            cf = np.zeros((h, w), np.float32)
            fl = np.zeros((h, w), bool)
        cc0, cr0 = self.core_origin(c0, r0)
        cc1, cr1 = min(cc0 + opts.tile, self.width), min(cr0 + opts.tile, self.height)
        sl_ = (slice(cr0 - r0, cr1 - r0), slice(cc0 - c0, cc1 - c0))
        return (np.ascontiguousarray(d[sl_], dtype=np.float32), np.ascontiguousarray(cf[sl_], dtype=np.float32),
                np.ascontiguousarray(fl[sl_], dtype=bool))


#: band descriptions of the disparity and confidence GeoTIFFs of :func:`match_rasters`
DISPARITY_BANDS = ("disparity: col_left - col_right of the left image's pixel, px; nodata -9999",)
CONFIDENCE_BANDS = ("confidence: texture x local smoothness, 0..1 (0 where filled); nodata -9999",
                    "filled: 1 where the disparity was filled by the background (not matched), else 0")


def match_rasters(
    left_path: StrPath,
    right_path: StrPath,
    disparity_path: StrPath,
    confidence_path: StrPath | None,
    *,
    disparity_range: tuple[float, float] | None = None,
    tie_points: ArrayLike | None = None,
    options: MatchOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
    scheduler: Scheduler | str | None = None,
    transform: Affine | None = None,
    crs: str | None = None,
) -> MatchStats:
    """Dense matching of two rectified rasters, tile by tile, into disparity and confidence GeoTIFFs.

    Parameters
    ----------
    left_path, right_path : path
        Rectified photos (equal heights), e.g. from :func:`stereo.dense.epipolar.resample_view`.
    disparity_path, confidence_path : path
        Float32 tiled GeoTIFFs to write as given (nodata ``NODATA``); the confidence raster has a
        second band, 1 where the disparity was filled (``confidence_path`` None: not written). Each
        band carries its description (:data:`DISPARITY_BANDS`, :data:`CONFIDENCE_BANDS`).
    disparity_range : (float, float), optional
        Global range; ``tie_points`` (N, 3: col, row, disparity in the left rectified photo) refine it
        per tile. Each tile takes the range of the coarse pass under it, else of its tie points,
        else the global one.
    options : MatchOptions, optional
    progress : callable(done, total), optional
        Tiles done.
    scheduler : Scheduler or str, optional
        Where the tiles are matched (:func:`rectify.raster.distributed.resolve_scheduler`): ``threads`` (the
        default, one tile at a time in this process), ``processes[:N]`` (a local Dask cluster) or
        ``tcp://HOST:PORT`` (an existing one); default ``$RECTIFY_SCHEDULER``, else ``threads``.
        On Dask each task opens the two rasters by path and matches one tile; its disparity block is
        written beside ``disparity_path`` and assembled here (the photos and the output folder must
        be visible to every worker under the same paths).
    transform, crs : optional
        Georeference of the rasters written (default: none; e.g. the left photo's, so that the
        disparity lies pixel for pixel on it).

    Raises
    ------
    InvalidInputError, ShapeError
        Bad inputs, options or scheduler.
    StereoError
        No disparity found anywhere.
    SchedulerError
        The Dask cluster cannot be started or reached, or lost a task.
    """
    opts = options or MatchOptions()
    if not isinstance(opts, MatchOptions):
        raise InvalidInputError(f"`options` must be a MatchOptions; got {type(opts).__name__}")
    sched = resolve_scheduler(scheduler)  # a bad value fails before any work
    scheduler = sched
    il, ir = raster_info(left_path), raster_info(right_path)
    if il.height != ir.height:
        raise InvalidInputError(f"rectified photos must have equal heights; got {il.height} and {ir.height}")
    rng = _check_range(disparity_range)
    ties = None
    if tie_points is not None:
        ties = np.asarray(tie_points, dtype=np.float64)
        if ties.ndim != 2 or ties.shape[1] != 3 or not np.isfinite(ties).all():
            raise ShapeError(f"`tie_points` must be finite (N, 3) col, row, disparity; got {ties.shape}",
                             actual_shape=ties.shape, expected_shape=(None, 3))
        if rng is None and len(ties):
            rng = (int(math.floor(ties[:, 2].min())), int(math.ceil(ties[:, 2].max())))
    # coarse pass on overviews (bounded size)
    coarse, k = None, 1.0
    if opts.coarse_max_px > 0:
        side = max(opts.coarse_max_px, 64)
        ovl, vl, sl = read_overview(left_path, side)
        ovr, vr, sr = read_overview(right_path, side)
        s = max(sl, sr)
        if s > 1.0 + 1e-9 or max(il.width, il.height) > side:
            # bring both to the same scale
            size_l = (max(8, int(round(il.width / s))), max(8, int(round(il.height / s))))
            size_r = (max(8, int(round(ir.width / s))), size_l[1])
            Lc = np.asarray(cv2.resize(_to_uint8(ovl[:, :, :3].mean(axis=2), vl), size_l, interpolation=cv2.INTER_AREA),
                            dtype=np.uint8)
            Rc = np.asarray(cv2.resize(_to_uint8(ovr[:, :, :3].mean(axis=2), vr), size_r, interpolation=cv2.INTER_AREA),
                            dtype=np.uint8)
            lvc = cv2.resize(vl.astype(np.uint8), size_l, interpolation=cv2.INTER_NEAREST) > 0
            rvc = cv2.resize(vr.astype(np.uint8), size_r, interpolation=cv2.INTER_NEAREST) > 0
            k = il.height / size_l[1]
            if rng is None:
                lo, hi = 0, max(16, size_l[0] // 3)
            else:
                lo, hi = int(math.floor(rng[0] / k)) - 2, int(math.ceil(rng[1] / k)) + 2
            Rs, rvs = _shifted_window(Rc, rvc, 0, size_l[1], -lo, size_l[0] - lo)
            coarse = _match_window(Lc, Rs, lvc, rvs, lo, hi, opts, lr_check=False) * k
    windows = list(iter_windows(il.width, il.height, opts.tile, opts.overlap))
    engine = _DenseTiles(str(Path(left_path).resolve()), str(Path(right_path).resolve()), il.width, il.height,
                         coarse, k, ties, rng, opts)
    acc = {"n_valid": 0, "n_filled": 0, "lo": math.inf, "hi": -math.inf}
    geo = transform if transform is not None else Affine.identity()
    with ignore_not_georeferenced(), contextlib.ExitStack() as writers:
        tile_px = min(512, opts.tile)
        wd = writers.enter_context(TiledWriter(disparity_path, il.width, il.height, 1, "float32", geo, crs,
                                               MaskPolicy("nodata", NODATA), tile=tile_px,
                                               descriptions=DISPARITY_BANDS))
        wc = None if confidence_path is None else writers.enter_context(
            TiledWriter(confidence_path, il.width, il.height, 2, "float32", geo, crs, MaskPolicy("nodata", NODATA),
                        tile=tile_px, descriptions=CONFIDENCE_BANDS))

        def write(res: tuple[NDArray, NDArray, NDArray], c0: int, r0: int) -> bool:
            dc, cfc, flc = res
            cc0, cr0 = engine.core_origin(c0, r0)
            ok = np.isfinite(dc)
            acc["n_valid"] += int(ok.sum())
            acc["n_filled"] += int(flc.sum())
            if ok.any():
                acc["lo"] = min(acc["lo"], float(dc[ok].min()))
                acc["hi"] = max(acc["hi"], float(dc[ok].max()))
            wd.write(np.where(ok, dc, NODATA).astype(np.float32)[:, :, None], cc0, cr0)
            if wc is not None:
                wc.write(np.dstack([np.where(ok, cfc, NODATA), flc.astype(np.float32)]).astype(np.float32),
                         cc0, cr0)
            return not ok.any()

        try:
            # one tile at a time on the local path (SGBM is multi-threaded itself); on Dask one tile per task
            run_windows(engine, write, windows, threads=1, progress=progress, scheduler=scheduler,
                        workdir=Path(disparity_path).resolve().parent, name="dense", windows_per_task=1)
        finally:
            engine.close()
    n_valid, n_filled, dlo, dhi = int(acc["n_valid"]), int(acc["n_filled"]), float(acc["lo"]), float(acc["hi"])
    if n_valid == 0:
        raise StereoError("dense matching found no disparity: no texture, no overlap, or a wrong disparity range "
                          f"({rng!r})")
    return MatchStats(il.width, il.height, n_valid, n_filled, len(windows), dlo, dhi)
