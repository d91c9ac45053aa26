"""``stereo block --method independent-models`` end to end (issue 25), on the synthetic block's files.

The block (:func:`tests.support.block_synthetic.make_block`, 3 strips x 6 images, 40 mm camera, 0.5 px,
5 full control points and 8 check points) is written as an observations CSV (its tie points: no
images, no matching), a camera JSON, a pose CSV without sigmas (it only names the images) and a block
control CSV.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.geometry.camera import Camera
from stereo.cli.main import cli
from stereo.formats.block import read_block_orientation
from stereo.formats.points import read_points_csv
from tests.support.block_files import write_block_files
from tests.support.block_synthetic import make_block, strip_control


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    cam = Camera(focal_length_mm=40.0, pixel_size_mm=0.02, width=2000, height=1500, principal_point_mm=(0.0, 0.0))
    blk = make_block(1, control_layout="corners+centre", n_check=8, n_points=1500, camera=cam)
    tmp = tmp_path_factory.mktemp("method")
    _images, camf, poses, ctrl, ties, checks = write_block_files(tmp, blk, gnss=False)
    obs = tmp / "observations.csv"
    obs.write_text("image,id,col,row\n" + "".join(
        f"{ties.images[i]},{ties.point_ids[p]},{float(c)!r},{float(r)!r}\n"
        for p, i, (c, r) in zip(ties.obs_point, ties.obs_image, ties.obs_pixel, strict=True)))
    return {"blk": blk, "camera": camf, "poses": poses, "control": ctrl, "checks": checks, "obs": obs, "ties": ties,
            "tmp": tmp}


def _args(f: dict, out: Path, *extra: str, obs: Path | None = None) -> list[str]:
    return ["block", "--observations", str(obs or f["obs"]), "--camera", str(f["camera"]), "--poses", str(f["poses"]),
            "--control", str(f["control"]), "--check", ",".join(f["checks"]), "-o", str(out), "--no-stac", *extra]


def test_independent_models_write_the_block_outputs(files, tmp_path) -> None:
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(files, out, "--method", "independent-models", "--no-report"))
    assert r.exit_code == 0, r.output
    assert "method: independent models adjusted together with the control (seed 002, 3.1.2)" in r.output
    assert "initial orientation: independent models (17 models), adjusted with control" in r.output
    assert "check: 8 points" in r.output and "bundle:" not in r.output
    for name in ("orientation.json", "poses.csv", "points.ply", "points.csv", "points.las", "observations.csv"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "orientation.json").read_text())
    assert doc["summary"]["method"] == "independent-models"
    o = read_block_orientation(out / "orientation.json")
    truth = {p.image: p.position for p in files["blk"].true_poses}
    d = np.array([p.position - truth[p.image] for p in o.poses])
    assert np.sqrt(np.mean(d ** 2)) < 2.0  # metres, from 1000 m
    pts = read_points_csv(out / "points.csv")
    assert len(pts.ids) > 1000


def test_strip_polynomial_with_too_little_control_fails_in_one_line(files, tmp_path) -> None:
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(files, out, "--method", "independent-models", "--strip-polynomial", "2",
                                      "--no-report"))
    assert r.exit_code != 0
    msg = r.output.strip().splitlines()[-1]
    assert "degree-2 strip polynomial needs at least 6 control points" in msg and "strip 1" in msg, r.output
    assert "Traceback" not in r.output
    assert not out.exists()


def test_too_little_control_for_the_models_fails_in_one_line(files, tmp_path) -> None:
    ctrl = tmp_path / "control.csv"
    keep = files["control"].read_text().splitlines()
    ids = sorted({ln.split(",")[0] for ln in keep[2:]} - set(files["checks"]))[:2]
    ctrl.write_text("\n".join(keep[:2] + [ln for ln in keep[2:] if ln.split(",")[0] in ids or
                                          ln.split(",")[0] in files["checks"]]) + "\n")
    out = tmp_path / "out"
    args = _args(files, out, "--method", "independent-models", "--no-report")
    args[args.index("--control") + 1] = str(ctrl)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0
    # the block's datum check or the method's own, each naming the minimum
    assert ("2 plan and >= 3 height" in r.output or "at least 2 points with plan coordinates and 3 with heights"
            in r.output), r.output
    assert "Traceback" not in r.output and not out.exists()


def test_a_model_with_too_few_tie_points_fails_in_one_line(files, tmp_path) -> None:
    """Image s0_005 keeps only the points no third image sees: its model shares no tie point with the block."""
    t = files["ties"]
    rays = np.bincount(t.obs_point, minlength=t.n_points)
    img = t.images.index("s0_005")
    keep = (t.obs_image != img) | (rays[t.obs_point] == 2)
    obs = tmp_path / "obs.csv"
    obs.write_text("image,id,col,row\n" + "".join(
        f"{t.images[i]},{t.point_ids[p]},{float(c)!r},{float(r)!r}\n"
        for p, i, (c, r) in zip(t.obs_point[keep], t.obs_image[keep], t.obs_pixel[keep], strict=True)))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(files, out, "--method", "independent-models", "--no-report", obs=obs))
    assert r.exit_code != 0
    assert "s0_005" in r.output and "tie points" in r.output and "at least" in r.output, r.output
    assert "Traceback" not in r.output and not out.exists()


def test_model_options_need_the_method(files, tmp_path) -> None:
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(files, out, "--strip-polynomial", "2", "--no-report"))
    assert r.exit_code != 0 and "need --method independent-models" in r.output
    r = CliRunner().invoke(cli, _args(files, out, "--method", "independent-models", "--strip-polynomial", "5"))
    assert r.exit_code != 0 and "--strip-polynomial" in r.output
    assert not out.exists()


def test_strip_polynomial_corrects_a_bent_strip(tmp_path) -> None:
    """A 10-image strip (9 models) whose camera's radial distortion (k1 = -0.01) is not in the camera JSON
    bends; the degree-2 strip polynomial (15 control points) brings the check-point height RMSE under 1 m."""
    true_cam = Camera(focal_length_mm=40.0, pixel_size_mm=0.02, width=2000, height=1500,
                      principal_point_mm=(0.0, 0.0), distortion={"k1": -0.01})
    blk = make_block(3, strips=1, images_per_strip=10, camera=true_cam, n_points=1500, control_layout="none",
                     n_check=0, image_noise_px=0.3)
    control = strip_control(blk, 30)
    blk = replace(blk, camera=replace(true_cam, distortion={}), control=control)
    _images, camf, poses, ctrl_path, ties, checks = write_block_files(tmp_path, blk, gnss=False)
    obs = tmp_path / "observations.csv"
    obs.write_text("image,id,col,row\n" + "".join(
        f"{ties.images[i]},{ties.point_ids[p]},{float(c)!r},{float(r)!r}\n"
        for p, i, (c, r) in zip(ties.obs_point, ties.obs_image, ties.obs_pixel, strict=True)))
    f = {"obs": obs, "camera": camf, "poses": poses, "control": ctrl_path, "checks": checks}
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(f, out, "--method", "independent-models", "--strip-polynomial", "2",
                                      "--no-report", "--frame", "map"))
    assert r.exit_code == 0, r.output
    assert "strip polynomial (seed 002, 3.1.1, eqs. 3.8-3.15): degree 2, 1 strip(s)" in r.output
    line = next(ln for ln in r.output.splitlines() if ln.startswith("check: 30 points"))
    after_z = float(line.split(" z ")[1].split()[0])
    before_z = float(line.split("similarity only:")[1].split(" z ")[1].split(")")[0])
    print(line)
    assert before_z > 5.0 and after_z < 1.0, line
    assert read_points_csv(out / "points.csv").ids
