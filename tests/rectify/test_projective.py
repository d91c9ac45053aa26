"""Tests of rectify.geometry.transforms: homography, cotangent four-point method, affine,
polynomials, the registry, GCP fitting and transform JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError, RasterIOError, ShapeError
from rectify.formats.transform import read_transform, write_transform
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms import (
    METHODS,
    PAIRS,
    AffineTransform,
    CotangentFourPoint,
    Homography,
    PolynomialTransform,
    base_cotangents,
    corrected_eq2,
    fit_gcps,
    printed_eq2,
    transform_from_dict,
    transform_to_dict,
)

# A known homography (source pixels of a 1000 x 800 image -> target)
H_TRUE = np.array([[1.1, 0.05, 10.0], [-0.02, 0.95, 20.0], [1e-4, -5e-5, 1.0]])
SRC = np.array([[0.0, 0.0], [1000.0, 0.0], [1000.0, 800.0], [0.0, 800.0]])
DST = Homography(H_TRUE)(SRC)
SIZE = 1000.0


def _grid(n: int = 21, lo: float = -200.0, hi: float = 1200.0) -> np.ndarray:
    g = np.linspace(lo, hi, n)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


# ----------------------------------------------------------------- homography
def test_homography_exact_four_points_recovers_known_matrix():
    H = Homography.from_points(SRC, DST)
    assert_allclose(H.matrix, H_TRUE, rtol=1e-9, atol=1e-9 * np.abs(H_TRUE).max())
    assert_allclose(H(SRC), DST, atol=1e-9)


def test_homography_least_squares_beats_or_equals_dlt_on_noise():
    rng = np.random.default_rng(1)
    s = rng.uniform(0, 1000, (40, 2))
    d = Homography(H_TRUE)(s) + rng.normal(0, 0.5, (40, 2))
    h_ls = Homography.from_points(s, d)
    h_dlt = Homography.from_points(s, d, refine=False)
    assert np.sum(h_ls.residuals(s, d) ** 2) <= np.sum(h_dlt.residuals(s, d) ** 2) + 1e-9
    # truth recovered to the noise level on a check grid
    g = _grid(11, 0, 1000)
    assert np.abs(h_ls(g) - Homography(H_TRUE)(g)).max() < 1.0


def test_homography_weights_zero_weight_ignores_point():
    rng = np.random.default_rng(2)
    s = rng.uniform(0, 1000, (8, 2))
    d = Homography(H_TRUE)(s)
    d_bad = d.copy()
    d_bad[3] += 50.0
    w = np.ones(8)
    w[3] = 0.0
    H = Homography.from_points(s, d_bad, weights=w)
    assert_allclose(H(s[[0, 1, 2, 4]]), d[[0, 1, 2, 4]], atol=1e-6)
    assert H.residuals(s, d_bad)[3] == pytest.approx(50.0 * math.sqrt(2.0), rel=1e-6)


def test_homography_inverse_and_composition():
    H = Homography(H_TRUE)
    g = _grid()
    assert_allclose(H.inverse(H(g)), g, atol=1e-8)
    assert_allclose((H @ H.inverse).matrix / (H @ H.inverse).matrix[2, 2], np.eye(3), atol=1e-12)
    A = AffineTransform([[2, 0, 1], [0, 3, -1], [0, 0, 1]])
    assert_allclose((H @ A)(g), H(A(g)), rtol=1e-12, atol=1e-9)
    assert isinstance(A @ A, AffineTransform)
    assert isinstance(H @ A, Homography)
    assert_allclose(np.asarray(H), H.matrix)


def test_homography_is_immutable_and_inputs_untouched():
    s, d = SRC.copy(), DST.copy()
    H = Homography.from_points(s, d)
    assert_allclose(s, SRC)
    with pytest.raises(ValueError):
        H.matrix[0, 0] = 5.0
    with pytest.raises(AttributeError):
        H.matrix = np.eye(3)  # type: ignore[misc]


def test_sizes_zero_one_many():
    for model in (Homography(H_TRUE), CotangentFourPoint(SRC, DST), AffineTransform(np.eye(3))):
        assert model(np.empty((0, 2))).shape == (0, 2)
        assert model([5.0, 7.0]).shape == (1, 2)
        assert model(_grid(5)).shape == (25, 2)
        assert model.residuals(SRC, DST).shape == (4,)


# ----------------------------------------------------------------- degenerate input, every method
@pytest.mark.parametrize("name", sorted(METHODS))
def test_degenerate_input_raises(name):
    m = METHODS[name]
    rng = np.random.default_rng(3)
    s = rng.uniform(0, 100, (12, 2))
    d = s * 1.5 + 3
    with pytest.raises(EstimationError, match="too few"):
        m.from_points(s[: m.min_points - 1], d[: m.min_points - 1])
    with pytest.raises(InvalidInputError, match="non-finite"):
        bad = s.copy()
        bad[2, 0] = np.nan
        m.from_points(bad, d)
    with pytest.raises(InvalidInputError, match="non-finite"):
        bad = d.copy()
        bad[1, 1] = np.inf
        m.from_points(s, bad)
    with pytest.raises(ShapeError, match=r"shape \(N, 2\); got \(12, 3\)"):
        m.from_points(np.ones((12, 3)), d)
    with pytest.raises(ShapeError, match="same number of points"):
        m.from_points(s, d[:-1])
    n = max(m.min_points, 4)
    dup = s[:n].copy()
    dup[1] = dup[0]
    with pytest.raises(EstimationError, match="duplicate"):
        m.from_points(dup, d[:n])
    line = np.column_stack([np.arange(n) * 10.0, np.arange(n) * 5.0 + 1])
    with pytest.raises(EstimationError, match="collinear"):
        m.from_points(line, d[:n])


@pytest.mark.parametrize("cls", [Homography, CotangentFourPoint])
def test_three_collinear_of_four_raises(cls):
    s = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [5.0, 9.0]])
    with pytest.raises(EstimationError, match="three of `src` are collinear: rows 0, 1, 2"):
        cls.from_points(s, DST)
    with pytest.raises(EstimationError, match="three of `dst` are collinear"):
        cls.from_points(SRC, s)


def test_cotangent_needs_exactly_four():
    with pytest.raises(EstimationError, match="exactly 4"):
        CotangentFourPoint.from_points(_grid(3), _grid(3))


# ----------------------------------------------------------------- cotangent method
def test_printed_eq2_is_wrong_and_corrected_eq2_is_right():
    """Seed 001 eq. (2) as printed misplaces points off the base; the corrected y-line fixes it."""
    a, b = SRC[0], SRC[1]
    p = np.array([[300.0, 200.0], [700.0, -150.0], [-50.0, 500.0]])
    cb, cg = base_cotangents(a, b, p)
    assert_allclose(corrected_eq2(a, b, cb, cg), p, atol=1e-9)
    printed = printed_eq2(a, b, cb, cg)
    assert_allclose(printed[:, 0], p[:, 0], atol=1e-9)  # the x-line is right
    assert np.abs(printed[:, 1] - p[:, 1]).min() > 100.0  # the y-line is not
    # and against the homography: carry with the printed formula fails
    C = CotangentFourPoint(SRC, DST)
    assert_allclose(C(p), Homography(H_TRUE)(p), atol=1e-8)


def test_cotangent_agrees_with_homography_on_grid_including_base_lines():
    C = CotangentFourPoint.from_points(SRC, DST)
    H = Homography(H_TRUE)
    g = np.vstack([_grid(41), SRC, [[500.0, 0.0], [1000.0, 400.0], [500.0, 400.0], [0.0, 123.0]]])
    assert np.abs(C(g) - H(g)).max() < 1e-8 * SIZE
    pair, bound = C.base_pairs(g)
    assert pair.shape == (len(g),) and (bound < 1e-11 * SIZE).all()
    # the chosen pair's full (float64) error measure is within 5x of the best of the six: the float32
    # choice leaves out the source guard term, which matters only close to a base line
    eb = C.error_bound(g)
    assert (eb[pair, np.arange(len(g))] <= 5 * eb.min(axis=0)).all()
    assert (pair == np.argmin(eb, axis=0)).mean() > 0.95


def test_cotangent_base_pair_avoids_the_base_line():
    """A point on the line through control points 0 and 1 must not use the pair (0, 1)."""
    C = CotangentFourPoint(SRC, DST)
    on_line = np.array([[500.0, 0.0], [-300.0, 0.0], [2000.0, 0.0]])
    pair, bound = C.base_pairs(on_line)
    assert (pair != PAIRS.index((0, 1))).all() and np.isfinite(bound).all()
    assert_allclose(C(on_line), Homography(H_TRUE)(on_line), atol=1e-8 * SIZE)
    assert np.isinf(C.error_bound(on_line)[PAIRS.index((0, 1))]).all()


def test_cotangent_near_base_line_is_stable_with_any_pair():
    """Eq. (2) near (not on) the base line is backward stable: forcing the base-line pair stays exact."""
    C = CotangentFourPoint(SRC, DST)
    H = Homography(H_TRUE)
    t = C._tables
    j = PAIRS.index((0, 1))
    for off in (1e-3, 1e-7, 1e-11):
        p = np.array([[300.0, off], [700.0, -off], [-200.0, off]])
        gx, gy = C._chain(j, p[:, 0] - t["centre"][0], p[:, 1] - t["centre"][1])
        assert np.abs(np.column_stack([gx, gy]) - H(p)).max() < 1e-10 * SIZE


def test_cotangent_raises_when_no_pair_is_conditioned(monkeypatch):
    import rectify.geometry.transforms.cotangent as proj

    monkeypatch.setattr(proj, "COT_MAX_REL_ERROR", 1e-20)
    with pytest.raises(EstimationError, match=r"no well-conditioned base pair: the best \(pair"):
        CotangentFourPoint(SRC, DST)([[400.0, 300.0]])


@pytest.mark.parametrize("eps, raises", [(1e-5, False), (1e-9, True)])
def test_cotangent_near_collinear_controls(eps, raises):
    """Control point 2 at eps * side from the line through points 1 and 3: the estimated error
    bounds the actual one, and past COT_MAX_REL_ERROR the method raises instead of answering."""
    H_t = Homography(np.array([[0.95, 0.08, 20.0], [-0.05, 1.05, 10.0], [6e-5, -4e-5, 1.0]]))
    src = np.array([[0.0, 0.0], [1000.0, 0.0], [1000.0, 1000.0], [0.0, 1000.0]])
    src[2] = (src[1] + src[3]) / 2 + np.array([1.0, 1.0]) / math.sqrt(2) * eps * SIZE
    C = CotangentFourPoint(src, H_t(src))
    g = _grid(9, 250, 750)
    if raises:
        with pytest.raises(EstimationError, match="no well-conditioned base pair"):
            C(g)
        return
    _, bound = C.base_pairs(g)
    err = np.abs(C(g) - H_t(g)).max(axis=1)
    assert (err <= bound + 1e-12 * SIZE).all()
    assert np.abs(C(g) - Homography.from_points(src, H_t(src))(g)).max() < 1e-8 * SIZE


def test_cotangent_map_coordinates_inverse():
    """Target in UTM-like coordinates (5e6 m): the inverse (map -> pixel) stays exact."""
    dst = DST * 0.5 + [500000.0, 5000000.0]
    C = CotangentFourPoint(SRC, dst)
    H = Homography.from_points(SRC, dst)
    g = _grid(15, 0, 1000)
    assert np.abs(C(g) - H(g)).max() < 1e-8 * SIZE
    assert np.abs(C.inverse(C(g)) - g).max() < 1e-8 * SIZE


def test_cotangent_inverse_swaps_roles():
    C = CotangentFourPoint(SRC, DST)
    assert_allclose(C.inverse.src, DST)
    assert_allclose(C.inverse(C(_grid())), _grid(), atol=1e-8 * SIZE)
    assert_allclose(Homography.from_points(C.src, C.dst).matrix, H_TRUE, rtol=1e-9, atol=1e-12)


_coord = st.floats(min_value=0.0, max_value=1.0, allow_nan=False)


def _quad(draw_pts):
    q = np.array(draw_pts, dtype=float).reshape(4, 2) * SIZE
    return q


def _min_tri_rel(q: np.ndarray) -> float:
    from itertools import combinations

    out = np.inf
    for i, j, k in combinations(range(4), 3):
        a, b, c = q[i], q[j], q[k]
        out = min(out, abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])) / SIZE ** 2)
    return out


# a point on or near the line through two control points: (pair, position along it, log10 offset or None)
_near_line = st.tuples(st.integers(0, 5), st.floats(-1.0, 2.0),
                       st.one_of(st.none(), st.floats(-15.0, -1.0)), st.booleans())


def _near_line_points(src: np.ndarray, draws) -> np.ndarray:
    out = []
    for k, t, lg, neg in draws:
        a, b = src[PAIRS[k][0]], src[PAIRS[k][1]]
        d = b - a
        n = np.array([-d[1], d[0]]) / np.hypot(*d)
        off = 0.0 if lg is None else (-1.0 if neg else 1.0) * 10.0 ** lg * SIZE
        out.append(a + t * d + off * n)
    return np.array(out).reshape(-1, 2)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_coord, min_size=8, max_size=8), st.lists(_coord, min_size=8, max_size=8),
       st.lists(_coord, min_size=20, max_size=20), st.lists(_near_line, min_size=0, max_size=12))
def test_property_cotangent_equals_homography_and_inverts(s, d, p, near):
    """For random non-degenerate configurations the two methods agree to 1e-8 of the image size,
    also for points on and near the lines through two control points (eq. 2's singular lines)."""
    src, dst = _quad(s), _quad(d)
    assume(_min_tri_rel(src) > 0.02 and _min_tri_rel(dst) > 0.02)
    H = Homography.from_points(src, dst)
    C = CotangentFourPoint.from_points(src, dst)
    pts = np.vstack([np.array(p).reshape(10, 2) * SIZE, _near_line_points(src, near), src])
    hp = H(pts)
    # keep points whose image stays within a few image sizes (far from the vanishing line)
    keep = np.abs(hp).max(axis=1) < 5 * SIZE
    assume(keep.sum() >= 3)
    pts, hp = pts[keep], hp[keep]
    assert np.abs(C(pts) - hp).max() <= 1e-8 * SIZE
    assert np.abs(C.inverse(C(pts)) - pts).max() <= 1e-8 * SIZE
    assert np.abs(H.inverse(H(pts)) - pts).max() <= 1e-8 * SIZE


@settings(max_examples=60, deadline=None)
@given(st.lists(_coord, min_size=8, max_size=8), st.lists(_coord, min_size=8, max_size=8))
def test_property_four_point_fit_recovers_known_homography(s, d):
    src, dst = _quad(s), _quad(d)
    assume(_min_tri_rel(src) > 0.02 and _min_tri_rel(dst) > 0.02)
    H0 = Homography.from_points(src, dst)
    # regenerate dst exactly from H0 and refit
    H1 = Homography.from_points(src, H0(src))
    m0, m1 = H0.matrix / np.linalg.norm(H0.matrix), H1.matrix / np.linalg.norm(H1.matrix)
    m1 = m1 * np.sign(np.sum(m0 * m1))
    assert np.abs(m1 - m0).max() <= 1e-9


# ----------------------------------------------------------------- affine and polynomials
def test_affine_exact_and_inverse():
    A_true = np.array([[0.9, -0.2, 30.0], [0.15, 1.05, -12.0], [0.0, 0.0, 1.0]])
    g = _grid(6, 0, 1000)
    A = AffineTransform.from_points(g, AffineTransform(A_true)(g))
    assert_allclose(A.matrix, A_true, rtol=1e-12, atol=1e-10)
    assert_allclose(A.inverse(A(g)), g, atol=1e-9)
    with pytest.raises(InvalidInputError, match="row"):
        AffineTransform(H_TRUE)


@pytest.mark.parametrize("order", [2, 3])
def test_polynomial_reproduces_polynomial_data_and_approx_inverse(order):
    rng = np.random.default_rng(5)
    s = rng.uniform(0, 1000, (40, 2))
    x, y = s[:, 0] / 1000, s[:, 1] / 1000
    d = np.column_stack([10 + 900 * x + 30 * y + 20 * x * y + (5 * x ** 3 if order == 3 else 0),
                         -5 + 20 * x + 800 * y - 15 * y ** 2])
    P = PolynomialTransform.from_points(s, d, order=order)
    assert P.residuals(s, d).max() < 1e-8
    inv = P.inverse
    assert inv.inverse_rmse is not None and inv.inverse_rmse < 0.05
    assert np.abs(inv(P(s)) - s).max() < 0.2  # approximate by construction


def test_polynomial_bad_parameters():
    with pytest.raises(InvalidInputError, match="order"):
        PolynomialTransform(4, np.zeros((2, 15)))
    with pytest.raises(ShapeError, match=r"\(2, 6\)"):
        PolynomialTransform(2, np.zeros((2, 5)))
    # order-2 polynomial with 6 points on a conic is rank deficient
    t = np.linspace(0, 2 * np.pi, 7)[:-1]
    circle = np.column_stack([np.cos(t), np.sin(t)]) * 100 + 500
    with pytest.raises(EstimationError, match="rank deficient"):
        PolynomialTransform.from_points(circle, circle, order=2)


def test_methods_registry_names():
    assert set(METHODS) == {"homography", "cotangent", "affine", "poly2", "poly3"}
    rng = np.random.default_rng(6)
    s = rng.uniform(0, 1000, (12, 2))
    d = Homography(H_TRUE)(s)
    for name, m in METHODS.items():
        ss, dd = (s[:4], d[:4]) if name == "cotangent" else (s, d)
        model = m.from_points(ss, dd)
        assert model(ss).shape == ss.shape
        assert model.residuals(ss, dd).shape == (len(ss),)
        if name in ("homography", "cotangent"):
            assert model.residuals(ss, dd).max() < 1e-8


# ----------------------------------------------------------------- GCP fitting and JSON
def _gcps(n: int = 9, check_rows=(7, 8), noise: float = 0.0, crs=None) -> GcpTable:
    rng = np.random.default_rng(7)
    pix = rng.uniform(0, 1000, (n, 2))
    tgt = Homography(H_TRUE)(pix) + rng.normal(0, noise, (n, 2)) if noise else Homography(H_TRUE)(pix)
    check = np.zeros(n, bool)
    check[list(check_rows)] = True
    return GcpTable(tuple(f"P{i}" for i in range(n)), pix, tgt, None, check, crs)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_fit_gcps_withholds_check_points(name):
    g = _gcps(14, check_rows=(12, 13), noise=0.3)
    r = fit_gcps(g, name)
    t = r.table
    assert t.n == 14 and t.check[12] and t.check[13]
    s = t.summary()
    assert s["rmse_check"] is not None and np.isfinite(s["rmse"])
    # the model was fitted without the check rows: changing them does not change the model
    tgt2 = g.target.copy()
    tgt2[12:] += 100.0
    g2 = GcpTable(g.ids, g.pixel, tgt2, None, g.check, None)
    r2 = fit_gcps(g2, name)
    assert_allclose(r2.model(g.pixel[:5]), r.model(g.pixel[:5]), atol=1e-9)
    assert r2.table.summary()["rmse_check"] > 50
    if name == "cotangent":
        assert s["n_fit"] == 4 and s["n_check"] == 10
        assert len(t.extra["control_ids"]) == 4


def test_fit_gcps_exact_homography_and_errors():
    g = _gcps(9, check_rows=(8,))
    r = fit_gcps(g, "homography")
    assert r.table.summary()["rmse"] < 1e-8 and r.table.summary()["rmse_check"] < 1e-8
    with pytest.raises(InvalidInputError, match="unknown method 'bogus'"):
        fit_gcps(g, "bogus")
    with pytest.raises(EstimationError, match="too few fit points for poly3: 3"):
        fit_gcps(_gcps(9, check_rows=range(3, 9)), "poly3")


@pytest.mark.parametrize("name", sorted(METHODS))
def test_transform_json_roundtrip(tmp_path, name):
    g = _gcps(14, check_rows=(13,), noise=0.2, crs="EPSG:32633")
    r = fit_gcps(g, name)
    p = write_transform(tmp_path / "t.json", r.model, table=r.table, crs=g.crs)
    d = json.loads(p.read_text())
    assert d["method"] == name and "rmse" in d and len(d["residuals"]) == 14 and d["crs"] == "EPSG:32633"
    if name == "homography":
        assert np.array(d["matrix"]).shape == (3, 3)
    if name == "cotangent":
        assert np.array(d["src"]).shape == (4, 2) and np.array(d["dst"]).shape == (4, 2)
    m2 = read_transform(p).model
    assert type(m2) is type(r.model)
    assert_allclose(m2(g.pixel), r.model(g.pixel), rtol=1e-12, atol=1e-9)
    with pytest.raises(InvalidInputError, match="exists"):
        write_transform(p, r.model)
    write_transform(p, r.model, overwrite=True)


def test_load_transform_errors(tmp_path):
    with pytest.raises(RasterIOError, match="not found"):
        read_transform(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InvalidInputError, match="not valid JSON"):
        read_transform(tmp_path / "bad.json")
    with pytest.raises(InvalidInputError, match="unknown method 'spline'"):
        transform_from_dict({"method": "spline"})
    with pytest.raises(InvalidInputError, match=r"misses key\(s\) \['matrix'\]"):
        transform_from_dict({"method": "homography"})
    assert transform_to_dict(Homography(H_TRUE))["method"] == "homography"


def test_matrix_validation():
    H = Homography([[0.5, 0.0, 5e5], [0.0, 0.5, 5e6], [0.0, 0.0, 1.0]])  # map coordinates: not singular
    assert_allclose(H.inverse(H([[10.0, 20.0]])), [[10.0, 20.0]], atol=1e-6)
    with pytest.raises(EstimationError, match="singular"):
        Homography(np.ones((3, 3)))
    with pytest.raises(ShapeError, match=r"\(3, 3\); got \(2, 3\)"):
        Homography(np.ones((2, 3)))
    with pytest.raises(InvalidInputError, match="non-finite"):
        Homography([[1.0, 0, 0], [0, np.nan, 0], [0, 0, 1]])
