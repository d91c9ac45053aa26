"""Stereo conventions against independent references.

* intersection: an asymmetric pair (unequal focal lengths, tilted photos, a base with y and z
  components) where both scale factors are checked: ``P = C1 + N1 d1 = C2 + N2 d2`` for every method
  (the normal case is symmetric and cannot tell N1 from N2);
* seed 001's nadir N-formula with a base z component;
* collinearity with a principal point offset, written out here;
* weights: an integer weight 2 equals the point listed twice (relative and absolute orientation).
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from rectify.geometry.rotation import matrix_from_angles
from stereo.pair.absolute import AbsoluteOrientation
from stereo.pair.intersection import METHODS, intersect, n_factor_seed001, project
from stereo.pair.resection import ExteriorOrientation, resect
from stereo.relative import RelativeOrientation
from tests.support.stereo_support import simulate_pair

R1 = matrix_from_angles(0.03, 0.21, 0.12)
R2 = matrix_from_angles(-0.05, -0.17, -0.4)
C1 = np.array([12.0, -7.0, 900.0])
B = np.array([380.0, 45.0, -60.0])
F1, F2 = 100.0, 153.0


def _scene(n=25, seed=4):
    rng = np.random.default_rng(seed)
    P = np.column_stack([rng.uniform(-150, 550, n), rng.uniform(-250, 250, n), rng.uniform(-40, 60, n)])

    def proj(R, C, f):
        p = (P - C) @ R
        return np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]])

    return P, proj(R1, C1, F1), proj(R2, C1 + B, F2)


@pytest.mark.parametrize("method", METHODS)
def test_both_scale_factors_asymmetric_pair(method):
    P, x1, x2 = _scene()
    it = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=(F1, F2),
                   centre_left=C1, method=method)
    d1 = np.column_stack([x1, np.full(len(x1), -F1)]) @ R1.T
    d2 = np.column_stack([x2, np.full(len(x2), -F2)]) @ R2.T
    assert_allclose(it.points, P, atol=1e-6)
    assert_allclose(C1 + it.scale_left[:, None] * d1, P, atol=1e-6)
    assert_allclose(C1 + B + it.scale_right[:, None] * d2, P, atol=1e-6)
    # an asymmetric case: the two factors differ by far more than the tolerance
    assert np.abs(it.scale_left / it.scale_right - 1).min() > 0.05
    assert np.abs(it.miss_distance).max() < 1e-6
    assert np.abs(it.residuals_mm).max() < 1e-9


@pytest.mark.parametrize("method", ["least-squares", "midpoint", "aerial-n"])
def test_vertical_parallax_sign_and_scale(method):
    """Shift the right y by +q in the normal case (R = I, B along +X): the parallax is y2 - y1 = +q (to first
    order: the common perpendicular leans off the y axis by the ray directions, about 2 % here)."""
    rng = np.random.default_rng(6)
    n, f = 10, 120.0
    P = np.column_stack([rng.uniform(0, 400, n), rng.uniform(-200, 200, n), rng.uniform(-1000, -900, n)])
    b = np.array([300.0, 0, 0])
    x1 = project(P, rotation=np.eye(3), centre=np.zeros(3), focal_length_mm=f)
    x2 = project(P, rotation=np.eye(3), centre=b, focal_length_mm=f)
    q = rng.uniform(-0.05, 0.05, n)
    x2[:, 1] += q
    it = intersect(x1, x2, rotation_left=np.eye(3), rotation_right=np.eye(3), base=b, focal_length_mm=f,
                   method=method)
    assert_allclose(it.vertical_parallax_mm, q, rtol=0.05, atol=1e-9)


def test_project_formula():
    rng = np.random.default_rng(2)
    P = rng.uniform(-100, 100, (6, 3)) + [0, 0, -1000]
    R, C, f = matrix_from_angles(0.1, -0.2, 0.3), np.array([5.0, -3.0, 20.0]), 88.0
    p = (R.T @ (P - C).T).T
    assert_allclose(project(P, rotation=R, centre=C, focal_length_mm=f),
                    np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]]), atol=1e-12)


def test_seed001_n_formula_with_bz():
    """Nadir photos, base (Bx, 0, Bz): N = (Bx + x2/f Bz) / (x1 - x2) puts the point at N (x1, y1, -f)."""
    f, bx, bz = 150.0, 250.0, 30.0
    rng = np.random.default_rng(3)
    P = np.column_stack([rng.uniform(-200, 400, 8), rng.uniform(-200, 200, 8), rng.uniform(-1100, -900, 8)])
    x1 = project(P, rotation=np.eye(3), centre=np.zeros(3), focal_length_mm=f)
    x2 = project(P, rotation=np.eye(3), centre=[bx, 0.0, bz], focal_length_mm=f)
    N = n_factor_seed001(x1[:, 0], x2[:, 0], bx=bx, bz=bz, focal_length_mm=f)
    assert_allclose(N[:, None] * np.column_stack([x1, np.full(8, -f)]), P, rtol=1e-12)


# ------------------------------------------------------------------ exterior orientation
def test_exterior_orientation_projection_with_principal_point():
    R, C, f, pp = matrix_from_angles(0.02, -0.04, 1.3), np.array([100.0, 200.0, 3000.0]), 120.0, (0.15, -0.25)
    eo = ExteriorOrientation(position=C, rotation=R, focal_length_mm=f, principal_point_mm=pp)
    rng = np.random.default_rng(9)
    G = np.column_stack([rng.uniform(-800, 800, 8) + C[0], rng.uniform(-800, 800, 8) + C[1], rng.uniform(0, 300, 8)])
    p = (G - C) @ R
    ref = np.column_stack([pp[0] - f * p[:, 0] / p[:, 2], pp[1] - f * p[:, 1] / p[:, 2]])
    assert_allclose(eo.project(G), ref, atol=1e-12)
    # resection with the principal point recovers the orientation; with a wrong sign it does not
    good = resect(ref, G, focal_length_mm=f, principal_point_mm=pp)
    assert_allclose(good.position, C, atol=1e-6)
    assert np.abs(good.residuals.residual).max() < 1e-9
    bad = resect(ref, G, focal_length_mm=f, principal_point_mm=(-pp[0], -pp[1]))
    assert np.abs(bad.position - C).max() > 1.0


def test_exterior_orientation_json_angles():
    """The EO JSON names omega, phi, kappa of R = Rx(omega) Ry(phi) Rz(kappa), each with its own value."""
    om, ph, ka = 0.03, -0.07, 1.9
    R = matrix_from_angles(om, ph, ka)
    eo = ExteriorOrientation(position=[1.0, 2.0, 3.0], rotation=R, focal_length_mm=100.0)
    d = eo.to_dict()
    assert d["angles"]["system"] == "omega-phi-kappa"
    assert [d["angles"][k] for k in ("omega", "phi", "kappa")] == pytest.approx([om, ph, ka], abs=1e-12)
    assert_allclose(matrix_from_angles(d["angles"]["omega"], d["angles"]["phi"], d["angles"]["kappa"]),
                    d["rotation"], atol=1e-12)


# ------------------------------------------------------------------ weights
def test_relative_orientation_weight_two_equals_repeated_point():
    sp = simulate_pair("convergent", n=30, noise_px=0.5, rng=12)
    f = sp.focal_length_mm
    w = np.ones(30)
    w[[4, 17]] = 2.0
    a = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=f, weights=w)
    eps = 1e-9
    l2 = np.vstack([sp.left_mm, sp.left_mm[[4, 17]] + eps])
    r2 = np.vstack([sp.right_mm, sp.right_mm[[4, 17]] + eps])
    b = RelativeOrientation.from_points(l2, r2, focal_length_mm=f)
    c = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=f)
    assert_allclose(a.elements, b.elements, atol=1e-8)
    assert np.abs(a.elements - c.elements).max() > 1e-6  # the weights matter
    # the same weighted sum of squares: sigma0^2 (n - 5) agrees (the redundancies differ)
    assert a.sigma0_mm ** 2 * 25 == pytest.approx(b.sigma0_mm ** 2 * 27, rel=1e-6)


@pytest.mark.parametrize("shape", ["point", "coordinate"])
def test_absolute_orientation_weight_two_equals_repeated_point(shape):
    rng = np.random.default_rng(13)
    R = matrix_from_angles(0.1, -0.05, 0.7)
    m = rng.uniform(-50, 50, (8, 3))
    g = 20.0 * m @ R.T + [1e3, 2e3, 50.0] + rng.normal(0, 0.3, (8, 3))
    w = np.ones(8) if shape == "point" else np.ones((8, 3))
    w[2] = 2.0
    a = AbsoluteOrientation.from_points(m, g, weights=w)
    eps = 1e-9
    b = AbsoluteOrientation.from_points(np.vstack([m, m[2] + eps]), np.vstack([g, g[2] + eps]))
    c = AbsoluteOrientation.from_points(m, g)
    assert_allclose(a.parameters, b.parameters, rtol=1e-8, atol=1e-8)
    assert np.abs(a.parameters - c.parameters).max() > 1e-5
    assert a.sigma0 ** 2 * (24 - 7) == pytest.approx(b.sigma0 ** 2 * (27 - 7), rel=1e-6)
