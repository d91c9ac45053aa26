"""``stereo surface`` end to end on a small rendered block, and its bad input (issue 27)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from rectify.formats.orthority import read_ext_param, read_int_param
from stereo.block.types import Pose
from stereo.cli.main import cli
from stereo.formats.block import block_orientation_text
from stereo.formats.points import points_csv_text
from tests.support.block_surface import GSD, make_surface_block, read_dsm, truth_on


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """A 2 x 3 block (true poses) with the images in their own folder and a points.csv of terrain heights."""
    root = tmp_path_factory.mktemp("surface_cli")
    blk = make_surface_block(root / "orient", strips=2, per_strip=3, images=root / "images", supersample=1)
    rng = np.random.default_rng(1)
    x0, y0, x1, y1 = blk.terrain.extent
    xy = np.column_stack([rng.uniform(x0 + 40, x1 - 40, 200), rng.uniform(y0 + 40, y1 - 40, 200)])
    xyz = np.column_stack([xy, blk.terrain.height(xy)])
    std = np.tile([0.02, 0.02, 0.03], (200, 1))     # the bundle's height std errors of its points: 3 cm
    (root / "orient" / "points.csv").write_text(points_csv_text([str(i) for i in range(200)], xyz, np.zeros(200),
                                                                std=std))
    return root, blk, float(np.median(xyz[:, 2]))


def _run(*args):
    return CliRunner().invoke(cli, ["surface", *map(str, args)])


def test_surface_end_to_end(block, tmp_path):
    root, blk, zmed = block
    out = tmp_path / "out"
    r = _run(root / "orient", "-o", out, "--images", root / "images")
    assert r.exit_code == 0, r.output
    assert "pairs: " in r.output and "DSM: " in r.output and "variance factor" in r.output
    assert sorted(p.name for p in out.iterdir()) == ["dsm.tif", "pairs.json", "points.laz"]   # no CRS: no mosaic
    bands, tr, desc = read_dsm(out / "dsm.tif")
    err = bands[0] - truth_on(tr, bands[0].shape, blk.terrain)
    ok = np.isfinite(err)
    assert ok.sum() > 20_000
    assert np.sqrt(np.mean(err[ok] ** 2)) <= 0.5 * GSD
    doc = json.loads((out / "pairs.json").read_text())
    assert doc["format"] == "rectify-stereo/surface-pairs" and len(doc["pairs"]) >= 2
    assert doc["ground_z"] == pytest.approx(zmed, abs=1e-3)      # from the block's points.csv
    assert doc["orientation_sigma"] == "points"                  # its std_z: the orientation's share
    assert np.nanmin(bands[1]) >= 0.03 * (1 - 1e-6)
    # an existing output is kept without --overwrite
    before = (out / "dsm.tif").read_bytes()
    r = _run(root / "orient", "-o", out, "--images", root / "images")
    assert r.exit_code == 1 and "--overwrite" in r.output and "Traceback" not in r.output
    assert (out / "dsm.tif").read_bytes() == before


@pytest.mark.parametrize(("args", "message"), [
    ((), "image 'img_1_1.png' of the block orientation is not in"),
    (("--cell", "0.01"), "DSM cell 0.01 is smaller than a tenth of the ground pixel"),
    (("--min-overlap", "0.95"), "no stereo pair passes the thresholds"),
    (("--images", "MISSING"), "image folder not found"),
])
def test_surface_bad_input(block, tmp_path, args, message):
    root, _blk, _z = block
    out = tmp_path / "out"
    extra = [a.replace("MISSING", str(tmp_path / "nowhere")) for a in args]
    if "--images" not in extra and args != ():
        extra += ["--images", str(root / "images")]
    r = _run(root / "orient", "-o", out, *extra)
    assert r.exit_code == 1, r.output
    assert message in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1
    assert not out.exists()


def test_images_missing_from_disk(block, tmp_path):
    root, _blk, _z = block
    imgs = tmp_path / "imgs"
    shutil.copytree(root / "images", imgs)
    (imgs / "img_2_3.png").unlink()
    r = _run(root / "orient", "-o", tmp_path / "out", "--images", imgs)
    assert r.exit_code == 1 and "image 'img_2_3.png'" in r.output
    assert not (tmp_path / "out").exists()


@pytest.mark.shared
def test_ngi_pair_as_a_block_of_two_against_the_dem(ngi_pair, tmp_path):
    """The two NGI frames with their AT orientations (orthority's files, read by the project's readers) as a
    block orientation of two -> ``stereo surface --reference-dem dem.tif``."""
    cams = read_int_param(ngi_pair / "orthority_int_param.yaml")
    ext = read_ext_param(ngi_pair / "orthority_ext_param.geojson")
    poses = [Pose(name, e["camera"] or next(iter(cams)), np.asarray(e["position"]), np.asarray(e["rotation"]))
             for name, e in ext.items()]
    crs = next(iter(ext.values()))["crs"]
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "orientation.json").write_text(block_orientation_text(cams, poses, crs=crs))
    with rasterio.open(ngi_pair / "dem.tif") as ds:
        dem = ds.read(1)
    ground_z = float(np.median(dem[np.isfinite(dem) & (dem > -1000)]))
    out = tmp_path / "out"
    r = _run(tmp_path / "o", "-o", out, "--images", ngi_pair, "--ground-z", ground_z, "--reference-dem",
             ngi_pair / "dem.tif")
    assert r.exit_code == 0, r.output
    cmp = json.loads((out / "pairs.json").read_text())["comparison"]
    # measured (docs/surface.md): RMSE 5.19 m = 0.90 cells of 5.8 m, NMAD 3.88 m, 80.7 % of the overlap
    assert cmp["rmse"] <= 1.5 * 6.0 and cmp["nmad"] <= 5.0 and cmp["coverage"] >= 0.7, cmp
