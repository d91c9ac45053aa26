"""Units of every printed angle and of every angle option (issue 32).

Angles are radians in code and files and degrees where a command prints "deg" (docs/architecture.md,
Conventions). Each test parses the printed lines of a command and compares every angle with the radians
the same run wrote to its JSON (converted with math.degrees here, not by the code under test); the angle
options given in degrees must reach the action as radians. Printed numbers are rounded (4 or 5 decimals),
so the comparison allows one unit of the last printed decimal.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.formats.tables import write_matches
from rectify.geometry.camera import Camera
from rectify.geometry.points import Matches
from rectify.geometry.rotation import matrix_from_angles
from stereo.calibration.rig import RigCalibration
from stereo.cli.main import cli
from tests.support.calibration_synthetic import rig_scene
from tests.support.stereo_support import simulate_pair

CAM = {"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152}
NUM = r"(-?\d+\.\d+)"


def _run(args: list[str]):
    r = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r.output


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("units_pair")
    cam = Camera.from_dict(CAM)
    # a pair with relative angles of a few degrees: radians printed as degrees would read 57 times too small
    sp = simulate_pair("convergent", n=60, noise_px=0.3, rng=7)
    m = Matches(tuple(f"p{i}" for i in range(60)), cam.pixel_from_photo(sp.left_mm), cam.pixel_from_photo(sp.right_mm))
    write_matches(d / "m.csv", m)
    (d / "cam.json").write_text(json.dumps(CAM))
    return d


@pytest.mark.parametrize("system", ["left-image", "basis", "dobrynin-pimshina"])
def test_orient_prints_degrees_of_the_radians_it_writes(pair_files, tmp_path, system):
    d = pair_files
    out = _run(["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "m.csv"), "-o",
                str(tmp_path / "ro.json"), "--system", system])
    ro = json.loads((tmp_path / "ro.json").read_text())
    printed = {m.group(1): (float(m.group(2)), float(m.group(3)))
               for m in re.finditer(rf"^\s+(\S+) = \s*{NUM} \+- {NUM} deg$", out, re.M)}
    assert set(printed) == set(ro["elements"]), (printed, ro["elements"])
    for name, rad in ro["elements"].items():
        value, se = printed[name]
        assert value == pytest.approx(math.degrees(rad), abs=1.01e-5), name
        assert se == pytest.approx(math.degrees(ro["std_errors"][name]), abs=1.01e-5), name
    assert any(abs(v) > 0.5 for v, _ in printed.values())  # degrees, not radians, of a few-degree geometry
    m = re.search(rf"relative omega, phi, kappa = {NUM}, {NUM}, {NUM} deg; base \(1, {NUM}, {NUM}\)", out)
    assert m is not None, out
    rel = ro["relative"]
    for k, name in enumerate(("omega", "phi", "kappa")):
        assert float(m.group(k + 1)) == pytest.approx(math.degrees(rel[name]), abs=1.01e-5), name
    assert float(m.group(4)) == pytest.approx(rel["by"], abs=1.01e-5)
    assert float(m.group(5)) == pytest.approx(rel["bz"], abs=1.01e-5)


def test_resect_prints_degrees_of_the_radians_it_writes(tmp_path):
    rng = np.random.default_rng(3)
    cam = Camera(focal_length_mm=50.0, pixel_size_mm=0.01, width=4000, height=3000)
    R = matrix_from_angles(0.05, -0.08, 0.6)  # about 3, -5 and 34 degrees
    C = np.array([500_100.0, 4_400_200.0, 900.0])
    G = np.column_stack([rng.uniform(499_800, 500_400, 12), rng.uniform(4_399_900, 4_400_500, 12),
                         rng.uniform(0, 60, 12)])
    p = (G - C) @ R
    mm = np.column_stack([-50.0 * p[:, 0] / p[:, 2], -50.0 * p[:, 1] / p[:, 2]]) + rng.normal(0, 0.002, (12, 2))
    px = cam.pixel_from_photo(mm)
    (tmp_path / "cam.json").write_text(json.dumps(cam.to_dict()))
    rows = [",".join([f"g{i}", *(repr(float(v)) for v in (*a, *g))])
            for i, (a, g) in enumerate(zip(px, G, strict=True))]
    (tmp_path / "g.csv").write_text("# crs=EPSG:32633\nid,col,row,x,y,z\n" + "\n".join(rows) + "\n")
    out = _run(["resect", "--camera", str(tmp_path / "cam.json"), "--gcps", str(tmp_path / "g.csv"), "-o",
                str(tmp_path / "eo.json")])
    eo = json.loads((tmp_path / "eo.json").read_text())
    m = re.search(rf"omega {NUM} deg \+- {NUM}, phi {NUM} \+- {NUM}, kappa {NUM} \+- {NUM}", out)
    assert m is not None, out
    for k, name in enumerate(("omega", "phi", "kappa")):
        assert float(m.group(2 * k + 1)) == pytest.approx(math.degrees(eo["angles"][name]), abs=1.01e-4), name
        assert float(m.group(2 * k + 2)) == pytest.approx(math.degrees(eo["std_errors"][name]), abs=1.01e-4), name
    assert float(m.group(5)) == pytest.approx(math.degrees(0.6), abs=0.05)


def test_rig_prints_degrees_of_the_radians_it_writes():
    """The rig's summary (printed by ``stereo calibrate --right``) against its rig JSON document."""
    left, right = rig_scene(np.random.default_rng(3), n_views=5, rel_rotvec=(0.02, 0.25, 0.01), noise_px=0.2)
    rig = RigCalibration.from_views(left.views, right.views, 640, 480, distortion=("k1", "k2"))
    doc = rig.to_dict()
    line = next(s for s in rig.summary_lines() if "relative omega, phi, kappa" in s)
    m = re.search(rf"= {NUM} \+- {NUM}, {NUM} \+- {NUM}, {NUM} \+- {NUM} deg", line)
    assert m is not None, line
    rel = doc["relative"]
    for k, name in enumerate(("omega", "phi", "kappa")):
        assert float(m.group(2 * k + 1)) == pytest.approx(math.degrees(rel[name]), abs=1.01e-4), name
        assert float(m.group(2 * k + 2)) == pytest.approx(math.degrees(rel[f"std_{name}"]), abs=1.01e-4), name
    assert abs(float(m.group(3))) > 10  # phi about 14 degrees


def test_block_angle_options_are_degrees(tmp_path, monkeypatch):
    """``--ins-sigma`` and ``--boresight`` are degrees on the command line and radians in BlockOptions."""
    import stereo.cli.block as block_cli

    seen = {}

    class _Result:
        def summary_lines(self) -> list[str]:
            return ["ok"]

    def fake_run_block(images, **kw):
        seen.update(kw)
        return _Result()

    monkeypatch.setattr(block_cli, "run_block", fake_run_block)
    img = tmp_path / "a.tif"
    img.write_bytes(b"x")
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(CAM))
    out = _run(["block", str(img), "--camera", str(cam), "-o", str(tmp_path / "out"), "--ins-sigma", "0.5,1,2",
                "--boresight", "0.2,-0.3,1.5"])
    assert "ok" in out
    o = seen["options"]
    np.testing.assert_allclose(o.ins_sigma_rad, np.radians([0.5, 1.0, 2.0]), rtol=1e-12)
    np.testing.assert_allclose(o.boresight_rad, np.radians([0.2, -0.3, 1.5]), rtol=1e-12)
    _run(["block", str(img), "--camera", str(cam), "-o", str(tmp_path / "out2"), "--ins-sigma", "0.05"])
    np.testing.assert_allclose(seen["options"].ins_sigma_rad, np.radians([0.05] * 3), rtol=1e-12)


def test_block_poses_csv_degrees_match_the_orientation_radians(tmp_path):
    """``stereo block`` writes poses.csv with ``# angles=deg`` and orientation.json in radians: the same angles."""
    from rectify.geometry.rotation import angles_from_matrix
    from stereo.actions.block import BlockOptions, run_block
    from tests.support.block_files import write_block_files
    from tests.support.block_synthetic import make_block

    blk = make_block(0, strips=2, images_per_strip=3, n_points=120)
    images, cam, poses, ctrl, ties, checks = write_block_files(tmp_path, blk)
    out = tmp_path / "out"
    run_block(images, out_dir=out, camera=cam, poses=poses, control=ctrl, tracks=ties,
              options=BlockOptions(check_ids=checks, report=False))
    lines = (out / "poses.csv").read_text().splitlines()
    assert "# angles=deg" in lines
    header = next(s for s in lines if s.startswith("image,"))
    cols = header.split(",")
    rows = [dict(zip(cols, s.split(","), strict=True)) for s in lines[lines.index(header) + 1:] if s]
    doc = json.loads((out / "orientation.json").read_text())
    images_doc = {im["image"] if "image" in im else im["id"]: im for im in doc["images"]}
    assert len(rows) == len(images_doc) == len(blk.true_poses)
    for r in rows:
        im = images_doc[r["image"]]
        R = np.array(im["rotation"]) if "rotation" in im else matrix_from_angles(*(im["angles"][k] for k in
                                                                               ("omega", "phi", "kappa")))
        rad = angles_from_matrix(R)
        got = np.radians([float(r["omega"]), float(r["phi"]), float(r["kappa"])])
        d = (got - rad + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(d).max() < 1e-8, (r["image"], got, rad)


def _docs() -> str:
    return (Path(__file__).resolve().parents[2] / "docs" / "architecture.md").read_text()


def test_the_convention_these_tests_check_is_documented():
    assert "Angles are radians in\n  code and files; commands show degrees where labelled." in _docs()
