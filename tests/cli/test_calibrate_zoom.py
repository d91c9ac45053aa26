"""``stereo calibrate --zoom`` end to end: synthetic views of a board rendered with known cameras at several focal
settings (``tests.support.calibration_synthetic.zoom_camera``), the zoom camera JSON evaluated by the readers the
other commands use, and the bad input of a zoom calibration."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.camera import read_camera, read_zoom_camera
from rectify.formats.detect import read_one_camera
from rectify.geometry.rotation import rodrigues
from rectify.geometry.zoom import ZOOM_MARGIN, ZoomCamera
from rectify.raster.exif import parse_exif_number
from stereo.calibration.model import Intrinsics
from stereo.cli.main import cli
from stereo.features.targets import Chessboard
from stereo.formats.calibration import camera_from_dict
from tests.support.calibration_synthetic import board_scene, zoom_camera

DIST = "k1,k2,p1,p2"


def _obs_csv(path, settings, *, n_views=3, noise_px=0.3, column=True):
    """Observation CSV (view,point,col,row,x,y,z[,setting]) of board views at each setting, rendered with
    :func:`zoom_camera` (seeded by the setting, as tests/stereo/test_calibration_zoom_rig.py)."""
    lines = ["view,point,col,row,x,y,z" + (",setting" if column else "")]
    for z in settings:
        sc = board_scene(np.random.default_rng(int(z)), n_views=n_views, camera=zoom_camera(z), noise_px=noise_px,
                         fill=0.5)
        for v in sc.views:
            for pid, (c, r), X in zip(v.ids, v.pixel, v.object_xyz, strict=True):
                row = f"z{z:g}_{v.name},{pid},{float(c)!r},{float(r)!r},{float(X[0])!r},{float(X[1])!r},{float(X[2])!r}"
                lines.append(row + (f",{z:g}" if column else ""))
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(*args):
    return CliRunner().invoke(cli, ["calibrate", *map(str, args)])


@pytest.fixture(scope="module")
def zoom_files(tmp_path_factory):
    """The zoom camera from settings 10, 15, 25, 30 and the held-out camera of setting 20, both by the CLI."""
    d = tmp_path_factory.mktemp("zoom")
    train = _obs_csv(d / "train.csv", (10.0, 15.0, 25.0, 30.0))
    held = _obs_csv(d / "held.csv", (20.0,), column=False)
    r = _run("--zoom", "--points", train, "--size", "640x480", "--distortion", DIST, "-o", d / "zoom.json")
    assert r.exit_code == 0, r.output
    r2 = _run("--points", held, "--size", "640x480", "--distortion", DIST, "-o", d / "cam20.json")
    assert r2.exit_code == 0, r2.output
    return d, r.output


def test_zoom_cli_predicts_held_out_setting(zoom_files):
    """The zoom camera written by the CLI, evaluated at the held-out setting 20 by the camera reader of the
    commands, agrees with the CLI's own calibration of setting 20: every element within 2 combined standard
    errors, their RMS within 1.5; and the truth within 3 standard errors of the prediction."""
    d, out = zoom_files
    assert "zoom model: degree 2 over 4 settings 10..30" in out
    assert "held out 15 (predicted from the other settings)" in out and "held out 25" in out
    cam = read_one_camera(d / "zoom.json", focal_setting=20.0)
    held = camera_from_dict(json.loads((d / "cam20.json").read_text()))
    K, hi = cam.K, held.intrinsics
    pred = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], **cam.distortion}
    key = {n: (f"{n}_px" if n in ("fx", "fy", "cx", "cy") else n) for n in ("fx", "fy", "cx", "cy", *DIST.split(","))}
    zs = {n: (pred[n] - getattr(hi, n)) / math.hypot(cam.std_errors[k], held.std_errors[k]) for n, k in key.items()}
    se = {n: cam.std_errors[k] for n, k in key.items()}
    assert len(zs) == 8
    assert max(abs(z) for z in zs.values()) < 2.0, zs
    assert math.sqrt(np.mean(np.square(list(zs.values())))) < 1.5, zs
    truth = zoom_camera(20.0)
    for n in ("fx", "fy", "cx", "cy", "k1"):
        assert abs(pred[n] - getattr(truth, n)) < 3 * se[n], (n, pred[n], getattr(truth, n), se[n])


def test_zoom_camera_file_and_range(zoom_files):
    d, _ = zoom_files
    doc = json.loads((d / "zoom.json").read_text())
    assert doc["format"] == "rectify-stereo/zoom-camera" and doc["degree"] == 2
    assert doc["settings"] == [10.0, 15.0, 25.0, 30.0] and len(doc["calibrations"]) == 4
    zc = read_zoom_camera(d / "zoom.json")
    # inside the range plus the margin: accepted; the ends give the calibrations' values within their errors
    assert read_camera(d / "zoom.json", focal_setting=30.0 + 0.9 * ZOOM_MARGIN * 20).width == 640
    v, se = zc.predict(10.0)
    c10 = doc["calibrations"][0]
    assert abs(v["fx"] - c10["values"]["fx"]) < 3 * c10["std_errors"]["fx"]
    with pytest.raises(CalibrationError, match=r"focal setting 31 is outside the zoom camera's calibrated range "
                                               r"10\.\.30 \(margin 0\.2\)"):
        read_camera(d / "zoom.json", focal_setting=31.0)
    with pytest.raises(InvalidInputError, match="is a zoom camera .*give the image's focal setting"):
        read_one_camera(d / "zoom.json")


def _tiff_with_focal(path, img, focal):
    with rasterio.open(path, "w", driver="GTiff", width=img.shape[1], height=img.shape[0], count=1,
                       dtype="uint8") as dst:
        dst.write(img[None])
        if focal is not None:
            dst.update_tags(EXIF_FocalLength=f"({focal:g})")


def test_zoom_from_chessboard_images_with_exif(tmp_path):
    """Chessboard images (no distortion) at three EXIF focal lengths: a degree-1 zoom camera; an image with
    EXIF FocalLength then gets its camera from the zoom file through the --camera reader."""
    board = Chessboard(7, 5, 1.0)
    tex = np.full((280, 360), 255, np.uint8)
    for j in range(6):
        for i in range(8):
            if (i + j) % 2 == 0:
                tex[20 + 40 * j:60 + 40 * j, 20 + 40 * i:60 + 40 * i] = 0
    A = np.array([[1 / 40, 0, -60 / 40 + 0.5 / 40], [0, 1 / 40, -60 / 40 + 0.5 / 40], [0, 0, 1.0]])
    paths = []
    for z in (20.0, 25.0, 30.0):
        cam = Intrinsics(fx=16.0 * z, fy=16.0 * z, cx=161.0, cy=118.0, width=320, height=240)
        sc = board_scene(np.random.default_rng(int(z)), n_views=3, board=board, camera=cam, noise_px=0.0, fill=0.55)
        for k, pose in enumerate(sc.poses):
            R = rodrigues(pose[:3])[0]
            H = cam.K @ np.column_stack([R[:, 0], R[:, 1], pose[3:]]) @ A
            img = cv2.warpPerspective(tex, H, (320, 240), flags=cv2.INTER_AREA, borderValue=255)
            p = tmp_path / f"z{z:g}_{k}.tif"
            _tiff_with_focal(p, img, z)
            paths.append(p)
    out = tmp_path / "zoom.json"
    r = _run(*paths, "--zoom", "--zoom-degree", "1", "--chessboard", "7x5", "--distortion", "none",
             "--equal-focal", "-o", out)
    assert r.exit_code == 0, r.output
    assert "setting 25 mm: 3 views" in r.output and "degree 1 over 3 settings 20..30 mm" in r.output
    assert "held out 25 mm" in r.output
    c25 = read_one_camera(out, image=paths[4])  # EXIF FocalLength 25 mm
    assert c25.K[0, 0] == pytest.approx(400.0, abs=4.0)
    assert c25.K[0, 0] == pytest.approx(read_one_camera(out, focal_setting=25.0).K[0, 0])
    # an image without EXIF FocalLength and no --focal-setting: refused, the image named
    bare = tmp_path / "bare.tif"
    _tiff_with_focal(bare, np.zeros((240, 320), np.uint8), None)
    with pytest.raises(InvalidInputError, match="bare.tif' has no EXIF FocalLength: give its focal setting"):
        read_one_camera(out, image=bare)


def test_parse_exif_number():
    assert parse_exif_number("(24.5)") == 24.5
    assert parse_exif_number("245/10") == 24.5
    assert parse_exif_number(" 35 ") == 35.0
    assert parse_exif_number("(0)") is None and parse_exif_number("abc") is None


@pytest.mark.parametrize(("settings", "extra", "msg"), [
    ((10.0, 30.0), (), "a zoom model of degree 2 needs views at 3 focal settings at least; got 2 (10, 30)"),
    ((10.0, 20.0, 30.0), ("--zoom-degree", "3"), "a zoom model of degree 3 needs views at 4 focal settings at "
                                                 "least; got 3 (10, 20, 30)"),
])
def test_zoom_too_few_settings(tmp_path, settings, extra, msg):
    obs = _obs_csv(tmp_path / "obs.csv", settings, n_views=1)
    out = tmp_path / "zoom.json"
    r = _run("--zoom", "--points", obs, "--size", "640x480", *extra, "-o", out)
    assert r.exit_code != 0 and msg in r.output, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1
    assert not out.exists()


def test_zoom_views_without_setting(tmp_path):
    obs = _obs_csv(tmp_path / "obs.csv", (10.0, 20.0, 30.0), n_views=1, column=False)
    obs3 = _obs_csv(tmp_path / "obs3.csv", (10.0, 20.0, 30.0), n_views=3, column=False)
    before = obs.read_text()
    out = tmp_path / "zoom.json"
    r = _run("--zoom", "--points", obs, "--size", "640x480", "-o", out)
    assert r.exit_code != 0 and "no focal setting for 3 views: z10_view00, z20_view00, z30_view00" in r.output
    assert not out.exists() and obs.read_text() == before
    # a settings file naming two of the three views: the third is named
    st = tmp_path / "settings.csv"
    st.write_text("view,setting\nz10_view00,10\nz20_view00,20\n")
    r = _run("--zoom", "--points", obs, "--size", "640x480", "--settings", st, "-o", out)
    assert r.exit_code != 0 and "no focal setting for 1 views: z30_view00" in r.output, r.output
    assert not out.exists()
    st.write_text("view,setting\n" + "".join(f"z{z}_view0{k},{z}\n" for z in (10, 20, 30) for k in range(3)))
    r = _run("--zoom", "--points", obs3, "--size", "640x480", "--settings", st, "--zoom-degree", "1", "-o", out)
    assert r.exit_code == 0, r.output
    assert out.exists()


@pytest.mark.parametrize(("args", "msg"), [
    (["--settings", "{st}"], "--settings gives the focal settings of a zoom calibration: add --zoom"),
    (["--zoom", "--pixel-size", "0.005"], "--pixel-size is not available with --zoom"),
    (["--zoom", "--symmetry"], "--symmetry is not available with --zoom"),
    (["--zoom", "-o", "{out}.yml"], "a zoom camera is written as a zoom camera JSON (.json)"),
])
def test_zoom_bad_options(tmp_path, args, msg):
    obs = _obs_csv(tmp_path / "obs.csv", (10.0, 20.0, 30.0), n_views=1)
    st = tmp_path / "st.csv"
    st.write_text("view,setting\nx,1\n")
    out = tmp_path / "zoom"
    sub = [a.format(st=st, out=out) for a in args]
    if "-o" not in sub:
        sub += ["-o", f"{out}.json"]
    r = _run("--points", obs, "--size", "640x480", *sub)
    assert r.exit_code != 0 and msg in r.output, r.output
    assert not list(tmp_path.glob("zoom*"))


def _pair_matches(path, cam, rng):
    """A matches CSV of a convergent-free pair: points 10 m ahead, base 1 m along x, seen by ``cam`` (photo y up)."""
    X = rng.uniform([-1.5, -1.5, -12], [2.5, 1.5, -9], (40, 3))
    f = cam.focal_length_mm
    left = cam.pixel_from_photo(-f * X[:, :2] / X[:, 2:])
    Xr = X - np.array([1.0, 0.0, 0.0])
    right = cam.pixel_from_photo(-f * Xr[:, :2] / Xr[:, 2:])
    rows = ["id,col_left,row_left,col_right,row_right"]
    rows += [f"p{i},{a[0]!r},{a[1]!r},{b[0]!r},{b[1]!r}" for i, (a, b) in enumerate(zip(left.tolist(), right.tolist(),
                                                                                          strict=True))]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_stereo_orient_evaluates_zoom_camera(zoom_files, tmp_path):
    """``stereo orient --camera zoom.json --focal-setting 20``: the camera of setting 20 is used and stored;
    outside the calibrated range or without a setting: one-line errors, nothing written."""
    d, _ = zoom_files
    cam20 = read_one_camera(d / "zoom.json", focal_setting=20.0)
    m = _pair_matches(tmp_path / "m.csv", cam20, np.random.default_rng(1))
    out = tmp_path / "ro.json"
    r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "zoom.json"), "--matches", str(m),
                                 "--focal-setting", "20", "-o", str(out)])
    assert r.exit_code == 0, r.output
    stored = json.loads(out.read_text())
    assert stored["camera"]["fx_px"] == pytest.approx(cam20.K[0, 0])
    assert stored["camera"]["fy_px"] == pytest.approx(cam20.K[1, 1])
    # two settings: a camera per image, both stored
    out2 = tmp_path / "ro2.json"
    r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "zoom.json"), "--matches", str(m),
                                 "--focal-setting", "20,21", "-o", str(out2)])
    assert r.exit_code == 0, r.output
    two = json.loads(out2.read_text())
    cam21 = read_one_camera(d / "zoom.json", focal_setting=21.0)
    assert two["camera"]["fx_px"] == pytest.approx(cam20.K[0, 0])
    assert two["camera_right"]["fx_px"] == pytest.approx(cam21.K[0, 0])
    assert abs(cam21.K[0, 0] - cam20.K[0, 0]) > 10.0  # about 40 px per setting step
    for extra, msg in ((["--focal-setting", "20,40"], "focal setting 40 is outside the zoom camera's calibrated "
                                                       "range 10..30"),
                       ([], "is a zoom camera (calibrated 10..30): give the image's focal setting"),
                       (["--focal-setting", "x"], "--focal-setting must be Z or ZLEFT,ZRIGHT (numbers); got 'x'")):
        bad = tmp_path / "bad.json"
        r = CliRunner().invoke(cli, ["orient", "--camera", str(d / "zoom.json"), "--matches", str(m), *extra,
                                     "-o", str(bad)])
        assert r.exit_code != 0 and msg in r.output, r.output
        assert len(r.output.strip().splitlines()) == 1 and not bad.exists()


def test_stereo_run_refuses_zoom_camera_without_one_setting(zoom_files, tmp_path):
    """``stereo run`` (one camera for both photos) with a zoom camera: photos at different EXIF focal lengths,
    or without EXIF: one-line errors before any matching, nothing written."""
    d, _ = zoom_files
    img = np.zeros((480, 640), np.uint8)
    left, right, bare = tmp_path / "l.tif", tmp_path / "r.tif", tmp_path / "bare.tif"
    _tiff_with_focal(left, img, 20.0)
    _tiff_with_focal(right, img, 25.0)
    _tiff_with_focal(bare, img, None)
    for a, b, msg in ((left, right, "their EXIF focal lengths differ (20.0 and 25.0 mm): orient the pair with "
                                     "stereo orient"),
                      (bare, right, "is a zoom camera, but image '" + str(bare) + "' has no EXIF FocalLength")):
        out = tmp_path / "out"
        r = CliRunner().invoke(cli, ["run", str(a), str(b), "--camera", str(d / "zoom.json"), "-o", str(out)])
        assert r.exit_code != 0 and msg in r.output, r.output
        assert len(r.output.strip().splitlines()) == 1 and not out.exists()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=3, max_size=3), st.floats(5.0, 40.0), st.floats(1.0, 30.0),
       st.floats(-0.2, 1.2))
def test_zoom_camera_polynomial_and_range(coefs, low, span, t):
    """ZoomCamera evaluates sum a_k u^k with u = (z - centre) / half_range; accepts [low - m, high + m] and
    refuses the rest (m = ZOOM_MARGIN * span), naming the range."""
    z = np.array([low, low + span / 2, low + span])
    half = span / 2
    cov = np.eye(3) * 0.01
    a = {n: np.array([v, *coefs[1:]]) for n, v in (("f", 800 + coefs[0]), ("cx", 320.0), ("cy", 240.0))}
    zc = ZoomCamera(z, 2, low + half, half, a, {n: cov for n in a}, 640, 480, "mm")
    s = low + t * span
    assert zc.margin == pytest.approx(ZOOM_MARGIN * span)
    inside = zc.low - zc.margin <= s <= zc.high + zc.margin
    if inside:
        v, se = zc.predict(s)
        u = (s - low - half) / half
        assert v["f"] == pytest.approx(800 + coefs[0] + coefs[1] * u + coefs[2] * u * u, abs=1e-9)
        assert se["cx"] == pytest.approx(0.1 * math.sqrt(1 + u * u + u ** 4))
        assert ZoomCamera.from_dict(json.loads(json.dumps(zc.to_dict()))).predict(s)[0]["f"] == pytest.approx(v["f"])
    else:
        with pytest.raises(CalibrationError, match="outside the zoom camera's calibrated range"):
            zc.predict(s)


def test_malformed_zoom_camera_file(tmp_path):
    m = tmp_path / "m.csv"
    m.write_text("id,col_left,row_left,col_right,row_right\np1,10,10,5,10\n")
    for body, msg in (({"width": 640}, "zoom camera JSON lacks key(s) ['height', 'degree', 'settings'"),
                      ({"width": 640, "height": 480, "degree": 1, "settings": [10, 20], "centre": 15,
                        "half_range": 5, "elements": {"fx": {"coefficients": [1, 2], "covariance": [[1, 0], [0, 1]]}}},
                       "zoom camera lacks the focal length or the principal point; has ['fx']"),
                      ({"width": 640, "height": 480, "degree": 2, "settings": [10, 20], "centre": 15,
                        "half_range": 5, "elements": {}}, "zoom camera `elements` must be an object of elements")):
        p = tmp_path / "zoom.json"
        p.write_text(json.dumps({"format": "rectify-stereo/zoom-camera", "version": 1, **body}))
        out = tmp_path / "ro.json"
        r = CliRunner().invoke(cli, ["orient", "--camera", str(p), "--matches", str(m), "--focal-setting", "12",
                                     "-o", str(out)])
        assert r.exit_code != 0 and msg in r.output, r.output
        assert len(r.output.strip().splitlines()) == 1 and not out.exists()
