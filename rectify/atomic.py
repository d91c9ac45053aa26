"""Outputs that appear whole or not at all.

Every writer goes through :func:`atomic_output`: data are written to a
temporary file in the destination folder and renamed over the destination
only when the writer finished without error, so a failure never leaves a
partial file and an existing output is replaced only with ``overwrite``.

Temporary files are named ``.<name>.<random><suffix>.part`` beside the destination. A run killed
with SIGKILL (no chance to clean up) may leave such a file behind: it is never read by any command
and can be deleted. Outputs get the permissions of a normal file (``0o666`` minus the umask), not
the ``0o600`` of :func:`tempfile.mkstemp`. A write failure is reported as :class:`RasterIOError`
naming the file and the reason ("no space left on device" when the disk is full).

Every JSON file of both packages is read by :func:`read_json` (or, for text already read, parsed by
:func:`parse_json`): a file larger than :data:`JSON_MAX_BYTES` or nesting arrays and objects deeper
than :data:`JSON_MAX_DEPTH` levels is refused before parsing, with one line naming the file and the
limit, so that no JSON file can exhaust the memory or the parser's recursion.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rectify.errors import InvalidInputError, RasterIOError, RectifyError

__all__ = ["note_termination", "terminated", "raise_if_terminated", "naming_destination",
           "check_output", "atomic_output", "atomic_write_text", "read_json", "parse_json", "json_depth",
           "check_nesting", "read_text",
           "write_failure_reason", "apply_umask", "current_umask", "make_temp", "NO_SPACE", "JSON_MAX_BYTES",
           "JSON_MAX_DEPTH"]

NO_SPACE = "no space left on device"
#: below this many free bytes on the destination's file system a write failure is blamed on a full disk
_NEARLY_FULL = 1 << 20
#: the largest JSON file read (bytes): parsed, JSON takes up to eight times its size in memory (an OpenSfM
#: reconstruction of 190 MiB: 1.5 GB), so that reading one stays within 2 GB
JSON_MAX_BYTES = 200 * 1024 * 1024
#: the deepest nesting of arrays and objects in a JSON file read (the project's files nest 6 levels or fewer)
JSON_MAX_DEPTH = 64


def write_failure_reason(err: BaseException | None, path: str | os.PathLike[str] | None = None) -> str:
    """A short reason for a failed write: ``"no space left on device"`` when that is the cause.

    The cause is found from ``errno`` (ENOSPC, EDQUOT), from the text of the error and its chain
    (GDAL reports libtiff's failures as text), or from the free space left beside ``path``.
    """
    e: BaseException | None = err
    while e is not None:
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
            return NO_SPACE
        if "no space left" in str(e).lower():
            return NO_SPACE
        e = e.__cause__ or e.__context__
    if path is not None:
        p = Path(path)
        folder = p.parent if str(p.parent) else Path(".")
        with contextlib.suppress(OSError):
            if shutil.disk_usage(folder).free < _NEARLY_FULL:
                return NO_SPACE
    if isinstance(err, OSError) and err.strerror:
        return str(err.strerror).lower()
    return str(err) if err is not None else "write failed"


def current_umask() -> int:
    """The process umask (read without changing it for longer than a call)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def apply_umask(path: str | os.PathLike[str]) -> None:
    """Give a finished temporary file the mode a new file would have (``0o666 & ~umask``)."""
    with contextlib.suppress(OSError):
        os.chmod(path, 0o666 & ~current_umask())


def check_output(path: str | os.PathLike[str], *, overwrite: bool) -> Path:
    """Validate an output path before any work is done.

    Raises
    ------
    InvalidInputError
        If ``path`` exists and ``overwrite`` is false, or is a directory.
    RasterIOError
        If its folder does not exist or is not writable.
    """
    p = Path(path)
    if p.is_dir():
        raise InvalidInputError(f"output {str(p)!r} is a directory")
    if p.exists() and not overwrite:
        raise InvalidInputError(f"output {str(p)!r} exists; pass --overwrite to replace it")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise RasterIOError(f"output folder {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK):
        raise RasterIOError(f"output folder {str(parent)!r} is not writable")
    return p


_TERMINATED: list[int] = []  # the signal number once SIGTERM (or another terminating signal) arrived


def note_termination(signum: int) -> None:
    """Record that the process was asked to terminate (by the command line's SIGTERM handler).

    The handler also raises ``SystemExit``, but an exception raised while Python runs a callback whose
    exceptions are only reported (a garbage-collector callback, a ``__del__``) is swallowed; every commit
    of an output therefore checks this record again with :func:`raise_if_terminated`, so a terminated run
    never publishes its outputs.
    """
    if not _TERMINATED:
        _TERMINATED.append(int(signum))


def terminated() -> bool:
    """True once :func:`note_termination` was called in this process."""
    return bool(_TERMINATED)


def raise_if_terminated() -> None:
    """Raise ``SystemExit(128 + signum)`` when :func:`note_termination` was called; else do nothing."""
    if _TERMINATED:
        raise SystemExit(128 + _TERMINATED[0])


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], *, overwrite: bool = False,
                  suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    On any exception the temporary file is removed and ``path`` is untouched.
    """
    p = check_output(path, overwrite=overwrite)
    tmp_path = make_temp(p, suffix)
    try:
        yield tmp_path
        raise_if_terminated()
        if p.exists() and not overwrite:
            raise InvalidInputError(f"output {str(p)!r} appeared while writing; pass --overwrite")
        apply_umask(tmp_path)
        os.replace(tmp_path, p)
    except RectifyError as err:
        _remove(tmp_path)
        renamed = naming_destination(err, tmp_path, p)
        if renamed is not None:
            raise renamed from err
        raise
    except OSError as err:
        _remove(tmp_path)
        raise RasterIOError(f"cannot write {str(p)!r}: {write_failure_reason(err, p)}") from err
    except BaseException:
        _remove(tmp_path)
        raise


def naming_destination(err: BaseException, tmp: Path, dst: Path) -> RectifyError | None:
    """The project error ``err`` (of the same class) naming ``dst`` where its message names the hidden temporary
    file ``tmp`` written for it (with anything GDAL appended to that name, up to the closing quote); None when
    ``err`` is not a project error or does not name ``tmp``."""
    if not isinstance(err, RectifyError) or str(tmp) not in str(err):
        return None
    return type(err)(re.sub(re.escape(str(tmp)) + r"[^'\"]*", str(dst), str(err)))


def make_temp(path: Path, suffix: str | None = None) -> Path:
    """Create the hidden temporary file ``.<name>.<random><suffix>`` beside ``path`` (default suffix ``<ext>.part``)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.",
                                   suffix=suffix if suffix is not None else path.suffix + ".part",
                                   dir=path.parent if str(path.parent) else ".")
    except OSError as err:
        raise RasterIOError(f"cannot write {str(path)!r}: {write_failure_reason(err, path)}") from err
    os.close(fd)
    return Path(tmp)


def _remove(path: Path) -> None:
    with contextlib.suppress(OSError):
        path.unlink()


def atomic_write_text(path: str | os.PathLike[str], text: str, *, overwrite: bool = False) -> Path:
    """Write ``text`` to ``path`` atomically; return the path."""
    with atomic_output(path, overwrite=overwrite) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
    return Path(path)


def read_text(path: str | Path, what: str = "file") -> str:
    """Read a text file; ``what`` names it in errors ("camera file", ...).

    Raises
    ------
    RasterIOError
        If the file is missing or unreadable.
    """
    p = Path(path)
    try:
        return p.read_text()
    except FileNotFoundError as err:
        raise RasterIOError(f"cannot read {what} {str(p)!r}: file not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise RasterIOError(f"cannot read {what} {str(p)!r}: {err}") from err


def read_json(path: str | os.PathLike[str], what: str = "JSON file", *, max_bytes: int = JSON_MAX_BYTES,
              max_depth: int = JSON_MAX_DEPTH) -> Any:
    """Parse a JSON file (UTF-8, a byte-order mark allowed); ``what`` names it in errors ("camera file", ...).

    The file is refused before parsing when it holds more than ``max_bytes`` bytes or nests arrays and
    objects deeper than ``max_depth`` levels (:func:`parse_json`).

    Raises
    ------
    RasterIOError
        If the file is missing or unreadable.
    InvalidInputError
        If it is too large, too deeply nested, not UTF-8 or not valid JSON (one line naming the file).
    """
    p = Path(path)
    label = f"{what} {str(p)!r}"
    try:
        with open(p, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > max_bytes:
                raise InvalidInputError(f"{label} holds {size} bytes, more than the {max_bytes} bytes a JSON file may "
                                        "have")
            data = fh.read(max_bytes + 1)  # a pipe or special file has no size: read one byte past the limit
    except FileNotFoundError as err:
        raise RasterIOError(f"cannot read {label}: file not found") from err
    except IsADirectoryError as err:
        raise RasterIOError(f"cannot read {label}: is a directory") from err
    except OSError as err:
        raise RasterIOError(f"cannot read {label}: {err.strerror or err}") from err
    if len(data) > max_bytes:
        raise InvalidInputError(f"{label} holds more than the {max_bytes} bytes a JSON file may have")
    return parse_json(data, label, max_depth=max_depth)


def parse_json(data: bytes | str, label: str, *, max_depth: int = JSON_MAX_DEPTH) -> Any:
    """Parse JSON text, refusing nesting deeper than ``max_depth`` before the parser sees it.

    ``label`` names the source in errors (``"camera file 'cam.json'"``). Bytes must be UTF-8 (a leading
    byte-order mark is dropped).

    Raises
    ------
    InvalidInputError
        Too deeply nested, not UTF-8, not valid JSON (or a number Python cannot hold, e.g. an integer of
        more than 4300 digits).
    """
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    check_nesting(raw, label, max_depth=max_depth)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise InvalidInputError(f"{label} is not UTF-8 text: byte {err.start} is {raw[err.start:err.start + 1]!r}"
                                ) from None
    del raw
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise InvalidInputError(f"{label} is not valid JSON: {err}") from None
    except (ValueError, RecursionError) as err:  # e.g. an integer of more than 4300 digits
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InvalidInputError(f"{label} is not valid JSON: {msg}") from None


def check_nesting(data: bytes | str, label: str, *, max_depth: int = JSON_MAX_DEPTH) -> None:
    """Refuse text nesting arrays and objects deeper than ``max_depth`` levels (:func:`json_depth`): JSON, and
    the flow style (``[...]``, ``{...}``) of YAML, before a recursive parser sees it.

    Raises
    ------
    InvalidInputError
        "<label> nests arrays and objects more than <max_depth> levels deep".
    """
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    if json_depth(raw, max_depth) > max_depth:
        raise InvalidInputError(f"{label} nests arrays and objects more than {max_depth} levels deep "
                                f"(the most a JSON file may have)")


#: the bytes that matter to nesting: '"', '[', ']', '{', '}'
_JSON_STRUCTURAL = np.zeros(256, dtype=bool)
_JSON_STRUCTURAL[[34, 91, 93, 123, 125]] = True
_JSON_DELTA = np.zeros(256, dtype=np.int64)
_JSON_DELTA[[91, 123]] = 1
_JSON_DELTA[[93, 125]] = -1
_SCAN_CHUNK = 1 << 22


def json_depth(data: bytes, stop: int | None = None, *, chunk: int = _SCAN_CHUNK) -> int:
    r"""The deepest nesting of arrays and objects in JSON text (UTF-8 bytes); brackets inside strings
    (escaped quotes included) do not count.

    The scan is vectorised over chunks of ``chunk`` bytes (4 MiB) and needs memory proportional to a
    chunk, not to the text. It stops as soon as the depth passes ``stop``. For text that is not valid
    JSON the number is at least the nesting of its longest valid beginning, all a parser could reach.

    >>> json_depth(b'{"a": [1, [2, "]]]"], {"b": "\\\"[["}]}')
    3
    """
    a = np.frombuffer(data, dtype=np.uint8)
    depth = deepest = 0
    in_string = False
    carry = 0  # length of the run of backslashes that ends the previous chunk
    for start in range(0, a.size, chunk):
        c = a[start:start + chunk]
        pos = np.flatnonzero(_JSON_STRUCTURAL[c])
        b = np.flatnonzero(c == 92)
        run_start = b
        if b.size:  # first backslash of the run each backslash belongs to
            new_run = np.empty(b.size, dtype=bool)
            new_run[0] = True
            np.not_equal(np.diff(b), 1, out=new_run[1:])
            run_start = b[new_run][np.cumsum(new_run) - 1]
        if pos.size:
            kind = c[pos]
            quote = kind == 34
            if b.size or carry:
                # a quote after an odd run of backslashes is escaped: it neither opens nor closes a string
                q = pos[quote]
                run = np.where(q == 0, carry, 0)
                if b.size:
                    k = np.maximum(np.searchsorted(b, q) - 1, 0)
                    adjacent = b[k] == q - 1
                    run = np.where(adjacent, q - run_start[k] + np.where(run_start[k] == 0, carry, 0), run)
                keep = np.ones(pos.size, dtype=bool)
                keep[np.flatnonzero(quote)] = run % 2 == 0
                kind, quote = kind[keep], quote[keep]
            inside = ((np.cumsum(quote) - quote) % 2 == 1) != in_string
            level = depth + np.cumsum(np.where(inside | quote, 0, _JSON_DELTA[kind]))
            if level.size:
                deepest = max(deepest, int(level.max()))
                depth = int(level[-1])
            in_string ^= bool(int(quote.sum()) % 2)
            if stop is not None and deepest > stop:
                return deepest
        if b.size and b[-1] == c.size - 1:
            carry = int(c.size - run_start[-1]) + (carry if run_start[-1] == 0 else 0)
        else:
            carry = 0
    return deepest
