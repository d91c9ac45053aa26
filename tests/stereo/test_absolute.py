"""Absolute orientation: Dewitt 3DCONF known answer, minimal control, robust, deformation, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.rotation import matrix_from_angles
from stereo.pair.absolute import AbsoluteOrientation, similarity_from_points


def _dewitt(path):
    blocks = (path / "3DCONF_sample.dat").read_text().split("#")
    ctrl = [ln.split() for ln in blocks[0].strip().splitlines()]
    pts = [ln.split() for ln in blocks[1].strip().splitlines()]
    c = np.array([r[1:] for r in ctrl], float)
    return [r[0] for r in ctrl], c[:, :3], c[:, 3:], np.array([r[1:] for r in pts], float)


def test_dewitt_3dconf_sample(dewitt):
    ids, model, ground, pts = _dewitt(dewitt)
    ao = AbsoluteOrientation.from_points(model, ground, ids=ids)
    p, se = ao.parameters, ao.std_errors
    # Final Results: value and Stan.Dev. as printed (angles in degrees)
    assert round(p[0], 5) == 0.99674 and round(se[0], 5) == 0.00051
    assert_allclose(np.degrees(p[1:4]), [0.0540, -0.1318, -0.0002], atol=0.5e-4)
    assert_allclose(np.degrees(se[1:4]), [0.0295, 0.0404, 0.0417], atol=0.5e-4)
    assert_allclose(p[4:], [219.620, 3.687, -0.060], atol=0.5e-3)
    assert_allclose(se[4:], [0.442, 0.414, 0.420], atol=0.5e-3)
    assert round(ao.sigma0, 5) == 0.24755
    printed_res = [[0.083, -0.385, 0.112], [-0.076, 0.032, -0.441], [0.044, 0.031, 0.030],
                   [0.017, -0.021, -0.112], [-0.115, 0.298, 0.426], [0.047, 0.046, -0.016]]
    assert_allclose(ao.residuals.residual, printed_res, atol=0.5e-3)
    # Transformed Points with SDev (parameter covariance propagated)
    printed_pts = [[827.919, 500.595, 470.725], [854.835, 326.217, 87.096], [790.878, 403.805, 85.836],
                   [864.319, 376.355, 85.261], [751.191, 287.683, 88.276]]
    printed_sd = [[0.266, 0.246, 0.237], [0.204, 0.215, 0.207], [0.156, 0.166, 0.162],
                  [0.187, 0.211, 0.204], [0.200, 0.176, 0.172]]
    assert_allclose(ao(pts), printed_pts, atol=0.5e-3)
    sd = np.sqrt(np.einsum("nii->ni", ao.point_covariance(pts)))
    assert_allclose(sd, printed_sd, atol=0.5e-3)


def _truth(rng, n=12):
    R = matrix_from_angles(0.3, -0.2, 2.5)
    s, T = 37.5, np.array([-55000.0, -3727000.0, 400.0])
    m = rng.uniform(-50, 50, (n, 3)) * [1, 1, 0.2]
    return m, s * m @ R.T + T, (s, R, T)


def test_minimal_two_full_and_one_height_point():
    m, g, (s, R, T) = _truth(np.random.default_rng(1), n=3)
    g = g.copy()
    g[2, :2] = np.nan  # third point: height only
    ao = AbsoluteOrientation.from_points(m, g)
    assert_allclose(ao.scale, s, rtol=1e-10)
    assert_allclose(ao.rotation, R, atol=1e-10)
    assert_allclose(ao.translation, T, atol=1e-6)
    assert ao.residuals.extra["n_height"] == 1


@settings(max_examples=25, deadline=None)
@given(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1), st.floats(0.01, 1e3))
def test_recovers_any_similarity(om, ph, ka, s):
    rng = np.random.default_rng(2)
    m = rng.uniform(-50, 50, (6, 3))
    R = matrix_from_angles(om, ph, ka)
    T = np.array([1e5, -2e6, 300.0])
    ao = AbsoluteOrientation.from_points(m, s * m @ R.T + T)
    assert_allclose(ao.scale * ao.rotation, s * R, atol=1e-8 * s)
    assert_allclose(ao(m), s * m @ R.T + T, atol=1e-6 * max(s, 1))


def test_std_errors_predict_check_point_errors():
    rng = np.random.default_rng(3)
    z = []
    for _ in range(100):
        m, g, _ = _truth(rng, n=10)
        chk = np.zeros(10, bool)
        chk[7:] = True
        gn = g + rng.normal(0, 0.5, g.shape)
        ao = AbsoluteOrientation.from_points(m, gn, check=chk)
        e = ao(m[chk]) - gn[chk]
        C = ao.point_covariance(m[chk])
        # check error = prediction error + the check point's own noise (0.5)
        z.append(e / np.sqrt(np.einsum("nii->ni", C) + 0.25))
    rms = np.sqrt(np.mean(np.square(np.concatenate(z))))
    assert 0.9 < rms < 1.1, rms


@pytest.mark.parametrize("psi", ["huber", "tukey", "hampel", "andrews"])
def test_robust_rejects_a_blunder(psi):
    rng = np.random.default_rng(4)
    m, g, (s, R, T) = _truth(rng, n=15)
    g = g + rng.normal(0, 0.05, g.shape)
    g[5, 2] += 30.0
    plain = AbsoluteOrientation.from_points(m, g)
    rob = AbsoluteOrientation.from_points(m, g, robust=psi)
    good = np.arange(15) != 5
    e_plain = np.abs(plain(m[good]) - (s * m[good] @ R.T + T)).max()
    e_rob = np.abs(rob(m[good]) - (s * m[good] @ R.T + T)).max()
    assert e_rob < 0.2 < e_plain
    assert rob.residuals.outlier[5] and rob.residuals.outlier.sum() <= 2


def test_polynomial_deformation_correction():
    rng = np.random.default_rng(5)
    m, g, _ = _truth(rng, n=20)
    # a bent model: quadratic deformation in height
    mb = m.copy()
    mb[:, 2] += 0.002 * (m[:, 0] ** 2 + m[:, 1] ** 2)
    chk = np.zeros(20, bool)
    chk[14:] = True
    plain = AbsoluteOrientation.from_points(mb, g, check=chk)
    corr = AbsoluteOrientation.from_points(mb, g, check=chk, deformation_order=2)
    assert corr.residuals.summary()["rmse_check"] < 0.05 * plain.residuals.summary()["rmse_check"]
    assert corr.to_dict()["deformation"]["order"] == 2


def test_closed_form_similarity():
    m, g, (s, R, T) = _truth(np.random.default_rng(6), n=4)
    s1, R1, T1 = similarity_from_points(m, g)
    assert_allclose([s1], [s])
    assert_allclose(R1, R, atol=1e-12)


def test_too_few_and_collinear_control():
    m, g, _ = _truth(np.random.default_rng(7), n=6)
    with pytest.raises(EstimationError, match="too few control points: 2 full and 0 height"):
        AbsoluteOrientation.from_points(m[:2], g[:2])
    gz = g.copy()
    gz[1:, :2] = np.nan
    with pytest.raises(EstimationError, match="too few control points: 1 full and 5 height"):
        AbsoluteOrientation.from_points(m, gz)
    line = np.outer(np.linspace(-1, 1, 6), [10.0, 5.0, 1.0])
    with pytest.raises(EstimationError, match="collinear"):
        AbsoluteOrientation.from_points(line, g)
    with pytest.raises(EstimationError, match="order-2 deformation correction: 5 given, 6 needed"):
        AbsoluteOrientation.from_points(m[:5], g[:5], deformation_order=2)
    chk = np.ones(6, bool)
    with pytest.raises(EstimationError, match="0 full"):
        AbsoluteOrientation.from_points(m, g, check=chk)


def test_bad_arguments():
    m, g, _ = _truth(np.random.default_rng(8), n=6)
    with pytest.raises(ShapeError, match=r"`ground` must have shape \(6, 3\)"):
        AbsoluteOrientation.from_points(m, g[:5])
    with pytest.raises(InvalidInputError, match="unknown robust option 'lms'"):
        AbsoluteOrientation.from_points(m, g, robust="lms")
    with pytest.raises(InvalidInputError, match="deformation_order"):
        AbsoluteOrientation.from_points(m, g, deformation_order=4)
    gb = g.copy()
    gb[0, 0] = np.nan
    with pytest.raises(InvalidInputError, match="ground point '1'"):
        AbsoluteOrientation.from_points(m, gb)


def _correlated_scene(seed=3, n=40):
    """Control with correlated (X, Z) noise, as intersected points have (x-parallax couples X and Z)."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(-1, 1, (n, 3)) * [1.0, 1.0, 0.1]
    R = matrix_from_angles(0.02, -0.03, 1.1)
    g0 = 900.0 * m @ R.T + [5e5, 4e6, 300.0]
    C = np.array([[0.25, 0.0, 0.55], [0.0, 0.25, 0.0], [0.55, 0.0, 1.6]])  # m^2, corr(X, Z) = 0.87
    L = np.linalg.cholesky(C)
    g = g0 + rng.standard_normal((n, 3)) @ L.T
    return m, g, C


def test_full_weight_matrices():
    """(N, 3, 3) weights: diagonal matrices reproduce (N, 3) weights; full ones give sigma0 ~ 1 with
    correlated noise (the diagonal alone misjudges it) and are invariant to a common factor."""
    m, g, C = _correlated_scene()
    n = len(m)
    d = np.tile(1.0 / np.diag(C), (n, 1))
    a = AbsoluteOrientation.from_points(m, g, weights=d)
    b = AbsoluteOrientation.from_points(m, g, weights=np.einsum("ni,ij->nij", d, np.eye(3)))
    assert_allclose(b.parameters, a.parameters, rtol=1e-9, atol=1e-9)
    assert_allclose(b.sigma0, a.sigma0, rtol=1e-9)
    P = np.tile(np.linalg.inv(C), (n, 1, 1))
    s0 = [AbsoluteOrientation.from_points(*_correlated_scene(seed)[:2], weights=P).sigma0 for seed in range(20)]
    assert 0.85 < np.sqrt(np.mean(np.square(s0))) < 1.15, s0
    f = AbsoluteOrientation.from_points(m, g, weights=P)
    f4 = AbsoluteOrientation.from_points(m, g, weights=4.0 * P)
    assert_allclose(f4.parameters, f.parameters, rtol=1e-9, atol=1e-9)
    assert_allclose(f4.covariance, f.covariance, rtol=1e-6, atol=1e-15)
    assert_allclose(f4.sigma0, 2.0 * f.sigma0, rtol=1e-9)  # v^T (4P) v


def test_full_weight_matrices_bad():
    m, g, C = _correlated_scene()
    P = np.tile(np.linalg.inv(C), (len(m), 1, 1))
    P[3] = [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]  # positive diagonal, indefinite
    with pytest.raises(InvalidInputError, match="positive definite"):
        AbsoluteOrientation.from_points(m, g, weights=P)
    P[3, 0, 0] = np.nan
    with pytest.raises(InvalidInputError, match="finite"):
        AbsoluteOrientation.from_points(m, g, weights=P)
