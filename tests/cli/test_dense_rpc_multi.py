"""``stereo dense-rpc IMG1 IMG2 IMG3``: the multi-view command end to end on a tiny synthetic triplet, its
``--reference-dem`` comparison, and bad input (one line, non-zero exit, nothing written)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from rasterio.transform import from_origin

from rectify.geometry.crs import transform_xy
from rectify.geometry.rpc import RPC
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
