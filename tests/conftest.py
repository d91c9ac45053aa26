"""Shared fixtures. Tests that need ../shared/data skip cleanly when it is absent."""

from __future__ import annotations

import gc
import os
import subprocess
from pathlib import Path

import matplotlib
import pytest

from tests.support.shared_data import shared_data_dir

matplotlib.use("Agg")

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = shared_data_dir()  # $RECTIFY_SHARED_DATA, else ../shared/data


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (set RECTIFY_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def ngi_pair(shared_data: Path) -> Path:
    p = shared_data / "ngi_strip05"
    if not (p / "3324c_2015_1004_05_0182_RGB.tif").is_file():
        pytest.skip(f"NGI pair not found under {p}")
    return p


@pytest.fixture(scope="session")
def dewitt(shared_data: Path) -> Path:
    p = shared_data / "dewitt_samples"
    if not p.is_dir():
        pytest.skip(f"Dewitt samples not found under {p}")
    return p


@pytest.fixture()
def small_disk(tmp_path: Path):
    """A 200 KiB tmpfs (root only; skipped otherwise); unmounted at teardown."""
    if os.geteuid() != 0:
        pytest.skip("a small tmpfs needs root")
    d = tmp_path / "small_disk"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {r.stderr.strip()}")
    try:
        yield d
    finally:
        gc.collect()  # a test's exception info keeps writers' frames (and their files) alive in cycles
        if subprocess.run(["umount", str(d)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)  # still busy: detach it anyway
