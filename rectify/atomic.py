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

from rectify.errors import InvalidInputError, RasterIOError, RectifyError

__all__ = ["check_output", "atomic_output", "atomic_write_text", "read_json", "read_text", "write_failure_reason",
           "apply_umask", "current_umask", "make_temp", "NO_SPACE"]

NO_SPACE = "no space left on device"
#: below this many free bytes on the destination's file system a write failure is blamed on a full disk
_NEARLY_FULL = 1 << 20


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
        if p.exists() and not overwrite:
            raise InvalidInputError(f"output {str(p)!r} appeared while writing; pass --overwrite")
        apply_umask(tmp_path)
        os.replace(tmp_path, p)
    except RasterIOError as err:
        _remove(tmp_path)
        msg = str(err)
        if str(tmp_path) in msg:  # name the destination, not the hidden temporary file
            raise RasterIOError(re.sub(re.escape(str(tmp_path)) + r"[^'\"]*", str(p), msg)) from err
        raise
    except RectifyError:
        _remove(tmp_path)
        raise
    except OSError as err:
        _remove(tmp_path)
        raise RasterIOError(f"cannot write {str(p)!r}: {write_failure_reason(err, p)}") from err
    except BaseException:
        _remove(tmp_path)
        raise


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


def read_json(path: str | os.PathLike[str], what: str = "JSON file") -> Any:
    """Parse a JSON file; ``what`` names it in errors ("camera file", ...).

    Raises
    ------
    RasterIOError
        If the file is missing or unreadable.
    InvalidInputError
        If it is not valid JSON.
    """
    p = Path(path)
    text = read_text(p, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise InvalidInputError(f"{what} {str(p)!r} is not valid JSON: {err}") from err
