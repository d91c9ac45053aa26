"""``stereo orient`` end to end with click's CliRunner."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.formats.tables import write_matches
from rectify.geometry.camera import Camera
from rectify.geometry.points import Matches
from stereo.cli.main import cli
from tests.support.stereo_support import simulate_pair

CAM = {"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152}


@pytest.fixture()
def files(tmp_path):
    cam = Camera.from_dict(CAM)
    sp = simulate_pair("vertical", n=60, noise_px=0.3, outlier_fraction=0.1, rng=5)
    m = Matches(tuple(f"p{i}" for i in range(60)), cam.pixel_from_photo(sp.left_mm), cam.pixel_from_photo(sp.right_mm))
    write_matches(tmp_path / "m.csv", m)
    (tmp_path / "cam.json").write_text(json.dumps(CAM))
    return tmp_path, sp


def run(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


@pytest.mark.parametrize("system", ["basis", "left-image", "dobrynin-pimshina"])
def test_orient_matches_file(files, system):
    d, sp = files
    r = run(["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "m.csv"), "-o", str(d / "ro.json"),
             "--system", system, "--robust", "tukey"])
    assert r.exit_code == 0, r.output
    assert "RMSE" in r.output and "sigma0" in r.output and "px" in r.output
    ro = json.loads((d / "ro.json").read_text())
    assert ro["system"] == system and ro["n_points"] == 60
    assert ro["n_used"] < 60 and sum(p["outlier"] for p in ro["points"]) >= 4
    R = np.array(ro["rotation_left"]).T @ np.array(ro["rotation_right"])
    ang = 2 * math.asin(min(1.0, np.linalg.norm(R - sp.R_rel) / (2 * math.sqrt(2))))
    assert math.degrees(ang) < 0.2
    names = list(ro["elements"])
    z = (np.array([ro["elements"][k] for k in names]) - sp.truth(system)) / [ro["std_errors"][k] for k in names]
    assert np.all(np.abs(z) < 3), z
    assert [p["id"] for p in ro["points"]][:2] == ["p0", "p1"]


def test_orient_never_overwrites_and_report(files):
    d, _ = files
    args = ["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "m.csv"), "-o", str(d / "ro.json")]
    assert run(args).exit_code == 0
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 1 and "exists" in r.output and "--overwrite" in r.output
    r = run(args + ["--overwrite", "--report", str(d / "rep")])
    assert r.exit_code == 0, r.output
    assert (d / "rep" / "report.html").is_file() and (d / "rep" / "report.json").is_file()


def test_orient_bad_input(files, tmp_path):
    d, _ = files
    r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "cam.json"), "-o", str(d / "x.json")])
    assert r.exit_code == 2 and "either --matches" in r.output
    (d / "few.csv").write_text("id,col_left,row_left,col_right,row_right\n1,1,2,3,4\n2,5,6,7,8\n")
    r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "few.csv"),
                                 "-o", str(d / "x.json")])
    assert r.exit_code == 1 and "too few tie points" in r.output and "2 given" in r.output
    assert not (d / "x.json").exists()
    r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "m.csv"),
                                 "-o", str(d / "x.json"), "--system", "nope"])
    assert r.exit_code == 2


def test_orient_images(ngi_pair, tmp_path):
    (tmp_path / "cam.json").write_text(json.dumps(CAM))
    r = run(["orient", str(ngi_pair / "3324c_2015_1004_05_0182_RGB.tif"),
             str(ngi_pair / "3324c_2015_1004_05_0184_RGB.tif"), "--camera", str(tmp_path / "cam.json"),
             "-o", str(tmp_path / "ro.json"), "--matches-out", str(tmp_path / "m.csv")])
    assert r.exit_code == 0, r.output
    ro = json.loads((tmp_path / "ro.json").read_text())
    assert ro["rms_parallax_mm"] / 0.144 < 0.35 and ro["n_points"] > 100
    assert (tmp_path / "m.csv").is_file()
