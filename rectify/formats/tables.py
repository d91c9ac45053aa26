"""Tables of image points: the matches CSV and the stereo control CSV (``docs/formats.md``).

==================  ===========================================  ================================
file                reader / writer                              header
==================  ===========================================  ================================
matches CSV         :func:`read_matches` / :func:`write_matches` ``id,col_left,row_left,col_right,row_right[,score]...``
stereo control CSV  :func:`read_control` / :func:`write_control` ``id,col_left,row_left,col_right,row_right,x,y,z``
==================  ===========================================  ================================

Pixels in the project's convention (x = column right, y = row down, pixel centres at integers); the
tables are :class:`rectify.geometry.points.Matches` and :class:`rectify.geometry.points.ControlTable`.
Each writer has a pure serialiser (``*_text``) for :meth:`rectify.actions.workspace.Workspace.output`.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from rectify.atomic import atomic_write_text
from rectify.errors import CRSError, InvalidInputError
from rectify.formats.common import (
    MAX_MATCH_ROWS,
    Columns,
    StrPath,
    TableReader,
    need_columns,
    no_duplicates,
)
from rectify.geometry.crs import parse_crs
from rectify.geometry.points import ControlTable, Matches

__all__ = ["read_matches", "read_matches_table", "write_matches", "matches_text", "read_control", "write_control",
           "control_text", "check_crs_comment"]

_MATCH_COLUMNS = ("id", "col_left", "row_left", "col_right", "row_right")
_CONTROL_COLUMNS = ("id", "col_left", "row_left", "col_right", "row_right", "x", "y", "z")


def check_crs_comment(cols: Columns) -> None:
    """Refuse a table whose ``# crs=`` value is not a CRS, naming the file and the line (before any work:
    a CRS found unknown only when a product is written would waste the run)."""
    if not cols.crs:
        return
    line = next((no for no, key, _ in reversed(cols.settings) if key == "crs"), None)
    try:
        parse_crs(cols.crs)
    except CRSError as err:
        where = f" line {line}" if line is not None else ""
        raise CRSError(f"{str(cols.path)!r}{where}: {err}") from None


def read_matches(path: StrPath) -> Matches:
    """Read a matches CSV (``id,col_left,row_left,col_right,row_right[,score][,sigma_px]``), pixel frame.

    Read as a stream (:class:`rectify.formats.common.TableReader`); more than
    :data:`rectify.formats.common.MAX_MATCH_ROWS` rows are refused.
    """
    with TableReader(path) as t:
        return read_matches_table(t)[0]


def read_matches_table(t: TableReader, *, max_rows: int = MAX_MATCH_ROWS) -> tuple[Matches, str | None]:
    """The matches of an open matches CSV (its header read) and its ``# crs=`` value; more than ``max_rows``
    rows are refused."""
    path = t.path
    need_columns(list(t.fields), _MATCH_COLUMNS, path)
    has_score = "score" in t.fields
    has_sigma = "sigma_px" in t.fields
    optional = (("score",) if has_score else ()) + (("sigma_px",) if has_sigma else ())
    cols = t.read("matches", numbers=_MATCH_COLUMNS[1:] + optional, texts=("id",),
                  empty=("score", "sigma_px"), max_rows=max_rows)
    ids = tuple(cols.texts.pop("id"))
    no_duplicates(ids, path, "match id(s)")
    num = cols.numbers
    sigma = num.pop("sigma_px") if has_sigma else None
    if sigma is not None:
        bad = np.flatnonzero(np.isfinite(sigma) & (sigma <= 0))
        if len(bad):
            raise InvalidInputError(f"{str(path)!r}: match {ids[bad[0]]!r} has sigma_px {sigma[bad[0]]:g}; "
                                    "a standard deviation must be > 0 (or empty: unknown)")
    return Matches(ids, np.column_stack([num.pop("col_left"), num.pop("row_left")]),
                   np.column_stack([num.pop("col_right"), num.pop("row_right")]),
                   num.pop("score") if has_score else None, sigma), cols.crs


def matches_text(matches: Matches) -> str:
    """The matches CSV text: positions with 6 decimals (1e-6 px), scores with 6 significant digits (empty
    for a NaN score: a match the refinement could not refine, kept at its raw position)."""
    buf = io.StringIO()
    cols = ["id", "col_left", "row_left", "col_right", "row_right"]
    if matches.score is not None:
        cols.append("score")
    if matches.sigma is not None:
        cols.append("sigma_px")
    buf.write(",".join(cols) + "\n")
    for i in range(len(matches)):
        vals = [matches.ids[i]] + [f"{v:.6f}" for v in (*matches.left[i], *matches.right[i])]
        if matches.score is not None:  # NaN (a match kept unrefined) is written empty
            vals.append(f"{matches.score[i]:.6g}" if math.isfinite(matches.score[i]) else "")
        if matches.sigma is not None:  # NaN (unknown) is written empty
            vals.append(f"{matches.sigma[i]:.4g}" if math.isfinite(matches.sigma[i]) else "")
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_matches(path: StrPath, matches: Matches, *, overwrite: bool = False) -> Path:
    """Write a matches CSV atomically (:func:`matches_text`); return the path."""
    return atomic_write_text(path, matches_text(matches), overwrite=overwrite)


def read_control(path: StrPath) -> ControlTable:
    """Read a stereo control CSV (``id,col_left,row_left,col_right,row_right,x,y,z``).

    Empty ``x, y, z`` make a tie point (NaN in ``xyz``); partly empty rows are refused. The ``# crs=``
    value must name a CRS (checked here, before any work, with the line named). Read as a stream; more
    than :data:`rectify.formats.common.MAX_POINT_ROWS` rows are refused.

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Missing columns, a bad number (line, column and value named), partly empty ground
        coordinates, duplicate ids, too many rows.
    CRSError
        The ``# crs=`` value is not a CRS.
    """
    with TableReader(path) as t:
        need_columns(list(t.fields), _CONTROL_COLUMNS, path)
        cols = t.read("rows", numbers=_CONTROL_COLUMNS[1:], texts=("id",), empty=("x", "y", "z"))
    check_crs_comment(cols)
    num = cols.numbers
    xyz = np.column_stack([num.pop("x"), num.pop("y"), num.pop("z")])
    given = np.isfinite(xyz)
    partial = np.flatnonzero(given.any(axis=1) & ~given.all(axis=1))
    if partial.size:
        raise InvalidInputError(f"{str(path)!r} line {int(cols.lines[partial[0]])}: x, y, z must be all given or all "
                                "empty")
    ids = tuple(cols.texts.pop("id"))
    no_duplicates(ids, path, "id(s)")
    return ControlTable(ids, np.column_stack([num.pop("col_left"), num.pop("row_left")]),
                        np.column_stack([num.pop("col_right"), num.pop("row_right")]), xyz, cols.crs)


def control_text(control: ControlTable) -> str:
    """The stereo control CSV text (``# crs=`` line when set; numbers as ``repr``, tie rows empty)."""
    buf = io.StringIO()
    if control.crs:
        buf.write(f"# crs={control.crs}\n")
    buf.write("id,col_left,row_left,col_right,row_right,x,y,z\n")
    for i in range(len(control)):
        g = control.xyz[i]
        ground = [repr(float(v)) for v in g] if np.isfinite(g).all() else ["", "", ""]
        vals = [control.ids[i], *(repr(float(v)) for v in (*control.left[i], *control.right[i])), *ground]
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_control(path: StrPath, control: ControlTable, *, overwrite: bool = False) -> Path:
    """Write a stereo control CSV atomically (:func:`control_text`); return the path."""
    return atomic_write_text(path, control_text(control), overwrite=overwrite)
