"""CLI end to end: stereo resect / model / run / demo on tiny files in tmp_path."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from click.testing import CliRunner

import stereo.cli
from rectify.formats.tables import write_matches
from rectify.geometry.points import Matches
from stereo.actions.scene import make_scene
from stereo.cli.main import cli
from stereo.formats.orientation import relative_json_text
from stereo.relative import RelativeOrientation
from tests.support.rectify_support import verify_report


@pytest.fixture(scope="module")
def scene():
    return make_scene(0, size_px=480)


def _files(tmp_path, scene, n_tie=120, n_ctrl=8):
    rng = np.random.default_rng(0)
    g = scene.random_ground_points(n_tie + n_ctrl, rng)
    cam = scene.camera
    pl = scene.pixel_from_ground(scene.left, g) + rng.normal(0, 0.2, (len(g), 2))
    pr = scene.pixel_from_ground(scene.right, g) + rng.normal(0, 0.2, (len(g), 2))
    (tmp_path / "cam.json").write_text(json.dumps(cam.to_dict()))
    ids = tuple(f"t{i}" for i in range(n_tie))
    write_matches(tmp_path / "matches.csv", Matches(ids, pl[:n_tie], pr[:n_tie]))
    ro = RelativeOrientation.from_pixels(pl[:n_tie], pr[:n_tie], cam, ids=ids)
    (tmp_path / "ro.json").write_text(relative_json_text(ro))
    lines = [f"# crs={scene.crs}", "id,col_left,row_left,col_right,row_right,x,y,z"]
    for i in range(n_tie, n_tie + n_ctrl):
        lines.append(f"c{i},{pl[i, 0]},{pl[i, 1]},{pr[i, 0]},{pr[i, 1]},{g[i, 0]},{g[i, 1]},{g[i, 2]}")
    (tmp_path / "control.csv").write_text("\n".join(lines) + "\n")
    gl = ["id,col,row,x,y,z"] + [f"g{i},{pl[i, 0]},{pl[i, 1]},{g[i, 0]},{g[i, 1]},{g[i, 2]}" for i in range(10)]
    (tmp_path / "gcps.csv").write_text("\n".join(gl) + "\n")
    return tmp_path


def test_resect_cli(tmp_path, scene):
    d = _files(tmp_path, scene)
    r = CliRunner().invoke(cli, ["resect", "--camera", str(d / "cam.json"), "--gcps", str(d / "gcps.csv"),
                                 "-o", str(d / "eo.json"), "--report", str(d / "rep")])
    assert r.exit_code == 0, r.output
    assert "space resection: 10 fit points" in r.output
    eo = json.loads((d / "eo.json").read_text())
    assert np.allclose(eo["position"], scene.left.position, atol=5.0)
    assert (d / "rep" / "report.html").is_file()
    r = CliRunner().invoke(cli, ["resect", "--camera", str(d / "cam.json"), "--gcps", str(d / "gcps.csv"),
                                 "-o", str(d / "eo.json")])
    assert r.exit_code != 0 and "exists" in r.output


def test_model_cli(tmp_path, scene):
    d = _files(tmp_path, scene)
    r = CliRunner().invoke(cli, ["model", str(d / "ro.json"), "--matches", str(d / "matches.csv"), "--camera",
                                 str(d / "cam.json"), "-o", str(d / "pts.ply"), "--control", str(d / "control.csv"),
                                 "--check", "c120,c121"])
    assert r.exit_code == 0, r.output
    assert "absolute orientation (topocentric frame)" in r.output and "map frame instead" in r.output
    assert (d / "pts.csv").is_file() and (d / "pts.orientation.json").is_file()
    o = json.loads((d / "pts.orientation.json").read_text())
    assert o["summary"]["n_check"] == 2 and o["summary"]["rmse_check_m"] < 30.0  # B/H 0.3, 0.2 px: sigma_Z ~ 5 m


@pytest.mark.parametrize("args, msg", [
    (["--check", "nope"], "check point id(s) ['nope']"),
    (["--frame", "map", "--check", "c120,c121,c122,c123,c124,c125,c126"], "too few control points"),
])
def test_model_cli_bad_control(tmp_path, scene, args, msg):
    d = _files(tmp_path, scene)
    r = CliRunner().invoke(cli, ["model", str(d / "ro.json"), "--matches", str(d / "matches.csv"), "--camera",
                                 str(d / "cam.json"), "-o", str(d / "pts.ply"), "--control",
                                 str(d / "control.csv")] + args)
    assert r.exit_code == 1 and msg in r.output


def test_model_cli_mismatched_ids(tmp_path, scene):
    d = _files(tmp_path, scene)
    txt = (d / "matches.csv").read_text().replace("\nt", "\nx")
    (d / "other.csv").write_text(txt)
    r = CliRunner().invoke(cli, ["model", str(d / "ro.json"), "--matches", str(d / "other.csv"), "--camera",
                                 str(d / "cam.json"), "-o", str(d / "pts.ply")])
    assert r.exit_code == 1 and "do not match the points" in r.output


def test_model_cli_collinear_control(tmp_path, scene):
    d = _files(tmp_path, scene)
    lines = (d / "control.csv").read_text().splitlines()
    rows = [ln.split(",") for ln in lines[2:]]
    for k, row in enumerate(rows):  # put the ground coordinates on one line
        row[5], row[6], row[7] = str(-55000 + 10 * k), str(-3727000 + 5 * k), str(400 + k)
    (d / "line.csv").write_text("\n".join(lines[:2] + [",".join(r) for r in rows]) + "\n")
    r = CliRunner().invoke(cli, ["model", str(d / "ro.json"), "--matches", str(d / "matches.csv"), "--camera",
                                 str(d / "cam.json"), "-o", str(d / "pts.ply"), "--control", str(d / "line.csv"),
                                 "--frame", "map"])
    assert r.exit_code == 1 and "EstimationError" in r.output


def test_demo_cli_default_configuration(tmp_path):
    """The demo as a user runs it (seed 0, 480 px): calibrated check-point std, units, counts, full report."""
    out = tmp_path / "demo"
    r = CliRunner().invoke(cli, ["demo", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "accuracy against the truth" in r.output
    t = json.loads((out / "truth_comparison.json").read_text())
    assert t["dem_rmse_m"] < 1.5 * t["ground_pixel_m"]
    # must show: check points within 1.5x their predicted standard errors
    assert 0.67 <= t["check_normalised_rms"] <= 1.5, t
    assert f"predicted std {t['check_normalised_rms']:.3f}" in r.output
    # the synthetic scene is metric: no "ground units" anywhere
    assert "ground units" not in r.output
    assert re.search(r"check points: RMSE X [0-9.]+ m, Y [0-9.]+ m, Z [0-9.]+ m", r.output)
    # the intersection count is explained: tie points kept by the RO + control-file points
    mm = re.search(r"intersection: (\d+) points \((\d+) tie points kept by the relative orientation \+ "
                   r"(\d+) control \+ (\d+) check points from the control file\)", r.output)
    assert mm, r.output
    n, n_tie, n_c, n_k = map(int, mm.groups())
    assert n == n_tie + n_c + n_k and (n_c, n_k) == (10, 20)
    n_matches = int(re.match(r"(\d+) matches", r.output).group(1))
    assert n_tie <= n_matches
    # complete stereo report: RO correlation heat map, AO plan vectors and height bars, GeoJSON (WKT CRS)
    rep = out / "report"
    assert verify_report(rep) == []
    for name in ("fig_ro_correlation_of_elements.png", "fig_ao_plan_residuals.png", "fig_ao_height_residuals.png",
                 "absolute_orientation.geojson"):
        assert (rep / name).is_file(), name
        if name.endswith(".png"):  # decoded, drawn (not blank)
            img = matplotlib.image.imread(rep / name)
            assert min(img.shape[:2]) >= 200 and np.ptp(img[..., :3]) > 0.5, (name, img.shape)
    gj = json.loads((rep / "absolute_orientation.geojson").read_text())
    assert len(gj["features"]) == 30
    assert (out / "points.ply").is_file()


def test_orient_then_model_without_camera_option(tmp_path, scene):
    """The documented chain: `stereo orient --camera ...` stores the camera in ro.json, so
    `stereo model RO.json --matches ... -o points.ply --control ...` needs no --camera."""
    d = _files(tmp_path, scene)
    r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "matches.csv"),
                                 "-o", str(d / "ro2.json")])
    assert r.exit_code == 0, r.output
    stored = json.loads((d / "ro2.json").read_text())["camera"]
    assert stored == json.loads((d / "cam.json").read_text())
    r = CliRunner().invoke(cli, ["model", str(d / "ro2.json"), "--matches", str(d / "matches.csv"),
                                 "-o", str(d / "pts.ply"), "--control", str(d / "control.csv")])
    assert r.exit_code == 0, r.output
    assert (d / "pts.ply").is_file() and "absolute orientation" in r.output
    # an RO JSON without a camera (written by the library) needs --camera, and says so
    r = CliRunner().invoke(cli, ["model", str(d / "ro.json"), "--matches", str(d / "matches.csv"),
                                 "-o", str(d / "q.ply")])
    assert r.exit_code == 1 and "holds no camera" in r.output and "--camera" in r.output
    assert not (d / "q.ply").exists()


def test_command_modules_are_thin():
    """Every ``stereo`` command module parses options and calls one action: it imports click, the shared
    options, the actions and the modules holding the choice lists, nothing that reads files or draws."""
    actions = {f"stereo.actions.{m}" for m in ("common", "orient", "model", "resect", "run", "demo", "dense", "block",
                                                 "dense_rpc", "dense_rpc_multi", "block_models", "block_projective",
                                                 "block_surface")}
    # the modules holding choice lists and their defaults (robust estimators, frames, systematic unknowns, methods)
    choices = {"rectify.geometry.robust", "rectify.geometry.mestimate", "stereo.block.bundle.robust",
               "stereo.block.bundle.systematic", "stereo.block.projective", "stereo.block.projective_bundle"}
    allowed = {"__future__", "click", "rectify.cli.options", *choices, *actions, "stereo.relative",
               "stereo.pair.model", "stereo.pair.intersection", "stereo.pair.absolute", "stereo.pair.resection",
               "stereo.block.bundle.adjust", "stereo.features.tracks", "math"}
    cli_dir = Path(stereo.cli.__file__).parent
    # the pair layout (issue 11), the block and the RPC dense command (issue 14)
    for name in ("orient", "model", "resect", "run", "demo", "block", "dense_rpc"):
        path = cli_dir / f"{name}.py"
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                name = node.module or ""
                assert name in allowed, (path.name, name)
            elif isinstance(node, ast.Import):
                assert all(a.name in allowed for a in node.names), (path.name, [a.name for a in node.names])
