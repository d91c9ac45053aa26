"""Descriptor matching, geometric verification and whole-image matching.

:class:`MatcherConfig` holds every option of the matcher (defaults live
there only); :func:`match_arrays` matches two in-memory images; the helpers
here (verification with the overlap checks, refinement, final even
selection, the result) are shared with the tiled path (:mod:`.tiled`).
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.features.detect import DETECTORS, Features, detect, grid_select
from rectify.features.lsm import LsmConfig, refine_matches
from rectify.features.shape import local_affine as _local_affine
from rectify.features.shape import neighbour_residuals
from rectify.features.verify import (
    VERIFY_METHODS,
    Verification,
    Verify,
    _apply_h,
    _errors,
    screen_refined,
    table_for,
    verify_matches,
)
from rectify.geometry.points import Matches
from rectify.geometry.residuals import rms
from rectify.raster import io as rio

__all__ = ["VERIFY_METHODS", "MatcherConfig", "MatchResult", "ProgressFn", "Verification", "Verify", "match_arrays",
           "match_descriptors", "verify_matches"]

ProgressFn = Callable[[int, int], None]

logger = logging.getLogger(__name__)

#: FLANN kd-tree search effort (leaves checked) of the forward search and of the mutual back-check. A
#: cheaper back-check (16) lost 15 % of the matches on the NGI pair (fundamental verification, where no
#: guided re-admission recovers them) for 0.2 s on the 2000 px pair.
FLANN_CHECKS = 64
FLANN_BACK_CHECKS = 64


@dataclass(frozen=True)
class MatcherConfig:
    """Options of the matcher. Defaults live here only (the CLI reuses them).

    Attributes
    ----------
    detector : {"sift", "orb", "akaze"}
    verify : {"homography", "fundamental", "none"}
    refine : bool
        Least-squares matching refinement of the right positions.
    max_matches : int
        At most this many matches are returned, chosen evenly over the left image.
    ratio : float
        Lowe's ratio test threshold (best / second best descriptor distance).
    mutual : bool
        Keep only matches that are each other's best (mutual check).
    threshold_px : float
        USAC inlier threshold: transfer error (homography) or distance to
        the epipolar line (fundamental), px.
    max_keypoints : int
        Keypoints kept per image (whole-image mode) or per tile (tiled mode),
        chosen evenly with a cap per grid cell.
    cell_cap : int
        Keypoints kept per grid cell (the cell size follows from
        ``max_keypoints``).
    tiled_above_px : int
        Images with a side larger than this are matched coarse-to-fine by tiles.
    tile_px, overlap_px : int
        Tile core size and the overlap added on each side (px).
    overview_px : int
        Longer side of the overviews used for the coarse match (px).
    search_margin_px : float
        Extra margin around the predicted right window (full-resolution px).
    max_candidates : int
        Candidate matches held at most in tiled mode (grid-thinned beyond).
    max_tiles : int
        Full-resolution tiles searched at most. Beyond, the search is sparse:
        tiles of half the side, at most 3 x ``max_tiles`` of them on an even
        sub-grid (every k-th tile in each direction), so the time stays
        bounded too while matches still spread over the whole overlap. A scene
        much larger than ``max_matches`` needs is searched on a budget grid
        instead: disjoint tiles of half the side on a regular grid over the
        whole image, enough for 1.5 x ``max_matches`` (``rectify.features.tiled``).
    min_inliers : int
        Fewer verified matches than this means the images do not overlap.
    guided : bool
        Guided re-admission after homography verification (whole-image mode, issue 12): a left keypoint
        without a verified match takes its nearest or second-nearest right descriptor when that lies within
        ``threshold_px`` of where the verified homography puts it and the distance ratio is below
        ``guided_ratio`` (instead of ``ratio``; no mutual check). The ratio test and the mutual check keep
        the estimation clean; the model then decides the final inliers: a wrong partner lands within 1.5 px
        of the prediction by chance about once in 10^5. Not done with a fundamental matrix, whose
        epipolar band admits wrong partners (on the NGI pair it raised the RMS Sampson error by 12 %).
    guided_ratio : float
        Distance-ratio bound of the homography-guided re-admission.
    guided_fill : int
        The guided re-admission tops up scarce matches only: it adds matches while fewer than this are
        verified (an even selection of the candidates when there are more). An ordinary pair has plenty
        (12 000 on the 2000 px benchmark pair) and skips it, so their refinement costs no time; a
        wide-baseline pair (a few hundred) gets them all.
    keep_unrefined : bool
        Keep verified matches whose refinement does not converge, at their unrefined positions and with
        an empty (NaN) score, instead of dropping them (issue 12: on wide-baseline pairs the square LSM
        window fails where the affine distortion is strong, and those matches are good). Whole-image mode.
    derotate : bool
        Whole-image mode (issue 30): when the right image is turned by about k quarter turns against the left
        one (their keypoints' orientations differ by more than 45 degrees; neighbouring aerial strips flown in
        opposite directions differ by 180), it is turned back by ``np.rot90`` (exact, no resampling) before
        its detection, so the pair is matched as an unturned one; the positions are returned in the given
        images' pixels (``MatchResult.n_turns``). The turn is guessed from a small copy of the right image
        (a few percent of the time) and checked by the verified matches, which match once more when the
        guess was wrong.
    lsm : LsmConfig
        Refinement options.
    percentiles : (float, float)
        Stretch to 8 bits between these percentiles (detection only).
    seed : int
        Seed of OpenCV's RNG (USAC sampling), for reproducible runs.
    """

    detector: str = "sift"
    verify: str = "homography"
    refine: bool = True
    max_matches: int = 20000
    ratio: float = 0.8
    mutual: bool = True
    threshold_px: float = 1.5
    max_keypoints: int = 40000
    cell_cap: int = 4
    tiled_above_px: int = 4096
    tile_px: int = 1024
    overlap_px: int = 48
    overview_px: int = 2048
    search_margin_px: float = 96.0
    max_candidates: int = 200000
    max_tiles: int = 100
    min_inliers: int = 15
    guided: bool = True
    guided_ratio: float = 0.95
    guided_fill: int = 5000
    keep_unrefined: bool = True
    derotate: bool = True
    lsm: LsmConfig = field(default_factory=LsmConfig)
    percentiles: tuple[float, float] = (0.5, 99.5)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise InvalidInputError(f"unknown detector {self.detector!r}; choose from {DETECTORS}")
        if self.verify not in VERIFY_METHODS:
            raise InvalidInputError(f"unknown verification {self.verify!r}; choose from {VERIFY_METHODS}")
        for name in ("max_matches", "max_keypoints", "cell_cap", "tile_px", "overview_px", "max_candidates",
                     "tiled_above_px", "max_tiles", "guided_fill"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise InvalidInputError(f"{name} must be a positive integer; got {v!r}")
        if self.overlap_px < 0:
            raise InvalidInputError(f"overlap_px must be >= 0; got {self.overlap_px!r}")
        if not (0 < self.ratio <= 1):
            raise InvalidInputError(f"ratio must be in (0, 1]; got {self.ratio!r}")
        if not (0 < self.guided_ratio <= 1):
            raise InvalidInputError(f"guided_ratio must be in (0, 1]; got {self.guided_ratio!r}")
        if not (math.isfinite(self.threshold_px) and self.threshold_px > 0):
            raise InvalidInputError(f"threshold_px must be > 0; got {self.threshold_px!r}")
        if self.min_inliers < 4:
            raise InvalidInputError(f"min_inliers must be >= 4; got {self.min_inliers!r}")
        if self.overview_px < 64:
            raise InvalidInputError(f"overview_px must be >= 64; got {self.overview_px!r}")


@dataclass(frozen=True, eq=False)
class MatchResult:
    """What :func:`match_images` / :func:`match_arrays` found.

    Attributes
    ----------
    matches : Matches
        Verified (and refined) tie points; ``score`` is the LSM position
        standard deviation (px) when refined, the descriptor ratio otherwise.
    n_detected : (int, int)
        Keypoints kept in the left and right image (summed over tiles).
    n_matched : int
        Matches after ratio test and mutual check (and the coarse gate when tiled).
    n_verified : int
        Matches consistent with the verification model (before the final cap).
    n_refined, n_refine_failed : int
        Matches refined by LSM, and those whose refinement did not converge: kept at their raw positions
        with a NaN score (``MatcherConfig.keep_unrefined``, whole-image mode) or dropped.
    rmse_px : float
        Verification residual RMSE of the returned matches, px: of the refined ones when refinement is on
        (the model fitted to them; unrefined matches are check points of the residual table).
    rmse_raw_px : float
        The same matches' RMSE at their raw (unrefined) positions.
    verification : Verification
        Model and residual table of the returned matches.
    candidates_left, candidates_right, candidate_inlier : arrays
        All candidate matches (up to a cap) and their verification status,
        for plots.
    tiled : bool
    image_shapes : ((H, W), (H, W))
    timings_s : dict
    n_duplicates : int
        Verified matches dropped because their left or right position repeats another's (the output is
        one-to-one; the best score is kept).
    n_guided : int
        Matches re-admitted after verification by the guided search (``MatcherConfig.guided``), included
        in ``n_verified``.
    refined : (N,) bool or None
        Which returned matches are refined (None when refinement is off: none is). The others are kept at
        their raw positions (``MatcherConfig.keep_unrefined``); they are never counted in ``rmse_px``.
    sigma_px : (N,) float64 or None
        Standard deviation of each returned right position, sqrt(sx^2 + sy^2), px: the LSM one for refined
        matches, and for the unrefined ones the RMS move of the refined matches from their raw positions
        (the raw positions' own error; about 0.5 px on the NGI pair against 0.08 px refined). None when
        unknown (refinement off).
    n_screened : int
        Refined matches whose residual against the model of the refined matches is too large for their
        precision (a wrong convergence): moved back to their raw positions as unrefined, or dropped.
    rmse_unrefined_px : float
        Verification residual RMSE of the returned unrefined matches (NaN when there are none).
    n_turns : int
        Quarter turns (0-3, ``np.rot90``) the right image was turned by before the final matching
        (``MatcherConfig.derotate``); the positions are always in the given images' pixels.
    """

    matches: Matches
    n_detected: tuple[int, int]
    n_matched: int
    n_verified: int
    n_refined: int
    n_refine_failed: int
    rmse_px: float
    rmse_raw_px: float
    verification: Verification
    candidates_left: NDArray[np.float64]
    candidates_right: NDArray[np.float64]
    candidate_inlier: NDArray[np.bool_]
    tiled: bool
    image_shapes: tuple[tuple[int, int], tuple[int, int]]
    timings_s: dict[str, float] = field(default_factory=dict)
    n_duplicates: int = 0
    n_guided: int = 0
    refined: NDArray[np.bool_] | None = None
    sigma_px: NDArray[np.float64] | None = None
    n_screened: int = 0
    rmse_unrefined_px: float = float("nan")
    n_turns: int = 0

    @property
    def n_unrefined(self) -> int:
        """Returned matches kept at their raw positions (refinement on), 0 otherwise."""
        return 0 if self.refined is None else int((~self.refined).sum())

    def summary(self) -> dict[str, Any]:
        return {"n_detected_left": self.n_detected[0], "n_detected_right": self.n_detected[1],
                "n_matched": self.n_matched, "n_verified": self.n_verified, "n_output": len(self.matches),
                "n_refined": self.n_refined, "n_refine_failed": self.n_refine_failed,
                "verification": self.verification.method, "rmse_px": self.rmse_px,
                "rmse_raw_px": self.rmse_raw_px, "tiled": self.tiled, "n_duplicates": self.n_duplicates,
                "n_guided": self.n_guided, "n_unrefined": self.n_unrefined, "n_screened": self.n_screened,
                "rmse_unrefined_px": self.rmse_unrefined_px if math.isfinite(self.rmse_unrefined_px) else None,
                "n_turns": self.n_turns,
                **{f"time_{k}_s": v for k, v in self.timings_s.items()}}


# --------------------------------------------------------------------------- matching
class _Pairs(NamedTuple):
    left: NDArray[np.int64]
    right: NDArray[np.int64]
    ratio: NDArray[np.float64]


class _Forward(NamedTuple):
    """Nearest and second-nearest right descriptor of every left one (index -1 and distance inf when absent)."""
    idx: NDArray[np.int64]      # (N, 2)
    dist: NDArray[np.float64]   # (N, 2)


def match_descriptors(left: Features, right: Features, *, ratio: float = 0.8, mutual: bool = True
                      ) -> _Pairs:
    """Match descriptors: nearest neighbour with Lowe's ratio test and mutual check.

    Float descriptors (SIFT) use FLANN (randomised kd-trees); binary ones
    (ORB, AKAZE) use brute force with the Hamming norm.

    Returns
    -------
    (left_idx, right_idx, ratio) : three (M,) arrays
        Indices into ``left`` and ``right`` and the distance ratio.
    """
    return _match_descriptors(left, right, ratio=ratio, mutual=mutual)[0]


def _match_descriptors(left: Features, right: Features, *, ratio: float, mutual: bool
                       ) -> tuple[_Pairs, _Forward | None]:
    """:func:`match_descriptors`, and the forward two-nearest-neighbour table (for the guided search)."""
    empty = _Pairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(left) < 2 or len(right) < 2:
        return empty, None
    flann = left.descriptors.dtype == np.float32
    dl = np.ascontiguousarray(left.descriptors)
    dr = np.ascontiguousarray(right.descriptors)
    # the forward index (right descriptors) and the back-check's (left ones) are built side by side
    index_r, index_l = _flann_indexes((dr, dl) if mutual else (dr,)) if flann else (None, None)
    fidx, fdist = _knn(dr, dl, 2, FLANN_CHECKS, flann, index=index_r)
    fwd = _Forward(fidx, fdist)
    a, b = fdist[:, 0], fdist[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(b > 0, a / np.where(b > 0, b, 1.0), np.where(a == 0, 0.0, 1.0))
    sel = np.flatnonzero((fidx[:, 1] >= 0) & (r < ratio))
    li, ri, rat = sel.astype(np.int64), fidx[sel, 0], r[sel].astype(np.float64)
    if mutual and li.size:
        # back-match only the right descriptors that are candidates (about half of them on ordinary pairs)
        cand = np.unique(ri)
        bidx, _ = _knn(dl, np.ascontiguousarray(dr[cand]), 1, FLANN_BACK_CHECKS, flann, index=index_l)
        best = np.full(len(right), -1, dtype=np.int64)
        best[cand] = bidx[:, 0]
        ok = best[ri] == li
        li, ri, rat = li[ok], ri[ok], rat[ok]
    # one right point per left point and vice versa (keep the best ratio)
    if li.size:
        order = np.argsort(rat, kind="stable")
        _, first = np.unique(ri[order], return_index=True)
        sel = order[first]
        li, ri, rat = li[sel], ri[sel], rat[sel]
    return _Pairs(li, ri, rat), fwd


#: seed of OpenCV's RNG (per thread) before a FLANN index is built: its randomised kd-trees, hence the
#: matches, are then the same on any thread, process or machine, whatever ran there before
FLANN_SEED = 0x5EED


def _flann_index(train: NDArray) -> Any:
    """A FLANN index of 4 randomised kd-trees over float descriptors (N, D), built from a fixed seed."""
    cv2.setRNGSeed(FLANN_SEED)
    return cv2.flann.Index(train, dict(algorithm=1, trees=4))


def _flann_indexes(trains: tuple[NDArray, ...]) -> tuple[Any, Any]:
    """FLANN indexes of one or two descriptor sets, two built at once on two threads (OpenCV releases the
    GIL; each build seeds its thread's RNG, so the indexes do not depend on the threads); (index, None)
    for one set."""
    if len(trains) == 1:
        return _flann_index(trains[0]), None
    if (os.cpu_count() or 1) > 1 and min(len(t) for t in trains) >= 4000:
        with ThreadPoolExecutor(2) as ex:
            a, b = ex.map(_flann_index, trains)
        return a, b
    return _flann_index(trains[0]), _flann_index(trains[1])


def _knn(train: NDArray, query: NDArray, k: int, checks: int, flann: bool, *, index: Any = None
         ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The k nearest train descriptors of every query one: indices (-1 where absent) and distances.

    Float descriptors: one FLANN index of 4 randomised kd-trees (``index``, built from ``train`` when
    None), searched by two threads (OpenCV releases the GIL; the search only reads the index, so the
    result is that of one search). Binary ones: brute force, Hamming norm."""
    n = len(query)
    idx = np.full((n, k), -1, dtype=np.int64)
    dist = np.full((n, k), np.inf)
    if not flann:
        for m in cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query, train, k=k):
            for j, d in enumerate(m[:k]):
                idx[d.queryIdx, j] = d.trainIdx
                dist[d.queryIdx, j] = d.distance
        return idx, dist
    if index is None:
        index = _flann_index(train)
    params: dict[str, bool | int | float | str] = {"checks": int(checks)}

    def search(span: tuple[int, int]):
        a, b = span
        return index.knnSearch(query[a:b], k, params=params)

    nw = 2 if n >= 4000 and (os.cpu_count() or 1) > 1 else 1
    bounds = np.linspace(0, n, nw + 1).astype(int)
    spans = list(zip(bounds[:-1], bounds[1:], strict=True))
    if nw > 1:
        with ThreadPoolExecutor(nw) as ex:
            parts = list(ex.map(search, spans))
    else:
        parts = [search(spans[0])]
    for (a, b), (ii, dd) in zip(spans, parts, strict=True):
        ii = np.asarray(ii, dtype=np.int64).reshape(b - a, k)
        dd = np.asarray(dd, dtype=np.float64).reshape(b - a, k)
        ok = ii >= 0
        idx[a:b] = np.where(ok, ii, -1)
        dist[a:b] = np.where(ok, np.sqrt(np.maximum(dd, 0.0)), np.inf)   # FLANN's L2 is squared
    return idx, dist


def _guided(fl: Features, fr: Features, pairs: _Pairs, inl: NDArray[np.bool_], fwd: _Forward | None,
            ver: Verification | None, cfg: MatcherConfig) -> _Pairs:
    """Matches re-admitted by the verified homography (see ``MatcherConfig.guided``): left keypoints without
    a verified match whose nearest or second-nearest right descriptor lies within ``threshold_px`` of the
    prediction; at most one per right keypoint, none on a right keypoint already used."""
    none = _Pairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if fwd is None or ver is None or ver.matrix is None or ver.method != "homography" or not cfg.guided:
        return none
    used_l = np.zeros(len(fl), bool)
    used_l[pairs.left[inl]] = True
    used_r = np.zeros(len(fr), bool)
    used_r[pairs.right[inl]] = True
    a, b = fwd.dist[:, 0], fwd.dist[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(b > 0, a / np.where(b > 0, b, 1.0), 1.0)
    cand_l, cand_r, cand_s = [], [], []
    for k in (0, 1):
        j = fwd.idx[:, k]
        i = np.flatnonzero(~used_l & (j >= 0) & (ratio < cfg.guided_ratio))
        j = j[i]
        j_ok = ~used_r[j]
        i, j = i[j_ok], j[j_ok]
        if not len(i):
            continue
        err = np.linalg.norm(_apply_h(ver.matrix, fl.xy[i]) - fr.xy[j], axis=1)
        good = np.isfinite(err) & (err <= cfg.threshold_px)
        i, j = i[good], j[good]
        used_l[i] = True                      # a left keypoint takes its nearest neighbour first
        cand_l.append(i)
        cand_r.append(j)
        cand_s.append(ratio[i] if k == 0 else np.ones(len(i)))
    if not cand_l:
        return none
    li, ri, rs = np.concatenate(cand_l), np.concatenate(cand_r), np.concatenate(cand_s)
    order = np.argsort(rs, kind="stable")
    _, first = np.unique(ri[order], return_index=True)
    sel = np.sort(order[first])
    return _Pairs(li[sel], ri[sel], rs[sel])


# --------------------------------------------------------------------------- helpers
def _grey_float(data: NDArray, valid: NDArray[np.bool_]) -> NDArray[np.float32]:
    g = data.astype(np.float32).mean(axis=2) if data.ndim == 3 else data.astype(np.float32)
    g[~valid] = np.nan
    return g


def _check_blank(feat: Features, name: str, path) -> None:
    if len(feat) < 8:
        raise EstimationError(f"only {len(feat)} keypoints found in the {name} image {str(path)!r}: "
                              "is it blank or without texture?")


def _no_overlap(n_ok: int, n_cand: int, cfg: MatcherConfig, what: str = "") -> EstimationError:
    return EstimationError(
        f"images do not overlap (or are too different): only {n_ok} of {n_cand} candidate matches are "
        f"geometrically consistent{what}; at least {cfg.min_inliers} are needed")


def _verify_checked(pl, pr, cfg: MatcherConfig, method: str) -> Verification:
    if len(pl) < cfg.min_inliers:
        raise _no_overlap(len(pl), len(pl), cfg)
    try:
        ver = verify_matches(pl, pr, method=method, threshold_px=cfg.threshold_px, seed=cfg.seed)
    except EstimationError as err:
        raise _no_overlap(0, len(pl), cfg, f" ({err})") from err
    n_ok = int(ver.inliers.sum())
    if n_ok < cfg.min_inliers:
        raise _no_overlap(n_ok, len(pl), cfg)
    if method == "homography":
        _check_homography_sane(ver.matrix, pl[ver.inliers], cfg)
    return ver


def _check_homography_sane(H, pl, cfg: MatcherConfig) -> None:
    """Reject degenerate homographies (all inliers on a tiny patch or a line)."""
    span = np.ptp(pl, axis=0) if len(pl) else np.zeros(2)
    if min(span) < 8:
        raise _no_overlap(len(pl), len(pl), cfg, f" (inliers span only {span.round(1).tolist()} px)")


def _refine(Lg, Rg, pl, pr, ver: Verification | None, cfg: MatcherConfig, progress=None, keypoints=None):
    A = _local_affine(pl, pr, ver, keypoints=keypoints)
    lim = None if keypoints is None else _shift_limits(np.asarray(keypoints)[:, 2])
    return refine_matches(Lg, Rg, pl, pr, affine=A, config=cfg.lsm, progress=progress, shift_limit_px=lim)


#: a refined position may move from its keypoint by up to this share of the right keypoint's size (SIFT: the size
#: is twice the scale; at coarse scales the detector's position is off by more than ``LsmConfig.max_shift_px``:
#: on the NGI pair 12 of 632 windows converged 2-4.3 px away, onto the known epipolar lines within 0.01-0.23 px),
#: and by at most ``SHIFT_CAP_PX``
SHIFT_PER_SIZE = 0.25
SHIFT_CAP_PX = 6.0


def _shift_limits(size_right: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-match bound of the refinement's move (right px) from the right keypoints' sizes (px)."""
    return np.minimum(SHIFT_PER_SIZE * np.asarray(size_right, dtype=np.float64), SHIFT_CAP_PX)


def _keypoint_shapes(fl: Features, fr: Features, li: NDArray[np.int64], ri: NDArray[np.int64]) -> NDArray[np.float64]:
    """(N, 4) size and orientation of the matched keypoints: size_l, angle_l, size_r, angle_r (px, radians)."""
    return np.c_[fl.size[li], fl.angle[li], fr.size[ri], fr.angle[ri]]


def _final_select(pl, pr, score, shape_left, budget, cap):
    if len(pl) <= budget:
        return np.arange(len(pl))
    # prefer the best scores (lower is better) within each cell
    return grid_select(pl, -score, shape_left, budget, cell_cap=cap)


def _result(pl, pr, score, ver, cfg, n_det, n_matched, n_verified, n_ref, n_fail, raw_pr, cand_l, cand_r,
            cand_inl, tiled, shapes, timings, n_dup: int = 0, n_guided: int = 0, n_screened: int = 0
            ) -> MatchResult:
    ids = tuple(str(i + 1) for i in range(len(pl)))
    refined = sigma = None
    rmse, rmse_unref = ver.rmse_px, float("nan")
    if cfg.refine:
        refined = np.isfinite(score)
        sigma = _sigmas(pr, raw_pr, score, refined)
        if cfg.verify != "none":
            e = ver.errors_px
            rmse = rms(e[refined]) if refined.any() else float("nan")
            rmse_unref = rms(e[~refined]) if (~refined).any() else float("nan")
    rmse_raw = float("nan")
    if cfg.verify != "none" and len(pl) >= 8:
        rmse_raw = rms(_errors(ver.method, ver.matrix, pl, raw_pr))
    return MatchResult(Matches(ids, pl, pr, score, sigma), n_det, n_matched, n_verified, n_ref, n_fail, rmse,
                       rmse_raw, ver, cand_l, cand_r, cand_inl, tiled, shapes, timings, n_dup, n_guided,
                       refined, sigma, n_screened, rmse_unref)


def _sigmas(pr, raw_pr, score, refined) -> NDArray[np.float64]:
    """Standard deviation of each right position (px): the LSM one where refined, else the RMS move of the refined
    matches from their raw positions (what a raw position is off by; NaN with fewer than 8 refined matches)."""
    moved = np.linalg.norm(pr[refined] - raw_pr[refined], axis=1)
    raw_sigma = rms(moved) if len(moved) >= 8 else float("nan")
    return np.where(refined, score, raw_sigma)


def _finish(pl, pr, ratio, Lg, Rg, cfg: MatcherConfig, ver0: Verification | None, progress=None, keypoints=None):
    """Refine (optional), drop failures, re-verify, cap evenly. Returns pieces for _result."""
    raw_pr = pr.copy()
    n_ref = n_fail = 0
    score = ratio.copy()
    if cfg.refine and len(pl):
        lr = _refine(Lg, Rg, pl, pr, ver0, cfg, progress, keypoints)
        ok = lr.converged
        n_ref, n_fail = int(ok.sum()), int((~ok).sum())
        if cfg.keep_unrefined:  # flagged by a NaN score, at the raw (verified) position
            pr = np.where(ok[:, None], lr.right, pr)
            score = np.where(ok, lr.std_px, np.nan)
        else:
            pl, pr, raw_pr, score = pl[ok], lr.right[ok], raw_pr[ok], lr.std_px[ok]
    return pl, pr, raw_pr, score, n_ref, n_fail


# --------------------------------------------------------------------------- in-memory matching
def match_arrays(left: ArrayLike, right: ArrayLike, *, left_valid: ArrayLike | None = None,
                 right_valid: ArrayLike | None = None, config: MatcherConfig | None = None,
                 progress: ProgressFn | None = None) -> MatchResult:
    """Match two in-memory images (whole-image mode).

    Parameters
    ----------
    left, right : (H, W) or (H, W, C) arrays, any dtype
    left_valid, right_valid : (H, W) bool, optional
        Validity masks (nodata = False).
    config : MatcherConfig, optional
    progress : callable(done, total), optional

    Returns
    -------
    MatchResult

    Raises
    ------
    EstimationError
        Blank images (too few keypoints) or images that do not overlap.
    """
    cfg = config or MatcherConfig()
    L = np.asarray(left)
    R = np.asarray(right)
    lv = np.ones(L.shape[:2], bool) if left_valid is None else np.asarray(left_valid, dtype=bool)
    rv = np.ones(R.shape[:2], bool) if right_valid is None else np.asarray(right_valid, dtype=bool)
    return _match_whole(L, lv, R, rv, cfg, progress, ("left", "right"))


def _match_whole(L, lv, R, rv, cfg: MatcherConfig, progress, names) -> MatchResult:
    """Whole-image matching (see :func:`match_arrays`).

    With ``cfg.derotate`` the quarter turn of the right image is first guessed by :func:`_coarse_turns` (a small
    copy of the right image against the left keypoints), and the right image is detected and matched turned back
    by it; the full matches' own orientations check the guess, and a wrong guess is matched once more (turned by
    what they say), so the result is the same as with the right guess."""
    t0 = time.perf_counter()
    if progress is not None:
        progress(0, 4)
    fl = detect(L, valid=lv, detector=cfg.detector, max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap,
                percentiles=cfg.percentiles)
    _check_blank(fl, "left", names[0])
    k = _coarse_turns(fl, L.shape[:2], R, rv, cfg) if cfg.derotate else 0
    t_coarse = time.perf_counter()
    try:
        out = _match_pass(L, lv, R, rv, cfg, progress, names, fl, k, cfg.derotate, t0)
    except EstimationError as err:
        if not k:
            raise
        logger.info("matching with the right image turned by %d quarter turns failed (%s); matching as given", k, err)
        k = 0
        out = _match_pass(L, lv, R, rv, cfg, progress, names, fl, 0, False, t0)
    if isinstance(out, int):   # the full matches say the right image is turned by ``out`` more quarter turns
        t_first = time.perf_counter() - t0
        k2 = (k + out) % 4
        again = None if progress is None else (lambda d, t: progress(max(d, 2), t))   # no step back
        try:
            res = _match_pass(L, lv, R, rv, cfg, again, names, fl, k2, False, time.perf_counter())
        except EstimationError as err:
            logger.info("matching with the right image turned by %d quarter turns failed (%s); matching as turned "
                        "by %d", k2, err, k)
            res = _match_pass(L, lv, R, rv, cfg, again, names, fl, k, False, time.perf_counter())
        assert isinstance(res, MatchResult)
        return replace(res, timings_s={**res.timings_s, "first_pass": t_first,
                                       "total": res.timings_s.get("total", 0.0) + t_first})
    if not cfg.derotate:
        return out
    # the left detection and the guess (included in "detect" and "total")
    return replace(out, timings_s={**out.timings_s, "coarse_turns": t_coarse - t0})


#: the quarter-turn guess of :func:`_coarse_turns`: the right image reduced to at most this long side (px) and
#: this many left keypoints (the largest of each grid cell) matched against its keypoints
COARSE_TURN_PX = 256
COARSE_TURN_KEYPOINTS = 400


def _coarse_turns(fl: Features, shape_left: tuple[int, int], R: NDArray, rv: NDArray[np.bool_],
                  cfg: MatcherConfig) -> int:
    """Quarter turns (0-3, ``np.rot90``) that turn the right image back to the left one, guessed cheaply (1-4 % of
    the matching's time): the right image reduced by an integer factor to at most :data:`COARSE_TURN_PX` px (area
    average), its keypoints matched by brute force (ratio test, mutual) with the :data:`COARSE_TURN_KEYPOINTS`
    largest left keypoints spread over the image; the median orientation difference of the matches, when at least
    12 matches and half of them agree within 30 degrees; 0 otherwise, and for images already that small (the full
    matches then decide, see :func:`_match_whole`)."""
    f = int(math.ceil(max(R.shape[:2]) / COARSE_TURN_PX))
    if f < 2 or len(fl) < 12:
        return 0
    h, w = R.shape[0] // f, R.shape[1] // f
    if min(h, w) < 16:
        return 0
    a = np.asarray(R)[:h * f, :w * f]
    if a.dtype not in (np.uint8, np.uint16, np.float32) or (a.ndim == 3 and a.shape[2] > 4):
        a = rio.to_uint8(a, rv[:h * f, :w * f], percentiles=cfg.percentiles)     # OpenCV's resize takes these only
    small = cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)              # NaN spreads over its cell: invalid
    valid = rv[:h * f, :w * f].reshape(h, f, w, f).all(axis=(1, 3))
    fs = detect(small, valid=valid, detector=cfg.detector, max_keypoints=3 * COARSE_TURN_KEYPOINTS,
                cell_cap=cfg.cell_cap, percentiles=cfg.percentiles)
    if len(fs) < 12:
        return 0
    sub = fl.subset(grid_select(fl.xy, fl.size, shape_left, COARSE_TURN_KEYPOINTS, cell_cap=cfg.cell_cap))
    li, ri = _brute_pairs(sub.descriptors, fs.descriptors, cfg.ratio)
    d = fs.angle[ri] - sub.angle[li]
    d = d[np.isfinite(d)]
    if len(d) < 12:
        return 0
    k = int(round(float(np.angle(np.median(np.cos(d)) + 1j * np.median(np.sin(d)))) / (math.pi / 2))) % 4
    off = np.abs(np.angle(np.exp(1j * (d - k * math.pi / 2))))
    return k if (off < math.radians(30.0)).mean() >= 0.5 else 0


def _brute_pairs(a: NDArray, b: NDArray, ratio: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Mutual nearest descriptors of two small sets (brute force: L2 for float descriptors, Hamming for binary ones)
    passing the ratio test: indices into ``a`` and ``b``."""
    bf = cv2.BFMatcher(cv2.NORM_L2 if a.dtype == np.float32 else cv2.NORM_HAMMING)
    fwd = [m for m in bf.knnMatch(a, b, k=2) if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    li = np.array([m[0].queryIdx for m in fwd], dtype=np.int64)
    ri = np.array([m[0].trainIdx for m in fwd], dtype=np.int64)
    if not len(li):
        return li, ri
    cand = np.unique(ri)                  # back-match the candidates only
    back = np.full(len(b), -1, dtype=np.int64)
    for m in bf.match(np.ascontiguousarray(b[cand]), a):
        back[cand[m.queryIdx]] = m.trainIdx
    ok = back[ri] == li
    return li[ok], ri[ok]


def _match_pass(L, lv, R, rv, cfg: MatcherConfig, progress, names, fl: Features, k: int, check: bool,
                t0: float) -> MatchResult | int:
    """One whole-image matching of the left features ``fl`` with ``np.rot90(R, k)``, returned in the given right
    image's pixels; with ``check``, the number of further quarter turns instead when the verified matches'
    orientations say the turned right image is still turned (:func:`_quarter_turns`)."""
    tick = progress or (lambda d, t: None)
    tick(0, 4)
    shape_right = R.shape[:2]
    if k:
        R, rv = np.rot90(R, k), np.rot90(rv, k)
    fr = detect(R, valid=rv, detector=cfg.detector, max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap,
                percentiles=cfg.percentiles)
    _check_blank(fr, "right", names[1])
    t1 = time.perf_counter()
    tick(1, 4)
    pairs, fwd = _match_descriptors(fl, fr, ratio=cfg.ratio, mutual=cfg.mutual)
    pl, pr = fl.xy[pairs.left], fr.xy[pairs.right]
    ratio = pairs.ratio
    t2 = time.perf_counter()
    tick(2, 4)
    if cfg.verify == "none":
        if len(pl) < cfg.min_inliers:
            raise _no_overlap(len(pl), len(pl), cfg)
        ver0 = None
        inl = np.ones(len(pl), bool)
    else:
        ver0 = _verify_checked(pl, pr, cfg, cfg.verify)
        inl = ver0.inliers
    if check:
        j = _quarter_turns(fl, fr, pairs, inl)
        if j:
            return j
    cand_l, cand_r, cand_inl = pl, pr, inl
    vl, vr, vratio = pl[inl], pr[inl], ratio[inl]
    vli, vri = pairs.left[inl], pairs.right[inl]          # keypoint indices (their sizes and orientations)
    room = cfg.guided_fill - len(vl)
    extra = _guided(fl, fr, pairs, inl, fwd, ver0, cfg) if room > 0 else _Pairs(np.zeros(0, np.int64),
                                                                                 np.zeros(0, np.int64), np.zeros(0))
    if len(extra.left) > room:
        keep = grid_select(fl.xy[extra.left], -extra.ratio, L.shape[:2], room, cell_cap=cfg.cell_cap)
        extra = _Pairs(extra.left[keep], extra.right[keep], extra.ratio[keep])
    n_guided = len(extra.left)
    if n_guided:
        vl = np.concatenate([vl, fl.xy[extra.left]])
        vr = np.concatenate([vr, fr.xy[extra.right]])
        vratio = np.concatenate([vratio, extra.ratio])
        vli, vri = np.concatenate([vli, extra.left]), np.concatenate([vri, extra.right])
    # SIFT's repeated keypoints (one per orientation) are one match: refine it once
    u = _one_to_one(vl, vr, vratio)
    n_dup0 = len(vl) - len(u)
    vl, vr, vratio, vli, vri = vl[u], vr[u], vratio[u], vli[u], vri[u]
    pre = int(math.ceil(1.25 * cfg.max_matches))
    if len(vl) > pre:       # refine only what can be returned (plus a reserve for failures)
        keep = grid_select(vl, -vratio, L.shape[:2], pre, cell_cap=cfg.cell_cap)
        vl, vr, vratio, vli, vri = vl[keep], vr[keep], vratio[keep], vli[keep], vri[keep]
    t3 = time.perf_counter()
    tick(3, 4)
    Lg = _grey_float(L, lv) if cfg.refine else None
    Rg = _grey_float(R, rv) if cfg.refine else None
    fl_, fr_, raw_pr, score, n_ref, n_fail = _finish(vl, vr, vratio, Lg, Rg, cfg, ver0,
                                                     keypoints=_keypoint_shapes(fl, fr, vli, vri))
    out_l, out_r, raw, sc, ver, n_dup, n_scr = _reverify_and_cap(fl_, fr_, raw_pr, score, cfg, L.shape[:2])
    t4 = time.perf_counter()
    tick(4, 4)
    timings = {"detect": t1 - t0, "match": t2 - t1, "verify": t3 - t2, "refine": t4 - t3, "total": t4 - t0}
    res = _result(out_l, out_r, sc, ver, cfg, (len(fl), len(fr)), len(pairs.left), int(inl.sum()) + n_guided,
                  n_ref, n_fail, raw, cand_l, cand_r, cand_inl, False, (L.shape[:2], R.shape[:2]), timings,
                  n_dup0 + n_dup, n_guided, n_scr)
    return _turned_back(res, k, shape_right, cfg) if k else res


def _quarter_turns(fl: Features, fr: Features, pairs: _Pairs, inl: NDArray[np.bool_]) -> int:
    """k in 0..3: the right image's content is turned by about k quarter turns against the left one (the median
    difference of the verified keypoints' orientations, x right, y down), so ``np.rot90(right, k)`` turns it
    back to within 45 degrees (0 without orientations or with fewer than 8 verified matches)."""
    d = fr.angle[pairs.right[inl]] - fl.angle[pairs.left[inl]]
    d = d[np.isfinite(d)]
    if len(d) < 8:
        return 0
    turn = float(np.angle(np.median(np.cos(d)) + 1j * np.median(np.sin(d))))
    return int(round(turn / (math.pi / 2))) % 4


def _turn_matrix(k: int, shape: tuple[int, int]) -> NDArray[np.float64]:
    """T (3, 3): pixel of ``np.rot90(img, k)`` -> pixel of ``img`` (shape (H, W)), homogeneous."""
    T = np.eye(3)
    h, w = shape
    for _ in range(k % 4):
        # one quarter turn: new[i, j] = old[j, w - 1 - i], so (x, y) in new is (w - 1 - y, x) in old
        q = np.array([[0.0, -1.0, w - 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        T = T @ q
        h, w = w, h
    return T


def _turned_back(res: MatchResult, k: int, shape_right: tuple[int, int], cfg: MatcherConfig) -> MatchResult:
    """``res`` (matched with the right image turned by ``np.rot90(right, k)``) in the given right image's pixels."""
    T = _turn_matrix(k, shape_right)

    def back(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(p, dtype=np.float64) @ T[:2, :2].T + T[:2, 2]

    m = res.matches
    matches = Matches(m.ids, m.left, back(m.right), m.score, m.sigma)
    ver = res.verification
    M = ver.matrix
    if M is not None:     # H' = T H (x_r = T x_turned); F' = T^-T F; transfer and Sampson errors are unchanged
        M = T @ M if ver.method == "homography" else np.linalg.inv(T).T @ M
        ver = table_for(Verification(ver.method, M, ver.inliers, ver.errors_px, None), m.left, matches.right,
                        threshold_px=cfg.threshold_px, refined=res.refined)
    logger.info("the right image is turned by %d quarter turns against the left one: matched turned back", k)
    return replace(res, matches=matches, verification=ver, candidates_right=back(res.candidates_right),
                   image_shapes=(res.image_shapes[0], shape_right), n_turns=k)


def _one_to_one(pl, pr, score, tol_px: float = 0.1):
    """Indices of matches with distinct left and distinct right positions (within ``tol_px``), keeping the best
    (lowest) score of each group: SIFT gives several keypoints at one position (one per orientation) and
    refinement can move two candidates onto one point; duplicates make the fitted models singular."""
    if len(pl) == 0:
        return np.arange(0)
    s = np.nan_to_num(np.asarray(score, dtype=float), nan=np.inf)
    order = np.argsort(s, kind="stable")
    keep = order
    for p in (pl, pr):
        q = np.round(np.asarray(p)[keep] / tol_px).astype(np.int64)
        _, first = np.unique(q, axis=0, return_index=True)
        keep = keep[np.sort(first)]
    return np.sort(keep)


#: a match (fundamental verification) farther than this many times the median from where its neighbours put it,
#: and than ``OFF_NEIGHBOURS_MIN_PX``, is a wrong partner along its epipolar line (its parallax is not the relief's)
OFF_NEIGHBOURS_RATIO = 20.0
OFF_NEIGHBOURS_MIN_PX = 20.0


def _off_neighbours(pl, pr) -> NDArray[np.bool_]:
    """Matches whose right point lies far from where their 8 nearest matches put it (fundamental verification lets
    a wrong partner along the epipolar line through); judged again against the nearest of the others only, so
    a good match among wrong ones is kept. None with fewer than 20 matches."""
    if len(pl) < 20:
        return np.zeros(len(pl), bool)
    e = neighbour_residuals(pl, pr)
    cut = max(OFF_NEIGHBOURS_MIN_PX, OFF_NEIGHBOURS_RATIO * float(np.median(e[np.isfinite(e)])))
    off = e > cut
    if off.any() and (~off).sum() >= 20:
        off &= neighbour_residuals(pl, pr, among=~off) > cut
    return np.asarray(off, dtype=bool)


def _reverify_and_cap(pl, pr, raw_pr, score, cfg: MatcherConfig, shape_left, keep_unrefined: bool | None = None):
    """One-to-one, re-verification, the screening of refined matches (refinement on) and the even cap.

    Returns the matches (left, right, raw right, score), the verification of exactly them (its model fitted to
    the refined matches when there are enough), the duplicates removed and the refined matches screened out
    (kept unrefined when ``keep_unrefined``, default ``cfg.keep_unrefined``, or dropped)."""
    u = _one_to_one(pl, pr, score)
    n_dup = len(pl) - len(u)
    pl, pr, raw_pr, score = pl[u], pr[u], raw_pr[u], score[u]
    if cfg.verify == "none":
        keep = _final_select(pl, pr, score, shape_left, cfg.max_matches, cfg.cell_cap)
        pl, pr, raw_pr, score = pl[keep], pr[keep], raw_pr[keep], score[keep]
        return pl, pr, raw_pr, score, verify_matches(pl, pr, method="none"), n_dup, 0
    n_screened = 0
    if cfg.verify == "fundamental":    # wrong partners along the epipolar lines, before the model is fitted
        odd = _off_neighbours(pl, pr)
        pl, pr, raw_pr, score = pl[~odd], pr[~odd], raw_pr[~odd], score[~odd]
        n_screened += int(odd.sum())
    ver = _verify_checked(pl, pr, cfg, cfg.verify)
    m = ver.inliers
    pl, pr, raw_pr, score = pl[m], pr[m], raw_pr[m], score[m]
    if cfg.refine:
        ver, pl, pr, raw_pr, score, n_off = screen_refined(
            ver, pl, pr, raw_pr, score, threshold_px=cfg.threshold_px, min_inliers=cfg.min_inliers,
            keep_unrefined=cfg.keep_unrefined if keep_unrefined is None else keep_unrefined, seed=cfg.seed)
        n_screened += n_off
    keep = _final_select(pl, pr, score, shape_left, cfg.max_matches, cfg.cell_cap)
    pl, pr, raw_pr, score = pl[keep], pr[keep], raw_pr[keep], score[keep]
    # the residual table of exactly the returned matches, with the same model
    ver = table_for(ver, pl, pr, threshold_px=cfg.threshold_px, refined=np.isfinite(score) if cfg.refine else None)
    return pl, pr, raw_pr, score, ver, n_dup, n_screened


