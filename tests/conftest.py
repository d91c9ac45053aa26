"""Shared fixtures. Tests that need ../shared/data skip cleanly when it is absent."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import pytest

from tests.support.disks import mounted_tmpfs
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
    with mounted_tmpfs(tmp_path / "small_disk", "200k") as d:
        yield d
