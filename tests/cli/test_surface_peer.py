"""`stereo surface` from another tool's orientation: orthority's ext_param + int_param give the same DSM as the
same poses in a block orientation JSON; without points the terrain height comes from --ground-z or the
reference DEM (issue 27: steps that chain with peers' files)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.formats.orthority import write_ext_param, write_int_param
from rectify.raster.io import write_raster
from stereo.block.types import Pose
from stereo.cli.main import cli
from stereo.formats.block import block_orientation_text
from tests.support.block_example import CAM, CRS, E0, N0, Z0, write_example_block, write_example_reconstruction
from tests.support.block_surface import read_dsm

FAST = ["--no-ortho", "--no-cloud", "--pairs-per-area", "1"]


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    d = tmp_path_factory.mktemp("peer_block")
    images, poses, xyz = write_example_block(d)
    write_example_reconstruction(d, images, poses)   # OpenSfM's topocentric frame, poses 0.5 deg and 5 cm off
    mapped = [Pose(img.name, "dmc", p.position + [E0, N0, 0.0], p.rotation) for p, img in zip(poses, images,
                                                                                                strict=True)]
    ext = write_ext_param(d / "ext_param.geojson", {p.image: {"position": p.position, "rotation": p.rotation,
                                                              "camera": "dmc"} for p in mapped}, CRS)
    intr = write_int_param(d / "int_param.yaml", {"dmc": CAM})
    (d / "ours").mkdir()
    (d / "ours" / "orientation.json").write_text(block_orientation_text({"dmc": CAM}, mapped, crs=CRS))
    return d, ext, intr, xyz + [E0, N0, 0.0]


def _run(*args):
    return CliRunner().invoke(cli, ["surface", *map(str, args)])


def test_orthority_files_give_the_dsm_of_the_same_block_orientation(block, tmp_path):
    d, ext, intr, xyz = block
    r1 = _run(ext, "--camera", intr, "--images", d, "--ground-z", Z0, *FAST, "-o", tmp_path / "oty")
    assert r1.exit_code == 0, r1.output
    r2 = _run(d / "ours", "--images", d, "--ground-z", Z0, *FAST, "-o", tmp_path / "ours")
    assert r2.exit_code == 0, r2.output
    a, ta, _ = read_dsm(tmp_path / "oty" / "dsm.tif")
    b, tb, _ = read_dsm(tmp_path / "ours" / "dsm.tif")
    assert ta == tb
    np.testing.assert_allclose(a[0], b[0], atol=1e-3, equal_nan=True)   # orthority stores angles in degrees
    doc = json.loads((tmp_path / "oty" / "pairs.json").read_text())
    assert doc["orientation_sigma"] == "none" and doc["crs"] == CRS
    # the DSM against the block's control points (terrain truth): within a ground pixel or two
    col, row = ~ta * (xyz[:, 0], xyz[:, 1])
    ok = (col >= 0) & (row >= 0) & (col < a.shape[2]) & (row < a.shape[1])
    h = a[0][row[ok].astype(int), col[ok].astype(int)]
    dz = h[np.isfinite(h)] - xyz[ok][np.isfinite(h), 2]
    assert len(dz) >= 4 and np.sqrt(np.mean(dz ** 2)) < 0.6, dz


def test_terrain_height_from_the_reference_dem(block, tmp_path):
    """No points and no --ground-z: the reference DEM's median under the images' nadir points (Z0 here); the
    orthomosaic is made from the peer's poses too."""
    d, ext, intr, _ = block
    dem = tmp_path / "dem.tif"
    write_raster(dem, np.full((100, 100), Z0, np.float32), Affine(2.0, 0, E0 - 100, 0, -2.0, N0 + 100), CRS)
    r = _run(ext, "--camera", intr, "--images", d, "--reference-dem", dem, "--no-cloud", "--pairs-per-area", "1",
             "-o", tmp_path / "o")
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "o" / "pairs.json").read_text())
    assert doc["ground_z"] == pytest.approx(Z0) and len(doc["ortho"]["images"]) == 6
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["dsm.tif", "ortho.source.tif", "ortho.tif",
                                                                 "pairs.json"]


@pytest.mark.parametrize("extra, message", [
    ([], "has no points to take the terrain height from: pass --ground-z"),
    (["--ground-z", "50"], "holds no camera 'dmc': pass --camera"),
])
def test_peer_orientation_errors_are_one_line(block, tmp_path, extra, message):
    d, ext, intr, _ = block
    args = [ext, "--images", d, *FAST, "-o", tmp_path / "o", *extra]
    if "--ground-z" not in extra:
        args += ["--camera", intr]
    r = _run(*args)
    assert r.exit_code == 1 and message in r.output and "Traceback" not in r.output, r.output
    assert len([ln for ln in r.output.splitlines() if ln.startswith("Error")]) == 1
    assert not (tmp_path / "o").exists()


def test_an_odm_reconstruction_gives_a_dsm_with_a_crs(block, tmp_path):
    """OpenSfM/ODM reconstruction.json (its cameras inside, topocentric frame): the DSM and the orthomosaic are
    written in the UTM zone (EPSG:32633 here) and the summary says the orientation was converted."""
    d, _ext, _intr, _ = block
    r = _run(d / "reconstruction.json", "--images", d, "--ground-z", Z0, "--no-cloud", "--pairs-per-area", "1",
             "-o", tmp_path / "o")
    assert r.exit_code == 0, r.output
    assert "orientation in EPSG:32633, converted from topocentric" in r.output
    for name in ("dsm.tif", "ortho.tif"):
        with rasterio.open(tmp_path / "o" / name) as ds:
            assert ds.crs is not None and ds.crs.to_epsg() == 32633
