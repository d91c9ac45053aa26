"""Zoom-camera model and two-camera rig calibration on synthetic scenes with known truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rectify.errors import CalibrationError, InvalidInputError
from rectify.geometry.rotation import rodrigues
from stereo.calibration.model import CV_FROM_PHOTO
from stereo.calibration.result import Calibration
from stereo.calibration.rig import RigCalibration
from stereo.calibration.zoom import ZoomModel
from stereo.formats.calibration import camera_from_dict
from tests.support.calibration_synthetic import board_scene, rig_scene, zoom_camera

DIST = ("k1", "k2", "p1", "p2")


@pytest.fixture(scope="module")
def zoom_cals():
    out = {}
    for z in (10.0, 15.0, 20.0, 25.0, 30.0):
        sc = board_scene(np.random.default_rng(int(z)), n_views=3, camera=zoom_camera(z), noise_px=0.3, fill=0.5)
        out[z] = Calibration.from_views(sc.views, 640, 480, distortion=DIST)
    return out


def test_zoom_model_predicts_held_out_setting(zoom_cals):
    """Quadratic model from 4 settings predicts the held-out setting (20) within 2 combined standard errors
    for every element (RMS of the normalised differences < 1.5), and the truth within 3 of its own."""
    train = [10.0, 15.0, 25.0, 30.0]
    zm = ZoomModel.from_calibrations(train, [zoom_cals[z] for z in train], degree=2)
    val, se = zm.predict(20.0)
    held = zoom_cals[20.0]
    zs = [(val[n] - held.value(n)) / math.hypot(se[n], held.std_errors[n]) for n in zm.names]
    assert max(abs(z) for z in zs) < 2.0, dict(zip(zm.names, zs, strict=True))
    assert float(np.sqrt(np.mean(np.square(zs)))) < 1.5
    truth = zoom_camera(20.0)
    for n in ("fx", "fy", "cx", "cy", "k1"):
        assert abs(val[n] - getattr(truth, n)) < 3 * se[n], (n, val[n], getattr(truth, n), se[n])
    intr = zm.intrinsics(20.0)
    assert intr.fx == pytest.approx(val["fx"])
    d = json.loads(json.dumps(zm.to_dict()))
    assert d["degree"] == 2 and set(d["elements"]) == set(zm.names)


def test_zoom_bad_input(zoom_cals):
    cals = [zoom_cals[10.0], zoom_cals[30.0]]
    with pytest.raises(CalibrationError, match="too few focal settings for a degree-2 model: 2 given, at least 3"):
        ZoomModel.from_calibrations([10, 30], cals, degree=2)
    with pytest.raises(InvalidInputError, match="2 settings for 1 calibrations"):
        ZoomModel.from_calibrations([10, 30], cals[:1])
    with pytest.raises(InvalidInputError, match="repeated focal settings"):
        ZoomModel.from_calibrations([10, 10], cals, degree=1)
    with pytest.raises(CalibrationError, match=r"\['k3'\] not estimated"):
        ZoomModel.from_calibrations([10, 30], cals, degree=1, names=["fx", "k3"])


def test_rig_recovers_relative_orientation():
    rel_rv, rel_t = (0.01, 0.2, 0.005), (-120.0, 1.5, 4.0)
    left, right = rig_scene(np.random.default_rng(3), n_views=4, rel_rotvec=rel_rv, rel_t=rel_t, noise_px=0.2)
    rig = RigCalibration.from_views(left.views, right.views, 640, 480, distortion=DIST)
    Rr = rodrigues(np.array(rel_rv))[0]
    base_true = CV_FROM_PHOTO @ (-Rr.T @ np.array(rel_t))
    assert np.all(np.abs(rig.base - base_true) < 3.5 * rig.std_base), (rig.base, base_true, rig.std_base)
    R_true = CV_FROM_PHOTO @ Rr.T @ CV_FROM_PHOTO
    ang = np.degrees(np.arccos(np.clip((np.trace(rig.rotation_right.T @ R_true) - 1) / 2, -1, 1)))
    assert ang < 3.5 * np.degrees(rig.std_angles.max())
    assert abs(rig.left.fx - 800) < 4 * rig.std_left["fx"]
    d = json.loads(json.dumps(rig.to_dict()))
    assert d["format"] == "rectify-stereo/rig"
    assert camera_from_dict(d["right"]).intrinsics.fx == pytest.approx(rig.right.fx)
    assert "base (" in rig.summary_lines()[-1]
    with pytest.raises(InvalidInputError, match="4 left views but 3 right views"):
        RigCalibration.from_views(left.views, right.views[:3], 640, 480)
