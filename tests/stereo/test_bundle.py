"""Bundle adjustment of a block (stereo.block.bundle) on synthetic blocks with known truth."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.camera import Camera
from rectify.rotation import matrix_from_angles
from stereo.block.bundle import BlockControl, GnssObservations, adjust_bundle
from stereo.block.bundle_model import interior_from_camera, project, rotation_axes, rotations
from stereo.block.synthetic import make_block
from stereo.block.types import Pose, project_pixel

DIST = Camera(focal_length_mm=100.0, pixel_size_mm=0.01, width=2000, height=1500, principal_point_mm=(0.03, -0.02),
              distortion={"k1": -0.08, "k2": 0.02, "k3": -0.01, "p1": 2e-4, "p2": -1e-4})


def _model(camera: Camera, pose: Pose, X: np.ndarray, jacobian: bool = True):
    m = len(X)
    ang = pose.angles[None, :]
    R = np.repeat(rotations(ang), m, axis=0)
    ax = np.repeat(rotation_axes(ang), m, axis=0)
    intr = np.repeat(interior_from_camera(camera)[None], m, axis=0)
    return project(R, np.repeat(pose.position[None], m, axis=0), ax, intr, np.full(m, camera.pixel_size_mm),
                   np.repeat([[(camera.width - 1) / 2, (camera.height - 1) / 2]], m, axis=0), X, jacobian=jacobian)


def _pose(angles, position, name="a") -> Pose:
    return Pose(name, "cam", np.asarray(position, float), matrix_from_angles(*angles))


# ------------------------------------------------------------------ the model
def test_model_equals_project_pixel_with_distortion():
    rng = np.random.default_rng(1)
    pose = _pose((0.02, -0.03, 2.9), (10.0, 20.0, 1000.0))
    X = np.column_stack([rng.uniform(-60, 80, 50), rng.uniform(-40, 80, 50), rng.uniform(-30, 30, 50)])
    pix = _model(DIST, pose, X, jacobian=False)[0]
    np.testing.assert_allclose(pix, project_pixel(DIST, pose, X), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(om=st.floats(-0.3, 0.3), ph=st.floats(-0.3, 0.3), ka=st.floats(-np.pi, np.pi),
       cx=st.floats(-100, 100), cy=st.floats(-100, 100), h=st.floats(300, 3000))
def test_model_equals_project_pixel_property(om, ph, ka, cx, cy, h):
    pose = _pose((om, ph, ka), (cx, cy, h))
    rng = np.random.default_rng(2)
    # points near the optical axis, in front of the camera
    rays = np.column_stack([rng.uniform(-6, 6, 20), rng.uniform(-5, 5, 20), np.full(20, -100.0)])
    X = pose.position + (rays @ pose.rotation.T) * (h / 100.0)
    pix = _model(DIST, pose, X, jacobian=False)[0]
    np.testing.assert_allclose(pix, project_pixel(DIST, pose, X), atol=1e-7)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    pose = _pose((0.05, -0.04, 0.3), (5.0, -3.0, 900.0))
    X = np.column_stack([rng.uniform(-60, 60, 8), rng.uniform(-50, 50, 8), rng.uniform(-20, 20, 8)])
    pix, _, Jpose, Jpt, Jint = _model(DIST, pose, X)
    ang0, C0, intr0 = pose.angles, pose.position, interior_from_camera(DIST)
    m = len(X)

    def f(ang, C, intr, Xp):
        R = np.repeat(rotations(ang[None]), m, axis=0)
        return project(R, np.repeat(C[None], m, 0), np.repeat(rotation_axes(ang[None]), m, 0),
                       np.repeat(intr[None], m, 0), np.full(m, DIST.pixel_size_mm),
                       np.repeat([[(DIST.width - 1) / 2, (DIST.height - 1) / 2]], m, 0), Xp, jacobian=False)[0]

    def num(k, which, eps):
        a, c, i, x = ang0.copy(), C0.copy(), intr0.copy(), X.copy()
        vec = {"a": a, "c": c, "i": i}
        if which == "x":
            xp, xm = X.copy(), X.copy()
            xp[:, k] += eps
            xm[:, k] -= eps
            return (f(a, c, i, xp) - f(a, c, i, xm)) / (2 * eps)
        v = vec[which]
        v[k] += eps
        up = f(a, c, i, x)
        v[k] -= 2 * eps
        return (up - f(a, c, i, x)) / (2 * eps)

    for k in range(3):
        np.testing.assert_allclose(Jpose[:, :, k], num(k, "a", 1e-7), rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(Jpose[:, :, 3 + k], num(k, "c", 1e-4), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(Jpt[:, :, k], num(k, "x", 1e-4), rtol=1e-5, atol=1e-6)
    for k, eps in enumerate((1e-5, 1e-6, 1e-6, 1e-7, 1e-7, 1e-7, 1e-8, 1e-8)):
        np.testing.assert_allclose(Jint[:, :, k], num(k, "i", eps), rtol=1e-4, atol=1e-3)


# ------------------------------------------------------------------ exact data
def _exact_block(**kw):
    return make_block(0, image_noise_px=0.0, gnss_noise_m=0.0, control_noise_m=0.0, **kw)


def test_exact_data_recovers_truth_from_perturbed_start():
    b = _exact_block(camera=DIST)
    ctrl = BlockControl(b.control.ids, b.control.xyz, b.control.kind, np.full_like(b.control.xyz, 0.05),
                        b.control.check)
    gn = GnssObservations(b.gnss.images, b.gnss.position, np.full((len(b.gnss.images), 3), 0.1))
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=ctrl, gnss=gn)
    assert r.converged
    ext = np.ptp(b.true_points, axis=0).max()
    assert np.abs(r.points - b.true_points).max() < 1e-6 * ext
    for p, q in zip(r.poses, b.true_poses, strict=True):
        assert np.abs(p.position - q.position).max() < 1e-6 * ext
        np.testing.assert_allclose(p.rotation, q.rotation, atol=1e-8)
    assert r.rms_px < 1e-6
    assert not r.flagged.any()
    np.testing.assert_allclose(r.check_errors, 0.0, atol=1e-6 * ext)
