"""CLI: ``rectify rpc-adjust`` end to end on a synthetic RPC triplet (tiny GeoTIFFs with RPC tags, a tie-point
CSV and a GCP CSV with a known 2 px along-track bias on one image): the biases are recovered within 0.05 px,
the written RPCs (VRT, .RPB, _RPC.TXT) are read by GDAL and reproduce the adjusted projection within 0.01 px;
bad input gives one line and writes nothing. The Pleiades triplet (shared data) runs with matched ties."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.formats.rpc import read_rpc
from rectify.geometry.rpc import RPC, RPCRefinement
from rectify.raster.rpcfiles import gdal_rpc_project
from tests.support.rpc_synthetic import SIZE, ground_points, measure, render, triplet
from tests.support.shared_data import SHARED_DATA

BIAS = np.array([[0.0, 0.0], [0.0, 2.0], [0.0, 0.0]])


def _image(path: Path, rpc: RPC | None, size=SIZE) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=size[0], height=size[1], count=1, dtype="uint8",
                       compress="deflate", rpcs=None if rpc is None else rpc.to_rasterio()) as ds:
        ds.write(np.zeros((1, size[1], size[0]), np.uint8))
    return path


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    d = tmp_path_factory.mktemp("rpcblock")
    rpcs = triplet()
    imgs = [_image(d / f"img{j + 1}.tif", r) for j, r in enumerate(rpcs)]
    ties = ground_points(120, seed=2)
    gcp = ground_points(8, seed=102)
    im, tr, px = measure(rpcs, ties, BIAS, noise=0.05, seed=3)
    with (d / "ties.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "id", "col", "row"])
        for m in range(len(im)):
            w.writerow([imgs[im[m]].name, f"t{tr[m]}", f"{px[m, 0]:.5f}", f"{px[m, 1]:.5f}"])
    gi, gt, gp = measure(rpcs, gcp, BIAS, noise=0.05, seed=4)
    with (d / "gcps.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "image", "col", "row", "lon", "lat", "h", "sigma_xy", "sigma_h"])
        for m in range(len(gi)):
            g = gcp[gt[m]]
            w.writerow([f"G{gt[m]}", imgs[gi[m]].stem, f"{gp[m, 0]:.5f}", f"{gp[m, 1]:.5f}", f"{g[0]:.9f}",
                        f"{g[1]:.9f}", f"{g[2]:.4f}", "0.02", "0.02"])
    return d, rpcs, imgs


def _run(*args):
    return CliRunner().invoke(cli, ["rpc-adjust", *map(str, args)])


def test_rpc_adjust_end_to_end(block, tmp_path):
    d, rpcs, imgs = block
    out = tmp_path / "out"
    res = _run(*imgs, "-o", out, "--ties", d / "ties.csv", "--gcps", d / "gcps.csv", "--check", "G0,G1",
               "--sigma", "0.05")
    assert res.exit_code == 0, res.output
    for word in ("sigma0", "refit error: max", "GDAL RPC transformer", "accuracy statement from 2 check points"):
        assert word in res.output, word
    doc = json.loads((out / "adjustment.json").read_text())
    assert doc["format"].endswith("rpc_adjustment") and doc["model"] == "shift"
    got = np.array([im["params"] for im in doc["images"]])[:, :, 0]
    assert np.abs(got - BIAS).max() < 0.05
    assert max(im["refit"]["max_px"] for im in doc["images"]) <= 0.01
    assert set(doc["check_points"]) == {"G0", "G1"} and doc["accuracy"]["n"] == 2
    rows = list(csv.DictReader((out / "residuals.csv").open()))
    assert len(rows) == 3 * 120 + 3 * 6 and {"res_col", "res_row", "weight"} <= set(rows[0])
    # GDAL reads each written model and agrees with the adjusted projection
    g = ground_points(30, seed=11)
    for j, img in enumerate(imgs):
        adjusted = RPCRefinement(rpcs[j], "shift", np.array(doc["images"][j]["params_plain"])).project(g)
        assert np.abs(gdal_rpc_project(out / f"{img.stem}.vrt", g) - adjusted).max() < 0.01
        for side in (f"{img.stem}.RPB", f"{img.stem}_RPC.TXT"):
            assert np.abs(read_rpc(out / side).project(g) - adjusted).max() < 0.01
        assert np.abs(rpcs[j].project(g) + BIAS[j] - adjusted).max() < 0.05
    # a sidecar beside a copy of the image (no tags) is what GDAL uses
    bare = tmp_path / "bare"
    bare.mkdir()
    _image(bare / f"{imgs[1].stem}.tif", None)
    shutil.copy(out / f"{imgs[1].stem}.RPB", bare / f"{imgs[1].stem}.RPB")
    ref = RPCRefinement(rpcs[1], "shift", np.array(doc["images"][1]["params_plain"])).project(g)
    assert np.abs(gdal_rpc_project(bare / f"{imgs[1].stem}.tif", g) - ref).max() < 0.01


def test_rpc_adjust_affine_and_no_gcps(block, tmp_path):
    d, _rpcs, imgs = block
    res = _run(*imgs, "-o", tmp_path / "o", "--ties", d / "ties.csv", "--model", "affine", "--sigma", "0.05",
               "--report", tmp_path / "rep")
    assert res.exit_code == 0, res.output
    assert "no GCPs: the datum is the bias prior" in res.output and "numerators" in res.output
    assert "relative to img1.tif" in res.output
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert len(rep["tables"]) == 3 and (tmp_path / "rep" / "report.html").is_file()
    doc = json.loads((tmp_path / "o" / "adjustment.json").read_text())
    assert max(im["refit"]["max_px"] for im in doc["images"]) <= 0.01
    assert max(im["gdal_check_max_px"] for im in doc["images"]) <= 0.01


def test_rpc_adjust_matched_ties_recover_the_bias(tmp_path):
    """The default path: rendered images (a textured DEM seen through the triplet, 400 x 400 px of 2.5 m, the
    2 px along-track bias in image 2), pairs matched and chained; GCPs measured at their true positions."""
    rpcs = triplet(gsd=2.5, size=400)
    imgs = []
    for j, rpc in enumerate(rpcs):
        with rasterio.open(tmp_path / f"s{j + 1}.tif", "w", driver="GTiff", width=400, height=400, count=1,
                           dtype="uint8", rpcs=rpc.to_rasterio()) as ds:
            ds.write(render(j, 400, 2.5, BIAS[j])[None])
        imgs.append(tmp_path / f"s{j + 1}.tif")
    gcp = ground_points(8, seed=102)
    gi, gt, gp = measure(rpcs, gcp, BIAS)
    rows = ["id,image,col,row,lon,lat,h,sigma_xy,sigma_h"]
    rows += [f"G{gt[m]},s{gi[m] + 1},{gp[m, 0]:.6f},{gp[m, 1]:.6f},{gcp[gt[m], 0]:.10f},{gcp[gt[m], 1]:.10f},"
             f"{gcp[gt[m], 2]:.5f},0.02,0.02" for m in range(len(gi))]
    (tmp_path / "gcps.csv").write_text("\n".join(rows) + "\n")
    res = _run(*imgs, "-o", tmp_path / "out", "--gcps", tmp_path / "gcps.csv", "--check", "G0,G1",
               "--max-matches", "400")
    assert res.exit_code == 0, res.output
    assert "matched 3 overlapping pairs, chained" in res.output
    doc = json.loads((tmp_path / "out" / "adjustment.json").read_text())
    assert doc["n_tracks"] > 200
    got = np.array([im["params"] for im in doc["images"]])[:, :, 0]
    assert np.abs(got - BIAS).max() < 0.05
    assert doc["accuracy"]["rmse_3d"] < 0.1  # m, 2.5 m pixels


def _nothing_written(res, out: Path, word: str):
    assert res.exit_code != 0
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert word in res.output, res.output
    assert not out.exists()


def test_bad_input_one_line_nothing_written(block, tmp_path):
    d, rpcs, imgs = block
    out = tmp_path / "out"
    no_rpc = _image(tmp_path / "plain.tif", None)
    _nothing_written(_run(imgs[0], imgs[1], no_rpc, "-o", out, "--ties", d / "ties.csv"), out, "has no RPC")
    far = rpcs[2].to_dict()
    far["long_off"] += 0.5
    far_img = _image(tmp_path / "far.tif", RPC.from_dict(far))
    _nothing_written(_run(imgs[0], imgs[1], far_img, "-o", out, "--ties", d / "ties.csv"), out,
                     "'far.tif' does not overlap any other image")
    bad = tmp_path / "gcps_out.csv"
    text = (d / "gcps.csv").read_text()
    bad.write_text(text + "GX,img1,100.0,100.0,5.67,43.3,200.0,0.02,0.02\n")  # 0.3 degrees east of the block
    _nothing_written(_run(*imgs, "-o", out, "--ties", d / "ties.csv", "--gcps", bad), out,
                     "projects outside every image")
    _nothing_written(_run(*imgs, "-o", out, "--ties", d / "ties.csv", "--model", "affine", "--refit-tolerance",
                          "1e-15"), out, "cannot reach the tolerance")
    _nothing_written(_run(*imgs, "-o", out, "--ties", d / "ties.csv", "--check", "G9"), out, "G9")
    _nothing_written(_run(imgs[0], "-o", out, "--ties", d / "ties.csv"), out, "at least 2 images")
    # tie-point CSV errors name the line
    ties = tmp_path / "ties_bad.csv"
    ties.write_text("image,id,col,row\nimg1.tif,a,1,2\nnope.tif,a,1,2\n")
    _nothing_written(_run(*imgs, "-o", out, "--ties", ties), out, "image 'nope.tif' is not one of the images")
    ties.write_text("image,id,col,row\nimg1.tif,a,1,2\nimg1,a,3,4\n")
    _nothing_written(_run(*imgs, "-o", out, "--ties", ties), out, "measured twice")
    ties.write_text("image,id,col\nimg1.tif,a,1\n")
    _nothing_written(_run(*imgs, "-o", out, "--ties", ties), out, "missing column(s) ['row']")
    # an existing output is kept without --overwrite
    out.mkdir()
    (out / "adjustment.json").write_text("{}")
    res = _run(*imgs, "-o", out, "--ties", d / "ties.csv")
    assert res.exit_code != 0 and "exists" in res.output
    assert (out / "adjustment.json").read_text() == "{}" and sorted(p.name for p in out.iterdir()) == [
        "adjustment.json"]


PLEIADES = SHARED_DATA / "pleiades_triplet"


@pytest.mark.shared
@pytest.mark.slow
def test_pleiades_triplet_runs(tmp_path):
    """The real triplet: matched ties, sigma0 and the refit error printed; the written RPCs within 0.01 px."""
    if not (PLEIADES / "img_03.tif").is_file():
        pytest.skip(f"Pleiades triplet not found under {PLEIADES}")
    imgs = [PLEIADES / f"img_0{i}.tif" for i in (1, 2, 3)]
    res = _run(*imgs, "-o", tmp_path / "o", "--max-matches", "800")
    assert res.exit_code == 0, res.output
    assert "sigma0" in res.output and "refit error: max" in res.output
    doc = json.loads((tmp_path / "o" / "adjustment.json").read_text())
    assert doc["n_tracks"] > 300 and 0 < doc["sigma0"] < 1
    assert max(im["refit"]["max_px"] for im in doc["images"]) <= 0.01
    assert max(im["gdal_check_max_px"] for im in doc["images"]) <= 0.01
    assert max(max(im["residual_rms_px"]) for im in doc["images"]) < 0.3
