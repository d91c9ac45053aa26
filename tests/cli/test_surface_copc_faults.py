"""``stereo surface --cloud-format copc`` (the cloud as a COPC beside its LAZ twin) and a disk that fills up
mid-run (issue 27): one line, nothing left, the inputs untouched."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from pathlib import Path

import laspy
import numpy as np
import pytest
from affine import Affine
from click.testing import CliRunner

import stereo.actions.surface_outputs as surface_outputs
import stereo.formats.cloud as cloud
from rectify.errors import InvalidInputError, RasterIOError
from rectify.raster.io import translate_to_cog, write_raster
from stereo.actions.block_surface import BlockSurfacePlan, plan_block_surface, run_block_surface
from stereo.actions.surface import SurfaceOptions
from stereo.cli.main import cli
from stereo.formats.cloud import copc_available
from stereo.formats.points import points_csv_text
from tests.support.block_surface import make_surface_block, read_dsm
from tests.support.disks import mounted_tmpfs

CRS = "EPSG:32633"
DIMS = ("sigma_z", "pair", "count")

needs_copc = pytest.mark.skipif(not copc_available(), reason="copclib not installed (the copc extra)")


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """Two images of one strip (one stereo pair, 181 x 220 cells of 0.25 m, about 25 000 cloud points) in a
    projected CRS: the orientation in ``orient``, the images in ``images``."""
    root = tmp_path_factory.mktemp("surface_copc")
    make_surface_block(root / "orient", strips=1, per_strip=2, images=root / "images", supersample=1)
    doc = json.loads((root / "orient" / "orientation.json").read_text())
    doc["crs"] = CRS
    (root / "orient" / "orientation.json").write_text(json.dumps(doc))
    return root


def _surface(root: Path, out: Path, *args: str):
    return CliRunner().invoke(cli, ["surface", str(root / "orient"), "--images", str(root / "images"), "--ground-z",
                                    "50", "-o", str(out), *args])


def _sorted_points(rec) -> dict[str, np.ndarray]:
    order = np.lexsort((np.asarray(rec.X), np.asarray(rec.Y)))
    return {n: np.asarray(rec[n])[order] for n in ("X", "Y", "Z", *DIMS)}


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@needs_copc
def test_copc_cloud_equals_the_laz_cloud(block, tmp_path, monkeypatch):
    """The same surface written as points.laz and as points.copc.laz (its octree built by batches of at most
    4000 points, as a cloud of more than ``COPC_BATCH`` points is): the same points (to the LAS count), the
    same sigma_z, pair and count; the COPC's octree answers a spatial query with the LAZ's points in the
    box; the CRS is stored; nothing else is left in the folder."""
    monkeypatch.setattr(cloud, "COPC_BATCH", 4000)
    r = _surface(block, tmp_path / "laz", "--no-ortho")
    assert r.exit_code == 0, r.output
    r = _surface(block, tmp_path / "copc", "--no-ortho", "--cloud-format", "copc")
    assert r.exit_code == 0, r.output
    assert "point cloud: " in r.output and "in points.copc.laz" in r.output
    assert sorted(os.listdir(tmp_path / "copc")) == ["dsm.tif", "pairs.json", "points.copc.laz"]
    las = laspy.read(tmp_path / "laz" / "points.laz")
    with laspy.CopcReader.open(tmp_path / "copc" / "points.copc.laz") as cr:
        assert cr.header.point_count == len(las.points)
        assert list(cr.header.point_format.extra_dimension_names) == list(DIMS)
        copc = cr.query()
        x0, y0 = float(np.min(las.x)), float(np.min(las.y))
        box = laspy.copc.Bounds(mins=np.array([x0 + 10, y0 + 10]), maxs=np.array([x0 + 25, y0 + 20]))
        part = cr.query(bounds=box)
    assert len(copc) == len(las.points) > 20_000
    a, b = _sorted_points(las.points), _sorted_points(copc)
    for name in a:
        assert np.array_equal(a[name], b[name]), name
    # the octree's spatial query: exactly the LAZ points inside the box
    x, y = np.asarray(las.x), np.asarray(las.y)
    inside = (x >= x0 + 10) & (x <= x0 + 25) & (y >= y0 + 10) & (y <= y0 + 20)
    assert 0 < len(part) == int(inside.sum())
    assert np.array_equal(np.sort(np.asarray(part.X)), np.sort(np.asarray(las.points.X)[inside]))
    # the CRS (an EVLR in a COPC, which CopcReader's header does not parse: read the whole file)
    assert laspy.read(tmp_path / "copc" / "points.copc.laz").header.parse_crs().to_epsg() == 32633
    # every point is a DSM cell: its fused height and sigma
    bands, tr, _desc = read_dsm(tmp_path / "copc" / "dsm.tif")
    assert len(copc) == int(np.isfinite(bands[0]).sum())
    c, rr = ~tr * (np.asarray(copc.x), np.asarray(copc.y))
    ci, ri = np.floor(c).astype(int), np.floor(rr).astype(int)
    assert np.allclose(np.asarray(copc.z), bands[0][ri, ci], atol=1e-3)
    assert np.allclose(np.asarray(copc.sigma_z), bands[1][ri, ci], rtol=1e-6)
    doc = json.loads((tmp_path / "copc" / "pairs.json").read_text())["cloud"]
    assert doc == {"file": "points.copc.laz", "format": "copc", "points": len(copc), "extra_dims": list(DIMS),
                   "colors": {"source": "images", "sampling": "bilinear", "bits": 8, "uncolored": 0}}


@needs_copc
def test_block_surface_writes_the_copc(block, tmp_path):
    """``stereo block --surface --surface-cloud-format copc`` (its action on a block's output folder)."""
    work = tmp_path / "blk"
    work.mkdir()
    (work / "orientation.json").write_bytes((block / "orient" / "orientation.json").read_bytes())
    xyz = np.array([[5.0, -5.0, 50.0], [20.0, 0.0, 51.0], [35.0, 5.0, 49.0]])   # the block's points: the terrain height
    (work / "points.csv").write_text(points_csv_text(["1", "2", "3"], xyz, np.zeros(3)))
    plan = plan_block_surface(sorted((block / "images").iterdir()), projective=False, method="bundle",
                              control=None, check_ids=(), cloud_format="copc")
    assert plan == BlockSurfacePlan(str((block / "images").resolve()), cloud_format="copc")
    res = run_block_surface(work, plan)
    assert res.cloud_file == "points.copc.laz" and res.cloud_points > 20_000
    with laspy.CopcReader.open(work / "surface" / "points.copc.laz") as cr:
        assert cr.header.point_count == res.cloud_points


def test_bad_cloud_format(block, tmp_path, monkeypatch):
    r = _surface(block, tmp_path / "out", "--cloud-format", "ply")
    assert r.exit_code == 2 and "'ply' is not one of 'las', 'laz', 'copc'" in r.output
    assert not (tmp_path / "out").exists()
    with pytest.raises(InvalidInputError, match="`cloud_format` must be one of"):
        SurfaceOptions(cloud_format="ply")
    # COPC without copclib: refused in one line before any work (nothing created)
    monkeypatch.setattr(surface_outputs, "copc_available", lambda: False)
    r = _surface(block, tmp_path / "out", "--cloud-format", "copc")
    assert r.exit_code == 1 and "--cloud-format copc needs the copclib package" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1 and not (tmp_path / "out").exists()
    with pytest.raises(InvalidInputError, match="copclib"):
        plan_block_surface([block / "images" / "img_1_1.png"], projective=False, method="bundle", control=None,
                           check_ids=(), cloud_format="copc")


# --------------------------------------------------------------------------- a full disk
@pytest.fixture()
def disk_900k(tmp_path):
    """A 900 KiB tmpfs (root only; skipped otherwise): the surface's scratch and DSM fit, its COPC does not
    (staging LAS 46 bytes per point: 1.1 MB). Measured: this block's COPC run fails between 600 and 1350 KiB."""
    with mounted_tmpfs(tmp_path / "disk", "900k") as d:
        yield d


def _one_error_line(output: str, name: str) -> None:
    errors = [ln for ln in output.splitlines() if ln.startswith("Error:")]
    assert len(errors) == 1 and len(output.strip().splitlines()) == 1, output
    assert name in errors[0] and "no space left on device" in errors[0], output
    assert "Traceback" not in output


def test_disk_full_in_the_first_pair(block, small_disk):
    """200 KiB: the first pair's scratch rasters do not fit. One line, no output folder, the inputs unchanged."""
    before = _digest(block)
    r = _surface(block, small_disk / "out")
    assert r.exit_code == 1, r.output
    _one_error_line(r.output, "pair0_")
    assert os.listdir(small_disk) == []
    assert _digest(block) == before


def test_disk_full_as_a_process_prints_one_line(block, small_disk):
    """The real command in its own process: libtiff's own messages on the standard error (``_tiffWriteProc: No
    space left on device.``, written by C code to fd 2) are not shown without -v; the one error line is."""
    import sys

    args = [sys.executable, "-c", "from stereo.cli.main import cli; cli()", "surface", str(block / "orient"),
            "--images", str(block / "images"), "--ground-z", "50", "-o", str(small_disk / "out")]
    r = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and r.stdout == "", (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: RasterIOError: ") and "no space left" in lines[0], r.stderr
    assert os.listdir(small_disk) == []
    r = subprocess.run([*args, "-v"], capture_output=True, text=True, timeout=300)   # -v: everything shown
    assert r.returncode == 1 and "_tiffWriteProc" in r.stderr and "INFO " in r.stderr, r.stderr[-2000:]


@needs_copc
def test_disk_full_in_the_copc_leaves_the_folder_as_before(block, disk_900k):
    """900 KiB: the DSM is written (staged), the COPC's staging LAS does not fit. The error names
    points.copc.laz; the existing output folder keeps exactly its one file; no hidden temporary is left."""
    out = disk_900k / "out"
    out.mkdir()
    (out / "notes.txt").write_text("kept\n")
    before = _digest(block)
    r = _surface(block, out, "--cloud-format", "copc", "--no-ortho")
    assert r.exit_code == 1, r.output
    _one_error_line(r.output, str(out / "points.copc.laz"))
    assert os.listdir(disk_900k) == ["out"] and os.listdir(out) == ["notes.txt"]
    assert (out / "notes.txt").read_text() == "kept\n"
    assert _digest(block) == before
    # the same run on a disk with room (the space freed again) succeeds
    r = _surface(block, disk_900k / "small", "--cloud-format", "copc", "--no-ortho", "--cell", "1")
    assert r.exit_code == 0, r.output
    assert sorted(os.listdir(disk_900k / "small")) == ["dsm.tif", "pairs.json", "points.copc.laz"]


def test_cog_copy_on_a_full_disk_is_one_line(small_disk, tmp_path):
    """The orthomosaic's last step (``translate_to_cog``, GDAL's COG driver) on a full disk: GDAL raises its own
    ``CPLE_AppDefinedError`` (not a ``RasterioError``), which used to escape as a traceback of ``stereo surface``;
    now a one-line :class:`RasterIOError` naming the file and the reason."""
    a = np.random.default_rng(0).random((600, 600)).astype("float32")     # 1.4 MB, incompressible
    write_raster(tmp_path / "src.tif", a, Affine(1, 0, 350000, 0, -1, 5800000), CRS)
    dst = small_disk / "cog.tif"
    with pytest.raises(RasterIOError, match="no space left on device") as info:
        translate_to_cog(tmp_path / "src.tif", dst, compress="zstd")
    assert str(dst) in str(info.value) and "\n" not in str(info.value)
    assert type(info.value.__cause__).__name__.startswith("CPLE_")


@needs_copc
def test_block_surface_on_a_full_disk_keeps_the_block(block, disk_900k):
    """``stereo block --surface``'s second step on a full disk: the block's folder (orientation.json,
    points.csv, committed before) is kept as it was, no ``surface`` folder is left, one-line error."""
    work = disk_900k / "blk"
    work.mkdir()
    (work / "orientation.json").write_bytes((block / "orient" / "orientation.json").read_bytes())
    xyz = np.array([[5.0, -5.0, 50.0], [20.0, 0.0, 51.0], [35.0, 5.0, 49.0]])
    (work / "points.csv").write_text(points_csv_text(["1", "2", "3"], xyz, np.zeros(3)))
    before = _digest(work)
    plan = plan_block_surface(sorted((block / "images").iterdir()), projective=False, method="bundle",
                              control=None, check_ids=(), cloud_format="copc")
    with pytest.raises(RasterIOError, match="no space left on device") as info:
        run_block_surface(work, plan)
    assert str(work / "surface" / "points.copc.laz") in str(info.value) and "\n" not in str(info.value)
    assert sorted(os.listdir(work)) == ["orientation.json", "points.csv"] and _digest(work) == before
