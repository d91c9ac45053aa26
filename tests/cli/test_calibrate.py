"""``stereo calibrate`` end to end on tiny rendered chessboard images and on CSV files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from rectify.geometry.rotation import rodrigues
from stereo.calibration.model import Intrinsics
from stereo.cli.main import cli
from stereo.features.targets import Chessboard
from stereo.formats.calibration import camera_from_dict
from tests.support.calibration_synthetic import board_scene, field_scene, rig_scene

CAM = Intrinsics(fx=420.0, fy=420.0, cx=161.0, cy=118.0, width=320, height=240)
BOARD = Chessboard(7, 5, 1.0)


def _render_poses(tmp_path, poses, prefix="board"):
    """Render a 7 x 5 (inner corners) chessboard seen from ``poses`` (rotation vector, t), 320 x 240 px."""
    s, off = 40, 20 + 40  # texture: 40 px squares, 20 px white border; X = -1 at the border
    tex = np.full((20 * 2 + 40 * 6, 20 * 2 + 40 * 8), 255, np.uint8)
    for j in range(6):
        for i in range(8):
            if (i + j) % 2 == 0:
                tex[20 + 40 * j:20 + 40 * (j + 1), 20 + 40 * i:20 + 40 * (i + 1)] = 0
    A = np.array([[1 / s, 0, -off / s + 0.5 / s], [0, 1 / s, -off / s + 0.5 / s], [0, 0, 1.0]])
    paths = []
    for k, pose in enumerate(poses):
        R = rodrigues(pose[:3])[0]
        H = CAM.K @ np.column_stack([R[:, 0], R[:, 1], pose[3:]]) @ A
        img = cv2.warpPerspective(tex, H, (CAM.width, CAM.height), flags=cv2.INTER_AREA, borderValue=255)
        p = tmp_path / f"{prefix}{k}.png"
        cv2.imwrite(str(p), img)
        paths.append(str(p))
    return paths


def _render(tmp_path, n=5, seed=0):
    sc = board_scene(np.random.default_rng(seed), n_views=n, board=BOARD, camera=CAM, noise_px=0.0, fill=0.55)
    return _render_poses(tmp_path, sc.poses)


def test_calibrate_chessboard_images(tmp_path):
    paths = _render(tmp_path)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((240, 320), 200, np.uint8))
    out = tmp_path / "camera.json"
    r = CliRunner().invoke(cli, ["calibrate", *paths, str(blank), "--chessboard", "7x5", "--square", "30mm",
                                 "-o", str(out), "--report", str(tmp_path / "rep"), "--distortion", "k1,k2,p1,p2"])
    assert r.exit_code == 0, r.output
    assert "board not found in 1 of 6 images: blank.png (left out)" in r.output
    assert "found in 5 of 6 images, 320 x 240 px" in r.output
    assert "corners (symmetry refinement): 175 of 175 kept" in r.output
    cam = camera_from_dict(json.loads(out.read_text()))
    assert abs(cam.intrinsics.fx - 420) < 4 and abs(cam.intrinsics.cx - 161) < 4 and abs(cam.intrinsics.cy - 118) < 4
    assert cam.sigma0_px is not None and cam.sigma0_px < 0.2
    for name in ("report.html", "fig_calibration_distortion.png", "fig_calibration_coverage.png",
                 "fig_calibration_residuals_per_view.png", "fig_calibration_correlation.png", "calibration.json"):
        assert (tmp_path / "rep" / name).is_file(), name
    # no --overwrite: refused, file untouched
    before = out.read_text()
    r = CliRunner().invoke(cli, ["calibrate", *paths, "--chessboard", "7x5", "-o", str(out)])
    assert r.exit_code == 1 and "exists" in r.output and out.read_text() == before


def test_calibrate_board_not_found_everywhere(tmp_path):
    paths = _render(tmp_path, n=3)
    out = tmp_path / "cam.json"
    r = CliRunner().invoke(cli, ["calibrate", *paths, "--chessboard", "9x6", "-o", str(out)])
    assert r.exit_code == 1
    assert "chessboard 9x6 found in only 0 of 3 images (not found: board0.png, board1.png, board2.png)" in r.output
    assert "Traceback" not in r.output and not out.exists()


@pytest.mark.parametrize("args, msg", [
    ([], "no input"),
    (["IMG"], "need --chessboard"),
    (["IMG", "--chessboard", "9by6"], "chessboard pattern must look like 9x6"),
    (["--points", "OBS"], "--points needs --size"),
    (["--points", "OBS", "--size", "640x480"], "no object coordinates"),
    (["--points", "OBS", "--field", "FIELD", "--size", "64x48"], "outside the 64 x 48 image"),
    (["--points", "OBS", "--field", "FIELD", "--size", "640x480", "--pixel-size", "0.005"], None),
])
def test_calibrate_cli_errors(tmp_path, args, msg):
    sc = field_scene(np.random.default_rng(3), n_views=2, n_points=40, noise_px=0.2)
    obs = ["view,point,col,row"] + [f"{v.name},{p},{c},{r}" for v in sc.views
                                    for p, (c, r) in zip(v.ids, v.pixel, strict=True)]
    v0 = sc.views[0]
    field = ["point,x,y,z"] + [f"{p},{x},{y},{z}" for p, (x, y, z) in zip(v0.ids, v0.object_xyz, strict=True)]
    (tmp_path / "obs.csv").write_text("\n".join(obs) + "\n")
    (tmp_path / "field.csv").write_text("\n".join(field) + "\n")
    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.zeros((48, 64), np.uint8))
    sub = {"OBS": str(tmp_path / "obs.csv"), "FIELD": str(tmp_path / "field.csv"), "IMG": str(img)}
    out = tmp_path / "cam.json"
    r = CliRunner().invoke(cli, ["calibrate", *[sub.get(a, a) for a in args], "-o", str(out)])
    if msg is None:  # the good case: a millimetre camera from a 3D field
        assert r.exit_code == 0, r.output
        assert "3D test field: 80 measured points in 2 views" in r.output and "(mm camera)" in r.output
        d = json.loads(out.read_text())
        assert d["pixel_size_mm"] == 0.005 and abs(d["focal_length_mm"] - 4.0) < 0.1
        return
    assert r.exit_code == 1 and msg in r.output, r.output
    assert "Traceback" not in r.output and not out.exists()


def test_calibrate_rig_images(tmp_path):
    """Two cameras on a rig: rendered synchronous views; the rig JSON has both cameras and the base."""
    left, right = rig_scene(np.random.default_rng(0), n_views=4, left=CAM, board=BOARD, rel_rotvec=(0.0, 0.1, 0.0),
                            rel_t=(-2.0, 0.05, 0.1), noise_px=0.0)
    lp = _render_poses(tmp_path, left.poses, "left")
    _render_poses(tmp_path, right.poses, "right")
    out = tmp_path / "rig.json"
    r = CliRunner().invoke(cli, ["calibrate", *lp, "--right", str(tmp_path / "right*.png"), "--chessboard", "7x5",
                                 "-o", str(out), "--distortion", "k1,p1,p2", "--equal-focal"])
    assert r.exit_code == 0, r.output
    assert "rig: chessboard 7x5 (square 1 unit) in 4 of 4 pairs" in r.output and "base (" in r.output
    d = json.loads(out.read_text())
    assert d["format"] == "rectify-stereo/rig"
    assert abs(camera_from_dict(d["right"]).intrinsics.fx - 420) < 6
    Rr = rodrigues(np.array([0.0, 0.1, 0.0]))[0]
    base_true = np.diag([1.0, -1.0, -1.0]) @ (-Rr.T @ np.array([-2.0, 0.05, 0.1]))
    assert np.allclose(d["base"], base_true, atol=0.05), (d["base"], base_true)
    r = CliRunner().invoke(cli, ["calibrate", *lp[:3], "--right", str(tmp_path / "right*.png"), "--chessboard", "7x5",
                                 "-o", str(tmp_path / "rig2.json")])
    assert r.exit_code == 1 and "3 left images but 4 right images" in r.output
