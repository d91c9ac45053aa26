"""Smoke test of ``scripts/bench_bundle.py`` outside the solvers: the synthetic block, the common
RMS, the COLMAP conventions and the message when pycolmap is missing."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from tests.support.scripts_support import load_script


@pytest.fixture(scope="module")
def bb():
    return load_script("bench_bundle")


@pytest.fixture(scope="module")
def block(bb):
    return bb.make_block("small", 3, 0.7)


def test_small_block_sizes_and_tracks(bb, block):
    assert block.R0.shape == (49, 3, 3) and block.X0.shape == (7800, 3)
    rays = np.bincount(block.obs_point, minlength=7800)
    assert rays.min() >= 2 and rays.max() <= 4
    assert 28_000 <= len(block.obs_point) <= 31_200
    assert np.bincount(block.obs_image, minlength=49).min() >= 50
    # sorted by point, then image; no point twice in one image
    key = block.obs_point * 49 + block.obs_image
    assert np.all(np.diff(key) > 0)
    assert len(block.control) == 5 and np.array_equal(block.X0[block.control], block.X_true[block.control])


def test_rms_at_truth_is_the_noise_and_start_is_perturbed(bb, block):
    assert bb.reprojection_rms(block, block.R_true, block.C_true, block.X_true) == pytest.approx(0.7, rel=0.03)
    assert bb.reprojection_rms(block, block.R0, block.C0, block.X0) > 5.0


def test_projection_matches_project_pixel(bb, block):
    from rectify.geometry.camera import Camera
    from stereo.block.types import Pose, project_pixel

    cam = Camera(**bb.CAMERA)
    i = 20
    sel = np.flatnonzero(block.obs_image == i)
    X = block.X_true[block.obs_point[sel]]
    ours = project_pixel(cam, Pose("a", "c", block.C_true[i], block.R_true[i]), X)
    n = len(X)
    mine, depth = bb.project(np.repeat(block.R_true[i][None], n, 0), np.repeat(block.C_true[i][None], n, 0), X, cam)
    assert np.abs(ours - mine).max() < 1e-9 and np.all(depth > 0)


def test_rodrigues_is_a_rotation(bb):
    R = bb.rodrigues(np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [1e-14, 0.0, 0.0]]))
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(R[0], np.eye(3))


def test_colmap_conventions(bb, block):
    pycolmap = pytest.importorskip("pycolmap")
    assert bb.check_conventions(pycolmap, block) < 1e-6
    R, C = bb.pose_from_colmap(bb.cam_from_world(pycolmap, block.R_true[5], block.C_true[5]))
    assert np.allclose(R, block.R_true[5], atol=1e-12) and np.allclose(C, block.C_true[5], atol=1e-9)


def test_missing_pycolmap_is_one_line(bb, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pycolmap" else real(name, *a))
    with pytest.raises(SystemExit) as exc:
        bb.main(["--block", "small"])
    msg = str(exc.value.code)
    assert 'pip install -e ".[bench]"' in msg and "\n" not in msg


def test_peak_rss_is_this_process_high_water_mark(bb):
    """VmHWM of this process (not ru_maxrss, which Linux carries from a parent through fork and exec)."""
    peak, now = bb._peak_mb(), bb._rss_mb()
    assert peak >= now * 0.99 and peak > 10
    a = np.ones(200_000_000 // 8)  # 200 MB touched: far above the churn of a long test session
    rss = bb._rss_mb()
    assert bb._peak_mb() >= rss * 0.99
    assert rss >= now + 150
    del a
