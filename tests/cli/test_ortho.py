"""``rectify ortho`` and ``rectify mosaic`` end to end on tiny files (issue 16)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.rpc import RPC

CRS = "EPSG:32632"
E0, N0 = 500_000.0, 5_000_000.0


def _dem(path, crs=CRS):
    n = 100
    yy, xx = np.mgrid[0:n, 0:n]
    z = 100 + 10 * np.sin(xx / 9.0) + 0.2 * yy
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=crs,
                       transform=Affine(4.0, 0, E0 - 200, 0, -4.0, N0 + 200)) as ds:
        ds.write(z.astype("float32"), 1)


def _image(path, w, h, rpc=None):
    rr, cc = np.mgrid[0:h, 0:w]
    img = (100 + 50 * np.sin(cc / 3.0) * np.cos(rr / 4.0)).astype(np.uint8)
    kw = {"rpcs": rpc.to_rasterio()} if rpc is not None else {}
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="uint8", **kw) as ds:
        ds.write(img[None])


@pytest.fixture()
def frame(tmp_path):
    _dem(tmp_path / "dem.tif")
    _image(tmp_path / "img.tif", 80, 60)
    (tmp_path / "cam.json").write_text(json.dumps({"focal_length_mm": 10.0, "pixel_size_mm": 0.02, "width": 80,
                                                   "height": 60}))
    R = matrix_from_angles(0.03, -0.02, 0.2)
    (tmp_path / "eo.json").write_text(json.dumps({"position": [E0, N0, 600.0], "rotation": R.tolist(),
                                                  "crs": CRS}))
    return tmp_path


@pytest.fixture()
def rpc_scene(tmp_path):
    from rectify.geometry.crs import transform_xy
    from rectify.raster.dem import Dem

    _dem(tmp_path / "dem.tif")
    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[E0, N0]])[0]
    m_lon, m_lat = 1.0 / (111_320 * np.cos(np.radians(lat0))), 1.0 / 111_320
    rpc = RPC.from_coefficients(offsets=(40.0, 40.0, lat0, lon0, 100.0),
                                scales=(40.0, 40.0, 80 * m_lat, 80 * m_lon, 50.0),
                                samp_num=[0.0, 1.0, 0.02, 0.1], line_num=[0.0, 0.02, -1.0, 0.03])
    _image(tmp_path / "sat.tif", 80, 80, rpc)
    # GCPs: true ground of some pixels; the delivered RPC is off by (2.5, -1.5) px
    dem = Dem.from_path(tmp_path / "dem.tif")
    px = np.array([[10, 10], [70, 12], [15, 68], [66, 70], [40, 40], [25, 50]], float)
    g = rpc.localize_on_dem(px, dem.lonlat_function(), h_range=(50, 200))
    obs = px + [2.5, -1.5]
    lines = ["# crs=EPSG:4326", "id,col,row,x,y,z"] + [
        f"g{i},{c},{r},{x!r},{y!r},{z!r}" for i, ((c, r), (x, y, z)) in enumerate(zip(obs, g.tolist(), strict=True))]
    (tmp_path / "gcps.csv").write_text("\n".join(lines) + "\n")
    return tmp_path


def test_ortho_frame_cli(frame):
    d = frame
    r = CliRunner().invoke(cli, ["ortho", str(d / "img.tif"), "--dem", str(d / "dem.tif"), "--camera",
                                 str(d / "cam.json"), "--exterior", str(d / "eo.json"), "-o", str(d / "o.tif"),
                                 "--resolution", "2", "--true-ortho", "--cog"])
    assert r.exit_code == 0, r.output
    assert "FrameModel" in r.output and "relief displacement removed" in r.output and "true ortho" in r.output
    with rasterio.open(d / "o.tif") as ds:
        assert ds.count == 2 and ds.crs.to_epsg() == 32632 and ds.res == (2.0, 2.0) and ds.nodata == 0
        vis = ds.read(2)
        assert set(np.unique(vis)) <= {0, 1, 2} and (vis == 2).sum() > 100


def test_ortho_rpc_cli_with_gcps(rpc_scene):
    d = rpc_scene
    r = CliRunner().invoke(cli, ["ortho", str(d / "sat.tif"), "--dem", str(d / "dem.tif"), "--rpc", "-o",
                                 str(d / "o.tif"), "--gcps", str(d / "gcps.csv"), "--resolution", "2"])
    assert r.exit_code == 0, r.output
    assert "RPC refinement (shift): 6 fit points, RMSE" in r.output
    assert "GCP error of the RPC alone: RMSE 2.9" in r.output  # hypot(2.5, 1.5) = 2.92 px
    assert "RPCModel" in r.output and "EPSG:32632" in r.output
    # with an RPC file instead of the tags
    (d / "sat_RPC.TXT").write_text(RPC.from_dict(rasterio.open(d / "sat.tif").rpcs.to_dict()).to_rpc_txt())
    r = CliRunner().invoke(cli, ["ortho", str(d / "sat.tif"), "--dem", str(d / "dem.tif"), "--rpc",
                                 str(d / "sat_RPC.TXT"), "-o", str(d / "o2.tif"), "--resolution", "0.00002",
                                 "--dst-crs", "EPSG:4326"])  # degrees: about 2 m (2 degrees: one empty cell)
    assert r.exit_code == 0, r.output
    with rasterio.open(d / "o2.tif") as ds:
        assert ds.crs.to_epsg() == 4326


@pytest.mark.parametrize("args,msg", [
    (["--camera", "cam.json"], "needs both --camera"),
    (["--rpc", "--camera", "cam.json", "--exterior", "eo.json"], "either an RPC"),
    ([], "either an RPC"),
    (["--rpc"], "has no RPC"),
    (["--camera", "cam.json", "--exterior", "missing.json"], "file not found"),
    (["--camera", "cam.json", "--exterior", "eo.json", "--dem", "missing.tif"], "not found"),
    (["--camera", "cam.json", "--exterior", "eo.json", "--resolution", "-3"], "resolution"),
    (["--camera", "cam.json", "--exterior", "eo.json", "--dst-crs", "EPSG:99999999"], "unknown CRS"),
])
def test_ortho_cli_bad_input(frame, args, msg):
    d = frame
    before = sorted(p.name for p in d.iterdir())
    full = ["ortho", str(d / "img.tif"), "-o", str(d / "o.tif")]
    full += [str(d / a) if a.endswith((".json", ".tif")) else a for a in args]
    if "--dem" not in args:
        full += ["--dem", str(d / "dem.tif")]
    r = CliRunner().invoke(cli, full)
    assert r.exit_code == 1, r.output
    assert msg in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1
    assert sorted(p.name for p in d.iterdir()) == before  # nothing written, inputs untouched


def test_ortho_cli_refuses_existing_output(frame):
    d = frame
    (d / "o.tif").write_bytes(b"keep")
    r = CliRunner().invoke(cli, ["ortho", str(d / "img.tif"), "--dem", str(d / "dem.tif"), "--camera",
                                 str(d / "cam.json"), "--exterior", str(d / "eo.json"), "-o", str(d / "o.tif")])
    assert r.exit_code == 1 and "exists" in r.output
    assert (d / "o.tif").read_bytes() == b"keep"


def test_mosaic_cli(frame):
    d = frame
    for k, x in (("a", E0 - 20), ("b", E0 + 20)):
        eo = json.loads((d / "eo.json").read_text())
        eo["position"][0] = x
        (d / f"eo_{k}.json").write_text(json.dumps(eo))
        r = CliRunner().invoke(cli, ["ortho", str(d / "img.tif"), "--dem", str(d / "dem.tif"), "--camera",
                                     str(d / "cam.json"), "--exterior", str(d / f"eo_{k}.json"), "-o",
                                     str(d / f"{k}.tif"), "--resolution", "2"])
        assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["mosaic", str(d / "a.tif"), str(d / "b.tif"), "-o", str(d / "m.tif"), "--cog"])
    assert r.exit_code == 0, r.output
    assert "2 orthophotos" in r.output and "a.tif:" in r.output
    r = CliRunner().invoke(cli, ["mosaic", str(d / "a.tif"), str(d / "dem.tif"), "-o", str(d / "m2.tif")])
    assert r.exit_code == 1 and "one data type" in r.output and "Traceback" not in r.output
    assert not (d / "m2.tif").exists()
    r = CliRunner().invoke(cli, ["mosaic", str(d / "a.tif"), "-o", str(d / "a.tif"), "--overwrite"])
    assert r.exit_code == 1 and "is an input" in r.output


def test_ortho_cli_report(rpc_scene):
    d = rpc_scene
    r = CliRunner().invoke(cli, ["ortho", str(d / "sat.tif"), "--dem", str(d / "dem.tif"), "--rpc", "-o",
                                 str(d / "o.tif"), "--gcps", str(d / "gcps.csv"), "--resolution", "2",
                                 "--report", str(d / "rep")])
    assert r.exit_code == 0, r.output
    doc = json.loads((d / "rep" / "ortho_report.json").read_text())
    assert doc["gcp_residuals"]["n_fit"] == 6 and doc["dem"]["path"].endswith("dem.tif")
    assert doc["relief_shift_removed"]["max"] > 0
    with rasterio.open(d / "rep" / "relief_shift.tif") as ds:
        assert ds.crs.to_epsg() == 32632 and np.nanmax(ds.read(1)) > 0
    assert (d / "rep" / "residuals.csv").read_text().startswith("# step=RPC refinement (shift)")
    # a second run without --overwrite fails before any work and leaves everything as it was
    (d / "o.tif").unlink()
    r = CliRunner().invoke(cli, ["ortho", str(d / "sat.tif"), "--dem", str(d / "dem.tif"), "--rpc", "-o",
                                 str(d / "o.tif"), "--report", str(d / "rep")])
    assert r.exit_code == 1 and "exists" in r.output and not (d / "o.tif").exists()
