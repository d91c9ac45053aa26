"""Accuracy statements (issue 27): hand-computed figures, closed forms of CE90/LE90, the coverage of the RMSE
confidence intervals, the ASPRS Edition 2 sentences, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from scipy.special import chdtri

from rectify.errors import InvalidInputError
from rectify.geometry.accuracy import AccuracyStatement, ce90, rmse_interval

# four check points, errors by hand (m)
E = np.array([[0.10, -0.20, 0.30], [-0.10, 0.00, -0.10], [0.20, 0.20, 0.00], [0.00, -0.20, 0.20]])


def test_figures_against_hand_computation():
    s = AccuracyStatement.from_errors(E)
    # RMSE_x = sqrt((0.01 + 0.01 + 0.04 + 0) / 4) = sqrt(0.015); RMSE_y = sqrt(0.12 / 4) = sqrt(0.03)
    # RMSE_z = sqrt((0.09 + 0.01 + 0 + 0.04) / 4) = sqrt(0.035)
    assert_allclose(s.rmse, [math.sqrt(0.015), math.sqrt(0.03), math.sqrt(0.035)], rtol=1e-12)
    assert s.rmse_r == pytest.approx(math.sqrt(0.045))
    assert s.rmse_3d == pytest.approx(math.sqrt(0.08))
    assert_allclose(s.mean, [0.05, -0.05, 0.1], atol=1e-12)
    assert s.std[0] == pytest.approx(np.std(E[:, 0], ddof=1))
    assert s.le90 == pytest.approx(1.6448536 * math.sqrt(0.035))
    # the interval of RMSE_z: 4 dof, chi2(4) quantiles 0.4844186 and 11.1432868
    assert_allclose(s.interval_z, [math.sqrt(0.035 * 4 / 11.1432868), math.sqrt(0.035 * 4 / 0.4844186)], rtol=1e-6)
    assert s.asprs_rmse_h == pytest.approx(s.rmse_r)
    text = "\n".join(s.lines())
    assert "RMSE_r 0.212 m" in text and "RMSE_z 0.187 m" in text and "LE90 0.308 m" in text
    assert "produced to meet" in text and "4 check points" in text
    assert "RMSE_H = 21.2 (cm)" in text and "RMSE_V = 18.7 (cm)" in text


def test_survey_accuracy_is_added_as_edition_2_asks():
    s = AccuracyStatement.from_errors(np.tile(E, (8, 1)), survey_rmse_h=0.05, survey_rmse_v=0.04)
    assert s.n == 32
    assert s.asprs_rmse_h == pytest.approx(math.hypot(math.sqrt(0.045), 0.05))
    assert s.asprs_rmse_v == pytest.approx(math.hypot(math.sqrt(0.035), 0.04))
    assert any("was tested to meet" in line for line in s.asprs_sentences())
    d = s.to_dict()
    assert d["asprs_2023"]["enough_checkpoints"] is True and d["n"] == 32


def test_planimetric_product_has_no_vertical_figures():
    s = AccuracyStatement.from_errors(E[:, :2])
    assert not s.has_heights and math.isnan(s.rmse_z) and math.isnan(s.le90)
    assert not any("RMSE_V" in line for line in s.lines())
    assert s.to_dict()["rmse_z"] is None


def test_ce90_closed_forms_and_monte_carlo():
    assert ce90(1.0, 1.0) == pytest.approx(math.sqrt(-2 * math.log(0.1)), rel=1e-6)   # 2.1460
    assert ce90(2.0, 0.0) == pytest.approx(2 * 1.6448536, rel=1e-6)
    rng = np.random.default_rng(3)
    for sx, sy in ((1.0, 0.5), (0.3, 1.2), (1.0, 0.05)):
        r = np.hypot(rng.normal(0, sx, 400_000), rng.normal(0, sy, 400_000))
        assert ce90(sx, sy) == pytest.approx(np.percentile(r, 90), rel=5e-3)


def test_rmse_intervals_cover_the_true_sigma_at_their_level():
    rng = np.random.default_rng(7)
    hit = 0
    trials = 2000
    for _ in range(trials):
        s = AccuracyStatement.from_errors(rng.normal(0, [0.1, 0.1, 0.2], (12, 3)))
        hit += s.interval_z[0] <= 0.2 <= s.interval_z[1]
    assert 0.93 <= hit / trials <= 0.97


@settings(max_examples=40, deadline=None)
@given(st.floats(0.01, 100), st.integers(1, 500), st.floats(0.5, 0.99))
def test_interval_brackets_the_estimate(rmse, dof, conf):
    lo, hi = rmse_interval(rmse, dof, conf)
    assert lo < rmse < hi or (dof > 1 and lo <= rmse <= hi)
    lo2, hi2 = rmse_interval(rmse, dof, min(conf + 0.005, 0.995))
    assert lo2 <= lo + 1e-12 and hi2 >= hi - 1e-12


@pytest.mark.parametrize("errors, match", [
    (np.zeros((0, 3)), "at least 1 check point; got 0"),
    (np.zeros((3, 4)), r"\(N, 2\) or \(N, 3\) array; got shape \(3, 4\)"),
    (np.array([[0.1, np.nan, 0.0]]), "check point 0 has a non-finite error"),
])
def test_bad_input(errors, match):
    with pytest.raises(InvalidInputError, match=match):
        AccuracyStatement.from_errors(errors)


def test_bad_options():
    with pytest.raises(InvalidInputError, match="survey_rmse_h must be a finite number >= 0; got -1"):
        AccuracyStatement.from_errors(E, survey_rmse_h=-1)
    with pytest.raises(InvalidInputError, match=r"confidence level must lie in \(0, 1\); got 1.5"):
        rmse_interval(1.0, 3, 1.5)


def test_vertical_only_statement_by_hand():
    """A DSM's statement at check points: RMSE_z, its chi-square interval and LE90 by hand; no horizontal figure."""
    ez = np.array([0.1, -0.2, 0.3, 0.05])
    s = AccuracyStatement.vertical(ez)
    rz = math.sqrt((0.01 + 0.04 + 0.09 + 0.0025) / 4)
    assert s.rmse_z == pytest.approx(rz, rel=1e-12) and s.le90 == pytest.approx(1.6448536269514722 * rz)
    lo, hi = s.interval_z
    assert lo == pytest.approx(rz * math.sqrt(4 / chdtri(4, 0.025)), rel=1e-9)
    assert hi == pytest.approx(rz * math.sqrt(4 / chdtri(4, 0.975)), rel=1e-9)
    assert not s.has_plan and math.isnan(s.rmse_r) and math.isnan(s.ce90)
    text = "\n".join(s.lines())
    assert "RMSE_H" not in text and "CE90" not in text and "RMSE_V = 18.9 (cm)" in text
    assert s.to_dict()["asprs_2023"]["rmse_h"] is None
    with pytest.raises(InvalidInputError, match=r"\(N,\) array"):
        AccuracyStatement.vertical(np.zeros((3, 2)))
