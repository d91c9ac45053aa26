"""Issue 32, ``stereo block``'s inputs: files that do not fit together are refused before any matching.

A pose file naming images that are not given, images of another size than their camera, a geographic
CRS label on projected numbers, control measured outside the frame or lying far outside every image
it is measured in, a datum from nothing (every control point a check point in a free network without
poses). Each: one line naming the values, a non-zero exit, no output folder, the inputs unchanged;
and the datum that does exist when every control point is a check point (GNSS) gives a correct result.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import stereo.actions.block as action
from stereo.cli.main import cli
from stereo.formats.block import read_block_orientation
from tests.support.block_example import E0, N0, write_example_block

ALL_CONTROL = ",".join(f"C{k}" for k in range(12))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("block_input")
    images, poses, xyz = write_example_block(d)
    return d, images, poses, xyz


def _hashes(paths) -> dict[Path, str]:
    return {Path(p): hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths}


def _refused(args: list[str], inputs: list[Path], out: Path, monkeypatch, *words: str) -> str:
    """Run ``stereo block``; it must stop before any matching with one line holding ``words``."""

    def no_matching(*a, **k):
        raise AssertionError("matching started")

    monkeypatch.setattr(action, "block_tie_points", no_matching)
    before = _hashes(inputs)
    r = CliRunner().invoke(cli, [*args, "-o", str(out)])
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error:"), r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not out.exists()
    assert _hashes(inputs) == before
    return lines[0]


def _base(d: Path, images) -> list[str]:
    return ["block", *map(str, images), "--camera", str(d / "camera.json")]


def test_pose_file_naming_images_not_given(scene, tmp_path, monkeypatch):
    d, images, _poses, _xyz = scene
    lines = (d / "poses.csv").read_text().splitlines()
    extra = tmp_path / "poses.csv"
    extra.write_text("\n".join(lines + [lines[-1].replace(images[-1].name, "img_9_9.png")]) + "\n")
    _refused([*_base(d, images), "--poses", str(extra)], [*images, extra], tmp_path / "out", monkeypatch,
             "poses of 1 image(s) that are not given", "img_9_9.png")
    # a subset of the images with the full pose file: the rows of the images left out are named
    _refused([*_base(d, images[:4]), "--poses", str(d / "poses.csv")], [*images, d / "poses.csv"],
             tmp_path / "out", monkeypatch, "poses of 2 image(s) that are not given", images[4].name)


@pytest.mark.parametrize("factor", [2.0, 0.5])
def test_images_of_another_size_than_the_camera(scene, tmp_path, monkeypatch, factor):
    """Images half (or twice) the camera's size: refused with both sizes."""
    d, images, _poses, _xyz = scene
    cam = json.loads((d / "camera.json").read_text())
    w, h = cam["width"], cam["height"]
    cam.update(width=int(w * factor), height=int(h * factor), pixel_size_mm=cam["pixel_size_mm"] / factor)
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(cam))
    _refused(["block", *map(str, images), "--camera", str(path), "--poses", str(d / "poses.csv")],
             [*images, path], tmp_path / "out", monkeypatch,
             f"the camera is {int(w * factor)} x {int(h * factor)} px", f"is {w} x {h} px", images[0].name)


@pytest.mark.parametrize("which", ["poses", "control"])
def test_geographic_crs_label_on_projected_numbers(scene, tmp_path, monkeypatch, which):
    d, images, _poses, _xyz = scene
    src = d / ("poses.csv" if which == "poses" else "control.csv")
    bad = tmp_path / src.name
    bad.write_text(src.read_text().replace("# crs=EPSG:32633", "# crs=EPSG:4326"))
    # the control alone (no poses: with a pose file of another CRS the two CRSs would differ, refused already)
    args = [*_base(d, images), *(["--poses", str(bad)] if which == "poses" else ["--control", str(bad)])]
    line = _refused(args, [*images, bad], tmp_path / "out", monkeypatch, "CRSError", src.name,
                    "not a longitude/latitude in EPSG:4326")
    assert ("img_1_1.png" if which == "poses" else "C0") in line


def test_control_measured_outside_the_frame(scene, tmp_path, monkeypatch):
    d, images, _poses, _xyz = scene
    lines = (d / "control.csv").read_text().splitlines()
    out = lines[:2]
    for ln in lines[2:]:
        f = ln.split(",")
        f[2] = str(float(f[2]) + 1000.0)  # columns a full frame to the right
        out.append(",".join(f))
    bad = tmp_path / "control.csv"
    bad.write_text("\n".join(out) + "\n")
    _refused([*_base(d, images), "--poses", str(d / "poses.csv"), "--control", str(bad)], [*images, bad],
             tmp_path / "out", monkeypatch, "control measurements", "outside the camera's 400 x 300 px frame")


@pytest.mark.parametrize("shift", [(5000.0, 0.0), (0.0, -250.0)])
def test_control_points_outside_every_image(scene, tmp_path, monkeypatch, shift):
    """Control coordinates far from the block (5 km east; 250 m south, beyond the half-frame margin): refused
    naming the points, projected through the given poses."""
    d, images, _poses, _xyz = scene
    lines = (d / "control.csv").read_text().splitlines()
    out = lines[:2]
    for ln in lines[2:]:
        f = ln.split(",")
        f[4], f[5] = str(float(f[4]) + shift[0]), str(float(f[5]) + shift[1])
        out.append(",".join(f))
    bad = tmp_path / "control.csv"
    bad.write_text("\n".join(out) + "\n")
    _refused([*_base(d, images), "--poses", str(d / "poses.csv"), "--control", str(bad), "--gnss-sigma", "0.05"],
             [*images, bad], tmp_path / "out", monkeypatch, "12 control point(s)", "lie outside every image",
             "C0 (")


def test_control_point_just_outside_an_image_is_kept(scene, tmp_path, monkeypatch):
    """The margin is half a frame: a control point 10 m (40 px) off its measured position is not refused by this
    check (the bundle judges it); the block then runs to its end."""
    from stereo.actions.block_checks import check_block_inputs
    from stereo.actions.workspace import PairWorkspace
    from stereo.formats.block import read_block_control
    from stereo.formats.poses import read_pose_csv
    from tests.support.block_example import CAM

    d, images, _poses, _xyz = scene
    ctrl = read_block_control(d / "control.csv")
    moved = ctrl.xyz.copy()
    moved[:, 0] += 10.0
    ctrl_moved = type(ctrl)(ctrl.ids, moved, ctrl.kind, ctrl.sigma_m, ctrl.meas_id, ctrl.meas_image,
                            ctrl.meas_pixel, ctrl.crs)
    table = read_pose_csv(d / "poses.csv", camera="camera")
    names = tuple(p.name for p in images)
    ws = PairWorkspace(tmp_path / "out", inputs=images)
    check_block_inputs(ws, images, names, {"camera": CAM}, ("camera",) * len(names), list(table.poses),
                       table.crs, ctrl_moved, control=d / "control.csv", poses_path=d / "poses.csv")
    far = ctrl.xyz.copy()
    far[:, 0] += 80.0  # 320 px: beyond the 200 px margin of a 400 px frame
    with pytest.raises(Exception, match="lie outside every image"):
        check_block_inputs(ws, images, names, {"camera": CAM}, ("camera",) * len(names), list(table.poses),
                           table.crs, type(ctrl)(ctrl.ids, far, ctrl.kind, ctrl.sigma_m, ctrl.meas_id,
                                                 ctrl.meas_image, ctrl.meas_pixel, ctrl.crs),
                           control=d / "control.csv", poses_path=d / "poses.csv")
    assert not (tmp_path / "out").exists()


def test_every_control_point_a_check_point_in_a_free_network_without_poses(scene, tmp_path, monkeypatch):
    """--free-network without poses is the model frame of the first pair; with every control point a check point
    nothing brings it to the ground: the check points would be compared with, and the outputs labelled by, a
    frame they are not in (before: "check: RMS error x 500039 m" and a LAS file labelled EPSG:32633)."""
    d, images, _poses, _xyz = scene
    _refused([*_base(d, images), "--control", str(d / "control.csv"), "--check", ALL_CONTROL, "--free-network"],
             [*images, d / "control.csv"], tmp_path / "out", monkeypatch, "datum from nothing", "12 of them check "
             "points", "--free-network")
    # without --free-network: the datum defect, named as before
    _refused([*_base(d, images), "--control", str(d / "control.csv"), "--check", ALL_CONTROL],
             [*images, d / "control.csv"], tmp_path / "out", monkeypatch, "datum defect", "0 plan and 0 height")


def test_every_control_point_a_check_point_with_gnss_gives_a_datum(scene, tmp_path):
    """Every control point a check point with GNSS positions observed: the datum exists (GNSS) and the check
    points measure it: their errors are within a few predicted standard deviations of the truth."""
    d, images, _poses, xyz = scene
    out = tmp_path / "out"
    inputs = [*images, d / "camera.json", d / "poses.csv", d / "control.csv"]
    before = _hashes(inputs)
    r = CliRunner().invoke(cli, [*_base(d, images), "--poses", str(d / "poses.csv"), "--gnss-sigma", "0.05",
                                 "--control", str(d / "control.csv"), "--check", ALL_CONTROL, "--no-report",
                                 "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "datum: GNSS positions of 6 images, no control" in r.output
    assert read_block_orientation(out / "orientation.json").crs is not None
    pts = {i: k for k, i in enumerate(
        ln.split(",")[0] for ln in (out / "points.csv").read_text().splitlines() if not ln.startswith(("#", "id")))}
    rows = [ln.split(",") for ln in (out / "points.csv").read_text().splitlines() if not ln.startswith(("#", "id"))]
    errs = []
    for k in range(12):
        if f"C{k}" in pts:
            row = rows[pts[f"C{k}"]]
            errs.append(np.array([float(row[1]) - E0, float(row[2]) - N0, float(row[3])]) - xyz[k])
    assert len(errs) >= 6
    assert np.abs(np.array(errs)).max() < 0.5, errs  # GNSS at 5 cm: decimetres at worst
    assert _hashes(inputs) == before
