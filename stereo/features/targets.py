"""Calibration targets: chessboards (:class:`Chessboard`) and their detection in images.

Detection gives one :class:`stereo.calibration.views.TargetView` per image where the board is found;
the observation and field CSV files are read by :mod:`stereo.formats.calibration`.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, RasterIOError
from stereo.calibration.views import TargetView

logger = logging.getLogger(__name__)

__all__ = ["Chessboard", "detect_chessboard", "detect_chessboards", "parse_pattern", "parse_square"]

F64 = NDArray[np.float64]


# -------------------------------------------------------------------- chessboards
@dataclass(frozen=True)
class Chessboard:
    """A chessboard target: ``cols`` x ``rows`` inner corners, ``square`` object units apart.

    Corners are numbered row by row as OpenCV returns them; the object frame has
    x along a row of corners, y across, z = 0 on the board.
    """

    cols: int
    rows: int
    square: float = 1.0

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            raise InvalidInputError(f"a chessboard needs at least 2 x 2 inner corners; got {self.cols}x{self.rows}")
        if not (math.isfinite(self.square) and self.square > 0):
            raise InvalidInputError(f"chessboard square size must be > 0; got {self.square!r}")

    @property
    def object_xyz(self) -> F64:
        """Corner coordinates (cols * rows, 3), object units."""
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        return np.column_stack([i.ravel() * self.square, j.ravel() * self.square, np.zeros(i.size)])

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(f"r{j}c{i}" for j in range(self.rows) for i in range(self.cols))


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6) inner corners."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", text or "")
    if not m:
        raise InvalidInputError(f"chessboard pattern must look like 9x6 (inner corners); got {text!r}")
    return int(m.group(1)), int(m.group(2))


_UNITS = {"": 1.0, "mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


def parse_square(text: str) -> tuple[float, str]:
    """``"25mm"`` -> (25.0, "mm"); a bare number is in object units ("unit")."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*([a-z]*)\s*", str(text or ""))
    if not m or m.group(2) not in _UNITS:
        raise InvalidInputError(f"square size must be a number with an optional unit mm, cm, m or in; got {text!r}")
    v = float(m.group(1))
    if v <= 0:
        raise InvalidInputError(f"square size must be > 0; got {text!r}")
    if m.group(2) == "":
        return v, "unit"
    return v * _UNITS[m.group(2)], "mm"


def detect_chessboard(image: ArrayLike, board: Chessboard, *, refine_window: int = 11) -> F64 | None:
    """Inner corners of a chessboard in one image, (cols * rows, 2) px, or ``None`` when not found.

    OpenCV's ``findChessboardCorners`` followed by ``cornerSubPix`` (sub-pixel
    refinement in a ``refine_window`` x ``refine_window`` window, as in
    OpenCV's calibration sample).
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        lo, hi = float(np.min(img)), float(np.max(img))
        img = np.clip((img - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(img, (board.cols, board.rows), flags=flags)
    if not ok or corners is None:
        return None
    half = max(2, refine_window // 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    corners = cv2.cornerSubPix(img, corners, (half, half), (-1, -1), crit)
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def detect_chessboards(paths: Sequence[str | Path], board: Chessboard, *, refine_window: int = 11
                       ) -> tuple[list[TargetView], list[str], tuple[int, int]]:
    """Detect the board in image files.

    Returns
    -------
    views : list of TargetView
        One per image where the board was found (named by the file name).
    missing : list of str
        File names where it was not found.
    size : (width, height)
        Image size, px (all images must share it).

    Raises
    ------
    RasterIOError
        An image cannot be read.
    InvalidInputError
        Images of different sizes.
    """
    views: list[TargetView] = []
    missing: list[str] = []
    size: tuple[int, int] | None = None
    for p in paths:
        path = Path(p)
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise RasterIOError(f"cannot read image {str(path)!r}")
        s = (int(img.shape[1]), int(img.shape[0]))
        if size is None:
            size = s
        elif s != size:
            raise InvalidInputError(f"image {path.name!r} is {s[0]} x {s[1]} px, the first was {size[0]} x {size[1]}")
        c = detect_chessboard(img, board, refine_window=refine_window)
        if c is None:
            logger.warning("chessboard %dx%d not found in %s", board.cols, board.rows, path.name)
            missing.append(path.name)
        else:
            views.append(TargetView(path.name, board.object_xyz, c, board.ids))
    if size is None:
        raise InvalidInputError("no images given")
    return views, missing, size
