"""Blocks of images without a known camera (seed 003, 3.4.1-3.4.4 and 1.2): models, joint affine and
projective orientation, virtual control by vector products, the projective bundle and the metric upgrade.

The synthetic block (3 strips x 4 images, :func:`tests.support.block_synthetic.make_block`) is taken with a
camera of fx 1500, fy 1545 (aspect 1.03) and skew 15 px (shear 0.01), principal point off the centre, over
terrain of 150 m relief from 1000 m; 0.5 px image noise; 9 full control points (corners, centre, the two lowest
and two highest tie points) and 6 check points. The projective path knows none of the camera.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.camera import NOMINAL_PIXEL_SIZE_MM, Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.model import interior_from_camera, project, rotation_axes, rotations
from stereo.block.projective import form_models, join_models, virtual_point
from stereo.block.projective_bundle import uncalibrated_block
from stereo.block.types import BlockControl, Tracks
from tests.support.block_synthetic import make_block

PS = NOMINAL_PIXEL_SIZE_MM
W, H = 2000, 1500
CAM = Camera(focal_length_mm=1500 * PS, pixel_size_mm=PS, width=W, height=H, principal_point_mm=(20 * PS, -15 * PS),
             pixel_camera=True, aspect=1.03, shear=0.01)
TRUTH = {"fx_px": 1500.0, "fy_px": 1545.0, "skew_px": 15.0, "cx_px": (W - 1) / 2 + 20, "cy_px": (H - 1) / 2 + 15}
SIZES = [(W, H)] * 12


def more_control(b, k: int = 4) -> BlockControl:
    """The block's control (5 full points, corners and centre; 6 check points) plus ``k`` full control points
    among the tie points seen 3 times or more: the lowest and the highest (1 cm noise)."""
    rng = np.random.default_rng(0)
    c = b.control
    rays = b.tracks.rays_per_point()
    cand = [i for i, p in enumerate(b.tracks.point_ids) if p not in set(c.ids) and rays[i] >= 3]
    o = np.argsort(b.true_points[cand, 2])
    pick = [cand[j] for j in list(o[: k // 2]) + list(o[-(k - k // 2):])]
    return BlockControl(c.ids + tuple(b.tracks.point_ids[j] for j in pick),
                        np.vstack([c.xyz, b.true_points[pick] + rng.normal(0, 0.01, (k, 3))]),
                        c.kind + ("full",) * k, np.vstack([c.sigma_m, np.full((k, 3), 0.01)]),
                        np.concatenate([c.check, np.zeros(k, bool)]))


@pytest.fixture(scope="module")
def block():
    b = make_block(0, strips=3, images_per_strip=4, camera=CAM, relief_m=150.0, n_points=300, image_noise_px=0.5)
    b = dataclasses.replace(b, control=more_control(b))
    # the metric bundle with the true camera held: the reference of the check-point errors
    ref = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control,
                        options=BundleOptions(max_iterations=50))
    return b, ref


def _rms3d(e) -> float:
    e = np.asarray(e, dtype=np.float64).reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


@pytest.mark.parametrize("method", ["projective", "affine"])
def test_uncalibrated_block_reaches_the_true_camera_bundle_and_recovers_fx_fy_skew(block, method):
    b, ref = block
    r = uncalibrated_block(b.tracks, SIZES, b.control, method=method)
    # the projective bundle fits the image observations at the noise level: sigma0 (a-priori 1 px) ~ 0.5 px
    assert 0.4 < r.projective.sigma0_px < 0.6, r.projective.sigma0_px
    assert r.bundle.converged
    # check points: within 1.5 x the errors of the metric bundle with the true camera
    ours, theirs = _rms3d(r.bundle.check_errors), _rms3d(ref.check_errors)
    assert len(r.bundle.check_ids) == len(ref.check_ids) == 6
    assert ours <= 1.5 * theirs, (ours, theirs)
    # the recovered camera within 2 standard errors of the truth
    for k, (v, sd) in r.interior.items():
        assert np.isfinite(sd) and sd > 0, (k, sd)
        assert abs(v - TRUTH[k]) <= 2 * sd, (k, v, TRUTH[k], sd)
    assert r.bundle.cameras["camera"].aspect != 1.0 and r.bundle.cameras["camera"].shear != 0.0
    if method == "affine":
        assert r.models.n_virtual == len(r.models.models) - 1
    lines = r.summary_lines()
    assert any(line.startswith("camera (px): fx ") for line in lines)


def test_joint_orientation_joins_exact_models_exactly():
    b = make_block(2, strips=2, images_per_strip=3, camera=CAM, relief_m=150.0, n_points=200, image_noise_px=0.0)
    t = b.tracks
    for method in ("projective", "affine"):
        ms = form_models(t, [(W, H)] * 6, method=method)
        mb = join_models(ms, t.n_points, 6, method=method)
        # projective models of exact data are projectively equivalent: they join to rounding; similar models
        # formed with the nominal camera (f = 2000 px for a true 1500 x 1545 px with skew) only nearly affinely
        assert mb.rms_model < (1e-6 if method == "projective" else 0.02), (method, mb.rms_model)


# ------------------------------------------------------------------ vector products (seed 003, 3.4.3)
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000))
def test_virtual_point_is_carried_by_a_similarity_not_by_an_affinity(seed):
    rng = np.random.default_rng(seed)
    p = rng.normal(0, 10, (3, 3))
    if np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0])) < 1e-3:
        return
    R = np.asarray(matrix_from_angles(*rng.uniform(-np.pi, np.pi, 3)))
    s, t = rng.uniform(0.1, 10), rng.normal(0, 100, 3)
    q = s * p @ R.T + t
    v = virtual_point(p[0], p[1], p[2])
    np.testing.assert_allclose(virtual_point(q[0], q[1], q[2]), s * R @ v + t, rtol=1e-9, atol=1e-8 * s * 10)
    A = np.diag([1.0, 1.0, 2.0])  # an affinity: (A a) x (A b) = det(A) A^-T (a x b), not A (a x b)
    a = p @ A.T
    c = np.cross(p[1] - p[0], p[2] - p[0])
    if abs(c[2]) > 1e-3 * np.linalg.norm(c) and np.linalg.norm(c[:2]) > 1e-3 * np.linalg.norm(c):
        assert not np.allclose(virtual_point(a[0], a[1], a[2]), A @ v, rtol=1e-6, atol=1e-6)


def test_interior_jacobian_by_aspect_and_shear_is_the_numeric_one():
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-300, 300, 9), rng.uniform(-200, 200, 9), rng.uniform(0, 60, 9)])
    ang = np.array([[0.02, -0.03, 0.4]])
    C = np.array([10.0, -5.0, 1000.0])
    m = len(X)

    def run(intr):
        return project(np.repeat(rotations(ang), m, 0), np.repeat(C[None], m, 0), np.repeat(rotation_axes(ang), m, 0),
                       np.repeat(intr[None], m, 0), np.full(m, PS), np.repeat([[(W - 1) / 2, (H - 1) / 2]], m, 0), X)

    intr = interior_from_camera(CAM)
    Jint = run(intr)[4]
    assert Jint.shape == (m, 2, 10)
    for k in (8, 9):
        e = np.zeros(10)
        e[k] = 1e-7
        num = (run(intr + e)[0] - run(intr - e)[0]) / 2e-7
        np.testing.assert_allclose(Jint[:, :, k], num, rtol=1e-6, atol=1e-4)


# ------------------------------------------------------------------ bad input
def _control(b, n_full: int) -> BlockControl:
    c = b.control
    keep = [k for k in range(len(c.ids)) if c.check[k]] + [k for k in range(len(c.ids)) if not c.check[k]][:n_full]
    return BlockControl(tuple(c.ids[k] for k in keep), c.xyz[keep], tuple(c.kind[k] for k in keep), c.sigma_m[keep],
                        c.check[keep])


def test_too_few_control_points_for_the_upgrade_name_the_minimum(block):
    b, _ = block
    with pytest.raises(EstimationError, match=r"too few control points for the metric upgrade of the projective "
                                              r"block: 4 .* at least 5 not on one plane .*15 parameters"):
        uncalibrated_block(b.tracks, SIZES, _control(b, 4), method="projective")
    with pytest.raises(EstimationError, match=r"affine block: 3 .* at least 4 .*12 parameters"):
        uncalibrated_block(b.tracks, SIZES, _control(b, 3), method="affine")


def test_coplanar_points_are_refused_for_the_projective_model():
    b = make_block(4, strips=1, images_per_strip=3, camera=CAM, relief_m=0.0, n_points=150, image_noise_px=0.0)
    with pytest.raises(EstimationError, match=r"model of images .* one plane"):
        uncalibrated_block(b.tracks, [(W, H)] * 3, b.control, method="projective")


def test_too_few_images_and_tracks():
    b = make_block(5, strips=1, images_per_strip=2, camera=CAM, relief_m=150.0, n_points=80)
    t = b.tracks
    one = t.subset(t.obs_image == 0)
    one = Tracks(one.images[:1], one.point_ids, one.obs_point, one.obs_image, one.obs_pixel, one.obs_sigma_px)
    with pytest.raises(InvalidInputError, match=r"at least 2 images; got 1"):
        uncalibrated_block(one, [(W, H)], b.control)
    few_pts = np.unique(t.obs_point)[:5]
    few = t.subset(np.isin(t.obs_point, few_pts))
    with pytest.raises(InvalidInputError, match=r"fewer than 6 tracks .*11\s+parameters"):
        uncalibrated_block(few, [(W, H)] * 2, b.control)
    with pytest.raises(InvalidInputError, match=r"one size"):
        uncalibrated_block(t, [(W, H), (W, H + 2)], b.control)
    with pytest.raises(InvalidInputError, match=r"unknown block method 'metric'"):
        uncalibrated_block(t, [(W, H)] * 2, b.control, method="metric")
