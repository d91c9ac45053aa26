"""The block -> one DSM + one orthomosaic + one point cloud chain of ``stereo surface`` and ``stereo block
--surface`` on rendered blocks with known surface and texture (issue 27)."""

from __future__ import annotations

import errno
import json
import math

import cv2
import laspy
import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

import stereo.actions.surface_outputs as surface_outputs
from rectify.errors import InvalidInputError
from rectify.geometry.accuracy import AccuracyStatement
from rectify.raster.io import write_raster
from stereo.cli.main import cli
from tests.support.block_example import write_example_block
from tests.support.block_surface import GSD, make_surface_block, read_dsm, truth_on
from tests.support.surface_checks import mosaic_patches, mosaic_shifts, write_orthority_orientation

CRS = "EPSG:32633"


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """A 3 x 4 block (true poses, in a projected CRS) with 40 check points on the terrain, run once through
    ``stereo surface --check --keep-orthophotos``."""
    root = tmp_path_factory.mktemp("surface_chain")
    blk = make_surface_block(root / "o", images=root / "img", supersample=1)
    doc = json.loads((root / "o" / "orientation.json").read_text())
    doc["crs"] = CRS
    (root / "o" / "orientation.json").write_text(json.dumps(doc))
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(0, 70, 40), rng.uniform(-60, 0, 40)])
    z = blk.terrain.height(xy) + rng.normal(0, 0.05, 40)      # surveyed heights with 5 cm errors
    lines = ["id,x,y,z"] + [f"c{i},{x:.4f},{y:.4f},{h:.4f}" for i, ((x, y), h) in enumerate(zip(xy, z, strict=True))]
    (root / "check.csv").write_text("\n".join(lines) + "\n")
    out = root / "out"
    r = CliRunner().invoke(cli, ["surface", str(root / "o"), "-o", str(out), "--images", str(root / "img"),
                                 "--ground-z", "50", "--check", str(root / "check.csv"), "--keep-orthophotos"])
    assert r.exit_code == 0, r.output
    return root, blk, out, r.output, np.round(np.column_stack([xy, z]), 4)   # as written


def test_one_dsm_within_half_a_ground_pixel(chain):
    _root, blk, out, text, _chk = chain
    bands, tr, _desc = read_dsm(out / "dsm.tif")
    err = bands[0] - truth_on(tr, bands[0].shape, blk.terrain)
    ok = np.isfinite(err)
    assert ok.sum() > 50_000
    assert np.sqrt(np.mean(err[ok] ** 2)) <= 0.5 * GSD
    assert "orthomosaic: " in text and "point cloud: " in text


def test_orthomosaic_against_the_orthophotos_and_the_texture(chain):
    """Per 32 px patch taken wholly from one image (provenance), the phase-correlation shift of the mosaic
    against that image's own true orthophoto (same grid alignment) <= 0.1 px; against the rendered texture
    (the truth) <= 0.5 px. The mosaic is a COG with overviews and a provenance raster."""
    _root, blk, out, _text, _chk = chain
    doc = json.loads((out / "pairs.json").read_text())
    names = doc["ortho"]["images"]
    assert sorted(doc["ortho"]["kept_orthophotos"]) == sorted(f"ortho_{n[:-4]}.tif" for n in names)
    with rasterio.open(out / "ortho.tif") as ds:
        mt = ds.transform
        assert ds.overviews(1) and ds.tags()["MOSAIC_SEAMS"] == "normal" and ds.crs.to_string() == CRS
    with rasterio.open(out / "ortho.source.tif") as ds:
        src = ds.read(1)
    assert len(np.unique(src[src > 0])) >= 10                   # most images reach the mosaic
    P = 32
    win = cv2.createHanningWindow((P, P), cv2.CV_64F)
    shifts, truth_shifts = [], []
    for r0, c0, a, b in mosaic_patches(out, P):
        (dx, dy), _ = cv2.phaseCorrelate(a, b, win)
        shifts.append(math.hypot(dx, dy))
        cx, cy = np.meshgrid(np.arange(P) + 0.5 + c0, np.arange(P) + 0.5 + r0)
        gx, gy = mt * (cx.ravel(), cy.ravel())
        tex = blk.terrain._sample(blk.terrain.texture, np.column_stack([gx, gy])).reshape(P, P)
        (dx, dy), _ = cv2.phaseCorrelate(a, tex.astype(np.float64) * 255, win)
        truth_shifts.append(math.hypot(dx, dy))
    assert len(shifts) >= 20
    assert max(shifts) <= 0.1, shifts
    assert np.median(truth_shifts) <= 0.5, truth_shifts


def test_one_cloud_with_sigma_z_and_pair(chain):
    _root, _blk, out, _text, _chk = chain
    bands, tr, _desc = read_dsm(out / "dsm.tif")
    las = laspy.read(out / "points.laz")
    dims = set(las.point_format.extra_dimension_names)
    assert {"sigma_z", "pair", "count"} <= dims
    ok = np.isfinite(bands[0])
    assert len(las.points) == ok.sum()
    # every point is its DSM cell: centre, height, sigma, pair
    c, r = ~tr * (np.asarray(las.x), np.asarray(las.y))
    ci, ri = np.floor(c).astype(int), np.floor(r).astype(int)
    assert np.allclose(c - ci, 0.5) and np.allclose(r - ri, 0.5)
    assert np.allclose(np.asarray(las.z), bands[0][ri, ci], atol=1e-3)
    assert np.allclose(np.asarray(las.sigma_z), bands[1][ri, ci], rtol=1e-6)
    assert np.array_equal(np.asarray(las.pair), bands[3][ri, ci].astype(int))
    n_pairs = len(json.loads((out / "pairs.json").read_text())["pairs"])
    assert np.asarray(las.pair).max() < n_pairs and np.asarray(las.count).min() >= 1


def test_check_point_statement_by_hand(chain):
    """The DSM's vertical statement at the check points: bilinear DSM heights by hand, the errors and the
    statement's figures from them."""
    _root, _blk, out, text, chk = chain
    bands, tr, _desc = read_dsm(out / "dsm.tif")
    z = bands[0]
    c, r = ~tr * (chk[:, 0], chk[:, 1])
    c, r = c - 0.5, r - 0.5
    c0, r0 = np.floor(c).astype(int), np.floor(r).astype(int)
    inside = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < z.shape[1]) & (r0 + 1 < z.shape[0])
    c0, r0 = np.where(inside, c0, 0), np.where(inside, r0, 0)
    fc, fr = c - c0, r - r0
    h = ((1 - fr) * ((1 - fc) * z[r0, c0] + fc * z[r0, c0 + 1]) + fr * ((1 - fc) * z[r0 + 1, c0] + fc *
                                                                         z[r0 + 1, c0 + 1]))
    h[~inside] = np.nan
    ok = np.isfinite(h)
    assert ok.sum() >= 30
    e = h[ok] - chk[ok, 2]
    rz = math.sqrt(np.mean(e ** 2))
    doc = json.loads((out / "pairs.json").read_text())["check_points"]
    assert doc["outside"] == int((~ok).sum())
    st = doc["statement"]
    assert st["rmse_z"] == pytest.approx(rz, rel=1e-5) and st["rmse_r"] is None
    assert st["le90"] == pytest.approx(1.6448536269514722 * rz, rel=1e-5)
    assert st["interval_z" if "interval_z" in st else "rmse_interval"]["z"] == pytest.approx(
        list(AccuracyStatement.vertical(e).interval_z), rel=1e-5)
    assert rz <= 0.5 * GSD                          # the DSM within half a pixel at the check points too
    assert "RMSE_z" in text and "LE90" in text and "RMSE_V" in text and "RMSE_H" not in text


def test_disk_full_while_writing_the_orthophotos_leaves_nothing(chain, tmp_path, monkeypatch):
    root, _blk, _out, _text, _chk = chain
    real = surface_outputs.orthorectify
    calls = {"n": 0}

    def full(src, dst, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:                          # the third orthophoto: half written, then the disk is full
            dst.write_bytes(b"II*\0partial")
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(surface_outputs, "orthorectify", full)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["surface", str(root / "o"), "-o", str(out), "--images", str(root / "img"),
                                 "--ground-z", "50"])
    assert r.exit_code != 0 and calls["n"] == 3
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert "no space left on device" in r.output.lower()
    assert not out.exists()


def test_bad_chain_options(chain, tmp_path):
    root, _blk, _out, _text, _chk = chain
    bad = tmp_path / "bad.csv"
    bad.write_text("id,x,y\nc1,1,2\n")
    for args, msg in ((["--check", str(tmp_path / "none.csv")], "check points file not found"),
                      (["--check", str(bad)], "missing column(s) ['z']")):
        r = CliRunner().invoke(cli, ["surface", str(root / "o"), "-o", str(tmp_path / "o"), "--images",
                                     str(root / "img"), "--ground-z", "50", *args])
        assert r.exit_code == 1 and msg in r.output and "Traceback" not in r.output, r.output
        assert not (tmp_path / "o").exists()


def test_stereo_block_with_surface(tmp_path):
    """``stereo block --surface``: the block adjusted from GNSS poses, then its surface in OUTDIR/surface."""
    images, _poses, _xyz = write_example_block(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["block", *map(str, images), "--camera", str(tmp_path / "camera.json"), "--poses",
                                 str(tmp_path / "poses.csv"), "--gnss-sigma", "0.05", "--no-report", "--surface",
                                 "--control", str(tmp_path / "control.csv"), "--check", "C1,C6,C10",
                                 "--control-sigma", "0.01", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "surface: DSM: " in r.output and "surface: orthomosaic: " in r.output
    # the block's check points check the DSM as well
    chk = json.loads((out / "surface" / "pairs.json").read_text())["check_points"]
    assert [p["id"] for p in chk["points"]] == ["C1", "C6", "C10"]
    assert "surface: check points control.csv: 3" in r.output
    names = sorted(p.name for p in (out / "surface").iterdir())
    assert names == ["dsm.tif", "ortho.source.tif", "ortho.tif", "pairs.json", "points.laz"]
    doc = json.loads((out / "surface" / "pairs.json").read_text())
    assert doc["orientation_sigma"] == "points" and doc["cloud"]["points"] > 10_000


@pytest.mark.shared
def test_ngi_pair_as_a_block_of_two_through_the_chain(ngi_pair, tmp_path):
    """The NGI pair as a block of two (orthority's AT orientations) -> DSM against dem.tif, the orthomosaic
    against the two single true orthophotos, the cloud (figures in docs/surface.md)."""
    write_orthority_orientation(ngi_pair, tmp_path / "o")
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["surface", str(tmp_path / "o"), "-o", str(out), "--images", str(ngi_pair),
                                 "--ground-z", "429.33", "--reference-dem", str(ngi_pair / "dem.tif"),
                                 "--keep-orthophotos"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "pairs.json").read_text())
    cmp = doc["comparison"]
    # measured: RMSE 5.19 m, NMAD 3.88 m, coverage 80.7 %, LE90 8.54 m (observed 7.60 m)
    assert cmp["rmse"] <= 9.0 and cmp["nmad"] <= 5.0 and cmp["coverage"] >= 0.7 and cmp["le90"] <= 15.0, cmp
    shifts = mosaic_shifts(out)
    assert len(shifts) >= 20 and max(shifts) <= 0.1, shifts     # measured: 45 patches, max 0.004 px
    las = laspy.read(out / "points.laz")
    assert len(las.points) == cmp["n"] and {"sigma_z", "pair"} <= set(las.point_format.extra_dimension_names)


def test_stereo_block_surface_refused_before_work(tmp_path):
    """--surface with a projective method (no metric block) or images in two folders: refused before any work."""
    images, _poses, _xyz = write_example_block(tmp_path)
    other = tmp_path / "b"
    other.mkdir()
    moved = other / images[-1].name
    images[-1].rename(moved)
    for args, msg in (([*map(str, images[:-1]), "--method", "affine"], "--surface needs a metric block"),
                      ([*map(str, images[:-1]), str(moved), "--camera", str(tmp_path / "camera.json")],
                       "--surface needs the images in one folder")):
        r = CliRunner().invoke(cli, ["block", *args, "--surface", "-o", str(tmp_path / "out")])
        assert r.exit_code == 1 and msg in r.output and "Traceback" not in r.output, r.output
        assert not (tmp_path / "out").exists()


def test_dsm_heights_at_points_reproduce_a_plane(tmp_path):
    """Bilinear heights reproduce a plane exactly; a point next to a cell of no height or off the grid is NaN;
    a check point id with two positions is refused."""
    H, W = 40, 50
    cc, rr = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    t = Affine(0.5, 0, 100.0, 0, -0.5, 200.0)
    x, y = t.c + t.a * cc, t.f + t.e * rr
    z = 10 + 0.3 * x - 0.2 * y
    z[30, 40] = -9999.0
    bands = np.dstack([z, np.full_like(z, 0.1), np.ones_like(z), np.zeros_like(z)]).astype(np.float32)
    write_raster(tmp_path / "d.tif", bands, t, CRS, nodata=-9999.0)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(101, 118, 200), rng.uniform(183, 199, 200)])
    h = surface_outputs.heights_at(tmp_path / "d.tif", pts)
    assert np.allclose(h, 10 + 0.3 * pts[:, 0] - 0.2 * pts[:, 1], atol=2e-5)
    xy_hole = t * (40.5 + 0.3, 30.5 - 0.2)
    off = (t.c - 1.0, 190.0)
    assert np.isnan(surface_outputs.heights_at(tmp_path / "d.tif", np.array([xy_hole, off]))).all()
    (tmp_path / "c.csv").write_text("id,x,y,z\na,110,190,1\na,110,190.5,1\n")
    with pytest.raises(InvalidInputError, match="check point 'a' has two positions"):
        surface_outputs.read_check_points(tmp_path / "c.csv")
