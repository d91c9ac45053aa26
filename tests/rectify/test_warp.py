"""rectify.raster.warp: the tiled resampling engine and GCP georectification."""

from importlib.resources import files
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
import rasterio.enums
import rasterio.transform
import rasterio.warp
from affine import Affine
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError, RasterIOError
from rectify.geometry.points import GcpTable
from rectify.raster.georectify import georectify, rectify_with_transform
from rectify.raster.georef import Grid, pixel_from_world, world_from_pixel
from rectify.raster.io import read_window, write_raster
from rectify.raster.warp import WarpOptions, warp_array, warp_raster
from tests.support.rectify_support import cog_problems, tiff_ifds

LANDSAT = Path(str(files("rectify") / "data" / "RGB.byte.tif"))
H_TILT = np.array([[0.9, 0.15, 40.0], [-0.1, 0.95, 60.0], [2e-4, 1e-4, 1.0]])  # landsat px -> frame px


def _tilted_frame(tmp_path):
    """The Landsat scene seen through a known homography, written without CRS, plus exact GCPs."""
    with rasterio.open(LANDSAT) as ds:
        T = ds.transform
    img, valid = read_window(LANDSAT, 0, 0, 791, 718)
    hinv = np.linalg.inv(H_TILT)
    frame = warp_array(img, hinv, (800, 900))
    fv = warp_array(valid.astype(np.uint8) * 255, hinv, (800, 900), resampling="nearest") > 0
    frame[~fv] = 0
    path = tmp_path / "tilted.tif"
    write_raster(path, frame, Affine.translation(0, 0) * Affine.scale(1, 1.0000001), None, nodata=0)
    rng = np.random.default_rng(3)
    pts = []
    while len(pts) < 10:
        p = rng.uniform([60, 60], [840, 740])
        if fv[int(p[1]), int(p[0])]:
            pts.append(p)
    pts = np.array(pts)
    h = np.c_[pts, np.ones(len(pts))] @ hinv.T
    lp = h[:, :2] / h[:, 2:]  # landsat pixels; their world coordinates by rasterio, not by the code under test
    tgt = np.column_stack(rasterio.transform.xy(T, lp[:, 1], lp[:, 0], offset="center"))
    g = GcpTable(tuple(f"g{i}" for i in range(len(pts))), pts, tgt, None, np.zeros(len(pts), bool), "EPSG:32618")
    return path, g, T


@pytest.mark.parametrize("method", ["homography", "cotangent"])
def test_landsat_round_trip(tmp_path, method):
    src, gcps, T = _tilted_frame(tmp_path)
    out = tmp_path / "rect.tif"
    r = georectify(src, out, gcps, method=method, resolution=300.0,
                   options=WarpOptions(resampling="bilinear", tile_px=256))
    assert r.fit.table.summary()["rmse"] < 1e-6
    # 1) geometry: output pixel -> (model) frame pixel -> truth landsat pixel vs the direct world -> landsat
    g = r.warp.grid
    rng = np.random.default_rng(0)
    op = rng.uniform(0, [g.width - 1, g.height - 1], (500, 2))
    world = world_from_pixel(g.transform, op)
    frame = r.fit.model.model.inverse(world - r.fit.model.offset) if hasattr(r.fit.model.model, "inverse") \
        else None
    hp = np.c_[frame, np.ones(len(frame))] @ np.linalg.inv(H_TILT).T
    assert_allclose(hp[:, :2] / hp[:, 2:], pixel_from_world(T, world), atol=1e-6)
    # 2) image: the rectified output vs the original resampled by GDAL onto the same grid
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32618
        assert ds.nodata == 0
        assert ds.transform == g.transform and ds.transform.a == 300.0
        assert ds.block_shapes[0] == (256, 256) and ds.compression is not None
        data = ds.read()
        ref = np.zeros_like(data)
        with rasterio.open(LANDSAT) as s:
            rasterio.warp.reproject(rasterio.band(s, [1, 2, 3]), ref, dst_transform=ds.transform,
                                    dst_crs=ds.crs, resampling=rasterio.enums.Resampling.bilinear,
                                    src_nodata=0, dst_nodata=0)
    m = (data > 0).all(0) & (ref > 0).all(0)
    m = cv2.erode(m.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert m.sum() > 200_000
    (dx, dy), resp = cv2.phaseCorrelate(data[0].astype(np.float32) * m, ref[0].astype(np.float32) * m)
    assert np.hypot(dx, dy) < 0.1, (dx, dy)
    diff = np.abs(data[:, m].astype(int) - ref[:, m])
    assert np.median(diff) <= 2 and diff.mean() < 10  # two bilinear resamplings blur a noisy scene
    # interior valid, outside footprint nodata
    assert (data[:, 0, 0] == 0).all()


_TRANSFORM = Affine(2, 0, 100, 0, -2, 500)


def _write(tmp_path, name, arr, *, nodata=None, transform=_TRANSFORM, crs="EPSG:32618"):
    p = tmp_path / name
    write_raster(p, arr, transform, crs, nodata=nodata)
    return p


class _Shift:
    """world -> source pixel for the grid of `_write`, shifted by (dx, dy) source pixels."""

    def __init__(self, t, dx=0.0, dy=0.0, matrix=True):
        self.t, self.d = t, np.array([dx, dy])
        if matrix:
            from rectify.raster.georef import pixel_from_world_matrix
            m = pixel_from_world_matrix(t)
            m[:2, 2] += self.d
            self.matrix = m

    def __call__(self, w):
        return pixel_from_world(self.t, w) + self.d


@pytest.mark.parametrize("dtype,bands,nodata", [("uint8", 1, None), ("uint16", 5, 0), ("float32", 2, None),
                                                ("int16", 3, -9999)])
@pytest.mark.parametrize("resampling", ["nearest", "bilinear", "cubic", "lanczos"])
def test_identity_keeps_values_dtype_and_nodata(tmp_path, dtype, bands, nodata, resampling):
    rng = np.random.default_rng(1)
    a = (rng.uniform(1, 200, (40, 37, bands))).astype(dtype)
    t = Affine(2, 0, 100, 0, -2, 500)
    src = _write(tmp_path, "a.tif", a, nodata=nodata, transform=t)
    grid = Grid(37, 40, t, "EPSG:32618")
    out = tmp_path / "o.tif"
    r = warp_raster(src, out, _Shift(t), grid, options=WarpOptions(resampling=resampling, tile_px=16))
    with rasterio.open(out) as ds:
        b = np.moveaxis(ds.read(), 0, -1)
        assert ds.dtypes[0] == dtype and ds.count == bands
        expected_nd = nodata if nodata is not None else (None if dtype != "float32" else ds.nodata)
        if expected_nd is not None and not np.isnan(expected_nd):
            assert ds.nodata == nodata
    assert_allclose(b.astype(float), a.astype(float), atol=1e-3 if dtype == "float32" else 0)
    assert r.n_tiles == 9


def test_shift_footprint_masks_and_tiles_agree(tmp_path):
    """Half-image shift: outside-footprint pixels are masked; tiling and threads do not change results."""
    rng = np.random.default_rng(2)
    a = rng.integers(1, 255, (50, 60, 3), dtype=np.uint8)
    t = Affine(2, 0, 100, 0, -2, 500)
    src = _write(tmp_path, "a.tif", a, transform=t)  # uint8 without nodata -> internal mask
    grid = Grid(60, 50, t, "EPSG:32618")
    outs = []
    for i, (tile, thr, mat) in enumerate([(16, 1, True), (512, 2, True), (32, 2, False)]):
        out = tmp_path / f"o{i}.tif"
        warp_raster(src, out, _Shift(t, 10.25, -3.5, matrix=mat), grid,
                    options=WarpOptions(tile_px=tile, threads=thr))
        with rasterio.open(out) as ds:
            outs.append((ds.read(), ds.dataset_mask()))
    data, mask = outs[0]
    # output col c takes source col c + 10.25: valid up to c + 10.25 <= 59.5
    assert mask[10, :49].all() and not mask[10, 50:].any()
    assert not mask[:3, :].any() and mask[4:, 0].all()
    # interior values: bilinear between columns
    expect = 0.75 * a[20, 11, 0].astype(float) + 0.25 * a[20, 12, 0] if False else None
    src_r, src_c = 20 - 3.5, 5 + 10.25
    r0, c0 = int(np.floor(src_r)), int(np.floor(src_c))
    fr, fc = src_r - r0, src_c - c0
    expect = ((1 - fr) * (1 - fc) * a[r0, c0, 0] + (1 - fr) * fc * a[r0, c0 + 1, 0]
              + fr * (1 - fc) * a[r0 + 1, c0, 0] + fr * fc * a[r0 + 1, c0 + 1, 0])
    assert abs(int(data[0, 20, 5]) - expect) <= 1
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])
    # sparse-grid mapping agrees with the analytic one (affine: exact interpolation)
    assert np.abs(outs[2][0].astype(int) - data).max() <= 1
    assert np.array_equal(outs[2][1], mask)


def test_float_nan_nodata_and_renormalised_edges(tmp_path):
    a = np.full((30, 30, 1), 7.0, np.float32)
    a[10:20, 10:20] = np.nan
    t = Affine(1, 0, 0, 0, -1, 30)
    src = _write(tmp_path, "f.tif", a, nodata=float("nan"), transform=t)
    out = tmp_path / "o.tif"
    warp_raster(src, out, _Shift(t, 0.4, 0.3), Grid(30, 30, t, "EPSG:32618"))
    with rasterio.open(out) as ds:
        b = ds.read(1)
        assert np.isnan(ds.nodata)
    ok = ~np.isnan(b)
    assert_allclose(b[ok], 7.0, atol=1e-4)  # no blending with the NaN hole
    assert np.isnan(b[14, 14]) and ok[5, 5]


def test_wider_than_opencv_limit(tmp_path):
    w = 33000
    a = np.tile((np.arange(w) % 251).astype(np.uint8), (24, 1))[:, :, None]
    t = Affine(1, 0, 0, 0, -1, 24)
    src = _write(tmp_path, "wide.tif", a, transform=t, nodata=None)
    out = tmp_path / "o.tif"
    r = warp_raster(src, out, _Shift(t, 1.0, 0.0), Grid(w, 24, t, "EPSG:32618"),
                    options=WarpOptions(resampling="nearest"))
    with rasterio.open(out) as ds:
        b = ds.read(1)
    assert ds.width == w and r.n_tiles == 65
    assert np.array_equal(b[5, :-1], a[5, 1:, 0])


def test_cog_layout(tmp_path):
    rng = np.random.default_rng(5)
    a = rng.integers(1, 255, (700, 900, 3), dtype=np.uint8)
    t = Affine(1, 0, 0, 0, -1, 700)
    src = _write(tmp_path, "a.tif", a, transform=t, nodata=0)
    out = tmp_path / "cog.tif"
    warp_raster(src, out, _Shift(t, 0.5, 0.5), Grid(900, 700, t, "EPSG:32618"),
                options=WarpOptions(cog=True, tile_px=256))
    ifds = tiff_ifds(out)
    assert len(ifds) >= 2 and all(d.tiled for d in ifds)
    assert cog_problems(out) == []
    with rasterio.open(out) as ds:
        assert ds.overviews(1) and ds.crs.to_epsg() == 32618 and ds.nodata == 0
    # a plain tiled file without overviews is not a COG: the check can fail
    plain = tmp_path / "plain.tif"
    warp_raster(src, plain, _Shift(t), Grid(900, 700, t, "EPSG:32618"))
    assert any("overview" in p for p in cog_problems(plain))
    assert not list(tmp_path.glob(".*part*"))


def test_bad_outputs_leave_nothing(tmp_path):
    a = np.ones((20, 20, 1), np.uint8)
    t = Affine(1, 0, 0, 0, -1, 20)
    src = _write(tmp_path, "a.tif", a, transform=t)
    g = Grid(20, 20, t, "EPSG:32618")
    out = tmp_path / "o.tif"
    out.write_bytes(b"keep")
    with pytest.raises(InvalidInputError, match="exists"):
        warp_raster(src, out, _Shift(t), g)
    assert out.read_bytes() == b"keep"
    with pytest.raises(InvalidInputError, match="is the input"):
        warp_raster(src, src, _Shift(t), g, overwrite=True)
    with pytest.raises(RasterIOError, match="does not exist"):
        warp_raster(src, tmp_path / "nope" / "o.tif", _Shift(t), g)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage" * 10)
    with pytest.raises(RasterIOError):
        warp_raster(bad, tmp_path / "o2.tif", _Shift(t), g)
    assert not (tmp_path / "o2.tif").exists()

    class Boom(_Shift):
        def __call__(self, w):
            raise EstimationError("boom")

    with pytest.raises(InvalidInputError, match="boom"):
        warp_raster(src, tmp_path / "o3.tif", Boom(t, matrix=False), g)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tif", "bad.tif", "o.tif"]
    with pytest.raises(InvalidInputError, match="resampling"):
        WarpOptions(resampling="magic")


def test_progress_and_gcp_errors(tmp_path):
    src, gcps, _ = _tilted_frame(tmp_path)
    calls = []
    georectify(src, tmp_path / "o.tif", gcps, method="affine", resolution=600.0,
               progress=lambda d, n: calls.append((d, n)))
    assert calls[0][0] == 0 and calls[-1][0] == calls[-1][1] > 0
    few = gcps.subset(np.arange(len(gcps)) < 3)
    with pytest.raises(EstimationError, match="too few"):
        georectify(src, tmp_path / "x.tif", few, method="homography")
    # GCPs outside the image are used (as by 'rectify fit') and named in a note
    outside = GcpTable(gcps.ids, gcps.pixel + [0, 2000], gcps.target, None, gcps.check, gcps.crs)
    r = georectify(src, tmp_path / "outside.tif", outside, method="affine", resolution=600.0)
    assert len(r.notes) == 1 and "outside" in r.notes[0] and repr(gcps.ids[0]) in r.notes[0]
    (tmp_path / "outside.tif").unlink()
    line = GcpTable(gcps.ids[:5], np.c_[np.arange(5) * 10.0, np.arange(5) * 10.0],
                    np.c_[np.arange(5) * 3e3, np.arange(5) * 3e3], None, np.zeros(5, bool), "EPSG:32618")
    with pytest.raises(EstimationError):
        georectify(src, tmp_path / "x.tif", line)
    assert not (tmp_path / "x.tif").exists()


class _MatrixModel:
    """A bare source -> target homography (no validation), for the transform path."""

    def __init__(self, m):
        self.matrix = np.asarray(m, dtype=np.float64)

    def __call__(self, p):
        h = np.c_[np.asarray(p), np.ones(len(p))] @ self.matrix.T
        return h[:, :2] / h[:, 2:]

    @property
    def inverse(self):
        return _MatrixModel(np.linalg.inv(self.matrix))


def test_residual_units_follow_the_output_crs(tmp_path):
    """Residuals of a fit into geographic coordinates are in degrees, not labelled metres (issue 11)."""
    src, gcps, _ = _tilted_frame(tmp_path)
    r = georectify(src, tmp_path / "geo.tif", gcps, method="homography", dst_crs="EPSG:4326",
                   options=WarpOptions(resampling="nearest"))
    assert r.fit.table.units == "degree"
    assert "degree" in r.fit.table.summary_line() and " m" not in r.fit.table.summary_line()
    r_utm = georectify(src, tmp_path / "utm.tif", gcps, method="homography", resolution=600.0)
    assert r_utm.fit.table.units == "m"


def test_dst_crs_through_pyproj(tmp_path):
    """GCPs in UTM, output in geographic degrees: a known landmark lands at its lon/lat."""
    from rectify.geometry.crs import transform_xy

    src, gcps, T = _tilted_frame(tmp_path)
    out = tmp_path / "geo.tif"
    r = georectify(src, out, gcps, method="homography", dst_crs="EPSG:4326",
                   options=WarpOptions(resampling="nearest"))
    assert r.crs == "EPSG:4326"
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 4326 and ds.transform.e < 0
    # transform JSON path: same model in UTM, output in EPSG:4326 via pyproj per pixel
    r_utm = georectify(src, tmp_path / "utm.tif", gcps, method="homography", resolution=600.0)
    model = _MatrixModel(r_utm.fit.model.matrix)
    r2 = rectify_with_transform(src, tmp_path / "geo2.tif", model, model_crs="EPSG:32618", dst_crs="EPSG:4326",
                                resolution=r.warp.grid.resolution[0])
    ll = transform_xy("EPSG:32618", "EPSG:4326", gcps.target[:1])
    g2 = r2.warp.grid
    px = pixel_from_world(g2.transform, ll)[0]
    with rasterio.open(tmp_path / "geo2.tif") as ds2:
        assert ds2.crs.to_epsg() == 4326
    assert 0 <= px[0] < g2.width and 0 <= px[1] < g2.height
    # the landmark's lon/lat by pyproj directly, its output pixel by rasterio's inverse geotransform
    import pyproj

    lon, lat = pyproj.Transformer.from_crs(32618, 4326, always_xy=True).transform(*gcps.target[0])
    assert_allclose(ll[0], [lon, lat], rtol=0, atol=1e-9)
    col, row = ~g2.transform * (lon, lat)
    assert_allclose(px, [col - 0.5, row - 0.5], atol=1e-6)
    # value: the nearest-resampled output pixel holding the landmark equals the frame pixel that its centre
    # maps to (centre lon/lat by rasterio, frame pixel by the model fitted in lon/lat, shifted by its offset)
    with rasterio.open(out) as ds, rasterio.open(src) as fr:
        r0, c0 = ds.index(lon, lat)
        clon, clat = ds.xy(r0, c0)
        q = r.fit.model.model.inverse(np.array([[clon, clat]]) - r.fit.model.offset)[0]
        assert np.hypot(*(q - gcps.pixel[0])) < 2.0  # within the output pixel (about 1.3 frame px)
        frame = fr.read()
        assert (ds.read()[:, r0, c0] == frame[:, int(round(q[1])), int(round(q[0]))]).all()


def test_block_cache_grows_with_the_threads_and_bad_sizes_are_refused():
    from rectify.errors import InvalidInputError
    from rectify.raster.warp import CACHE_MB_PER_THREAD, WarpOptions

    assert WarpOptions(threads=1).block_cache_mb == CACHE_MB_PER_THREAD
    assert WarpOptions(threads=3).block_cache_mb == 3 * CACHE_MB_PER_THREAD
    assert WarpOptions(threads=3, cache_mb=100).block_cache_mb == 100
    for bad in (0, -5, float("nan")):
        with pytest.raises(InvalidInputError, match="cache_mb must be >= 1"):
            WarpOptions(cache_mb=bad)
