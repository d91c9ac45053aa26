"""Projective and universal pair methods (seed 003, 3.2.1-3.3.2; issue 26): the fundamental matrix, the
projective cameras and model, the 3D affine and projective transformations, universal and projective
relative orientation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import EstimationError, InvalidInputError
from stereo.pair.absolute import similarity_from_points
from stereo.pair.projective import (
    Affine3D,
    Projective3D,
    cameras_from_fundamental,
    fundamental_from_points,
    triangulate_projective,
)
from stereo.pair.projective_model import metric_cameras
from stereo.relative import RelativeOrientation
from stereo.relative.universal import affine_matrix, gram_schmidt
from tests.support.projective_scene import pair_scene
from tests.support.stereo_support import simulate_pair


def _angle_deg(Ra, Rb):
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(Ra.T @ Rb) - 1) / 2))))


# ------------------------------------------------------------------ fundamental matrix
def test_fundamental_exact_and_cameras_reproject():
    sc = pair_scene(1, noise_px=0.0)
    F, fit = fundamental_from_points(sc.left, sc.right)
    h1 = np.column_stack([sc.left, np.ones(len(sc.left))])
    h2 = np.column_stack([sc.right, np.ones(len(sc.right))])
    assert np.abs(np.einsum("ij,jk,ik->i", h2, F, h1)).max() < 1e-9
    assert fit.rms_px < 1e-8 and np.linalg.matrix_rank(F, tol=1e-10) == 2
    P1, P2 = cameras_from_fundamental(F)
    Xh = triangulate_projective([P1, P2], [sc.left, sc.right])
    for P, x in ((P1, sc.left), (P2, sc.right)):
        p = Xh @ P.T
        assert np.abs(p[:, :2] / p[:, 2:] - x).max() < 1e-6


def test_fundamental_sigma0_estimates_the_image_noise():
    sc = pair_scene(2, n=150, noise_px=0.5)
    _, fit = fundamental_from_points(sc.left, sc.right)
    # Sampson sigma0 estimates the standard deviation of one image coordinate (redundancy n - 7)
    assert fit.redundancy == 143
    assert 0.42 < fit.sigma0_px < 0.58, fit.sigma0_px


def test_fundamental_outlier_threshold():
    sc = pair_scene(6, n=100, noise_px=0.5)
    right = sc.right.copy()
    right[:6] += np.array([25.0, -30.0])  # gross errors
    _, fit = fundamental_from_points(sc.left, right, outlier_px=2.0)
    assert not fit.inliers[:6].any() and fit.inliers[6:].mean() > 0.95
    assert 0.35 < fit.sigma0_px < 0.65
    with pytest.raises(InvalidInputError, match="> 0 px"):
        fundamental_from_points(sc.left, right, outlier_px=0.0)


def test_fundamental_too_few_points_and_plane():
    sc = pair_scene(3)
    with pytest.raises(EstimationError, match=r"7.*at least 8|at least 8.*7"):
        fundamental_from_points(sc.left[:7], sc.right[:7])
    flat = pair_scene(3, relief=0.0)  # every point on one plane: a homography, F undetermined
    with pytest.raises(EstimationError, match="degenerate configuration.*one plane"):
        fundamental_from_points(flat.left, flat.right)
    with pytest.raises(EstimationError, match="rank 2"):
        cameras_from_fundamental(np.eye(3))


def test_triangulate_missing_observations():
    g = np.random.default_rng(4)
    X = np.column_stack([g.uniform(-10, 10, (30, 3)), np.ones(30)])
    Ps = []
    for k in range(3):  # cameras at (4k - 4, 0, 50) looking down, 1000 px focal, principal point (500, 400)
        K = np.array([[1000.0, 2.0, 500.0], [0.0, 1030.0, 400.0], [0.0, 0.0, 1.0]])
        Ps.append(K @ np.diag([1.0, -1.0, -1.0]) @ np.hstack([np.eye(3), -np.array([[4.0 * k - 4], [0], [50]])]))
    x = []
    for P in Ps:
        p = X @ P.T
        x.append(p[:, :2] / p[:, 2:])
    x[1][:5] = np.nan          # points 0-4 seen by cameras 0 and 2 only: still two rays
    x[0][5] = x[2][5] = np.nan  # point 5 seen once: NaN
    Xh = triangulate_projective(Ps, x)
    assert np.isnan(Xh[5]).all() and np.isfinite(np.delete(Xh, 5, axis=0)).all()
    ok = np.ones(30, dtype=bool)
    ok[5] = False
    assert np.abs(Xh[ok, :3] / Xh[ok, 3:] - X[ok, :3]).max() < 1e-8
    with pytest.raises(InvalidInputError, match="at least 2 cameras"):
        triangulate_projective([Ps[0]], [x[0]])


# ------------------------------------------------------------------ 3D transformations
def _points(n, seed=0):
    g = np.random.default_rng(seed)
    return np.column_stack([g.uniform(-50, 50, n), g.uniform(-40, 40, n), g.uniform(-10, 10, n)])


def test_affine_and_projective_exact_and_minimum():
    src = _points(12)
    A = np.array([[1.2, 0.1, -0.05], [0.02, 0.9, 0.1], [0.03, -0.2, 1.1]])
    t = np.array([100.0, -50.0, 20.0])
    aff = Affine3D.from_points(src, src @ A.T + t)
    assert np.allclose(aff.A, A) and np.allclose(aff.t, t) and aff.redundancy == 24
    H = np.array([[1.0, 0.1, 0, 5], [0, 1.1, 0.1, -3], [0.05, 0, 0.9, 2], [1e-3, -2e-3, 5e-4, 1]])
    dst = Projective3D(H=H, residuals=np.zeros((0, 3)), weights=np.zeros(0), sigma0=None, redundancy=0,
                       covariance=np.zeros((15, 15)))(src)
    pro = Projective3D.from_points(src, dst)
    assert np.allclose(pro.H, H, atol=1e-9) and np.abs(pro.residuals).max() < 1e-8
    with pytest.raises(EstimationError, match="3D affine.*: 3; at least 4 non-coplanar"):
        Affine3D.from_points(src[:3], src[:3])
    with pytest.raises(EstimationError, match="3D projective.*: 4; at least 5"):
        Projective3D.from_points(src[:4], dst[:4])
    five = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.3, 0.2, 1.0]])
    with pytest.raises(EstimationError, match="5 points are not in general position"):
        Projective3D.from_points(five, 2 * five)  # four of the five on one plane
    flat = src.copy()
    flat[:, 2] = 0.3 * flat[:, 0] - 2.0  # a tilted plane

    with pytest.raises(EstimationError, match="coplanar"):
        Projective3D.from_points(flat, dst)
    with pytest.raises(EstimationError, match="coplanar"):
        Affine3D.from_points(flat, dst)


def test_transform_precision_figures():
    g = np.random.default_rng(7)
    src = _points(60, 7)
    A = np.array([[1.2, 0.1, -0.05], [0.02, 0.9, 0.1], [0.03, -0.2, 1.1]])
    dst = src @ A.T + 3.0 + g.normal(0, 0.05, (60, 3))
    aff = Affine3D.from_points(src, dst)
    assert 0.04 < aff.sigma0 < 0.06 and aff.redundancy == 3 * 60 - 12
    # standard error of the translation ~ sigma / sqrt(n) near the centroid
    centre_std = aff.point_std(src.mean(axis=0, keepdims=True)).max()
    assert np.all(aff.std_errors > 0) and centre_std < 0.05 / math.sqrt(60) * 1.5
    pro = Projective3D.from_points(src, dst)
    assert 0.04 < pro.sigma0 < 0.06 and pro.redundancy == 3 * 60 - 15 and np.all(np.isfinite(pro.std_errors))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-0.3, 0.3), min_size=12, max_size=12), st.integers(0, 10_000))
def test_property_round_trips(params, seed):
    src = _points(15, seed)
    A = np.eye(3) + np.array(params[:9]).reshape(3, 3)
    t = np.array(params[9:]) * 100
    dst = src @ A.T + t
    aff = Affine3D.from_points(src, dst)
    assert np.allclose(aff(src), dst, atol=1e-7)
    assert np.allclose(Affine3D.from_points(dst, src)(aff(src)), src, atol=1e-7)  # the inverse round trip
    H = np.eye(4)
    H[:3, :3] = A
    H[:3, 3] = t
    H[3, :3] = np.array(params[:3]) * 1e-3
    d2 = np.column_stack([src, np.ones(15)]) @ H.T
    d2 = d2[:, :3] / d2[:, 3:]
    pro = Projective3D.from_points(src, d2)
    assert np.allclose(pro(src), d2, atol=1e-6 * max(1.0, np.abs(d2).max()))
    back = Projective3D.from_points(d2, src)
    assert np.allclose(back(pro(src)), src, atol=1e-6 * max(1.0, np.abs(src).max()))


# ------------------------------------------------------------------ relative orientation
def test_gram_schmidt_gives_a_rotation():
    C = gram_schmidt(affine_matrix(np.array([0.2, -0.1, 0.3])))
    assert np.allclose(C.T @ C, np.eye(3)) and np.linalg.det(C) > 0


@pytest.mark.parametrize("kind", ["vertical", "convergent", "kappa180"])
def test_universal_and_projective_agree_with_the_systems_exact(kind):
    sp = simulate_pair(kind, n=60, rng=11)
    kw = dict(focal_length_mm=sp.focal_length_mm, pixel_size_mm=sp.pixel_size_mm)
    ref = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="left-image", **kw)
    for system in ("universal", "projective"):
        ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system=system, **kw)
        assert _angle_deg(ro.relative_rotation, sp.R_rel) < 0.01
        assert _angle_deg(ro.relative_rotation, ref.relative_rotation) < 0.01
        assert np.degrees(np.arccos(min(1.0, ro.base_left @ sp.base_left))) < 0.01


def test_universal_and_projective_same_precision_on_noise():
    sp = simulate_pair("convergent", n=80, noise_px=0.5, rng=12)
    kw = dict(focal_length_mm=sp.focal_length_mm, pixel_size_mm=sp.pixel_size_mm)
    ref = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="left-image", **kw)
    basis = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="basis", **kw)
    uni = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="universal", **kw)
    pro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="projective", **kw)
    # stated tolerance: sigma0, rms parallax and the standard errors of the elements within 1 %
    for ro, same in ((uni, basis), (pro, ref)):
        assert ro.sigma0_mm == pytest.approx(ref.sigma0_mm, rel=0.01)
        assert ro.rms_parallax_mm() == pytest.approx(ref.rms_parallax_mm(), rel=0.01)
        assert np.allclose(ro.std_errors, same.std_errors, rtol=0.01)
        assert ro.names == same.names
    assert pro.method_figures["sampson_sigma0_px"] == pytest.approx(0.5, rel=0.2)
    assert uni.initial_method == "universal" and pro.initial_method == "fundamental"


def test_universal_needs_no_start_values_at_large_convergence():
    """Seed 003, 3.2.1: convergence up to 70 degrees and tilt about 10 degrees without approximate values."""
    sc = pair_scene(5, noise_px=0.0, convergence_deg=70.0)
    cam = sc.camera
    ro = RelativeOrientation.from_pixels(sc.left, sc.right, cam, system="universal")
    assert _angle_deg(ro.relative_rotation, sc.R_rel) < 0.01


@pytest.mark.parametrize("turn", [90, 180, 270])
def test_universal_any_base_direction(turn):
    """The photo frames turned in their plane put the base along +y, -x or -y of the photos."""
    sp = simulate_pair("vertical", n=40, noise_px=0.3, rng=14)
    c, s = round(math.cos(math.radians(turn))), round(math.sin(math.radians(turn)))
    Q = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    L, R = sp.left_mm @ Q[:2, :2].T, sp.right_mm @ Q[:2, :2].T
    kw = dict(focal_length_mm=sp.focal_length_mm, pixel_size_mm=sp.pixel_size_mm)
    ref = RelativeOrientation.from_points(L, R, system="left-image", **kw)
    uni = RelativeOrientation.from_points(L, R, system="universal", **kw)
    assert _angle_deg(uni.relative_rotation, ref.relative_rotation) < 1e-4
    assert _angle_deg(uni.relative_rotation, Q @ sp.R_rel @ Q.T) < 0.3


def test_method_systems_bad_input():
    sp = simulate_pair("vertical", n=30, rng=13)
    kw = dict(focal_length_mm=sp.focal_length_mm, pixel_size_mm=sp.pixel_size_mm)
    with pytest.raises(EstimationError, match="7 given, at least 8"):
        RelativeOrientation.from_points(sp.left_mm[:7], sp.right_mm[:7], system="projective", **kw)
    with pytest.raises(InvalidInputError, match="robust"):
        RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="projective", robust="tukey", **kw)
    with pytest.raises(InvalidInputError, match="needs no initial values"):
        RelativeOrientation.from_points(sp.left_mm, sp.right_mm, system="universal", initial="zero", **kw)


# ------------------------------------------------------------------ model orientation
def _check_errors(seed, n_control=14):
    sc = pair_scene(seed, n=80, noise_px=0.5)
    ctl, chk = np.arange(n_control), np.arange(n_control, 80)
    cam = sc.camera
    # metric: the true camera, relative orientation, intersection, 7-parameter similarity
    ro = RelativeOrientation.from_pixels(sc.left, sc.right, cam, system="left-image")
    P1, P2 = metric_cameras(ro.rotation_left, ro.rotation_right, ro.base)
    f = cam.focal_length_mm
    Xm = triangulate_projective([P1, P2], [-cam.photo_from_pixel(sc.left) / f, -cam.photo_from_pixel(sc.right) / f])
    Xm = Xm[:, :3] / Xm[:, 3:]
    s, R, T = similarity_from_points(Xm[ctl], sc.X[ctl])
    metric = np.sqrt(np.mean(np.sum((s * Xm[chk] @ R.T + T - sc.X[chk]) ** 2, axis=1)))
    # projective: no camera; F, canonical cameras, projective model, 15-parameter transformation
    F, _ = fundamental_from_points(sc.left, sc.right)
    Xp = triangulate_projective(list(cameras_from_fundamental(F)), [sc.left, sc.right])
    H = Projective3D.from_points(Xp[ctl], sc.X[ctl])
    projective = np.sqrt(np.mean(np.sum((H(Xp[chk]) - sc.X[chk]) ** 2, axis=1)))
    return metric, projective


def test_projective_model_reaches_the_metric_model_within_1_5():
    """Camera with unknown f, fy = 1.04 fx and skew: the projective path with 14 control points reaches
    check-point errors within 1.5 times those of the metric path with the true camera (mean of 3 pairs)."""
    r = np.array([_check_errors(seed) for seed in (21, 22, 23)])
    metric, projective = r.mean(axis=0)
    assert projective < 1.5 * metric, (metric, projective)
    assert metric < 0.15  # ~0.06 m at 0.5 px noise


def test_point_std_matches_monte_carlo():
    """The predicted standard deviation of a transformed point (outside the control) agrees with the
    scatter over repeated noisy fits within 20 % (200 affine, 100 projective trials)."""
    g = np.random.default_rng(8)
    src = _points(20, 8)
    far = np.array([[60.0, 50.0, 15.0]])
    H = np.array([[1.0, 0.1, 0, 5], [0, 1.1, 0.1, -3], [0.05, 0, 0.9, 2], [1e-3, -2e-3, 5e-4, 1]])
    truth = Projective3D(H=H, residuals=np.zeros((0, 3)), weights=np.zeros(0), sigma0=None, redundancy=0,
                         covariance=np.zeros((15, 15)))
    A = np.array([[1.2, 0.1, -0.05], [0.02, 0.9, 0.1], [0.03, -0.2, 1.1]])
    for cls, trials, dst in ((Affine3D, 200, src @ A.T + 3.0), (Projective3D, 100, truth(src))):
        out, pred = [], []
        for _ in range(trials):
            t = cls.from_points(src, dst + g.normal(0, 0.05, dst.shape))
            out.append(t(far)[0])
            pred.append(t.point_std(far)[0])
        scatter = np.std(np.array(out), axis=0)
        assert np.allclose(np.mean(pred, axis=0), scatter, rtol=0.2), (cls.__name__, np.mean(pred, axis=0), scatter)
