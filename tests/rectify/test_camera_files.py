"""Camera files in pixels (as written by ``stereo calibrate``) and with standard errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.camera import intrinsics_document as camera_to_dict
from rectify.formats.camera import read_camera, write_camera
from rectify.geometry.camera import NOMINAL_PIXEL_SIZE_MM, Camera
from stereo.calibration.model import Intrinsics

PIXEL_CAMERA = {"focal_length_px": 812.5, "principal_point_px": [321.25, 238.75], "width": 640, "height": 480,
                "distortion": {"k1": -0.21, "k2": 0.05, "k3": 0.0, "p1": 1e-4, "p2": -2e-4},
                "std_errors": {"focal_length_px": 0.8, "cx_px": 0.5}, "sigma0_px": 0.12}


def test_pixel_camera_projects_like_opencv():
    cam = Camera.from_dict(PIXEL_CAMERA)
    assert cam.pixel_camera and cam.pixel_size_mm == NOMINAL_PIXEL_SIZE_MM
    assert_allclose(cam.focal_px, 812.5, rtol=1e-12)
    assert_allclose(cam.principal_point_px, [321.25, 238.75], atol=1e-9)
    # an undistorted ray through the principal point plus (100, 50) px must land where K says
    k = cam.K
    assert_allclose(k, [[812.5, 0, 321.25], [0, 812.5, 238.75], [0, 0, 1]], atol=1e-9)
    px = np.array([[421.25, 288.75], [10.0, 470.0]])
    assert_allclose(cam.pixel_from_photo(cam.photo_from_pixel(px)), px, atol=1e-7)


def test_pixel_camera_round_trip(tmp_path):
    cam = Camera.from_dict(PIXEL_CAMERA)
    p = write_camera(tmp_path / "cam.json", cam)
    doc = json.loads(p.read_text())
    assert doc["format"] == "rectify-stereo/camera" and doc["version"] == 2
    assert "pixel_size_mm" not in doc and doc["focal_length_px"] == pytest.approx(812.5, rel=1e-12)
    back = read_camera(p)
    assert back.pixel_camera and back.std_errors == PIXEL_CAMERA["std_errors"] and back.sigma0_px == 0.12
    assert_allclose(back.K, cam.K, atol=1e-9)
    assert back.distortion == cam.distortion


def test_millimetre_camera_keeps_its_keys(tmp_path):
    d = {"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152,
         "std_errors": {"focal_length_mm": 0.002}}
    back = read_camera(write_camera(tmp_path / "cam.json", Camera.from_dict(d)))
    assert not back.pixel_camera and back.focal_length_mm == 120.0 and back.std_errors == d["std_errors"]


def test_calibration_output_is_read_by_the_rest_of_the_project(tmp_path):
    intr = Intrinsics(fx=900.0, fy=900.0, cx=330.0, cy=250.0, width=640, height=480, k1=-0.1, k2=0.02)
    doc = camera_to_dict(intr, std_errors={"f": 0.9, "cx": 0.4, "cy": 0.5}, sigma0_px=0.2)
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    cam = read_camera(tmp_path / "cal.json")
    assert_allclose(cam.K, [[900, 0, 330], [0, 900, 250], [0, 0, 1]], atol=1e-9)
    assert cam.distortion["k1"] == -0.1 and cam.sigma0_px == 0.2


@pytest.mark.parametrize("bad, message", [
    ({"fx_px": 800.0}, "without `fy_px`"),  # fx_px != fy_px is read (issue 24: tests/stereo/test_seams_camera.py)
    ({"point_of_symmetry_px": [300.0, 200.0]}, "point of symmetry"),
    ({"focal_length_px": -3.0}, "focal_length_px"),
    ({"principal_point_px": [1.0]}, "principal_point_px"),
    ({"sigma0_px": float("nan")}, "sigma0_px"),
    ({"std_errors": {"cx_px": -1.0}}, "standard error"),
    ({"lens": "wide"}, "unknown key"),
])
def test_bad_pixel_cameras_are_refused_by_name(bad, message):
    d = {k: v for k, v in PIXEL_CAMERA.items() if not (k == "focal_length_px" and "fx_px" in bad)}
    d.update(bad)
    with pytest.raises(CalibrationError, match=message):
        Camera.from_dict(d)


def test_newer_camera_version_is_refused(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({"format": "rectify-stereo/camera", "version": 99, **PIXEL_CAMERA}))
    with pytest.raises(InvalidInputError, match="99"):
        read_camera(tmp_path / "c.json")
