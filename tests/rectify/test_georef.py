"""rectify.raster.georef: the half-pixel shift, grids, resolution as GDAL suggests."""

import numpy as np
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import InvalidInputError, ShapeError
from rectify.raster.georef import (
    Grid,
    boundary_pixels,
    output_grid,
    pixel_from_world,
    suggest_resolution,
    world_from_pixel,
    world_from_pixel_matrix,
)

T = Affine(300.0, 0.0, 101985.0, 0.0, -300.0, 2826915.0)


def test_half_pixel_shift_matches_rasterio_xy():
    import rasterio.transform

    rows, cols = np.array([0, 5, 717]), np.array([0, 3, 790])
    xs, ys = rasterio.transform.xy(T, rows, cols, offset="center")
    assert_allclose(world_from_pixel(T, np.column_stack([cols, rows])), np.column_stack([xs, ys]))
    # the corner of the top-left pixel is (-0.5, -0.5)
    assert_allclose(world_from_pixel(T, [[-0.5, -0.5]]), [[T.c, T.f]])


@settings(max_examples=50, deadline=None)
@given(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(0.1, 100), st.floats(-0.5, 0.5))
def test_round_trip_rotated(x, y, res, rot):
    t = Affine(res * np.cos(rot), -res * np.sin(rot), 5e5, -res * np.sin(rot), -res * np.cos(rot), 4e6)
    p = np.array([[x, y]])
    assert_allclose(pixel_from_world(t, world_from_pixel(t, p)), p, atol=1e-6)
    m = world_from_pixel_matrix(t)
    assert_allclose((m @ [x, y, 1])[:2], world_from_pixel(t, p)[0])


def test_bad_inputs():
    with pytest.raises(ShapeError):
        world_from_pixel(T, np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match="singular"):
        pixel_from_world(Affine(0, 0, 0, 0, 0, 0), [[1.0, 2.0]])
    with pytest.raises(InvalidInputError, match="positive"):
        Grid(0, 10, T)
    with pytest.raises(InvalidInputError, match="resolution"):
        output_grid(lambda p: p, 10, 10, resolution=-1.0)
    with pytest.raises(InvalidInputError, match="finite"):
        output_grid(lambda p: p * np.nan, 10, 10)
    with pytest.raises(InvalidInputError, match="too large"):
        output_grid(lambda p: p * 1e9, 10, 10, resolution=1.0)


def test_output_grid_identity_like_and_alignment():
    # source pixel -> world: 10 m pixels, north-up, origin at (1000, 5000) corner
    t = Affine(10.0, 0, 1000.0, 0, -10.0, 5000.0)
    g = output_grid(lambda p: world_from_pixel(t, p), 40, 30, crs="EPSG:32618")
    assert (g.width, g.height) == (40, 30)
    assert g.resolution == (10.0, 10.0)
    assert g.transform == t
    assert g.bounds == (1000.0, 4700.0, 1400.0, 5000.0)
    g2 = output_grid(lambda p: world_from_pixel(t, p), 40, 30, resolution=7.0)
    left, bottom, right, top = g2.bounds
    for v in (left, bottom, right, top):
        assert abs(v / 7.0 - round(v / 7.0)) < 1e-9
    assert left <= 1000 and right >= 1400 and bottom <= 4700 and top >= 5000


def test_suggest_resolution_rotation_invariant():
    a = 0.3
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) * 2.5

    def f(p):
        return np.asarray(p) @ R.T

    # a rotated square-pixel grid keeps its pixel size along the diagonal
    assert_allclose(suggest_resolution(f, 100, 100), 2.5, rtol=1e-12)
    g = output_grid(f, 100, 100)
    assert g.resolution[0] == pytest.approx(2.5)


def test_boundary_and_pixel_frame_grid():
    b = boundary_pixels(10, 5, 3)
    assert b.shape == (12, 2)
    assert b[:, 0].min() == -0.5 and b[:, 0].max() == 9.5 and b[:, 1].max() == 4.5
    g = output_grid(lambda p: np.asarray(p) + 3.0, 10, 5, resolution=1.0, y_up=False)
    assert g.transform.e > 0
    assert_allclose(world_from_pixel(g.transform, [[0, 0]]), [[3.0, 3.0]])
