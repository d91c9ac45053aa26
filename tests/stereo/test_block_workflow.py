"""``stereo.actions.block.run_block`` on a synthetic block with known truth, through its files.

The synthetic block (:func:`tests.support.block_synthetic.make_block`: 3 strips x 6 images, 60 % / 30 %
overlap, relief, 0.5 px image noise, 5 cm GNSS noise) is written as the files a user gives: a
position/angle CSV (GNSS positions with their sigma, perturbed angles), a block control CSV (the
control points' image measurements and ground coordinates) and placeholder image files; its tie
tracks are handed in, so the matching is skipped (the CLI tests cover the matching).
"""

from __future__ import annotations

import math

import laspy
import numpy as np
import pytest

from rectify.errors import EstimationError, InvalidInputError
from rectify.formats.camera import read_camera
from rectify.geometry.rotation import angles_from_matrix
from stereo.actions.block import BLOCK_LAYOUT, BlockOptions, run_block
from stereo.block.bundle.adjust import BundleOptions
from stereo.block.types import Tracks
from stereo.formats.block import read_block_control, read_block_orientation
from stereo.formats.points import read_points_csv
from stereo.formats.poses import read_pose_csv
from tests.support.block_files import write_block_files
from tests.support.block_synthetic import make_block


def _files(tmp_path, blk, **kwargs):
    """Images (placeholders named like the block's), camera JSON, pose CSV, control CSV, tie tracks, check ids."""
    return write_block_files(tmp_path, blk, **kwargs)


@pytest.fixture(scope="module")
def block():
    return make_block(0, blunder_fraction=0.05)


@pytest.fixture(scope="module")
def run(block, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("blk")
    images, cam, poses, ctrl, ties, checks = _files(tmp, block)
    # frame="map": the synthetic block is Cartesian in its (UTM-labelled) coordinates
    opts = BlockOptions(check_ids=checks, bundle=BundleOptions(robust="tukey", image_sigma_px=0.5), frame="map")
    out = tmp / "out"
    res = run_block(images, out_dir=out, camera=cam, poses=poses, control=ctrl, options=opts, tracks=ties)
    return res, out, block, (images, cam, poses, ctrl, ties, checks)


def test_outputs_are_written_and_read_back(run):
    res, out, blk, _ = run
    for name in BLOCK_LAYOUT.values():
        assert (out / name).is_file(), name
    assert (out / "report" / "report.html").is_file()
    cam = read_camera(out / "camera_camera.json")
    assert cam.focal_length_mm == blk.camera.focal_length_mm
    o = read_block_orientation(out / "orientation.json")
    assert [p.image for p in o.poses] == list(blk.tracks.images)
    assert o.crs == "EPSG:32633"
    assert np.isfinite(o.std_errors).all()
    assert o.datum and any("GNSS" in line or "control" in line for line in o.datum)
    back = read_pose_csv(out / "poses.csv")
    for p, q in zip(o.poses, back.poses, strict=True):
        np.testing.assert_allclose(p.position, q.position, atol=1e-9)
        np.testing.assert_allclose(p.rotation, q.rotation, atol=1e-12)
    pts = read_points_csv(out / "points.csv")
    assert len(pts.ids) == res.n_points_written > 0.95 * len(res.bundle.point_ids)
    las = laspy.read(out / "points.las")
    assert len(las.points) == len(pts.ids)
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), pts.xyz, atol=2e-3)
    # the LAS carries the bundle's height standard error of each point (issue 27), as the CSV's std_z
    assert pts.std is not None
    np.testing.assert_allclose(np.asarray(las["sigma_z"]), pts.std[:, 2], atol=1e-4)
    obs = (out / "observations.csv").read_text().splitlines()
    assert len(obs) == 1 + res.tracks.n_obs


def test_orientation_and_check_points_within_their_predicted_precision(run):
    res, _out, blk, _ = run
    b = res.bundle
    truth = {p.image: p for p in blk.true_poses}
    dpos = np.array([p.position - truth[p.image].position for p in b.poses])
    z = dpos / b.pose_std[:, 3:]
    assert rms(z) < 1.5, rms(z)
    dang = np.array([angles_from_matrix(truth[p.image].rotation.T @ p.rotation) for p in b.poses])
    assert rms(dang / b.pose_std[:, :3]) < 1.5
    assert len(b.check_ids) == int(blk.control.check.sum()) > 0
    zc = b.check_errors / b.check_std
    assert rms(zc) < 1.5, rms(zc)
    assert 0.85 < b.sigma0 < 1.15


def test_planted_blunders_are_flagged(run):
    res, _out, blk, _ = run
    t = res.tracks
    # map the planted blunders (observation rows of the synthetic tracks) to rows of the run's tracks
    src = blk.tracks
    key = {(src.point_ids[src.obs_point[k]], src.images[src.obs_image[k]]) for k in blk.blunder_obs}
    rows = [k for k in range(t.n_obs) if (t.point_ids[t.obs_point[k]], t.images[t.obs_image[k]]) in key]
    assert len(rows) >= 0.9 * len(key)  # the rest were dropped already by the intersection's rejection
    assert np.asarray(res.bundle.flagged)[rows].all()
    assert int(np.asarray(res.bundle.flagged).sum()) <= len(key) + 5


def test_summary_lines(run):
    res = run[0]
    text = "\n".join(res.summary_lines())
    assert "bundle: 18 images" in text and "sigma0" in text and "check: 6 points" in text
    assert "initial orientation: from the given poses" in text
    assert "wrote " in text and "report: " in text


def test_without_poses_independent_models_and_control(block, tmp_path):
    blk = make_block(1, control_layout="corners+centre", n_check=4, n_points=1500)
    images, cam, _poses, ctrl, ties, checks = _files(tmp_path, blk, gnss=False)
    res = run_block(images, out_dir=tmp_path / "o", camera=cam, control=ctrl, tracks=ties,
                    options=BlockOptions(check_ids=checks, bundle=BundleOptions(robust="tukey", image_sigma_px=0.5,
                                                                                max_iterations=100),
                                         frame="map"))  # the synthetic block is Cartesian in its coordinates
    assert res.initial.startswith("independent models")
    b = res.bundle
    truth = {p.image: p for p in blk.true_poses}
    dpos = np.array([p.position - truth[p.image].position for p in b.poses])
    assert rms(dpos / b.pose_std[:, 3:]) < 2.0
    assert rms(b.check_errors / b.check_std) < 2.0
    assert any("control" in line for line in b.datum)


def test_no_datum_fails_in_one_line_and_leaves_nothing(tmp_path):
    blk = make_block(2)
    images, cam, _poses, _ctrl, ties, _ = _files(tmp_path, blk, gnss=False, control=False)
    out = tmp_path / "o"
    with pytest.raises(EstimationError, match="datum"):
        run_block(images, out_dir=out, camera=cam, tracks=ties)
    assert not out.exists()


def test_free_network_runs_without_datum(tmp_path):
    blk = make_block(2)
    images, cam, _poses, _ctrl, ties, _ = _files(tmp_path, blk, gnss=False, control=False)
    res = run_block(images, out_dir=tmp_path / "o", camera=cam, tracks=ties,
                    options=BlockOptions(bundle=BundleOptions(robust="tukey", free_network=True), report=False))
    assert res.bundle.converged and res.report is None
    assert not (tmp_path / "o" / "report").exists()


@pytest.mark.parametrize("case", ["one_image", "check_without_control", "unknown_check", "pose_missing",
                                  "control_unknown_image", "exists", "tracks_other_images"])
def test_bad_input(run, tmp_path, case):
    _res, out, blk, (images, cam, poses, ctrl, ties, checks) = run
    kw = dict(out_dir=tmp_path / "o", camera=cam, poses=poses, control=ctrl, tracks=ties,
              options=BlockOptions(check_ids=checks))
    before = {p: p.read_bytes() for p in (cam, poses, ctrl)}
    msg = {"one_image": "at least 2 images", "check_without_control": "without a control file",
           "unknown_check": r"check id\(s\) \['nope'\]", "pose_missing": "has no pose for image",
           "control_unknown_image": "not in the block", "exists": "exists", "tracks_other_images": "given tracks"}[case]
    if case == "one_image":
        call = dict(kw, images=images[:1])
    elif case == "check_without_control":
        call = dict(kw, images=images, control=None)
    elif case == "unknown_check":
        call = dict(kw, images=images, options=BlockOptions(check_ids=("nope",)))
    elif case == "pose_missing":
        p2 = tmp_path / "p2.csv"
        p2.write_text("\n".join(poses.read_text().splitlines()[:-1]) + "\n")
        call = dict(kw, images=images, poses=p2)
    elif case == "control_unknown_image":
        c2 = tmp_path / "c2.csv"
        c2.write_text(ctrl.read_text() + "X,other.tif,1,2,3,4,5,1,1,1\nX,another.tif,1,2,,,,,,\n")
        call = dict(kw, images=images, control=c2)
    elif case == "exists":
        call = dict(kw, images=images, out_dir=out)
    else:
        t2 = Tracks(tuple(f"x{k}" for k in range(len(ties.images))), ties.point_ids, ties.obs_point,
                    ties.obs_image, ties.obs_pixel, ties.obs_sigma_px)
        call = dict(kw, images=images, tracks=t2)
    with pytest.raises(InvalidInputError, match=msg):
        run_block(**call)
    if case != "exists":
        assert not (tmp_path / "o").exists()
    for p, b in before.items():
        assert p.read_bytes() == b


def test_control_file_kinds_reach_the_adjustment(run):
    _res, _out, blk, (_i, _c, _p, ctrl, _t, _k) = run
    c = read_block_control(ctrl)
    assert set(c.kind) == {"full"} and len(c.ids) == len(blk.control.ids)


def rms(a):
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return math.sqrt(float(np.mean(a * a)))
