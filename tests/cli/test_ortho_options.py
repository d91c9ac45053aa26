"""``rectify ortho`` output options and ``--dem-height`` end to end on tiny files (issue 27).

JPEG-in-TIFF (YCbCr, internal mask, no nodata value) and COG (internal overviews) open in rasterio
with what they promise; ``--dem-height H`` writes the pixels a flat DEM file of height H gives; bad
combinations fail in one line, exit non-zero and leave nothing behind.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.geometry.crs import transform_xy
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.rpc import RPC

CRS = "EPSG:32632"
E0, N0 = 500_000.0, 5_000_000.0


def _dem(path, z):
    n = 120
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=CRS,
                       transform=Affine(4.0, 0, E0 - 240, 0, -4.0, N0 + 240)) as ds:
        ds.write(np.broadcast_to(np.asarray(z, np.float32), (n, n)), 1)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("ortho_options")
    yy, xx = np.mgrid[0:120, 0:120]
    _dem(d / "dem.tif", 100 + 10 * np.sin(xx / 9.0) + 0.2 * yy)
    _dem(d / "flat.tif", 104.25)
    w, h = 96, 72
    rr, cc = np.mgrid[0:h, 0:w]
    rgb = np.stack([100 + 80 * np.sin(cc / 3.0) * np.cos(rr / 4.0), 120 + 60 * np.sin((cc + rr) / 5.0),
                    90 + 40 * np.cos(cc / 6.0)]).astype(np.uint8)
    with rasterio.open(d / "rgb.tif", "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8") as ds:
        ds.write(rgb)
    with rasterio.open(d / "float.tif", "w", driver="GTiff", width=w, height=h, count=1, dtype="float32") as ds:
        ds.write(rgb[:1].astype(np.float32))
    (d / "cam.json").write_text(json.dumps({"focal_length_mm": 10.0, "pixel_size_mm": 0.02, "width": w,
                                            "height": h}))
    R = matrix_from_angles(0.03, -0.02, 0.2)
    (d / "eo.json").write_text(json.dumps({"position": [E0, N0, 600.0], "rotation": R.tolist(), "crs": CRS}))
    return d


def _run(d, out, *extra, src="rgb.tif", dem=("--dem", "dem.tif")):
    args = ["ortho", str(d / src), "--camera", str(d / "cam.json"), "--exterior", str(d / "eo.json"),
            "-o", str(out), "--resolution", "2", "--no-stac"]
    dem_args = [dem[0], str(d / dem[1]) if dem[0] == "--dem" else dem[1]] if dem else []
    return CliRunner().invoke(cli, args + dem_args + list(extra))


def test_jpeg_cog_has_ycbcr_mask_and_overviews(scene, tmp_path):
    r = _run(scene, tmp_path / "lossless.tif", "--resolution", "0.1")
    assert r.exit_code == 0, r.output
    r = _run(scene, tmp_path / "j.tif", "--resolution", "0.1", "--compress", "jpeg", "--cog", "--jpeg-quality", "90")
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "j.tif") as j, rasterio.open(tmp_path / "lossless.tif") as ref:
        st = j.tags(ns="IMAGE_STRUCTURE")
        assert j.compression.value.upper() == "JPEG" and st.get("COMPRESSION") == "YCbCr JPEG"
        assert st.get("LAYOUT") == "COG" and j.overviews(1)  # internal overviews
        assert j.nodata is None and all(f == [rasterio.enums.MaskFlags.per_dataset] for f in j.mask_flag_enums)
        m = j.dataset_mask() > 0
        valid = ref.dataset_mask() > 0
        assert m.any() and (~m).any()
        np.testing.assert_array_equal(m, valid)  # the mask is the lossless file's nodata area, exactly
        a, b = j.read().astype(float), ref.read().astype(float)
        assert np.abs(a - b)[:, valid].mean() < 6.0  # lossy, but the same picture
        assert j.overviews(1)[0] == 2 and j.read_masks(1, out_shape=(m.shape[0] // 2, m.shape[1] // 2)).any()


def test_jpeg_plain_and_lossless_cog(scene, tmp_path):
    r = _run(scene, tmp_path / "j.tif", "--compress", "jpeg")
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "j.tif") as ds:
        assert ds.compression.value.upper() == "JPEG" and not ds.overviews(1) and ds.nodata is None
        assert (ds.dataset_mask() == 0).any()
    r = _run(scene, tmp_path / "c.tif", "--compress", "deflate", "--cog", "--resolution", "0.1")
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "c.tif") as ds:
        assert ds.compression.value.upper() == "DEFLATE" and ds.overviews(1) and ds.nodata == 0


def test_dem_height_equals_flat_dem(scene, tmp_path):
    r1 = _run(scene, tmp_path / "flat.tif", dem=("--dem", "flat.tif"))
    r2 = _run(scene, tmp_path / "const.tif", dem=("--dem-height", "104.25"))
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    assert "constant height 104.25 m" in r2.output
    with rasterio.open(tmp_path / "flat.tif") as a, rasterio.open(tmp_path / "const.tif") as b:
        assert a.transform == b.transform and a.shape == b.shape
        np.testing.assert_array_equal(a.read(), b.read())


def test_dem_height_rpc_equals_flat_dem(scene, tmp_path):
    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[E0, N0]])[0]
    m_lon, m_lat = 1.0 / (111_320 * np.cos(np.radians(lat0))), 1.0 / 111_320
    rpc = RPC.from_coefficients(offsets=(40.0, 40.0, lat0, lon0, 100.0),
                                scales=(40.0, 40.0, 80 * m_lat, 80 * m_lon, 50.0),
                                samp_num=[0.0, 1.0, 0.02, 0.1], line_num=[0.0, 0.02, -1.0, 0.03])
    img = (100 + 50 * np.sin(np.arange(80)[None, :] / 3.0) * np.cos(np.arange(80)[:, None] / 4.0)).astype(np.uint8)
    with rasterio.open(tmp_path / "sat.tif", "w", driver="GTiff", width=80, height=80, count=1, dtype="uint8",
                       rpcs=rpc.to_rasterio()) as ds:
        ds.write(img[None])
    runs = []
    for dem in (["--dem", str(scene / "flat.tif")], ["--dem-height", "104.25"]):
        out = tmp_path / f"o{len(runs)}.tif"
        r = CliRunner().invoke(cli, ["ortho", str(tmp_path / "sat.tif"), "--rpc", "-o", str(out), "--resolution", "1",
                                     "--dst-crs", CRS, "--no-stac", *dem])
        assert r.exit_code == 0, r.output
        runs.append(out)
    with rasterio.open(runs[0]) as a, rasterio.open(runs[1]) as b:
        assert a.transform == b.transform and a.shape == b.shape
        x, y = a.read().astype(int), b.read().astype(int)
        assert (x > 0).sum() > 1000
        assert np.abs(x - y).max() <= 1 and (x != y).mean() < 0.001  # the same heights to rounding (1e-13 m)


@pytest.mark.parametrize("extra, dem, src, message", [
    ((), None, "rgb.tif", "give a DEM (--dem DEM.tif) or a constant ground height"),
    (("--dem-height", "100"), ("--dem", "dem.tif"), "rgb.tif", "not both"),
    ((), ("--dem-height", "nan"), "rgb.tif", "--dem-height must be a finite number"),
    ((), ("--dem-height", "inf"), "rgb.tif", "--dem-height must be a finite number"),
    (("--undulation", "30"), ("--dem-height", "100"), "rgb.tif", "already in the model's heights"),
    (("--compress", "jpeg"), ("--dem", "dem.tif"), "float.tif", "needs an 8-bit (uint8) output; this one is float32"),
    (("--compress", "jpeg", "--true-ortho"), ("--dem", "dem.tif"), "rgb.tif", "visibility band"),
    (("--compress", "jpeg", "--jpeg-quality", "0"), ("--dem", "dem.tif"), "rgb.tif", "quality must be an integer"),
])
def test_bad_options_one_line_nothing_written(scene, tmp_path, extra, dem, src, message):
    out = tmp_path / "out" / "o.tif"
    out.parent.mkdir()
    r = _run(scene, out, *extra, src=src, dem=dem)
    assert r.exit_code != 0
    lines = [ln for ln in r.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and message in lines[0], r.output
    assert "Traceback" not in r.output
    assert list(out.parent.iterdir()) == []
