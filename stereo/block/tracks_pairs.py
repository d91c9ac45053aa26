"""Which image pairs of a block to match.

Strategies (:func:`select_pairs`)
---------------------------------
``footprints``
    Poses and cameras known: each image's footprint is its four corner rays intersected with the
    plane z = ``ground_z`` (the mean terrain height), a convex quadrilateral in the ground frame.
    A pair is kept when the area of the intersection of the two footprints is at least
    ``min_overlap`` of the smaller footprint. A corner ray that does not reach the plane (an oblique
    image looking over the horizon) is cut at 20 flying heights. Bounding boxes are tested first,
    so large blocks cost about one polygon intersection per neighbour.
``all``
    Every pair: for small blocks (<= ``max_all_pairs`` images) matching them all is cheap and
    misses nothing.
``overview``
    Images only: every image is read as a small overview (longer side ``overview_px``, area
    averaged, bounded memory), a few SIFT features are detected, every pair is matched and
    verified with a homography, and each image is linked to its ``neighbours`` best partners (by
    verified matches; a link needs ``overview_min_matches``). Costs n (n - 1) / 2 small matches.
``auto``
    ``footprints`` when poses, cameras and ``ground_z`` are all given, else ``all`` up to
    ``max_all_pairs`` images, else ``overview``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.features.detect import Features, detect
from rectify.features.match import match_descriptors, verify_matches
from rectify.geometry.camera import Camera
from rectify.raster import io as rio
from stereo.block.types import Pose

logger = logging.getLogger(__name__)

__all__ = ["PAIR_STRATEGIES", "ImagePair", "footprints", "select_pairs"]

PAIR_STRATEGIES = ("auto", "footprints", "all", "overview")

#: a corner ray that misses the ground plane is cut at this many flying heights
_FAR_HEIGHTS = 20.0


@dataclass(frozen=True)
class ImagePair:
    """One pair of a block chosen for matching.

    Attributes
    ----------
    i, j : int
        Image indices, i < j.
    reason : {"footprints", "all", "overview"}
        The strategy that chose it.
    overlap : float
        Predicted overlap: the footprint intersection over the smaller footprint (``footprints``);
        NaN when not predicted.
    overview_matches : int
        Verified matches of the overview match (``overview``), else 0.
    """

    i: int
    j: int
    reason: str
    overlap: float = float("nan")
    overview_matches: int = 0


def _camera_of(cameras: Camera | Mapping[str, Camera], pose: Pose) -> Camera:
    if isinstance(cameras, Camera):
        return cameras
    for key in (pose.camera, pose.image):
        if key in cameras:
            return cameras[key]
    raise InvalidInputError(f"image {pose.image!r} names camera {pose.camera!r}, which is not given "
                            f"(cameras: {sorted(cameras)})")


def footprints(poses: Sequence[Pose], cameras: Camera | Mapping[str, Camera], ground_z: float
               ) -> list[NDArray[np.float64]]:
    """Ground footprint of each image on the plane z = ``ground_z``.

    Parameters
    ----------
    poses : sequence of Pose
    cameras : Camera or mapping camera id -> Camera
        One camera for all images, or cameras looked up by each pose's camera id (then by its
        image name).
    ground_z : float
        Mean terrain height, ground frame, m.

    Returns
    -------
    list of (4, 2) float64
        Ground (x, y) of the image corners (pixel edges (-0.5, -0.5) ... (W - 0.5, H - 0.5)), in
        the order top-left, top-right, bottom-right, bottom-left.
    """
    if not math.isfinite(ground_z):
        raise InvalidInputError(f"ground_z must be a finite height; got {ground_z!r}")
    out = []
    for pose in poses:
        cam = _camera_of(cameras, pose)
        w, h = cam.width - 0.5, cam.height - 0.5
        corners = np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]])
        d = cam.rays_from_pixel(corners) @ pose.rotation.T
        C = pose.position
        height = abs(C[2] - ground_z)
        if height <= 0:
            raise InvalidInputError(f"image {pose.image!r}: projection centre lies on the ground plane "
                                    f"z = {ground_z}; footprints need a height above it")
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ground_z - C[2]) / d[:, 2]
        far = _FAR_HEIGHTS * height / np.maximum(np.linalg.norm(d[:, :2], axis=1), 1e-12)
        t = np.where(np.isfinite(t) & (t > 0), np.minimum(t, far), far)
        out.append(C[:2] + t[:, None] * d[:, :2])
    return out


def _footprint_pairs(polys: list[NDArray[np.float64]], min_overlap: float) -> list[ImagePair]:
    n = len(polys)
    if n < 2:
        return []
    origin = np.mean([p.mean(axis=0) for p in polys], axis=0)
    local = [np.ascontiguousarray(p - origin, dtype=np.float32) for p in polys]
    hulls = [cv2.convexHull(p) for p in local]
    area = np.array([cv2.contourArea(h) for h in hulls])
    lo = np.array([p.min(axis=0) for p in local])
    hi = np.array([p.max(axis=0) for p in local])
    out = []
    for i in range(n - 1):
        cand = np.flatnonzero(np.all(lo[i + 1:] <= hi[i], axis=1) & np.all(hi[i + 1:] >= lo[i], axis=1)) + i + 1
        for j in cand:
            inter, _ = cv2.intersectConvexConvex(hulls[i], hulls[j])
            denom = min(area[i], area[j])
            frac = float(inter) / float(denom) if denom > 0 else 0.0
            if frac >= min_overlap:
                out.append(ImagePair(i, int(j), "footprints", frac))
    return out


def _overview_features(path: str | Path, overview_px: int, n_features: int) -> Features:
    data, valid, _ = rio.read_overview_average(path, overview_px)
    grey = data.astype(np.float32).mean(axis=2)
    return detect(grey, valid=valid, detector="sift", max_keypoints=n_features)


def _overview_pairs(images: Sequence[str | Path], *, neighbours: int, overview_px: int, n_features: int,
                    min_matches: int, progress: Callable[[int, int], None] | None) -> list[ImagePair]:
    n = len(images)
    total = n + n * (n - 1) // 2
    feats = []
    for k, p in enumerate(images):
        feats.append(_overview_features(p, overview_px, n_features))
        if progress is not None:
            progress(k + 1, total)
    counts = np.zeros((n, n), dtype=np.int64)
    done = n
    for i in range(n - 1):
        for j in range(i + 1, n):
            pm = match_descriptors(feats[i], feats[j], ratio=0.8, mutual=True)
            if len(pm.left) >= max(min_matches, 8):
                try:
                    ver = verify_matches(feats[i].xy[pm.left], feats[j].xy[pm.right], method="homography",
                                         threshold_px=3.0)
                    counts[i, j] = counts[j, i] = int(ver.inliers.sum())
                except EstimationError:
                    pass
            done += 1
            if progress is not None:
                progress(done, total)
    chosen: dict[tuple[int, int], int] = {}
    for i in range(n):
        order = np.argsort(-counts[i], kind="stable")
        for j in order[:neighbours]:
            if j != i and counts[i, j] >= min_matches:
                chosen[(min(i, int(j)), max(i, int(j)))] = int(counts[i, j])
    return [ImagePair(i, j, "overview", float("nan"), c) for (i, j), c in sorted(chosen.items())]


def select_pairs(n_or_names: int | Sequence[str], *, cameras: Camera | Mapping[str, Camera] | None = None,
                 poses: Sequence[Pose] | None = None, ground_z: float | None = None,
                 images: Sequence[str | Path] | None = None, strategy: str = "auto", min_overlap: float = 0.1,
                 max_all_pairs: int = 12, neighbours: int = 6, overview_px: int = 512,
                 overview_features: int = 800, overview_min_matches: int = 12,
                 progress: Callable[[int, int], None] | None = None) -> list[ImagePair]:
    """Choose the image pairs of a block to match (module docstring: the strategies).

    Parameters
    ----------
    n_or_names : int or sequence of str
        The number of images, or their names (block order).
    cameras : Camera or mapping camera id -> Camera, optional
        One camera for all, or looked up by each pose's camera id, then by its image name.
    poses : sequence of Pose, optional
        One per image, in block order (approximate poses, e.g. from GNSS/IMU, are enough).
    ground_z : float, optional
        Mean terrain height, ground frame, m.
    images : sequence of path, optional
        Image files, one per image (the ``overview`` strategy reads them).
    strategy : {"auto", "footprints", "all", "overview"}
    min_overlap : float
        Footprint overlap kept at least, as a fraction of the smaller footprint, in (0, 1].
    max_all_pairs : int
        ``auto`` matches all pairs up to this many images.
    neighbours : int
        ``overview``: partners kept per image.
    overview_px, overview_features, overview_min_matches : int
        ``overview``: longer side of the overviews (px), SIFT features per overview, verified
        matches needed for a link.
    progress : callable(done, total), optional
        ``overview`` reports images read and pairs matched.

    Returns
    -------
    list of ImagePair
        Sorted by (i, j).

    Raises
    ------
    InvalidInputError
        Unknown strategy, fewer than 2 images, inputs that do not fit the strategy.
    """
    if strategy not in PAIR_STRATEGIES:
        raise InvalidInputError(f"unknown pair strategy {strategy!r}; choose from {PAIR_STRATEGIES}")
    n = int(n_or_names) if isinstance(n_or_names, (int, np.integer)) else len(n_or_names)
    if n < 2:
        raise InvalidInputError(f"a block needs at least 2 images; got {n}")
    if not (0 < min_overlap <= 1):
        raise InvalidInputError(f"min_overlap must be in (0, 1]; got {min_overlap!r}")
    if neighbours < 1 or max_all_pairs < 2:
        raise InvalidInputError(f"neighbours must be >= 1 and max_all_pairs >= 2; got {neighbours} and "
                                f"{max_all_pairs}")
    if poses is not None and len(poses) != n:
        raise InvalidInputError(f"{len(poses)} poses for {n} images")
    if images is not None and len(images) != n:
        raise InvalidInputError(f"{len(images)} image paths for {n} images")
    if strategy == "auto":
        if poses is not None and cameras is not None and ground_z is not None:
            strategy = "footprints"
        elif n <= max_all_pairs or images is None:
            strategy = "all"
        else:
            strategy = "overview"
    if strategy == "footprints":
        if poses is None or cameras is None or ground_z is None:
            missing = [k for k, v in (("poses", poses), ("cameras", cameras), ("ground_z", ground_z)) if v is None]
            raise InvalidInputError(f"footprint pair selection needs poses, cameras and ground_z; missing {missing}")
        out = _footprint_pairs(footprints(poses, cameras, float(ground_z)), float(min_overlap))
    elif strategy == "all":
        out = [ImagePair(i, j, "all") for i in range(n - 1) for j in range(i + 1, n)]
    else:
        if images is None:
            raise InvalidInputError("overview pair selection needs the image paths (`images`)")
        out = _overview_pairs(images, neighbours=int(neighbours), overview_px=int(overview_px),
                              n_features=int(overview_features), min_matches=int(overview_min_matches),
                              progress=progress)
    logger.info("pair selection (%s): %d of %d pairs", strategy, len(out), n * (n - 1) // 2)
    return out
