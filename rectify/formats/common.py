"""What every file of the project shares: the ``format``/``version`` stamp and its check, and the CSV toolkit.

Every JSON output carries ``"format": "rectify-stereo/<name>"`` and an integer ``"version"``
(:func:`stamp`); readers (:func:`check_format`, the one check of both packages) accept the unversioned
files of release 0.1.0 and reject a wrong format name or a version newer than this release reads,
naming the file and value.

CSV toolkit (the point tables of :mod:`rectify.formats.gcps` and :mod:`rectify.formats.tables`, and the
CSV files of :mod:`stereo.formats`): :func:`read_table_text` (UTF-8, byte-order mark dropped),
:func:`table_rows` (rows by header name, ``#`` comments, the ``# crs=`` line), :func:`load_table`,
:func:`need_columns`, :func:`cell_number` and :func:`no_duplicates`. Their errors name the file, the line
and the column: :class:`~rectify.errors.RasterIOError` for unreadable files,
:class:`~rectify.errors.InvalidInputError` for malformed content.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rectify.errors import InvalidInputError, RasterIOError

__all__ = [
    "FORMAT_PREFIX", "StrPath", "stamp", "check_format", "unstamped", "check_numbers",
    "read_table_text", "table_rows", "load_table", "need_columns", "cell_number", "finite_number", "no_duplicates",
]

#: Prefix of every ``format`` value written by this project.
FORMAT_PREFIX = "rectify-stereo/"

StrPath = str | os.PathLike[str]


# --------------------------------------------------------------------------- versioning
def stamp(name: str, version: int, body: Mapping[str, Any]) -> dict[str, Any]:
    """``{"format": "rectify-stereo/<name>", "version": version, **body}`` (the stamp comes first).

    >>> stamp("camera", 1, {"width": 4})
    {'format': 'rectify-stereo/camera', 'version': 1, 'width': 4}
    """
    out: dict[str, Any] = {"format": FORMAT_PREFIX + name, "version": int(version)}
    out.update({k: v for k, v in body.items() if k not in ("format", "version")})
    return out


def check_format(doc: Any, name: str, version: int, path: StrPath | None = None, *, what: str | None = None,
                 legacy: Mapping[str, int] | None = None, version_key: str = "version") -> int:
    """Check the ``format``/``version`` keys of a JSON document; return the version it was written with.

    Parameters
    ----------
    doc : object
        The parsed JSON.
    name : str
        Format name without the prefix (``"camera"``).
    version : int
        Newest version this release reads.
    path : path, optional
        The file, named in errors.
    what : str, optional
        Human name of the file in errors (default ``"<name> file"``).
    legacy : dict format value -> version, optional
        Older ``format`` values accepted, with the version they stand for when the file has none
        (e.g. ``{"rectify-transform": 1}``).
    version_key : str
        Key holding the version in unstamped files of release 0.1.0 (``"report_version"``).

    Returns
    -------
    int
        The file's version; 0 for an unversioned file of release 0.1.0.

    Raises
    ------
    InvalidInputError
        Not a JSON object, a different format, or a version newer than ``version``.
    """
    label = f"{what or name + ' file'}{'' if path is None else ' ' + repr(str(path))}"
    if not isinstance(doc, dict):
        raise InvalidInputError(f"{label} must hold a JSON object (expected a JSON object at the top level, "
                                f"got {type(doc).__name__})")
    legacy = dict(legacy or {})
    fmt = doc.get("format")
    if fmt is None:
        found = doc.get(version_key, doc.get("version", 0))
    elif fmt == FORMAT_PREFIX + name or fmt in legacy:
        found = doc.get("version", legacy.get(fmt, 0))
    else:
        raise InvalidInputError(f"{label} has format {fmt!r}; expected {FORMAT_PREFIX + name!r}")
    if isinstance(found, bool) or not isinstance(found, int) or found < 0:
        raise InvalidInputError(f"{label} has version {found!r}; expected an integer <= {version}")
    if found > version:
        raise InvalidInputError(f"{label} has version {found}, newer than this release reads (<= {version})")
    return found


def unstamped(doc: Mapping[str, Any]) -> dict[str, Any]:
    """``doc`` without its ``format`` and ``version`` keys."""
    return {k: v for k, v in doc.items() if k not in ("format", "version")}


# --------------------------------------------------------------------------- JSON numbers
_JSON_SHAPE_NAMES = {(): "a number", (2,): "a list of 2 numbers", (3,): "a list of 3 numbers",
                     (3, 3): "a 3 x 3 list of numbers"}


def _is_json_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def check_numbers(d: dict[str, Any], key: str, shape: tuple[int, ...], path: StrPath) -> None:
    """Refuse ``d[key]`` unless it is finite numbers of ``shape`` (strings and bools are not numbers).

    Raises
    ------
    InvalidInputError
        Naming the file, the key and the value.
    """
    v = d.get(key)

    def ok(x: Any, shp: tuple[int, ...]) -> bool:
        if not shp:
            return _is_json_number(x) and math.isfinite(x)
        return isinstance(x, list) and len(x) == shp[0] and all(ok(e, shp[1:]) for e in x)

    if not ok(v, shape):
        raise InvalidInputError(f"{str(path)!r}: `{key}` must be {_JSON_SHAPE_NAMES.get(shape, 'numbers')}; "
                                f"got {v!r}")


# --------------------------------------------------------------------------- CSV toolkit
def read_table_text(path: StrPath) -> str:
    """The text of a CSV table (UTF-8; a byte-order mark anywhere is dropped).

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    """
    p = Path(path)
    try:
        # utf-8-sig: spreadsheets write a byte-order mark before the header or the '# crs=' line
        return p.read_text(encoding="utf-8-sig").replace("\ufeff", "")
    except FileNotFoundError as err:
        raise RasterIOError(f"file not found: {str(p)!r}") from err
    except (OSError, UnicodeDecodeError) as err:
        raise RasterIOError(f"cannot read {str(p)!r}: {err}") from err


def table_rows(text: str, path: StrPath) -> tuple[list[dict[str, str]], list[int], str | None]:
    """Parse CSV text with comment lines; return rows, their line numbers and the crs comment.

    Lines starting with ``#`` are comments; ``# crs=...`` (or a QGIS ``CRS:`` header) gives the CRS.
    Rows are dicts keyed by the stripped header names, values stripped; ``path`` is named in errors.

    Raises
    ------
    InvalidInputError
        No header and no rows.
    """
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
    reader = csv.DictReader(io.StringIO("\n".join(text for _, text in data_lines)))
    reader.fieldnames = [f.strip() for f in (reader.fieldnames or [])]
    rows = [{k: (v or "").strip() for k, v in r.items() if k is not None} for r in reader]
    return rows, [no for no, _ in data_lines[1:]], crs


def load_table(path: StrPath, what: str) -> tuple[list[dict[str, str]], list[int], str | None, list[str]]:
    """Read a point table: its rows, their line numbers, the ``# crs=`` value and the header;
    raise when the file has a header but no ``what`` (``"GCP rows"``, ``"matches"``)."""
    rows, lines, crs = table_rows(read_table_text(path), path)
    if not rows:
        raise InvalidInputError(f"{str(path)!r} has a header but no {what}")
    return rows, lines, crs, list(rows[0].keys())


def need_columns(fields: list[str], required: tuple[str, ...], path: StrPath) -> None:
    """Raise :class:`InvalidInputError` naming the ``required`` columns missing from the header ``fields``."""
    missing = [f for f in required if f not in fields]
    if missing:
        raise InvalidInputError(f"{str(path)!r}: missing column(s) {missing}; header is {fields}")


def cell_number(row: dict[str, str], key: str, line: int, path: StrPath, *, allow_empty: bool = False) -> float:
    """The finite number in column ``key`` of a row (file line ``line``); NaN for an empty cell with
    ``allow_empty``; else :class:`InvalidInputError` naming the file, line and column."""
    s = row.get(key, "")
    if s == "" and allow_empty:
        return math.nan
    return finite_number(s, f"{str(path)!r} line {line}: column {key!r}")


def finite_number(value: str | float, label: str) -> float:
    """``value`` as a finite float; else :class:`InvalidInputError` "<label> is not a number|finite: <value>"."""
    try:
        v = float(value)
    except ValueError:
        raise InvalidInputError(f"{label} is not a number: {value!r}") from None
    if not math.isfinite(v):
        raise InvalidInputError(f"{label} is not finite: {value!r}")
    return v


def no_duplicates(ids: list[str], path: StrPath, what: str) -> None:
    """Raise :class:`InvalidInputError` naming the duplicated ``ids`` (``what``: ``"GCP id(s)"``)."""
    counts = Counter(ids)
    dup = {i for i, n in counts.items() if n > 1}
    if dup:
        raise InvalidInputError(f"{str(path)!r}: duplicate {what} {sorted(dup)}")
