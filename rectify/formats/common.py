"""What every file of the project shares: the ``format``/``version`` stamp and its check, and the CSV toolkit.

Every JSON output carries ``"format": "rectify-stereo/<name>"`` and an integer ``"version"``
(:func:`stamp`); readers (:func:`check_format`, the one check of both packages) accept the unversioned
files of release 0.1.0 and reject a wrong format name or a version newer than this release reads,
naming the file and value.

CSV toolkit (the point tables of :mod:`rectify.formats.gcps` and :mod:`rectify.formats.tables`, and the
CSV files of :mod:`stereo.formats`): :class:`TableReader` (the point tables' reader: the file is read as a
stream, chunk by chunk, and the rows go straight into one float64 array per numeric column and one list
per text column, so that memory follows the size of the table, not of its text; a table of more rows
than its kind may have, :data:`MAX_POINT_ROWS` or :data:`MAX_MATCH_ROWS`, is refused while reading with
the limit named), :func:`read_table_text` (UTF-8, byte-order mark dropped), :func:`table_rows` (rows by
header name, ``#`` comments, the ``# crs=`` line; for small tables held as text), :func:`load_table`,
:func:`need_columns`, :func:`cell_number` and :func:`no_duplicates`. Their errors name the file, the line
and the column: :class:`~rectify.errors.RasterIOError` for unreadable files,
:class:`~rectify.errors.InvalidInputError` for malformed content.
"""

from __future__ import annotations

import contextlib
import csv
import gc
import io
import itertools
import math
import os
import re
from collections import Counter
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError, RasterIOError, RectifyError

__all__ = [
    "FORMAT_PREFIX", "StrPath", "stamp", "check_format", "unstamped", "check_numbers",
    "read_table_text", "table_rows", "load_table", "need_columns", "cell_number", "finite_number", "no_duplicates",
    "TableReader", "Columns", "MAX_POINT_ROWS", "MAX_MATCH_ROWS", "malformed",
]

#: Prefix of every ``format`` value written by this project.
FORMAT_PREFIX = "rectify-stereo/"

StrPath = str | os.PathLike[str]

#: the most rows a table of surveyed or hand-measured points may have: GCP, stereo control, block control and
#: pose CSVs (such tables hold hundreds or thousands of rows; more are refused while reading, the limit named,
#: so that neither the reading nor the adjustments and reports after it can exhaust the memory)
MAX_POINT_ROWS = 100_000
#: the most rows a table of measured points may have: matches, calibration observation and field CSVs, and
#: the tables read as dict rows (:func:`load_table`)
MAX_MATCH_ROWS = 1_000_000
#: rows parsed at a time by :class:`TableReader`
_CHUNK_ROWS = 65536


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
    if fmt is not None and not isinstance(fmt, str):
        raise InvalidInputError(f"{label} has format {fmt!r}; expected {FORMAT_PREFIX + name!r}")
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


@contextlib.contextmanager
def malformed(label: str) -> Iterator[None]:
    """Turn the built-in errors a reader meets in a malformed document into one line naming ``label``.

    Inside the block, a ``TypeError``, ``ValueError``, ``KeyError``, ``IndexError``, ``AttributeError`` or
    ``OverflowError`` (a string where a number belongs, ``int(None)``, a missing key, ``int(inf)``)
    becomes :class:`~rectify.errors.InvalidInputError` "<label> is malformed: <reason>"; the project's
    own errors pass unchanged. The readers check what they can by name first; this is the net under them.
    """
    try:
        yield
    except RectifyError:
        raise
    except KeyError as err:
        raise InvalidInputError(f"{label} is malformed: missing key {err}") from err
    except (TypeError, ValueError, IndexError, AttributeError, OverflowError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InvalidInputError(f"{label} is malformed: {reason}") from err


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

    The whole file is read: the point tables are read as a stream by :class:`TableReader`.

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


def _crs_comment(body: str) -> tuple[bool, str | None]:
    """Whether a comment line's text (after ``#``) gives the CRS, and the CRS it gives."""
    if body.lower().startswith("crs="):
        return True, body[4:].strip()
    if body.upper().startswith("CRS:"):  # QGIS .points header
        return True, body[4:].strip() or None
    return False, None


def table_rows(text: str, path: StrPath) -> tuple[list[dict[str, str]], list[int], str | None]:
    """Parse CSV text with comment lines; return rows, their line numbers and the crs comment.

    Lines starting with ``#`` are comments; ``# crs=...`` (or a QGIS ``CRS:`` header) gives the CRS.
    Rows are dicts keyed by the stripped header names, values stripped; ``path`` is named in errors.
    For small tables held as text; the point tables are read by :class:`TableReader`.

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
            found, value = _crs_comment(s.lstrip("#").strip())
            if found:
                crs = value
            continue
        data_lines.append((no, line))
    if not data_lines:
        raise InvalidInputError(f"{str(path)!r} has no header and no rows")
    try:
        reader = csv.DictReader(io.StringIO("\n".join(text for _, text in data_lines)))
        reader.fieldnames = [f.strip() for f in (reader.fieldnames or [])]
        rows = [{k: (v or "").strip() for k, v in r.items() if k is not None} for r in reader]
    except csv.Error as err:
        raise InvalidInputError(f"{str(path)!r} is not a readable CSV table: {err}") from None
    return rows, [no for no, _ in data_lines[1:]], crs


def load_table(path: StrPath, what: str, *, max_rows: int = MAX_MATCH_ROWS
               ) -> tuple[list[dict[str, str]], list[int], str | None, list[str]]:
    """Read a table as dict rows: its rows, their line numbers, the ``# crs=`` value and the header;
    raise when the file has a header but no ``what`` (``"residual rows"``) or more than ``max_rows`` rows.

    Every cell is kept as text: for small tables (the point tables use :class:`TableReader` directly).
    """
    with TableReader(path) as t:
        cols = t.read(what, texts=t.fields, max_rows=max_rows)
    fields = list(dict.fromkeys(cols.fields))
    values = [cols.texts[f] for f in fields]
    rows = [dict(zip(fields, r, strict=True)) for r in zip(*values, strict=True)]
    return rows, cols.lines.tolist(), cols.crs, fields


@dataclass(frozen=True, eq=False)
class Columns:
    """The columns of a CSV table read by :meth:`TableReader.read`.

    Attributes
    ----------
    path : Path
    fields : tuple of str
        The header, names stripped.
    lines : (N,) int64
        The file line (1-based) where each row starts.
    numbers : dict str -> (N,) float64
        The numeric columns asked for: finite numbers, NaN for an empty cell where allowed.
    texts : dict str -> list of str
        The text columns asked for, cells stripped ("" for a missing cell).
    crs : str or None
        The ``# crs=`` (or QGIS ``CRS:``) comment line's value; the last one wins.
    settings : tuple of (line, key, value)
        Every ``# key=value`` comment line, key lower-case, key and value stripped, in file order.
    """

    path: Path
    fields: tuple[str, ...]
    lines: NDArray[np.int64]
    numbers: dict[str, NDArray[np.float64]]
    texts: dict[str, list[str]]
    crs: str | None
    settings: tuple[tuple[int, str, str], ...]

    def __len__(self) -> int:
        return int(self.lines.size)


#: a line of a block that is not a data line: a comment or a blank line
_SKIP_LINE = re.compile(r"^[^\S\n]*(?:#|\n)", re.MULTILINE)
#: characters of text read at a time by :class:`TableReader`
_BLOCK_CHARS = 1 << 20


class TableReader:
    """A CSV table read as a stream: the header first, then the columns asked for.

    ``with TableReader(path) as t:`` opens the file and reads up to the header (``t.fields``);
    :meth:`read` then reads the rows chunk by chunk into arrays. Lines starting with ``#`` are comments
    (anywhere in the file); ``# crs=...`` (or a QGIS ``CRS:`` header) gives the CRS and every
    ``# key=value`` line is kept (:attr:`Columns.settings`); blank lines are skipped; a byte-order mark
    anywhere is dropped; quoted cells may hold commas and line breaks.

    Memory: the numbers of a row take 8 bytes a column, its text cells a Python string each; the text of
    the file is never held whole (it is read in blocks of about a mebibyte). A table of more rows than
    ``max_rows`` is refused as soon as the reader passes the limit, so that a huge file costs neither the
    memory nor the time of reading it.

    Raises
    ------
    RasterIOError
        The file is missing, unreadable or not UTF-8 text.
    InvalidInputError
        No header, a malformed CSV line, too many rows, a bad number (file, line, column and value named).
    """

    def __init__(self, path: StrPath, *, lower: bool = False) -> None:
        self.path = Path(path)
        self._label = repr(str(self.path))
        self._crs: str | None = None
        self._settings: list[tuple[int, str, str]] = []
        self._no = 0  # file lines read
        self._data = 0  # data lines handed to the CSV parser
        # data line -> file line: data line d is file line seg_line[j] + d - seg_data[j] (j: last seg_data <= d)
        self._seg_data: list[int] = []
        self._seg_line: list[int] = []
        self._parsed = 0  # data lines the CSV parser consumed before the current chunk
        try:
            self._fh = open(self.path, encoding="utf-8-sig", newline=None)  # noqa: SIM115 (closed by close())
        except FileNotFoundError as err:
            raise RasterIOError(f"file not found: {self._label}") from err
        except OSError as err:
            raise RasterIOError(f"cannot read {self._label}: {err.strerror or err}") from err
        try:
            self._reader = csv.reader(self._data_lines())
            header = self._rows(1)
            if not header:
                raise InvalidInputError(f"{self._label} has no header and no rows")
            self._parsed = self._reader.line_num
            self.fields: tuple[str, ...] = tuple(f.strip().lower() if lower else f.strip() for f in header[0])
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> TableReader:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        self._fh.close()

    def _data_lines(self) -> Iterator[str]:
        """The file's data lines for the CSV parser: comments noted and dropped, blank lines dropped."""
        try:
            while True:
                block = self._fh.readlines(_BLOCK_CHARS)
                if not block:
                    return
                text = "".join(block)
                if "\ufeff" not in text and _SKIP_LINE.search(text) is None and block[-1].strip():
                    self._segment(self._no + 1)  # every line of the block is a data line
                    self._no += len(block)
                    self._data += len(block)
                    yield from block
                    continue
                for line in block:
                    self._no += 1
                    line = line.replace("\ufeff", "")
                    s = line.strip()
                    if not s:
                        continue
                    if s[0] == "#":
                        self._comment(s.lstrip("#").strip())
                        continue
                    if not self._seg_data or self._seg_line[-1] + self._data - self._seg_data[-1] != self._no:
                        self._segment(self._no)
                    self._data += 1
                    yield line
        except UnicodeDecodeError as err:
            raise RasterIOError(f"cannot read {self._label}: not UTF-8 text after line {self._no} "
                                f"({err.reason})") from None
        except OSError as err:
            raise RasterIOError(f"cannot read {self._label}: {err.strerror or err}") from err

    def _segment(self, line: int) -> None:
        self._seg_data.append(self._data)
        self._seg_line.append(line)

    def _comment(self, body: str) -> None:
        found, value = _crs_comment(body)
        if found:
            self._crs = value
        key, sep, val = body.partition("=")
        if sep:
            self._settings.append((self._no, key.strip().lower(), val.strip()))

    def _rows(self, n: int) -> list[list[str]]:
        try:
            return list(itertools.islice(self._reader, n))
        except csv.Error as err:
            raise InvalidInputError(f"{self._label} line {self._no}: not a readable CSV line: {err}") from None

    def read(self, what: str, *, numbers: Sequence[str] = (), texts: Sequence[str] = (),
             empty: Collection[str] = (), max_rows: int = MAX_POINT_ROWS) -> Columns:
        """Read the rows: the ``numbers`` columns as float64 arrays, the ``texts`` columns as lists of str.

        Parameters
        ----------
        what : str
            The rows' name in errors (``"GCP rows"``).
        numbers, texts : sequence of str
            Column names; a column missing from the header, or a cell missing from a short row, reads
            as an empty cell.
        empty : collection of str
            Numeric columns whose empty cells read as NaN (elsewhere an empty cell is an error).
        max_rows : int
            The most rows the table may have.

        Raises
        ------
        InvalidInputError
            A header but no rows, more than ``max_rows`` rows, a cell of ``numbers`` that is not a finite
            number (file, line, column and value named).
        """
        collecting = gc.isenabled()
        gc.disable()  # rows make no reference cycles: the collector would only walk them again and again
        try:
            return self._read(what, numbers, texts, empty, max_rows)
        finally:
            if collecting:
                gc.enable()

    def _read(self, what: str, numbers: Sequence[str], texts: Sequence[str], empty: Collection[str],
              max_rows: int) -> Columns:
        index = {f: i for i, f in enumerate(self.fields)}  # a repeated name: the last column (as csv.DictReader)
        nf = len(self.fields)
        num_parts: dict[str, list[NDArray[np.float64]]] = {k: [] for k in numbers}
        text_cols: dict[str, list[str]] = {k: [] for k in texts}
        line_parts: list[NDArray[np.int64]] = []
        n = 0
        while True:
            rows = self._rows(_CHUNK_ROWS)
            if not rows:
                break
            lines = self._row_lines(rows)
            n += len(rows)
            if n > max_rows:
                extra = int(lines[max_rows - (n - len(rows))])
                raise InvalidInputError(f"{self._label} has more than {max_rows} {what} (row {max_rows + 1} is on line "
                                        f"{extra}): {max_rows} is the most such a table may have")
            if max(map(len, rows)) > nf:  # cells past the header are ignored (as csv.DictReader)
                rows = [r[:nf] for r in rows]
            columns = list(itertools.zip_longest(*rows, fillvalue=""))  # short rows padded with empty cells
            blank = ("",) * len(rows)
            for k, parts in num_parts.items():
                i = index.get(k)
                parts.append(self._numbers(columns[i] if i is not None and i < len(columns) else blank, k, lines,
                                           allow_empty=k in empty))
            for k, cells in text_cols.items():
                i = index.get(k)
                cells.extend([c.strip() for c in columns[i]] if i is not None and i < len(columns) else blank)
            line_parts.append(lines)
            del rows, columns
        if n == 0:
            raise InvalidInputError(f"{self._label} has a header but no {what}")
        arrays = {}
        for k in list(num_parts):
            arrays[k] = np.concatenate(num_parts.pop(k))
        return Columns(self.path, self.fields, np.concatenate(line_parts), arrays, text_cols, self._crs,
                       tuple(self._settings))

    def _row_lines(self, rows: list[list[str]]) -> NDArray[np.int64]:
        """The file line where each row of a chunk starts (a quoted cell may hold line breaks)."""
        start, stop = self._parsed, self._reader.line_num
        self._parsed = stop
        if stop - start == len(rows):
            first = np.arange(start, stop, dtype=np.int64)
        else:  # a row spans one data line more for each line break in its cells
            spans = np.fromiter((1 + sum(c.count("\n") for c in r) for r in rows), dtype=np.int64, count=len(rows))
            first = start + np.cumsum(spans) - spans
        seg_data = np.array(self._seg_data, dtype=np.int64)
        j = np.searchsorted(seg_data, first, side="right") - 1
        out = np.array(self._seg_line, dtype=np.int64)[j] + first - seg_data[j]
        keep = max(int(j[-1]) if j.size else 0, 0)  # segments before the last one used are done with
        del self._seg_data[:keep], self._seg_line[:keep]
        return out

    def _numbers(self, col: Sequence[str], key: str, lines: NDArray[np.int64], *, allow_empty: bool
                 ) -> NDArray[np.float64]:
        try:
            v = np.array(col, dtype=np.float64)
            if np.isfinite(v).all():
                return v
        except ValueError:
            pass
        out = np.empty(len(col))  # a bad, empty or non-finite cell: cell by cell, the first bad one named
        for j, cell in enumerate(col):
            c = cell.strip()
            out[j] = math.nan if c == "" and allow_empty else \
                finite_number(c, f"{self._label} line {int(lines[j])}: column {key!r}")
        return out


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


def no_duplicates(ids: Sequence[str], path: StrPath, what: str) -> None:
    """Raise :class:`InvalidInputError` naming the duplicated ``ids`` (``what``: ``"GCP id(s)"``).

    Ids are compared by their hashes first (sorted int64), so that a table of millions of ids needs
    three int64 arrays, not a dictionary of its ids.
    """
    n = len(ids)
    if n < 2:
        return
    h = np.fromiter(map(hash, ids), dtype=np.int64, count=n)
    order = np.argsort(h, kind="stable")
    hs = h[order]
    same = np.flatnonzero(hs[1:] == hs[:-1])
    if not same.size:
        return
    candidates = np.unique(np.concatenate([order[same], order[same + 1]]))
    counts = Counter(ids[int(i)] for i in candidates)
    dup = {i for i, c in counts.items() if c > 1}
    if dup:
        listed = sorted(dup)
        more = f" and {len(listed) - 20} more" if len(listed) > 20 else ""
        raise InvalidInputError(f"{str(path)!r}: duplicate {what} {listed[:20]}{more}")
