"""Orthorectification (issue 16): synthetic frame and RPC images rendered over a known DEM.

The rendered images carry their own ground truth: bands 1 and 2 are the easting and northing
(minus a local origin) of the ground point each image pixel sees (exact ray-DEM intersection),
band 3 a texture. In the orthophoto, band 1/2 at an output pixel must equal that pixel's centre:
the difference is the geolocation error (tolerance 0.1 output pixel, as the issue asks).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.formats.exterior import read_exterior
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.sensors import FrameModel, RPCModel
from rectify.raster.dem import Dem, bilinear
from rectify.raster.georef import Grid, pixel_from_world
from rectify.raster.ortho import OrthoOptions, orthorectify
from tests.support.shared_data import SHARED_DATA

CRS = "EPSG:32632"
E0, N0 = 500_000.0, 5_000_000.0


def write_dem(path: Path, fn, *, res: float = 2.0, size: float = 600.0, crs: str = CRS) -> None:
    n = int(size / res)
    x = E0 - size / 2 + res * (np.arange(n) + 0.5)
    y = N0 + size / 2 - res * (np.arange(n) + 0.5)
    X, Y = np.meshgrid(x, y)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=crs,
                       transform=Affine(res, 0, E0 - size / 2, 0, -res, N0 + size / 2)) as ds:
        ds.write(fn(X, Y).astype("float32"), 1)


def hills(X, Y):
    return 100 + 40 * np.sin((X - E0) / 60.0) * np.cos((Y - N0) / 45.0) + 0.1 * (X - E0)


def surface(dem_path: Path):
    """The DEM surface exactly as the orthorectifier sees it (bilinear between cell centres)."""
    with rasterio.open(dem_path) as ds:
        z = ds.read(1).astype(np.float64)
        tr = ds.transform

    def f(xy):
        px = pixel_from_world(tr, xy)
        return bilinear(z, None, px[:, 0], px[:, 1])
    return f


def texture(x, y):
    return 100 + 60 * np.sin(x / 3.1) * np.cos(y / 4.3) + 40 * np.sin((x + y) / 7.7)


def write_image(path: Path, xy: np.ndarray, shape: tuple[int, int]) -> None:
    """Bands: easting - E0, northing - N0, texture (float32, NaN where the ray misses)."""
    h, w = shape
    bands = np.stack([xy[:, 0] - E0, xy[:, 1] - N0, texture(xy[:, 0] - E0, xy[:, 1] - N0)]).reshape(3, h, w)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="float32", nodata=np.nan) as ds:
        ds.write(bands.astype("float32"))


def render_frame(model: FrameModel, surf, zlim: tuple[float, float], dz: float = 0.5) -> np.ndarray:
    """Ground (E, N) seen by every pixel: first crossing of the ray with the surface, then bisection."""
    cam = model.camera
    cc, rr = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    px = np.column_stack([cc.ravel(), rr.ravel()]).astype(float)
    rays = cam.rays_from_pixel(px) @ model.rotation.T
    C = model.position

    def at(z):
        t = (z - C[2]) / rays[:, 2]
        return C + t[:, None] * rays
    zs = np.arange(zlim[1], zlim[0] - dz, -dz)
    hi = np.full(len(px), np.nan)
    lo = np.full(len(px), np.nan)
    prev = zs[0]
    for z in zs[1:]:
        p = at(np.full(len(px), z))
        below = (p[:, 2] <= surf(p[:, :2])) & np.isnan(hi)
        hi[below], lo[below] = prev, z
        prev = z
    for _ in range(50):
        mid = 0.5 * (hi + lo)
        p = at(mid)
        above = p[:, 2] > surf(p[:, :2])
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return at(0.5 * (hi + lo))[:, :2]


def frame_scene(tmp_path: Path, dem_fn=hills, angles=(0.06, -0.05, 0.35), height=800.0, offset=(0.0, 0.0),
                size=(240, 200), dem_res=2.0, focal_mm=10.0):
    cam = Camera(focal_length_mm=focal_mm, pixel_size_mm=0.01, width=size[0], height=size[1])
    R = matrix_from_angles(*angles)
    model = FrameModel(cam, [E0 + offset[0], N0 + offset[1], height], R, CRS)
    write_dem(tmp_path / "dem.tif", dem_fn, res=dem_res)
    surf = surface(tmp_path / "dem.tif")
    with rasterio.open(tmp_path / "dem.tif") as ds:
        z = ds.read(1)
    xy = render_frame(model, surf, (float(z.min()) - 1, float(z.max()) + 1))
    write_image(tmp_path / "frame.tif", xy, (cam.height, cam.width))
    return model


def geolocation_error(path: Path, *, visible_only: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-pixel error (in output pixels) of bands 1/2 against the output pixel centres."""
    with rasterio.open(path) as ds:
        a = ds.read().astype(np.float64)
        tr = ds.transform
        res = tr.a
    h, w = a.shape[1:]
    cc, rr = np.meshgrid(np.arange(w), np.arange(h))
    X = tr.c + tr.a * (cc + 0.5) - E0
    Y = tr.f + tr.e * (rr + 0.5) - N0
    err = np.hypot(a[0] - X, a[1] - Y) / res
    # within half a source pixel of the image edge the border pixel is replicated (no extrapolation):
    # measure away from the footprint edge (the valid area eroded by one output pixel)
    from scipy.ndimage import binary_erosion

    err[~binary_erosion(np.isfinite(err), np.ones((3, 3), bool))] = np.nan
    return err, a, res


def test_frame_ortho_geolocation(tmp_path):
    model = frame_scene(tmp_path)
    dem = Dem.from_path(tmp_path / "dem.tif")
    res = orthorectify(tmp_path / "frame.tif", tmp_path / "ortho.tif", model, dem, resolution=1.0,
                       options=OrthoOptions(tile_px=64, threads=2))
    err, a, _ = geolocation_error(tmp_path / "ortho.tif")
    ok = np.isfinite(err)
    assert ok.mean() > 0.3
    # the image is 0.8 m/px at 800 m; interpolation of the smooth coordinate bands is near exact
    assert np.percentile(err[ok], 99.9) < 0.1, np.percentile(err[ok], [50, 99, 99.9, 100])
    # the DEM mattered: heights 60-140 m, so a planar rectification would be off by metres
    assert res.max_relief_shift > 3.0
    assert res.dem_range[0] < res.dem_range[1]
    with rasterio.open(tmp_path / "ortho.tif") as ds:
        assert ds.crs.to_epsg() == 32632 and ds.count == 3 and ds.tags()["ORTHO_MODEL"] == "FrameModel"
        assert np.isnan(ds.nodata)


def test_frame_ortho_dem_in_other_crs_and_cog(tmp_path):
    """DEM in geographic coordinates at another resolution, output in UTM, COG."""
    from tests.support.rectify_support import cog_problems

    model = frame_scene(tmp_path)
    # the same surface written in EPSG:4326: resample the UTM DEM at lon/lat cell centres
    from rectify.geometry.crs import transform_xy
    surf = surface(tmp_path / "dem.tif")
    ll0 = transform_xy(CRS, "EPSG:4326", [[E0 - 300, N0 - 300]])[0]
    ll1 = transform_xy(CRS, "EPSG:4326", [[E0 + 300, N0 + 300]])[0]
    n = 400
    rx, ry = (ll1[0] - ll0[0]) / n, (ll1[1] - ll0[1]) / n
    lon = ll0[0] + rx * (np.arange(n) + 0.5)
    lat = ll1[1] - ry * (np.arange(n) + 0.5)
    LON, LAT = np.meshgrid(lon, lat)
    en = transform_xy("EPSG:4326", CRS, np.column_stack([LON.ravel(), LAT.ravel()]))
    z = surf(en).reshape(n, n)
    with rasterio.open(tmp_path / "dem_ll.tif", "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs="EPSG:4326", transform=Affine(rx, 0, ll0[0], 0, -ry, ll1[1]), nodata=np.nan) as ds:
        ds.write(z.astype("float32"), 1)
    dem = Dem.from_path(tmp_path / "dem_ll.tif")
    orthorectify(tmp_path / "frame.tif", tmp_path / "ortho.tif", model, dem, resolution=1.0,
                 options=OrthoOptions(tile_px=128, cog=True))
    assert cog_problems(tmp_path / "ortho.tif") == []
    err, _, _ = geolocation_error(tmp_path / "ortho.tif")
    ok = np.isfinite(err)
    # the lon/lat DEM is a resampled copy (1.5 m cells): heights differ by up to ~0.3 m, i.e. < 0.1 m shift
    assert np.percentile(err[ok], 99) < 0.15, np.percentile(err[ok], [50, 99, 100])


def test_true_ortho_wall(tmp_path):
    """A 30 m high, 10 m thick wall; the camera looks at it from the side: the ground behind is hidden."""
    def wall(X, Y):
        return np.where(np.abs(X - E0) < 5.0, 130.0, 100.0)
    model = frame_scene(tmp_path, dem_fn=wall, angles=(0.0, 0.0, 0.0), height=600.0, offset=(-80.0, 0.0),
                        dem_res=1.0, focal_mm=5.0)
    dem = Dem.from_path(tmp_path / "dem.tif")
    res = orthorectify(tmp_path / "frame.tif", tmp_path / "true.tif", model, dem, resolution=0.5,
                       options=OrthoOptions(tile_px=64, true_ortho=True, threads=2))
    orthorectify(tmp_path / "frame.tif", tmp_path / "plain.tif", model, dem, resolution=0.5,
                 options=OrthoOptions(tile_px=64))
    err, a, _ = geolocation_error(tmp_path / "true.tif")
    vis = a[3]
    with rasterio.open(tmp_path / "true.tif") as ds:
        tr = ds.transform
        assert ds.count == 4
    h, w = vis.shape
    X = tr.c + tr.a * (np.arange(w) + 0.5) - E0
    # expected shadow: the DEM cells (1 m) put the wall top edge at x = 4.5 m (last 130 m cell centre; the
    # bilinear surface drops to the ground at 5.5 m); the ray from the camera (xc = -80, 600 m) over that edge
    # meets the ground at x_end = 4.5 + 30 * (4.5 + 80) / (600 - 130)
    x_end = 4.5 + 30 * (4.5 + 80) / (600 - 130)
    cols_shadow = (X > 5.5) & (X < x_end - 0.5)
    cols_clear = (X > x_end + 0.5) | (X < -5.5)
    inside = vis > 0
    rows = inside.all(axis=1)
    assert rows.sum() > 20
    band = vis[rows]
    assert (band[:, cols_shadow] == 1).mean() > 0.97
    assert (band[:, cols_clear] == 2).mean() > 0.99
    assert res.n_occluded > 0
    # occluded cells are nodata; visible cells are correctly located (no ghosting)
    assert np.isnan(a[0][vis == 1]).all()
    ok = (vis == 2) & np.isfinite(err)
    # the wall faces and edges are sampled steeply: keep the ground away from them
    ground = ok & np.broadcast_to((np.abs(X) > 6) & ~((X > 4) & (X < x_end + 1.5)), ok.shape)
    assert np.percentile(err[ground], 99) < 0.1
    # the plain ortho shows the wall top again in the hidden strip (ghost): large errors there
    err_p, _, _ = geolocation_error(tmp_path / "plain.tif")
    ghost = err_p[rows][:, cols_shadow]
    assert np.nanmedian(ghost) > 5


def test_rpc_ortho_geolocation(tmp_path):
    from rectify.geometry.crs import transform_xy
    from rectify.geometry.rpc import RPC

    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[E0, N0]])[0]
    # 200 x 200 px at ~1 m; 0.3 px per m of height across track (about 17 degrees off nadir)
    m_lon = 1.0 / (111_320 * np.cos(np.radians(lat0)))
    m_lat = 1.0 / 111_320
    rpc = RPC.from_coefficients(
        offsets=(100.0, 100.0, lat0, lon0, 100.0), scales=(100.0, 100.0, 100 * m_lat, 100 * m_lon, 100.0),
        samp_num=[0.0, 1.0, 0.05, 0.3, 0.001, 0.0, 0.0, 0.002], samp_den=[1.0, 0.001],
        line_num=[0.0, 0.04, -1.0, 0.05, 0.0, 0.0, 0.001], line_den=[1.0, 0.0, 0.001])
    write_dem(tmp_path / "dem.tif", hills)
    dem = Dem.from_path(tmp_path / "dem.tif")
    cc, rr = np.meshgrid(np.arange(200), np.arange(200))
    px = np.column_stack([cc.ravel(), rr.ravel()]).astype(float)
    g = rpc.localize_on_dem(px, dem.lonlat_function(), h_range=(40.0, 200.0))
    en = transform_xy("EPSG:4326", CRS, g[:, :2])
    write_image(tmp_path / "rpc.tif", en, (200, 200))
    res = orthorectify(tmp_path / "rpc.tif", tmp_path / "ortho.tif", RPCModel(rpc, 200, 200), dem, resolution=1.0,
                       options=OrthoOptions(tile_px=64, threads=2))
    assert res.grid.crs == CRS  # default: the UTM zone of the scene
    err, _, _ = geolocation_error(tmp_path / "ortho.tif")
    ok = np.isfinite(err)
    assert ok.mean() > 0.5
    assert np.percentile(err[ok], 99.9) < 0.1, np.percentile(err[ok], [50, 99, 99.9, 100])
    assert res.max_relief_shift > 10


def test_ortho_bad_input(tmp_path):
    model = frame_scene(tmp_path, size=(60, 50))
    dem = Dem.from_path(tmp_path / "dem.tif")
    with pytest.raises(InvalidInputError, match="is an input"):
        orthorectify(tmp_path / "frame.tif", tmp_path / "dem.tif", model, dem)
    (tmp_path / "exists.tif").write_bytes(b"x")
    with pytest.raises(InvalidInputError, match="exists"):
        orthorectify(tmp_path / "frame.tif", tmp_path / "exists.tif", model, dem)
    assert (tmp_path / "exists.tif").read_bytes() == b"x"
    with pytest.raises(RasterIOError, match="not found"):
        orthorectify(tmp_path / "nope.tif", tmp_path / "o.tif", model, dem)
    other = FrameModel(Camera(focal_length_mm=10.0, pixel_size_mm=0.01, width=61, height=50), model.position,
                       model.rotation, CRS)
    with pytest.raises(InvalidInputError, match="expects"):
        orthorectify(tmp_path / "frame.tif", tmp_path / "o.tif", other, dem)
    with pytest.raises(InvalidInputError, match="resolution"):
        orthorectify(tmp_path / "frame.tif", tmp_path / "o.tif", model, dem, resolution=-1.0)
    up = FrameModel(model.camera, [E0, N0, 20.0], model.rotation, CRS)  # camera below the ground
    with pytest.raises(InvalidInputError, match="footprint"):
        orthorectify(tmp_path / "frame.tif", tmp_path / "o.tif", up, dem)
    assert not (tmp_path / "o.tif").exists()
    with pytest.raises(InvalidInputError, match="resampling"):
        OrthoOptions(resampling="lanczos7")
    with pytest.raises(CRSError):
        FrameModel(model.camera, model.position, model.rotation, None)  # type: ignore[arg-type]
    with rasterio.open(tmp_path / "nocrs.tif", "w", driver="GTiff", width=4, height=4, count=1,
                       dtype="float32") as ds:
        ds.write(np.zeros((1, 4, 4), np.float32))
    with pytest.raises(CRSError, match="no CRS"):
        Dem.from_path(tmp_path / "nocrs.tif")
    grid = Grid(10, 10, Affine(1, 0, E0, 0, -1, N0), None)
    with pytest.raises(CRSError):
        orthorectify(tmp_path / "frame.tif", tmp_path / "o.tif", model, dem, grid=grid)


def test_read_exterior(tmp_path):
    import json

    R = matrix_from_angles(0.1, -0.2, 0.3)
    (tmp_path / "eo.json").write_text(json.dumps({"position": [1, 2, 3], "rotation": R.tolist(), "crs": CRS}))
    eo = read_exterior(tmp_path / "eo.json")
    assert np.allclose(eo["rotation"], R) and eo["crs"] == CRS
    (tmp_path / "eo2.json").write_text(json.dumps({"position": [1, 2, 3],
                                                   "angles": {"omega": 0.1, "phi": -0.2, "kappa": 0.3}}))
    assert np.allclose(read_exterior(tmp_path / "eo2.json")["rotation"], R)
    (tmp_path / "bad.json").write_text(json.dumps({"position": [1, 2]}))
    with pytest.raises(InvalidInputError, match="position"):
        read_exterior(tmp_path / "bad.json")
    (tmp_path / "bad2.json").write_text(json.dumps({"position": [1, 2, 3], "rotation": [[1, 0, 0]] * 3}))
    with pytest.raises(InvalidInputError, match="rotation"):
        read_exterior(tmp_path / "bad2.json")
    (tmp_path / "bad3.json").write_text(json.dumps({"position": [1, 2, 3]}))
    with pytest.raises(InvalidInputError, match="lacks 'rotation'"):
        read_exterior(tmp_path / "bad3.json")


# ----------------------------------------------------------------- mosaic
def _flat_ortho(path: Path, x0: float, x1: float, value: float, nadir_x: float, *, vis=None) -> None:
    res = 1.0
    w, h = int(x1 - x0), 40
    data = np.full((1, h, w), value, np.float32)
    count = 1 if vis is None else 2
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=count, dtype="float32", crs=CRS,
                       nodata=np.nan, transform=Affine(res, 0, E0 + x0, 0, -res, N0 + 40)) as ds:
        if vis is not None:
            data = np.where(vis == 2, data, np.nan).astype(np.float32)
            ds.write(np.concatenate([data, vis[None].astype(np.float32)]))
            ds.update_tags(ORTHO_VISIBILITY_BAND="2")
        else:
            ds.write(data)
        ds.update_tags(ORTHO_NADIR_X=repr(E0 + nadir_x), ORTHO_NADIR_Y=repr(N0 + 20))


def test_mosaic_nearest_nadir_and_feathering(tmp_path):
    from rectify.raster.mosaic import MosaicOptions, mosaic

    _flat_ortho(tmp_path / "a.tif", 0, 100, 100.0, 30.0)
    _flat_ortho(tmp_path / "b.tif", 40, 140, 200.0, 110.0)
    r = mosaic([tmp_path / "a.tif", tmp_path / "b.tif"], tmp_path / "hard.tif", options=MosaicOptions(feather_px=0))
    with rasterio.open(tmp_path / "hard.tif") as ds:
        m = ds.read(1)
        assert ds.width == 140 and ds.crs.to_epsg() == 32632
    x = np.arange(140) + 0.5
    # the seam is the bisector of the nadirs, x = 70
    assert (m[:, x < 70] == 100).all() and (m[:, x > 70] == 200).all()
    assert abs(r.share[0] - 0.5) < 0.01
    mosaic([tmp_path / "a.tif", tmp_path / "b.tif"], tmp_path / "soft.tif", options=MosaicOptions(feather_px=20))
    with rasterio.open(tmp_path / "soft.tif") as ds:
        s = ds.read(1)[20]
    # feathering: along the nadir line d_a - d_b changes by 2 per unit, so the blend spans 20 m around x = 70
    assert s[int(70 - 12)] == 100 and s[int(70 + 12)] == 200
    assert 140 < s[70] < 160 and np.all(np.diff(s[55:86]) >= -1e-3)
    assert "2 orthophotos" in r.summary_lines()[0]


def test_mosaic_fills_occluded_pixels_from_the_next_image(tmp_path):
    from rectify.raster.mosaic import MosaicOptions, mosaic

    vis = np.full((40, 100), 2, np.uint8)
    vis[:, 10:20] = 1  # occluded in a: the nearest image there, but hidden
    _flat_ortho(tmp_path / "a.tif", 0, 100, 100.0, 30.0, vis=vis)
    _flat_ortho(tmp_path / "b.tif", 0, 100, 200.0, 110.0)
    mosaic([tmp_path / "a.tif", tmp_path / "b.tif"], tmp_path / "m.tif", options=MosaicOptions(feather_px=0))
    with rasterio.open(tmp_path / "m.tif") as ds:
        m = ds.read(1)
        assert ds.count == 1  # the visibility band is not mosaicked
    assert (m[:, 10:20] == 200).all() and (m[:, :10] == 100).all() and (m[:, 20:70] == 100).all()


def test_mosaic_bad_input(tmp_path):
    from rectify.raster.mosaic import mosaic

    _flat_ortho(tmp_path / "a.tif", 0, 100, 100.0, 30.0)
    with rasterio.open(tmp_path / "other.tif", "w", driver="GTiff", width=4, height=4, count=1, dtype="float32",
                       crs="EPSG:4326", transform=Affine(1, 0, 0, 0, -1, 4)) as ds:
        ds.write(np.zeros((1, 4, 4), np.float32))
    with pytest.raises(CRSError, match="share one CRS"):
        mosaic([tmp_path / "a.tif", tmp_path / "other.tif"], tmp_path / "m.tif")
    with pytest.raises(InvalidInputError, match="is an input"):
        mosaic([tmp_path / "a.tif"], tmp_path / "a.tif", overwrite=True)
    with pytest.raises(InvalidInputError, match="twice"):
        mosaic([tmp_path / "a.tif", tmp_path / "a.tif"], tmp_path / "m.tif")
    with pytest.raises(InvalidInputError, match="at least one"):
        mosaic([], tmp_path / "m.tif")
    with pytest.raises(RasterIOError, match="not found"):
        mosaic([tmp_path / "nope.tif"], tmp_path / "m.tif")
    assert not (tmp_path / "m.tif").exists()


# ----------------------------------------------------------------- real aerial pair (shared data)
NGI = SHARED_DATA / "ngi_strip05"  # $RECTIFY_SHARED_DATA, else ../shared/data
LO25 = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs"
NGI_EO = {"0182": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702),
          "0184": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883)}


def overlap_shift(a_path: Path, b_path: Path, patch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Phase-correlation shifts (px) of patches over the overlap of two orthophotos, and the global shift."""
    import cv2
    from rasterio.windows import from_bounds

    with rasterio.open(a_path) as A, rasterio.open(b_path) as B:
        left, right = max(A.bounds.left, B.bounds.left), min(A.bounds.right, B.bounds.right)
        bottom, top = max(A.bounds.bottom, B.bounds.bottom), min(A.bounds.top, B.bounds.top)
        wa = from_bounds(left, bottom, right, top, A.transform).round_offsets().round_lengths()
        wb = from_bounds(left, bottom, right, top, B.transform).round_offsets().round_lengths()
        ga = A.read(window=wa).astype(np.float64)[:3].mean(0)
        gb = B.read(window=wb).astype(np.float64)[:3].mean(0)
        both = (A.read_masks(1, window=wa) > 0) & (B.read_masks(1, window=wb) > 0)
    han = cv2.createHanningWindow((patch, patch), cv2.CV_64F)
    shifts = []
    for r0 in range(0, ga.shape[0] - patch, patch // 2):
        for c0 in range(0, ga.shape[1] - patch, patch // 2):
            if both[r0:r0 + patch, c0:c0 + patch].all():
                pa, pb = ga[r0:r0 + patch, c0:c0 + patch], gb[r0:r0 + patch, c0:c0 + patch]
                if pa.std() > 2 and pb.std() > 2:
                    (dx, dy), resp = cv2.phaseCorrelate(pa, pb, han)
                    if resp > 0.2:
                        shifts.append((dx, dy))
    fa = np.where(both, ga, ga[both].mean())
    fb = np.where(both, gb, gb[both].mean())
    ys, xs = np.nonzero(both)
    sl = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    (dx, dy), _ = cv2.phaseCorrelate(fa[sl], fb[sl])
    return np.array(shifts), np.array([dx, dy])


@pytest.mark.shared
def test_ngi_pair_orthophotos_coincide(tmp_path):
    import json

    from rectify.actions.ortho import ortho_from_files
    from rectify.raster.mosaic import mosaic

    if not (NGI / "dem.tif").is_file():
        pytest.skip(f"NGI pair not found under {NGI}")
    (tmp_path / "cam.json").write_text(json.dumps({"focal_length_mm": 120.0, "pixel_size_mm": 0.144,
                                                   "width": 640, "height": 1152}))
    for k, (x, y, z, o, p, kk) in NGI_EO.items():
        R = matrix_from_angles(*np.radians([o, p, kk]))
        (tmp_path / f"eo_{k}.json").write_text(json.dumps({"position": [x, y, z], "rotation": R.tolist(),
                                                           "crs": LO25}))
        run = ortho_from_files(NGI / f"3324c_2015_1004_05_{k}_RGB.tif", tmp_path / f"o{k}.tif", NGI / "dem.tif",
                               camera=tmp_path / "cam.json", exterior=tmp_path / f"eo_{k}.json", resolution=6.0,
                               options=OrthoOptions(threads=2))
        assert run.result.max_relief_shift > 100  # 150-780 m terrain seen from 5250 m
    shifts, glob = overlap_shift(tmp_path / "o0182.tif", tmp_path / "o0184.tif")
    assert len(shifts) > 50
    # measured: global 0.06 px; patches median |shift| 0.15 px, 90th percentile 0.40 px (6 m pixels)
    assert np.hypot(*glob) <= 0.5
    assert np.median(np.hypot(shifts[:, 0], shifts[:, 1])) <= 0.5
    m = mosaic([tmp_path / "o0182.tif", tmp_path / "o0184.tif"], tmp_path / "mosaic.tif")
    assert min(m.share) > 0.3


# ----------------------------------------------------------------- internals with stated tolerances
def test_interpolated_projection_matches_exact(tmp_path):
    """The per-tile projection (sparse grid x 4 heights, cubic in h) is within 1e-3 px of the exact one."""
    from rectify.raster.ortho import PROJECTION_TOLERANCE_PX, _Engine, ortho_grid

    model = FrameModel(Camera(focal_length_mm=10.0, pixel_size_mm=0.01, width=240, height=200),
                       [E0 + 30, N0 - 20, 800.0], matrix_from_angles(0.06, -0.05, 0.35), CRS)
    write_dem(tmp_path / "dem.tif", hills)
    dem = Dem.from_path(tmp_path / "dem.tif")
    grid = ortho_grid(model, dem, resolution=1.0)
    eng = _Engine(str(tmp_path / "dem.tif"), model, dem, grid, OrthoOptions(tile_px=128), np.dtype("float32"), 1,
                  float("nan"), 0, 100.0)
    c0, r0, w, h = 64, 64, 128, 96
    z = eng._heights(c0, r0, w, h)
    col, row = eng._project(c0, r0, w, h, z)
    mx, my = eng._model_xy(c0, r0, w, h)
    ex = model.project(np.column_stack([mx.ravel(), my.ravel(), z.ravel()]))
    d = np.abs(np.column_stack([col.ravel(), row.ravel()]) - ex)
    assert np.nanmax(d) < PROJECTION_TOLERANCE_PX
    # a flat DEM takes the single-height path and is exact
    col1, row1 = eng._project(c0, r0, w, h, np.full((h, w), 120.0))
    ex1 = model.project(np.column_stack([mx.ravel(), my.ravel(), np.full(mx.size, 120.0)]))
    assert np.abs(col1.ravel() - ex1[:, 0]).max() < PROJECTION_TOLERANCE_PX


def test_dem_undulation_and_geoid(tmp_path):
    from rectify.raster.dem import geoid_undulation

    write_dem(tmp_path / "dem.tif", hills)
    plain = Dem.from_path(tmp_path / "dem.tif")
    shifted = Dem.from_path(tmp_path / "dem.tif", undulation=32.5)
    pts = np.array([[E0 + 10.3, N0 - 40.7], [E0 - 100.0, N0 + 3.0]])
    assert np.allclose(shifted.sample(pts) - plain.sample(pts), 32.5)
    # bilinear between cell centres: the DEM is sampled exactly at a centre
    assert abs(plain.sample([[E0 - 300 + 1.0, N0 + 300 - 1.0]])[0] - hills(E0 - 299.0, N0 + 299.0)) < 1e-3
    assert np.isnan(plain.sample([[E0 + 5000, N0]])[0])  # outside: NaN
    with pytest.raises(InvalidInputError, match="undulation"):
        Dem.from_path(tmp_path / "dem.tif", undulation=float("nan"))
    try:
        n = geoid_undulation([[9.0, 45.0]], "EPSG:5773")
    except CRSError as err:  # no grid installed: the message says what to do
        assert "constant undulation" in str(err)
    else:
        assert 30 < n[0] < 60  # EGM96 near 9 E, 45 N is about 47 m
