"""Parsers at the field's edge through the commands (issue 32): each case of the issue exits non-zero with one
line naming the problem (or, for a GeoPackage named with '%', gives the CSV's transform), writes nothing and
leaves its inputs untouched. The library side is in ``tests/rectify/test_field_parsers.py``."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli as rectify_cli
from rectify.formats.common import MAX_POINT_ROWS
from rectify.formats.gcps import gcps_text, write_gcps
from rectify.geometry.points import GcpTable
from rectify.raster.io import write_raster
from stereo.actions.scene import make_scene, render
from stereo.cli.main import cli as stereo_cli
from stereo.formats.orientation import write_exterior
from tests.rectify.test_field_parsers import _png_declaring

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 160 px synthetic pair with exact exterior orientations, its camera, 40 tie points, a DEM under it
    and a 64 px orthophoto."""
    d = tmp_path_factory.mktemp("field_parsers")
    sc = make_scene(3, size_px=160)
    cv2.imwrite(str(d / "l.png"), render(sc, "left"))
    cv2.imwrite(str(d / "r.png"), render(sc, "right"))
    cam = sc.camera.to_dict()
    (d / "cam.json").write_text(json.dumps(cam))
    write_exterior(d / "l.json", dataclasses.replace(sc.left, sigma0=0.0, crs=sc.crs), camera=cam)
    write_exterior(d / "r.json", dataclasses.replace(sc.right, sigma0=0.0, crs=sc.crs), camera=cam)
    g = sc.random_ground_points(40, np.random.default_rng(0), margin_px=10.0)
    pl, pr = sc.pixel_from_ground(sc.left, g), sc.pixel_from_ground(sc.right, g)
    (d / "m.csv").write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"{i},{a[0]},{a[1]},{b[0]},{b[1]}\n" for i, (a, b) in enumerate(zip(pl, pr, strict=True))))
    (d / "c.csv").write_text("# crs=EPSG:999999\nid,col_left,row_left,col_right,row_right,x,y,z\n" + "".join(
        f"{i},{a[0]},{a[1]},{b[0]},{b[1]},{q[0]},{q[1]},{q[2]}\n" for i, (a, b, q) in enumerate(zip(pl, pr, g,
                                                                                                  strict=True))))
    write_raster(d / "dem.tif", np.zeros((50, 50), np.float32), Affine(100, 0, -2500, 0, -100, 2500), sc.crs)
    img = (np.random.default_rng(0).random((64, 64)) * 200 + 1).astype(np.uint8)
    write_raster(d / "ortho.tif", img, Affine(1, 0, 500000, 0, -1, 4400000), "EPSG:32618")
    deep = "[" * 10_000 + "]" * 10_000
    for name in ("deep.json", "deep.geojson"):
        (d / name).write_text(deep)
    for name, position in (("eo_str.json", "1,2,3"), ("eo_strs.json", ["1", "2", "3"])):
        doc = json.loads((d / "l.json").read_text())
        doc["position"] = position
        (d / name).write_text(json.dumps(doc))
    return d


def _hashes(d: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir()) if p.is_file()}


def _run(cli, args: list[str], d: Path, out: Path, *words: str) -> str:
    """Run a command that must fail: non-zero exit, one error line holding ``words``, no traceback, nothing in
    ``out``, every input file of ``d`` unchanged."""
    before = _hashes(d)
    out.mkdir(exist_ok=True)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0, r.output
    assert "Traceback" not in r.output, r.output
    errors = [ln for ln in r.output.splitlines() if ln.startswith("Error")]
    assert len(errors) == 1, r.output
    for w in words:
        assert w in errors[0], r.output
    assert sorted(p.name for p in out.iterdir()) == []
    assert _hashes(d) == before
    return errors[0]


# --------------------------------------------------------------------------- JSON nested 10 000 deep
DEEP = {
    "camera": (rectify_cli, ["ortho", "{d}/l.png", "-o", "{o}/o.tif", "--dem", "{d}/dem.tif", "--exterior",
                             "{d}/l.json", "--camera", "{d}/deep.json"]),
    "exterior orientation": (rectify_cli, ["ortho", "{d}/l.png", "-o", "{o}/o.tif", "--dem", "{d}/dem.tif",
                                           "--exterior", "{d}/deep.json", "--camera", "{d}/cam.json"]),
    "orientation": (stereo_cli, ["dense", "{d}/deep.json", "{d}/l.png", "{d}/r.png", "-o", "{o}/dense"]),
    "transform": (rectify_cli, ["warp", "{d}/l.png", "{o}/w.tif", "--transform", "{d}/deep.json"]),
    "GeoJSON": (rectify_cli, ["fit", "{d}/deep.geojson", "-o", "{o}/t.json"]),
    "reconstruction": (stereo_cli, ["block", "{d}/l.png", "{d}/r.png", "--camera", "{d}/cam.json", "--poses",
                                    "opensfm:{d}/deep.json", "-o", "{o}/block"]),
    "block camera": (stereo_cli, ["block", "{d}/l.png", "{d}/r.png", "--camera", "{d}/deep.json", "-o",
                                  "{o}/block"]),
}


@pytest.mark.parametrize("case", list(DEEP))
def test_json_nested_10000_deep(scene, tmp_path, case):
    """Issue 32: RecursionError (camera, orientation, transform, GeoJSON, reconstruction, EO)."""
    cli, args = DEEP[case]
    out = tmp_path / "out"
    _run(cli, [a.format(d=scene, o=out) for a in args], scene, out, "deep.", "levels deep")


# --------------------------------------------------------------------------- CRS, EO values
def test_control_csv_with_unknown_epsg_in_stereo_dense(scene, tmp_path):
    """Issue 32: rasterio's CRSError (after the whole dense run, when the DSM was written)."""
    out = tmp_path / "out"
    _run(stereo_cli, ["dense", str(scene / "l.json"), str(scene / "l.png"), str(scene / "r.png"), "-o",
                      str(out / "dense"), "--right-orientation", str(scene / "r.json"), "--matches",
                      str(scene / "m.csv"), "--control", str(scene / "c.csv")], scene, out,
         "CRSError", "c.csv", "line 1", "EPSG:999999")


@pytest.mark.parametrize("name", ["eo_str.json", "eo_strs.json"])
def test_eo_position_given_as_a_string(scene, tmp_path, name):
    """Issue 32: ValueError."""
    out = tmp_path / "out"
    _run(rectify_cli, ["ortho", str(scene / "l.png"), "-o", str(out / "o.tif"), "--dem", str(scene / "dem.tif"),
                       "--exterior", str(scene / name), "--camera", str(scene / "cam.json")], scene, out,
         name, "position")
    _run(stereo_cli, ["dense", str(scene / name), str(scene / "l.png"), str(scene / "r.png"), "-o",
                      str(out / "dense"), "--right-orientation", str(scene / "r.json")], scene, out, name, "position")


# --------------------------------------------------------------------------- GeoPackage names
@pytest.mark.parametrize("name", ["a%41b", "100%", "it's", "why?", "no#1", "two words"])
def test_geopackage_named_with_uri_characters_gives_the_csv_transform(tmp_path, name):
    """Issue 32: 'a%41b.gpkg' was opened as 'aAb.gpkg' (here a decoy with other points: a different transform,
    exit 0), "it's.gpkg" failed in sqlite3, 'why?.gpkg' created 'why'. Now the transform equals the CSV's."""
    d = tmp_path / "in"
    d.mkdir()
    pix = np.array([[1.0, 2], [300, 4], [5, 270], [280, 290], [150, 140], [40, 220]])
    tgt = np.column_stack([500000 + 2 * pix[:, 0] + 0.1 * pix[:, 1], 4400000 - 2 * pix[:, 1] + 0.05 * pix[:, 0]])
    g = GcpTable(tuple(f"g{i}" for i in range(6)), pix, tgt, None, np.zeros(6, dtype=bool), "EPSG:32633")
    write_gcps(d / "aAb.gpkg", GcpTable(g.ids, pix * 1.5 + 7, tgt, None, g.check, g.crs))  # the decoy
    (d / "gcps.csv").write_text(gcps_text(g))
    write_gcps(d / f"{name}.gpkg", g)
    before = _hashes(d)
    out = tmp_path / "out"
    out.mkdir()
    runs = {}
    for src in ("gcps.csv", f"{name}.gpkg"):
        t = out / f"{len(runs)}.json"
        r = CliRunner().invoke(rectify_cli, ["fit", str(d / src), "-o", str(t), "--method", "affine"])
        assert r.exit_code == 0, r.output
        runs[src] = json.loads(t.read_text())
    csv_doc, gpkg_doc = runs.values()
    assert gpkg_doc["matrix"] == csv_doc["matrix"]
    assert gpkg_doc["rmse"] == csv_doc["rmse"] and gpkg_doc["crs"] == csv_doc["crs"]
    assert _hashes(d) == before  # and no file created beside the inputs


# --------------------------------------------------------------------------- images, grids
def test_chessboard_image_declaring_more_pixels_than_opencv_allows(tmp_path):
    """Issue 32: cv2.error."""
    d = tmp_path / "in"
    d.mkdir()
    _png_declaring(d / "huge.png", 100_000, 100_000)
    out = tmp_path / "out"
    _run(stereo_cli, ["calibrate", str(d / "huge.png"), "--chessboard", "9x6", "-o", str(out / "cam.json")], d, out,
         "huge.png", "100000 x 100000 px", str(1 << 30))


@pytest.mark.parametrize("resolution", ["1e-320", "1e-300", "1e-6"])
def test_mosaic_with_a_tiny_resolution(scene, tmp_path, resolution):
    """Issue 32: MemoryError (1e-320: OverflowError); refused up front with the numbers."""
    out = tmp_path / "out"
    msg = _run(rectify_cli, ["mosaic", str(scene / "ortho.tif"), "-o", str(out / "m.tif"), "--resolution", resolution],
               scene, out, "px", "coarser --resolution")
    assert f"{float(resolution):.6g}" in msg


# --------------------------------------------------------------------------- tables past the row limit
def _rows(path: Path, head: str, fmt: str, n: int) -> Path:
    with open(path, "w") as fh:
        fh.write("# crs=EPSG:32633\n" + head + "\n")
        for s in range(0, n, 200_000):
            fh.write("".join(fmt.format(i, i % 160, 500000 + i % 9000) + "\n" for i in range(s, min(n, s + 200_000))))
    return path


def test_pose_block_control_and_stereo_control_past_the_limit(scene, tmp_path):
    """Issue 32: pose, block-control and stereo-control CSVs of millions of rows died with MemoryError; one row
    past the limit is refused with the limit named."""
    d = tmp_path / "in"
    d.mkdir()
    n = MAX_POINT_ROWS + 1
    _rows(d / "poses.csv", "image,x,y,z,omega,phi,kappa", "i{0}.png,{2},4400000,900,0,0,{1}", n)
    _rows(d / "control.csv", "id,image,col,row,x,y,z", "p{0},l.png,{1},{1},{2},4400000,100", n)
    _rows(d / "stereo.csv", "id,col_left,row_left,col_right,row_right,x,y,z", "p{0},{1},{1},{1},{1},{2},4400000,1", n)
    for name in ("l.png", "r.png", "cam.json", "l.json", "r.json", "m.csv"):
        (d / name).write_bytes((scene / name).read_bytes())
    out = tmp_path / "out"
    limit = f"more than {MAX_POINT_ROWS}"
    _run(stereo_cli, ["block", str(d / "l.png"), str(d / "r.png"), "--camera", str(d / "cam.json"), "--poses",
                      str(d / "poses.csv"), "-o", str(out / "b")], d, out, "poses.csv", limit)
    _run(stereo_cli, ["block", str(d / "l.png"), str(d / "r.png"), "--camera", str(d / "cam.json"), "--control",
                      str(d / "control.csv"), "-o", str(out / "b")], d, out, "control.csv", limit)
    _run(stereo_cli, ["dense", str(d / "l.json"), str(d / "l.png"), str(d / "r.png"), "-o", str(out / "dense"),
                      "--right-orientation", str(d / "r.json"), "--matches", str(d / "m.csv"), "--control",
                      str(d / "stereo.csv")], d, out, "stereo.csv", limit)


_PEAK = textwrap.dedent("""
    # the command's peak RSS: the child inherits this small wrapper's peak across exec, not the test runner's
    import json, resource, subprocess, sys, time
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", "from rectify.cli.main import cli; cli()", *sys.argv[1:]],
                       capture_output=True, text=True)
    print(json.dumps({"rc": r.returncode, "output": r.stdout + r.stderr, "seconds": time.perf_counter() - t,
                      "peak_kb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))
""")


@pytest.mark.slow
def test_ten_million_row_gcp_csv_is_refused_within_memory(tmp_path):
    """Issue 32: a GCP CSV of 10 million rows reached 9.7 GB (12.1 GB measured here before the change) and died
    with MemoryError. Now `rectify fit` refuses it while reading, the limit named, in a few seconds and well under
    2 GB (peak RSS of the command, measured in a subprocess)."""
    big = tmp_path / "big.csv"
    with open(big, "w") as fh:
        fh.write("# crs=EPSG:32633\nid,col,row,x,y,z\n")
        for s in range(0, 10_000_000, 500_000):
            fh.write("".join(f"gcp{i},{i % 4000}.25,{i % 3000}.75,{500000 + i % 9000}.5,4400000.125,{i % 500}.5\n"
                             for i in range(s, s + 500_000)))
    out = tmp_path / "t.json"
    r = subprocess.run([sys.executable, "-c", _PEAK, "fit", str(big), "-o", str(out)], capture_output=True,
                       text=True, cwd=ROOT, timeout=600)
    res = json.loads(r.stdout)
    assert res["rc"] != 0 and "Traceback" not in res["output"], res
    assert f"more than {MAX_POINT_ROWS} GCP rows" in res["output"], res
    assert res["peak_kb"] / 1024 < 500, res
    assert res["seconds"] < 60, res
    assert not out.exists()
