"""The adjustment frames (stereo.block.frames) and seed 004's curvature formulas (rectify.geometry.curvature)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stereo.block.frames as frames
from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.curvature import (
    EARTH_RADIUS_M,
    arc_minus_chord,
    ellipsoid_exact,
    gaussian_radius,
    height_drop,
    model_errors,
    printed_eq2,
    projection_height,
    projection_plan_correction,
    sphere_exact,
    unrolling_height,
)
from rectify.geometry.geodesy import ellipsoid_of, map_from_geodetic
from rectify.geometry.mapframe import true_north_azimuth
from stereo.block.frames import AdjustmentFrame, curvature_warning, default_frame_kind
from stereo.block.navigation import body_rotation
from stereo.formats.opensfm import topocentric_crs_wkt

UTM = "EPSG:32633"  # central meridian 15 E


def _block(lon=15.34, lat=48.0, half_km=14.0):
    """Map points of a block about (lon, lat): the centre and four points half_km away, heights 0-2000 m."""
    c = map_from_geodetic([[lon, lat, 0.0]], UTM)[0]
    d = half_km * 1000.0
    return c + np.array([[0, 0, 0], [d, 0, 500], [-d, 0, 1000], [0, d, 2000], [0, -d, 300.0]])


@pytest.mark.parametrize("kind", ["topocentric", "geocentric", "map"])
def test_round_trip_of_points_and_rotations(kind):
    pts = _block()
    fr = AdjustmentFrame.from_points(kind, UTM, pts)
    x = fr.frame_from_map(pts)
    assert np.abs(fr.map_from_frame(x) - pts).max() < 1e-6
    rng = np.random.default_rng(1)
    R = body_rotation(rng.uniform(0, 6.28, 5), rng.normal(0, 0.05, 5), rng.normal(0, 0.05, 5))
    for nav in (False, True):
        Rf = fr.rotations_in(R, pts, navigation=nav)
        assert np.allclose(Rf @ np.swapaxes(Rf, 1, 2), np.eye(3), atol=1e-12)
    Rg = fr.rotations_out(fr.rotations_in(R, pts), x)
    assert np.abs(Rg - R).max() < 1e-10


def test_topocentric_origin_and_axes():
    pts = _block()
    fr = AdjustmentFrame.from_points("topocentric", UTM, pts)
    o = fr.origin_lonlat_h
    assert o is not None and o[2] == 0.0
    on = map_from_geodetic([[o[0], o[1], 0.0], [o[0], o[1], 100.0]], UTM)
    x = fr.frame_from_map(on)
    assert np.abs(x[0]).max() < 1e-6  # the origin is on the ellipsoid
    assert np.allclose(x[1], [0, 0, 100.0], atol=1e-6)  # up is the normal at the origin


def test_distance_is_kept_and_the_level_surface_drops_as_seed_004_says():
    """A point on the ellipsoid s = 14 km north of the origin lies s^2 / 2R below the tangent plane."""
    fr = AdjustmentFrame("topocentric", UTM, np.array([15.3, 48.0, 0.0]))
    enu = ellipsoid_exact(15.3, 48.0, 0.0, 14_000.0, 0.0, crs=UTM)
    x = fr.frame_from_map(fr.map_from_frame(enu[None, :]))
    assert np.allclose(x, enu[None, :], atol=1e-6)
    R = gaussian_radius(48.0, ellipsoid_of(UTM))
    assert abs(-enu[2] - float(height_drop(14_000.0, R))) < 0.05 * 15.4  # within 5 % (the meridian radius is smaller)
    a, e2 = ellipsoid_of(UTM)
    M = a * (1 - e2) / (1 - e2 * math.sin(math.radians(48)) ** 2) ** 1.5
    assert abs(-enu[2] - 14_000.0 ** 2 / (2 * M)) < 1e-3  # along the meridian: the meridian radius M


def test_navigation_angles_get_the_meridian_convergence():
    """A camera levelled in the local ENU at a point 25 km east of the central meridian: in the map frame its
    kappa differs from the ENU one by the convergence (lon - lon0) sin(lat), to 1e-5 rad."""
    lon, lat = 15.3364, 48.0
    p = map_from_geodetic([[lon, lat, 3000.0]], UTM)
    fr = AdjustmentFrame.from_points("map", UTM, p)
    R = fr.rotations_in(np.eye(3)[None], p, navigation=True)[0]
    a = true_north_azimuth(UTM, lon, lat)
    assert abs(math.atan2(R[1, 0], R[0, 0]) + a) < 1e-9  # grid_from_enu = Rz(-a)
    assert abs(a + math.radians(lon - 15.0) * math.sin(math.radians(lat))) < 1e-5
    assert np.allclose(R[:, 2], [0, 0, 1], atol=1e-12)  # the map frame keeps the vertical


def test_topocentric_rotation_holds_the_vertical_deflection():
    """14 km east of the origin the local vertical leans s / R away from the frame's z axis (within 1 %)."""
    fr = AdjustmentFrame("topocentric", UTM, np.array([15.3, 48.0, 0.0]))
    enu = ellipsoid_exact(15.3, 48.0, math.pi / 2, 14_000.0, 3000.0, crs=UTM)
    p = fr.map_from_frame(enu[None, :])
    R = fr.rotations_in(np.eye(3)[None], p, navigation=True)[0]
    tilt = math.acos(R[2, 2])
    N = ellipsoid_of(UTM).a / math.sqrt(1 - ellipsoid_of(UTM).e2 * math.sin(math.radians(48)) ** 2)
    assert abs(tilt - 14_000.0 / N) < 0.01 * 14_000.0 / N
    assert (R @ [0, 0, 1])[0] > 0  # the camera's vertical leans east in the frame (away from the origin)


@settings(max_examples=25, deadline=None)
@given(st.floats(-20_000, 20_000), st.floats(-20_000, 20_000), st.floats(-100, 4000))
def test_round_trip_property(de, dn, h):
    pts = _block()
    fr = AdjustmentFrame.from_points("topocentric", UTM, pts)
    p = pts[:1] + np.array([[de, dn, h]])
    assert np.abs(fr.map_from_frame(fr.frame_from_map(p)) - p).max() < 1e-6


def test_frames_that_conflict_with_the_crs_are_refused():
    with pytest.raises(InvalidInputError, match="needs a CRS"):
        AdjustmentFrame.from_points("topocentric", None, np.zeros((1, 3)))
    with pytest.raises(InvalidInputError, match="needs a CRS"):
        AdjustmentFrame("geocentric", None)
    with pytest.raises(InvalidInputError, match="geographic CRS"):
        AdjustmentFrame.from_points("map", "EPSG:4979", np.array([[15.0, 48.0, 0.0]]))
    with pytest.raises(InvalidInputError, match="unknown adjustment frame"):
        AdjustmentFrame.from_points("utm", UTM, _block())
    assert default_frame_kind(None) == "map" and default_frame_kind(UTM) == "topocentric"


def test_geographic_crs_in_the_topocentric_frame():
    ll = np.array([[15.3, 48.0, 100.0], [15.5, 48.1, 500.0]])
    fr = AdjustmentFrame.from_points("topocentric", "EPSG:4979", ll)
    assert np.abs(fr.map_from_frame(fr.frame_from_map(ll)) - ll).max() < 1e-8


def test_curvature_warning_figure():
    c = map_from_geodetic([[15.3, 48.0, 0.0]], UTM)[0]
    pts = c + np.array([[-14_000, 0, 0], [14_000, 0, 0.0]])
    w = curvature_warning(pts, UTM)
    assert w is not None and "over 28.0 km" in w and "15.4 m" in w
    assert curvature_warning(c + np.array([[-500, 0, 0], [500, 0, 0.0]]), UTM) is None
    assert curvature_warning(pts, None) is None


# --------------------------------------------------------------------------- seed 004 formulas
def test_eq3_is_exact_on_the_sphere_and_eq2_corrected_closes_the_triangle():
    s = np.array([1e3, 2e4, 5e4, 1e5])
    h = np.array([0.0, 500.0, 2000.0, 2730.0])
    R = EARTH_RADIUS_M
    plan, height = sphere_exact(s, h, R)
    assert np.allclose(projection_height(s, h, R), height, atol=1e-9)
    # the plumb line meets the tangent plane at R tan(s/R); eq. 2 corrected adds the rest of the plan distance
    assert np.allclose(R * np.tan(s / R) + projection_plan_correction(s, h, R), plan, atol=1e-8)
    assert np.all(np.abs(printed_eq2(s, h, R) - h) < 0.01 * h + 1e-3)  # the printed bracket gives about h


def test_unrolling_eq1_differs_from_the_exact_sphere_by_h_theta2_over_2():
    s, h = 20_000.0, 2000.0
    t = s / EARTH_RADIUS_M
    _, exact = sphere_exact(s, h)
    assert abs(float(unrolling_height(s, h)) - (exact - h * (1 - math.cos(t)))) < 1e-9


def test_seed_claim_about_0_03_m_at_40_km():
    assert abs(float(arc_minus_chord(20_000.0)) - 0.0328) < 5e-4  # 40 km across: 20 km from the centre
    assert float(arc_minus_chord(40_000.0)) > 0.25  # a 40 km radius: eight times more
    dp, _ = model_errors("unrolling", 20_000.0, 2000.0)
    assert abs(float(dp)) > 6.0  # and 2 km above the level surface the plan error is h s / R


def test_bad_curvature_input():
    with pytest.raises(InvalidInputError):
        sphere_exact(1e3, 0.0, -1.0)
    with pytest.raises(InvalidInputError):
        height_drop(float("nan"))
    with pytest.raises(InvalidInputError):
        model_errors("flat", 1.0, 0.0)


def test_an_opensfm_topocentric_crs_is_adjusted_as_given():
    wkt = topocentric_crs_wkt((15.0, 48.0, 100.0))
    assert default_frame_kind(wkt) == "map"
    with pytest.raises(InvalidInputError, match="topocentric frame already"):
        AdjustmentFrame.from_points("topocentric", wkt, np.zeros((1, 3)))


def test_heights_above_a_geoid(monkeypatch):
    """A compound CRS's heights are converted with the geoid undulation N (h = H + N) and back."""
    crs = "EPSG:32633+3855"  # UTM 33N + EGM2008 height
    pts = _block()
    try:
        AdjustmentFrame.from_points("topocentric", crs, pts)
    except CRSError as err:  # without the grid (as here): refused by name, in one line
        assert "grid" in str(err) and "\n" not in str(err)
    monkeypatch.setattr(frames, "geoid_height", lambda v, ll: np.full(len(ll), 47.0))
    fr = AdjustmentFrame.from_points("topocentric", crs, pts)
    o = fr.origin_lonlat_h
    assert o is not None
    on = map_from_geodetic([[o[0], o[1], 0.0]], UTM)  # orthometric H = 0 at the origin: 47 m above the ellipsoid
    assert np.allclose(fr.frame_from_map(on), [[0.0, 0.0, 47.0]], atol=1e-6)
    assert np.abs(fr.map_from_frame(fr.frame_from_map(pts)) - pts).max() < 1e-6
    assert "heights above" in fr.description()
