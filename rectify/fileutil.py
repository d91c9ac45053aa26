"""Outputs that appear whole or not at all.

Every writer goes through :func:`atomic_output`: data are written to a
temporary file in the destination folder and renamed over the destination
only when the writer finished without error, so a failure never leaves a
partial file and an existing output is replaced only with ``overwrite``.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .errors import InvalidInputError, RasterIOError

__all__ = ["check_output", "atomic_output", "atomic_write_text", "read_json"]


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
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=suffix if suffix is not None else p.suffix + ".part",
                               dir=p.parent if str(p.parent) else ".")
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if p.exists() and not overwrite:
            raise InvalidInputError(f"output {str(p)!r} appeared while writing; pass --overwrite")
        os.replace(tmp_path, p)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str, *, overwrite: bool = False) -> Path:
    """Write ``text`` to ``path`` atomically; return the path."""
    with atomic_output(path, overwrite=overwrite) as tmp:
        tmp.write_text(text)
    return Path(path)


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
    try:
        text = p.read_text()
    except FileNotFoundError as err:
        raise RasterIOError(f"cannot read {what} {str(p)!r}: file not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise RasterIOError(f"cannot read {what} {str(p)!r}: {err}") from err
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise InvalidInputError(f"{what} {str(p)!r} is not valid JSON: {err}") from err
