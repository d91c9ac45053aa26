"""``stereo block --method affine|projective`` end to end: a block without a known camera.

The measurements of a synthetic block (3 x 4 images taken with fx 1500, fy 1545, skew 15 px; see
``tests/stereo/test_block_projective.py``) are written as an observations CSV and a block control CSV; the
images are blank files that only give their size. No camera file is given: the command recovers the camera.
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from rectify.formats.camera import read_camera
from stereo.cli.main import cli
from stereo.formats.block import read_block_orientation
from tests.stereo.test_block_projective import CAM, TRUTH, more_control
from tests.support.block_synthetic import make_block


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("projblock")
    b = make_block(0, strips=3, images_per_strip=4, camera=CAM, relief_m=150.0, n_points=300, image_noise_px=0.5)
    b = dataclasses.replace(b, control=more_control(b))
    t, c = b.tracks, b.control
    images = []
    blank = np.zeros((CAM.height, CAM.width), np.uint8)
    for name in t.images:
        p = d / f"{name}.png"
        cv2.imwrite(str(p), blank)
        images.append(p)
    ctrl = set(c.ids)
    obs = ["image,id,col,row"]
    rows = ["id,image,col,row,x,y,z"]
    where = {i: k for k, i in enumerate(c.ids)}
    for k in range(t.n_obs):
        pid, img = t.point_ids[t.obs_point[k]], t.images[t.obs_image[k]] + ".png"
        col, row = t.obs_pixel[k]
        if pid in ctrl:
            x, y, z = c.xyz[where[pid]]
            rows.append(f"{pid},{img},{col:.4f},{row:.4f},{x:.4f},{y:.4f},{z:.4f}")
        else:
            obs.append(f"{img},{pid},{col:.4f},{row:.4f}")
    (d / "obs.csv").write_text("\n".join(obs) + "\n")
    (d / "control.csv").write_text("\n".join(rows) + "\n")
    checks = [i for i, k in zip(c.ids, c.check, strict=True) if k]
    return d, images, checks, b


def _run(args):
    return CliRunner().invoke(cli, ["block", *args], catch_exceptions=False)


def test_block_projective_recovers_the_camera(scene, tmp_path):
    d, images, checks, b = scene
    out = tmp_path / "out"
    before = {p: p.read_bytes() for p in [*images, d / "obs.csv", d / "control.csv"]}
    r = _run([*map(str, images), "--method", "projective", "--observations", str(d / "obs.csv"), "--control",
              str(d / "control.csv"), "--check", ",".join(checks), "--control-sigma", "0.01", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "projective bundle: sigma0" in r.output and "camera (px): fx " in r.output
    assert f"check: {len(checks)} points" in r.output
    for name in ("orientation.json", "poses.csv", "points.ply", "points.csv", "points.las", "observations.csv",
                 "camera_camera.json"):
        assert (out / name).is_file(), name
    cam = read_camera(out / "camera_camera.json")
    se = cam.std_errors
    for key, got in (("fx_px", cam.focal_px), ("fy_px", cam.fy_px), ("skew_px", cam.skew_px)):
        assert abs(got - TRUTH[key]) <= 2 * se[key], (key, got, TRUTH[key], se[key])
    o = read_block_orientation(out / "orientation.json")
    truth = {p.image + ".png": p.position for p in b.true_poses}
    err = np.array([q.position - truth[q.image] for q in o.poses])
    assert np.abs(err).max() < 5.0, err  # metres, from 1000 m
    summary = json.loads((out / "orientation.json").read_text())["summary"]
    assert summary["method"] == "projective" and len(summary["per_image_interior_px"]) == 12
    assert {p: p.read_bytes() for p in before} == before


@pytest.mark.parametrize("case", ["camera_given", "too_few_control", "one_image", "no_control"])
def test_block_projective_bad_input(scene, tmp_path, case):
    d, images, checks, _b = scene
    out = tmp_path / "out"
    args = [*map(str, images), "--method", "affine", "--observations", str(d / "obs.csv"), "--control",
            str(d / "control.csv"), "-o", str(out)]
    expect = ""
    if case == "camera_given":
        (tmp_path / "cam.json").write_text(json.dumps(CAM.to_dict()))
        args += ["--camera", str(tmp_path / "cam.json")]
        expect = "without a known camera"
    elif case == "too_few_control":
        lines = (d / "control.csv").read_text().splitlines()
        keep_ids = sorted({ln.split(",")[0] for ln in lines[1:]})[:3]
        (tmp_path / "c.csv").write_text("\n".join([lines[0]] + [ln for ln in lines[1:]
                                                                if ln.split(",")[0] in keep_ids]) + "\n")
        args[args.index(str(d / "control.csv"))] = str(tmp_path / "c.csv")
        args[args.index("affine")] = "projective"
        expect = "too few control points for the metric upgrade of a projective block: 3"
    elif case == "one_image":
        args = args[len(images) - 1:]
        expect = "at least 2 images; got 1"
    elif case == "no_control":
        i = args.index("--control")
        del args[i:i + 2]
        expect = "needs --control"
    r = _run(args)
    assert r.exit_code != 0
    assert expect in r.output, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not out.exists()
