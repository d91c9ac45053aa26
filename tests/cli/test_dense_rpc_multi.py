"""``stereo dense-rpc IMG1 IMG2 IMG3``: the multi-view command end to end on a tiny synthetic triplet, its
``--reference-dem`` comparison, and bad input (one line, non-zero exit, nothing written)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from rasterio.transform import from_origin

from rectify.geometry.crs import transform_xy
from rectify.geometry.rpc import RPC
from stereo.actions import dense_rpc_multi
from stereo.cli.main import cli
from tests.support.rpc_synthetic import LAT0, LON0, dem, render, triplet

SIZE, GSD = 256, 0.5


@pytest.fixture(scope="module")
def triplet_files(tmp_path_factory):
    """Nadir, forward, backward (no bias), 256 x 256 px of 0.5 m; the true DEM as a UTM GeoTIFF of 1 m cells."""
    d = tmp_path_factory.mktemp("cli_triplet")
    rpcs = triplet(gsd=GSD, size=SIZE)
    paths = []
    for j in (1, 0, 2):
        p = d / f"v{j}.tif"
        with rasterio.open(p, "w", driver="GTiff", width=SIZE, height=SIZE, count=1, dtype="uint8",
                           rpcs=rpcs[j].to_rasterio()) as ds:
            ds.write(render(j, SIZE, GSD, np.zeros(2))[None])
        paths.append(p)
    x0, y0 = transform_xy("EPSG:4326", "EPSG:32631", np.array([[LON0, LAT0]]))[0]
    n = 300
    xs = x0 - 150 + 0.5 + np.arange(n)
    ys = y0 + 150 - 0.5 - np.arange(n)
    X, Y = np.meshgrid(xs, ys)
    ll = transform_xy("EPSG:32631", "EPSG:4326", np.column_stack([X.ravel(), Y.ravel()]))
    with rasterio.open(d / "dem.tif", "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs="EPSG:32631", transform=from_origin(x0 - 150, y0 + 150, 1.0, 1.0)) as ds:
        ds.write(dem(ll).reshape(1, n, n).astype(np.float32))
    return d, paths, rpcs


def _run(*args):
    return CliRunner().invoke(cli, ["dense-rpc", *(str(a) for a in args)])


def test_cli_three_images_with_a_reference_dem(triplet_files, tmp_path):
    d, paths, _ = triplet_files
    out = tmp_path / "o"
    r = _run(*paths, "-o", out, "--no-adjust", "--roi", "64,64,128,128", "--tile", "128", "--reference-dem",
             d / "dem.tif")
    assert r.exit_code == 0, r.output
    assert "RPC adjustment: not run" in r.output and "fused DSM" in r.output and "DSM vs reference DEM" in r.output
    doc = json.loads((out / "dense_rpc.json").read_text())
    cmp = doc["comparison"]
    assert cmp["n"] > 2000 and abs(cmp["median"]) < 0.5 and cmp["nmad"] < 1.0, cmp
    assert {p.name for p in (out / "report").iterdir()} == {"dsm.png", "dz.png", "dz_histogram.png"}
    assert doc["dsm"]["roi"]["coverage"] > 0.9
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.count == 4 and ds.descriptions[1].startswith("sigma_z")


def test_cli_one_image_without_rpc(triplet_files, tmp_path):
    _, paths, _ = triplet_files
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, 64, 64), np.uint8))
    r = _run(paths[0], paths[1], plain, "-o", tmp_path / "o")
    assert r.exit_code != 0 and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1 and "no RPC" in r.output, r.output
    assert not (tmp_path / "o").exists()


def test_cli_images_that_do_not_overlap(triplet_files, tmp_path):
    _, paths, rpcs = triplet_files
    moved = rpcs[2].to_dict()
    moved["lat_off"] = moved["lat_off"] + 0.05  # 5.5 km north
    far = tmp_path / "far.tif"
    with rasterio.open(far, "w", driver="GTiff", width=SIZE, height=SIZE, count=1, dtype="uint8",
                       rpcs=RPC.from_dict(moved).to_rasterio()) as ds:
        ds.write(np.zeros((1, SIZE, SIZE), np.uint8))
    r = _run(paths[0], paths[1], far, "-o", tmp_path / "o")
    assert r.exit_code != 0 and len(r.output.strip().splitlines()) == 1, r.output
    assert "does not overlap" in r.output and "far.tif" in r.output
    assert not (tmp_path / "o").exists()


def test_cli_bad_options(triplet_files, tmp_path):
    _, paths, _ = triplet_files
    r = _run(paths[0], "-o", tmp_path / "o")
    assert r.exit_code != 0 and "at least two images" in r.output
    r = _run(*paths, "-o", tmp_path / "o", "--min-angle", "30", "--max-angle", "20")
    assert r.exit_code != 0 and "angle range" in r.output and len(r.output.strip().splitlines()) == 1
    r = _run(*paths, "-o", tmp_path / "o", "--no-adjust", "--min-angle", "40", "--max-angle", "45", "--roi",
             "64,64,128,128")
    assert r.exit_code != 0 and "no pair" in r.output and len(r.output.strip().splitlines()) == 1, r.output
    r = _run(*paths, "-o", tmp_path / "o", "--no-adjust", "--gcps", paths[0])
    assert r.exit_code != 0 and "no-adjust" in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "o").exists()


def test_cli_fused_holes_filled_by_default_and_flagged(triplet_files, tmp_path, monkeypatch):
    """An interior hole of the fused DSM (a 6 x 5 cell block emptied after the fusion, as where no pair
    matched) is interpolated by default and flagged (sigma_Z nodata, count 0, provenance -1, height within the
    heights around it); ``--fill-holes 0`` leaves it empty."""
    _, paths, _ = triplet_files
    real = dense_rpc_multi.fuse_heights

    def holed(*args, **kwargs):
        f = real(*args, **kwargs)
        r0, c0 = f.height.shape[0] // 2, f.height.shape[1] // 2
        blk = (slice(r0, r0 + 6), slice(c0, c0 + 5))
        assert np.isfinite(f.height[r0 - 3:r0 + 9, c0 - 3:c0 + 8]).all()  # the block lies inside the heights
        h, s, c, p = f.height.copy(), f.sigma.copy(), f.count.copy(), f.provenance.copy()
        h[blk], s[blk], c[blk], p[blk] = np.nan, np.nan, 0, -1
        return dataclasses.replace(f, height=h, sigma=s, count=c, provenance=p)

    monkeypatch.setattr(dense_rpc_multi, "fuse_heights", holed)
    bands = {}
    for name, extra in (("default", ()), ("off", ("--fill-holes", "0"))):
        out = tmp_path / name
        r = _run(*paths, "-o", out, "--no-adjust", "--roi", "64,64,128,128", "--tile", "128", *extra)
        assert r.exit_code == 0, r.output
        with rasterio.open(out / "dsm.tif") as ds:
            bands[name] = ds.read()
        doc = json.loads((out / "dense_rpc.json").read_text())
        bands[name + "_doc"] = doc["dsm"]
    h, s, c, p = bands["default"]
    r0, c0 = h.shape[0] // 2, h.shape[1] // 2
    blk = (slice(r0, r0 + 6), slice(c0, c0 + 5))
    rim = h[r0 - 1:r0 + 7, c0 - 1:c0 + 6].astype(np.float64)
    rim[1:-1, 1:-1] = np.nan  # the ring of cells around the block
    assert (h[blk] != -9999.0).all() and (c[blk] == 0).all() and (s[blk] == -9999.0).all() and (p[blk] == -1).all()
    assert np.nanmin(rim) - 1e-3 <= h[blk].min() and h[blk].max() <= np.nanmax(rim) + 1e-3
    assert bands["default_doc"]["filled_cells"] >= 30
    assert bands["default_doc"]["roi"]["coverage"] > bands["default_doc"]["roi_coverage_without_filled"]
    h0, _s0, c0_, _p0 = bands["off"]
    assert (h0[blk] == -9999.0).all() and (c0_[blk] == 0).all() and bands["off_doc"]["filled_cells"] == 0
    assert bands["off_doc"]["roi"]["coverage"] == bands["off_doc"]["roi_coverage_without_filled"]
