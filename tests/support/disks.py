"""Small disks for the full-disk tests: a tmpfs of a few hundred KiB mounted on a test's folder."""

from __future__ import annotations

import contextlib
import gc
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def mounted_tmpfs(d: Path, size: str) -> Iterator[Path]:
    """Mount a tmpfs of ``size`` (``"200k"``) on the new folder ``d`` (root only: the test is skipped otherwise);
    unmounted on leaving (lazily when still busy)."""
    if os.geteuid() != 0:
        pytest.skip("a small tmpfs needs root")
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {r.stderr.strip()}")
    try:
        yield d
    finally:
        gc.collect()  # a test's exception info keeps writers' frames (and their files) alive in cycles
        if subprocess.run(["umount", str(d)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)  # still busy: detach it anyway
