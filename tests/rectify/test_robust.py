"""rectify.geometry.robust: psi functions, robust scale, IRLS, generic RANSAC."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.robust import (
    PSI_FUNCTIONS,
    Andrews,
    Hampel,
    Huber,
    Tukey,
    efficiency,
    get_psi,
    irls,
    irls_linear,
    ransac,
    robust_scale,
)


# ------------------------------------------------------------------ psi
@pytest.mark.parametrize("name", sorted(PSI_FUNCTIONS))
def test_tuning_constants_give_95_percent_efficiency(name):
    assert efficiency(name) == pytest.approx(0.95, abs=0.002)


@pytest.mark.parametrize("name", sorted(PSI_FUNCTIONS))
def test_psi_weight_consistency(name):
    p = get_psi(name)
    u = np.linspace(-15, 15, 3001)
    u = u[u != 0]
    assert_allclose(p.weight(u) * u, p.psi(u), atol=1e-12)
    assert_allclose(p.weight(np.array([0.0, 1e-9])), [1.0, 1.0], atol=1e-9)
    assert np.all(p.weight(u) >= 0) and np.all(p.weight(u) <= 1 + 1e-12)
    # odd psi, even weight
    assert_allclose(p.psi(-u), -p.psi(u), atol=1e-12)
    # derivative matches finite differences away from breakpoints
    h = 1e-6
    uu = np.array([0.3, 1.0, 2.2, 4.0, 6.0])
    fd = (p.psi(uu + h) - p.psi(uu - h)) / (2 * h)
    assert_allclose(p.dpsi(uu), fd, atol=1e-5)


def test_redescending_reject_and_huber_does_not():
    big = np.array([50.0])
    assert Huber().weight(big)[0] > 0
    for p in (Tukey(), Hampel(), Andrews()):
        assert p.weight(big)[0] == 0.0
        assert np.isfinite(p.rejection_point)
    assert Huber().rejection_point == np.inf


def test_get_psi_unknown_name():
    with pytest.raises(InvalidInputError, match="unknown psi function 'cauchy'"):
        get_psi("cauchy")
    with pytest.raises(InvalidInputError, match="must be a name"):
        get_psi(42)


# ---------------------------------------------------------------- scale
def test_robust_scale_normal_sample():
    rng = np.random.default_rng(1)
    r = rng.normal(0, 2.5, 20000)
    assert robust_scale(r) == pytest.approx(2.5, rel=0.03)
    # 20 % gross errors barely move it
    r[:4000] = 1000.0
    assert robust_scale(r) < 3.5


def test_robust_scale_zero_and_mask_and_nan():
    assert robust_scale(np.zeros(5)) == 0.0
    assert robust_scale([1.0, 2.0, 100.0], mask=[True, True, False]) == pytest.approx(1.5 / 0.6744897501960817)
    with pytest.raises(InvalidInputError, match="NaN"):
        robust_scale([1.0, np.nan])


# ----------------------------------------------------------------- IRLS
def _line(rng, n=60, frac=0.2):
    x = np.linspace(0, 10, n)
    A = np.column_stack([np.ones(n), x])
    b = 1.5 - 0.7 * x + rng.normal(0, 0.05, n)
    bad = rng.choice(n, int(frac * n), replace=False)
    b[bad] += rng.uniform(5, 20, bad.size) * rng.choice([-1, 1], bad.size)
    return A, b, bad


@pytest.mark.parametrize("name", sorted(PSI_FUNCTIONS))
def test_irls_linear_not_pulled_by_outliers(name):
    rng = np.random.default_rng(7)
    A, b, bad = _line(rng)
    ls = np.linalg.lstsq(A, b, rcond=None)[0]
    res = irls_linear(A, b, psi=name)
    assert abs(res.model[1] + 0.7) < 0.03
    assert abs(ls[1] + 0.7) > abs(res.model[1] + 0.7)
    assert set(bad) <= set(np.flatnonzero(res.outlier_mask))
    assert res.converged and res.iterations >= 2
    assert res.scale == pytest.approx(0.05, rel=0.4)
    if name != "huber":
        assert np.all(res.weights[bad] == 0)


def test_irls_exact_fit_stops():
    A = np.column_stack([np.ones(5), np.arange(5.0)])
    res = irls_linear(A, A @ [1.0, 2.0])
    assert_allclose(res.model, [1.0, 2.0])
    assert res.scale < 1e-12 and res.converged and not res.outlier_mask.any()


def test_irls_generic_with_warm_start_and_bad_input():
    y = np.array([1.0, 1.1, 0.9, 1.05, 30.0])

    def fit(w, prev):
        return float(np.sum(w * y) / np.sum(w))

    res = irls(fit, lambda m: y - m, len(y), psi="tukey")
    assert res.model == pytest.approx(1.0125, abs=0.05)
    assert res.outlier_mask.tolist() == [False] * 4 + [True]
    with pytest.raises(InvalidInputError, match="`n` must be"):
        irls(fit, lambda m: y - m, 0)
    with pytest.raises(ShapeError, match="prior_weights"):
        irls(fit, lambda m: y - m, 5, prior_weights=[1, 1])
    with pytest.raises(InvalidInputError, match="scale"):
        irls(fit, lambda m: y - m, 5, scale=-1.0)
    with pytest.raises(EstimationError, match="positive weight"):
        irls(fit, lambda m: y - m, 5, psi="tukey", scale=1e-6, min_used=2, initial=100.0)


def test_irls_linear_rank_deficient():
    A = np.column_stack([np.ones(5), np.ones(5)])
    with pytest.raises(EstimationError, match="rank deficient"):
        irls_linear(A, np.arange(5.0))
    with pytest.raises(ShapeError):
        irls_linear(np.ones((4, 2)), np.ones(5))


# --------------------------------------------------------------- RANSAC
@dataclass(frozen=True, eq=False)
class Line:
    a: float
    b: float

    @classmethod
    def from_points(cls, x, y):
        if len(x) < 2 or np.ptp(x) == 0:
            raise EstimationError("points coincide in x")
        a, b = np.polyfit(x, y, 1)
        return cls(float(a), float(b))

    def residuals(self, x, y):
        return np.abs(y - (self.a * x + self.b))


def test_ransac_line_with_outliers():
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 100, 200)
    y = 0.5 * x + 3 + rng.normal(0, 0.2, 200)
    bad = rng.choice(200, 80, replace=False)
    y[bad] = rng.uniform(-100, 100, 80)
    res = ransac((x, y), Line, min_samples=2, residual_threshold_px=1.0, rng=0)
    assert res.model.a == pytest.approx(0.5, abs=0.005)
    assert res.n_inliers >= 115
    assert not res.inlier_mask[bad][np.abs(y[bad] - 0.5 * x[bad] - 3) > 2].any()
    assert res.n_trials < 1000
    # deterministic with a seed
    res2 = ransac((x, y), Line, min_samples=2, residual_threshold_px=1.0, rng=0)
    assert np.array_equal(res.inlier_mask, res2.inlier_mask)


def test_ransac_errors():
    x = np.arange(5.0)
    with pytest.raises(EstimationError, match="too few points for RANSAC: 1 given"):
        ransac((x[:1], x[:1]), Line, min_samples=2, residual_threshold_px=1.0)
    with pytest.raises(EstimationError, match="no consensus"):
        ransac((np.zeros(5), x), Line, min_samples=2, residual_threshold_px=1.0, max_trials=20)
    with pytest.raises(InvalidInputError, match="residual_threshold_px"):
        ransac((x, x), Line, min_samples=2, residual_threshold_px=0.0)
    with pytest.raises(InvalidInputError, match="confidence"):
        ransac((x, x), Line, min_samples=2, residual_threshold_px=1.0, confidence=1.0)
    with pytest.raises(ShapeError, match="first dimension"):
        ransac((x, x[:3]), Line, min_samples=2, residual_threshold_px=1.0)


@settings(max_examples=25, deadline=None)
@given(st.floats(-5, 5), st.floats(-50, 50), st.integers(0, 2**31 - 1))
def test_ransac_recovers_any_line_exact(a, b, seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-10, 10, 40)
    y = a * x + b
    y[:10] += 1000.0
    res = ransac((x, y), Line, min_samples=2, residual_threshold_px=1e-3, rng=seed)
    assert res.model.a == pytest.approx(a, abs=1e-6)
    assert res.inlier_mask[10:].all() and not res.inlier_mask[:10].any()
