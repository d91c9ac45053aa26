"""Two-sided Monte Carlo checks of the precision the 2D fits report (sigma0, residuals), and weights.

GCP fits report sigma0 = sqrt(sum w |v|^2 / (2 n - u)) in their residual table. With known Gaussian
noise sigma on the target coordinates, ``sqrt(mean(sigma0^2))`` over the trials must be within +-5 %
of sigma (sigma0^2 is unbiased; sigma0 is not). Its relative standard deviation is
``1 / sqrt(2 * sum(dof))``: with ``sum(dof) >= 1800`` the band is at least 3 standard deviations and
the fixed seeds land well inside it (measured values in the comments). The redundancies are small
(dof 4-12) so that dividing by the number of observations instead moves sigma0 by 20 % or more.

The 2D fits report no parameter covariance, so sigma0 (and, with unequal weights, its weighting) is
the precision figure checked here.
"""

from __future__ import annotations

import math

import numpy as np

from rectify.geometry.points import GcpTable
from rectify.geometry.transforms import fit_gcps

H_TRUE = np.array([[0.9, 0.12, 35.0], [-0.08, 1.05, 20.0], [2e-4, -1.5e-4, 1.0]])


A_TRUE = np.array([[0.9, 0.12, 35.0], [-0.08, 1.05, 20.0], [0.0, 0.0, 1.0]])


def _gcps(rng, n, sigma, truth, crs=None):
    pix = rng.uniform(0, 1000, (n, 2))
    h = np.c_[pix, np.ones(n)] @ truth.T
    tgt = h[:, :2] / h[:, 2:] + rng.normal(0, sigma, (n, 2))
    return GcpTable(tuple(str(i) for i in range(n)), pix, tgt, None, np.zeros(n, bool), crs)


def _sigma0_trials(method, n, n_params, trials, seed, truth, sigma=0.5):
    rng = np.random.default_rng(seed)
    s0sq, dof_sum = [], 0
    for _ in range(trials):
        fr = fit_gcps(_gcps(rng, n, sigma, truth), method)
        s = fr.table.summary()
        assert s["n_params"] == n_params
        s0sq.append(fr.table.sigma0 ** 2)
        dof_sum += 2 * n - n_params
    return math.sqrt(np.mean(s0sq)) / sigma, dof_sum


def test_homography_sigma0_two_sided():
    """10 GCPs (20 equations, 8 parameters, dof 12), 150 trials: sum(dof) = 1800."""
    ratio, dof_sum = _sigma0_trials("homography", 10, 8, 150, seed=1811, truth=H_TRUE)
    assert dof_sum == 1800
    assert 0.95 < ratio < 1.05, ratio  # measured 1.001


def test_affine_sigma0_two_sided():
    """5 GCPs (10 equations, 6 parameters, dof 4), 500 trials: sum(dof) = 2000 (affine truth)."""
    ratio, dof_sum = _sigma0_trials("affine", 5, 6, 500, seed=1812, truth=A_TRUE)
    assert dof_sum == 2000
    assert 0.95 < ratio < 1.05, ratio  # measured 1.010


def test_weighted_sigma0_is_unit_with_inverse_variance_weights():
    """Weights 1 / sigma_i^2 with unequal sigma_i: sigma0 is about 1 (it would not be with sqrt weights or
    with the weights ignored in sigma0)."""
    rng = np.random.default_rng(1813)
    s0sq = []
    n = 10
    sig = np.where(np.arange(n) % 2 == 0, 0.2, 1.0)
    for _ in range(150):
        pix = rng.uniform(0, 1000, (n, 2))
        h = np.c_[pix, np.ones(n)] @ H_TRUE.T
        tgt = h[:, :2] / h[:, 2:] + rng.normal(0, 1, (n, 2)) * sig[:, None]
        g = GcpTable(tuple(str(i) for i in range(n)), pix, tgt, None, np.zeros(n, bool), None)
        s0sq.append(fit_gcps(g, "homography", weights=1 / sig ** 2).table.sigma0 ** 2)
    ratio = math.sqrt(np.mean(s0sq))
    assert 0.95 < ratio < 1.05, ratio  # measured 1.002
