"""``stereo dense`` end to end on a tiny synthetic pair, and its bad input (issue 14)."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from stereo.actions.scene import make_scene, render
from stereo.cli.main import cli
from stereo.formats.orientation import write_exterior


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A 160 px synthetic pair with exact exterior orientations (camera inside) and 40 exact tie points."""
    d = tmp_path_factory.mktemp("dense_pair")
    sc = make_scene(3, size_px=160)
    cv2.imwrite(str(d / "l.png"), render(sc, "left"))
    cv2.imwrite(str(d / "r.png"), render(sc, "right"))
    cam = sc.camera.to_dict()
    # known orientations: sigma0 0 (not adjusted), so that the JSON holds no NaN
    write_exterior(d / "l.json", dataclasses.replace(sc.left, sigma0=0.0, crs=sc.crs), camera=cam)
    write_exterior(d / "r.json", dataclasses.replace(sc.right, sigma0=0.0, crs=sc.crs), camera=cam)
    g = sc.random_ground_points(40, np.random.default_rng(0), margin_px=10.0)
    pl, pr = sc.pixel_from_ground(sc.left, g), sc.pixel_from_ground(sc.right, g)
    (d / "m.csv").write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"{i},{a[0]},{a[1]},{b[0]},{b[1]}\n" for i, (a, b) in enumerate(zip(pl, pr, strict=True))))
    return d, sc


def _args(d, out, *extra):
    return ["dense", str(d / "l.json"), str(d / "l.png"), str(d / "r.png"), "-o", str(out),
            "--right-orientation", str(d / "r.json"), "--matches", str(d / "m.csv"), *extra]


def test_dense_end_to_end(pair, tmp_path):
    d, sc = pair
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(d, out, "--cloud", "ply"))
    assert r.exit_code == 0, r.output
    for key in ("normal case:", "vertical parallax", "disparity:", "points:", "DSM:", "outputs in"):
        assert key in r.output, r.output
    for name in ("left_normal.tif", "right_normal.tif", "disparity.tif", "confidence.tif", "dsm.tif", "dense.json",
                 "points.ply", "report/dsm.png", "report/disparity.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "dense.json").read_text())
    assert summary["frame"] == "ground" and summary["n_points"] > 5000
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.count == 3 and ds.nodata == -9999 and ds.crs is not None
        h = ds.read(1)
        rr, cc = np.nonzero(h != -9999)
        x, y = rasterio.transform.xy(ds.transform, rr, cc)
    dz = h[rr, cc] - sc.height(np.column_stack([x, y]))
    dz = dz[np.isfinite(dz)]
    # the DSM agrees with the true surface (tiny photos: 1 GSD here is about 14 m)
    gsd = summary["dsm_cell"]
    assert dz.size > 1000 and abs(np.median(dz)) < 0.2 * gsd and np.sqrt(np.mean(dz ** 2)) < gsd, \
        (np.median(dz), np.sqrt(np.mean(dz ** 2)), gsd)


def _one_line_error(r, *words):
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error:"), r.output
    for w in words:
        assert w in lines[0], r.output


def test_dense_missing_file(pair, tmp_path):
    d, _ = pair
    out = tmp_path / "out"
    args = _args(d, out)
    args[3] = str(tmp_path / "nope.png")
    r = CliRunner().invoke(cli, args)
    _one_line_error(r, "not found", "nope.png")
    assert not out.exists()


def test_dense_bad_orientation_json(pair, tmp_path):
    d, _ = pair
    out = tmp_path / "out"
    bad = tmp_path / "ro.json"
    bad.write_text("{ not json")
    r = CliRunner().invoke(cli, ["dense", str(bad), str(d / "l.png"), str(d / "r.png"), "-o", str(out)])
    _one_line_error(r, "ro.json")
    assert not out.exists()
    bad.write_text(json.dumps({"format": "rectify-stereo/relative-orientation", "version": 1, "base": [1, 0]}))
    r = CliRunner().invoke(cli, ["dense", str(bad), str(d / "l.png"), str(d / "r.png"), "-o", str(out)])
    _one_line_error(r, "ro.json")
    assert not out.exists()


def test_dense_output_exists_without_overwrite(pair, tmp_path):
    d, _ = pair
    out = tmp_path / "out"
    out.mkdir()
    (out / "dsm.tif").write_bytes(b"keep me")
    r = CliRunner().invoke(cli, _args(d, out))
    _one_line_error(r, "dsm.tif")
    # nothing written: the folder holds only what was there
    assert sorted(p.name for p in out.iterdir()) == ["dsm.tif"] and (out / "dsm.tif").read_bytes() == b"keep me"
