"""stereo.relative: coplanarity relative orientation in three systems of elements."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import (
    ConvergenceError,
    EstimationError,
    InvalidInputError,
    ShapeError,
    WeakGeometryWarning,
)
from rectify.features import MatcherConfig, match_images
from rectify.geometry.camera import Camera
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.rotation import matrix_from_angles
from stereo.formats.orientation import relative_json_text, write_relative
from stereo.relative import (
    SYSTEMS,
    RelativeOptions,
    RelativeOrientation,
    coplanarity,
    relative_from_essential,
)
from tests.support.stereo_support import simulate_pair

DEG = math.pi / 180
F_NGI, PIX = 120.0, 0.144


def rot_angle_deg(Ra, Rb):
    """Angle of Ra^T Rb, accurate near zero (|Ra - Rb|_F = 2 sqrt(2) sin(angle / 2))."""
    return math.degrees(2 * math.asin(min(1.0, np.linalg.norm(Ra - Rb) / (2 * math.sqrt(2)))))


def vec_angle_deg(a, b):
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------ Jacobians
@pytest.mark.parametrize("system", list(SYSTEMS))
def test_analytic_jacobian_matches_finite_differences(system):
    rng = np.random.default_rng(11)
    sp = simulate_pair("vertical", n=30, rng=rng)
    for _ in range(3):
        p = rng.uniform(-0.3, 0.3, 5)
        _, J = coplanarity(system, p, sp.left_mm, sp.right_mm, F_NGI)
        h = 1e-6
        Jfd = np.empty_like(J)
        for k in range(5):
            d = np.zeros(5)
            d[k] = h
            Jfd[:, k] = (coplanarity(system, p + d, sp.left_mm, sp.right_mm, F_NGI)[0]
                         - coplanarity(system, p - d, sp.left_mm, sp.right_mm, F_NGI)[0]) / (2 * h)
        assert_allclose(J, Jfd, rtol=1e-6, atol=1e-7 * np.abs(J).max())


def _seed000(p, lm, r, f):
    """Seed 000, eqs. (2), (4) and the coefficients a..e of the correction equations (5)."""
    tau, w1, a1, a2, c2 = p
    x1, y1, x2, y2 = lm[:, 0], lm[:, 1], r[:, 0], r[:, 1]
    X1 = x1 * np.cos(a1) - f * np.sin(a1)
    Y1 = x1 * np.sin(w1) * np.sin(a1) + y1 * np.cos(w1) + f * np.sin(w1) * np.cos(a1)
    Z1 = -x1 * np.cos(w1) * np.sin(a1) + y1 * np.sin(w1) - f * np.cos(w1) * np.cos(a1)
    X2 = x2 * np.cos(a2) * np.cos(c2) - y2 * np.cos(a2) * np.sin(c2) - f * np.sin(a2)
    Y2 = x2 * np.sin(c2) + y2 * np.cos(c2)
    Z2 = -x2 * np.sin(a2) * np.cos(c2) + y2 * np.sin(a2) * np.sin(c2) - f * np.cos(a2)
    t = np.tan(tau)
    F = (Y1 * Z2 - Z1 * Y2) + (Z1 * X2 - X1 * Z2) * t
    a = (Z1 * X2 - X1 * Z2) / np.cos(tau) ** 2
    b = Y1 * (X2 * t - Y2) - Z1 * Z2
    c = (X1 * (Y2 * np.cos(w1) + Z2 * np.sin(w1))
         + (Z2 * (x1 * np.sin(a1) + f * np.cos(a1)) - X1 * X2 * np.cos(w1)) * t)
    d = (X1 * X2 + Z1 * Z2) * t - Y1 * X2
    e = (Y1 * Y2 * np.sin(a2) - Z1 * (x2 * np.cos(c2) - y2 * np.sin(c2))
         - (X1 * Y2 * np.sin(a2) + Z1 * Y2 * np.cos(a2)) * t)
    return F, np.column_stack([a, b, c, d, e])


def test_seed000_equations_and_coefficients():
    """Our dobrynin-pimshina misclosure is seed 000's eq. (2) times cos(tau); the
    printed coefficients a, b, c, d, e match finite differences of eq. (2)."""
    rng = np.random.default_rng(5)
    sp = simulate_pair("vertical", n=25, rng=rng)
    p = rng.uniform(-0.2, 0.2, 5)
    F, J = coplanarity("dobrynin-pimshina", p, sp.left_mm, sp.right_mm, F_NGI)
    Fs, coef = _seed000(p, sp.left_mm, sp.right_mm, F_NGI)
    assert_allclose(F, Fs * math.cos(p[0]), rtol=1e-10)
    h = 1e-6
    for col, k in zip(range(5), range(5), strict=True):
        d = np.zeros(5)
        d[k] = h
        fd = (_seed000(p + d, sp.left_mm, sp.right_mm, F_NGI)[0]
              - _seed000(p - d, sp.left_mm, sp.right_mm, F_NGI)[0]) / (2 * h)
        assert_allclose(coef[:, col], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    # our analytic Jacobian is the seed's times cos(tau) (plus F * d cos(tau) / d tau for tau)
    scale = math.cos(p[0])
    assert_allclose(J[:, 0], coef[:, 0] * scale - Fs * math.sin(p[0]), rtol=1e-8, atol=1e-8 * np.abs(J).max())
    for k in range(1, 5):
        assert_allclose(J[:, k], coef[:, k] * scale, rtol=1e-8, atol=1e-8 * np.abs(J[:, k]).max())


# ------------------------------------------------------- Dewitt known answer
def test_dewitt_relor_sample(dewitt):
    """Wolf & Dewitt relor_sample: omega, phi, kappa, YL, ZL and their SDs to the printed digits."""
    lines = (dewitt / "relor_sample.dat").read_text().split("\n")
    f = float(lines[0])
    rows = [ln.split() for ln in lines[1:] if ln.strip()]
    ids = [r[0] for r in rows]
    d = np.array([[float(v) for v in r[1:]] for r in rows])
    printed = {"omega": (2.4077, 0.0065), "phi": (0.5550, 0.0069), "kappa": (-0.2053, 0.0032),
               "YL": (-1.7187, 0.0209), "ZL": (148.3025, 0.0075)}
    for system in SYSTEMS:  # the left-image system is Dewitt's; the others give the same answer
        ro = RelativeOrientation.from_points(d[:, :2], d[:, 2:], focal_length_mm=f, system=system, ids=ids)
        wf = ro.western(bx=91.9825)
        got = {"omega": (math.degrees(wf.omega), math.degrees(wf.std_omega)),
               "phi": (math.degrees(wf.phi), math.degrees(wf.std_phi)),
               "kappa": (math.degrees(wf.kappa), math.degrees(wf.std_kappa)),
               "YL": (wf.by, wf.std_by), "ZL": (f + wf.bz, wf.std_bz)}
        for k, (v, s) in printed.items():
            assert round(got[k][0], 4) == pytest.approx(v, abs=1e-9), (system, k, got[k])
            assert round(got[k][1], 4) == pytest.approx(s, abs=1e-9), (system, k, got[k])
        assert round(ro.sigma0_mm, 4) == 0.0045
        assert 3 <= ro.iterations <= 6
        # Dewitt's y-residuals: yl - yr is our residual vertical parallax
        assert_allclose(np.abs(ro.parallax_mm), [0.0037, 0.0036, 0.0020, 0.0020, 0.0017, 0.0017], atol=1.1e-4)


# --------------------------------------------------------- synthetic truth
@pytest.mark.parametrize("kind", ["vertical", "kappa180", "convergent"])
@pytest.mark.parametrize("system", list(SYSTEMS))
def test_exact_data_and_systems_agree(kind, system):
    sp = simulate_pair(kind, n=60, rng=3)
    ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system=system)
    assert rot_angle_deg(ro.relative_rotation, sp.R_rel) < math.degrees(1e-9)
    assert vec_angle_deg(ro.base_left, sp.base_left) < math.degrees(1e-9)
    assert_allclose(wrap(ro.elements - sp.truth(system)), 0, atol=1e-9)
    assert np.abs(ro.parallax_mm).max() < 1e-9
    # the contract: R_left^T R_right, base in the model frame
    assert_allclose(ro.rotation_left @ ro.base_left, ro.base, atol=1e-12)
    for other in SYSTEMS:
        q = ro.to_system(other)
        R1, R2, b = SYSTEMS[other].geometry(q)
        assert rot_angle_deg(R1.T @ R2, ro.relative_rotation) < math.degrees(1e-9)
        assert vec_angle_deg(R1.T @ b, ro.base_left) < math.degrees(1e-9)
    if kind == "kappa180":
        assert ro.initial_method == "essential"  # zero angles cannot serve
        assert abs(abs(math.degrees(ro.western().kappa)) - 180) < 2


@pytest.mark.parametrize("kind", ["vertical", "kappa180", "convergent"])
def test_noisy_within_three_predicted_std_errors(kind):
    sp = simulate_pair(kind, n=150, noise_px=0.3, rng=21)
    for system in SYSTEMS:
        ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system=system,
                                             pixel_size_mm=PIX)
        z = wrap(ro.elements - sp.truth(system)) / ro.std_errors
        assert np.all(np.abs(z) < 3), (system, z)
        # sigma0 of one photo coordinate ~ 0.3 px
        assert ro.sigma0_mm / PIX == pytest.approx(0.3, rel=0.2)
        assert 2 <= ro.iterations <= 8
        assert not ro.outlier.any()


@pytest.mark.parametrize("kind", ["vertical", "kappa180", "convergent"])
@pytest.mark.parametrize("robust", ["huber", "tukey", "hampel", "andrews"])
def test_robust_not_pulled_by_outliers(kind, robust):
    sp = simulate_pair(kind, n=150, noise_px=0.3, outlier_fraction=0.2, rng=8)
    ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system="left-image",
                                         robust=robust, pixel_size_mm=PIX)
    z = wrap(ro.elements - sp.truth("left-image")) / ro.std_errors
    assert np.all(np.abs(z) < 3), z
    clean = RelativeOrientation.from_points(sp.left_mm[~sp.outlier], sp.right_mm[~sp.outlier],
                                            focal_length_mm=F_NGI, system="left-image")
    assert np.all(np.abs(wrap(ro.elements - clean.elements)) < clean.std_errors)
    # planted outliers that violate coplanarity by > 3 px are flagged; no clean point is
    true_q = np.abs(clean.residuals(sp.left_mm, sp.right_mm)) / PIX
    assert ro.outlier[sp.outlier & (true_q > 3)].all()
    assert ro.outlier[~sp.outlier].sum() <= 2
    assert ro.rms_parallax_mm() / PIX < 0.6
    # plain least squares on the same data is pulled far away
    ls = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system="left-image")
    assert np.max(np.abs(wrap(ls.elements - sp.truth("left-image"))) / ro.std_errors) > 5


@settings(max_examples=40, deadline=None)
@given(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(-3.1, 3.1), st.floats(-0.5, 0.5),
       st.floats(-0.3, 0.3), st.sampled_from(list(SYSTEMS)))
def test_conversion_round_trip(o, p, k, by, bz, system):
    """Any relative geometry converts into each system and back unchanged."""
    R_rel = matrix_from_angles(o, p, k)
    b = np.array([1.0, by, bz])
    if system == "dobrynin-pimshina" and max(abs(o), abs(p), abs(by), abs(bz)) > 0.3:
        # not every geometry has a frame with chi1 = omega2 = B'z = 0 (large y-base and y-tilt):
        # then a clear error, otherwise the round trip below
        try:
            q = SYSTEMS[system].elements_from_relative(R_rel, b)
        except EstimationError as err:
            assert "undefined for this pair" in str(err)
            return
    q = SYSTEMS[system].elements_from_relative(R_rel, b)
    R1, R2, bm = SYSTEMS[system].geometry(q)
    assert_allclose(R1.T @ R2, R_rel, atol=1e-10)
    assert_allclose(R1.T @ bm, b / np.linalg.norm(b), atol=1e-10)
    fixed_ok = {"basis": abs(bm[1]) + abs(bm[2]) < 1e-12, "left-image": np.allclose(R1, np.eye(3)),
                "dobrynin-pimshina": abs(bm[2]) < 1e-12}
    assert fixed_ok[system]


def test_essential_start_matches_truth():
    sp = simulate_pair("convergent", n=80, rng=4)
    R, b, inl = relative_from_essential(sp.left_mm, sp.right_mm, F_NGI)
    assert rot_angle_deg(R, sp.R_rel) < 1e-4
    assert vec_angle_deg(b, sp.base_left) < 1e-3
    assert inl.all()


# ----------------------------------------------------------------- real pair
EO = {
    "0182": [-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702],
    "0184": [-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883],
}


@pytest.fixture(scope="module")
def ngi_matches(ngi_pair):
    res = match_images(ngi_pair / "3324c_2015_1004_05_0182_RGB.tif", ngi_pair / "3324c_2015_1004_05_0184_RGB.tif",
                       config=MatcherConfig(verify="fundamental"))
    return res.matches


def test_ngi_pair_against_aerotriangulation(ngi_matches):
    cam = Camera(F_NGI, PIX, 640, 1152)
    R1 = matrix_from_angles(*np.radians(EO["0182"][3:]))
    R2 = matrix_from_angles(*np.radians(EO["0184"][3:]))
    R_rel = R1.T @ R2
    b = R1.T @ (np.array(EO["0184"][:3]) - EO["0182"][:3])
    assert len(ngi_matches) > 100
    for system in SYSTEMS:
        for robust in ("none", "tukey"):
            ro = RelativeOrientation.from_pixels(ngi_matches.left, ngi_matches.right, cam, system=system,
                                                 robust=robust, ids=ngi_matches.ids)
            assert rot_angle_deg(ro.relative_rotation, R_rel) < 0.1
            assert vec_angle_deg(ro.base_left, b) < 0.1
            assert ro.rms_parallax_mm() / PIX <= 0.35
            assert ro.iterations <= 6


# ------------------------------------------------------------ contract / IO
def test_to_dict_contract_and_json(tmp_path):
    sp = simulate_pair("vertical", n=40, noise_px=0.3, rng=2)
    ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system="dobrynin-pimshina",
                                         pixel_size_mm=PIX)
    d = ro.to_dict()
    for key in ("system", "elements", "std_errors", "correlation", "sigma0_mm", "iterations", "converged",
                "rotation_left", "rotation_right", "base", "focal_length_mm", "n_points", "n_used", "points"):
        assert key in d
    assert list(d["elements"]) == ["tau", "omega1", "alpha1", "alpha2", "chi2"]
    assert d["correlation"]["names"] == list(d["elements"])
    C = np.array(d["correlation"]["matrix"])
    assert_allclose(np.diag(C), 1.0)
    assert np.all(np.abs(C) <= 1 + 1e-12)
    assert set(d["points"][0]) >= {"id", "residual_mm", "weight", "outlier"}
    write_relative(tmp_path / "ro.json", ro)
    back = json.loads((tmp_path / "ro.json").read_text())
    assert back == json.loads(relative_json_text(ro))
    json.dumps(d, allow_nan=False)  # never NaN
    with pytest.raises(Exception, match="exists"):
        write_relative(tmp_path / "ro.json", ro)
    R = np.array(back["rotation_left"])
    assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    t = ro.residual_table()
    assert isinstance(t, ResidualTable) and t.units == "px" and t.n == 40
    assert_allclose(-t.residual[:, 0], ro.parallax_px)
    assert ro.residual_table(units="mm").units == "mm"


def test_inputs_not_modified_and_result_frozen():
    sp = simulate_pair("vertical", n=20, rng=1)
    lm, r = sp.left_mm.copy(), sp.right_mm.copy()
    ro = RelativeOrientation.from_points(lm, r, focal_length_mm=F_NGI)
    assert np.array_equal(lm, sp.left_mm) and np.array_equal(r, sp.right_mm)
    with pytest.raises(ValueError):
        ro.elements[0] = 1.0


def test_given_initial_values_dict_and_vector():
    sp = simulate_pair("kappa180", n=40, rng=6)
    tr = sp.truth("basis")
    ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system="basis",
                                         initial=dict(zip(SYSTEMS["basis"].names, tr + 0.05, strict=True)))
    assert ro.initial_method == "given"
    assert_allclose(wrap(ro.elements - tr), 0, atol=1e-9)
    ro2 = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, system="basis",
                                          initial="essential")
    assert_allclose(wrap(ro2.elements - tr), 0, atol=1e-9)


# ----------------------------------------------------------------- bad input
def test_bad_input_messages():
    sp = simulate_pair("vertical", n=20, rng=1)
    lm, r = sp.left_mm, sp.right_mm
    fr = RelativeOrientation.from_points
    with pytest.raises(EstimationError, match="too few tie points for relative orientation: 4 given"):
        fr(lm[:4], r[:4], focal_length_mm=F_NGI)
    with pytest.raises(ShapeError, match="same number of points"):
        fr(lm, r[:10], focal_length_mm=F_NGI)
    bad = lm.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InvalidInputError, match="non-finite"):
        fr(bad, r, focal_length_mm=F_NGI)
    with pytest.raises(InvalidInputError, match="unknown system 'foo'"):
        fr(lm, r, focal_length_mm=F_NGI, system="foo")
    with pytest.raises(InvalidInputError, match="unknown robust method 'l1'"):
        fr(lm, r, focal_length_mm=F_NGI, robust="l1")
    with pytest.raises(InvalidInputError, match="unknown initial 'random'"):
        fr(lm, r, focal_length_mm=F_NGI, initial="random")
    with pytest.raises(InvalidInputError, match="unknown element"):
        fr(lm, r, focal_length_mm=F_NGI, initial={"phi": 0.1})
    with pytest.raises(InvalidInputError, match="5 finite angles"):
        fr(lm, r, focal_length_mm=F_NGI, initial=[0, 0, 0])
    with pytest.raises(InvalidInputError, match="focal_length_mm"):
        fr(lm, r, focal_length_mm=-1.0)
    with pytest.raises(InvalidInputError, match="pixel_size_mm"):
        fr(lm, r, focal_length_mm=F_NGI, pixel_size_mm=0.0)
    with pytest.raises(InvalidInputError, match="ids"):
        fr(lm, r, focal_length_mm=F_NGI, ids=["a"])


def test_degenerate_no_parallax():
    """Identical images (zero base): the base direction is undetermined."""
    sp = simulate_pair("vertical", n=30, rng=1)
    with pytest.raises(EstimationError, match="degenerate configuration|undetermined|no parallax|behind"):
        RelativeOrientation.from_points(sp.left_mm, sp.left_mm, focal_length_mm=F_NGI, initial="zero")


def test_degenerate_collinear_points():
    x = np.linspace(-40, 40, 12)
    lm = np.column_stack([x, 0.5 * x])
    r = lm + [-30.0, 0.0]
    with pytest.raises(EstimationError, match="degenerate configuration"):
        RelativeOrientation.from_points(lm, r, focal_length_mm=F_NGI, initial="zero")


def test_divergence_reported():
    sp = simulate_pair("convergent", n=40, noise_px=0.3, rng=1)
    with pytest.raises(ConvergenceError, match="did not converge in 1 iterations"):
        RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI, initial="zero",
                                        options=RelativeOptions(max_iterations=1))


def test_weak_geometry_warning_and_exactly_five_points():
    sp = simulate_pair("vertical", n=40, noise_px=0.3, rng=1)
    with pytest.warns(WeakGeometryWarning, match="condition number"):
        RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=F_NGI,
                                        options=RelativeOptions(weak_condition=10.0))
    five = simulate_pair("vertical", n=5, rng=2)
    ro = RelativeOrientation.from_points(five.left_mm, five.right_mm, focal_length_mm=F_NGI)
    assert ro.sigma0_mm is None and ro.std_errors is None and ro.correlation is None
    assert rot_angle_deg(ro.relative_rotation, five.R_rel) < 1e-6
    json.dumps(ro.to_dict(), allow_nan=False)


def test_from_pixels_uses_camera():
    cam = Camera(F_NGI, PIX, 640, 1152, principal_point_mm=(0.1, -0.05))
    sp = simulate_pair("vertical", n=40, rng=9)
    lp, rp = cam.pixel_from_photo(sp.left_mm), cam.pixel_from_photo(sp.right_mm)
    ro = RelativeOrientation.from_pixels(lp, rp, cam)
    assert ro.pixel_size_mm == PIX
    assert rot_angle_deg(ro.relative_rotation, sp.R_rel) < 1e-7
