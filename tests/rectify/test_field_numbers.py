"""The numbers users rely on, computed independently (issue 32): the half-pixel origin of every raster
rectify writes (warp, ortho, mosaic), the tile-size independence of every tiled step, and the residual
sign of the GCP fit.

Half-pixel origins: the inputs carry their own truth (bands holding the source pixel position, or the
world coordinates, of each pixel centre, linear functions that bilinear and cubic interpolation reproduce
exactly), and the output's geotransform is recomputed from the inputs by the grid rule the docs state
(footprint of the outer pixel edges, edges on whole multiples of the resolution). rasterio, numpy and
pyproj compute the expected values, not the code under test. Tile-size independence: the same product with
tiles of 16, 48 and 512 px must be the same raster.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyproj
import pytest
import rasterio
import rasterio.transform
from affine import Affine

from rectify.geometry.camera import Camera
from rectify.geometry.points import GcpTable
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.sensors import FrameModel
from rectify.geometry.transforms.gcp import fit_gcps
from rectify.geometry.transforms.matrix import Homography
from rectify.raster.dem import Dem
from rectify.raster.georectify import rectify_with_transform
from rectify.raster.georef import Grid
from rectify.raster.mosaic import MosaicOptions, mosaic
from rectify.raster.ortho import OrthoOptions, orthorectify
from rectify.raster.warp import WarpOptions, warp_raster

CRS = "EPSG:32633"
#: source pixel (col, row) -> world (E, N) of EPSG:32633: 0.5 m pixels, turned and slightly tilted
H_SRC = np.array([[0.45, 0.12, 500_010.3], [0.10, -0.48, 5_000_070.9], [2e-6, -1e-6, 1.0]])


def _write(path: Path, bands: np.ndarray, transform: Affine | None = None, crs: str | None = None,
           nodata: float | None = None) -> Path:
    c, h, w = bands.shape
    kw = {} if transform is None else {"transform": transform}
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=c, dtype=bands.dtype.name, crs=crs,
                       nodata=nodata, **kw) as ds:
        ds.write(bands)
    return path


def _position_source(path: Path, w: int = 140, h: int = 110) -> Path:
    """float32 bands: the source column and row of each pixel centre."""
    cc, rr = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return _write(path, np.stack([cc, rr]))


def _apply_h(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:]


def _centres(T: Affine, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """World (x, y) of every pixel centre, (h, w) each, by rasterio."""
    rr, cc = np.mgrid[0:h, 0:w]
    x, y = rasterio.transform.xy(T, rr.ravel(), cc.ravel(), offset="center")
    return np.asarray(x).reshape(h, w), np.asarray(y).reshape(h, w)


def _tap_grid(xy: np.ndarray, res: float) -> tuple[float, float, int, int]:
    """(left, top, width, height) of the grid with edges on whole multiples of ``res`` covering ``xy``."""
    x0 = math.floor(xy[:, 0].min() / res + 1e-9) * res
    x1 = math.ceil(xy[:, 0].max() / res - 1e-9) * res
    y0 = math.floor(xy[:, 1].min() / res + 1e-9) * res
    y1 = math.ceil(xy[:, 1].max() / res - 1e-9) * res
    return x0, y1, int(round((x1 - x0) / res)), int(round((y1 - y0) / res))


def _edges(w: int, h: int, n: int = 401) -> np.ndarray:
    """Points along the outer pixel edges of a w x h image (pixel centres at integers)."""
    t = np.linspace(0, 1, n)
    a, b = -0.5 + t * w, -0.5 + t * h
    return np.vstack([np.c_[a, np.full(n, -0.5)], np.c_[a, np.full(n, h - 0.5)], np.c_[np.full(n, -0.5), b],
                      np.c_[np.full(n, w - 0.5), b]])


# ====================================================================== warp
@pytest.mark.parametrize("resampling", ["bilinear", "cubic"])
def test_warp_geotransform_and_half_pixel_in_the_transforms_crs(tmp_path, resampling):
    """A homography (matrix path): the grid from the footprint of the outer pixel edges; every valid output
    pixel holds the source position of its centre, H^-1(rasterio's centre), to OpenCV's resolution of source
    positions (1/32 px: 0.022 px measured; cubic 0.068 px: its weights are tabulated at that step too)."""
    src = _position_source(tmp_path / "src.tif")
    res = 0.7
    rectify_with_transform(src, tmp_path / "out.tif", Homography(H_SRC), model_crs=CRS, resolution=res,
                           options=WarpOptions(resampling=resampling, tile_px=32))
    left, top, w, h = _tap_grid(_apply_h(H_SRC, _edges(140, 110)), res)
    with rasterio.open(tmp_path / "out.tif") as ds:
        assert ds.transform.almost_equals(Affine(res, 0, left, 0, -res, top), precision=1e-9), ds.transform
        assert (ds.width, ds.height) == (w, h)
        a = ds.read().astype(np.float64)
        valid = ds.read_masks(1) > 0
    X, Y = _centres(Affine(res, 0, left, 0, -res, top), w, h)
    expect = _apply_h(np.linalg.inv(H_SRC), np.c_[X.ravel(), Y.ravel()]).reshape(h, w, 2)
    # well inside the footprint: the kernel sees only source pixels
    inner = valid & (expect[..., 0] > 2) & (expect[..., 0] < 137) & (expect[..., 1] > 2) & (expect[..., 1] < 107)
    assert inner.sum() > 0.5 * valid.sum()
    err = np.hypot(a[0] - expect[..., 0], a[1] - expect[..., 1])[inner]
    assert err.max() < (0.03 if resampling == "bilinear" else 0.08), err.max()
    assert abs(float(np.median(a[0][inner] - expect[..., 0][inner]))) < 0.005
    assert abs(float(np.median(a[1][inner] - expect[..., 1][inner]))) < 0.005
    # the footprint: valid exactly where the nearest source pixel exists
    inside = (expect[..., 0] > -0.5 + 1e-6) & (expect[..., 0] < 139.5 - 1e-6) & \
        (expect[..., 1] > -0.5 + 1e-6) & (expect[..., 1] < 109.5 - 1e-6)
    sure = inside & (np.minimum.reduce([expect[..., 0] + 0.5, 139.5 - expect[..., 0], expect[..., 1] + 0.5,
                                        109.5 - expect[..., 1]]) > 0.01)
    assert valid[sure].all() and not valid[~inside].any()


def test_warp_geotransform_and_half_pixel_across_crss(tmp_path):
    """The same homography written in another CRS (UTM 34N; the map path through pyproj, maps on a sparse
    lattice): the grid from the pyproj-transformed footprint, the values at the centres to 0.03 px (OpenCV's
    1/32 px), their median to 0.005 px."""
    src = _position_source(tmp_path / "src.tif")
    res = 0.7
    out_crs = "EPSG:32634"
    rectify_with_transform(src, tmp_path / "out.tif", Homography(H_SRC), model_crs=CRS, dst_crs=out_crs,
                           resolution=res, options=WarpOptions(resampling="bilinear", tile_px=32))
    fwd = pyproj.Transformer.from_crs(CRS, out_crs, always_xy=True)
    inv = pyproj.Transformer.from_crs(out_crs, CRS, always_xy=True)
    e = _apply_h(H_SRC, _edges(140, 110))
    left, top, w, h = _tap_grid(np.column_stack(fwd.transform(e[:, 0], e[:, 1])), res)
    with rasterio.open(tmp_path / "out.tif") as ds:
        assert ds.transform.almost_equals(Affine(res, 0, left, 0, -res, top), precision=1e-6), ds.transform
        assert (ds.width, ds.height) == (w, h)
        a = ds.read().astype(np.float64)
        valid = ds.read_masks(1) > 0
    X, Y = _centres(Affine(res, 0, left, 0, -res, top), w, h)
    gx, gy = inv.transform(X.ravel(), Y.ravel())
    expect = _apply_h(np.linalg.inv(H_SRC), np.c_[gx, gy]).reshape(h, w, 2)
    inner = valid & (expect[..., 0] > 2) & (expect[..., 0] < 137) & (expect[..., 1] > 2) & (expect[..., 1] < 107)
    assert inner.sum() > 0.5 * valid.sum()
    err = np.hypot(a[0] - expect[..., 0], a[1] - expect[..., 1])[inner]
    assert err.max() < 0.03, err.max()
    assert abs(float(np.median(a[0][inner] - expect[..., 0][inner]))) < 0.005
    assert abs(float(np.median(a[1][inner] - expect[..., 1][inner]))) < 0.005


class _Smooth:
    """Output world (x, y) -> source pixel: a rotation plus a gentle quadratic term (no matrix: the map path)."""

    def __init__(self, T: Affine):
        a = math.radians(17)
        self.inv_T = ~T
        self.c, self.s = math.cos(a), math.sin(a)

    def __call__(self, world: np.ndarray) -> np.ndarray:
        cols, rows = self.inv_T * (world[:, 0], world[:, 1])
        u, v = np.asarray(cols) - 0.5 - 70, np.asarray(rows) - 0.5 - 55
        x = self.c * u - self.s * v + 70 + 4e-4 * u * u
        y = self.s * u + self.c * v + 55 - 3e-4 * u * v
        return np.column_stack([x, y])


class _Matrix:
    """The same rotation as a (3, 3) matrix (the matrix path: cv2.warpAffine)."""

    def __init__(self, T: Affine):
        a = math.radians(17)
        c, s = math.cos(a), math.sin(a)
        to_px = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]]) @ np.array(list(~T) + [0, 0, 0])[:9].reshape(3, 3)
        centre = np.array([[1, 0, -70], [0, 1, -55], [0, 0, 1.0]])
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        self.matrix = np.linalg.inv(centre) @ R @ centre @ to_px

    def __call__(self, world: np.ndarray) -> np.ndarray:
        return _apply_h(self.matrix, world)


def _texture_source(tmp_path: Path, dtype: str) -> tuple[Path, Affine]:
    """A noisy texture (high frequencies: the kernels' tails matter) with a nodata hole."""
    rng = np.random.default_rng(7)
    h, w = 110, 140
    t = Affine(1.0, 0, 1000.0, 0, -1.0, 2000.0)
    img = rng.uniform(0, 250, (2, h, w))
    img[:, 40:52, 60:75] = 255.0  # the hole (nodata 255)
    if dtype == "uint8":
        return _write(tmp_path / "tex.tif", img.astype(np.uint8), t, CRS, nodata=255), t
    return _write(tmp_path / "tex.tif", img.astype(np.float32), t, CRS, nodata=255), t


@pytest.mark.parametrize("resampling", ["nearest", "bilinear", "cubic", "lanczos"])
@pytest.mark.parametrize("path", ["matrix", "map"])
@pytest.mark.parametrize("dtype", ["float32", "uint8"])
def test_warp_does_not_depend_on_the_tile_size(tmp_path, resampling, path, dtype):
    """Tiles of 16, 48 and 512 px give the same raster, byte for byte (mask and values), with a nodata hole
    and the source's edge in the output. A kernel that reads too small a window reaches past it at tile
    borders (the cubic kernel needs 2 source pixels, Lanczos 4); OpenCV's warpAffine on a tile-relative
    transform moved some pixels by 1/32 px from one tiling to another (up to 8 DN on this texture)."""
    src, t = _texture_source(tmp_path, dtype)
    f = _Matrix(t) if path == "matrix" else _Smooth(t)
    grid = Grid(150, 120, Affine(0.9, 0, 995.0, 0, -0.9, 2004.0), CRS)
    outs = []
    for tile in (16, 48, 512):
        out = tmp_path / f"o{tile}.tif"
        # a lattice step (12) that does not divide every tile size: the map path's lattice must be the grid's
        warp_raster(src, out, f, grid, options=WarpOptions(resampling=resampling, tile_px=tile, threads=1,
                                                           map_step_px=12))
        with rasterio.open(out) as ds:
            outs.append((ds.read(), ds.read_masks(1) > 0))
    a, ma = outs[0]
    assert 0.5 < ma.mean() < 1.0
    for b, mb in outs[1:]:
        assert np.array_equal(ma, mb)
        d = np.abs(a.astype(np.float64) - b)[:, ma]
        assert np.array_equal(a[:, ma], b[:, ma]), (float(d.max()), int((d > 0).sum()))


@pytest.mark.parametrize("path", ["matrix", "map"])
def test_warp_nearest_half_way_positions_do_not_depend_on_the_tile_size(tmp_path, path):
    """Halving the resolution on the source's lattice puts every output centre half-way between four source
    pixels: nearest-neighbour must choose the same one in every tiling (OpenCV rounds half-way positions to the
    even pixel of the window: half the pixels changed with the window's origin)."""
    rng = np.random.default_rng(8)
    h, w = 200, 240
    src = _write(tmp_path / "s.tif", rng.integers(1, 255, (1, h, w)).astype(np.uint8), Affine(1, 0, 0, 0, -1, h), CRS)
    inv = np.linalg.inv(np.array([[1, 0, 0.5], [0, -1, h - 0.5], [0, 0, 1.0]]))

    class Lattice:
        matrix = inv

        def __call__(self, p: np.ndarray) -> np.ndarray:
            return _apply_h(inv, p)

    f = Lattice() if path == "matrix" else (lambda p: _apply_h(inv, p))
    grid = Grid(w // 2, h // 2, Affine(2, 0, 0, 0, -2, h), CRS)
    outs = []
    for tile in (16, 48, 512):
        warp_raster(src, tmp_path / f"o{tile}.tif", f, grid, options=WarpOptions(resampling="nearest", tile_px=tile))
        with rasterio.open(tmp_path / f"o{tile}.tif") as ds:
            outs.append(ds.read(1))
    assert np.array_equal(outs[0], outs[1]) and np.array_equal(outs[0], outs[2])


# ====================================================================== mosaic
X0, Y0 = 500_000.0, 5_000_000.0


def _world_ortho(path: Path, T: Affine, w: int, h: int) -> Path:
    """float32 orthophoto whose bands are the world x - X0, y - Y0 of each pixel centre (nodata NaN)."""
    X, Y = _centres(T, w, h)
    return _write(path, np.stack([X - X0, Y - Y0]).astype(np.float32), T, CRS, nodata=float("nan"))


def test_mosaic_geotransform_and_half_pixel(tmp_path):
    """Two orthophotos off the mosaic's lattice: the grid is the union of their outer edges on whole multiples
    of the resolution; every mosaic pixel holds the world coordinates of its own centre (1e-6 m), also
    where the two are feathered together."""
    a = _world_ortho(tmp_path / "a.tif", Affine(0.5, 0, 500_000.13, 0, -0.5, 5_000_100.41), 90, 70)
    b = _world_ortho(tmp_path / "b.tif", Affine(0.5, 0, 500_030.37, 0, -0.5, 5_000_085.22), 80, 75)
    res = 0.6
    mosaic([a, b], tmp_path / "m.tif", resolution=res, options=MosaicOptions(feather_px=8, tile_px=32))
    corners = np.array([[500_000.13, 5_000_100.41 - 35], [500_000.13 + 45, 5_000_100.41],
                        [500_030.37, 5_000_085.22 - 37.5], [500_030.37 + 40, 5_000_085.22]])
    left, top, w, h = _tap_grid(corners, res)
    with rasterio.open(tmp_path / "m.tif") as ds:
        assert ds.transform.almost_equals(Affine(res, 0, left, 0, -res, top), precision=1e-9), ds.transform
        assert (ds.width, ds.height) == (w, h)
        m = ds.read().astype(np.float64)
    X, Y = _centres(Affine(res, 0, left, 0, -res, top), w, h)
    ok = np.isfinite(m).all(axis=0)
    assert ok.mean() > 0.5
    err = np.hypot(m[0] - (X - X0), m[1] - (Y - Y0))[ok]
    # bilinear between the inputs' centres is exact for a linear function, except within half an input pixel
    # of an input's edge, where the border pixel is repeated (an error of at most 0.25 m here)
    near_edge = np.zeros_like(ok)
    for x0, y0, x1, y1 in ((500_000.13, 5_000_065.41, 500_045.13, 5_000_100.41),
                           (500_030.37, 5_000_047.72, 500_070.37, 5_000_085.22)):
        d = np.minimum.reduce([X - x0, x1 - X, Y - y0, y1 - Y])  # > 0 inside
        near_edge |= np.abs(d) < res
    far = ok & ~near_edge
    assert far.sum() > 0.8 * ok.sum()
    assert err[far[ok]].max() < 1e-4, err[far[ok]].max()  # float32 bands
    assert err.max() < 0.25 * math.sqrt(2) + 1e-4, err.max()  # (a corner repeats its pixel in x and y)


def test_mosaic_does_not_depend_on_the_tile_size(tmp_path):
    """Three overlapping inputs, feathered, at a resolution whose lattice meets an input's edge exactly (a
    mosaic pixel centre on the edge: the nearest-pixel validity test rounds a half-way position), with tiles
    of 16, 48 and 512 px: the same bytes."""
    rng = np.random.default_rng(9)
    ins = []
    for k, (x0, y0) in enumerate(((500_000.0, 5_000_100.0), (500_021.0, 5_000_093.0), (500_005.0, 5_000_070.0))):
        img = rng.integers(1, 255, (3, 60, 70)).astype(np.uint8)
        ins.append(_write(tmp_path / f"i{k}.tif", img, Affine(0.5, 0, x0, 0, -0.5, y0), CRS, nodata=0))
    outs = []
    for tile in (16, 48, 512):
        mosaic(ins, tmp_path / f"m{tile}.tif", resolution=0.4, options=MosaicOptions(feather_px=10, tile_px=tile))
        with rasterio.open(tmp_path / f"m{tile}.tif") as ds:
            outs.append(ds.read())
    assert np.array_equal(outs[0], outs[1]) and np.array_equal(outs[0], outs[2])


# ====================================================================== ortho
E0, N0 = 500_000.0, 5_000_000.0


def _ortho_scene(tmp_path: Path) -> tuple[FrameModel, Path]:
    """A tilted frame camera over a DEM of hills; the photo's bands are its own pixel column and row."""
    n, r = 300, 2.0
    x = E0 - 300 + r * (np.arange(n) + 0.5)
    y = N0 + 300 - r * (np.arange(n) + 0.5)
    X, Y = np.meshgrid(x, y)
    Z = 100 + 30 * np.sin((X - E0) / 60.0) * np.cos((Y - N0) / 45.0)
    _write(tmp_path / "dem.tif", Z[None].astype(np.float32), Affine(r, 0, E0 - 300, 0, -r, N0 + 300), CRS)
    cam = Camera(focal_length_mm=10.0, pixel_size_mm=0.01, width=200, height=160)
    model = FrameModel(cam, [E0 + 3.0, N0 - 2.0, 800.0], matrix_from_angles(0.05, -0.04, 0.3), CRS)
    rng = np.random.default_rng(3)
    tex = rng.uniform(0, 250, (160, 200)).astype(np.float32)
    cc, rr = np.meshgrid(np.arange(200, dtype=np.float32), np.arange(160, dtype=np.float32))
    _write(tmp_path / "photo.tif", np.stack([cc, rr, tex]))
    return model, tmp_path / "dem.tif"


def test_ortho_geotransform_from_the_footprint(tmp_path):
    """The grid covers the outer pixel edges projected to the DEM's lowest and highest heights (own
    collinearity), edges on whole multiples of the resolution."""
    model, dem_path = _ortho_scene(tmp_path)
    res = orthorectify(tmp_path / "photo.tif", tmp_path / "o.tif", model, Dem.from_path(dem_path), resolution=0.8,
                       options=OrthoOptions(tile_px=64))
    with rasterio.open(dem_path) as ds:
        z = ds.read(1)
    cam = model.camera
    e = _edges(cam.width, cam.height, 33)
    mm = np.column_stack([(e[:, 0] - (cam.width - 1) / 2) * cam.pixel_size_mm,
                          ((cam.height - 1) / 2 - e[:, 1]) * cam.pixel_size_mm, np.full(len(e), -cam.focal_length_mm)])
    rays = mm @ model.rotation.T
    pts = []
    for hz in (float(z.min()), float(z.max())):
        t = (hz - model.position[2]) / rays[:, 2]
        pts.append(model.position[:2] + t[:, None] * rays[:, :2])
    left, top, w, h = _tap_grid(np.vstack(pts), 0.8)
    with rasterio.open(tmp_path / "o.tif") as ds:
        assert ds.transform.almost_equals(Affine(0.8, 0, left, 0, -0.8, top), precision=1e-9), ds.transform
        assert (ds.width, ds.height) == (w, h)
        a = ds.read().astype(np.float64)
    assert res.grid.width == w
    # content at the centres: each ortho pixel holds the photo position (bands 1, 2) of its centre on the DEM
    # (bilinear between the DEM's cell centres), projected by our own collinearity
    from scipy.ndimage import map_coordinates

    X, Y = _centres(Affine(0.8, 0, left, 0, -0.8, top), w, h)
    dem_c = (X - (E0 - 300)) / 2.0 - 0.5
    dem_r = ((N0 + 300) - Y) / 2.0 - 0.5
    Zc = map_coordinates(z.astype(np.float64), [dem_r.ravel(), dem_c.ravel()], order=1).reshape(h, w)
    G = np.stack([X, Y, Zc], axis=-1).reshape(-1, 3)
    q = (G - model.position) @ model.rotation
    xm, ym = -cam.focal_length_mm * q[:, 0] / q[:, 2], -cam.focal_length_mm * q[:, 1] / q[:, 2]
    col = ((cam.width - 1) / 2 + xm / cam.pixel_size_mm).reshape(h, w)
    row = ((cam.height - 1) / 2 - ym / cam.pixel_size_mm).reshape(h, w)
    ok = np.isfinite(a).all(axis=0) & (col > 1) & (col < cam.width - 2) & (row > 1) & (row < cam.height - 2)
    ok &= (dem_c > 0) & (dem_r > 0) & (dem_c < z.shape[1] - 1) & (dem_r < z.shape[0] - 1)
    assert ok.sum() > 0.3 * ok.size
    err = np.hypot(a[0] - col, a[1] - row)[ok]
    assert err.max() < 0.03, err.max()  # OpenCV's 1/32 px positions; half a pixel off is 0.5
    assert abs(float(np.median((a[0] - col)[ok]))) < 0.005 and abs(float(np.median((a[1] - row)[ok]))) < 0.005


@pytest.mark.parametrize("resampling", ["bilinear", "cubic"])
@pytest.mark.parametrize("true_ortho", [False, True])
def test_ortho_does_not_depend_on_the_tile_size(tmp_path, resampling, true_ortho):
    model, dem_path = _ortho_scene(tmp_path)
    outs = []
    for tile in (16, 48, 512):
        out = tmp_path / f"o{tile}.tif"
        orthorectify(tmp_path / "photo.tif", out, model, Dem.from_path(dem_path), resolution=0.8,
                     options=OrthoOptions(tile_px=tile, resampling=resampling, true_ortho=true_ortho, threads=1))
        with rasterio.open(out) as ds:
            outs.append(ds.read().astype(np.float64))
    a = outs[0]
    for b in outs[1:]:
        fa, fb = np.isfinite(a), np.isfinite(b)
        assert np.array_equal(fa, fb)
        d = np.abs(a - b)[fa]
        # the projection is interpolated per tile within PROJECTION_TOLERANCE_PX (1e-3 px): 1e-3 DN measured
        assert d.max() <= 0.01, (float(d.max()), int((d > 0.01).sum()))


# ====================================================================== GCP fit
@pytest.mark.parametrize("method", ["affine", "homography", "poly2", "cotangent"])
def test_fit_residuals_are_adjusted_minus_observed(method):
    """docs/formats.md: residual = adjusted - observed, the model applied to the source point minus the GCP's
    target coordinates."""
    rng = np.random.default_rng(21)
    src = rng.uniform([0, 0], [800, 600], (14, 2))
    dst = _apply_h(H_SRC, src) + rng.normal(0, 0.3, (14, 2))
    g = GcpTable(tuple(f"g{i}" for i in range(14)), src, dst, None, np.zeros(14, bool), CRS)
    fit = fit_gcps(g, method=method)
    tab = fit.table
    np.testing.assert_allclose(tab.observed, dst, atol=1e-9)
    np.testing.assert_allclose(tab.adjusted, fit.model(src), atol=1e-6)
    np.testing.assert_allclose(tab.residual, fit.model(src) - dst, atol=1e-6)
    assert "residual = adjusted - observed" in tab.to_csv().splitlines()[0]


# ====================================================================== the shared data's location
def test_every_shared_data_lookup_honours_RECTIFY_SHARED_DATA(tmp_path):
    """No test builds the shared data path itself; the modules that read it take ``$RECTIFY_SHARED_DATA``
    (checked in a fresh interpreter with the variable pointing elsewhere)."""
    import re
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    pattern = re.compile(r"""["']shared["']\s*\)?\s*/\s*["']data["']|["'][./]*\.\./shared/data""")
    offenders = [str(p.relative_to(root)) for p in sorted((root / "tests").rglob("*.py"))
                 if p.name != "shared_data.py" and pattern.search(p.read_text(encoding="utf-8"))]
    assert offenders == [], offenders
    probe = ("import tests.conftest as c, tests.rectify.test_rpc as a, tests.rectify.test_ortho as b, "
             "tests.stereo.test_calibration as d, tests.stereo.test_dense as e; "
             "print(c.SHARED_DATA, a.SHARED, b.NGI.parent, d.SHARED, e.DATA, sep='\\n')")
    env = {**__import__("os").environ, "RECTIFY_SHARED_DATA": str(tmp_path / "elsewhere")}
    r = subprocess.run([sys.executable, "-c", probe], cwd=root, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == [str(tmp_path / "elsewhere")] * 5, r.stdout
