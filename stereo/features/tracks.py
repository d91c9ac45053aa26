"""Block tie points: multi-image tracks from the images of a block.

:func:`block_tie_points` runs these steps:

1. **Pairs** (:func:`stereo.block.tracks_pairs.select_pairs`): from footprints when poses,
   cameras and the mean terrain height are given, all pairs for small blocks, an overview match
   otherwise.
2. **Detection once per image** (:func:`rectify.features.detect`), so a keypoint index means the
   same point in every pair. Images whose longer side exceeds ``detect_max_px`` are detected on an
   area-averaged overview of that size (read by strips through :mod:`rectify.raster.io`, bounded memory)
   and their positions scaled to full resolution; their a-priori sigma grows by the scale.
3. **Matching per pair**: :func:`rectify.features.match_descriptors` (ratio test, mutual check),
   then :func:`rectify.features.verify_matches` with the matcher's model: the fundamental matrix
   by default, as the stereo pair matcher does (a homography drops the matches off the dominant
   plane when there is relief). A pair with fewer than ``min_inliers`` verified matches gives none.
4. **Tracks** (:mod:`stereo.block.tracks_graph`): union-find over (image, keypoint) nodes; a
   component holding two keypoints of one image is dropped or split (``conflicts``); tracks seen
   in fewer than ``min_rays`` images are dropped; tracks with more rays rank first. Two
   observations of a track joined only transitively are checked against their pair's verified
   model, and the observation in the most failing pairs is removed until none fails.
5. **Even spread** (:func:`stereo.block.tracks_graph.spread_tracks`): every image keeps up to
   ``per_cell`` tracks in each cell of a ``grid``, preferring more rays, then better match ratios.
6. **Refinement** (optional, ``matcher.refine``): least-squares matching
   (:func:`rectify.features.lsm.refine_matches`). A track must carry one position per image, so each
   track's *reference* observation (the one nearest its image's centre) stays fixed and every
   other observation of the track is refined against it, with the initial affine shape fitted to
   the neighbouring tracks of the same image pair. Observations whose refinement does not
   converge keep their detected position and the unrefined sigma (``sigma_px``); refined
   observations, and the reference of a track with at least one refined observation, get
   ``sigma_refined_px``. Images detected on an overview are not refined.

The result :class:`BlockTiePoints` holds the tracks with a-priori sigmas, the pairs with their
match counts, per-image counts and grid coverage, the histogram of rays per track and what was
rejected. Inputs are checked first (fewer than 2 images, duplicate names, unreadable files), and a
block whose tie points leave an image unconnected or split the block in parts is refused with the
images named.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.features.detect import Features, detect
from rectify.features.lsm import refine_matches
from rectify.features.match import MatcherConfig, _local_affine, match_descriptors, verify_matches
from rectify.geometry.camera import Camera
from rectify.raster import io as rio
from stereo.block.tracks_graph import (
    CONFLICT_POLICIES,
    PairMatches,
    TrackBuild,
    build_tracks,
    connected_labels,
    grid_coverage,
    rays_histogram,
    spread_tracks,
)
from stereo.block.tracks_pairs import PAIR_STRATEGIES, ImagePair, select_pairs
from stereo.block.types import Pose, Tracks

logger = logging.getLogger(__name__)

__all__ = ["BLOCK_MATCHER", "BlockMatchOptions", "BlockTiePoints", "PairMatchStats", "block_tie_points",
           "block_components"]

#: the matcher of a block: fundamental-matrix verification, 8000 keypoints per image, LSM refinement
BLOCK_MATCHER = MatcherConfig(verify="fundamental", max_keypoints=8000)


@dataclass(frozen=True)
class BlockMatchOptions:
    """Options of :func:`block_tie_points`. Defaults live here only.

    Attributes
    ----------
    matcher : MatcherConfig
        Detector, ``max_keypoints`` per image, ``cell_cap``, ``ratio``, ``mutual``, ``verify``,
        ``threshold_px``, ``min_inliers`` (per pair), ``refine`` and ``lsm``, ``percentiles``,
        ``seed`` are used; the tiling options are not (see ``detect_max_px``).
    pair_strategy : {"auto", "footprints", "all", "overview"}
    min_overlap : float
        Footprint overlap a pair needs (fraction of the smaller footprint).
    max_all_pairs : int
        ``auto`` matches all pairs of blocks up to this many images.
    neighbours : int
        ``overview`` pair selection: partners per image.
    overview_px : int
        ``overview`` pair selection: longer side of the overviews, px.
    detect_max_px : int
        Images with a longer side above this are detected on an overview of this size.
    conflicts : {"drop", "split"}
        Tracks holding two keypoints of one image (:mod:`stereo.block.tracks_graph`).
    min_rays : int
        Images a track must reach (>= 2).
    grid : (int, int)
        Cells across and down each image for the even spread and the coverage.
    per_cell : int
        Tracks chosen per cell of every image.
    sigma_px : float
        A-priori standard deviation of a detected (unrefined) position, px.
    sigma_refined_px : float
        The same for a position refined by least-squares matching, px.
    """

    matcher: MatcherConfig = field(default_factory=lambda: BLOCK_MATCHER)
    pair_strategy: str = "auto"
    min_overlap: float = 0.1
    max_all_pairs: int = 12
    neighbours: int = 6
    overview_px: int = 512
    detect_max_px: int = 4096
    conflicts: str = "drop"
    min_rays: int = 2
    grid: tuple[int, int] = (8, 8)
    per_cell: int = 6
    sigma_px: float = 0.5
    sigma_refined_px: float = 0.25

    def __post_init__(self) -> None:
        if not isinstance(self.matcher, MatcherConfig):
            raise InvalidInputError(f"matcher must be a MatcherConfig; got {type(self.matcher).__name__}")
        if self.pair_strategy not in PAIR_STRATEGIES:
            raise InvalidInputError(f"unknown pair strategy {self.pair_strategy!r}; choose from {PAIR_STRATEGIES}")
        if self.conflicts not in CONFLICT_POLICIES:
            raise InvalidInputError(f"unknown conflict policy {self.conflicts!r}; choose from {CONFLICT_POLICIES}")
        if not (0 < self.min_overlap <= 1):
            raise InvalidInputError(f"min_overlap must be in (0, 1]; got {self.min_overlap!r}")
        for name, lo in (("max_all_pairs", 2), ("neighbours", 1), ("overview_px", 64), ("detect_max_px", 64),
                         ("min_rays", 2), ("per_cell", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise InvalidInputError(f"{name} must be an integer >= {lo}; got {v!r}")
        g = tuple(self.grid)
        if len(g) != 2 or not all(isinstance(c, (int, np.integer)) and c >= 1 for c in g):
            raise InvalidInputError(f"grid must be two integers >= 1 (cells across, down); got {self.grid!r}")
        for name in ("sigma_px", "sigma_refined_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InvalidInputError(f"{name} must be a positive number; got {v!r}")


@dataclass(frozen=True)
class PairMatchStats:
    """How one selected pair matched.

    Attributes
    ----------
    i, j : int
        Image indices.
    reason : str
        Why the pair was selected (:class:`ImagePair`).
    overlap : float
        Predicted footprint overlap (NaN when not predicted).
    n_candidates : int
        Matches after the ratio test and mutual check.
    n_verified : int
        Matches consistent with the verification model (0 when the pair failed).
    status : str
        ``"ok"``, or why the pair gave no matches.
    """

    i: int
    j: int
    reason: str
    overlap: float
    n_candidates: int
    n_verified: int
    status: str = "ok"


@dataclass(frozen=True, eq=False)
class BlockTiePoints:
    """The tie points of a block (:func:`block_tie_points`).

    Attributes
    ----------
    tracks : Tracks
        The kept tracks; pixels in each image's frame, ``obs_sigma_px`` the a-priori sigmas.
    pairs : tuple of PairMatchStats
        Every selected pair with its match counts.
    n_keypoints : (n_images,) int64
        Keypoints detected per image.
    points_per_image : (n_images,) int64
        Observations kept per image.
    coverage : (n_images,) float64
        Fraction of each image's grid cells holding a kept observation.
    rays_histogram : dict
        {rays: number of tracks}.
    n_tracks_built : int
        Tracks after conflicts and ``min_rays``, before the even spread.
    n_conflicting : int
        Components holding two keypoints of one image (dropped or split).
    n_split : int
        Tracks made from the pieces of conflicting components.
    n_obs_dropped : int
        Observations lost to conflicts.
    n_short : int
        Components seen in fewer than ``min_rays`` images.
    n_inconsistent : int
        Observations removed because they do not fit the verified model of a pair with another
        observation of their track (they were joined transitively, never matched to each other).
    n_spread_dropped : int
        Tracks left out by the even spread.
    n_refined, n_refine_failed : int
        Observations refined by least-squares matching, and those whose refinement did not converge.
    grid : (int, int)
        The coverage grid (cells across, down).
    timings_s : dict
    """

    tracks: Tracks
    pairs: tuple[PairMatchStats, ...]
    n_keypoints: NDArray[np.int64]
    points_per_image: NDArray[np.int64]
    coverage: NDArray[np.float64]
    rays_histogram: dict[int, int]
    n_tracks_built: int
    n_conflicting: int
    n_split: int
    n_obs_dropped: int
    n_short: int
    n_inconsistent: int
    n_spread_dropped: int
    n_refined: int
    n_refine_failed: int
    grid: tuple[int, int] = (8, 8)
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def images(self) -> tuple[str, ...]:
        return self.tracks.images

    @property
    def rejected(self) -> dict[str, int]:
        """Counts of what was rejected: conflicting tracks, their observations, short tracks, spread."""
        return {"conflicting_tracks": self.n_conflicting, "conflict_observations": self.n_obs_dropped,
                "short_tracks": self.n_short, "inconsistent_observations": self.n_inconsistent,
                "spread_tracks": self.n_spread_dropped,
                "failed_pairs": sum(p.status != "ok" for p in self.pairs)}

    def summary_lines(self) -> list[str]:
        """The lines a command prints: totals, rays histogram, rejections, per-image counts."""
        t = self.tracks
        ok = sum(p.status == "ok" for p in self.pairs)
        hist = ", ".join(f"{k}: {v}" for k, v in self.rays_histogram.items())
        lines = [f"block tie points: {t.n_points} tracks, {t.n_obs} observations in {len(t.images)} images",
                 f"pairs: {ok} of {len(self.pairs)} matched, "
                 f"{sum(p.n_verified for p in self.pairs)} verified matches",
                 f"rays per track: {hist or 'none'}",
                 f"rejected: {self.n_conflicting} conflicting tracks ({self.n_split} pieces kept, "
                 f"{self.n_obs_dropped} observations), {self.n_short} short, "
                 f"{self.n_inconsistent} inconsistent observations, {self.n_spread_dropped} tracks by the spread",
                 f"refined: {self.n_refined} observations ({self.n_refine_failed} did not converge)"]
        gx, gy = self.grid
        for k, name in enumerate(t.images):
            lines.append(f"  {name}: {int(self.points_per_image[k])} points, {int(self.n_keypoints[k])} keypoints, "
                         f"coverage {100 * self.coverage[k]:.0f}% of {gx}x{gy} cells")
        for p in self.pairs:
            if p.status != "ok":
                lines.append(f"  pair {t.images[p.i]} - {t.images[p.j]}: {p.status}")
        return lines


# --------------------------------------------------------------------------- inputs
def _names(paths: Sequence[Path], names: Sequence[str] | None) -> tuple[str, ...]:
    out = tuple(p.stem for p in paths) if names is None else tuple(str(n) for n in names)
    if len(out) != len(paths):
        raise InvalidInputError(f"{len(out)} names for {len(paths)} images")
    if any(not n for n in out):
        raise InvalidInputError(f"image names must be non-empty; got {list(out)}")
    seen: set[str] = set()
    dup = sorted({n for n in out if n in seen or seen.add(n)})  # type: ignore[func-returns-value]
    if dup:
        hint = "" if names is not None else " (file names without suffix; pass `names=`)"
        raise InvalidInputError(f"duplicate image names {dup}{hint}")
    return out


def _poses_in_order(poses: Sequence[Pose] | Mapping[str, Pose], names: tuple[str, ...]) -> list[Pose]:
    by_name = dict(poses) if isinstance(poses, Mapping) else {p.image: p for p in poses}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise InvalidInputError(f"no pose for image(s) {missing} (poses given for {sorted(by_name)[:10]})")
    return [by_name[n] for n in names]


# --------------------------------------------------------------------------- detection
@dataclass(frozen=True, eq=False)
class _ImageFeatures:
    features: Features
    scale: tuple[float, float]    # full-resolution px per detection px (x, y)
    size: tuple[int, int]         # (width, height)


def _detect_image(path: Path, info: rio.RasterInfo, opts: BlockMatchOptions) -> _ImageFeatures:
    cfg = opts.matcher
    big = max(info.width, info.height) > opts.detect_max_px
    if big:
        data, valid, _ = rio.read_overview_average(path, opts.detect_max_px)
        scale = (info.width / data.shape[1], info.height / data.shape[0])
    else:
        data, valid = rio.read_window(path, 0, 0, info.width, info.height)
        scale = (1.0, 1.0)
    f = detect(data, valid=valid, detector=cfg.detector, max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap,
               percentiles=cfg.percentiles)
    if len(f) < 8:
        raise EstimationError(f"only {len(f)} keypoints found in image {str(path)!r}: is it blank or without "
                              "texture?")
    if big:
        xy = (f.xy + 0.5) * np.asarray(scale) - 0.5
        f = Features(xy, f.size * max(scale), f.angle, f.response, f.level, f.descriptors)
    return _ImageFeatures(f, scale, (info.width, info.height))


def _match_pair(a: _ImageFeatures, b: _ImageFeatures, pair: ImagePair, cfg: MatcherConfig
                ) -> tuple[PairMatchStats, PairMatches | None, NDArray[np.float64] | None]:
    pm = match_descriptors(a.features, b.features, ratio=cfg.ratio, mutual=cfg.mutual)
    n = len(pm.left)

    def stats(nv: int, status: str) -> PairMatchStats:
        return PairMatchStats(pair.i, pair.j, pair.reason, float(pair.overlap), n, nv, status)

    if n < cfg.min_inliers:
        return stats(0, f"only {n} candidate matches (at least {cfg.min_inliers} needed)"), None, None
    thr = cfg.threshold_px * max(*a.scale, *b.scale)
    try:
        ver = verify_matches(a.features.xy[pm.left], b.features.xy[pm.right], method=cfg.verify, threshold_px=thr,
                             seed=cfg.seed)
    except EstimationError as err:
        return stats(0, f"verification failed ({err})"), None, None
    inl = ver.inliers
    nv = int(inl.sum())
    if nv < cfg.min_inliers:
        return stats(0, f"only {nv} of {n} matches verified (at least {cfg.min_inliers} needed)"), None, None
    return stats(nv, "ok"), PairMatches(pair.i, pair.j, pm.left[inl], pm.right[inl], pm.ratio[inl]), ver.matrix


# --------------------------------------------------------------------------- track consistency
def _pair_errors(method: str, M: NDArray[np.float64], pi: NDArray[np.float64], pj: NDArray[np.float64]
                 ) -> NDArray[np.float64]:
    """Sampson distance (fundamental, x_j^T F x_i = 0) or transfer error |H x_i - x_j| (homography), px."""
    xi = np.c_[pi, np.ones(len(pi))]
    xj = np.c_[pj, np.ones(len(pj))]
    if method == "homography":
        q = xi @ M.T
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(q[:, :2] / q[:, 2:] - pj, axis=1)
    else:
        Fx = xi @ M.T
        Ftx = xj @ M
        num = np.sum(xj * Fx, axis=1)
        den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.abs(num) / np.sqrt(den)
    return np.where(np.isfinite(e), e, np.inf)


def _inconsistent_obs(tracks: Tracks, models: Mapping[tuple[int, int], NDArray[np.float64]], method: str,
                      threshold_px: float) -> NDArray[np.bool_]:
    """Observations to drop so that every pair of observations in a track fits its pair's model.

    Union-find joins matches transitively, so two observations of a track may never have been
    matched to each other; where their pair was verified, its model checks them. In each track the
    observation in the most failing pairs is removed until none fails.
    """
    m = tracks.n_obs
    drop = np.zeros(m, dtype=bool)
    if m == 0 or method == "none" or not models:
        return drop
    rays = tracks.rays_per_point()
    a_list, b_list = [], []
    idx = np.arange(m)
    for d in range(1, int(rays.max())):
        a = idx[:-d]
        b = idx[d:]
        same = tracks.obs_point[a] == tracks.obs_point[b]
        a_list.append(a[same])
        b_list.append(b[same])
    a = np.concatenate(a_list) if a_list else np.zeros(0, np.int64)
    b = np.concatenate(b_list) if b_list else np.zeros(0, np.int64)
    bad = np.zeros(len(a), dtype=bool)
    ia, ib = tracks.obs_image[a], tracks.obs_image[b]     # ia < ib: observations are sorted by image
    for (i, j), M in models.items():
        sel = np.flatnonzero((ia == i) & (ib == j))
        if sel.size:
            e = _pair_errors(method, M, tracks.obs_pixel[a[sel]], tracks.obs_pixel[b[sel]])
            bad[sel] = e > threshold_px
    if not bad.any():
        return drop
    a, b = a[bad], b[bad]
    for t in np.unique(tracks.obs_point[a]):
        sel = tracks.obs_point[a] == t
        edges = list(zip(a[sel].tolist(), b[sel].tolist(), strict=True))
        while edges:
            cnt: dict[int, int] = {}
            for x, y in edges:
                cnt[x] = cnt.get(x, 0) + 1
                cnt[y] = cnt.get(y, 0) + 1
            worst = max(sorted(cnt), key=lambda k: cnt[k])
            drop[worst] = True
            edges = [(x, y) for x, y in edges if worst not in (x, y)]
    return drop


# --------------------------------------------------------------------------- refinement
class _GreyCache:
    """Grey float32 images read through rectify.raster.io, a few at a time (bounded memory)."""

    def __init__(self, paths: Sequence[Path], size: int = 3):
        self.paths = paths
        self.size = size
        self.cache: OrderedDict[int, NDArray[np.float32]] = OrderedDict()

    def get(self, k: int) -> NDArray[np.float32]:
        if k in self.cache:
            self.cache.move_to_end(k)
            return self.cache[k]
        info = rio.raster_info(self.paths[k])
        data, valid = rio.read_window(self.paths[k], 0, 0, info.width, info.height)
        g = data.astype(np.float32).mean(axis=2)
        g[~valid] = np.nan
        self.cache[k] = g
        while len(self.cache) > self.size:
            self.cache.popitem(last=False)
        return g


def _reference_obs(tracks: Tracks, sizes: NDArray[np.int64]) -> NDArray[np.int64]:
    """(P,) index of each track's observation nearest its image's centre (normalised by the size)."""
    centre = (sizes[tracks.obs_image] - 1) / 2.0
    d = np.linalg.norm((tracks.obs_pixel - centre) / sizes[tracks.obs_image], axis=1)
    order = np.lexsort((d, tracks.obs_point))
    first = np.r_[True, tracks.obs_point[order][1:] != tracks.obs_point[order][:-1]]
    return order[first]


def _refine(tracks: Tracks, paths: Sequence[Path], feats: Sequence[_ImageFeatures], cfg: MatcherConfig
            ) -> tuple[NDArray[np.float64], NDArray[np.bool_], int]:
    """Refine every non-reference observation against its track's reference observation.

    Returns the new pixels (M, 2), a refined flag (M,) and the number of observations tried.
    """
    sizes = np.array([f.size for f in feats], dtype=np.int64)
    full = np.array([f.scale == (1.0, 1.0) for f in feats])
    ref = _reference_obs(tracks, sizes)
    ref_of = ref[tracks.obs_point]            # reference observation of each observation's track
    ref_img = tracks.obs_image[ref_of]
    todo = (np.arange(tracks.n_obs) != ref_of) & full[tracks.obs_image] & full[ref_img]
    pix = np.array(tracks.obs_pixel, copy=True)
    done = np.zeros(tracks.n_obs, dtype=bool)
    cache = _GreyCache(paths)
    keys = np.unique(np.c_[ref_img[todo], tracks.obs_image[todo]], axis=0)
    for r, o in keys:
        sel = np.flatnonzero(todo & (ref_img == r) & (tracks.obs_image == o))
        pl = tracks.obs_pixel[ref_of[sel]]
        pr = tracks.obs_pixel[sel]
        A = _local_affine(pl, pr, None)
        res = refine_matches(cache.get(int(r)), cache.get(int(o)), pl, pr, affine=A, config=cfg.lsm)
        pix[sel[res.converged]] = res.right[res.converged]
        done[sel[res.converged]] = True
    return pix, done, int(todo.sum())


# --------------------------------------------------------------------------- connectivity
def block_components(tracks: Tracks) -> list[list[int]]:
    """Groups of images connected through shared tracks (image indices, each group sorted; largest first).

    An image with no observation is a group of its own.
    """
    n = len(tracks.images)
    if tracks.n_obs == 0:
        return [[k] for k in range(n)]
    first = np.full(tracks.n_points, -1, dtype=np.int64)
    first[tracks.obs_point[::-1]] = tracks.obs_image[::-1]
    label = connected_labels(n, first[tracks.obs_point], tracks.obs_image)
    groups: dict[int, list[int]] = {}
    for k in range(n):
        groups.setdefault(int(label[k]), []).append(k)
    return sorted(groups.values(), key=lambda g: (-len(g), g[0]))


def _check_block(tracks: Tracks, names: tuple[str, ...], result_pairs: Sequence[PairMatchStats]) -> None:
    counts = tracks.points_per_image()
    lonely = [names[k] for k in np.flatnonzero(counts == 0)]
    if lonely:
        tried = {k: 0 for k in range(len(names))}
        for p in result_pairs:
            tried[p.i] += 1
            tried[p.j] += 1
        detail = ", ".join(f"{names[k]!r} ({tried[k]} pairs tried)" for k in np.flatnonzero(counts == 0).tolist())
        raise EstimationError(f"image(s) {lonely} have no tie points to any other image: {detail}")
    comps = block_components(tracks)
    if len(comps) > 1:
        parts = " | ".join("[" + ", ".join(names[k] for k in c) + "]" for c in comps)
        raise EstimationError(f"the block is disconnected: {len(comps)} groups of images share no tie points: "
                              f"{parts}")


# --------------------------------------------------------------------------- the step
def block_tie_points(image_paths: Sequence[str | Path], *, names: Sequence[str] | None = None,
                     cameras: Camera | Mapping[str, Camera] | None = None,
                     poses: Sequence[Pose] | Mapping[str, Pose] | None = None, ground_z: float | None = None,
                     options: BlockMatchOptions | None = None,
                     progress: Callable[[int, int], None] | None = None) -> BlockTiePoints:
    """Find the multi-image tie points (tracks) of a block of images.

    Parameters
    ----------
    image_paths : sequence of path
        The images (any raster rasterio reads), in block order.
    names : sequence of str, optional
        Image names (default: the file names without suffix); unique.
    cameras : Camera or mapping camera id -> Camera, optional
        With ``poses`` and ``ground_z``: pair selection from footprints.
    poses : sequence of Pose or mapping name -> Pose, optional
        Approximate exterior orientations, matched to the images by name.
    ground_z : float, optional
        Mean terrain height, ground frame, m.
    options : BlockMatchOptions, optional
    progress : callable(done, total), optional
        Called after each image detected, each pair matched, and the track steps.

    Returns
    -------
    BlockTiePoints

    Raises
    ------
    InvalidInputError
        Fewer than 2 images, duplicate or missing names, poses missing for an image.
    RasterIOError
        An image cannot be read (the error names the file).
    EstimationError
        A blank image, an image with no tie points to any other, or a disconnected block (the
        images are named).
    """
    opts = options or BlockMatchOptions()
    cfg = opts.matcher
    paths = [Path(p) for p in image_paths]
    if len(paths) < 2:
        raise InvalidInputError(f"a block needs at least 2 images; got {len(paths)}")
    block_names = _names(paths, names)
    ordered = _poses_in_order(poses, block_names) if poses is not None else None
    infos = [rio.raster_info(p) for p in paths]
    t0 = time.perf_counter()
    pairs = select_pairs(block_names, cameras=cameras, poses=ordered, ground_z=ground_z, images=paths,
                         strategy=opts.pair_strategy, min_overlap=opts.min_overlap,
                         max_all_pairs=opts.max_all_pairs, neighbours=opts.neighbours,
                         overview_px=opts.overview_px)
    n = len(paths)
    total = n + len(pairs) + 2
    tick = progress or (lambda d, t: None)
    t1 = time.perf_counter()
    feats = []
    for k, (p, info) in enumerate(zip(paths, infos, strict=True)):
        feats.append(_detect_image(p, info, opts))
        tick(k + 1, total)
    t2 = time.perf_counter()
    stats: list[PairMatchStats] = []
    matches: list[PairMatches] = []
    models: dict[tuple[int, int], NDArray[np.float64]] = {}
    for k, pair in enumerate(pairs):
        st, pm, M = _match_pair(feats[pair.i], feats[pair.j], pair, cfg)
        stats.append(st)
        if pm is not None and M is not None:
            matches.append(pm)
            models[(pair.i, pair.j)] = M
        tick(n + k + 1, total)
    t3 = time.perf_counter()
    build: TrackBuild = build_tracks([f.features.xy for f in feats], matches, images=block_names,
                                     conflicts=opts.conflicts, min_rays=opts.min_rays)
    thr = cfg.threshold_px * float(max(max(f.scale) for f in feats))
    bad_obs = _inconsistent_obs(build.tracks, models, cfg.verify, max(2.5 * thr, thr + 1.0))
    built = build.tracks
    score = build.track_score
    if bad_obs.any():
        counts = np.bincount(built.obs_point[~bad_obs], minlength=built.n_points)
        ok_track = counts >= opts.min_rays
        score = score[ok_track]
        built = built.subset(~bad_obs & ok_track[built.obs_point])
    n_inconsistent = int(bad_obs.sum())
    sizes = np.array([f.size for f in feats], dtype=np.int64)
    grid = (int(opts.grid[0]), int(opts.grid[1]))
    spread = spread_tracks(built, sizes, grid=grid, per_cell=opts.per_cell, track_score=score)
    tracks = built.subset(spread.keep[built.obs_point])
    tick(n + len(pairs) + 1, total)
    t4 = time.perf_counter()
    scale = np.array([max(f.scale) for f in feats])
    sigma = opts.sigma_px * scale[tracks.obs_image]
    n_ref = n_fail = 0
    if cfg.refine and tracks.n_obs:
        pix, ok, n_try = _refine(tracks, paths, feats, cfg)
        n_ref, n_fail = int(ok.sum()), n_try - int(ok.sum())
        # the reference defines the point its refined partners were matched to: it shares their sigma
        sizes_ = np.array([f.size for f in feats], dtype=np.int64)
        has_refined = np.bincount(tracks.obs_point[ok], minlength=tracks.n_points) > 0
        ref = np.zeros(tracks.n_obs, dtype=bool)
        ref[_reference_obs(tracks, sizes_)] = True
        sigma = np.where(ok | (ref & has_refined[tracks.obs_point]), opts.sigma_refined_px, sigma)
    else:
        pix = tracks.obs_pixel
    tracks = Tracks(tracks.images, tracks.point_ids, tracks.obs_point, tracks.obs_image, pix, sigma)
    tick(total, total)
    t5 = time.perf_counter()
    _check_block(tracks, block_names, stats)
    cov = grid_coverage(tracks.obs_pixel, tracks.obs_image, sizes, grid=grid)
    result = BlockTiePoints(
        tracks=tracks, pairs=tuple(stats), n_keypoints=np.array([len(f.features) for f in feats], dtype=np.int64),
        points_per_image=tracks.points_per_image(), coverage=cov, rays_histogram=rays_histogram(tracks),
        n_tracks_built=built.n_points, n_conflicting=build.n_conflicting, n_split=build.n_split,
        n_obs_dropped=build.n_obs_dropped, n_short=build.n_short, n_inconsistent=n_inconsistent,
        n_spread_dropped=built.n_points - tracks.n_points, n_refined=n_ref, n_refine_failed=n_fail,
        grid=grid, timings_s={"pairs": t1 - t0, "detect": t2 - t1, "match": t3 - t2, "tracks": t4 - t3,
                              "refine": t5 - t4, "total": t5 - t0})
    logger.info("block tie points: %d tracks, %d observations in %d images", tracks.n_points, tracks.n_obs, n)
    return result
