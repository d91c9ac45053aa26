"""``rectify demo`` end to end (embedded data, ~3 s)."""

import re

import rasterio
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.io import raster_info


def test_demo(tmp_path):
    out = tmp_path / "demo"
    r = CliRunner().invoke(cli, ["demo", "--out", str(out)])
    assert r.exit_code == 0, r.output
    m = re.search(r"geolocation RMSE against the truth: ([\d.]+) m = ([\d.]+) Landsat px", r.output)
    assert m and float(m.group(2)) < 0.5  # 0.15 px picking noise on 12 GCPs
    assert "12 control, 4 check points" in r.output
    for name in ("tilted_frame.tif", "gcps.csv", "rectified.tif", "report/report.html", "report/report.json"):
        assert (out / name).is_file(), name
    info = raster_info(out / "rectified.tif")
    assert info.crs == "EPSG:32618" and info.nodata == 0
    with rasterio.open(out / "tilted_frame.tif") as ds:
        assert ds.crs is None
    # a second run refuses to replace outputs
    r2 = CliRunner().invoke(cli, ["demo", "--out", str(out)])
    assert r2.exit_code != 0 and "exists" in r2.output
    r3 = CliRunner().invoke(cli, ["demo", "--out", str(out), "--overwrite"])
    assert r3.exit_code == 0, r3.output
