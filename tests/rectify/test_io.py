"""Windowed raster reading on tiny GeoTIFFs made in tmp_path."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.raster.io import iter_windows, raster_info, read_overview, read_window, to_uint8, write_raster


@pytest.fixture()
def tif(tmp_path):
    p = tmp_path / "a.tif"
    data = np.arange(3 * 40 * 60, dtype=np.uint16).reshape(3, 40, 60)
    data[:, :5, :] = 0  # nodata rows
    with rasterio.open(p, "w", driver="GTiff", width=60, height=40, count=3, dtype="uint16", nodata=0,
                       crs="EPSG:32618", transform=from_origin(1000, 2000, 10, 10)) as ds:
        ds.write(data)
    return p, data


def test_info_and_window(tif):
    p, data = tif
    info = raster_info(p)
    assert (info.width, info.height, info.count, info.crs) == (60, 40, 3, "EPSG:32618")
    d, v = read_window(p, 10, 3, 20, 8)
    assert d.shape == (8, 20, 3)
    np.testing.assert_array_equal(d[..., 1], data[1, 3:11, 10:30])
    assert not v[:2].any() and v[2:].all()


def test_window_outside_is_invalid(tif):
    p, _ = tif
    d, v = read_window(p, 50, 30, 20, 20)
    assert d.shape == (20, 20, 3)
    assert v[:10, :10].all() and not v[10:, :].any() and not v[:, 10:].any()


def test_overview(tif):
    p, data = tif
    d, v, s = read_overview(p, 30)
    assert max(d.shape[:2]) == 30 and s == pytest.approx(2.0)
    # values: each overview pixel holds one of the 2 x 2 source pixels it covers (bands kept together)
    src = data.transpose(1, 2, 0)
    cand = np.stack([src[a::2, b::2] for a in (0, 1) for b in (0, 1)])  # (4, 20, 30, 3)
    hit = (cand == d[None]).all(axis=-1).any(axis=0)
    assert hit[3:].all()
    assert not v[:2].any() and v[3:].all()  # source rows 0-4 are nodata


def test_errors(tif, tmp_path):
    p, _ = tif
    with pytest.raises(RasterIOError, match="not found"):
        raster_info(tmp_path / "none.tif")
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage")
    with pytest.raises(RasterIOError, match="cannot read raster"):
        raster_info(bad)
    with pytest.raises(InvalidInputError, match="band"):
        read_window(p, 0, 0, 5, 5, bands=[4])
    with pytest.raises(InvalidInputError, match="positive"):
        read_window(p, 0, 0, 0, 5)


def test_iter_windows_cover_once():
    cover = np.zeros((70, 95), int)
    for c, r, w, h in iter_windows(95, 70, 32, 0):
        cover[r:r + h, c:c + w] += 1
    assert (cover == 1).all()
    for c, r, w, h in iter_windows(95, 70, 32, 8):
        assert c >= 0 and r >= 0 and c + w <= 95 and r + h <= 70


def test_to_uint8_stretch():
    a = np.linspace(0, 4000, 100, dtype=np.float32).reshape(10, 10)
    v = np.ones((10, 10), bool)
    v[0, 0] = False
    u = to_uint8(a, v)
    assert u.dtype == np.uint8 and u[0, 0] == 0 and u.max() == 255
    assert to_uint8(np.zeros((4, 4))).max() == 0
    with pytest.raises(InvalidInputError):
        to_uint8(np.zeros((2, 2, 2, 2)))


TOPOCENTRIC = ('PROJCRS["Topocentric ENU",BASEGEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",'
               '6378137,298.257223563,LENGTHUNIT["metre",1]]],PRIMEM["Greenwich",0,ANGLEUNIT["degree",'
               '0.0174532925199433]]],CONVERSION["Topocentric",METHOD["Geographic/topocentric conversions",'
               'ID["EPSG",9837]],PARAMETER["Latitude of topocentric origin",45,ANGLEUNIT["degree",0.0174532925199433],'
               'ID["EPSG",8834]],PARAMETER["Longitude of topocentric origin",15,ANGLEUNIT["degree",'
               '0.0174532925199433],ID["EPSG",8835]],PARAMETER["Ellipsoidal height of topocentric origin",0,'
               'LENGTHUNIT["metre",1],ID["EPSG",8836]]],CS[Cartesian,3],AXIS["(E)",east,ORDER[1],LENGTHUNIT["metre",'
               '1]],AXIS["(N)",north,ORDER[2],LENGTHUNIT["metre",1]],AXIS["(U)",up,ORDER[3],LENGTHUNIT["metre",1]]]')


def test_a_crs_geotiff_cannot_record_is_refused_not_lost(tmp_path):
    """GDAL keeps a CRS that GeoTIFF keys cannot express in a sidecar named after the temporary file, so the
    renamed output had no CRS: now one CRSError naming the output, and nothing left (no file, no sidecar)."""
    a = np.zeros((8, 8), np.float32)
    with pytest.raises(CRSError, match=r"cannot write '.*/a\.tif': a GeoTIFF cannot record its CRS") as info:
        write_raster(tmp_path / "a.tif", a, from_origin(0, 16, 2, 2), TOPOCENTRIC)
    assert "\n" not in str(info.value) and sorted(p.name for p in tmp_path.iterdir()) == []
    write_raster(tmp_path / "b.tif", a, from_origin(0, 16, 2, 2), "EPSG:32633+5773")   # compound: recorded
    with rasterio.open(tmp_path / "b.tif") as ds:
        assert ds.crs is not None
