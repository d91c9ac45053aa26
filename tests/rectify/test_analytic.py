"""Tests of rectify.geometry.analytic (seed 001, eq. 1)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import InvalidInputError
from rectify.geometry.analytic import TiltedFrame
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.transforms import CotangentFourPoint, Homography
from tests.support.transforms_support import rectify_tilted

F = 1000.0  # Resurs-F: f = 1000 mm, 300 x 300 mm frame
FRAME = np.array([[-150.0, -150.0], [150.0, -150.0], [150.0, 150.0], [-150.0, 150.0]])


def _grid(n=7, half=150.0):
    g = np.linspace(-half, half, n)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def test_vertical_frame_is_identity_up_to_principal_point():
    fr = TiltedFrame(F, np.eye(3), principal_point_mm=(0.3, -0.2))
    g = _grid()
    assert_allclose(fr(g), g - [0.3, -0.2], atol=1e-12)
    assert fr.tilt == 0.0


def test_pure_omega_known_answer():
    """R = Rx(omega): the principal point maps to (0, f tan omega); y0 = -f (y cos w + f sin w)/(y sin w - f cos w)."""
    w = math.radians(7.0)
    fr = TiltedFrame.from_angles(F, w, 0.0, 0.0)
    y = np.array([-150.0, 0.0, 80.0])
    out = fr(np.column_stack([np.zeros(3), y]))
    expect = -F * (y * math.cos(w) + F * math.sin(w)) / (y * math.sin(w) - F * math.cos(w))
    assert_allclose(out[:, 1], expect, rtol=1e-13)
    assert_allclose(out[:, 0], 0.0, atol=1e-12)
    assert out[1, 1] == pytest.approx(F * math.tan(w), rel=1e-13)
    assert fr.tilt == pytest.approx(w, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.18, 0.18), st.floats(-0.18, 0.18), st.floats(-math.pi, math.pi),
       st.sampled_from(["omega-phi-kappa", "phi-omega-kappa", "omega-alpha-chi"]),
       st.floats(-2.0, 2.0), st.floats(-2.0, 2.0))
def test_eq1_equals_fitted_homography(a1, a2, a3, order, x0, y0):
    """Eq. (1) equals the homography fitted to the same points (and the cotangent method)."""
    fr = TiltedFrame.from_angles(F, a1, a2, a3, order=order, principal_point_mm=(x0, y0))
    dst4 = fr(FRAME)
    H = Homography.from_points(FRAME, dst4)
    g = _grid(9)
    scale = np.abs(fr(g)).max()
    assert np.abs(H(g) - fr(g)).max() <= 1e-9 * scale
    assert np.abs(fr.homography(g) - fr(g)).max() <= 1e-9 * scale
    m1 = H.matrix / np.linalg.norm(H.matrix)
    m2 = fr.homography.matrix / np.linalg.norm(fr.homography.matrix)
    assert np.abs(m1 - m2 * np.sign(np.sum(m1 * m2))).max() <= 1e-9
    C = CotangentFourPoint.from_points(FRAME, dst4)
    assert np.abs(C(g) - fr(g)).max() <= 1e-9 * scale
    # many points, least squares: still exact
    Hn = Homography.from_points(g, fr(g))
    assert np.abs(Hn(g) - fr(g)).max() <= 1e-9 * scale
    assert_allclose(fr.inverse(fr(g)), g, atol=1e-9 * 150)


def test_functional_form_and_f_out():
    R = matrix_from_angles(0.05, -0.03, 0.4)
    fr = TiltedFrame(F, R, f_out_mm=500.0)
    g = _grid()
    assert_allclose(rectify_tilted(g, focal_length_mm=F, angles=(0.05, -0.03, 0.4), f_out_mm=500.0), fr(g))
    assert_allclose(fr(g), TiltedFrame(F, R)(g) * 0.5, rtol=1e-12)


def test_pixel_homography_with_camera():
    cam = Camera(focal_length_mm=153.0, pixel_size_mm=0.02, width=1000, height=800)
    fr = TiltedFrame.from_angles(153.0, 0.02, -0.04, 0.1)
    px = np.array([[0.0, 0.0], [999.0, 0.0], [500.0, 400.0], [10.0, 790.0]])
    assert_allclose(fr.pixel_homography(cam)(px), fr(cam.photo_from_pixel(px)), atol=1e-9)
    with pytest.raises(InvalidInputError, match="principal_point_mm=\\(0, 0\\)"):
        TiltedFrame(153.0, np.eye(3), principal_point_mm=(1.0, 0.0)).pixel_homography(cam)
    cam_d = Camera(focal_length_mm=153.0, pixel_size_mm=0.02, width=1000, height=800, distortion={"k1": 0.01})
    with pytest.raises(InvalidInputError, match="distortion-free"):
        fr.pixel_homography(cam_d)


def test_bad_input():
    with pytest.raises(InvalidInputError, match="focal_length_mm"):
        TiltedFrame(0.0, np.eye(3))
    with pytest.raises(InvalidInputError, match="not a proper rotation"):
        TiltedFrame(F, np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(InvalidInputError, match="principal_point_mm"):
        TiltedFrame(F, np.eye(3), principal_point_mm=(np.nan, 0.0))
    with pytest.raises(InvalidInputError, match="angle `a2` must be finite"):
        TiltedFrame.from_angles(F, 0.0, np.inf, 0.0)
    with pytest.raises(InvalidInputError, match="unknown rotation order"):
        TiltedFrame.from_angles(F, 0.0, 0.0, 0.0, order="zyx")
    with pytest.raises(InvalidInputError, match="non-finite"):
        TiltedFrame(F, np.eye(3))([[np.nan, 0.0]])
    fr = TiltedFrame(F, np.eye(3))
    assert fr.residuals(_grid(), _grid()).shape == (49,)
