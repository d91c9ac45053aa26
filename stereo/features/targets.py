"""Calibration targets: chessboard detection and observation / field CSV files.

Observation CSV (``--points``)
------------------------------
One row per measured image point; ``#`` lines are comments::

    view,point,col,row
    img01,p1,1021.37,733.05

``col, row`` are pixels (x = column right, y = row down, pixel centres at
integers). Optional columns ``x, y, z`` give the object coordinates in the
row itself (then no field file is needed).

Field CSV (``--field``)
-----------------------
Object coordinates of the target points (plane or 3D), any unit::

    point,x,y,z
    p1,0.0,0.0,0.0
"""

from __future__ import annotations

import csv
import io
import logging
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import read_text
from rectify.errors import CalibrationError, InvalidInputError, RasterIOError, ShapeError

logger = logging.getLogger(__name__)

__all__ = ["Chessboard", "TargetView", "detect_chessboard", "detect_chessboards", "parse_pattern",
           "parse_square", "read_field_csv", "read_observations_csv", "views_from_csv", "check_inside"]

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class TargetView:
    """The measured target points of one image.

    Attributes
    ----------
    name : str
        View name (file stem or the CSV's ``view``).
    object_xyz : (N, 3) float64
        Target coordinates, object frame and units.
    pixel : (N, 2) float64
        Measured pixels (col, row).
    ids : tuple of str, length N
        Point identifiers.
    """

    name: str
    object_xyz: F64
    pixel: F64
    ids: tuple[str, ...]

    def __post_init__(self) -> None:
        X = np.array(self.object_xyz, dtype=np.float64, copy=True)
        x = np.array(self.pixel, dtype=np.float64, copy=True)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ShapeError(f"view {self.name!r}: `object_xyz` must have shape (N, 3); got {X.shape}",
                             actual_shape=X.shape, expected_shape=(None, 3))
        if x.shape != (len(X), 2):
            raise ShapeError(f"view {self.name!r}: `pixel` must have shape ({len(X)}, 2); got {x.shape}",
                             actual_shape=x.shape, expected_shape=(len(X), 2))
        if not (np.isfinite(X).all() and np.isfinite(x).all()):
            raise InvalidInputError(f"view {self.name!r} has NaN or infinite coordinates")
        ids = tuple(str(i) for i in self.ids) if self.ids is not None else tuple(str(i) for i in range(len(X)))
        if len(ids) != len(X):
            raise ShapeError(f"view {self.name!r}: {len(ids)} ids for {len(X)} points", actual_shape=(len(ids),))
        X.flags.writeable = False
        x.flags.writeable = False
        object.__setattr__(self, "object_xyz", X)
        object.__setattr__(self, "pixel", x)
        object.__setattr__(self, "ids", ids)

    @property
    def n(self) -> int:
        return len(self.ids)

    @property
    def is_planar(self) -> bool:
        """True when the object points lie on one plane (thickness < 1e-6 of the extent)."""
        if self.n < 4:
            return True
        sv = np.linalg.svd(self.object_xyz - self.object_xyz.mean(axis=0), compute_uv=False)
        return bool(sv[2] <= 1e-6 * sv[0])


def check_inside(views: Iterable[TargetView], width: int, height: int) -> None:
    """Raise :class:`InvalidInputError` naming the first point outside the image."""
    for v in views:
        x = v.pixel
        bad = (x[:, 0] < -0.5) | (x[:, 0] > width - 0.5) | (x[:, 1] < -0.5) | (x[:, 1] > height - 0.5)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidInputError(
                f"view {v.name!r}: point {v.ids[i]!r} at ({x[i, 0]:.2f}, {x[i, 1]:.2f}) px is outside the "
                f"{width} x {height} image ({int(bad.sum())} such points)")


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
    import cv2

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
    import cv2

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


# ---------------------------------------------------------------------- CSV files
def _read_rows(path: str | Path, what: str) -> tuple[list[str], list[list[str]]]:
    p = Path(path)
    text = read_text(p, what)
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InvalidInputError(f"{what} {str(p)!r} is empty")
    rows = list(csv.reader(io.StringIO("\n".join(lines))))
    header = [h.strip().lower() for h in rows[0]]
    return header, [[c.strip() for c in r] for r in rows[1:]]


def _num(v: str, what: str, line: int, col: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise InvalidInputError(f"{what} line {line}: column {col!r} is not a number: {v!r}") from None
    if not math.isfinite(x):
        raise InvalidInputError(f"{what} line {line}: column {col!r} is not finite: {v!r}")
    return x


def read_field_csv(path: str | Path) -> dict[str, F64]:
    """Read a field CSV ``point,x,y,z`` -> {point id: (3,) object coordinates}.

    Raises
    ------
    InvalidInputError
        Missing columns, bad numbers, duplicate point ids.
    """
    what = f"field file {str(path)!r}"
    header, rows = _read_rows(path, "field file")
    need = ["point", "x", "y", "z"]
    miss = [c for c in need if c not in header]
    if miss:
        raise InvalidInputError(f"{what} lacks column(s) {miss}; expected point,x,y,z")
    ix = [header.index(c) for c in need]
    out: dict[str, F64] = {}
    for k, r in enumerate(rows, start=2):
        if len(r) < len(header):
            raise InvalidInputError(f"{what} line {k}: {len(r)} fields, expected {len(header)}")
        pid = r[ix[0]]
        if pid in out:
            raise InvalidInputError(f"{what} line {k}: duplicate point {pid!r}")
        out[pid] = np.array([_num(r[i], what, k, c) for i, c in zip(ix[1:], need[1:], strict=True)])
    return out


def read_observations_csv(path: str | Path) -> tuple[list[tuple[str, str, float, float]], dict[str, F64]]:
    """Read an observation CSV -> ([(view, point, col, row), ...], {point: xyz} from optional x,y,z columns)."""
    what = f"observation file {str(path)!r}"
    header, rows = _read_rows(path, "observation file")
    need = ["view", "point", "col", "row"]
    miss = [c for c in need if c not in header]
    if miss:
        raise InvalidInputError(f"{what} lacks column(s) {miss}; expected view,point,col,row[,x,y,z]")
    ix = [header.index(c) for c in need]
    has_xyz = all(c in header for c in ("x", "y", "z"))
    ixyz = [header.index(c) for c in ("x", "y", "z")] if has_xyz else []
    obs: list[tuple[str, str, float, float]] = []
    xyz: dict[str, F64] = {}
    seen: set[tuple[str, str]] = set()
    for k, r in enumerate(rows, start=2):
        if len(r) < len(header):
            raise InvalidInputError(f"{what} line {k}: {len(r)} fields, expected {len(header)}")
        view, pid = r[ix[0]], r[ix[1]]
        if (view, pid) in seen:
            raise InvalidInputError(f"{what} line {k}: point {pid!r} measured twice in view {view!r}")
        seen.add((view, pid))
        obs.append((view, pid, _num(r[ix[2]], what, k, "col"), _num(r[ix[3]], what, k, "row")))
        if has_xyz:
            p = np.array([_num(r[i], what, k, c) for i, c in zip(ixyz, "xyz", strict=True)])
            if pid in xyz and not np.allclose(xyz[pid], p):
                raise InvalidInputError(f"{what} line {k}: point {pid!r} has two different object coordinates")
            xyz[pid] = p
    if not obs:
        raise InvalidInputError(f"{what} has no observations")
    return obs, xyz


def views_from_csv(points_path: str | Path, field_path: str | Path | None = None) -> list[TargetView]:
    """Build views from an observation CSV and (optionally) a field CSV.

    Raises
    ------
    InvalidInputError
        Points without object coordinates (named), or no object coordinates at all.
    """
    obs, xyz = read_observations_csv(points_path)
    if field_path is not None:
        field = read_field_csv(field_path)
        xyz = {**xyz, **field}
    if not xyz:
        raise InvalidInputError(f"no object coordinates: give a field file or x,y,z columns in {str(points_path)!r}")
    unknown = sorted({pid for _, pid, _, _ in obs if pid not in xyz})
    if unknown:
        raise CalibrationError(f"{len(unknown)} measured point(s) have no object coordinates: {unknown[:5]}")
    order: list[str] = []
    by_view: dict[str, list[tuple[str, float, float]]] = {}
    for view, pid, c, r in obs:
        if view not in by_view:
            order.append(view)
            by_view[view] = []
        by_view[view].append((pid, c, r))
    out = []
    for v in order:
        items = by_view[v]
        out.append(TargetView(v, np.array([xyz[p] for p, _, _ in items]), np.array([[c, r] for _, c, r in items]),
                              tuple(p for p, _, _ in items)))
    return out
