"""Point tables of DESIGN.md: GCP CSV (and QGIS ``.points``), matches CSV,
stereo control CSV.

Files use the project's pixel convention (pixel centres at integers). Lines
starting with ``#`` are comments; a comment ``# crs=EPSG:32618`` sets the CRS.
Readers raise :class:`RasterIOError` for unreadable files and
:class:`InvalidInputError` naming the line for malformed content.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .errors import InvalidInputError, RasterIOError
from .fileutil import atomic_write_text

__all__ = ["GcpTable", "Matches", "ControlTable", "read_gcps", "write_gcps", "read_matches",
           "write_matches", "read_control"]


@dataclass(frozen=True, eq=False)
class GcpTable:
    """Ground control for 2D rectification.

    Attributes
    ----------
    ids : tuple of str
    pixel : (N, 2) float64
        Source pixels (col, row).
    target : (N, 2) float64
        Target coordinates (map units when ``crs`` is set, target pixels otherwise).
    z : (N,) float64 or None
        Heights, when the file has a ``z`` column.
    check : (N,) bool
        Rows withheld from the fit (``check`` column = 1).
    crs : str or None
    """

    ids: tuple[str, ...]
    pixel: NDArray[np.float64]
    target: NDArray[np.float64]
    z: NDArray[np.float64] | None
    check: NDArray[np.bool_]
    crs: str | None = None

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def fit(self) -> GcpTable:
        """The rows used for fitting (not check points)."""
        return self.subset(~self.check)

    def subset(self, mask: NDArray[np.bool_]) -> GcpTable:
        m = np.asarray(mask, dtype=bool)
        return GcpTable(tuple(i for i, k in zip(self.ids, m) if k), self.pixel[m], self.target[m],
                        None if self.z is None else self.z[m], self.check[m], self.crs)


@dataclass(frozen=True, eq=False)
class Matches:
    """Tie points between two images, pixel frame.

    Attributes
    ----------
    ids : tuple of str
    left, right : (N, 2) float64
        (col, row) in the left and right image.
    score : (N,) float64 or None
    """

    ids: tuple[str, ...]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    score: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True, eq=False)
class ControlTable:
    """Stereo control: image points in both images plus ground coordinates.

    ``xyz`` rows are NaN for tie points (empty x, y, z in the file).
    """

    ids: tuple[str, ...]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    xyz: NDArray[np.float64]
    crs: str | None = None

    @property
    def is_control(self) -> NDArray[np.bool_]:
        """(N,) rows with full ground coordinates."""
        return np.isfinite(self.xyz).all(axis=1)


def _read_text(path: str | Path) -> str:
    p = Path(path)
    try:
        return p.read_text()
    except FileNotFoundError as err:
        raise RasterIOError(f"file not found: {str(p)!r}") from err
    except (OSError, UnicodeDecodeError) as err:
        raise RasterIOError(f"cannot read {str(p)!r}: {err}") from err


def _rows(text: str, path: str | Path) -> tuple[list[dict[str, str]], list[int], str | None]:
    """Parse CSV text with comment lines; return rows, their line numbers and the crs comment."""
    crs = None
    data_lines: list[tuple[int, str]] = []
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            if body.lower().startswith("crs="):
                crs = body[4:].strip()
            elif body.upper().startswith("CRS:"):  # QGIS .points header
                crs = body[4:].strip() or None
            continue
        data_lines.append((no, line))
    if not data_lines:
        raise InvalidInputError(f"{str(path)!r} has no header and no rows")
    reader = csv.DictReader(io.StringIO("\n".join(l for _, l in data_lines)))
    reader.fieldnames = [f.strip() for f in (reader.fieldnames or [])]
    rows = [{k: (v or "").strip() for k, v in r.items() if k is not None} for r in reader]
    return rows, [no for no, _ in data_lines[1:]], crs


def _load(path: str | Path, what: str) -> tuple[list[dict[str, str]], list[int], str | None, list[str]]:
    """Read a point table: its rows, their line numbers, the ``# crs=`` value and the header;
    raise when the file has a header but no ``what``."""
    rows, lines, crs = _rows(_read_text(path), path)
    if not rows:
        raise InvalidInputError(f"{str(path)!r} has a header but no {what}")
    return rows, lines, crs, list(rows[0].keys())


def _need(fields: list[str], required: tuple[str, ...], path) -> None:
    missing = [f for f in required if f not in fields]
    if missing:
        raise InvalidInputError(f"{str(path)!r}: missing column(s) {missing}; header is {fields}")


def _num(row: dict[str, str], key: str, line: int, path, *, allow_empty: bool = False) -> float:
    s = row.get(key, "")
    if s == "" and allow_empty:
        return math.nan
    try:
        v = float(s)
    except ValueError:
        raise InvalidInputError(f"{str(path)!r} line {line}: column {key!r} is not a number: {s!r}") from None
    if not math.isfinite(v):
        raise InvalidInputError(f"{str(path)!r} line {line}: column {key!r} is not finite: {s!r}")
    return v


def read_gcps(path: str | Path) -> GcpTable:
    """Read a GCP CSV (``id,col,row,x,y[,z][,check]``) or a QGIS ``.points`` file.

    QGIS files (``mapX,mapY,sourceX,sourceY,enable,...``, pixel corners, rows
    negative) are converted to the project's convention; disabled rows become
    check points.
    """
    rows, lines, crs, fields = _load(path, "GCP rows")
    ids, pix, tgt, zs, chk = [], [], [], [], []
    if "mapX" in fields:
        sx = "sourceX" if "sourceX" in fields else "pixelX"
        sy = "sourceY" if "sourceY" in fields else "pixelY"
        _need(fields, ("mapX", "mapY", sx, sy), path)
        for k, (r, ln) in enumerate(zip(rows, lines)):
            ids.append(str(k + 1))
            # QGIS: corner convention, row axis negative
            pix.append((_num(r, sx, ln, path) - 0.5, -_num(r, sy, ln, path) - 0.5))
            tgt.append((_num(r, "mapX", ln, path), _num(r, "mapY", ln, path)))
            chk.append(r.get("enable", "1") in ("0", "false", "False"))
        z = None
    else:
        _need(fields, ("id", "col", "row", "x", "y"), path)
        has_z = "z" in fields
        for r, ln in zip(rows, lines):
            ids.append(r["id"])
            pix.append((_num(r, "col", ln, path), _num(r, "row", ln, path)))
            tgt.append((_num(r, "x", ln, path), _num(r, "y", ln, path)))
            if has_z:
                zs.append(_num(r, "z", ln, path))
            c = r.get("check", "0") or "0"
            if c not in ("0", "1"):
                raise InvalidInputError(f"{str(path)!r} line {ln}: column 'check' must be 0 or 1; got {c!r}")
            chk.append(c == "1")
        z = np.array(zs) if has_z else None
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise InvalidInputError(f"{str(path)!r}: duplicate GCP id(s) {sorted(dup)}")
    return GcpTable(tuple(ids), np.array(pix, dtype=float).reshape(-1, 2),
                    np.array(tgt, dtype=float).reshape(-1, 2), z, np.array(chk, dtype=bool), crs)


def write_gcps(path: str | Path, gcps: GcpTable, *, overwrite: bool = False) -> Path:
    """Write a GCP CSV in the project's format (with ``# crs=`` when set)."""
    buf = io.StringIO()
    if gcps.crs:
        buf.write(f"# crs={gcps.crs}\n")
    cols = ["id", "col", "row", "x", "y"] + (["z"] if gcps.z is not None else []) + ["check"]
    buf.write(",".join(cols) + "\n")
    for i in range(len(gcps)):
        vals = [gcps.ids[i], *map(repr, map(float, gcps.pixel[i])), *map(repr, map(float, gcps.target[i]))]
        if gcps.z is not None:
            vals.append(repr(float(gcps.z[i])))
        vals.append("1" if gcps.check[i] else "0")
        buf.write(",".join(vals) + "\n")
    return atomic_write_text(path, buf.getvalue(), overwrite=overwrite)


def read_matches(path: str | Path) -> Matches:
    """Read a matches CSV (``id,col_left,row_left,col_right,row_right[,score]``)."""
    rows, lines, _, fields = _load(path, "matches")
    _need(fields, ("id", "col_left", "row_left", "col_right", "row_right"), path)
    has_score = "score" in fields
    ids, left, right, score = [], [], [], []
    for r, ln in zip(rows, lines):
        ids.append(r["id"])
        left.append((_num(r, "col_left", ln, path), _num(r, "row_left", ln, path)))
        right.append((_num(r, "col_right", ln, path), _num(r, "row_right", ln, path)))
        if has_score:
            score.append(_num(r, "score", ln, path, allow_empty=True))
    return Matches(tuple(ids), np.array(left).reshape(-1, 2), np.array(right).reshape(-1, 2),
                   np.array(score) if has_score else None)


def write_matches(path: str | Path, matches: Matches, *, overwrite: bool = False) -> Path:
    """Write a matches CSV atomically."""
    buf = io.StringIO()
    cols = ["id", "col_left", "row_left", "col_right", "row_right"]
    if matches.score is not None:
        cols.append("score")
    buf.write(",".join(cols) + "\n")
    for i in range(len(matches)):
        vals = [matches.ids[i]] + [f"{v:.6f}" for v in (*matches.left[i], *matches.right[i])]
        if matches.score is not None:
            vals.append(f"{matches.score[i]:.6g}")
        buf.write(",".join(vals) + "\n")
    return atomic_write_text(path, buf.getvalue(), overwrite=overwrite)


def read_control(path: str | Path) -> ControlTable:
    """Read a stereo control CSV (``id,col_left,row_left,col_right,row_right,x,y,z``)."""
    rows, lines, crs, fields = _load(path, "rows")
    _need(fields, ("id", "col_left", "row_left", "col_right", "row_right", "x", "y", "z"), path)
    ids, left, right, xyz = [], [], [], []
    for r, ln in zip(rows, lines):
        ids.append(r["id"])
        left.append((_num(r, "col_left", ln, path), _num(r, "row_left", ln, path)))
        right.append((_num(r, "col_right", ln, path), _num(r, "row_right", ln, path)))
        p = [_num(r, k, ln, path, allow_empty=True) for k in ("x", "y", "z")]
        if any(math.isnan(v) for v in p) and not all(math.isnan(v) for v in p):
            raise InvalidInputError(f"{str(path)!r} line {ln}: x, y, z must be all given or all empty")
        xyz.append(p)
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise InvalidInputError(f"{str(path)!r}: duplicate id(s) {sorted(dup)}")
    return ControlTable(tuple(ids), np.array(left).reshape(-1, 2), np.array(right).reshape(-1, 2),
                        np.array(xyz, dtype=float).reshape(-1, 3), crs)
