"""Two-sided Monte Carlo checks of the precision every stereo estimator reports.

For relative orientation, absolute orientation, space resection and intersection, synthetic data with
known Gaussian noise sigma are adjusted many times (seeded, fixed trial counts). Two figures must
match the simulation on *both* sides:

* sigma0: ``sqrt(mean(sigma0^2))`` over the trials within +-5 % of sigma. The mean of sigma0^2, not
  of sigma0, because sigma0^2 is unbiased (sigma0 itself is biased low by c4(dof), 11 % at dof 3).
  Its relative standard deviation is ``1 / sqrt(2 * sum(dof))``; the trial counts give
  ``sum(dof) >= 1500``, so +-5 % is at least 2.7 standard deviations and the fixed seeds land well
  inside (the measured values are in the comments). Redundancies are kept small (dof 3-8 per trial)
  so that a wrong denominator (n instead of n - u, n - 6 instead of n - 5) moves sigma0 by 10 % or
  more and leaves the band.
* standardised errors: the RMS over all trials and parameters of ``(estimate - truth) / se`` in
  [0.9, 1.1], where ``se`` is the reported standard error rescaled to the true sigma
  (``se / sigma0 * sigma``): this checks the cofactor matrix and the covariance scaling without the
  Student-t inflation of a per-trial sigma0. Its relative standard deviation is about
  ``1 / sqrt(2 * trials * parameters)`` (about 2 % here), so the band is about 5 standard deviations.
"""

from __future__ import annotations

import math

import numpy as np

from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles
from stereo.pair.absolute import AbsoluteOrientation
from stereo.pair.intersection import intersect
from stereo.pair.resection import ExteriorOrientation, resect
from stereo.relative import RelativeOrientation
from tests.support.stereo_support import simulate_pair


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------ relative orientation
def test_relative_orientation_sigma0_and_standard_errors():
    """10 points (dof 5), 0.3 px noise, 400 trials: sum(dof) = 2000."""
    sigma_px, pix = 0.3, 0.144
    sigma = sigma_px * pix
    s0sq, z = [], []
    for seed in range(400):
        sp = simulate_pair("vertical", n=10, noise_px=sigma_px, rng=1000 + seed)
        ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=sp.focal_length_mm,
                                             system="left-image")
        assert ro.n_used - 5 == 5
        s0sq.append(ro.sigma0_mm ** 2)
        se = ro.std_errors / ro.sigma0_mm * sigma
        z.append(_wrap(ro.elements - sp.truth("left-image")) / se)
    ratio = math.sqrt(np.mean(s0sq)) / sigma
    assert 0.95 < ratio < 1.05, ratio  # measured 1.004
    rz = _rms(z)
    assert 0.9 < rz < 1.1, rz  # measured 1.022


# ------------------------------------------------------------ absolute orientation
def _similarity(rng, n):
    R = matrix_from_angles(*rng.uniform(-0.3, 0.3, 3))
    s, T = rng.uniform(5, 50), rng.uniform(-1e3, 1e3, 3)
    m = rng.uniform(-50, 50, (n, 3)) * [1, 1, 0.3]
    return m, s * m @ R.T + T, np.concatenate([[s], angles_from_matrix(R), T])


def test_absolute_orientation_sigma0_and_standard_errors():
    """5 full points (15 equations, dof 8), 0.2 m noise, 250 trials: sum(dof) = 2000."""
    rng = np.random.default_rng(181)
    sigma = 0.2
    s0sq, z = [], []
    for _ in range(250):
        m, g, p_true = _similarity(rng, 5)
        ao = AbsoluteOrientation.from_points(m, g + rng.normal(0, sigma, g.shape))
        assert ao.residuals.summary()["n_fit"] == 5
        s0sq.append(ao.sigma0 ** 2)
        se = ao.std_errors / ao.sigma0 * sigma
        z.append(_wrap(ao.parameters - p_true) / se)
    ratio = math.sqrt(np.mean(s0sq)) / sigma
    assert 0.95 < ratio < 1.05, ratio  # measured 1.002
    rz = _rms(z)
    assert 0.9 < rz < 1.1, rz  # measured 1.012


# ------------------------------------------------------------------ resection
def test_resection_sigma0_and_standard_errors():
    """6 control points (12 equations, dof 6), 5 um noise, 300 trials: sum(dof) = 1800."""
    rng = np.random.default_rng(182)
    sigma = 0.005
    s0sq, z = [], []
    for _ in range(300):
        R = matrix_from_angles(*rng.uniform(-0.05, 0.05, 2), rng.uniform(-np.pi, np.pi))
        C = np.array([5e5, 4e6, 3000.0]) + rng.uniform(-100, 100, 3)
        G = np.column_stack([C[0] + rng.uniform(-1500, 1500, 6), C[1] + rng.uniform(-1500, 1500, 6),
                             rng.uniform(0, 400, 6)])
        eo0 = ExteriorOrientation(position=C, rotation=R, focal_length_mm=120.0, principal_point_mm=(0.01, -0.02))
        x = eo0.project(G) + rng.normal(0, sigma, (6, 2))
        eo = resect(x, G, focal_length_mm=120.0, principal_point_mm=(0.01, -0.02))
        s0sq.append(eo.sigma0 ** 2)
        se = eo.std_errors
        k = sigma / eo.sigma0
        z.append((eo.position - C) / (np.array([se["x"], se["y"], se["z"]]) * k))
    ratio = math.sqrt(np.mean(s0sq)) / sigma
    assert 0.95 < ratio < 1.05, ratio  # measured 0.978
    rz = _rms(z)
    assert 0.9 < rz < 1.1, rz  # measured 1.011


# --------------------------------------------------------------- intersection
def test_intersection_covariance_and_residuals():
    """Convergent pair with unequal focal lengths; 3000 points, 4 photo coordinates and 3 unknowns each
    (dof 1 per point): the point covariance predicts the errors, the residuals estimate sigma."""
    rng = np.random.default_rng(183)
    sigma = 0.004
    R1 = matrix_from_angles(0.02, 0.25, 0.1)
    R2 = matrix_from_angles(-0.03, -0.2, -0.05)
    C1, B = np.array([10.0, -5.0, 1000.0]), np.array([420.0, 30.0, -25.0])
    f1, f2 = 100.0, 150.0
    n = 3000
    P = np.column_stack([rng.uniform(-200, 600, n), rng.uniform(-300, 300, n), rng.uniform(-50, 50, n)])

    def proj(R, C, f):
        p = (P - C) @ R
        return np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]])

    x1 = proj(R1, C1, f1) + rng.normal(0, sigma, (n, 2))
    x2 = proj(R2, C1 + B, f2) + rng.normal(0, sigma, (n, 2))
    it = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=(f1, f2),
                   centre_left=C1, sigma_mm=sigma)
    z = (it.points - P) / it.std
    rz = np.sqrt(np.mean(z * z, axis=0))
    assert np.all((rz > 0.9) & (rz < 1.1)), rz  # measured 1.022, 1.023, 1.025
    # sigma0 from the photo residuals: v'v / (4 n - 3 n)
    s0 = math.sqrt(float(np.sum(np.square(it.residuals_mm))) / n)
    assert 0.95 < s0 / sigma < 1.05, s0 / sigma  # measured 0.995
