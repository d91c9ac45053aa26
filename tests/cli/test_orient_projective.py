"""``stereo orient --system universal|projective`` and ``stereo model --transform affine|projective`` end to
end (issue 26, seed 003 3.2-3.3)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.formats.tables import write_control, write_matches
from rectify.geometry.points import ControlTable, Matches
from stereo.cli.main import cli
from tests.support.projective_scene import pair_scene

N_TIE, N_CONTROL, N_CHECK = 50, 14, 16


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("projective")
    sc = pair_scene(31, n=N_TIE + N_CONTROL + N_CHECK, noise_px=0.3)
    tie = slice(0, N_TIE)
    write_matches(d / "m.csv", Matches(tuple(f"t{i}" for i in range(N_TIE)), sc.left[tie], sc.right[tie]))
    ids = tuple(f"c{i}" for i in range(N_CONTROL + N_CHECK))
    rest = slice(N_TIE, None)
    write_control(d / "control.csv", ControlTable(ids, sc.left[rest], sc.right[rest], sc.X[rest]))
    few = slice(N_TIE, N_TIE + 4)
    write_control(d / "control4.csv", ControlTable(ids[:4], sc.left[few], sc.right[few], sc.X[few]))
    few = slice(N_TIE, N_TIE + 3)
    write_control(d / "control3.csv", ControlTable(ids[:3], sc.left[few], sc.right[few], sc.X[few]))
    write_matches(d / "m7.csv", Matches(tuple(f"t{i}" for i in range(7)), sc.left[:7], sc.right[:7]))
    flat = sc.X[rest].copy()
    flat[:, 2] = 0.0
    write_control(d / "flat.csv", ControlTable(ids, sc.left[rest], sc.right[rest], flat))
    cam = sc.camera  # fx != fy and skew: written as a pixel camera
    (d / "cam.json").write_text(json.dumps({
        "fx_px": cam.focal_px, "fy_px": cam.fy_px, "skew_px": cam.skew_px,
        "principal_point_px": [float(c) for c in cam.principal_point_px], "width": cam.width, "height": cam.height}))
    plane = pair_scene(32, n=40, relief=0.0, noise_px=0.3)
    write_matches(d / "plane.csv", Matches(tuple(f"t{i}" for i in range(40)), plane.left, plane.right))
    return d, sc


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def checks():
    return ",".join(f"c{i}" for i in range(N_CONTROL, N_CONTROL + N_CHECK))


def test_orient_universal_and_projective_with_camera(files):
    d, sc = files
    rel = {}
    for system in ("left-image", "universal", "projective"):
        out = d / f"ro-{system}.json"
        r = run("orient", "--camera", d / "cam.json", "--matches", d / "m.csv", "-o", out, "--system", system,
                "--overwrite")
        assert r.exit_code == 0, r.output
        assert "residual vertical parallax: RMSE" in r.output and "sigma0" in r.output
        doc = json.loads(out.read_text())
        assert doc["system"] == system
        rel[system] = (np.array(doc["rotation_left"]).T @ np.array(doc["rotation_right"]), doc["sigma0_mm"])
    assert "fundamental matrix: Sampson RMSE" in r.output  # the projective run's own stage
    assert "fundamental" in doc and doc["fundamental"]["redundancy"] == N_TIE - 7
    for system in ("universal", "projective"):
        R, s0 = rel[system]
        ang = math.degrees(math.acos(min(1.0, (np.trace(R.T @ rel["left-image"][0]) - 1) / 2)))
        assert ang < 1e-3 and s0 == pytest.approx(rel["left-image"][1], rel=0.01)


def test_projective_pair_without_camera_to_control(files):
    d, sc = files
    r = run("orient", "--system", "projective", "--matches", d / "m.csv", "-o", d / "pp.json", "--overwrite")
    assert r.exit_code == 0, r.output
    assert "no metric elements" in r.output and "Sampson residual" in r.output
    pp = json.loads((d / "pp.json").read_text())
    assert pp["format"] == "rectify-stereo/projective-pair" and pp["metric"] is False
    assert 0.2 < pp["sigma0_px"] < 0.4 and np.array(pp["camera_right"]).shape == (3, 4)
    r = run("model", d / "pp.json", "--matches", d / "m.csv", "--control", d / "control.csv", "--check", checks(),
            "--transform", "projective", "-o", d / "pts.ply", "--overwrite")
    assert r.exit_code == 0, r.output
    assert "projective orientation (15 parameters)" in r.output and "check points: 16" in r.output
    o = json.loads((d / "pts.orientation.json").read_text())
    assert o["transform"] == "projective" and o["model"] == "projective"
    assert o["check_rmse"] < 0.1 and o["n_control"] == N_CONTROL  # 0.3 px noise, 100 m away: ~4 cm
    csv = (d / "pts.csv").read_text().splitlines()
    assert csv[0].startswith("id,x,y,z") and len(csv) == 1 + N_TIE + N_CONTROL + N_CHECK
    xyz = np.array([[float(v) for v in line.split(",")[1:4]] for line in csv[1:N_TIE + 1]])
    assert np.sqrt(np.mean(np.sum((xyz - sc.X[:N_TIE]) ** 2, axis=1))) < 0.1
    assert (d / "pts.ply").stat().st_size > 0


def test_affine_orientation_of_a_similar_model(files):
    d, _ = files
    assert run("orient", "--camera", d / "cam.json", "--matches", d / "m.csv", "-o", d / "ro.json",
               "--overwrite").exit_code == 0
    for transform in ("affine", "projective"):
        r = run("model", d / "ro.json", "--matches", d / "m.csv", "--control", d / "control.csv", "--check",
                checks(), "--transform", transform, "-o", d / f"{transform}.ply", "--overwrite")
        assert r.exit_code == 0, r.output
        o = json.loads((d / f"{transform}.orientation.json").read_text())
        assert o["model"] == "similar" and o["check_rmse"] < 0.1
        assert o["parameters"]["model"] == f"{transform}3d"


@pytest.mark.parametrize(("args", "message"), [
    (("orient", "--matches", "{d}/m.csv", "-o", "{d}/bad.json"), "needs a camera"),
    (("orient", "--system", "projective", "--matches", "{d}/plane.csv", "-o", "{d}/bad.json"),
     "degenerate configuration"),
    (("orient", "--system", "projective", "--matches", "{d}/m7.csv", "-o", "{d}/bad.json"), "7; the eight-point"),
    (("orient", "--system", "projective", "--camera", "{d}/cam.json", "--matches", "{d}/m7.csv", "-o",
      "{d}/bad.json"), "7 given, at least 8"),
    (("model", "{d}/ro.json", "--matches", "{d}/m.csv", "--control", "{d}/control3.csv", "--transform", "affine",
      "-o", "{d}/bad.ply"), "3; at least 4 non-coplanar"),
    (("model", "{d}/pp.json", "--matches", "{d}/m.csv", "--control", "{d}/control.csv", "-o", "{d}/bad.ply"),
     "is a projective pair"),
    (("model", "{d}/pp.json", "--matches", "{d}/m.csv", "--control", "{d}/control.csv", "--transform", "affine",
      "-o", "{d}/bad.ply"), "only by the 15-parameter"),
    (("model", "{d}/pp.json", "--matches", "{d}/m.csv", "--control", "{d}/control4.csv", "--transform",
      "projective", "-o", "{d}/bad.ply"), "4; at least 5"),
    (("model", "{d}/pp.json", "--matches", "{d}/m.csv", "--control", "{d}/flat.csv", "--transform",
      "projective", "-o", "{d}/bad.ply"), "coplanar"),
    (("model", "{d}/ro.json", "--matches", "{d}/m.csv", "--control", "{d}/flat.csv", "--transform",
      "affine", "-o", "{d}/bad.ply"), "coplanar"),
])
def test_bad_input_one_line_nothing_written(files, args, message):
    d, _ = files
    if not (d / "pp.json").exists():
        assert run("orient", "--system", "projective", "--matches", d / "m.csv", "-o", d / "pp.json").exit_code == 0
    if not (d / "ro.json").exists():
        assert run("orient", "--camera", d / "cam.json", "--matches", d / "m.csv", "-o", d / "ro.json").exit_code == 0
    before = sorted(p.name for p in d.iterdir())
    r = run(*(a.format(d=d) for a in args))
    assert r.exit_code != 0
    assert message in r.output, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert sorted(p.name for p in d.iterdir()) == before
