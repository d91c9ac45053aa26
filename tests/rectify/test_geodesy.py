"""rectify.geometry.geodesy: geodetic <-> geocentric <-> ENU through pyproj; seed 001 / 004 formulas."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import CRSError, InvalidInputError, ShapeError
from rectify.geometry.geodesy import (
    Ellipsoid,
    blh_from_geocentric_formula,
    ecef_from_enu,
    ecef_from_geodetic,
    ecef_from_map,
    ellipsoid_of,
    enu_from_body,
    enu_from_ecef,
    enu_from_map,
    enu_rotation,
    geocentric_from_blh_formula,
    geodetic_from_ecef,
    geodetic_from_map,
    map_from_enu,
    map_from_geodetic,
    navigation_matrix,
    neu_from_enu,
)

WGS84 = Ellipsoid(6378137.0, 6.69437999014e-3)
KRASS = ellipsoid_of("EPSG:28404")  # Krassowsky 1940 (Pulkovo 1942, Gauss-Krueger)


def test_ellipsoids():
    e = ellipsoid_of("EPSG:32618")
    assert_allclose(e.a, 6378137.0)
    assert_allclose(e.e2, 6.69437999014e-3, rtol=1e-10)
    assert_allclose(KRASS.a, 6378245.0)
    assert_allclose(KRASS.e2, 6.693421622966e-3, rtol=1e-9)


def test_ecef_known_answers():
    out = ecef_from_geodetic([[0, 0, 0], [90, 0, 0], [0, 90, 0], [0, 0, 100]])
    b = 6378137.0 * math.sqrt(1 - WGS84.e2)
    assert_allclose(out, [[6378137, 0, 0], [0, 6378137, 0], [0, 0, b], [6378237, 0, 0]], atol=1e-6)


def test_geodetic_ecef_round_trip_other_datum():
    rng = np.random.default_rng(4)
    llh = np.column_stack([rng.uniform(-180, 180, 50), rng.uniform(-89, 89, 50), rng.uniform(-500, 9000, 50)])
    for crs in ("EPSG:4326", "EPSG:28404"):
        xyz = ecef_from_geodetic(llh, crs=crs)
        assert_allclose(geodetic_from_ecef(xyz, crs=crs), llh, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.floats(-180, 180), st.floats(-89.9, 89.9), st.floats(-1000, 1e6))
def test_seed001_formulas_match_pyproj(lon, lat, h):
    """Seed 001 step 5, both directions, against pyproj on Krassowsky."""
    xyz_proj = ecef_from_geodetic([[lon, lat, h]], crs="EPSG:28404")
    blh = np.array([[math.radians(lat), math.radians(lon), h]])
    xyz_formula = geocentric_from_blh_formula(blh, KRASS)
    assert_allclose(xyz_formula, xyz_proj, atol=1e-6)
    back = blh_from_geocentric_formula(xyz_proj, KRASS)
    assert_allclose(back[0, 0], blh[0, 0], atol=1e-11)
    dl = (back[0, 1] - blh[0, 1] + math.pi) % (2 * math.pi) - math.pi
    assert abs(dl) < 1e-11
    assert_allclose(back[0, 2], h, atol=1e-5)


def test_seed001_lon0_and_centre():
    blh = np.array([[0.7, 0.5, 200.0]])
    xyz = geocentric_from_blh_formula(blh, WGS84, lon0_rad=0.4)
    assert_allclose(blh_from_geocentric_formula(xyz, WGS84, lon0_rad=0.4), blh, atol=1e-9)
    with pytest.raises(InvalidInputError, match="centre of the Earth"):
        blh_from_geocentric_formula([[0, 0, 0]], WGS84)


def test_enu_known_answers():
    # at (0, 0, 0): east = +Y_ecef, north = +Z_ecef, up = +X_ecef
    o = (0.0, 0.0, 0.0)
    pts = [[6378137.0, 10.0, 0.0], [6378137.0, 0.0, 20.0], [6378147.0, 0.0, 0.0]]
    assert_allclose(enu_from_ecef(pts, o), [[10, 0, 0], [0, 20, 0], [0, 0, 10]], atol=1e-8)
    R = enu_rotation(37.0, -21.0)
    assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert_allclose(np.linalg.det(R), 1.0)
    assert_allclose(neu_from_enu([[1, 2, 3]]), [[2, 1, 3]])


def test_enu_round_trip_and_up_is_height():
    o = (-75.5, 38.0, 50.0)
    rng = np.random.default_rng(7)
    enu = rng.uniform(-5000, 5000, (30, 3))
    xyz = ecef_from_enu(enu, o)
    assert_allclose(enu_from_ecef(xyz, o), enu, atol=1e-7)
    # a point straight above the origin
    above = ecef_from_geodetic([[o[0], o[1], o[2] + 123.0]])
    assert_allclose(enu_from_ecef(above, o), [[0, 0, 123.0]], atol=1e-7)


def test_map_chain_utm_and_gk():
    o = (-75.0, 40.0, 0.0)
    xyh = np.array([[500000.0, 4427757.0, 0.0], [510000.0, 4437757.0, 250.0]])
    llh = geodetic_from_map(xyh, "EPSG:32618")
    assert_allclose(llh[0, 0], -75.0, atol=1e-9)
    assert_allclose(map_from_geodetic(llh, "EPSG:32618"), xyh, atol=1e-6)
    enu = enu_from_map(xyh, "EPSG:32618", o)
    assert_allclose(map_from_enu(enu, "EPSG:32618", o), xyh, atol=1e-6)
    # distances are preserved by the rigid map ECEF -> ENU
    e = ecef_from_map(xyh, "EPSG:32618")
    assert_allclose(np.linalg.norm(enu[1] - enu[0]), np.linalg.norm(e[1] - e[0]), rtol=1e-12)
    gk = np.array([[4500000.0, 5540000.0, 10.0]])
    assert_allclose(map_from_enu(enu_from_map(gk, "EPSG:28404", (21, 50, 0)), "EPSG:28404", (21, 50, 0)),
                    gk, atol=1e-6)


def test_bad_inputs():
    with pytest.raises(ShapeError):
        ecef_from_geodetic([[1.0, 2.0]])
    with pytest.raises(InvalidInputError, match="origin"):
        enu_from_ecef([[1.0, 2.0, 3.0]], (1.0, 2.0))
    with pytest.raises(InvalidInputError, match="latitude"):
        enu_from_ecef([[1.0, 2.0, 3.0]], (1.0, 95.0, 0.0))
    with pytest.raises(CRSError):
        geodetic_from_map([[0.0, 0.0, 0.0]], "EPSG:99999999")
    with pytest.raises(CRSError, match="geocentric"):
        geodetic_from_map([[0.0, 0.0, 0.0]], "EPSG:4978")


def test_navigation_identity_and_heading():
    assert_allclose(navigation_matrix(0, 0, 0), np.eye(3), atol=1e-15)
    # heading 90 deg: forward points east (seed frame: X north, Y east, Z up)
    A = navigation_matrix(math.pi / 2, 0, 0)
    assert_allclose(A[:, 0], [0, 1, 0], atol=1e-15)
    assert_allclose(A[:, 1], [-1, 0, 0], atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-1.2, 1.2), st.floats(-0.3, 0.3))
def test_navigation_is_rotation_with_stated_elevations(h, d, r):
    A = navigation_matrix(h, d, r)
    assert_allclose(A.T @ A, np.eye(3), atol=1e-12)
    assert_allclose(np.linalg.det(A), 1.0, atol=1e-12)
    # pitch and roll are the elevations of X' and Y' above the horizon
    assert_allclose(math.asin(A[2, 0]), d, atol=1e-12)
    assert_allclose(math.asin(A[2, 1]), r, atol=1e-12)
    # heading is the azimuth of X' from north towards east
    if math.cos(d) > 1e-6:
        dh = (math.atan2(A[1, 0], A[0, 0]) - h + math.pi) % (2 * math.pi) - math.pi
        assert abs(dh) < 1e-9
    R = enu_from_body(h, d, r)
    assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # forward (body y) in ENU has the same elevation; right (body x) has the roll elevation
    assert_allclose(R[2, 1], math.sin(d), atol=1e-12)
    assert_allclose(R[2, 0], math.sin(r), atol=1e-12)


def test_navigation_small_angles_match_rotation_product():
    """For small pitch and roll, A ~ Rz(heading) Ry(-pitch) Rx(roll) in the seed frame."""
    h, d, r = 0.3, 0.002, -0.001
    A = navigation_matrix(h, d, r)
    assert_allclose(A[:, 0], [math.cos(h), math.sin(h), d], atol=1e-5)


def test_navigation_bad():
    with pytest.raises(InvalidInputError, match="finite"):
        navigation_matrix(float("nan"), 0, 0)
    with pytest.raises(InvalidInputError, match="no orthogonal"):
        navigation_matrix(0, 1.2, 1.2)
