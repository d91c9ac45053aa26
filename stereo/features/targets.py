"""Calibration targets: chessboards (:class:`Chessboard`) and their detection in images.

Detection gives one :class:`stereo.calibration.views.TargetView` per image where the board is found;
the observation and field CSV files are read by :mod:`stereo.formats.calibration`.
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, RasterIOError
from rectify.raster.io import ignore_not_georeferenced, raster_info
from stereo.calibration.views import TargetView

logger = logging.getLogger(__name__)

__all__ = ["CORNER_METHODS", "Chessboard", "ChessboardCorners", "ChessboardDetection", "RejectedCorner",
           "corner_spacing", "detect_chessboard", "detect_chessboards", "find_chessboards", "parse_pattern",
           "parse_square", "refine_corners"]

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


# ------------------------------------------------------------- corner refinement
#: Corner refinement methods: ``symmetry`` (ours, the default: the point about which the image is
#: point-symmetric) and ``opencv`` (OpenCV's ``cornerSubPix``).
CORNER_METHODS = ("symmetry", "opencv")

_MAX_ITER = 50          # refinement iterations per corner
_STEP_TOL_PX = 1e-3     # converged when a step is shorter
_MOVE_LIMIT = 0.5       # of the local corner spacing: a refinement that moves further has left its corner
_ASYM_LIMIT = 0.05      # symmetry residual / contrast above which a neighbourhood is not a corner ...
_ASYM_FACTOR = 3.0      # ... and above this many times the view's median
_CONTRAST_FACTOR = 0.2  # contrast below this share of the view's median: no corner there
_OFF_CENTRE_PX = 0.5    # a corner further than this from the centre of symmetry of its neighbourhood failed


@dataclass(frozen=True)
class RejectedCorner:
    """A chessboard corner left out because its refinement failed.

    Attributes
    ----------
    view : str
        Image (file) name.
    index : int
        Corner index in OpenCV's order (row by row), 0-based.
    id : str
        Corner name ``r<row>c<col>`` (:attr:`Chessboard.ids`).
    col, row : float
        Where the refinement left it, px.
    reason : str
        What failed, with the figures.
    """

    view: str
    index: int
    id: str
    col: float
    row: float
    reason: str

    @property
    def label(self) -> str:
        return f"{self.view} corner {self.id} (#{self.index})"

    def as_dict(self) -> dict[str, object]:
        return {"view": self.view, "index": self.index, "corner": self.id, "col": round(self.col, 3),
                "row": round(self.row, 3), "reason": self.reason}


@dataclass(frozen=True, eq=False)
class ChessboardCorners:
    """The refined inner corners of one chessboard image and the verdict on each.

    Attributes
    ----------
    pixel : (N, 2) float64
        Refined corners (col, row), px, OpenCV's order.
    start : (N, 2) float64
        ``findChessboardCorners``' positions, px.
    ok : (N,) bool
        False where the refinement failed (``reasons`` says why).
    reasons : tuple of str
        Empty for good corners.
    half_window : (N,) int
        Half size of the refinement window, px (half the local corner spacing).
    asymmetry : (N,) float64
        Weighted RMS of ``I(c + d) - I(c - d)`` over the window over the local contrast (0 for a perfect corner).
    method : str
    """

    pixel: F64
    start: F64
    ok: NDArray[np.bool_]
    reasons: tuple[str, ...]
    half_window: NDArray[np.intp]
    asymmetry: F64
    method: str


def _grey(image: ArrayLike) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """The image as uint8 (for the board search) and as float32 on the same 0..255 scale (for refinement)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint8:
        return img, img.astype(np.float32)
    f = img.astype(np.float64)
    lo, hi = float(np.min(f)), float(np.max(f))
    f = (f - lo) / max(hi - lo, 1e-12) * 255.0
    return np.clip(np.round(f), 0, 255).astype(np.uint8), f.astype(np.float32)


def corner_spacing(corners: ArrayLike, board: Chessboard) -> F64:
    """Distance from each corner to its nearest grid neighbour (along a row or column, or diagonal / sqrt 2), px.

    ``corners`` is (cols * rows, 2) in OpenCV's order; returns (cols * rows,).
    """
    g = np.full((board.rows + 2, board.cols + 2, 2), np.nan)
    g[1:-1, 1:-1] = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    c = g[1:-1, 1:-1]
    d = []
    for dj in (-1, 0, 1):
        for di in (-1, 0, 1):
            if dj or di:
                nb = g[1 + dj:board.rows + 1 + dj, 1 + di:board.cols + 1 + di]
                d.append(np.linalg.norm(nb - c, axis=2) / (math.sqrt(2) if dj and di else 1.0))
    return np.nanmin(np.array(d), axis=0).ravel()


_OPS: dict[int, tuple[F64, F64]] = {}


def _window_ops(r: int) -> tuple[F64, F64]:
    """Gaussian window weights ((2r+1)^2,) and the weighted quadratic-fit operator (6, (2r+1)^2) for half size r."""
    if r not in _OPS:
        y, x = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
        x, y = x.ravel(), y.ravel()
        w = np.exp(-(x * x + y * y) / (2 * (r / 1.5) ** 2))
        A = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
        Aw = A * w[:, None]
        _OPS[r] = (w, np.linalg.solve(A.T @ Aw, Aw.T))
    return _OPS[r]


def _patch(img: NDArray[np.float32], c: F64, r: int) -> F64:
    """Bilinear samples of ``img`` on a (2r+3)^2 grid centred on ``c`` (one pixel margin for gradients)."""
    n = 2 * r + 3
    return np.asarray(cv2.getRectSubPix(img, (n, n), (float(c[0]), float(c[1])), patchType=cv2.CV_32F),
                      dtype=np.float64)


def _symmetry_step(p: F64, w: F64) -> tuple[F64, float]:
    """Gauss-Newton step towards the centre of point symmetry of a patch, and the symmetry residual / contrast.

    With ``r(d) = I(c + d) - I(c - d)``, ``dr/dc = grad I(c + d) - grad I(c - d)``.
    """
    P = p[1:-1, 1:-1]
    gx = 0.5 * (p[1:-1, 2:] - p[1:-1, :-2])
    gy = 0.5 * (p[2:, 1:-1] - p[:-2, 1:-1])
    res = (P - P[::-1, ::-1]).ravel()
    J = np.column_stack([(gx - gx[::-1, ::-1]).ravel(), (gy - gy[::-1, ::-1]).ravel()])
    N = J.T @ (J * w[:, None])
    lo, hi = np.percentile(P, [5, 95])
    q = math.sqrt(float(np.sum(w * res * res) / np.sum(w))) / max(float(hi - lo), 1e-9)
    try:
        step = -np.linalg.solve(N, J.T @ (w * res))
    except np.linalg.LinAlgError:
        step = np.full(2, np.nan)
    return step, q


def _refine_symmetry(img: NDArray[np.float32], start: F64, half: NDArray[np.intp]) -> tuple[F64, NDArray[np.bool_]]:
    """Each corner moved to the centre of point symmetry of its window (Gauss-Newton), and whether it converged."""
    out = np.array(start, dtype=np.float64)
    conv = np.zeros(len(out), dtype=bool)
    for k in range(len(out)):
        r = int(half[k])
        w, _ = _window_ops(r)
        c = out[k].copy()
        for _ in range(_MAX_ITER):
            step, _q = _symmetry_step(_patch(img, c, r), w)
            n = float(np.hypot(*step))
            if not math.isfinite(n):
                break
            if n > 0.5 * r:
                step *= 0.5 * r / n
            c += step
            if n < _STEP_TOL_PX:
                conv[k] = True
                break
        out[k] = c
    return out, conv


def _quality(img: NDArray[np.float32], pixel: F64, half: NDArray[np.intp]) -> tuple[F64, F64, F64, F64]:
    """Asymmetry, contrast (grey levels), the saddle determinant (< 0 for a saddle) and the distance to the
    centre of symmetry (one Gauss-Newton step, px) at each corner."""
    n = len(pixel)
    asym, contrast, det, off = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    for k, c in enumerate(pixel):
        r = int(half[k])
        w, M = _window_ops(r)
        p = _patch(img, c, r)
        step, asym[k] = _symmetry_step(p, w)
        off[k] = float(np.hypot(*step)) if np.all(np.isfinite(step)) else np.inf
        P = p[1:-1, 1:-1]
        lo, hi = np.percentile(P, [5, 95])
        contrast[k] = hi - lo
        a, b, cc = (M @ P.ravel())[:3]
        det[k] = 4 * a * cc - b * b
    return asym, contrast, det, off


def refine_corners(image: ArrayLike, start: ArrayLike, board: Chessboard, *, method: str = "symmetry",
                   refine_window: int = 11) -> ChessboardCorners:
    """Refine detected chessboard corners to sub-pixel positions and check each refinement.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        The image (any dtype; colour is BGR).
    start : (cols * rows, 2) float
        Corners from ``findChessboardCorners``, OpenCV's order, px.
    board : Chessboard
    method : {"symmetry", "opencv"}
        ``symmetry``: each corner moves to the point about which its neighbourhood is point-symmetric
        (``I(c + d) = I(c - d)``: true of a chessboard corner under any blur, contrast and local
        perspective), by Gauss-Newton on the bilinearly sampled image in a Gaussian-weighted window of
        half the local corner spacing. ``opencv``: ``cornerSubPix`` in a ``refine_window`` window
        (11 x 11 px: OpenCV's Python calibration sample), 30 iterations, epsilon 0.001.
    refine_window : int
        Window size of ``opencv``, px.

    A corner is rejected (``ok`` False, with the reason) when its refinement did not converge in 50
    iterations, moved more than half the local corner spacing from its detected position, stayed at its
    start (``cornerSubPix`` gives up that way), or ended where the image is not a corner: an asymmetric
    neighbourhood (residual over 0.05 of the contrast and 3 times the view's median), no contrast
    (under 0.2 times the view's median), no saddle point (the fitted quadratic surface is not a saddle),
    or more than 0.5 px from the centre of symmetry of its neighbourhood (``opencv``).

    Raises
    ------
    InvalidInputError
        An unknown method or a wrong number of corners.
    """
    if method not in CORNER_METHODS:
        raise InvalidInputError(f"corner refinement must be one of {', '.join(CORNER_METHODS)}; got {method!r}")
    u8, img = _grey(image)
    x0 = np.asarray(start, dtype=np.float64).reshape(-1, 2)
    if len(x0) != board.cols * board.rows:
        raise InvalidInputError(f"{len(x0)} corners for a {board.cols}x{board.rows} chessboard")
    spacing = corner_spacing(x0, board)
    h, w = img.shape
    border = np.min(np.column_stack([x0[:, 0], x0[:, 1], w - 1 - x0[:, 0], h - 1 - x0[:, 1]]), axis=1)
    half = np.clip(np.minimum(np.floor(_MOVE_LIMIT * spacing), np.floor(border) - 2), 2, 25).astype(np.intp)
    if method == "symmetry":
        x, conv = _refine_symmetry(img, x0, half)
    else:
        half_cv = max(2, refine_window // 2)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
        cv_x = cv2.cornerSubPix(u8, x0.astype(np.float32).reshape(-1, 1, 2), (half_cv, half_cv), (-1, -1), crit)
        x = np.asarray(cv_x, dtype=np.float64).reshape(-1, 2)
        conv = np.ones(len(x), dtype=bool)
    asym, contrast, det, off = _quality(img, x, half)
    moved = np.linalg.norm(x - x0, axis=1)
    inside = (x[:, 0] >= 0) & (x[:, 0] <= img.shape[1] - 1) & (x[:, 1] >= 0) & (x[:, 1] <= img.shape[0] - 1)
    med_asym = float(np.median(asym))
    med_con = float(np.median(contrast))
    reasons = []
    for k in range(len(x)):
        why = ""
        if not inside[k]:
            why = f"refined to ({x[k, 0]:.1f}, {x[k, 1]:.1f}) px, outside the image"
        elif not conv[k]:
            why = f"refinement did not converge in {_MAX_ITER} iterations"
        elif moved[k] > _MOVE_LIMIT * spacing[k]:
            why = (f"moved {moved[k]:.1f} px from its detected position (limit {_MOVE_LIMIT * spacing[k]:.1f} px, "
                   "half the corner spacing)")
        elif method == "opencv" and moved[k] == 0.0:
            why = "cornerSubPix left it at its detected position (refinement gave up)"
        elif contrast[k] < _CONTRAST_FACTOR * med_con:
            why = f"no contrast: {contrast[k]:.0f} grey levels (view median {med_con:.0f})"
        elif asym[k] > max(_ASYM_LIMIT, _ASYM_FACTOR * med_asym):
            why = (f"not a corner: asymmetric neighbourhood, residual {asym[k]:.2f} of the contrast "
                   f"(view median {med_asym:.2f}, limit {max(_ASYM_LIMIT, _ASYM_FACTOR * med_asym):.2f})")
        elif det[k] >= 0:
            why = "not a saddle point (the fitted surface curves the same way in every direction)"
        elif off[k] > _OFF_CENTRE_PX:
            why = (f"{off[k]:.2f} px from the centre of symmetry of its neighbourhood "
                   f"(limit {_OFF_CENTRE_PX:g} px)")
        reasons.append(why)
    ok = np.array([not r for r in reasons], dtype=bool)
    return ChessboardCorners(x, x0, ok, tuple(reasons), half, asym, method)


def detect_chessboard(image: ArrayLike, board: Chessboard, *, method: str = "symmetry",
                      refine_window: int = 11) -> ChessboardCorners | None:
    """Inner corners of a chessboard in one image, refined and checked, or ``None`` when the board is not found.

    OpenCV's ``findChessboardCorners`` (adaptive threshold, normalised image) finds the board;
    :func:`refine_corners` refines and checks every corner.
    """
    u8, _f = _grey(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(u8, (board.cols, board.rows), flags=flags)
    if not found or corners is None:
        return None
    return refine_corners(image, np.asarray(corners, dtype=np.float64).reshape(-1, 2), board, method=method,
                          refine_window=refine_window)


@dataclass(frozen=True, eq=False)
class ChessboardDetection:
    """The chessboard in a set of images.

    Attributes
    ----------
    views : list of TargetView
        One per image where the board was found (named by the file name), without its rejected corners.
    missing : list of str
        File names where the board was not found.
    size : (width, height)
        Image size, px.
    rejected : list of RejectedCorner
        Corners whose refinement failed (left out of ``views``).
    n_corners : int
        Corners found in all images (kept and rejected).
    method : str
        Corner refinement method.
    """

    views: list[TargetView]
    missing: list[str]
    size: tuple[int, int]
    rejected: list[RejectedCorner]
    n_corners: int
    method: str

    def summary_lines(self, *, max_listed: int = 30) -> list[str]:
        """Corners kept and each rejected one by name (the first ``max_listed``; the report lists all)."""
        kept = self.n_corners - len(self.rejected)
        out = [f"corners ({self.method} refinement): {kept} of {self.n_corners} kept"
               + (f", {len(self.rejected)} rejected (left out of the fit):" if self.rejected else "")]
        out += [f"  rejected {r.label} at ({r.col:.2f}, {r.row:.2f}) px: {r.reason}"
                for r in self.rejected[:max_listed]]
        if len(self.rejected) > max_listed:
            out.append(f"  ... and {len(self.rejected) - max_listed} more (all listed in the report)")
        return out


def _opencv_pixel_limit() -> int:
    """The most pixels OpenCV decodes from one image file (``OPENCV_IO_MAX_IMAGE_PIXELS``, default 2^30)."""
    try:
        return int(os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS", "")) or 1 << 30
    except ValueError:
        return 1 << 30


def _read_grey(path: Path) -> NDArray[np.uint8]:
    """An image file as 8-bit grey; an image OpenCV refuses (too many pixels, corrupt) is named in one line.

    Raises
    ------
    RasterIOError
        The file is missing, unreadable, or declares more pixels than OpenCV decodes (the size and the
        limit named).
    """
    try:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    except cv2.error as err:
        limit = _opencv_pixel_limit()
        try:
            with ignore_not_georeferenced():
                info = raster_info(path)  # the size the file declares, read from its header
        except RasterIOError:
            info = None
        if info is not None and info.width * info.height > limit:
            raise RasterIOError(f"cannot read image {str(path)!r}: it declares {info.width} x {info.height} px "
                                f"({info.width * info.height} pixels), more than OpenCV reads ({limit} pixels, "
                                "OPENCV_IO_MAX_IMAGE_PIXELS)") from None
        reason = (err.err or str(err)).strip().splitlines()[0] if str(err) else "decoding failed"
        raise RasterIOError(f"cannot read image {str(path)!r}: OpenCV refused it ({reason})") from None
    if img is None:
        raise RasterIOError(f"cannot read image {str(path)!r}")
    return np.asarray(img, dtype=np.uint8)


def find_chessboards(paths: Sequence[str | Path], board: Chessboard, *, method: str = "symmetry",
                     refine_window: int = 11) -> ChessboardDetection:
    """Detect the board in image files, refine and check its corners (:func:`refine_corners`).

    A view keeps its good corners; a view left with fewer than 4 is dropped (named in ``missing``).

    Raises
    ------
    RasterIOError
        An image cannot be read.
    InvalidInputError
        Images of different sizes, no images, an unknown method.
    """
    if method not in CORNER_METHODS:
        raise InvalidInputError(f"corner refinement must be one of {', '.join(CORNER_METHODS)}; got {method!r}")
    views: list[TargetView] = []
    missing: list[str] = []
    rejected: list[RejectedCorner] = []
    n_corners = 0
    size: tuple[int, int] | None = None
    ids = board.ids
    X = board.object_xyz
    for p in paths:
        path = Path(p)
        img = _read_grey(path)
        s = (int(img.shape[1]), int(img.shape[0]))
        if size is None:
            size = s
        elif s != size:
            raise InvalidInputError(f"image {path.name!r} is {s[0]} x {s[1]} px, the first was {size[0]} x {size[1]}")
        c = detect_chessboard(img, board, method=method, refine_window=refine_window)
        if c is None:
            logger.warning("chessboard %dx%d not found in %s", board.cols, board.rows, path.name)
            missing.append(path.name)
            continue
        n_corners += len(c.ok)
        bad = [RejectedCorner(path.name, int(k), ids[k], float(c.pixel[k, 0]), float(c.pixel[k, 1]), c.reasons[k])
               for k in np.flatnonzero(~c.ok)]
        for r in bad:
            logger.info("rejected %s: %s", r.label, r.reason)
        rejected += bad
        if int(c.ok.sum()) < 4:
            logger.warning("%s: only %d good corners, view left out", path.name, int(c.ok.sum()))
            missing.append(path.name)
            continue
        keep = np.flatnonzero(c.ok)
        views.append(TargetView(path.name, X[keep], c.pixel[keep], tuple(ids[k] for k in keep)))
    if size is None:
        raise InvalidInputError("no images given")
    return ChessboardDetection(views, missing, size, rejected, n_corners, method)


def detect_chessboards(paths: Sequence[str | Path], board: Chessboard, *, method: str = "symmetry",
                       refine_window: int = 11) -> tuple[list[TargetView], list[str], tuple[int, int]]:
    """Detect the board in image files: ``(views, missing, size)`` of :func:`find_chessboards`.

    Returns
    -------
    views : list of TargetView
        One per image where the board was found (named by the file name), without rejected corners
        (each logged as a warning).
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
    d = find_chessboards(paths, board, method=method, refine_window=refine_window)
    for r in d.rejected:
        logger.warning("rejected %s at (%.2f, %.2f) px: %s", r.label, r.col, r.row, r.reason)
    return d.views, d.missing, d.size
