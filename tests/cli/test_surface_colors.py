"""The colours of ``stereo surface``'s point cloud (issue 27): RGB from the true orthomosaic (nearest pixel to the
cell centre), else from the left image of each point's provenance pair (the point projected, bilinear); 8-bit
sources x 257 to LAS's 16 bits, one band as grey, 16 bits kept; unknown colours 0 and counted."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

import stereo.actions.surface_outputs as surface_outputs
from rectify.errors import InvalidInputError, RasterIOError
from rectify.geometry.camera import Camera
from rectify.raster.io import write_raster
from stereo.actions.surface_outputs import COLOR_SAMPLING, CloudWritten, PairView, write_cloud
from stereo.block.types import Pose
from stereo.cli.main import cli
from stereo.dense.dsm import DSM_NODATA
from stereo.formats.cloud import LasWriter, copc_available
from tests.support.block_surface import make_surface_block

CRS = "EPSG:32633"


def _rgb(las) -> np.ndarray:
    return np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)]).astype(np.int64)


def _truth_grey(blk, x, y) -> np.ndarray:
    """The rendered images' grey value of the texture at ground (x, y): ``20 + 215 t`` (block_render)."""
    return 20.0 + 215.0 * blk.terrain._sample(blk.terrain.texture, np.column_stack([x, y]))


# --------------------------------------------------------------------------- the command on a rendered block
@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """Two rendered images of one strip in a projected CRS (one pair, about 25 000 cloud points), run with the
    orthomosaic (colours from it) and with --no-ortho (colours from the images)."""
    root = tmp_path_factory.mktemp("surface_colors")
    blk = make_surface_block(root / "orient", strips=1, per_strip=2, images=root / "images", supersample=1)
    doc = json.loads((root / "orient" / "orientation.json").read_text())
    doc["crs"] = CRS
    (root / "orient" / "orientation.json").write_text(json.dumps(doc))
    outs = {}
    for name, args in (("mos", ()), ("img", ("--no-ortho",))):
        r = _surface(root, root / name, *args)
        assert r.exit_code == 0, r.output
        outs[name] = r.output
    return root, blk, outs


def _surface(root, out, *args: str):
    return CliRunner().invoke(cli, ["surface", str(root / "orient"), "--images", str(root / "images"), "--ground-z",
                                    "50", "-o", str(out), *args])


def test_colours_from_the_orthomosaic(block):
    """Every point's RGB is the mosaic's pixel at its XY x 257 (exactly: at the default cell a cell centre is a
    pixel centre), grey (R = G = B), and matches the rendered texture at its XY: measured median |d| 2.0 and
    RMS 4.5 grey levels (the texture's own spread 22.5), asserted 3 and 6."""
    root, blk, outs = block
    las = laspy.read(root / "mos" / "points.laz")
    assert las.point_format.id == 7 and {"red", "green", "blue"} <= set(las.point_format.dimension_names)
    rgb = _rgb(las)
    assert (rgb[:, 0] == rgb[:, 1]).all() and (rgb[:, 0] == rgb[:, 2]).all()
    x, y = np.asarray(las.x), np.asarray(las.y)
    with rasterio.open(root / "mos" / "ortho.tif") as ds:
        a, tr = ds.read(1), ds.transform
    c, r = ~tr * (x, y)
    assert np.allclose(c % 1, 0.5) and np.allclose(r % 1, 0.5)      # the cell centres are pixel centres
    pix = a[np.floor(r).astype(int), np.floor(c).astype(int)].astype(np.int64)
    assert (pix > 0).all()                                            # no nodata under a point here
    assert np.array_equal(rgb[:, 0], pix * 257)
    d = rgb[:, 0] / 257 - _truth_grey(blk, x, y)
    assert np.median(np.abs(d)) <= 3.0 and np.sqrt(np.mean(d ** 2)) <= 6.0
    cloud = json.loads((root / "mos" / "pairs.json").read_text())["cloud"]
    assert cloud["colors"] == {"source": "orthomosaic", "sampling": "nearest", "bits": 8, "uncolored": 0}
    assert "RGB from the orthomosaic (nearest pixel), 0 without a colour (RGB 0)" in outs["mos"]
    assert "outputs in " in outs["mos"] and "ortho.source.tif, points.laz, pairs.json" in outs["mos"]


def test_colours_from_the_images_without_a_mosaic(block):
    """--no-ortho: each point projected into the left image of its pair, bilinear: against the texture measured
    median |d| 2.0 and RMS 4.5 grey levels (asserted 3 and 6); against the mosaic run's colours at the same
    points measured median 0.4, RMS 1.5 (asserted 1 and 3)."""
    root, blk, outs = block
    las = laspy.read(root / "img" / "points.laz")
    ref = laspy.read(root / "mos" / "points.laz")
    assert np.array_equal(np.asarray(las.X), np.asarray(ref.X)) and np.array_equal(np.asarray(las.Y), np.asarray(ref.Y))
    rgb = _rgb(las)
    assert (rgb[:, 0] == rgb[:, 2]).all() and (rgb > 0).all()
    grey = rgb[:, 0] / 257
    d = grey - _truth_grey(blk, np.asarray(las.x), np.asarray(las.y))
    assert np.median(np.abs(d)) <= 3.0 and np.sqrt(np.mean(d ** 2)) <= 6.0
    dm = grey - _rgb(ref)[:, 0] / 257
    assert np.median(np.abs(dm)) <= 1.0 and np.sqrt(np.mean(dm ** 2)) <= 3.0
    assert (rgb[:, 0] % 257 != 0).any()                               # interpolated, not only whole grey levels
    cloud = json.loads((root / "img" / "pairs.json").read_text())["cloud"]
    assert cloud["colors"] == {"source": "images", "sampling": "bilinear", "bits": 8, "uncolored": 0}
    assert "RGB from the left image of each point's pair (bilinear)" in outs["img"]


@pytest.mark.skipif(not copc_available(), reason="copclib not installed (the copc extra)")
def test_copc_carries_the_same_rgb(block, tmp_path):
    root, _blk, _outs = block
    r = _surface(root, tmp_path / "c", "--cloud-format", "copc")
    assert r.exit_code == 0, r.output
    laz = laspy.read(root / "mos" / "points.laz")
    with laspy.CopcReader.open(tmp_path / "c" / "points.copc.laz") as cr:
        assert cr.header.point_format.id == 7
        copc = cr.query()
    key = lambda p: np.lexsort((np.asarray(p.X), np.asarray(p.Y)))   # noqa: E731
    a, b = _rgb(laz)[key(laz)], _rgb(copc)[key(copc)]
    assert len(a) == len(b) > 20_000 and np.array_equal(a, b) and (a > 0).all()


def test_no_cloud_colors(block, tmp_path):
    root, _blk, _outs = block
    r = _surface(root, tmp_path / "n", "--no-ortho", "--no-cloud-colors")
    assert r.exit_code == 0, r.output
    assert "no colours (RGB 0)" in r.output
    assert (_rgb(laspy.read(tmp_path / "n" / "points.laz")) == 0).all()
    assert json.loads((tmp_path / "n" / "pairs.json").read_text())["cloud"]["colors"]["source"] == "none"


# --------------------------------------------------------------------------- write_cloud on known rasters
def _dsm(path, h=6, w=8, cell=1.0, pair: float | np.ndarray = 0.0) -> Affine:
    """A flat DSM at z = 10 (one cell without a height) with the 4 fused bands; its transform."""
    t = Affine(cell, 0, 100.0, 0, -cell, 200.0)
    a = np.zeros((h, w, 4), np.float32)
    a[..., 0], a[..., 1], a[..., 2], a[..., 3] = 10.0, 0.1, 1, pair
    a[0, 0, :] = DSM_NODATA
    write_raster(path, a, t, CRS, nodata=DSM_NODATA)
    return t


def test_mosaic_rgb_nearest_pixel_with_nodata(tmp_path):
    """An RGB uint8 mosaic of a third of the cell (the cell centre on a pixel centre) with a nodata hole: every
    point's RGB is its pixel x 257; the points over the hole get 0 and are counted."""
    t = _dsm(tmp_path / "d.tif")
    rng = np.random.default_rng(1)
    m = rng.integers(1, 256, (18, 24, 3)).astype(np.uint8)
    valid = np.ones((18, 24), bool)
    valid[6:9, 9:12] = False                   # the cell (row 2, col 3)
    mt = Affine(1 / 3, 0, 100.0, 0, -1 / 3, 200.0)
    write_raster(tmp_path / "m.tif", m, mt, CRS, nodata=0, valid=valid)
    res = write_cloud(tmp_path / "d.tif", tmp_path / "p.las", "las", CRS, mosaic=tmp_path / "m.tif")
    assert res == CloudWritten(47, "orthomosaic", 1, 8)
    las = laspy.read(tmp_path / "p.las")
    c, r = ~t * (np.asarray(las.x), np.asarray(las.y))
    ci, ri = np.floor(c).astype(int), np.floor(r).astype(int)
    want = m[3 * ri + 1, 3 * ci + 1].astype(np.int64) * 257
    hole = (ri == 2) & (ci == 3)
    want[hole] = 0
    assert np.array_equal(_rgb(las), want) and hole.sum() == 1


def test_16_bit_grey_mosaic_kept(tmp_path):
    _dsm(tmp_path / "d.tif")
    m = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 1000 + 7)
    write_raster(tmp_path / "m.tif", m, Affine(1, 0, 100.0, 0, -1, 200.0), CRS)
    res = write_cloud(tmp_path / "d.tif", tmp_path / "p.laz", "laz", CRS, mosaic=tmp_path / "m.tif")
    assert res.bits == 16 and res.uncolored == 0
    las = laspy.read(tmp_path / "p.laz")
    c, r = ~Affine(1, 0, 100.0, 0, -1, 200.0) * (np.asarray(las.x), np.asarray(las.y))
    want = m[np.floor(r).astype(int), np.floor(c).astype(int)].astype(np.int64)
    rgb = _rgb(las)
    assert np.array_equal(rgb[:, 0], want) and np.array_equal(rgb[:, 1], want) and np.array_equal(rgb[:, 2], want)


def _nadir_view(tmp_path, img: np.ndarray, name: str) -> PairView:
    """A vertical camera 100 m above the DSM's plane z = 10 at (104, 197): 0.5 m per pixel; the image written."""
    cam = Camera(focal_length_mm=20.0, pixel_size_mm=0.1, width=img.shape[1], height=img.shape[0])
    pose = Pose(name, "cam", np.array([104.0, 197.0, 110.0]), np.eye(3))
    write_raster(tmp_path / name, img, Affine.identity(), None)
    return PairView(tmp_path / name, cam, pose)


def test_image_colours_bilinear_and_outside(tmp_path):
    """Colours from the left image of each point's pair: an image whose grey is linear in (col, row), so the
    bilinear value at the projected pixel is known exactly; pair 1's image is small, so some points fall
    outside it (RGB 0, counted); a 3-band image gives RGB."""
    _dsm(tmp_path / "d.tif", pair=0.0)
    _dsm(tmp_path / "d1.tif", pair=1.0)
    cc, rr = np.meshgrid(np.arange(40), np.arange(30))
    ramp = (20 + 3 * cc + 2 * rr).astype(np.uint8)
    big = _nadir_view(tmp_path, ramp, "a.tif")
    rgb_img = np.dstack([ramp, ramp // 2, 255 - ramp]).astype(np.uint8)[:8, :8]
    small = _nadir_view(tmp_path, rgb_img, "b.tif")
    res = write_cloud(tmp_path / "d.tif", tmp_path / "p.las", "las", None, views=[big, small])
    assert res.source == "images" and res.uncolored == 0 and res.bits == 8
    las = laspy.read(tmp_path / "p.las")
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    px = big.pose.pixel_from_ground(big.camera, xyz)
    want = (20 + 3 * px[:, 0] + 2 * px[:, 1]) * 257
    rgb = _rgb(las)
    assert np.abs(rgb[:, 0] - want).max() <= 1.0 and np.array_equal(rgb[:, 0], rgb[:, 1])
    # pair 1: the 8 x 8 px RGB image covers a corner of the DSM only
    res = write_cloud(tmp_path / "d1.tif", tmp_path / "q.las", "las", None, views=[big, small])
    las = laspy.read(tmp_path / "q.las")
    px = small.pose.pixel_from_ground(small.camera, np.column_stack([las.x, las.y, las.z]))
    inside = (px[:, 0] >= -0.5) & (px[:, 0] < 7.5) & (px[:, 1] >= -0.5) & (px[:, 1] < 7.5)
    assert 0 < inside.sum() < len(px) and res.uncolored == int((~inside).sum())
    rgb = _rgb(las)
    assert (rgb[~inside] == 0).all() and (rgb[inside] > 0).all()
    assert not np.array_equal(rgb[inside, 0], rgb[inside, 1])        # three bands: R, G, B differ
    assert np.abs(rgb[inside, 0] - (20 + 3 * px[inside, 0] + 2 * px[inside, 1]) * 257).max() <= 1.0


def test_images_closed_and_reopened(tmp_path, monkeypatch):
    """Pairs alternating by column with one image open at a time (``COLOR_OPEN_IMAGES`` 1): the same colours
    as with both open."""
    pair = np.tile(np.arange(8) % 2, (6, 1)).astype(np.float32)
    _dsm(tmp_path / "d.tif", pair=pair)
    cc, rr = np.meshgrid(np.arange(40), np.arange(30))
    views = [_nadir_view(tmp_path, (20 + 3 * cc + 2 * rr).astype(np.uint8), "a.tif"),
             _nadir_view(tmp_path, (200 - 3 * cc - 2 * rr).astype(np.uint8), "b.tif")]
    both = write_cloud(tmp_path / "d.tif", tmp_path / "p.las", "las", None, views=views)
    monkeypatch.setattr(surface_outputs, "COLOR_OPEN_IMAGES", 1)
    one = write_cloud(tmp_path / "d.tif", tmp_path / "q.las", "las", None, views=views)
    assert both == one == CloudWritten(47, "images", 0, 8)
    a, b = laspy.read(tmp_path / "p.las"), laspy.read(tmp_path / "q.las")
    assert np.array_equal(_rgb(a), _rgb(b))
    xyz = np.column_stack([np.asarray(a.x), np.asarray(a.y), np.asarray(a.z)])
    px = views[0].pose.pixel_from_ground(views[0].camera, xyz)
    want = np.where(np.asarray(a.pair) == 0, 20 + 3 * px[:, 0] + 2 * px[:, 1], 200 - 3 * px[:, 0] - 2 * px[:, 1])
    assert np.abs(_rgb(a)[:, 0] - want * 257).max() <= 1.0


def test_bad_inputs(tmp_path):
    _dsm(tmp_path / "d.tif")
    with pytest.raises(RasterIOError):
        write_cloud(tmp_path / "d.tif", tmp_path / "p.las", "las", None, mosaic=tmp_path / "missing.tif")
    assert not (tmp_path / "p.las").exists()
    with pytest.raises(InvalidInputError, match="`color_bits` must be 8 or 16; got 12"):
        LasWriter(tmp_path / "x.las", (0, 0, 0), color_bits=12)
    assert COLOR_SAMPLING == {"orthomosaic": "nearest", "images": "bilinear"}


def test_las_writer_color_depths(tmp_path):
    """8-bit colours x 257 (255 -> 65535), 16-bit colours as given, both rounded and clipped."""
    xyz = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]])
    with LasWriter(tmp_path / "a.las", (0, 0, 0)) as w:
        w.write(xyz, np.array([[0, 1, 255], [300, -5, 127.6], [10, 20, 30]]))
    assert _rgb(laspy.read(tmp_path / "a.las")).tolist() == [[0, 257, 65535], [65535, 0, 128 * 257],
                                                             [2570, 5140, 7710]]
    with LasWriter(tmp_path / "b.las", (0, 0, 0), color_bits=16) as w:
        w.write(xyz, np.array([[0, 1, 65535], [70000, -5, 1000.4], [10, 20, 30]]))
    assert _rgb(laspy.read(tmp_path / "b.las")).tolist() == [[0, 1, 65535], [65535, 0, 1000], [10, 20, 30]]


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 255), min_size=3, max_size=30), st.integers(0, 65535))
def test_color_depth_property(values, v16):
    """Any 8-bit value v is stored as 257 v (0 -> 0, 255 -> 65535); any 16-bit value as itself."""
    n = len(values) // 3
    c8 = np.array(values[:3 * n]).reshape(n, 3)
    with tempfile.TemporaryDirectory() as d:
        with LasWriter(Path(d) / "a.las", (0, 0, 0)) as w:
            w.write(np.zeros((n, 3)), c8)
        with LasWriter(Path(d) / "b.las", (0, 0, 0), color_bits=16) as w:
            w.write(np.zeros((1, 3)), np.array([[v16, v16, 0]]))
        assert np.array_equal(_rgb(laspy.read(Path(d) / "a.las")), c8 * 257)
        assert _rgb(laspy.read(Path(d) / "b.las")).tolist() == [[v16, v16, 0]]
