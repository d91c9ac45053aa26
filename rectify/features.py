"""Tie points: detection, matching, geometric verification, large images.

Pipeline (:func:`match_images`)::

    read (windows) -> grey uint8 (percentile stretch, detection only; nodata masked)
      -> detect (SIFT | ORB | AKAZE), bias-free subpixel positions, even spread (cap per grid cell)
      -> match (ratio test + mutual check; FLANN for float, Hamming brute force for binary)
      -> verify (OpenCV USAC MAGSAC++: homography | fundamental | none)
      -> refine (least-squares matching, :mod:`rectify.lsm`) -> re-verify -> even selection

Small images (both sides <= ``MatcherConfig.tiled_above_px``) are matched whole.
Larger ones go coarse-to-fine: both images are read as area-averaged overviews
(streamed by strips), matched and verified with a homography; then the left
image is processed tile by tile (``tile_px`` plus ``overlap_px``), and for each
tile only the right window where the coarse homography predicts the partner
(plus ``search_margin_px``) is read and searched. Candidates are thinned by a
global grid cap, so the memory held does not grow with the image size.

Memory bound (defaults, any image size): one left tile (1120 x 1120 px) and
one right tile or window being detected, with their SIFT scale spaces (about
0.35 GB each), the right-tile feature cache (at most 256 MB of descriptors),
two overviews of at most 2048 px per side (float32, 16 MB per band), overview
strips of at most 16 Mpx of source, the right pixels under one tile's matches
for refinement, and at most ``max_candidates`` candidate matches (about 60
bytes each): about 1.3 GB. Measured peak RSS: 1.10 GB on an 8000^2 pair and
1.28 GB on a 33 000^2 pair (``scripts/bench_match.py``).

Positions
---------
Every position is in the project's pixel convention (pixel centres at
integers, x = column, y = row). Each detector's systematic offset is removed
where the keypoints are made (:func:`detect`):

- OpenCV SIFT works on an image upsampled 2x whose pixel ``i`` is taken to
  be at ``i / 2``; its centre is at ``i / 2 - 0.25``, so SIFT positions are
  0.25 px too large in x and y at every octave: we subtract 0.25.
- OpenCV ORB reports ``x_l * s**l`` for a keypoint at pixel ``x_l`` of
  pyramid level ``l`` (scale factor ``s``), but level ``l`` has
  ``round(W / s**l)`` columns, resized with pixel centres aligned, so the
  true position is ``(x_l + 0.5) * W / round(W / s**l) - 0.5`` (rows alike
  with H). The error is up to -0.9 px at coarse levels and grows with the
  distance from the origin; we recompute the true position.
- AKAZE is not part of OpenCV 5.0's main modules (it moved to contrib);
  ``detector="akaze"`` raises :class:`InvalidInputError` there. On builds
  that have ``cv2.AKAZE_create`` its positions are used as reported, after
  the rotated-copy check in the tests.

The rotated-copy experiment (an image against its 180-degree rotation, where
``x' = W - 1 - x`` exactly) measures what remains; the tests require <= 0.02 px.
"""

from __future__ import annotations

import enum
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import io as rio
from .errors import EstimationError, InvalidInputError
from .lsm import LsmConfig, refine_matches
from .residuals import ResidualTable, rms
from .tables import Matches

__all__ = [
    "DETECTORS",
    "VERIFY_METHODS",
    "Detector",
    "Features",
    "MatchResult",
    "MatcherConfig",
    "Verification",
    "Verify",
    "akaze_available",
    "detect",
    "grid_select",
    "match_arrays",
    "match_descriptors",
    "match_figures",
    "match_images",
    "verify_matches",
]

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]


class Detector(str, enum.Enum):
    SIFT = "sift"
    ORB = "orb"
    AKAZE = "akaze"


class Verify(str, enum.Enum):
    HOMOGRAPHY = "homography"
    FUNDAMENTAL = "fundamental"
    NONE = "none"


DETECTORS = tuple(d.value for d in Detector)
VERIFY_METHODS = tuple(v.value for v in Verify)

SIFT_OFFSET_PX = 0.25
"""OpenCV SIFT positions exceed the pixel-centre convention by this, in x and y."""


def akaze_available() -> bool:
    """True when the installed OpenCV build provides AKAZE."""
    import cv2

    return hasattr(cv2, "AKAZE_create")


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
        bounded too while matches still spread over the whole overlap.
    min_inliers : int
        Fewer verified matches than this means the images do not overlap.
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
    lsm: LsmConfig = field(default_factory=LsmConfig)
    percentiles: tuple[float, float] = (0.5, 99.5)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise InvalidInputError(f"unknown detector {self.detector!r}; choose from {DETECTORS}")
        if self.verify not in VERIFY_METHODS:
            raise InvalidInputError(f"unknown verification {self.verify!r}; choose from {VERIFY_METHODS}")
        for name in ("max_matches", "max_keypoints", "cell_cap", "tile_px", "overview_px", "max_candidates",
                     "tiled_above_px", "max_tiles"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise InvalidInputError(f"{name} must be a positive integer; got {v!r}")
        if self.overlap_px < 0:
            raise InvalidInputError(f"overlap_px must be >= 0; got {self.overlap_px!r}")
        if not (0 < self.ratio <= 1):
            raise InvalidInputError(f"ratio must be in (0, 1]; got {self.ratio!r}")
        if not (math.isfinite(self.threshold_px) and self.threshold_px > 0):
            raise InvalidInputError(f"threshold_px must be > 0; got {self.threshold_px!r}")
        if self.min_inliers < 4:
            raise InvalidInputError(f"min_inliers must be >= 4; got {self.min_inliers!r}")
        if self.overview_px < 64:
            raise InvalidInputError(f"overview_px must be >= 64; got {self.overview_px!r}")


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints of one image, pixel frame, detector bias removed.

    Attributes
    ----------
    xy : (N, 2) float64
        Positions (x = column, y = row), px, pixel centres at integers.
    size : (N,) float64
        Keypoint diameter, px.
    angle : (N,) float64
        Orientation, radians (OpenCV's convention), NaN when absent.
    response : (N,) float64
    level : (N,) int64
        Pyramid octave/level of the keypoint (0 = full resolution; SIFT -1 = upsampled).
    descriptors : (N, D) uint8 or float32
    """

    xy: NDArray[np.float64]
    size: NDArray[np.float64]
    angle: NDArray[np.float64]
    response: NDArray[np.float64]
    level: NDArray[np.int64]
    descriptors: NDArray

    def __len__(self) -> int:
        return len(self.xy)

    def subset(self, idx: ArrayLike) -> Features:
        i = np.asarray(idx)
        return Features(self.xy[i], self.size[i], self.angle[i], self.response[i], self.level[i],
                        self.descriptors[i])

    def transformed(self, scale: float, origin: tuple[float, float]) -> Features:
        """Positions mapped from a (decimated, offset) window to the full image:
        ``x_full = (x + 0.5) * scale - 0.5 + origin``."""
        xy = (self.xy + 0.5) * scale - 0.5 + np.asarray(origin, dtype=np.float64)
        return Features(xy, self.size * scale, self.angle, self.response, self.level, self.descriptors)

    @staticmethod
    def concat(items: list[Features], dim: int, dtype) -> Features:
        if not items:
            return Features(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, np.int64),
                            np.zeros((0, dim), dtype=dtype))
        return Features(*(np.concatenate([getattr(f, a) for f in items]) for a in
                          ("xy", "size", "angle", "response", "level", "descriptors")))


@dataclass(frozen=True, eq=False)
class Verification:
    """Result of geometric verification.

    Attributes
    ----------
    method : str
    matrix : (3, 3) float64 or None
        H_right_from_left (homography) or F with x_r^T F x_l = 0 (fundamental).
    inliers : (N,) bool
    errors_px : (N,) float64
        Transfer error |H x_l - x_r| (homography) or Sampson distance
        (fundamental), px; NaN for ``none``.
    table : ResidualTable or None
    """

    method: str
    matrix: NDArray[np.float64] | None
    inliers: NDArray[np.bool_]
    errors_px: NDArray[np.float64]
    table: ResidualTable | None

    @property
    def rmse_px(self) -> float:
        e = self.errors_px[self.inliers]
        return rms(e) if e.size and np.isfinite(e).all() else float("nan")


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
        Matches refined by LSM, and dropped because refinement did not converge.
    rmse_px : float
        Verification residual RMSE of the returned matches, px.
    rmse_raw_px : float
        The same for the raw (unrefined) positions of the same matches.
    verification : Verification
        Model and residual table of the returned matches.
    candidates_left, candidates_right, candidate_inlier : arrays
        All candidate matches (up to a cap) and their verification status,
        for plots.
    tiled : bool
    image_shapes : ((H, W), (H, W))
    timings_s : dict
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

    def summary(self) -> dict[str, Any]:
        return {"n_detected_left": self.n_detected[0], "n_detected_right": self.n_detected[1],
                "n_matched": self.n_matched, "n_verified": self.n_verified, "n_output": len(self.matches),
                "n_refined": self.n_refined, "n_refine_failed": self.n_refine_failed,
                "verification": self.verification.method, "rmse_px": self.rmse_px,
                "rmse_raw_px": self.rmse_raw_px, "tiled": self.tiled,
                **{f"time_{k}_s": v for k, v in self.timings_s.items()}}


# --------------------------------------------------------------------------- detection
def _make_detector(name: str, nfeatures: int):
    import cv2

    if name == "sift":
        # OpenCV keeps the 2 * nfeatures strongest before computing descriptors (the costly part);
        # grid_select then spreads the final max_keypoints evenly
        return cv2.SIFT_create(nfeatures=2 * max(1, int(nfeatures)))
    if name == "orb":
        return cv2.ORB_create(nfeatures=max(500, int(nfeatures)))
    if name == "akaze":
        if not akaze_available():
            raise InvalidInputError(
                "detector 'akaze' is not available in this OpenCV build "
                f"(opencv {cv2.__version__}: AKAZE moved to opencv-contrib); use 'sift' or 'orb'")
        return cv2.AKAZE_create()
    raise InvalidInputError(f"unknown detector {name!r}; choose from {DETECTORS}")


def _unbias(name: str, pts: NDArray[np.float64], level: NDArray[np.int64], shape: tuple[int, int],
            det) -> NDArray[np.float64]:
    """Detector positions -> pixel-centre convention (see the module docstring)."""
    if name == "sift":
        return pts - SIFT_OFFSET_PX
    if name == "orb":
        s = float(det.getScaleFactor())
        h, w = shape
        out = pts.copy()
        for lv in np.unique(level):
            if lv == 0:
                continue
            sel = level == lv
            f = s ** int(lv)
            wl, hl = round(w / f), round(h / f)
            out[sel, 0] = (pts[sel, 0] / f + 0.5) * w / wl - 0.5
            out[sel, 1] = (pts[sel, 1] / f + 0.5) * h / hl - 0.5
        return out
    return pts


def _sift_octave(octave: NDArray[np.int64]) -> NDArray[np.int64]:
    o = octave & 255
    return np.where(o >= 128, o - 256, o)


def grid_select(xy: ArrayLike, response: ArrayLike, shape: tuple[int, int], budget: int, *,
                cell_cap: int = 4) -> NDArray[np.int64]:
    """Indices of at most ``budget`` points spread evenly over an image.

    The image is cut into square cells sized so that ``budget / cell_cap``
    cells cover it; points are ranked within their cell by ``response`` and
    taken round by round (every cell's best, then every cell's second, ...),
    strongest first within a round, until ``budget`` points are taken. So no
    cell gets more than ``cell_cap`` points while another cell still has
    untaken ones below that, and the budget is used whenever there are enough
    points.

    Parameters
    ----------
    xy : (N, 2) positions, px
    response : (N,) strength (larger is better)
    shape : (H, W) of the image the positions lie in
    budget, cell_cap : int

    Returns
    -------
    (M,) int64 indices into ``xy``, M <= budget.
    """
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    r = np.asarray(response, dtype=np.float64).reshape(-1)
    n = len(p)
    if n <= budget:
        return np.arange(n)
    h, w = shape
    ncell = max(1.0, budget / max(cell_cap, 1))
    cell = max(4.0, math.sqrt(max(h, 1) * max(w, 1) / ncell))
    ncol = int(math.ceil(max(w, 1) / cell)) + 1
    cx = np.clip(np.floor((p[:, 0] + 0.5) / cell), 0, ncol - 1).astype(np.int64)
    cy = np.maximum(np.floor((p[:, 1] + 0.5) / cell), 0).astype(np.int64)
    key = cy * ncol + cx
    order = np.lexsort((-r, key))
    ks = key[order]
    start = np.r_[0, np.flatnonzero(np.diff(ks)) + 1]
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n) - np.repeat(start, np.diff(np.r_[start, n]))
    keep = np.lexsort((-r, rank))[:budget]
    return np.sort(keep)


def detect(image: ArrayLike, *, valid: ArrayLike | None = None, detector: str = "sift",
           max_keypoints: int = 40000, cell_cap: int = 4,
           percentiles: tuple[float, float] = (0.5, 99.5),
           limits: tuple[float, float] | None = None) -> Features:
    """Detect and describe keypoints in one in-memory image.

    Parameters
    ----------
    image : (H, W) or (H, W, C) array, any dtype
        Converted to 8-bit grey by percentile stretch for detection only.
    valid : (H, W) bool, optional
        False marks nodata; no keypoint is taken within 4 px of it.
    detector : {"sift", "orb", "akaze"}
    max_keypoints : int
        Kept at most, spread evenly (:func:`grid_select`).
    cell_cap : int
    percentiles : (lo, hi)
    limits : (lo, hi), optional
        Fixed stretch limits (tiles of one image share them).

    Returns
    -------
    Features
        Positions in the pixel-centre convention, detector bias removed.

    Raises
    ------
    InvalidInputError
        Unknown detector, bad image shape.
    """
    import cv2

    if detector not in DETECTORS:
        raise InvalidInputError(f"unknown detector {detector!r}; choose from {DETECTORS}")
    a = np.asarray(image)
    if a.ndim not in (2, 3) or a.shape[0] < 8 or a.shape[1] < 8:
        raise InvalidInputError(f"image must be (H, W) or (H, W, C) with H, W >= 8; got shape {a.shape}")
    v = None if valid is None else np.asarray(valid, dtype=bool)
    if v is not None and v.shape != a.shape[:2]:
        raise InvalidInputError(f"`valid` must have shape {a.shape[:2]}; got {v.shape}")
    grey = rio.to_uint8(a, v, percentiles=percentiles, limits=limits)
    mask = None
    if v is not None and not v.all():
        mask = cv2.erode(v.astype(np.uint8) * 255, np.ones((9, 9), np.uint8))
    det = _make_detector(detector, max_keypoints)
    try:
        kps, desc = det.detectAndCompute(grey, mask)
    except cv2.error as err:  # pragma: no cover - OpenCV internal failure
        raise EstimationError(f"{detector} detection failed on image of shape {grey.shape}: {err}") from err
    dim, dtype = (128, np.float32) if detector == "sift" else (61 if detector == "akaze" else 32, np.uint8)
    if not kps or desc is None:
        return Features.concat([], dim, dtype)
    pts = np.array([k.pt for k in kps], dtype=np.float64)
    octave = np.array([k.octave for k in kps], dtype=np.int64)
    level = _sift_octave(octave) if detector == "sift" else octave
    f = Features(_unbias(detector, pts, level, grey.shape, det),
                 np.array([k.size for k in kps], dtype=np.float64),
                 np.deg2rad(np.array([k.angle if k.angle >= 0 else np.nan for k in kps], dtype=np.float64)),
                 np.array([k.response for k in kps], dtype=np.float64), level, desc)
    keep = grid_select(f.xy, f.response, grey.shape, max_keypoints, cell_cap=cell_cap)
    return f.subset(keep) if len(keep) < len(f) else f


# --------------------------------------------------------------------------- matching
class _Pairs(NamedTuple):
    left: NDArray[np.int64]
    right: NDArray[np.int64]
    ratio: NDArray[np.float64]


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
    import cv2

    empty = _Pairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(left) < 2 or len(right) < 2:
        return empty
    if left.descriptors.dtype == np.float32:
        index = dict(algorithm=1, trees=4)
        matcher = cv2.FlannBasedMatcher(index, dict(checks=64))
    else:
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    dl = np.ascontiguousarray(left.descriptors)
    dr = np.ascontiguousarray(right.descriptors)
    knn = matcher.knnMatch(dl, dr, k=2)
    li, ri, rat = [], [], []
    for m in knn:
        if len(m) < 2:
            continue
        a, b = m
        r = a.distance / b.distance if b.distance > 0 else (0.0 if a.distance == 0 else 1.0)
        if r < ratio:
            li.append(a.queryIdx)
            ri.append(a.trainIdx)
            rat.append(r)
    li, ri, rat = np.array(li, np.int64), np.array(ri, np.int64), np.array(rat, np.float64)
    if mutual and li.size:
        back = matcher.knnMatch(dr, dl, k=1)
        best = np.full(len(right), -1, dtype=np.int64)
        for m in back:
            if m:
                best[m[0].queryIdx] = m[0].trainIdx
        ok = best[ri] == li
        li, ri, rat = li[ok], ri[ok], rat[ok]
    # one right point per left point and vice versa (keep the best ratio)
    if li.size:
        order = np.argsort(rat, kind="stable")
        _, first = np.unique(ri[order], return_index=True)
        sel = order[first]
        li, ri, rat = li[sel], ri[sel], rat[sel]
    return _Pairs(li, ri, rat)


# --------------------------------------------------------------------------- verification
def _sampson_vectors(F: NDArray[np.float64], pl: NDArray[np.float64], pr: NDArray[np.float64]
                     ) -> NDArray[np.float64]:
    """First-order (Sampson) corrections (N, 4) to (xl, yl, xr, yr); their norm is the Sampson distance."""
    xl = np.c_[pl, np.ones(len(pl))]
    xr = np.c_[pr, np.ones(len(pr))]
    Fx = xl @ F.T          # F x_l
    Ftx = xr @ F           # F^T x_r
    e = np.sum(xr * Fx, axis=1)
    den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
    k = -e / np.where(den > 0, den, np.nan)
    return k[:, None] * np.c_[Ftx[:, 0], Ftx[:, 1], Fx[:, 0], Fx[:, 1]]


def _apply_h(H: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:]


def verify_matches(left_xy: ArrayLike, right_xy: ArrayLike, *, method: str = "homography",
                   threshold_px: float = 1.5, ids: list[str] | None = None, seed: int = 0,
                   max_iters: int = 10000, confidence: float = 0.9999) -> Verification:
    """Geometric verification with OpenCV USAC (MAGSAC++).

    Parameters
    ----------
    left_xy, right_xy : (N, 2) array_like
        Matched positions, px.
    method : {"homography", "fundamental", "none"}
    threshold_px : float
        USAC threshold, px.
    ids : list of str, optional
        Point ids for the residual table (default "1".."N").

    Returns
    -------
    Verification
        For ``homography`` the residual table holds the transfer error in the
        right image (observed x_r, adjusted H x_l); for ``fundamental`` the
        Sampson correction of (x_l, y_l, x_r, y_r), whose norm is the Sampson
        distance. Non-inliers are flagged as outliers.

    Raises
    ------
    EstimationError
        Fewer than the minimal number of matches, or USAC finds no model.
    """
    import cv2

    from .points import as_pair

    if method not in VERIFY_METHODS:
        raise InvalidInputError(f"unknown verification {method!r}; choose from {VERIFY_METHODS}")
    pl, pr = as_pair(left_xy, right_xy, names=("left_xy", "right_xy"))
    n = len(pl)
    ids = [str(i + 1) for i in range(n)] if ids is None else list(ids)
    if method == "none":
        return Verification("none", None, np.ones(n, dtype=bool), np.full(n, np.nan), None)
    need = 4 if method == "homography" else 8
    if n < need:
        raise EstimationError(f"{method} verification needs at least {need} matches; got {n}")
    cv2.setRNGSeed(int(seed))
    params_thr = float(threshold_px)
    try:
        if method == "homography":
            M, mask = cv2.findHomography(pl, pr, cv2.USAC_MAGSAC, params_thr, maxIters=max_iters,
                                         confidence=confidence)
        else:
            M, mask = cv2.findFundamentalMat(pl, pr, cv2.USAC_MAGSAC, params_thr, confidence, max_iters)
    except cv2.error as err:
        raise EstimationError(f"USAC {method} estimation failed on {n} matches: {err}") from err
    if M is None or mask is None or M.shape != (3, 3):
        raise EstimationError(f"USAC found no {method} consistent with {n} matches")
    M = np.asarray(M, dtype=np.float64)
    if method == "homography":
        pred = _apply_h(M, pl)
        err = np.linalg.norm(pred - pr, axis=1)
        inl = mask.ravel().astype(bool) & (err <= max(2.5 * threshold_px, threshold_px + 1))
        table = ResidualTable(f"match verification ({method})", ids, pr, pred, "px", ("dx", "dy"),
                              outlier=~inl, position_px=pl, n_params=8,
                              extra={"threshold_px": float(threshold_px)})
    else:
        d = _sampson_vectors(M, pl, pr)
        err = np.linalg.norm(d, axis=1)
        err = np.where(np.isfinite(err), err, np.inf)
        inl = mask.ravel().astype(bool) & (err <= max(2.5 * threshold_px, threshold_px + 1))
        obs = np.c_[pl, pr]
        table = ResidualTable(f"match verification ({method})", ids, obs, obs + np.nan_to_num(d), "px",
                              ("dx_left", "dy_left", "dx_right", "dy_right"), outlier=~inl,
                              position_px=pl, n_params=7, extra={"threshold_px": float(threshold_px)})
    return Verification(method, M, inl, err, table)


# --------------------------------------------------------------------------- helpers
def _local_affine(pl: NDArray[np.float64], pr: NDArray[np.float64], ver: Verification | None,
                  k: int = 12) -> NDArray[np.float64]:
    """Initial local shape d(right)/d(left) at every match, (N, 2, 2).

    Homography: its Jacobian. Otherwise an affine fit to the k nearest
    matches (identity when fewer than 6 matches).
    """
    n = len(pl)
    if ver is not None and ver.method == "homography" and ver.matrix is not None:
        return _h_jacobian(ver.matrix, pl)
    if n < 6:
        return np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    from scipy.spatial import cKDTree

    kk = min(k, n)
    _, nb = cKDTree(pl).query(pl, k=kk)
    X = pl[nb] - pl[nb].mean(axis=1, keepdims=True)      # (n, k, 2)
    Y = pr[nb] - pr[nb].mean(axis=1, keepdims=True)
    XtX = np.einsum("nki,nkj->nij", X, X) + 1e-9 * np.eye(2)
    XtY = np.einsum("nki,nkj->nij", X, Y)
    B = np.linalg.solve(XtX, XtY)                          # Y ~ X @ B -> A = B^T
    A = np.transpose(B, (0, 2, 1))
    bad = ~np.isfinite(A).all(axis=(1, 2)) | (np.abs(np.linalg.det(A)) < 0.05)
    A[bad] = np.eye(2)
    return A


def _h_jacobian(H: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    q = np.c_[p, np.ones(len(p))] @ H.T
    w = q[:, 2]
    J = np.empty((len(p), 2, 2))
    for i in range(2):
        for j in range(2):
            J[:, i, j] = (H[i, j] * w - q[:, i] * H[2, j]) / (w * w)
    return J


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


def _refine(Lg, Rg, pl, pr, ver: Verification | None, cfg: MatcherConfig, progress=None):
    A = _local_affine(pl, pr, ver)
    return refine_matches(Lg, Rg, pl, pr, affine=A, config=cfg.lsm, progress=progress)


def _final_select(pl, pr, score, shape_left, budget, cap):
    if len(pl) <= budget:
        return np.arange(len(pl))
    # prefer the best scores (lower is better) within each cell
    return grid_select(pl, -score, shape_left, budget, cell_cap=cap)


def _result(pl, pr, score, ver, cfg, n_det, n_matched, n_verified, n_ref, n_fail, raw_pr, cand_l, cand_r,
            cand_inl, tiled, shapes, timings) -> MatchResult:
    ids = tuple(str(i + 1) for i in range(len(pl)))
    rmse = ver.rmse_px
    rmse_raw = float("nan")
    if cfg.verify != "none" and len(pl) >= 8:
        if ver.method == "homography":
            rmse_raw = rms(np.linalg.norm(_apply_h(ver.matrix, pl) - raw_pr, axis=1))
        else:
            rmse_raw = rms(np.linalg.norm(_sampson_vectors(ver.matrix, pl, raw_pr), axis=1))
    return MatchResult(Matches(ids, pl, pr, score), n_det, n_matched, n_verified, n_ref, n_fail, rmse,
                       rmse_raw, ver, cand_l, cand_r, cand_inl, tiled, shapes, timings)


def _finish(pl, pr, ratio, Lg, Rg, cfg: MatcherConfig, ver0: Verification | None, progress=None):
    """Refine (optional), drop failures, re-verify, cap evenly. Returns pieces for _result."""
    raw_pr = pr.copy()
    n_ref = n_fail = 0
    score = ratio.copy()
    if cfg.refine and len(pl):
        lr = _refine(Lg, Rg, pl, pr, ver0, cfg, progress)
        ok = lr.converged
        n_ref, n_fail = int(ok.sum()), int((~ok).sum())
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
    t0 = time.perf_counter()
    tick = progress or (lambda d, t: None)
    tick(0, 4)
    fl = detect(L, valid=lv, detector=cfg.detector, max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap,
                percentiles=cfg.percentiles)
    _check_blank(fl, "left", names[0])
    fr = detect(R, valid=rv, detector=cfg.detector, max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap,
                percentiles=cfg.percentiles)
    _check_blank(fr, "right", names[1])
    t1 = time.perf_counter()
    tick(1, 4)
    pairs = match_descriptors(fl, fr, ratio=cfg.ratio, mutual=cfg.mutual)
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
    cand_l, cand_r, cand_inl = pl, pr, inl
    vl, vr, vratio = pl[inl], pr[inl], ratio[inl]
    pre = int(math.ceil(1.25 * cfg.max_matches))
    if len(vl) > pre:       # refine only what can be returned (plus a reserve for failures)
        keep = grid_select(vl, -vratio, L.shape[:2], pre, cell_cap=cfg.cell_cap)
        vl, vr, vratio = vl[keep], vr[keep], vratio[keep]
    t3 = time.perf_counter()
    tick(3, 4)
    Lg = _grey_float(L, lv) if cfg.refine else None
    Rg = _grey_float(R, rv) if cfg.refine else None
    fl_, fr_, raw_pr, score, n_ref, n_fail = _finish(vl, vr, vratio, Lg, Rg, cfg, ver0)
    out_l, out_r, raw, sc, ver = _reverify_and_cap(fl_, fr_, raw_pr, score, cfg, L.shape[:2])
    t4 = time.perf_counter()
    tick(4, 4)
    timings = {"detect": t1 - t0, "match": t2 - t1, "verify": t3 - t2, "refine": t4 - t3, "total": t4 - t0}
    return _result(out_l, out_r, sc, ver, cfg, (len(fl), len(fr)), len(pairs.left), int(inl.sum()), n_ref,
                   n_fail, raw, cand_l, cand_r, cand_inl, False, (L.shape[:2], R.shape[:2]), timings)


def _reverify_and_cap(pl, pr, raw_pr, score, cfg: MatcherConfig, shape_left):
    if cfg.verify == "none":
        keep = _final_select(pl, pr, score, shape_left, cfg.max_matches, cfg.cell_cap)
        pl, pr, raw_pr, score = pl[keep], pr[keep], raw_pr[keep], score[keep]
        return pl, pr, raw_pr, score, verify_matches(pl, pr, method="none")
    ver = _verify_checked(pl, pr, cfg, cfg.verify)
    m = ver.inliers
    pl, pr, raw_pr, score = pl[m], pr[m], raw_pr[m], score[m]
    keep = _final_select(pl, pr, score, shape_left, cfg.max_matches, cfg.cell_cap)
    pl, pr, raw_pr, score = pl[keep], pr[keep], raw_pr[keep], score[keep]
    # the residual table of exactly the returned matches, with the same model
    ver = _table_for(ver, pl, pr, cfg)
    return pl, pr, raw_pr, score, ver


def _table_for(ver: Verification, pl, pr, cfg: MatcherConfig) -> Verification:
    ids = [str(i + 1) for i in range(len(pl))]
    M = ver.matrix
    if ver.method == "homography":
        pred = _apply_h(M, pl)
        err = np.linalg.norm(pred - pr, axis=1)
        table = ResidualTable("match verification (homography)", ids, pr, pred, "px", ("dx", "dy"),
                              position_px=pl, n_params=8, extra={"threshold_px": cfg.threshold_px})
    else:
        d = _sampson_vectors(M, pl, pr)
        err = np.linalg.norm(d, axis=1)
        obs = np.c_[pl, pr]
        table = ResidualTable("match verification (fundamental)", ids, obs, obs + d, "px",
                              ("dx_left", "dy_left", "dx_right", "dy_right"), position_px=pl, n_params=7,
                              extra={"threshold_px": cfg.threshold_px})
    return Verification(ver.method, M, np.ones(len(pl), bool), err, table)


# --------------------------------------------------------------------------- files
def match_images(left_path: str | Path, right_path: str | Path, *, config: MatcherConfig | None = None,
                 progress: ProgressFn | None = None) -> MatchResult:
    """Match two raster files (any format rasterio reads; any band count and dtype).

    Images whose sides are all <= ``config.tiled_above_px`` are read whole;
    larger ones are matched coarse-to-fine by tiles with bounded memory (see
    the module docstring for the bound).

    Parameters
    ----------
    left_path, right_path : path
    config : MatcherConfig, optional
    progress : callable(done, total), optional

    Returns
    -------
    MatchResult

    Raises
    ------
    RasterIOError
        Unreadable file.
    EstimationError
        Blank images, or images that do not overlap.
    """
    cfg = config or MatcherConfig()
    il = rio.raster_info(left_path)
    ir = rio.raster_info(right_path)
    big = max(il.width, il.height, ir.width, ir.height) > cfg.tiled_above_px
    if not big:
        L, lv = rio.read_window(left_path, 0, 0, il.width, il.height)
        R, rv = rio.read_window(right_path, 0, 0, ir.width, ir.height)
        return _match_whole(L, lv, R, rv, cfg, progress, (str(left_path), str(right_path)))
    return _match_tiled(left_path, right_path, il, ir, cfg, progress)


def _overview(path, info, cfg: MatcherConfig):
    data, valid, _ = rio.read_overview_average(path, cfg.overview_px)
    scale = (info.width / data.shape[1], info.height / data.shape[0])
    g = data.astype(np.float32).mean(axis=2) if data.ndim == 3 else data.astype(np.float32)
    ok = valid & np.isfinite(g)
    if ok.any():
        sample = g[ok]
        lo, hi = np.percentile(sample, cfg.percentiles)
    else:
        lo, hi = 0.0, 1.0
    return g, valid, scale, (float(lo), float(hi))


def _scale_mat(s: tuple[float, float]) -> NDArray[np.float64]:
    """Full-resolution pixel -> overview pixel, u = (x + 0.5) / sx - 0.5 (rows alike)."""
    sx, sy = s
    return np.array([[1 / sx, 0, 0.5 / sx - 0.5], [0, 1 / sy, 0.5 / sy - 0.5], [0, 0, 1]])


def _coarse(left_path, right_path, il, ir, cfg: MatcherConfig):
    gl, vl, sl, lim_l = _overview(left_path, il, cfg)
    gr, vr, sr, lim_r = _overview(right_path, ir, cfg)
    kw = dict(detector="sift", max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap, percentiles=cfg.percentiles)
    fl = detect(gl, valid=vl, **kw)
    _check_blank(fl, "left", left_path)
    fr = detect(gr, valid=vr, **kw)
    _check_blank(fr, "right", right_path)
    pairs = match_descriptors(fl, fr, ratio=cfg.ratio, mutual=True)
    pl, pr = fl.xy[pairs.left], fr.xy[pairs.right]
    ver = _verify_checked(pl, pr, replace(cfg, threshold_px=max(cfg.threshold_px, 2.0)), "homography")
    H = np.linalg.inv(_scale_mat(sr)) @ ver.matrix @ _scale_mat(sl)
    H /= H[2, 2]
    err_full = ver.rmse_px * max(sr)
    logger.info("coarse match: %d of %d verified, RMSE %.2f overview px (scales %.2f, %.2f)",
                int(ver.inliers.sum()), len(pl), ver.rmse_px, sl[0], sr[0])
    return H, err_full, lim_l, lim_r, vl, sl


def _match_tiled(left_path, right_path, il, ir, cfg: MatcherConfig, progress) -> MatchResult:
    t0 = time.perf_counter()
    H, err_full, lim_l, lim_r, ov_valid_l, sl = _coarse(left_path, right_path, il, ir, cfg)
    t1 = time.perf_counter()
    margin = cfg.search_margin_px + 4.0 * err_full
    gate = margin
    n_all = math.ceil(il.width / cfg.tile_px) * math.ceil(il.height / cfg.tile_px)
    sparse = n_all > cfg.max_tiles
    if sparse:
        # search a sparse, even sub-grid of smaller tiles (3x as many, half the side: less area,
        # denser coverage); right windows are detected directly (little reuse between sparse tiles)
        cfg = replace(cfg, tile_px=max(128, cfg.tile_px // 2), max_tiles=3 * cfg.max_tiles)
    tiles = _pick_tiles(il, cfg)
    n_tiles = len(tiles)
    quota = max(50, int(math.ceil(2.0 * cfg.max_matches / max(n_tiles, 1))))
    per_tile_kp = max(1500, min(cfg.max_keypoints, 4 * quota, int(4 * cfg.max_candidates / max(n_tiles, 1))))
    store_l: list[NDArray] = []
    store_r: list[NDArray] = []
    store_raw: list[NDArray] = []
    store_s: list[NDArray] = []
    n_stored = 0
    n_det_l = n_det_r = n_matched = n_ref = n_fail = 0
    kw = dict(detector=cfg.detector, cell_cap=cfg.cell_cap, percentiles=cfg.percentiles)
    right = _RightTiles(right_path, ir, cfg, per_tile_kp, lim_r)
    for k, (c0, r0, w, h) in enumerate(tiles):
        if progress is not None:
            progress(k, n_tiles)
        core = _core(c0, r0, w, h, il, cfg)
        if not _tile_has_data(ov_valid_l, sl, c0, r0, w, h):
            continue
        corners = np.array([[c0, r0], [c0 + w - 1, r0], [c0, r0 + h - 1], [c0 + w - 1, r0 + h - 1]], float)
        pc = _apply_h(H, corners)
        if not np.isfinite(pc).all():
            continue
        x0, y0 = np.floor(pc.min(axis=0) - margin).astype(int)
        x1, y1 = np.ceil(pc.max(axis=0) + margin).astype(int)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, ir.width - 1), min(y1, ir.height - 1)
        if x1 - x0 < 32 or y1 - y0 < 32:
            continue
        if sparse:
            Rd, Rv = rio.read_window(right_path, x0, y0, x1 - x0 + 1, y1 - y0 + 1)
            if Rv.mean() < 0.02:
                continue
            fr = detect(Rd, valid=Rv, max_keypoints=3 * per_tile_kp, limits=lim_r,
                        **kw).transformed(1.0, (x0, y0))
            right.n_detected += len(fr)
        else:
            fr = right.features(x0, y0, x1, y1)
        if len(fr) < 4:
            continue
        Ld, Lv = rio.read_window(left_path, c0, r0, w, h)
        if Lv.mean() < 0.02:
            continue
        fl = detect(Ld, valid=Lv, max_keypoints=per_tile_kp, limits=lim_l, **kw)
        n_det_l += len(fl)
        if len(fl) < 4:
            continue
        pairs = match_descriptors(fl, fr, ratio=cfg.ratio, mutual=cfg.mutual)
        pl = fl.xy[pairs.left] + [c0, r0]
        pr = fr.xy[pairs.right]
        ratio = pairs.ratio
        inside = (pl[:, 0] >= core[0]) & (pl[:, 0] < core[2]) & (pl[:, 1] >= core[1]) & (pl[:, 1] < core[3])
        ok = inside & (np.linalg.norm(_apply_h(H, pl) - pr, axis=1) < gate)
        pl, pr, ratio = pl[ok], pr[ok], ratio[ok]
        n_matched += len(pl)
        if not len(pl):
            continue
        if len(pl) > quota:     # keep what the output can use, evenly over the tile core
            keep = grid_select(pl - [c0, r0], -ratio, (h, w), quota, cell_cap=cfg.cell_cap)
            pl, pr, ratio = pl[keep], pr[keep], ratio[keep]
        raw = pr.copy()
        score = ratio
        if cfg.refine:
            m = int(cfg.lsm.radius_px) + 4
            bx0, by0 = np.floor(pr.min(axis=0)).astype(int) - m
            bx1, by1 = np.ceil(pr.max(axis=0)).astype(int) + m
            Rd, Rv = rio.read_window(right_path, bx0, by0, bx1 - bx0 + 1, by1 - by0 + 1)
            Lg = _grey_float(Ld, Lv)
            Rg = _grey_float(Rd, Rv)
            A = _h_jacobian(H, pl)
            lr = refine_matches(Lg, Rg, pl - [c0, r0], pr - [bx0, by0], affine=A, config=cfg.lsm)
            okr = lr.converged
            n_ref += int(okr.sum())
            n_fail += int((~okr).sum())
            pl, raw = pl[okr], raw[okr]
            pr = lr.right[okr] + [bx0, by0]
            score = lr.std_px[okr]
        store_l.append(pl)
        store_r.append(pr)
        store_raw.append(raw)
        store_s.append(score)
        n_stored += len(pl)
        if n_stored > 2 * cfg.max_candidates:
            store_l, store_r, store_raw, store_s = _thin(store_l, store_r, store_raw, store_s, il, cfg)
            n_stored = len(store_l[0])
    if progress is not None:
        progress(n_tiles, n_tiles)
    n_det_r = right.n_detected
    t2 = time.perf_counter()
    if n_stored > cfg.max_candidates:
        store_l, store_r, store_raw, store_s = _thin(store_l, store_r, store_raw, store_s, il, cfg)
    pl = np.concatenate(store_l) if store_l else np.zeros((0, 2))
    pr = np.concatenate(store_r) if store_r else np.zeros((0, 2))
    raw = np.concatenate(store_raw) if store_raw else np.zeros((0, 2))
    sc = np.concatenate(store_s) if store_s else np.zeros(0)
    if cfg.verify == "none":
        if len(pl) < cfg.min_inliers:
            raise _no_overlap(len(pl), len(pl), cfg)
        inl = np.ones(len(pl), bool)
    else:
        ver0 = _verify_checked(pl, pr, cfg, cfg.verify)
        inl = ver0.inliers
    cand = _cap_candidates(pl, pr, inl, 200000)
    n_verified = int(inl.sum())
    out_l, out_r, out_raw, out_s, ver = _reverify_and_cap(pl[inl], pr[inl], raw[inl], sc[inl], cfg,
                                                          (il.height, il.width))
    t3 = time.perf_counter()
    timings = {"coarse": t1 - t0, "tiles": t2 - t1, "verify": t3 - t2, "total": t3 - t0}
    return _result(out_l, out_r, out_s, ver, cfg, (n_det_l, n_det_r), n_matched, n_verified, n_ref, n_fail,
                   out_raw, *cand, True, ((il.height, il.width), (ir.height, ir.width)), timings)


class _RightTiles:
    """Right-image features by tiles, each tile detected once (keypoints of its core only) and kept in
    a least-recently-used cache bounded to ``cache_mb`` of descriptors."""

    def __init__(self, path, info, cfg: MatcherConfig, per_tile_kp: int, limits, cache_mb: float = 256.0):
        self.path, self.info, self.cfg = path, info, cfg
        self.kp = per_tile_kp
        self.limits = limits
        self.tiles = list(rio.iter_windows(info.width, info.height, cfg.tile_px, cfg.overlap_px))
        self.nx = math.ceil(info.width / cfg.tile_px)
        self.cache: dict[int, Features] = {}
        self.bytes = 0
        self.max_bytes = cache_mb * 2 ** 20
        self.n_detected = 0

    def _tile(self, idx: int) -> Features:
        f = self.cache.pop(idx, None)
        if f is None:
            c0, r0, w, h = self.tiles[idx]
            data, valid = rio.read_window(self.path, c0, r0, w, h)
            cfg = self.cfg
            if valid.mean() < 0.02:
                f = Features.concat([], 128 if cfg.detector == "sift" else 32,
                                    np.float32 if cfg.detector == "sift" else np.uint8)
            else:
                f = detect(data, valid=valid, detector=cfg.detector, max_keypoints=self.kp, cell_cap=cfg.cell_cap,
                           percentiles=cfg.percentiles, limits=self.limits).transformed(1.0, (c0, r0))
                x0, y0, x1, y1 = _core(c0, r0, w, h, self.info, cfg)
                inside = (f.xy[:, 0] >= x0) & (f.xy[:, 0] < x1) & (f.xy[:, 1] >= y0) & (f.xy[:, 1] < y1)
                f = f.subset(np.flatnonzero(inside))
            self.n_detected += len(f)
            self.bytes += f.descriptors.nbytes
            while self.cache and self.bytes > self.max_bytes:
                old = next(iter(self.cache))
                self.bytes -= self.cache.pop(old).descriptors.nbytes
        self.cache[idx] = f           # most recently used last
        return f

    def features(self, x0: int, y0: int, x1: int, y1: int) -> Features:
        """Keypoints inside [x0, x1] x [y0, y1] (full-resolution right pixels)."""
        t = self.cfg.tile_px
        items = []
        for ty in range(max(y0, 0) // t, min(y1, self.info.height - 1) // t + 1):
            for tx in range(max(x0, 0) // t, min(x1, self.info.width - 1) // t + 1):
                f = self._tile(ty * self.nx + tx)
                m = (f.xy[:, 0] >= x0) & (f.xy[:, 0] <= x1) & (f.xy[:, 1] >= y0) & (f.xy[:, 1] <= y1)
                items.append(f.subset(np.flatnonzero(m)))
        return Features.concat(items, 128 if self.cfg.detector == "sift" else 32,
                               np.float32 if self.cfg.detector == "sift" else np.uint8)


def _pick_tiles(info, cfg: MatcherConfig) -> list[tuple[int, int, int, int]]:
    """Tile windows to search: all of them, or an even sub-grid of at most ``max_tiles``."""
    tiles = list(rio.iter_windows(info.width, info.height, cfg.tile_px, cfg.overlap_px))
    if len(tiles) <= cfg.max_tiles:
        return tiles
    nx = math.ceil(info.width / cfg.tile_px)
    ny = math.ceil(info.height / cfg.tile_px)
    k = math.ceil(math.sqrt(len(tiles) / cfg.max_tiles))
    while math.ceil(nx / k) * math.ceil(ny / k) > cfg.max_tiles:
        k += 1
    ox, oy = (nx - 1) % k // 2, (ny - 1) % k // 2
    return [t for i, t in enumerate(tiles) if (i // nx - oy) % k == 0 and (i % nx - ox) % k == 0]


def _core(c0, r0, w, h, info, cfg):
    """Core (no-overlap) rectangle [x0, y0, x1, y1) of a window from :func:`rectify.io.iter_windows`."""
    cx = 0 if c0 == 0 else c0 + cfg.overlap_px
    cy = 0 if r0 == 0 else r0 + cfg.overlap_px
    return cx - 0.5, cy - 0.5, min(cx + cfg.tile_px, info.width) - 0.5, min(cy + cfg.tile_px, info.height) - 0.5


def _tile_has_data(ov_valid, s, c0, r0, w, h) -> bool:
    a0, b0 = int(c0 / s[0]), int(r0 / s[1])
    a1, b1 = int(math.ceil((c0 + w) / s[0])), int(math.ceil((r0 + h) / s[1]))
    sub = ov_valid[b0:max(b1, b0 + 1), a0:max(a1, a0 + 1)]
    return bool(sub.size and sub.any())


def _thin(sl, sr, sraw, ss, info, cfg: MatcherConfig):
    pl, pr, raw, sc = (np.concatenate(x) for x in (sl, sr, sraw, ss))
    keep = grid_select(pl, -sc, (info.height, info.width), cfg.max_candidates, cell_cap=max(cfg.cell_cap, 8))
    return [pl[keep]], [pr[keep]], [raw[keep]], [sc[keep]]


def _cap_candidates(pl, pr, inl, cap):
    if len(pl) <= cap:
        return pl, pr, inl
    idx = np.random.default_rng(0).choice(len(pl), cap, replace=False)
    return pl[idx], pr[idx], inl[idx]


# --------------------------------------------------------------------------- report figures
def match_figures(result: MatchResult, left_preview: tuple[NDArray, float] | None = None,
                  right_preview: tuple[NDArray, float] | None = None) -> dict[str, Any]:
    """Figures for the report: inliers/outliers side by side, and match density.

    Parameters
    ----------
    result : MatchResult
    left_preview, right_preview : (image (h, w[, C]), scale), optional
        Downsampled images and their scale (full-resolution px per preview px),
        e.g. from :func:`rectify.io.read_overview`.

    Returns
    -------
    dict name -> matplotlib Figure (``"matches"``, ``"density"``)
    """
    from matplotlib.figure import Figure

    (hl, wl), _ = result.image_shapes
    fig = Figure(figsize=(11, 6), layout="constrained")
    axes = fig.subplots(1, 2)
    pts = [result.candidates_left, result.candidates_right]
    inl = result.candidate_inlier
    for ax, prev, (h, w), p, name in zip(axes, (left_preview, right_preview), result.image_shapes, pts,
                                         ("left", "right")):
        if prev is not None:
            img, _scale = prev
            a = np.asarray(img, dtype=np.float64)
            a = a.mean(axis=2) if a.ndim == 3 else a
            ax.imshow(a, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
        sub = np.random.default_rng(0).permutation(len(p))[:20000]
        ax.scatter(p[sub][~inl[sub], 0], p[sub][~inl[sub], 1], s=2, c="tab:red", label="rejected")
        ax.scatter(p[sub][inl[sub], 0], p[sub][inl[sub], 1], s=2, c="tab:green", label="verified")
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_title(f"{name} image ({w} x {h} px)")
        ax.set_aspect("equal")
    axes[0].legend(loc="upper right", markerscale=4)
    fig.suptitle(f"{int(inl.sum())} verified / {len(inl)} candidate matches ({result.verification.method})")
    dens = Figure(figsize=(6, 6), layout="constrained")
    ax = dens.subplots()
    pl = result.matches.left
    nb = 32
    cell = max(hl, wl) / nb
    hist, _, _ = np.histogram2d(pl[:, 1], pl[:, 0], bins=(max(1, int(np.ceil(hl / cell))),
                                                         max(1, int(np.ceil(wl / cell)))),
                                range=((-0.5, hl - 0.5), (-0.5, wl - 0.5)))
    im = ax.imshow(hist, extent=(-0.5, wl - 0.5, hl - 0.5, -0.5), cmap="viridis", interpolation="nearest")
    dens.colorbar(im, ax=ax, label=f"matches per {cell:.0f} x {cell:.0f} px cell")
    ax.set_title(f"match density, left image ({len(pl)} matches)")
    return {"matches": fig, "density": dens}
