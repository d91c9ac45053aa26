"""Tables of image points: the matches CSV and the stereo control CSV (``docs/formats.md``).

==================  ===========================================  ================================
file                reader / writer                              header
==================  ===========================================  ================================
matches CSV         :func:`read_matches` / :func:`write_matches` ``id,col_left,row_left,col_right,row_right[,score]``
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
from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath, cell_number, load_table, need_columns, no_duplicates
from rectify.geometry.points import ControlTable, Matches

__all__ = ["read_matches", "write_matches", "matches_text", "read_control", "write_control", "control_text"]


def read_matches(path: StrPath) -> Matches:
    """Read a matches CSV (``id,col_left,row_left,col_right,row_right[,score]``), pixel frame."""
    rows, lines, _, fields = load_table(path, "matches")
    need_columns(fields, ("id", "col_left", "row_left", "col_right", "row_right"), path)
    has_score = "score" in fields
    ids, left, right, score = [], [], [], []
    for r, ln in zip(rows, lines, strict=False):
        ids.append(r["id"])
        left.append((cell_number(r, "col_left", ln, path), cell_number(r, "row_left", ln, path)))
        right.append((cell_number(r, "col_right", ln, path), cell_number(r, "row_right", ln, path)))
        if has_score:
            score.append(cell_number(r, "score", ln, path, allow_empty=True))
    no_duplicates(ids, path, "match id(s)")
    return Matches(tuple(ids), np.array(left).reshape(-1, 2), np.array(right).reshape(-1, 2),
                   np.array(score) if has_score else None)


def matches_text(matches: Matches) -> str:
    """The matches CSV text: positions with 6 decimals (1e-6 px), scores with 6 significant digits (empty
    for a NaN score: a match the refinement could not refine, kept at its raw position)."""
    buf = io.StringIO()
    cols = ["id", "col_left", "row_left", "col_right", "row_right"]
    if matches.score is not None:
        cols.append("score")
    buf.write(",".join(cols) + "\n")
    for i in range(len(matches)):
        vals = [matches.ids[i]] + [f"{v:.6f}" for v in (*matches.left[i], *matches.right[i])]
        if matches.score is not None:  # NaN (a match kept unrefined) is written empty
            vals.append(f"{matches.score[i]:.6g}" if math.isfinite(matches.score[i]) else "")
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_matches(path: StrPath, matches: Matches, *, overwrite: bool = False) -> Path:
    """Write a matches CSV atomically (:func:`matches_text`); return the path."""
    return atomic_write_text(path, matches_text(matches), overwrite=overwrite)


def read_control(path: StrPath) -> ControlTable:
    """Read a stereo control CSV (``id,col_left,row_left,col_right,row_right,x,y,z``).

    Empty ``x, y, z`` make a tie point (NaN in ``xyz``); partly empty rows are refused.
    """
    rows, lines, crs, fields = load_table(path, "rows")
    need_columns(fields, ("id", "col_left", "row_left", "col_right", "row_right", "x", "y", "z"), path)
    ids, left, right, xyz = [], [], [], []
    for r, ln in zip(rows, lines, strict=False):
        ids.append(r["id"])
        left.append((cell_number(r, "col_left", ln, path), cell_number(r, "row_left", ln, path)))
        right.append((cell_number(r, "col_right", ln, path), cell_number(r, "row_right", ln, path)))
        p = [cell_number(r, k, ln, path, allow_empty=True) for k in ("x", "y", "z")]
        if any(math.isnan(v) for v in p) and not all(math.isnan(v) for v in p):
            raise InvalidInputError(f"{str(path)!r} line {ln}: x, y, z must be all given or all empty")
        xyz.append(p)
    no_duplicates(ids, path, "id(s)")
    return ControlTable(tuple(ids), np.array(left).reshape(-1, 2), np.array(right).reshape(-1, 2),
                        np.array(xyz, dtype=float).reshape(-1, 3), crs)


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
