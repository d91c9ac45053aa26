"""``rectify warp`` end to end on tiny GeoTIFFs."""


import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.raster.io import write_raster
from tests.support.rectify_support import cog_problems

T = Affine(30.0, 0.0, 500000.0, 0.0, -30.0, 4400000.0)


@pytest.fixture()
def scene(tmp_path):
    """A 64 x 48 RGB raster (no CRS, as a raw frame) and GCPs from a known affine to UTM 18N."""
    rr, cc = np.mgrid[0:48, 0:64]
    img = np.stack([10 + 2 * cc + 2 * rr + 10 * k for k in range(3)], axis=-1).astype(np.uint8)  # smooth
    src = tmp_path / "frame.tif"
    write_raster(src, img, Affine(1, 0, 0, 0, 1.0000001, 0), None, nodata=0)
    A = np.array([[29.0, 6.0, 500100.0], [5.0, -31.0, 4399900.0]])
    pix = np.array([[2, 3], [60, 4], [5, 44], [58, 45], [30, 20], [12, 30], [45, 12]], float)
    tgt = pix @ A[:, :2].T + A[:, 2]
    lines = ["# crs=EPSG:32618", "id,col,row,x,y"] + [f"p{i},{c},{r},{float(x)!r},{float(y)!r}" for i, ((c, r), (x, y))
                                                        in enumerate(zip(pix, tgt, strict=True))]
    gcps = tmp_path / "gcps.csv"
    gcps.write_text("\n".join(lines) + "\n")
    return tmp_path, src, gcps, A


def _files(d):
    return sorted(p.name for p in d.iterdir())


def test_warp_gcps_report_and_cog(scene):
    d, src, gcps, A = scene
    out = d / "out.tif"
    r = CliRunner().invoke(cli, ["warp", str(src), str(out), "--gcps", str(gcps), "--method", "affine",
                                 "--resolution", "30", "--report", str(d / "rep"), "--cog"])
    assert r.exit_code == 0, r.output
    assert "7 fit points, RMSE" in r.output and "sigma0" in r.output
    assert (d / "rep" / "report.html").is_file()
    assert list((d / "rep").glob("*.csv"))
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32618 and ds.nodata == 0 and ds.transform.a == 30.0
        # the GCP p4 (col 30, row 20) lands on its map coordinate
        x, y = A[:, :2] @ [30, 20] + A[:, 2]
        row, col = ds.index(x, y)
        src_val = rasterio.open(src).read()[:, 20, 30]
        assert np.abs(ds.read()[:, row, col].astype(int) - src_val).max() <= 3
    assert cog_problems(out) == []
    # rerun without --overwrite: refused, the output is untouched
    before = out.read_bytes()
    r = CliRunner().invoke(cli, ["warp", str(src), str(out), "--gcps", str(gcps)])
    assert r.exit_code != 0 and "exists" in r.output
    assert out.read_bytes() == before
    r = CliRunner().invoke(cli, ["warp", str(src), str(out), "--gcps", str(gcps), "--overwrite",
                                 "--dst-crs", "EPSG:4326", "--resampling", "cubic"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 4326


def test_warp_transform_json(scene):
    d, src, gcps, A = scene
    from rectify.formats.transform import write_transform
    from rectify.geometry.transforms import AffineTransform

    # small coordinates keep the matrix well scaled
    m = np.vstack([A, [0, 0, 1]])
    m[0, 2], m[1, 2] = 1000.0, 2000.0
    write_transform(d / "t.json", AffineTransform(m), crs="EPSG:32618")
    out = d / "o.tif"
    r = CliRunner().invoke(cli, ["warp", str(src), str(out), "--transform", str(d / "t.json"), "--threads", "1"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32618
        left, bottom, right, top = ds.bounds
        assert left <= 1000 - 0.5 * 29 and top >= 2000


@pytest.mark.parametrize("case,msg", [
    ("few", "too few"), ("collinear", "collinear|degenerate|rank"),
    ("crs", "unknown CRS"), ("dir", "does not exist"), ("corrupt", "cannot read"), ("both", "exactly one"),
    ("none", "exactly one"), ("nocrs", "needs the GCP CRS")])
def test_warp_bad_input(scene, case, msg):
    d, src, gcps, A = scene
    out = d / "bad.tif"
    args = ["warp", str(src), str(out), "--gcps", str(gcps)]
    lines = gcps.read_text().splitlines()
    if case == "few":
        gcps.write_text("\n".join(lines[:4]) + "\n")
        args += ["--method", "homography"]
    elif case == "collinear":
        rows = ["# crs=EPSG:32618", "id,col,row,x,y"] + [f"c{i},{i * 5},{i * 5},{500000 + i * 100},"
                                                         f"{4400000 - i * 100}" for i in range(6)]
        gcps.write_text("\n".join(rows) + "\n")
    elif case == "crs":
        args += ["--dst-crs", "EPSG:99999999"]
    elif case == "dir":
        args[2] = str(d / "missing" / "o.tif")
    elif case == "corrupt":
        (d / "c.tif").write_bytes(b"II*\x00" + b"\x00" * 100)
        args[1] = str(d / "c.tif")
    elif case == "both":
        args += ["--transform", str(gcps)]
    elif case == "none":
        args = args[:3]
    elif case == "nocrs":
        gcps.write_text("\n".join(lines[1:]) + "\n")
        args += ["--dst-crs", "EPSG:4326"]
    before = _files(d)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0
    import re
    assert re.search(msg, r.output), r.output
    assert _files(d) == before  # no partial output
    assert "Traceback" not in r.output
