"""The synthetic block of tests.support.block_synthetic: truth, visibility, blunders, control, speed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rectify.errors import InvalidInputError
from stereo.block.types import project_pixel
from tests.support.block_synthetic import default_camera, make_block


def test_block_layout_and_truth():
    b = make_block(0, camera=default_camera(distortion=True))
    t = b.tracks
    assert len(b.true_poses) == 18 and t.images[0] == "s0_000"
    kappas = np.array([p.angles[2] for p in b.true_poses])
    assert np.all(np.abs(kappas[:6]) < 0.05) and np.all(np.abs(np.abs(kappas[6:12]) - np.pi) < 0.05)
    assert (t.rays_per_point() >= 2).all()
    assert np.ptp(b.true_points[:, 2]) > 20.0  # relief
    for i, pose in enumerate(b.true_poses):
        m = t.obs_image == i
        pix = project_pixel(b.camera, pose, b.true_points[t.obs_point[m]])
        np.testing.assert_allclose(pix, b.true_pixels[m], atol=1e-9)
        assert (pix >= 0).all() and (pix[:, 0] <= 1999).all() and (pix[:, 1] <= 1499).all()
    noise = t.obs_pixel - b.true_pixels
    assert 0.4 < noise.std() < 0.6
    assert b.base_m == pytest.approx(80.0) and b.strip_spacing_m == pytest.approx(105.0)


def test_blunders_control_and_gnss():
    b = make_block(0, blunder_fraction=0.05, lever_arm_m=(0.0, 0.0, 1.0), ins_noise_rad=1e-3)
    t = b.tracks
    d = np.linalg.norm(t.obs_pixel - b.true_pixels, axis=1)
    assert (d[b.blunder_obs] >= 14).all()
    assert len(np.unique(t.obs_point[b.blunder_obs])) == len(b.blunder_obs)
    assert (t.rays_per_point()[t.obs_point[b.blunder_obs]] >= 4).all()
    c = b.control
    assert int((~c.check).sum()) == 5 and int(c.check.sum()) == 6
    assert set(c.ids) <= set(t.point_ids)
    assert np.abs(c.xyz - b.control_true).max() < 0.05
    ant = np.array([p.position + p.rotation @ [0.0, 0.0, 1.0] for p in b.true_poses])
    assert np.abs(b.gnss.position - ant).max() < 0.3
    assert b.gnss.angles is not None and b.gnss.sigma_rad is not None


def test_noise_seed_keeps_geometry():
    a, b = make_block(3, noise_seed=1), make_block(3, noise_seed=2)
    np.testing.assert_array_equal(a.true_points, b.true_points)
    assert not np.allclose(a.tracks.obs_pixel, b.tracks.obs_pixel)


def test_large_block_is_fast():
    t0 = time.perf_counter()
    b = make_block(0, strips=6, images_per_strip=40, n_points=40_000, forward_overlap=0.7, side_overlap=0.4)
    assert time.perf_counter() - t0 < 10.0
    assert len(b.true_poses) == 240 and b.tracks.n_obs > 150_000


@pytest.mark.parametrize("kw, match", [
    ({"strips": 0}, "needs >= 1 strip of >= 2 images; got 0 x 6"),
    ({"forward_overlap": 1.0}, "`forward_overlap` must be in \\[0, 1\\); got 1.0"),
    ({"side_overlap": -0.1}, "`side_overlap` must be in \\[0, 1\\); got -0.1"),
    ({"control_layout": "ring"}, "unknown control_layout 'ring'"),
])
def test_bad_block_arguments(kw, match):
    with pytest.raises(InvalidInputError, match=match):
        make_block(0, **kw)
