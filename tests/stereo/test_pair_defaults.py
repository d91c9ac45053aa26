"""Issue 12: the pair defaults. Absolute orientation is robust (Tukey) by default and survives bad control
points; the stereo demo keeps least squares (its figures are the README's); stereo pairs are matched with
fundamental-matrix verification, and `stereo run` / `stereo orient` expose the matcher options."""

from __future__ import annotations

import numpy as np
import pytest

from rectify.geometry.points import ControlTable
from rectify.geometry.residuals import rms
from stereo.actions.common import ORIENT_MATCHER, PAIR_MATCHER, matcher_config
from stereo.actions.scene import make_scene
from stereo.cli.main import cli as stereo_cli
from stereo.pair.model import ModelOptions, build_model, match_control
from stereo.relative import RelativeGeometry, RelativeOrientation


@pytest.fixture(scope="module")
def scene():
    return make_scene(0, size_px=480)


def _check_rmse(scene, robust, seed=3, n_tie=250, n_ctrl=10, n_chk=30, n_bad=2):
    rng = np.random.default_rng(seed)
    n = n_tie + n_ctrl + n_chk
    g = scene.random_ground_points(n, rng)
    cam = scene.camera
    pl = scene.pixel_from_ground(scene.left, g) + rng.normal(0, 0.3, (n, 2))
    pr = scene.pixel_from_ground(scene.right, g) + rng.normal(0, 0.3, (n, 2))
    ids = [f"t{i}" for i in range(n_tie)]
    ro = RelativeOrientation.from_pixels(pl[:n_tie], pr[:n_tie], cam, ids=ids)
    gc = g[n_tie:].copy()
    gc[:n_bad] += np.array([[25.0, -20.0, 30.0], [-30.0, 15.0, -25.0]])[:n_bad]   # blundered control points
    cids = [f"c{i}" for i in range(n_ctrl + n_chk)]
    ctrl = ControlTable(tuple(cids), pl[n_tie:], pr[n_tie:], gc, crs=scene.crs)
    opts = ModelOptions(check_ids=tuple(cids[n_ctrl:])) if robust is None else \
        ModelOptions(check_ids=tuple(cids[n_ctrl:]), robust=robust)
    m = build_model(cam.photo_from_pixel(pl[:n_tie]), cam.photo_from_pixel(pr[:n_tie]),
                    RelativeGeometry.from_relative(ro), ids=ids, control=ctrl, control_mm=match_control(ctrl, cam),
                    options=opts, pixel_size_mm=cam.pixel_size_mm)
    e = m.ground[m.is_check] - g[n_tie + n_ctrl:]
    return rms(np.linalg.norm(e, axis=1))


def test_robust_absolute_orientation_is_the_default(scene):
    assert ModelOptions().robust == "tukey"
    clean = _check_rmse(scene, "none", n_bad=0)
    lsq = _check_rmse(scene, "none")
    default = _check_rmse(scene, None)
    # least squares is pulled off by the two blunders; the default stays at the clean figure
    assert lsq > 1.5 * clean and default < 1.1 * clean, (clean, lsq, default)


def test_stereo_demo_keeps_least_squares():
    import inspect

    import stereo.actions.demo as sa

    assert 'robust="none"' in inspect.getsource(sa.demo)


def test_pair_matcher_defaults_and_options():
    assert PAIR_MATCHER.verify == "fundamental"
    c = matcher_config(detector="orb", verify="homography", refine=False, max_matches=500, max_keypoints=3000)
    assert (c.detector, c.verify, c.refine, c.max_matches, c.max_keypoints) == ("orb", "homography", False, 500,
                                                                                 3000)
    assert matcher_config() == PAIR_MATCHER
    # stereo orient LEFT RIGHT: capped keypoints and matches (speed; a relative orientation needs few)
    assert (ORIENT_MATCHER.verify, ORIENT_MATCHER.max_keypoints, ORIENT_MATCHER.max_matches) == ("fundamental",
                                                                                              12000, 4000)
    assert matcher_config(base=ORIENT_MATCHER, max_matches=100).max_keypoints == 12000
    from click.testing import CliRunner

    for cmd in ("run", "orient"):
        r = CliRunner().invoke(stereo_cli, [cmd, "--help"])
        assert r.exit_code == 0
        for opt in ("--detector", "--verify", "--refine / --no-refine", "--max-matches", "--max-keypoints"):
            assert opt in r.output, (cmd, opt)
        assert "[default: fundamental]" in r.output
    r = CliRunner().invoke(stereo_cli, ["run", "--help"])
    assert "[default: tukey]" in r.output
