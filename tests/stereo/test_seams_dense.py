"""Issue 24, the dense and pair seams: every figure with its unit and its reason, the photos' CRS, a block's
orientation as the dense chain's input, the RPC chain's reference DEM, band descriptions, aligned DSM
grids, no folder left by a failed run, and ``stereo disparity``."""

from __future__ import annotations

import dataclasses
import json
import re

import cv2
import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from rectify.errors import InvalidInputError, StereoError
from rectify.geometry.points import ControlTable
from stereo.actions.scene import make_scene, render, write_scene_inputs
from stereo.block.types import Pose
from stereo.cli.main import cli
from stereo.dense.dsm import DsmGrid, default_cell
from stereo.formats.block import block_orientation_text
from stereo.formats.orientation import write_exterior
from stereo.pair.model import ModelOptions, build_model, match_control
from stereo.relative import RelativeGeometry, RelativeOrientation


# ---------------------------------------------------------------------------- item 9: robust absolute orientation
@pytest.fixture(scope="module")
def scene480():
    return make_scene(0, size_px=480)


def _model(scene, seed, *, blunder=None, n_tie=250, n_ctrl=7):
    """A pair with 0.3 px tie points and control points projected exactly (no image noise)."""
    rng = np.random.default_rng(seed)
    n = n_tie + n_ctrl
    g = scene.random_ground_points(n, rng)
    cam = scene.camera
    sd = np.full((n, 1), 0.3)
    sd[n_tie:] = 0.0
    pl = scene.pixel_from_ground(scene.left, g) + rng.normal(0, 1, (n, 2)) * sd
    pr = scene.pixel_from_ground(scene.right, g) + rng.normal(0, 1, (n, 2)) * sd
    ids = [f"t{i}" for i in range(n_tie)]
    ro = RelativeOrientation.from_pixels(pl[:n_tie], pr[:n_tie], cam, ids=ids)
    gc = g[n_tie:].copy()
    if blunder is not None:
        gc[2] += blunder
    ctrl = ControlTable(tuple(f"c{i}" for i in range(n_ctrl)), pl[n_tie:], pr[n_tie:], gc, crs=scene.crs)
    return build_model(cam.photo_from_pixel(pl[:n_tie]), cam.photo_from_pixel(pr[:n_tie]),
                       RelativeGeometry.from_relative(ro), ids=ids, control=ctrl,
                       control_mm=match_control(ctrl, cam), options=ModelOptions(), pixel_size_mm=cam.pixel_size_mm)


def test_exactly_projected_control_is_not_flagged(scene480):
    """Item 9: with control points projected exactly, the robust (Tukey) absolute orientation flagged 1 to 4
    of 7 good control points in 5 of these 6 pairs (points of 0.1 m flagged while 0.5 m ones were kept): its
    scale, the residuals' own median absolute residual, shrank onto a subset of the control that the
    similarity fits nearly exactly, down to 0.01 of the predicted standard deviations. The scale is now
    at least the a-priori one (residuals within 3 predicted standard deviations are never flagged)."""
    models = [_model(scene480, seed) for seed in range(6)]
    flagged = {seed: [i for i, o in zip(m.absolute.residuals.ids, m.absolute.residuals.outlier, strict=True) if o]
               for seed, m in enumerate(models)}
    assert not any(flagged.values()), flagged
    for m in models:
        test = m.absolute.extra["outlier_test"]
        assert test["scale"] >= 1.0 and test["threshold"] == 3.0
        assert max(test["standardised"].values()) <= 3.0


def test_a_flagged_control_point_is_explained(scene480):
    """A 10 m blunder is still flagged, and the console says why: the criterion with its figures, the
    flagged point's residual (m) and standardised residual, and the largest kept one."""
    m = _model(scene480, 0, blunder=np.array([10.0, 0.0, 0.0]))
    t = m.absolute.residuals
    assert [i for i, o in zip(t.ids, t.outlier, strict=True) if o] == ["c2"]
    lines = m.summary_lines()
    why = next(line for line in lines if line.startswith("robust absolute orientation"))
    assert "exceeds 3 x the robust scale" in why
    mt = re.search(r"flagged: c2 (\d+\.\d+) m \(standardised (\d+\.\d+)\); "
                   r"largest kept: c\d (\d+\.\d+) m \((\d+\.\d+)\)", why)
    assert mt, why
    assert float(mt.group(1)) == pytest.approx(10.0, abs=0.5)
    assert float(mt.group(2)) > 3.0 * m.absolute.extra["outlier_test"]["scale"] > float(mt.group(4))
    assert "1 outlier;" in next(line for line in lines if line.startswith("absolute orientation:"))


@pytest.fixture(scope="module")
def run_dense_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("seam_run")
    scene = make_scene(0, size_px=320)
    inp = write_scene_inputs(scene, d / "input")
    out = d / "run"
    r = CliRunner().invoke(cli, ["run", str(inp["left"]), str(inp["right"]), "--camera", str(inp["camera"]),
                                 "--control", str(inp["control"]), "-o", str(out), "--dense"])
    assert r.exit_code == 0, r.output
    return r.output, out


def test_run_dense_control_rmse_has_its_unit(run_dense_scene):
    """Item 9: `stereo run --dense` printed "RMSE 0.143 (3D)": now the unit and what the figure is."""
    output, out = run_dense_scene
    line = next(x for x in output.splitlines() if x.startswith("dense: absolute orientation to the control"))
    assert re.search(r"RMSE \d+\.\d{3} m \(3D", line), line
    assert "30 full control points" in line
    doc = json.loads((out / "dense" / "dense.json").read_text())
    assert doc["control_unit"] == "m" and doc["n_control"] == 30


# ---------------------------------------------------------------------------- items 10 and 12: the frame pair
@pytest.fixture(scope="module")
def frame_pair(tmp_path_factory):
    """A 160 px synthetic pair: PNG photos, GeoTIFF photos with the scene's CRS, exterior orientations
    without a `crs` key, and a block orientation of both photos."""
    d = tmp_path_factory.mktemp("seam_frame")
    sc = make_scene(3, size_px=160)
    cam = sc.camera.to_dict()
    for side, eo in (("l", sc.left), ("r", sc.right)):
        img = render(sc, "left" if side == "l" else "right")
        cv2.imwrite(str(d / f"{side}.png"), img)
        with rasterio.open(d / f"{side}.tif", "w", driver="GTiff", width=img.shape[1], height=img.shape[0], count=1,
                           dtype="uint8", crs=sc.crs, transform=rasterio.transform.from_origin(0, 0, 1, 1)) as ds:
            ds.write(img, 1)
        write_exterior(d / f"{side}.json", dataclasses.replace(eo, sigma0=0.0, crs=None), camera=cam)
        doc = json.loads((d / f"{side}.json").read_text())
        doc.pop("crs", None)
        (d / f"{side}.json").write_text(json.dumps(doc))
    poses = [Pose("l.tif", "dmc", sc.left.position, sc.left.rotation),
             Pose("r.tif", "dmc", sc.right.position, sc.right.rotation)]
    (d / "orientation.json").write_text(block_orientation_text({"dmc": sc.camera}, poses, crs=sc.crs))
    return d, sc


def test_dense_takes_the_photos_crs(frame_pair, tmp_path):
    """Item 10: orientation files without a `crs` key and photos that both name one: the DSM and the
    summary carry the photos' CRS, and the output says where it came from."""
    d, sc = frame_pair
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["dense", str(d / "l.json"), str(d / "l.tif"), str(d / "r.tif"), "-o", str(out),
                                 "--right-orientation", str(d / "r.json"), "--cloud", "none"])
    assert r.exit_code == 0, r.output
    assert "CRS: taken from the photos" in r.output
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.crs is not None and ds.crs == rasterio.crs.CRS.from_wkt(sc.crs)
    assert json.loads((out / "dense.json").read_text())["crs"]


def test_dense_warns_when_no_crs_is_known(frame_pair, tmp_path):
    d, _ = frame_pair
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["dense", str(d / "l.json"), str(d / "l.png"), str(d / "r.png"), "-o", str(out),
                                 "--right-orientation", str(d / "r.json"), "--cloud", "none"])
    assert r.exit_code == 0, r.output
    assert "warning: no CRS: none in the orientation files, none in the photos" in r.output
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.crs is None


def test_dense_reads_a_block_orientation(frame_pair, tmp_path):
    """Item 12 (dense side): `stereo dense orientation.json LEFT RIGHT` with the block's orientation file;
    the images are found by their file names, or named by --left-id/--right-id."""
    d, sc = frame_pair
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["dense", str(d / "orientation.json"), str(d / "l.tif"), str(d / "r.tif"), "-o",
                                 str(out), "--cloud", "none"])
    assert r.exit_code == 0, r.output
    assert "block images 'l.tif' (left) and 'r.tif' (right)" in r.output
    with rasterio.open(out / "dsm.tif") as ds:
        h = ds.read(1)
        rr, cc = np.nonzero(h != -9999)
        x, y = rasterio.transform.xy(ds.transform, rr, cc)
        assert ds.crs is not None
    dz = h[rr, cc] - sc.height(np.column_stack([x, y]))
    dz = dz[np.isfinite(dz)]
    cell = json.loads((out / "dense.json").read_text())["dsm_cell"]
    assert dz.size > 1000 and np.sqrt(np.mean(dz ** 2)) < cell, (np.sqrt(np.mean(dz ** 2)), cell)
    # the photos under other names: ids given
    out2 = tmp_path / "out2"
    r = CliRunner().invoke(cli, ["dense", str(d / "orientation.json"), str(d / "l.png"), str(d / "r.png"), "-o",
                                 str(out2), "--left-id", "l.tif", "--right-id", "r.tif", "--cloud", "none"])
    assert r.exit_code == 0, r.output
    # bad ids: one line naming the id and the block's images; nothing written
    out3 = tmp_path / "out3"
    r = CliRunner().invoke(cli, ["dense", str(d / "orientation.json"), str(d / "l.tif"), str(d / "r.tif"), "-o",
                                 str(out3), "--left-id", "nope"])
    assert r.exit_code == 1 and "--left-id 'nope' is not an image of the block orientation" in r.output
    assert "'l.tif', 'r.tif'" in r.output and len(r.output.strip().splitlines()) == 1
    assert not out3.exists()
    r = CliRunner().invoke(cli, ["dense", str(d / "l.json"), str(d / "l.tif"), str(d / "r.tif"), "-o", str(out3),
                                 "--right-orientation", str(d / "r.json"), "--left-id", "l.tif"])
    assert r.exit_code == 1 and "go with a block orientation" in r.output and not out3.exists()


# ---------------------------------------------------------------------------- item 13: DSM grids and bands
def test_dsm_grid_origin_on_whole_multiples_of_the_cell(tmp_path):
    """Item 13: the grid's corner lies on whole multiples of the cell (it was half a cell off), so that
    two DSMs of overlapping extents share their cells; the bands are described in the file."""
    cell = 0.5069
    ba, bb = (1000.13, 2000.71, 1010.0, 2010.0), (1003.77, 2003.02, 1012.0, 2013.0)
    a, b = DsmGrid(ba, cell), DsmGrid(bb, cell)
    for g, (x0, y0, x1, y1) in ((a, ba), (b, bb)):
        t = g.transform
        assert abs(t.c / cell - round(t.c / cell)) < 1e-9 and abs(t.f / cell - round(t.f / cell)) < 1e-9
        # the grid covers its bounds, by less than a cell more on the left and top
        assert x0 - cell < t.c <= x0 and y1 <= t.f < y1 + cell
        assert t.c + g.width * cell >= x1 and t.f - g.height * cell <= y0
    # one lattice: b's corner is a whole number of a's cells away
    k = (b.transform.c - a.transform.c) / cell
    assert abs(k - round(k)) < 1e-9
    assert default_cell(0.5069) == 0.51 and default_cell(5.963) == 6.0 and default_cell(14.05) == 14.0
    with pytest.raises(InvalidInputError, match="ground sampling distance"):
        default_cell(float("nan"))
    g = DsmGrid((0, 0, 10, 10), 1.0, crs="EPSG:32633", heights="m above the WGS 84 ellipsoid")
    g.add(np.array([[2.5, 2.5, 10.0], [3.5, 2.5, 11.0]]))
    p = g.result().write(tmp_path / "dsm.tif")
    with rasterio.open(p) as ds:
        assert ds.descriptions[0].startswith("height:") and "WGS 84 ellipsoid" in ds.descriptions[0]
        assert ds.descriptions[1].startswith("count:") and ds.descriptions[2].startswith("filled:")


def test_dense_rasters_describe_their_bands(frame_pair, tmp_path):
    d, _ = frame_pair
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["dense", str(d / "l.json"), str(d / "l.tif"), str(d / "r.tif"), "-o", str(out),
                                 "--right-orientation", str(d / "r.json"), "--cloud", "none"])
    assert r.exit_code == 0, r.output
    for name, n in (("dsm.tif", 3), ("disparity.tif", 1), ("confidence.tif", 2)):
        with rasterio.open(out / name) as ds:
            assert len(ds.descriptions) == n and all(ds.descriptions), (name, ds.descriptions)
    with rasterio.open(out / "dsm.tif") as ds:
        t, cell = ds.transform, ds.transform.a
        assert abs(t.c / cell - round(t.c / cell)) < 1e-6 and abs(t.f / cell - round(t.f / cell)) < 1e-6
    assert "origin on whole multiples of the cell" in r.output


# ---------------------------------------------------------------------------- items 13 and 14: dense-rpc
@pytest.fixture(scope="module")
def rpc_pair(tmp_path_factory):
    """The rendered pushbroom pair of test_rpc_dense and a reference DEM of its true surface (UTM 31N)."""
    from rectify.formats.rpc import rpc_from_raster
    from rectify.geometry.crs import transform_xy
    from tests.stereo.test_rpc_dense import CAMERAS, SIZE, Pushbroom, _texture, dem_lonlat, make_rpc
    from tests.stereo.test_rpc_dense import render as render_pushbroom

    d = tmp_path_factory.mktemp("seam_rpc")
    tex = _texture()
    for side, (p, r, y) in CAMERAS.items():
        cam = Pushbroom(p, r, y)
        rpc = make_rpc(cam, side)
        with rasterio.open(d / f"{side}.tif", "w", driver="GTiff", width=SIZE, height=SIZE, count=1, dtype="uint16",
                           rpcs=rpc.to_rasterio()) as ds:
            ds.write(render_pushbroom(cam, tex), 1)
    centre = rpc_from_raster(d / "left.tif").localize(np.array([[SIZE / 2, SIZE / 2]]), 200.0)[0]
    cx, cy = transform_xy("EPSG:4326", "EPSG:32631", centre[None, :2])[0]
    n, step = 200, 1.0
    xs = cx - n / 2 * step + (np.arange(n) + 0.5) * step
    ys = cy + n / 2 * step - (np.arange(n) + 0.5) * step
    X, Y = np.meshgrid(xs, ys)
    ll = transform_xy("EPSG:32631", "EPSG:4326", np.column_stack([X.ravel(), Y.ravel()]))
    z = dem_lonlat(ll[:, 0], ll[:, 1]).reshape(n, n).astype(np.float32)
    with rasterio.open(d / "dem.tif", "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs="EPSG:32631", transform=rasterio.transform.from_origin(cx - n / 2 * step,
                                                                                 cy + n / 2 * step, step, step)) as ds:
        ds.write(z, 1)
    return d


def test_dense_rpc_reference_dem_bands_and_grid(rpc_pair, tmp_path):
    """Item 13: `stereo dense-rpc --reference-dem`: the statistics (printed and in dense_rpc.json) and the
    pictures as in `stereo dense`; every band of dsm.tif described; the grid on whole multiples of the cell;
    the tiles' real size printed beside --tile."""
    d = rpc_pair
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["dense-rpc", str(d / "left.tif"), str(d / "right.tif"), "-o", str(out), "--roi",
                                 "96,96,192,192", "--tile", "192", "--cloud", "none", "--reference-dem",
                                 str(d / "dem.tif")])
    assert r.exit_code == 0, r.output
    line = next(x for x in r.output.splitlines() if x.startswith("DSM vs reference DEM"))
    found = re.search(r"RMSE (\d+\.\d+) m", line)
    assert found, line
    rmse = float(found.group(1))
    assert rmse < 0.5, line  # the true surface: the DSM's own error (about 0.1 m)
    doc = json.loads((out / "dense_rpc.json").read_text())
    assert doc["comparison"]["rmse"] == pytest.approx(rmse, abs=0.01) and doc["comparison"]["n"] > 1000
    for name in ("report/dz.png", "report/dz_histogram.png", "report/dsm.png"):
        assert (out / name).is_file(), name
    with rasterio.open(out / "dsm.tif") as ds:
        assert [s.split(":")[0] for s in ds.descriptions] == ["height", "count", "filled"]
        assert "WGS 84 ellipsoid" in ds.descriptions[0]
        t, cell = ds.transform, ds.transform.a
        assert cell == default_cell(doc["dsm"]["ground_sampling_distance_m"]) == doc["dsm_cell"]
        assert abs(t.c / cell - round(t.c / cell)) < 1e-6 and abs(t.f / cell - round(t.f / cell)) < 1e-6
    assert "tiles: 1 of 1 matched (192 x 192 px; --tile 192 cuts the 192 x 192 px ROI into 1 x 1 equal tiles)" \
        in r.output
    # a missing reference DEM: refused before any work, nothing made
    r = CliRunner().invoke(cli, ["dense-rpc", str(d / "left.tif"), str(d / "right.tif"), "-o", str(tmp_path / "x"),
                                 "--reference-dem", str(d / "none.tif")])
    assert r.exit_code == 1 and "reference DEM file not found" in r.output and not (tmp_path / "x").exists()


def test_failed_dense_rpc_leaves_no_folder(rpc_pair, tmp_path, monkeypatch):
    """Item 14: a run that fails after it made its output folder (here: no tie point in any tile) removes it."""
    import stereo.actions.dense_rpc as dr

    monkeypatch.setattr(dr, "_tile_ties", lambda *a, **k: (np.zeros((0, 2)), np.zeros((0, 2))))
    out = tmp_path / "new" / "out"
    with pytest.raises(StereoError, match="tie points"):
        dr.run_dense_rpc(rpc_pair / "left.tif", rpc_pair / "right.tif", out, roi=(96, 96, 192, 192),
                         options=dr.RpcDenseOptions(tile=192, cloud_format="none"))
    assert not out.exists() and not (tmp_path / "new").exists()
    # an existing folder stays (empty as it was)
    out.mkdir(parents=True)
    r = CliRunner().invoke(cli, ["dense-rpc", str(rpc_pair / "left.tif"), str(rpc_pair / "right.tif"), "-o",
                                 str(out), "--roi", "96,96,192,192", "--tile", "192"])
    assert r.exit_code == 1 and "tie points" in r.output
    assert out.is_dir() and not any(out.iterdir())


# ---------------------------------------------------------------------------- stereo disparity
def _shifted_pair(d, shift=12, h=200, w=260):
    rng = np.random.default_rng(5)
    big = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + shift)).astype(np.float32), (0, 0), 1.2)
    big = np.round(255 * (big - big.min()) / np.ptp(big)).astype(np.uint8)
    left, right = big[:, :w], big[:, shift:shift + w]  # left[:, x] = right[:, x - shift]: col_l - col_r = shift
    cv2.imwrite(str(d / "left.png"), left)
    cv2.imwrite(str(d / "right.png"), right)
    return d / "left.png", d / "right.png"


def test_disparity_of_a_known_shift(tmp_path):
    left, right = _shifted_pair(tmp_path)
    out = tmp_path / "disp.tif"
    r = CliRunner().invoke(cli, ["disparity", str(left), str(right), "-o", str(out), "--min-disparity", "0",
                                 "--num-disparities", "32"])
    assert r.exit_code == 0, r.output
    assert "searched: 0 .. 31 px" in r.output and "wrote" in r.output
    with rasterio.open(out) as ds:
        assert ds.dtypes[0] == "float32" and ds.nodata == -9999 and (ds.width, ds.height) == (260, 200)
        assert ds.descriptions[0].startswith("disparity")
        dd = ds.read(1)
    ok = dd != -9999
    assert ok.mean() > 0.8 and np.median(np.abs(dd[ok] - 12.0)) < 0.05 and np.mean(np.abs(dd[ok] - 12) > 1) < 0.01
    # without a range: the coarse pass finds it
    out2 = tmp_path / "disp2.tif"
    r = CliRunner().invoke(cli, ["disparity", str(left), str(right), "-o", str(out2)])
    assert r.exit_code == 0, r.output
    with rasterio.open(out2) as ds:
        d2 = ds.read(1)
    assert np.median(d2[d2 != -9999]) == pytest.approx(12.0, abs=0.05)


@pytest.mark.parametrize("case", ["sizes", "missing", "range16", "range_half", "range_wide", "exists"])
def test_disparity_bad_input_one_line_nothing_written(tmp_path, case):
    left, right = _shifted_pair(tmp_path)
    out = tmp_path / "disp.tif"
    args = ["disparity", str(left), str(right), "-o", str(out)]
    expect = {"sizes": "equal heights", "missing": "not found", "range16": "multiple of 16",
              "range_half": "go together", "range_wide": "not below the left image's width",
              "exists": "--overwrite"}[case]
    if case == "sizes":
        cv2.imwrite(str(right), np.zeros((190, 260), np.uint8))
    elif case == "missing":
        args[2] = str(tmp_path / "nope.png")
    elif case == "range16":
        args += ["--min-disparity", "0", "--num-disparities", "20"]
    elif case == "range_half":
        args += ["--num-disparities", "32"]
    elif case == "range_wide":
        args += ["--min-disparity", "0", "--num-disparities", "272"]
    else:
        out.write_bytes(b"x")
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0 and expect in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    if case == "exists":
        assert out.read_bytes() == b"x"
    else:
        assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["left.png", "right.png"] + (
        ["disp.tif"] if case == "exists" else []))


# ---------------------------------------------------------------------------- docs/dense.md against the program
def _resolves(name: str) -> bool:
    import importlib

    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for a in parts[i:]:
                obj = getattr(obj, a)
        except AttributeError:
            return False
        return True
    return False


def test_dense_docs_agree_with_the_program():
    """docs/dense.md listed `stereo run --dense` as not done, named functions by paths that do not exist,
    mixed up s2p's pair and triplet heights, and did not say what --tile does to the tiles."""
    from pathlib import Path

    from stereo.actions.dense import DenseOptions
    from stereo.actions.dense_rpc import RpcDenseOptions

    text = (Path(__file__).resolve().parents[2] / "docs" / "dense.md").read_text()
    not_done = text.split("## Not done", 1)[1].split("\n## ", 1)[0]
    assert not [line for line in not_done.splitlines() if line.startswith("- `stereo run --dense`")]
    names = set(re.findall(r"`((?:stereo|rectify)\.[A-Za-z_][\w.]*)", text))
    assert names and not [n for n in sorted(names) if not _resolves(n)]
    assert f"[--tile {RpcDenseOptions().tile}]" in text and f"`--tile` (default {DenseOptions().matching.tile})" in text
    assert "round(width / tile)" in text and "--tile 300 cuts the 700 x 700 px ROI into 2 x 2 equal tiles" in text
    assert "85-260 m" in text and "La Reunion" in text and "does not fit these crops" not in text
    r = CliRunner().invoke(cli, ["dense-rpc", "--help"])
    assert "round(width / tile)" in " ".join(r.output.split())
