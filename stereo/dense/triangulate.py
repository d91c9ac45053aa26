"""Disparity -> 3D through the original cameras, with the project's own intersection.

A disparity ``d`` at rectified left pixel (col, row) pairs the rectified right pixel (col - d, row).
Both are mapped back to *ideal photo coordinates of the original photos*
(:meth:`EpipolarRectification.photo_from_rectified`) and intersected by
:func:`stereo.pair.intersection.intersect` with the original rotations and base (not a Q matrix).
Corresponding rectified pixels lie on one row, so the two rays meet exactly and the default
``midpoint`` method equals the photo-metric ``least-squares`` one; ``least-squares`` may be asked for.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError
from stereo.dense.epipolar import EpipolarRectification
from stereo.pair.intersection import METHODS, intersect

logger = logging.getLogger(__name__)

__all__ = ["DensePoints", "triangulate_disparity"]


@dataclass(frozen=True, eq=False)
class DensePoints:
    """Points of a disparity window.

    Attributes
    ----------
    xyz : (N, 3) float64
        Orientation frame (model or ground), or the ground frame after ``transform``.
    pixel : (N, 2) float64
        Rectified left pixel (col, row) of each point.
    miss_distance : (N,) float64
        Miss distance of the rays, orientation units (about 0 by construction).
    """

    xyz: NDArray[np.float64]
    pixel: NDArray[np.float64]
    miss_distance: NDArray[np.float64]

    def __post_init__(self) -> None:
        for a in (self.xyz, self.pixel, self.miss_distance):
            a.flags.writeable = False

    def __len__(self) -> int:
        return len(self.xyz)


def triangulate_disparity(
    rect: EpipolarRectification,
    disparity: ArrayLike,
    *,
    col_off: int = 0,
    row_off: int = 0,
    mask: ArrayLike | None = None,
    method: str = "midpoint",
    transform: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
) -> DensePoints:
    """Intersect every valid disparity of a window of the left rectified photo.

    Parameters
    ----------
    rect : EpipolarRectification
    disparity : (h, w) array_like
        ``col_left - col_right``; NaN (or ``mask`` False) where none.
    col_off, row_off : int
        Position of the window in the left rectified photo.
    mask : (h, w) bool, optional
        Pixels to use (besides finite disparity).
    method : str
        Intersection method (:data:`stereo.pair.intersection.METHODS`).
    transform : callable, optional
        Applied to the (N, 3) points (e.g. an absolute orientation to the ground).

    Raises
    ------
    ShapeError, InvalidInputError
        Bad disparity shape, mask or method.
    StereoError
        From the intersection (parallel rays).
    """
    if not isinstance(rect, EpipolarRectification):
        raise InvalidInputError(f"`rect` must be an EpipolarRectification; got {type(rect).__name__}")
    if method not in METHODS:
        raise InvalidInputError(f"unknown intersection method {method!r}; expected one of {list(METHODS)}")
    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2:
        raise ShapeError(f"`disparity` must be a 2-D array; got shape {d.shape}", actual_shape=d.shape)
    ok = np.isfinite(d)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != d.shape:
            raise ShapeError(f"`mask` must have the disparity's shape {d.shape}; got {m.shape}",
                             actual_shape=m.shape, expected_shape=d.shape)
        ok &= m.astype(bool)
    rows, cols = np.nonzero(ok)
    if len(rows) == 0:
        e = np.zeros((0, 3))
        return DensePoints(e, np.zeros((0, 2)), np.zeros(0))
    c = cols.astype(np.float64) + col_off
    r = rows.astype(np.float64) + row_off
    dd = d[rows, cols]
    pl = np.column_stack([c, r])
    pr = np.column_stack([c - dd, r])
    ml = rect.photo_from_rectified("left", pl)
    mr = rect.photo_from_rectified("right", pr)
    good = np.isfinite(ml).all(axis=1) & np.isfinite(mr).all(axis=1)
    # rays must meet in front of both cameras: positive disparity in the normal case means convergence
    good &= (dd + rect.disparity_offset) > 1e-6
    ml, mr, pl = ml[good], mr[good], pl[good]
    if len(pl) == 0:
        e = np.zeros((0, 3))
        return DensePoints(e, np.zeros((0, 2)), np.zeros(0))
    inter = intersect(ml, mr, rotation_left=rect.left.rotation, rotation_right=rect.right.rotation, base=rect.base,
                      focal_length_mm=(rect.left.camera.focal_length_mm, rect.right.camera.focal_length_mm),
                      centre_left=rect.centre_left, method=method)
    xyz = np.array(inter.points)
    front = (inter.scale_left > 0) & (inter.scale_right > 0)
    xyz, pl, miss = xyz[front], pl[front], np.array(inter.miss_distance)[front]
    if transform is not None:
        xyz = np.asarray(transform(xyz), dtype=np.float64).reshape(-1, 3)
    return DensePoints(xyz, pl, miss)
