"""Space intersection: known answers, agreement of the formulas, diagnostics, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import InvalidInputError, ShapeError, StereoError
from rectify.geometry.rotation import matrix_from_angles
from stereo.pair.intersection import METHODS, intersect, intersect_relative, n_factor_seed001, project

I3 = np.eye(3)
F = 120.0


def _scene(rng, n=200, R1=None, R2=None, B=(2600.0, 40.0, -15.0)):
    R1 = matrix_from_angles(0.02, -0.01, 0.03) if R1 is None else R1
    R2 = matrix_from_angles(-0.015, 0.02, -0.02) if R2 is None else R2
    B = np.asarray(B, float)
    P = np.column_stack([rng.uniform(-1000, 3600, n), rng.uniform(-2000, 2000, n),
                         rng.uniform(-5300, -4600, n)])
    x1 = project(P, rotation=R1, centre=np.zeros(3), focal_length_mm=F)
    x2 = project(P, rotation=R2, centre=B, focal_length_mm=F)
    return P, x1, x2, R1, R2, B


@pytest.mark.parametrize("method", METHODS)
def test_normal_case_known_answer(method):
    # f = 100, B = 200 along X, point (100, 50, -1000): x1 = (10, 5), x2 = (-10, 5)
    r = intersect([[10.0, 5.0]], [[-10.0, 5.0]], rotation_left=I3, rotation_right=I3,
                  base=[200.0, 0, 0], focal_length_mm=100.0, method=method)
    assert_allclose(r.points, [[100.0, 50.0, -1000.0]], atol=1e-9)
    assert_allclose(r.scale_left, [10.0])
    assert_allclose(r.scale_right, [10.0])
    assert_allclose(r.miss_distance, [0.0], atol=1e-12)
    assert_allclose(r.residuals_mm, 0.0, atol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_exact_rays_all_methods_recover_points(method):
    P, x1, x2, R1, R2, B = _scene(np.random.default_rng(1))
    r = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F, method=method)
    assert_allclose(r.points, P, atol=1e-7)
    assert_allclose(r.miss_distance, 0.0, atol=1e-7)
    assert_allclose(r.vertical_parallax_mm, 0.0, atol=1e-9)


def test_centre_left_offsets_points():
    P, x1, x2, R1, R2, B = _scene(np.random.default_rng(2), n=5)
    C = np.array([-55094.5, -3727407.0, 5258.3])
    r = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F, centre_left=C)
    assert_allclose(r.points, P + C, atol=1e-6)


def test_seed001_formula_equals_general_aerial_form_on_nadir_photos():
    rng = np.random.default_rng(3)
    P, x1, x2, _, _, B = _scene(rng, R1=I3, R2=I3, B=(2500.0, 0.0, 30.0))
    N = n_factor_seed001(x1[:, 0], x2[:, 0], bx=B[0], bz=B[2], focal_length_mm=F)
    # X = N x1, Y = N y1, Z = -N f
    assert_allclose(np.column_stack([N * x1[:, 0], N * x1[:, 1], -N * F]), P, rtol=1e-10)
    r = intersect(x1, x2, rotation_left=I3, rotation_right=I3, base=B, focal_length_mm=F, method="aerial-n")
    assert_allclose(r.scale_left, N, rtol=1e-12)


def test_seed001_formula_parallel_raises():
    with pytest.raises(StereoError, match="x-parallax"):
        n_factor_seed001([1.0, 2.0], [1.0, 1.0], bx=1.0, bz=0.0, focal_length_mm=F)
    with pytest.raises(ShapeError, match="equal shapes"):
        n_factor_seed001([1.0, 2.0], [1.0], bx=1.0, bz=0.0, focal_length_mm=F)


def test_vertical_parallax_sign_and_miss_distance_normal_case():
    # left ray hits (100, 50, -1000); the right image y is off by +0.5 mm
    x1 = [[10.0, 5.0]]
    x2 = [[-10.0, 5.5]]
    r = intersect(x1, x2, rotation_left=I3, rotation_right=I3, base=[200.0, 0, 0], focal_length_mm=100.0,
                  method="midpoint")
    assert_allclose(r.vertical_parallax_mm, [0.5], rtol=3e-3)  # q = y2 - y1
    # the rays miss by about N * q = 10 * 0.5 = 5 object units
    assert_allclose(r.miss_distance, [5.0], rtol=2e-3)


def test_least_squares_is_the_photo_metric_optimum():
    rng = np.random.default_rng(4)
    P, x1, x2, R1, R2, B = _scene(rng, n=50)
    x1 = x1 + rng.normal(0, 0.01, x1.shape)
    x2 = x2 + rng.normal(0, 0.01, x2.shape)
    r = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F)
    ss = (r.residuals_mm ** 2).sum(1)
    # every other method has larger (or equal) image residuals for every point
    for m in ("midpoint", "general-n", "aerial-n"):
        o = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F, method=m)
        assert np.all(ss <= (o.residuals_mm ** 2).sum(1) + 1e-15)
    # and tighter convergence does not move the points (default step_tol leaves < 1e-8 of the distance)
    t = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F, step_tol=1e-15,
                  max_iterations=50)
    assert_allclose(r.points, t.points, atol=5e-5)


def test_covariance_predicts_scatter():
    rng = np.random.default_rng(5)
    P, x1, x2, R1, R2, B = _scene(rng, n=4000)
    s = 0.005
    r = intersect(x1 + rng.normal(0, s, x1.shape), x2 + rng.normal(0, s, x2.shape), rotation_left=R1,
                  rotation_right=R2, base=B, focal_length_mm=F, sigma_mm=s)
    z = (r.points - P) / r.std
    rms = np.sqrt((z ** 2).mean(0))
    assert np.all((rms > 0.93) & (rms < 1.07)), rms
    assert r.covariance.shape == (4000, 3, 3)


@settings(max_examples=30, deadline=None)
@given(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-3.1, 3.1),
       st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(0.5, 3.0))
def test_rigid_motion_and_scale_invariance(om, ph, ka, tx, ty, scale):
    """Moving and scaling the whole object frame moves and scales the points alike."""
    P, x1, x2, R1, R2, B = _scene(np.random.default_rng(6), n=20)
    Q = matrix_from_angles(om, ph, ka)
    C = np.array([tx, ty, 100.0])
    r0 = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F)
    r1 = intersect(x1, x2, rotation_left=Q @ R1, rotation_right=Q @ R2, base=scale * (Q @ B),
                   focal_length_mm=F, centre_left=C)
    assert_allclose(r1.points, scale * r0.points @ Q.T + C, atol=1e-6 * scale * 6000)


def test_intersect_relative_duck_typing():
    P, x1, x2, R1, R2, B = _scene(np.random.default_rng(7), n=3)

    class RO:
        rotation_left, rotation_right, base, focal_length_mm = R1, R2, B, F

    assert_allclose(intersect_relative(RO(), x1, x2).points, P, atol=1e-7)
    with pytest.raises(InvalidInputError, match="not a relative orientation"):
        intersect_relative(object(), x1, x2)


def test_inputs_not_modified_and_empty_ok():
    P, x1, x2, R1, R2, B = _scene(np.random.default_rng(8), n=4)
    a, b = x1.copy(), x2.copy()
    intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=F)
    assert_allclose(x1, a)
    assert_allclose(x2, b)
    r = intersect(np.zeros((0, 2)), np.zeros((0, 2)), rotation_left=R1, rotation_right=R2, base=B,
                  focal_length_mm=F)
    assert r.points.shape == (0, 3)


def test_parallel_rays_raise_with_point_index():
    x1 = np.array([[10.0, 5.0], [3.0, 3.0], [1.0, 1.0]])
    x2 = np.array([[-10.0, 5.0], [3.0, 3.0], [-1.0, 1.0]])
    with pytest.raises(StereoError, match=r"parallel rays: 1 of 3 .* first is point 1"):
        intersect(x1, x2, rotation_left=I3, rotation_right=I3, base=[200.0, 0, 0], focal_length_mm=100.0)


def test_general_n_singular_configuration_raises():
    # seed 000's denominator u.(d1 x d2) with u = (1, 1, 1) vanishes when the epipolar plane
    # contains (1, 1, 1): in the normal case d1 x d2 ~ p (0, f, y), so at y = -f
    x1 = [[10.0, -100.0]]
    x2 = [[-10.0, -100.0]]
    kw = dict(rotation_left=I3, rotation_right=I3, base=[200.0, 0, 0], focal_length_mm=100.0)
    with pytest.raises(StereoError, match="general-n formula is singular.*point 0"):
        intersect(x1, x2, method="general-n", **kw)
    # the other methods are fine there
    assert_allclose(intersect(x1, x2, **kw).points, [[100.0, -1000.0, -1000.0]], atol=1e-9)


@pytest.mark.parametrize("kw, exc, msg", [
    (dict(method="dlt"), InvalidInputError, "unknown intersection method 'dlt'"),
    (dict(base=[0.0, 0.0, 0.0]), StereoError, "base is zero"),
    (dict(base=[1.0, 2.0]), ShapeError, "`base` must be 3 finite numbers"),
    (dict(focal_length_mm=-1.0), InvalidInputError, "focal_length_mm"),
    (dict(rotation_left=np.diag([1.0, 1.0, -1.0])), InvalidInputError, "not a proper rotation"),
    (dict(sigma_mm=0.0), InvalidInputError, "sigma_mm"),
])
def test_bad_options(kw, exc, msg):
    args = dict(rotation_left=I3, rotation_right=I3, base=[200.0, 0, 0], focal_length_mm=100.0)
    args.update(kw)
    with pytest.raises(exc, match=msg):
        intersect([[10.0, 5.0]], [[-10.0, 5.0]], **args)


def test_bad_point_arrays():
    kw = dict(rotation_left=I3, rotation_right=I3, base=[200.0, 0, 0], focal_length_mm=100.0)
    with pytest.raises(ShapeError, match="same number of points"):
        intersect([[1.0, 2.0]], [[1.0, 2.0], [3.0, 4.0]], **kw)
    with pytest.raises(ShapeError, match=r"must have shape \(N, 2\)"):
        intersect([[1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0]], **kw)
    with pytest.raises(InvalidInputError, match="non-finite"):
        intersect([[np.nan, 2.0]], [[1.0, 2.0]], **kw)
