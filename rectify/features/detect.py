"""Keypoint detection (SIFT, ORB, AKAZE) with bias-free positions, spread evenly over the image.

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
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.raster import io as rio

__all__ = ["DETECTORS", "SIFT_OFFSET_PX", "Detector", "Features", "akaze_available", "detect", "grid_select"]


class Detector(str, enum.Enum):
    SIFT = "sift"
    ORB = "orb"
    AKAZE = "akaze"


DETECTORS = tuple(d.value for d in Detector)

SIFT_OFFSET_PX = 0.25
"""OpenCV SIFT positions exceed the pixel-centre convention by this, in x and y."""


def akaze_available() -> bool:
    """True when the installed OpenCV build provides AKAZE."""
    return hasattr(cv2, "AKAZE_create")


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


# --------------------------------------------------------------------------- detection
def _make_detector(name: str, nfeatures: int):
    if name == "sift":
        # OpenCV keeps the 2 * nfeatures strongest before computing descriptors (the costly part);
        # grid_select then spreads the final max_keypoints evenly
        return cv2.SIFT.create(nfeatures=2 * max(1, int(nfeatures)))
    if name == "orb":
        return cv2.ORB.create(nfeatures=max(500, int(nfeatures)))
    if name == "akaze":
        if not akaze_available():
            raise InvalidInputError(
                "detector 'akaze' is not available in this OpenCV build "
                f"(opencv {cv2.__version__}: AKAZE moved to opencv-contrib); use 'sift' or 'orb'")
        return cv2.AKAZE_create()  # type: ignore[attr-defined]  # absent from OpenCV 5's main modules and stubs
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
