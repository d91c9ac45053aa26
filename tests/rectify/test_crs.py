"""rectify.geometry.crs: parsing, the cached transformer door, errcheck."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from rectify.errors import CRSError, ShapeError
from rectify.geometry.crs import (
    crs_to_string,
    get_transformer,
    is_geographic,
    parse_crs,
    same_crs,
    transform_xy,
    transform_xyz,
    utm_crs,
)


def test_parse_and_string():
    assert crs_to_string("EPSG:32618") == "EPSG:32618"
    assert crs_to_string(parse_crs("EPSG:4326").to_wkt()) == "EPSG:4326"
    assert is_geographic("EPSG:4326") and not is_geographic("EPSG:32618")
    assert same_crs("EPSG:32618", parse_crs("EPSG:32618").to_wkt())


@pytest.mark.parametrize("bad", ["EPSG:99999999", "not a crs", "", "   "])
def test_unknown_crs(bad):
    with pytest.raises(CRSError, match="CRS"):
        parse_crs(bad)


def test_none_and_type():
    with pytest.raises(CRSError, match="missing"):
        parse_crs(None)
    with pytest.raises(CRSError, match="non-empty string"):
        parse_crs(4326)


def test_transformer_cached_and_xy_order():
    t1 = get_transformer("EPSG:4326", "EPSG:32618")
    t2 = get_transformer("EPSG:4326", "EPSG:32618")
    assert t1 is t2
    # lon, lat order: the central meridian of zone 18 (-75) maps to easting 500000
    out = transform_xy("EPSG:4326", "EPSG:32618", [[-75.0, 40.0]])
    assert_allclose(out[0, 0], 500000.0, atol=1e-6)
    assert 4.4e6 < out[0, 1] < 4.5e6


def test_round_trip_and_no_mutation():
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-78, -72, 20), rng.uniform(30, 50, 20)])
    keep = pts.copy()
    utm = transform_xy("EPSG:4326", "EPSG:32618", pts)
    back = transform_xy("EPSG:32618", "EPSG:4326", utm)
    assert_allclose(back, pts, atol=1e-9)
    assert np.array_equal(pts, keep)


def test_empty_and_shape():
    assert transform_xy("EPSG:4326", "EPSG:32618", np.zeros((0, 2))).shape == (0, 2)
    with pytest.raises(ShapeError):
        transform_xy("EPSG:4326", "EPSG:32618", np.zeros((3, 3)))


def test_errcheck_raises_on_impossible_point():
    with pytest.raises(CRSError, match="cannot transform|cannot be transformed"):
        transform_xy("EPSG:4326", "EPSG:32618", [[0.0, 95.0]])


def test_xyz_gk():
    # Gauss-Krueger zone 4 (Pulkovo 1942): false easting 4 500 000 at lon 21
    out = transform_xyz("EPSG:4284", "EPSG:28404", [[21.0, 50.0, 100.0]])
    assert_allclose(out[0, 0], 4500000.0, atol=1e-3)
    assert_allclose(out[0, 2], 100.0)


def test_unit_label():
    from rectify.geometry.crs import unit_label

    assert unit_label("EPSG:32618") == "m"
    assert unit_label("EPSG:4326") == "degree"
    assert "foot" in unit_label("EPSG:2263")
    assert unit_label(None) == "map units"
    assert unit_label("not a crs", default="ground units") == "ground units"


@pytest.mark.parametrize("lon, lat, code", [(15.0, 45.13, "EPSG:32633"), (-0.1, -1.0, "EPSG:32730"),
                                            (-180.0, 10.0, "EPSG:32601"), (180.0, 10.0, "EPSG:32601"),
                                            (25.0, -33.9, "EPSG:32735"), (-77.03, 38.9, "EPSG:32618")])
def test_utm_crs_known_zones(lon, lat, code):
    assert utm_crs(lon, lat) == code
