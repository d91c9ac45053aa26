"""``stereo block`` end to end on a rendered block (2 strips x 3 images of a textured terrain with relief).

The images are rendered from known poses (:mod:`tests.support.block_render`), so every output is compared
with the truth: the adjusted projection centres, and the check points' ground coordinates.
"""

from __future__ import annotations

import csv
import hashlib
import json

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.geometry.rotation import angles_from_matrix
from stereo.cli.main import cli
from stereo.formats.block import read_block_orientation
from stereo.formats.points import read_points_csv
from tests.support.block_example import CAM, E0, N0, write_example_block


def _hashes(paths):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("blockcli")
    images, poses, xyz = write_example_block(d)
    return d, images, poses, xyz


def _run(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def test_block_with_poses_gnss_and_control(scene, tmp_path):
    d, images, poses, xyz = scene
    inputs = [*images, d / "camera.json", d / "poses.csv", d / "control.csv"]
    before = _hashes(inputs)
    out = tmp_path / "out"
    r = _run(["block", *map(str, images), "--camera", str(d / "camera.json"), "--poses", str(d / "poses.csv"),
              "--gnss-sigma", "0.05", "--control", str(d / "control.csv"), "--check", "C1,C6,C10",
              "--control-sigma", "0.01", "-o", str(out)])
    assert r.exit_code == 0, r.output
    text = r.output
    assert "bundle: 6 images" in text and "sigma0" in text and "check: 3 points" in text
    assert "datum: GNSS positions of 6 images" in text
    o = read_block_orientation(out / "orientation.json")
    truth = {path.name: p for p, path in zip(poses, images, strict=True)}
    err = np.array([q.position - truth[q.image].position - [E0, N0, 0.0] for q in o.poses])
    # projection centres within 4 predicted standard deviations and a few centimetres
    assert np.all(np.abs(err) < 4 * o.std_errors[:, 3:] + 0.02), (err, o.std_errors[:, 3:])
    dang = np.array([angles_from_matrix(truth[q.image].rotation.T @ q.rotation) for q in o.poses])
    assert np.degrees(np.abs(dang)).max() < 0.05
    # check points: the adjusted ground coordinates against the truth, within 3 predicted std
    rep = json.loads((out / "report" / "report.json").read_text())
    chk = [t for t in rep["tables"] if t["step"].startswith("bundle: check")][0]
    assert chk["summary"]["n_points"] == 3
    # the accuracy statement of the check points (issue 27): the same RMSE per axis as the block's summary
    summ = json.loads((out / "orientation.json").read_text())["summary"]
    acc = summ["accuracy_statement"]
    assert acc["n"] == 3 and np.allclose(acc["rmse"], summ["check_rmse_xyz_m"], rtol=1e-12)
    assert acc["rmse_r"] == pytest.approx(np.hypot(*summ["check_rmse_xyz_m"][:2]))
    assert "accuracy statement from 3 check points (m;" in text and f"RMSE_z {acc['rmse_z']:.3f} m" in text
    pts = read_points_csv(out / "points.csv")
    ids = list(pts.ids)
    for k in (1, 6, 10):
        i = ids.index(f"C{k}")
        g = pts.xyz[i] - [E0, N0, 0.0]
        assert np.all(np.abs(g - xyz[k]) < 3 * pts.std[i] + 0.01), (k, g - xyz[k], pts.std[i])
    assert len(pts.ids) > 100
    for name in ("orientation.json", "poses.csv", "points.ply", "points.csv", "points.las", "observations.csv",
                 "report/report.html"):
        assert (out / name).is_file()
    assert _hashes(inputs) == before
    # the redundancy numbers of the image measurements (issue 31): each in 0..1, summing to the redundancy of
    # the image observations (less than their count: the unknowns take the rest)
    with (out / "observations.csv").open() as f:
        rows = list(csv.DictReader(f))
    red = np.array([float(r["redundancy"]) for r in rows if r["redundancy"]])
    assert len(red) == len(rows) > 100
    assert red.min() >= -1e-9 and red.max() <= 1 + 1e-9
    assert 0.3 * len(rows) < red.sum() < len(rows)


def test_block_without_poses_by_independent_models(scene, tmp_path):
    d, images, poses, xyz = scene
    out = tmp_path / "out"
    r = _run(["block", *map(str, images), "--camera", str(d / "camera.json"), "--control", str(d / "control.csv"),
              "--no-report", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "initial orientation: independent models" in r.output
    assert "datum: no GNSS, control at" in r.output
    o = read_block_orientation(out / "orientation.json")
    truth = {path.name: p for p, path in zip(poses, images, strict=True)}
    err = np.array([q.position - truth[q.image].position - [E0, N0, 0.0] for q in o.poses])
    assert np.abs(err).max() < 0.5, err
    assert not (out / "report").exists()


@pytest.mark.parametrize("case", ["one_image", "no_camera", "bad_sigma", "no_datum", "bad_check", "exists",
                                  "bad_calibrate", "control_bad_value"])
def test_block_bad_input(scene, tmp_path, case):
    d, images, _poses, _xyz = scene
    out = tmp_path / "out"
    base = ["block", *map(str, images), "--camera", str(d / "camera.json"), "-o", str(out)]
    args = {
        "one_image": ["block", str(images[0]), "--camera", str(d / "camera.json"), "-o", str(out)],
        "no_camera": ["block", *map(str, images), "-o", str(out)],
        "bad_sigma": [*base, "--gnss-sigma", "0.05,-1,2"],
        "no_datum": base,
        "bad_check": [*base, "--control", str(d / "control.csv"), "--check", "nope"],
        "exists": base,
        "bad_calibrate": [*base, "--calibrate", "f,zoom"],
        "control_bad_value": [*base, "--control", str(tmp_path / "c.csv")],
    }[case]
    expect = {"one_image": "at least 2 images", "no_camera": "no camera", "bad_sigma": "each > 0",
              "no_datum": "datum defect", "bad_check": "check id(s) ['nope']", "exists": "exists",
              "bad_calibrate": "unknown parameter 'zoom'", "control_bad_value": "is not a number"}[case]
    if case == "exists":
        out.mkdir()
        (out / "orientation.json").write_text("{}")
    if case == "control_bad_value":
        (tmp_path / "c.csv").write_text("id,image,col,row,x,y,z\nA,x.png,1,zwei,1,2,3\n")
    before = _hashes(images)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0
    assert expect in r.output, r.output
    assert "Traceback" not in r.output
    if case == "exists":
        assert sorted(p.name for p in out.iterdir()) == ["orientation.json"]
    else:
        assert not out.exists()
    assert _hashes(images) == before


def test_block_help_lists_the_options():
    r = _run(["block", "--help"])
    assert r.exit_code == 0
    for opt in ("--poses", "--control", "--check", "--gnss-sigma", "--ins-sigma", "--self-calibrate", "--robust",
                "--lever-arm", "--boresight", "--free-network", "--variance-components"):
        assert opt in r.output


def test_block_with_opensfm_reconstruction(scene, tmp_path):
    """Poses and a pixel camera from an OpenSfM reconstruction.json (local frame, no CRS)."""
    import cv2

    d, images, poses, _xyz = scene
    s = max(CAM.width, CAM.height)
    shots = {}
    for p, path in zip(poses, images, strict=True):
        R_cw = np.diag([1.0, -1.0, -1.0]) @ p.rotation.T          # world -> OpenCV camera axes
        t = -R_cw @ p.position
        rvec, _ = cv2.Rodrigues(R_cw)
        shots[path.name] = {"camera": "v1", "rotation": rvec.ravel().tolist(), "translation": t.tolist()}
    rec = [{"cameras": {"v1": {"projection_type": "perspective", "width": CAM.width, "height": CAM.height,
                               "focal": CAM.focal_px / s, "k1": 0.0, "k2": 0.0}},
            "shots": shots, "points": {}}]
    (tmp_path / "reconstruction.json").write_text(json.dumps(rec))
    # GNSS-like positions: the reconstruction's centres are observations with 5 cm, plus 3 control points
    out = tmp_path / "out"
    r = _run(["block", *map(str, images), "--poses", str(tmp_path / "reconstruction.json"), "--gnss-sigma", "0.05",
              "--no-report", "-o", str(out)])
    assert r.exit_code == 0, r.output
    o = read_block_orientation(out / "orientation.json")
    assert set(o.cameras) == {"v1"} and o.cameras["v1"].pixel_camera
    assert abs(o.cameras["v1"].focal_px - CAM.focal_px) < 1e-9
    truth = {path.name: p for p, path in zip(poses, images, strict=True)}
    err = np.array([q.position - truth[q.image].position for q in o.poses])
    # error-free positions observed at 5 cm: the block stays within a few centimetres of them
    assert np.abs(err).max() < 0.1, err
    assert "datum: GNSS positions of 6 images, no control" in r.output


def test_block_on_a_full_disk_leaves_nothing(scene, small_disk):
    """Outputs that do not fit: one line naming the cause, no output folder, no temporary file."""
    d, images, _poses, _xyz = scene
    out = small_disk / "out"
    res = CliRunner().invoke(cli, ["block", *map(str, images), "--camera", str(d / "camera.json"), "--poses",
                                   str(d / "poses.csv"), "--gnss-sigma", "0.05", "-o", str(out)])
    assert res.exit_code == 1, res.output
    assert "no space left on device" in res.output and "Traceback" not in res.output
    assert list(small_disk.iterdir()) == []


def test_block_interrupted_by_sigterm_leaves_nothing(scene, tmp_path):
    """SIGTERM (as from `timeout` or a batch scheduler) mid-run: exit 143, no output folder."""
    import signal
    import subprocess
    import sys
    import time

    d, images, _poses, _xyz = scene
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-c", "from stereo.cli.main import cli; cli()", "block",
                             *map(str, images), "--camera", str(d / "camera.json"), "--poses", str(d / "poses.csv"),
                             "--gnss-sigma", "0.05", "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    time.sleep(3.0)  # imports done, matching under way (the whole run takes about 6 s on an idle machine)
    if proc.poll() is not None:
        pytest.skip(f"the block ended before it could be interrupted (exit {proc.returncode})")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == -signal.SIGTERM:  # killed while still importing (a loaded machine): no handler yet
        assert not out.exists()
        pytest.skip("the process was still starting up when it was interrupted")
    if (out / "orientation.json").exists() and (out / "report" / "report.html").exists():
        pytest.skip("the signal came after the outputs were committed")  # a race with a fast machine
    assert not out.exists()
    assert proc.returncode == 143, err.decode()
    assert b"Traceback" not in err


def test_block_with_a_reconstruction_and_no_datum_stops_before_matching(scene, tmp_path, monkeypatch):
    """Issue 24 item 8: the documented `stereo block IMAGES --poses reconstruction.json` without GPS in it: one
    line naming --gnss-sigma and --free-network, before any matching, nothing written."""
    import stereo.actions.block as action
    from tests.support.block_example import write_example_reconstruction

    d, images, poses, _xyz = scene
    rec = write_example_reconstruction(tmp_path, images, poses)
    doc = json.loads(rec.read_text())
    for shot in doc[0]["shots"].values():
        del shot["gps_position"], shot["gps_dop"]
    rec.write_text(json.dumps(doc))

    def no_matching(*args, **kwargs):
        raise AssertionError("matching started")

    monkeypatch.setattr(action, "block_tie_points", no_matching)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["block", *map(str, images), "--poses", str(rec), "-o", str(out)])
    assert r.exit_code != 0
    assert "datum defect" in r.output and "reconstruction.json has no gps_position" in r.output
    assert "--gnss-sigma" in r.output and "--free-network" in r.output and "free_network" not in r.output
    assert "Traceback" not in r.output and "matching started" not in r.output
    assert not out.exists()
