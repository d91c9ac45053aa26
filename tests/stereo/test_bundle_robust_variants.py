"""Seed 002's estimation details in the bundle adjustment (docs/robust.md): the M-estimate covariance
(eq. 2.28), the weighted-median scale (eq. 2.29), the modified residuals (eqs. 2.25-2.27) and the modified
Newton-Raphson, on synthetic blocks with known truth; and the ``stereo block`` options end to end."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.errors import InvalidInputError
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.cli.main import cli
from tests.support.block_files import write_block_files
from tests.support.block_synthetic import make_block


@pytest.fixture(scope="module")
def blunders():
    return make_block(0, blunder_fraction=0.05)


def _adjust(b, **kw):
    o = {"robust": "tukey", "image_sigma_px": 0.5, "max_iterations": 300}
    o.update(kw)
    return adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                         options=BundleOptions(**o))


@pytest.mark.parametrize("kw", [{"robust_algorithm": "modified-residuals"}, {"robust_scale": "weighted-median"},
                                {"newton": "modified"}])
def test_variants_reach_the_reweighting_solution(blunders, kw):
    """Every variant converges, flags every planted blunder and gives the points of the default within a
    tenth of their standard deviation (the weighted-median scale: within one; it changes the weights)."""
    ref = _adjust(blunders)
    r = _adjust(blunders, **kw)
    assert r.converged
    planted = set(blunders.blunder_obs.tolist())
    assert planted <= set(r.flagged_obs.tolist())
    ok = ref.points_determined & r.points_determined
    assert ok.mean() > 0.95
    tol = 1.0 if "robust_scale" in kw else 0.1
    assert np.nanmax(np.abs(r.points - ref.points)[ok] / ref.point_std[ok]) < tol


def test_modified_newton_takes_more_iterations_for_least_squares():
    b = make_block(2)
    full = _adjust(b, robust="none")
    mod = _adjust(b, robust="none", newton="modified")
    assert mod.iterations > full.iterations
    np.testing.assert_allclose(mod.points, full.points, atol=1e-3)


def test_m_estimate_std_is_that_of_least_squares_without_the_blunders():
    """Eq. 2.28 on a block with 5 % blunders: the robust pose and point std agree with those of least squares
    on the same block without blunders (the factor ~ 1 / efficiency, 1.05 for Tukey), where sigma0^2 (A^T W A)^-1
    of the robust weights would shrink or swell with the rejected rays."""
    clean = make_block(0)
    dirty = make_block(0, blunder_fraction=0.05)
    ls = _adjust(clean, robust="none")
    rb = _adjust(dirty)
    ratio = rb.pose_std / ls.pose_std
    assert 0.95 < float(np.median(ratio)) < 1.15, np.median(ratio)
    ok = rb.points_determined
    pr = np.nanmedian(rb.point_std[ok] / ls.point_std[ok], axis=0)
    assert ((pr > 0.95) & (pr < 1.2)).all(), pr


def test_bad_variant_options():
    for kw, msg in (({"robust_algorithm": "irls"}, "robust_algorithm must be one of"),
                    ({"robust_scale": "mad"}, "robust_scale must be one of"),
                    ({"newton": "half"}, "newton must be one of")):
        with pytest.raises(InvalidInputError, match=msg):
            BundleOptions(**kw)


def test_stereo_block_options_end_to_end_from_observations(tmp_path):
    """``stereo block --observations`` with the seed 002 variants: runs, writes its outputs, and the bad
    choice is one line naming the value."""
    blk = make_block(0, blunder_fraction=0.05)
    _images, cam, poses, ctrl, ties, checks = write_block_files(tmp_path, blk)
    obs = tmp_path / "in" / "obs.csv"
    rows = ["image,id,col,row"]
    for k in range(ties.n_obs):
        rows.append(f"{ties.images[ties.obs_image[k]]},{ties.point_ids[ties.obs_point[k]]},"
                    f"{float(ties.obs_pixel[k, 0])!r},{float(ties.obs_pixel[k, 1])!r}")
    obs.write_text("\n".join(rows) + "\n")
    out = tmp_path / "out"
    base = ["block", "--observations", str(obs), "--camera", str(cam), "--poses", str(poses), "--control", str(ctrl),
            "--check", ",".join(checks), "--no-report", "--no-stac"]
    r = CliRunner().invoke(cli, [*base, "-o", str(out), "--newton", "modified", "--robust-scale", "weighted-median",
                                 "--max-iterations", "300"])
    assert r.exit_code == 0, r.output
    assert (out / "orientation.json").is_file() and (out / "points.csv").is_file()
    r = CliRunner().invoke(cli, [*base, "-o", str(tmp_path / "o2"), "--newton", "half"])
    assert r.exit_code != 0 and "half" in r.output and not (tmp_path / "o2").exists()
