"""The fast paths of the orthophoto engine against the straightforward ones (issue 27, speed).

- :func:`rectify.raster.visibility.line_of_sight` (skipping the steps its height and slope bounds clear,
  on the box the lines reach, in batches of lines) gives the reference line-of-sight march's visibility
  cell for cell, on DEM blocks with walls, holes, hills, side margins and any direction; the true
  orthophoto written with either is byte-identical, and so is the one with the tiles' side margins and
  the one with the grid's margin on every side.
- :meth:`rectify.raster.dem.Dem.heights_on_lattice` (separable sampling) equals the point-by-point
  :meth:`Dem.heights_at_dem_pixels` bit for bit, outside cells included; a window with nodata falls back.
- A small one-band DEM's windows cut from its cached overview equal the reads of the file.
- The interpolated projection of a tile (matrix form) stays within ``PROJECTION_TOLERANCE_PX`` of the
  exact projection of every pixel.
- ``--dem-height H`` (:meth:`Dem.constant_height`) writes the same orthophoto as a flat DEM file of height H.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

import rectify.raster.ortho as ortho_mod
import rectify.raster.visibility as vis_mod
from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.sensors import FrameModel
from rectify.raster.dem import Dem
from rectify.raster.engine import tile_windows
from rectify.raster.ortho import PROJECTION_TOLERANCE_PX, OrthoOptions, ortho_grid, orthorectify
from rectify.raster.visibility import line_of_sight, line_of_sight_reference

CRS = "EPSG:32632"
E0, N0 = 500_000.0, 5_000_000.0


def _buildings(X, Y):
    z = 100 + 20 * np.sin((X - E0) / 50.0) * np.cos((Y - N0) / 40.0)
    for cx, cy, half, hgt in ((-40, 30, 12, 35), (50, -20, 10, 50), (0, -60, 15, 25)):
        z = np.where((np.abs(X - E0 - cx) < half) & (np.abs(Y - N0 - cy) < half), z + hgt, z)
    return z


def _write_dem(path: Path, fn, *, res: float = 2.0, size: float = 400.0, hole: bool = False) -> None:
    n = int(size / res)
    x = E0 - size / 2 + res * (np.arange(n) + 0.5)
    y = N0 + size / 2 - res * (np.arange(n) + 0.5)
    X, Y = np.meshgrid(x, y)
    z = fn(X, Y).astype("float32")
    if hole:
        z[40:50, 60:75] = -9999
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=CRS,
                       nodata=-9999 if hole else None,
                       transform=Affine(res, 0, E0 - size / 2, 0, -res, N0 + size / 2)) as ds:
        ds.write(z, 1)


def _write_image(path: Path, w: int, h: int) -> None:
    rr, cc = np.mgrid[0:h, 0:w]
    img = np.stack([100 + 60 * np.sin(cc / 3.1) * np.cos(rr / 4.3), 90 + 50 * np.sin((cc + rr) / 7.7),
                    128 + 0 * cc]).astype(np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8") as ds:
        ds.write(img)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("speed")
    _write_dem(d / "dem.tif", _buildings)
    _write_image(d / "img.tif", 160, 120)
    cam = Camera(focal_length_mm=8.0, pixel_size_mm=0.02, width=160, height=120)
    # oblique enough that the buildings hide ground
    model = FrameModel(cam, [E0 + 60, N0 - 40, 420.0], matrix_from_angles(0.12, -0.10, 0.3), CRS)
    return d, model


# ------------------------------------------------------------------------------------------- visibility
def _block(rng: np.random.Generator, n: int, walls: int, holes: bool) -> np.ndarray:
    yy, xx = np.mgrid[0:n, 0:n]
    Z = 50 + 5 * np.sin(xx / 7.0) * np.cos(yy / 5.0) + rng.normal(0, 0.3, (n, n))
    for _ in range(walls):
        r, c = rng.integers(0, n - 6, 2)
        Z[r:r + rng.integers(2, 8), c:c + rng.integers(2, 8)] += rng.uniform(5, 40)
    if holes:
        r, c = rng.integers(0, n - 4, 2)
        Z[r:r + 3, c:c + 3] = np.nan
    return Z


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), block=st.sampled_from([1, 2, 4, 8]), levels=st.integers(1, 3),
       chunk=st.sampled_from([1, 3, 8]), walls=st.integers(0, 12), holes=st.booleans())
def test_line_of_sight_equals_reference(seed, block, levels, chunk, walls, holes):
    rng = np.random.default_rng(seed)
    m, h, w = 20, 24, 28
    Z = _block(rng, 2 * m + max(h, w), walls, holes)[:h + 2 * m, :w + 2 * m]
    z = Z[m:m + h, m:m + w]
    ang = rng.uniform(0, 2 * np.pi)
    mag = rng.uniform(0.05, 2.0, (h, w))  # px per metre, varying over the tile
    d = np.dstack([mag * np.cos(ang), mag * np.sin(ang)])
    inside = rng.random((h, w)) > 0.1
    ref = line_of_sight_reference(Z, m, d, z, inside)
    fast = line_of_sight(Z, m, d, z, inside, block=block, levels=levels, chunk=chunk)
    np.testing.assert_array_equal(fast, ref)


def test_line_of_sight_equals_reference_many_seeds():
    """Deterministic sweep (the smallest blocks skip most often: a skip bound missing the cell corners
    beyond the block neighbourhood failed about one case in 50 here)."""
    for seed in range(80):
        rng = np.random.default_rng(seed)
        m, h, w = 20, 24, 28
        Z = _block(rng, 2 * m + max(h, w), seed % 13, seed % 2 == 1)[:h + 2 * m, :w + 2 * m]
        z = Z[m:m + h, m:m + w]
        ang = rng.uniform(0, 2 * np.pi)
        mag = rng.uniform(0.05, 2.0, (h, w))
        d = np.dstack([mag * np.cos(ang), mag * np.sin(ang)])
        inside = rng.random((h, w)) > 0.1
        ref = line_of_sight_reference(Z, m, d, z, inside)
        for block, levels in ((1, 1), (1, 3)):
            np.testing.assert_array_equal(line_of_sight(Z, m, d, z, inside, block=block, levels=levels), ref,
                                          err_msg=f"seed {seed}, block {block}, levels {levels}")


def test_line_of_sight_finds_the_occlusion_behind_a_wall():
    m, n = 10, 30
    Z = np.full((n + 2 * m, n + 2 * m), 10.0)
    Z[:, m + 15:m + 17] = 60.0  # a wall, 50 m high, two cells thick
    z = Z[m:m + n, m:m + n]
    d = np.zeros((n, n, 2))
    d[..., 0] = 0.5  # the sensor is towards +x (column), 0.5 px per metre
    vis = line_of_sight(Z, m, d, z, np.ones((n, n), bool))
    np.testing.assert_array_equal(vis, line_of_sight_reference(Z, m, d, z, np.ones((n, n), bool)))
    # cells just in front of the wall (towards -x) are hidden; the wall's top and the far side are seen
    assert not vis[:, 10:15].any() and vis[:, 15:17].all() and vis[:, 17:].all()


@pytest.mark.parametrize("seed", range(6))
def test_line_of_sight_equals_reference_on_smooth_terrain_and_steep_lines(seed):
    """The regime of an aerial frame over hills (the NGI pair): lines rising faster than the terrain, which
    the march skips from their first sample and by their height above the terrain (slope bounds along x
    and y); a few walls, a hole and lines along the axes (|ux| or |uy| = 0) keep every branch honest."""
    rng = np.random.default_rng(100 + seed)
    m, h, w = 48, 40, 36
    n = 2 * m + max(h, w)
    yy, xx = np.mgrid[0:n, 0:n]
    Z = 300 + 40 * np.sin(xx / 23.0 + seed) * np.cos(yy / 17.0) + 0.02 * xx * yy + rng.normal(0, 0.2, (n, n))
    for _ in range(seed):
        r, c = rng.integers(m - 10, m + 30, 2)
        Z[r:r + 3, c:c + 4] += rng.uniform(20, 120)
    if seed % 2:
        Z[m + 5:m + 8, m + 20:m + 23] = np.nan
    Z = Z[:h + 2 * m, :w + 2 * m]
    z = Z[m:m + h, m:m + w]
    ang = [0.0, np.pi / 2, np.pi, rng.uniform(0, 2 * np.pi)][seed % 4]
    mag = rng.uniform(0.02, 0.3, (h, w))  # 3..50 m of rise a pixel: steeper than the hills, not the walls
    d = np.dstack([mag * np.cos(ang), mag * np.sin(ang)])
    inside = rng.random((h, w)) > 0.05
    ref = line_of_sight_reference(Z, m, d, z, inside)
    for block, levels, chunk in ((1, 3, 1), (1, 4, 1), (2, 3, 3)):
        np.testing.assert_array_equal(line_of_sight(Z, m, d, z, inside, block=block, levels=levels, chunk=chunk),
                                      ref, err_msg=f"seed {seed}, block {block}, levels {levels}, chunk {chunk}")


def test_true_ortho_file_identical_with_the_reference_march(scene, tmp_path, monkeypatch):
    d, model = scene
    dem = Dem.from_path(d / "dem.tif")
    opts = OrthoOptions(true_ortho=True, threads=1, tile_px=64)
    fast = orthorectify(d / "img.tif", tmp_path / "fast.tif", model, dem, resolution=1.0, options=opts)
    monkeypatch.setattr(ortho_mod, "line_of_sight", line_of_sight_reference)
    ref = orthorectify(d / "img.tif", tmp_path / "ref.tif", model, dem, resolution=1.0, options=opts)
    assert fast.n_occluded == ref.n_occluded > 100  # the scene hides ground
    with rasterio.open(tmp_path / "fast.tif") as a, rasterio.open(tmp_path / "ref.tif") as b:
        np.testing.assert_array_equal(a.read(), b.read())


def test_true_ortho_tile_margins_give_the_file_of_the_full_margin(scene, tmp_path, monkeypatch):
    """Each tile's line-of-sight block reaches only as far on each side as its ground points move towards the
    sensor over the DEM's height range (x 1.5 + 4): the same file as with the grid's margin on every side."""
    d, model = scene
    dem = Dem.from_path(d / "dem.tif")
    opts = OrthoOptions(true_ortho=True, threads=1, tile_px=64)
    seen = []
    margins = ortho_mod._Engine._margins

    def spy(self, c0, r0, w, h):
        seen.append((self.margin, margins(self, c0, r0, w, h)))
        return seen[-1][1]
    monkeypatch.setattr(ortho_mod._Engine, "_margins", spy)
    tight = orthorectify(d / "img.tif", tmp_path / "tight.tif", model, dem, resolution=1.0, options=opts)
    assert seen and all(max(s) <= m for m, s in seen) and any(min(s) < m for m, s in seen)  # tighter somewhere
    monkeypatch.setattr(ortho_mod._Engine, "_margins", lambda self, *a: (self.margin,) * 4)
    full = orthorectify(d / "img.tif", tmp_path / "full.tif", model, dem, resolution=1.0, options=opts)
    assert tight.n_occluded == full.n_occluded > 100
    with rasterio.open(tmp_path / "tight.tif") as a, rasterio.open(tmp_path / "full.tif") as b:
        np.testing.assert_array_equal(a.read(), b.read())


def test_line_of_sight_in_small_batches_equals_reference(monkeypatch):
    """Lines marched in batches (a batch of 37 here, many per block, the last one short): the same cells."""
    monkeypatch.setattr(vis_mod, "RAYS_PER_BATCH", 37)
    for seed in range(4):
        rng = np.random.default_rng(200 + seed)
        m, h, w = 20, 24, 28
        Z = _block(rng, 2 * m + max(h, w), 10, seed % 2 == 1)[:h + 2 * m, :w + 2 * m]
        z = Z[m:m + h, m:m + w]
        ang = rng.uniform(0, 2 * np.pi)
        d = np.dstack([np.full((h, w), np.cos(ang)), np.full((h, w), np.sin(ang))]) * rng.uniform(0.05, 2.0, (h, w, 1))
        inside = rng.random((h, w)) > 0.1
        ref = line_of_sight_reference(Z, m, d, z, inside)
        assert (~ref).sum() > 0
        np.testing.assert_array_equal(line_of_sight(Z, m, d, z, inside, chunk=1 + seed % 3), ref)


def test_line_of_sight_with_side_margins_equals_reference():
    """A block with its own margin on each side (the tile at (mx, my)), as the engine makes them."""
    rng = np.random.default_rng(7)
    h, w, (mx, my), (rx, ry) = 24, 28, (5, 31), (26, 3)
    Z = _block(rng, max(h + my + ry, w + mx + rx), 9, True)[:h + my + ry, :w + mx + rx]
    z = Z[my:my + h, mx:mx + w]
    mag = rng.uniform(0.05, 2.0, (h, w))
    hidden = 0
    for ang in (0.4, 2.0, 3.5, 5.5):
        dd = np.dstack([mag * np.cos(ang), mag * np.sin(ang)])
        inside = rng.random((h, w)) > 0.1
        ref = line_of_sight_reference(Z, (mx, my), dd, z, inside)
        np.testing.assert_array_equal(line_of_sight(Z, (mx, my), dd, z, inside), ref)
        hidden += int((~ref).sum())
    assert hidden > 20  # the walls hide ground: not an empty case


# ------------------------------------------------------------------------------------------- DEM sampling
@pytest.mark.parametrize("hole", [False, True])
def test_heights_on_lattice_bit_identical(tmp_path, hole):
    _write_dem(tmp_path / "dem.tif", _buildings, res=3.0, hole=hole)
    dem = Dem.from_path(tmp_path / "dem.tif")
    rng = np.random.default_rng(1)
    # columns and rows reaching outside the DEM on both sides (NaN there), exact last row/column included
    x = np.sort(np.concatenate([rng.uniform(-3, dem.width + 2, 70), [0.0, dem.width - 1.0]]))
    y = np.sort(np.concatenate([rng.uniform(-3, dem.height + 2, 50), [0.0, dem.height - 1.0]]))
    lat = dem.heights_on_lattice(x, y)
    pts = dem.heights_at_dem_pixels(*np.meshgrid(x, y))
    if hole:
        assert lat is None  # the window holds nodata: the caller samples point by point
        return
    assert lat is not None
    np.testing.assert_array_equal(lat, pts)  # NaN at the same places, the same bits elsewhere
    assert np.isnan(lat).any() and np.isfinite(lat).any()


@pytest.mark.parametrize("hole", [False, True])
def test_small_dem_windows_cut_from_its_overview_equal_the_file_reads(tmp_path, hole):
    """A one-band DEM of at most 512 px a side is read once (its overview, for the height range); the
    tiles' windows cut from it hold the values and the mask of a read of the file, bit for bit."""
    _write_dem(tmp_path / "dem.tif", _buildings, res=3.0, hole=hole)
    dem = Dem.from_path(tmp_path / "dem.tif")
    assert dem.count == 1 and max(dem.width, dem.height) <= 512
    direct = dataclasses.replace(dem, count=None)  # count unknown: the file is read
    rng = np.random.default_rng(3)
    for _ in range(40):
        c0, r0 = (int(v) for v in rng.integers(0, [dem.width - 1, dem.height - 1]))
        c1, r1 = int(rng.integers(c0 + 1, dem.width + 1)), int(rng.integers(r0 + 1, dem.height + 1))
        a, va = dem._read_window(c0, r0, c1, r1)
        b, vb = direct._read_window(c0, r0, c1, r1)
        assert a.dtype == b.dtype == np.float64
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(va, vb)
    assert (~dem._read_window(0, 0, dem.width, dem.height)[1]).any() == hole


def test_projection_matrix_form_within_tolerance(scene):
    d, model = scene
    dem = Dem.from_path(d / "dem.tif")
    grid = ortho_grid(model, dem, resolution=0.7)
    eng = ortho_mod._Engine(str(d / "img.tif"), model, dem, grid, OrthoOptions(), np.dtype("uint8"), 3, 0.0, 0,
                            120.0)
    worst = 0.0
    for c0, r0, w, h in tile_windows(grid.width, grid.height, 256):
        z = eng._heights(c0, r0, w, h)
        col, row = eng._project(c0, r0, w, h, z)
        mx, my = eng._model_xy(c0, r0, w, h)
        ex = model.project(np.column_stack([mx.ravel(), my.ravel(), z.ravel()]))
        fin = np.isfinite(ex).all(axis=1)
        got = np.column_stack([col.ravel(), row.ravel()])
        np.testing.assert_array_equal(np.isfinite(got).all(axis=1), fin)
        worst = max(worst, float(np.abs(got[fin] - ex[fin]).max()))
    assert worst <= PROJECTION_TOLERANCE_PX


# ------------------------------------------------------------------------------------------- constant height
def test_constant_height_equals_a_flat_dem_file(scene, tmp_path):
    d, model = scene
    _write_dem(tmp_path / "flat.tif", lambda X, Y: np.full(X.shape, 112.5), size=800.0)
    opts = OrthoOptions(threads=1, tile_px=64)
    a = orthorectify(d / "img.tif", tmp_path / "flat_o.tif", model, Dem.from_path(tmp_path / "flat.tif"),
                     resolution=1.0, options=opts)
    b = orthorectify(d / "img.tif", tmp_path / "const_o.tif", model, Dem.constant_height(112.5, CRS),
                     resolution=1.0, options=opts)
    assert (a.grid.width, a.grid.height, tuple(a.grid.transform)) == (b.grid.width, b.grid.height,
                                                                       tuple(b.grid.transform))
    with rasterio.open(tmp_path / "flat_o.tif") as x, rasterio.open(tmp_path / "const_o.tif") as y:
        np.testing.assert_array_equal(x.read(), y.read())
        assert y.tags()["ORTHO_DEM"] == "constant height 112.5 m"
    assert b.dem_range == (112.5, 112.5)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "100", True])
def test_constant_height_refuses_non_finite(bad):
    with pytest.raises(InvalidInputError, match="--dem-height must be a finite number"):
        Dem.constant_height(bad, CRS)
