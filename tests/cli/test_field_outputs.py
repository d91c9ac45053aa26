"""Issue 32, outputs: no input destroyed, no empty product, nothing partial, no hang.

Each case: a one-line error (no traceback), a non-zero exit, nothing left at any output path (no
file, no hidden temporary, no folder the command created) and every input unchanged (hashed before
and after). The full disk is the 200 KiB tmpfs of ``tests/conftest.py`` (root only), filled as
``tests/cli/test_faults.py`` does.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli as rectify_cli
from rectify.geometry.rotation import matrix_from_angles
from stereo.actions.scene import make_scene, render
from stereo.cli.main import cli as stereo_cli
from stereo.formats.orientation import write_exterior
from tests.cli.test_calibrate import _render
from tests.cli.test_faults import _entries, _fill, _hash
from tests.cli.test_ortho import CRS, E0, N0, _dem, _image

# ----------------------------------------------------------------------------- helpers


def _one_line_error(r, *words: str) -> str:
    assert r.exit_code not in (0, None), r.output
    assert "Traceback" not in r.output, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    err = [ln for ln in lines if ln.startswith("Error")]
    assert len(err) == 1, r.output
    for w in words:
        assert w in err[0], (w, err[0])
    return err[0]


def _tree(d: Path) -> list[str]:
    """Every path below ``d`` (hidden temporaries included), relative."""
    return sorted(p.relative_to(d).as_posix() for p in Path(d).rglob("*"))


def _points_csv(d: Path) -> Path:
    """A measured 3D test field (two views) as an observation CSV with object coordinates."""
    from tests.support.calibration_synthetic import field_scene

    sc = field_scene(np.random.default_rng(3), n_views=2, n_points=40, noise_px=0.2)
    rows = ["view,point,col,row,x,y,z"]
    for v in sc.views:
        for p, (c, r), (x, y, z) in zip(v.ids, v.pixel, v.object_xyz, strict=True):
            rows.append(f"{v.name},{p},{c},{r},{x},{y},{z}")
    obs = d / "obs.csv"
    obs.write_text("\n".join(rows) + "\n")
    return obs


@pytest.fixture()
def frame(tmp_path):
    """A frame photo over a DEM (tests/cli/test_ortho.py's), its camera and exterior orientation."""
    _dem(tmp_path / "dem.tif")
    _image(tmp_path / "img.tif", 80, 60)
    (tmp_path / "cam.json").write_text(json.dumps({"focal_length_mm": 10.0, "pixel_size_mm": 0.02, "width": 80,
                                                   "height": 60}))
    R = matrix_from_angles(0.03, -0.02, 0.2)
    (tmp_path / "eo.json").write_text(json.dumps({"position": [E0, N0, 600.0], "rotation": R.tolist(), "crs": CRS}))
    return tmp_path


def _ortho_args(d: Path, out: Path, *extra: str) -> list[str]:
    return ["ortho", str(d / "img.tif"), "--dem", str(d / "dem.tif"), "--camera", str(d / "cam.json"),
            "--exterior", str(d / "eo.json"), "-o", str(out), "--resolution", "2", *extra]


def _dense_pair(d: Path, size: int = 160) -> Path:
    """A synthetic frame pair with exact exterior orientations and 40 exact tie points (tests/cli/test_dense.py's)."""
    d.mkdir(parents=True, exist_ok=True)
    sc = make_scene(3, size_px=size)
    cv2.imwrite(str(d / "l.png"), render(sc, "left"))
    cv2.imwrite(str(d / "r.png"), render(sc, "right"))
    cam = sc.camera.to_dict()
    write_exterior(d / "l.json", dataclasses.replace(sc.left, sigma0=0.0, crs=sc.crs), camera=cam)
    write_exterior(d / "r.json", dataclasses.replace(sc.right, sigma0=0.0, crs=sc.crs), camera=cam)
    g = sc.random_ground_points(40, np.random.default_rng(0), margin_px=10.0)
    pl, pr = sc.pixel_from_ground(sc.left, g), sc.pixel_from_ground(sc.right, g)
    (d / "m.csv").write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"{i},{a[0]},{a[1]},{b[0]},{b[1]}\n" for i, (a, b) in enumerate(zip(pl, pr, strict=True))))
    return d


def _dense_args(d: Path, out: Path, right: str = "r.json", *extra: str) -> list[str]:
    return ["dense", str(d / "l.json"), str(d / "l.png"), str(d / "r.png"), "-o", str(out), "--right-orientation",
            str(d / right), "--matches", str(d / "m.csv"), *extra]


# ----------------------------------------------------------------------------- inputs destroyed
@pytest.mark.parametrize("how", ["same", "symlink", "hardlink", "dotdot"])
def test_calibrate_output_naming_an_input_image_is_refused(tmp_path, how):
    """`stereo calibrate -o` naming one of its own chessboard images (as given, through a symlink, a hard link
    or a `..` path): refused before any detection, even with --overwrite; the image is unchanged."""
    paths = [Path(p) for p in _render(tmp_path, n=3)]
    out = {"same": paths[1], "symlink": tmp_path / "cam.json", "hardlink": tmp_path / "cam.json",
           "dotdot": tmp_path / "sub" / ".." / paths[1].name}[how]
    if how == "symlink":
        out.symlink_to(paths[1])
    elif how == "hardlink":
        os.link(paths[1], out)
    elif how == "dotdot":
        (tmp_path / "sub").mkdir()
    before, names = _hash(*paths), _tree(tmp_path)
    r = CliRunner().invoke(stereo_cli, ["calibrate", *map(str, paths), "--chessboard", "7x5", "-o", str(out),
                                        "--overwrite"])
    _one_line_error(r, "is also an input", "inputs are never modified")
    assert _hash(*paths) == before and _tree(tmp_path) == names
    if how == "symlink":
        assert out.is_symlink()


def test_calibrate_output_naming_its_observations_csv_is_refused(tmp_path):
    """`-o` naming the observations CSV, and a report folder holding an input under a report file's name (the
    report's files are part of the output plan): refused before any work, even with --overwrite."""
    obs = _points_csv(tmp_path)
    rep = tmp_path / "rep"
    rep.mkdir()
    field = rep / "calibration.json"
    field.write_text("point,x,y,z\n")
    for args, clash in ((["-o", str(obs)], obs),
                        (["--field", str(field), "-o", str(tmp_path / "cam.json"), "--report", str(rep)], field)):
        before, names = _hash(obs, field), _tree(tmp_path)
        r = CliRunner().invoke(stereo_cli, ["calibrate", "--points", str(obs), "--size", "640x480", *args,
                                            "--overwrite"])
        _one_line_error(r, str(clash), "is also an input")
        assert _hash(obs, field) == before and _tree(tmp_path) == names


def test_dense_reference_dem_at_an_output_path_is_refused(tmp_path):
    """`stereo dense --reference-dem OUT/dsm.tif --overwrite`: the DEM would be overwritten by the DSM: refused
    before any work; the DEM (and everything in OUT) unchanged."""
    d = _dense_pair(tmp_path / "in")
    out = tmp_path / "out"
    out.mkdir()
    ref = out / "dsm.tif"
    with rasterio.open(ref, "w", driver="GTiff", width=8, height=8, count=1, dtype="float32", crs="EPSG:32632",
                       transform=Affine(100.0, 0, 0, 0, -100.0, 800)) as ds:
        ds.write(np.ones((1, 8, 8), np.float32))
    inputs = [ref, *sorted(d.iterdir())]
    before, names = _hash(*inputs), _tree(tmp_path)
    r = CliRunner().invoke(stereo_cli, _dense_args(d, out, "r.json", "--reference-dem", str(ref), "--overwrite"))
    _one_line_error(r, "dsm.tif", "is also an input")
    assert _hash(*inputs) == before and _tree(tmp_path) == names


@pytest.mark.parametrize("command", ["ortho", "mosaic"])
def test_output_that_is_a_symlink_to_an_input_is_not_written_through(frame, command):
    d = frame
    r = CliRunner().invoke(rectify_cli, _ortho_args(d, d / "a.tif"))
    assert r.exit_code == 0, r.output
    link = d / "link.tif"
    if command == "ortho":
        link.symlink_to(d / "dem.tif")
        args = _ortho_args(d, link, "--overwrite")
    else:
        link.symlink_to(d / "a.tif")
        args = ["mosaic", str(d / "a.tif"), "-o", str(link), "--overwrite"]
    inputs = [d / "dem.tif", d / "img.tif", d / "a.tif"]
    before, names = _hash(*inputs), _tree(d)
    r = CliRunner().invoke(rectify_cli, args)
    _one_line_error(r, "link.tif", "is also an input")
    assert _hash(*inputs) == before and _tree(d) == names and link.is_symlink()


# ----------------------------------------------------------------------------- empty products
@pytest.mark.parametrize("case", ["dem_elsewhere", "exterior_far", "gcps_far"])
def test_ortho_that_would_be_empty_is_refused_with_the_numbers(frame, case):
    """A DEM that does not cover the image, an exterior orientation far from the DEM, an RPC moved far by its
    GCPs: refused before any tile with the valid share, the DEM's extent and the footprint; nothing written."""
    d = frame
    out = d / "o.tif"
    if case == "dem_elsewhere":
        _dem(d / "dem.tif")
        with rasterio.open(d / "dem.tif", "r+") as ds:
            ds.transform = Affine(4.0, 0, E0 + 50_000, 0, -4.0, N0 + 200)
        args = _ortho_args(d, out, "--report", str(d / "rep"))
    elif case == "exterior_far":
        eo = json.loads((d / "eo.json").read_text())
        eo["position"] = [E0 + 90_000.0, N0 + 70_000.0, 600.0]
        (d / "eo.json").write_text(json.dumps(eo))
        args = _ortho_args(d, out)
    else:
        _rpc_scene(d)
        lines = (d / "gcps.csv").read_text().splitlines()
        far = lines[:2] + [",".join([*ln.split(",")[:3], str(float(ln.split(",")[3]) + 0.5), *ln.split(",")[4:]])
                           for ln in lines[2:]]
        (d / "gcps.csv").write_text("\n".join(far) + "\n")
        args = ["ortho", str(d / "sat.tif"), "--dem", str(d / "dem.tif"), "--rpc", "-o", str(out), "--gcps",
                str(d / "gcps.csv"), "--resolution", "2"]
    inputs = sorted(p for p in d.iterdir() if p.is_file())
    before, names = _hash(*inputs), _tree(d)
    r = CliRunner().invoke(rectify_cli, args)
    line = _one_line_error(r, "the orthophoto would be empty", "0.0 % of the output grid", "the DEM covers",
                           "image footprint is")
    assert "nan" not in line
    assert _hash(*inputs) == before and _tree(d) == names


def _rpc_scene(d: Path) -> None:
    """tests/cli/test_ortho.py's RPC scene (an 80 x 80 image, its RPC, six GCPs) written into ``d``."""
    from rectify.geometry.crs import transform_xy
    from rectify.geometry.rpc import RPC
    from rectify.raster.dem import Dem

    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[E0, N0]])[0]
    m_lon, m_lat = 1.0 / (111_320 * np.cos(np.radians(lat0))), 1.0 / 111_320
    rpc = RPC.from_coefficients(offsets=(40.0, 40.0, lat0, lon0, 100.0),
                                scales=(40.0, 40.0, 80 * m_lat, 80 * m_lon, 50.0),
                                samp_num=[0.0, 1.0, 0.02, 0.1], line_num=[0.0, 0.02, -1.0, 0.03])
    _image(d / "sat.tif", 80, 80, rpc)
    dem = Dem.from_path(d / "dem.tif")
    px = np.array([[10, 10], [70, 12], [15, 68], [66, 70], [40, 40], [25, 50]], float)
    g = rpc.localize_on_dem(px, dem.lonlat_function(), h_range=(50, 200))
    (d / "gcps.csv").write_text("\n".join(["# crs=EPSG:4326", "id,col,row,x,y,z"] + [
        f"g{i},{c},{r},{x!r},{y!r},{z!r}" for i, ((c, r), (x, y, z)) in enumerate(zip(px, g.tolist(),
                                                                                       strict=True))]) + "\n")


def test_ortho_partly_covered_by_its_dem_is_written_with_its_share(frame):
    """A DEM covering part of the footprint is no error: the orthophoto is written and its valid share said."""
    d = frame
    with rasterio.open(d / "dem.tif", "r+") as ds:
        ds.transform = Affine(4.0, 0, E0 - 370, 0, -4.0, N0 + 200)  # its east edge 30 m east of the nadir
    r = CliRunner().invoke(rectify_cli, _ortho_args(d, d / "o.tif"))
    assert r.exit_code == 0, r.output
    share = float(r.output.split("(about ")[1].split(" %")[0])
    with rasterio.open(d / "o.tif") as ds:
        measured = 100.0 * float((ds.read_masks(1) > 0).mean())
    assert 5 < measured < 95, measured
    assert abs(share - measured) < 10, (share, measured)  # a 64 x 64 sample of the grid


@pytest.mark.parametrize("right", ["zero", "micrometre"])
def test_dense_without_base_is_refused_by_name(tmp_path, right):
    """Exterior orientations from one point (the same position, or 1 um apart at 3.7e6 m coordinates):
    "no base", before any output folder is made."""
    d = _dense_pair(tmp_path / "in")
    eo_l = json.loads((d / "l.json").read_text())
    eo_r = json.loads((d / "r.json").read_text())
    eo_r["position"] = list(eo_l["position"])
    if right == "micrometre":
        eo_r["position"][0] += 1e-6
    (d / "r_bad.json").write_text(json.dumps(eo_r))
    inputs = sorted(d.iterdir())
    before, names = _hash(*inputs), _tree(tmp_path)
    r = CliRunner().invoke(stereo_cli, _dense_args(d, tmp_path / "new" / "out", "r_bad.json"))
    _one_line_error(r, "no base", "the base is zero")
    assert _hash(*inputs) == before and _tree(tmp_path) == names


def test_dense_ties_without_parallax_are_refused_by_name():
    """A relative orientation whose tie points show no x-parallax (one photo twice): "no base" with the median
    parallax and the base-to-distance ratio."""
    from rectify.errors import StereoError
    from rectify.geometry.camera import Camera
    from stereo.dense.epipolar import rectify_pair

    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)
    ties = np.random.default_rng(1).uniform([50, 50], [590, 1100], (30, 2))
    with pytest.raises(StereoError, match=r"no base: the tie points' parallax in the normal case is .* px .* "
                                          r"base-to-distance ratio"):
        rectify_pair(cam, cam, rotation_left=np.eye(3), rotation_right=np.eye(3), base=[1.0, 0, 0], tie_left=ties,
                     tie_right=ties)


# ----------------------------------------------------------------------------- hangs
def test_mosaic_of_orthophotos_far_apart_is_refused_at_once(frame):
    """Two orthophotos 100 km apart (a 2e5 x 2e5 px grid that took minutes): refused in seconds with the grid size
    and the share the inputs cover; nothing written."""
    d = frame
    for k, dx in (("a", 0.0), ("b", 100_000.0)):
        r = CliRunner().invoke(rectify_cli, _ortho_args(d, d / f"{k}.tif"))
        assert r.exit_code == 0, r.output
        with rasterio.open(d / f"{k}.tif", "r+") as ds:
            t = ds.transform
            ds.transform = Affine(0.5, 0, t.c + dx, 0, -0.5, t.f + dx)
    inputs = [d / "a.tif", d / "b.tif"]
    before, names = _hash(*inputs), _tree(d)
    t0 = time.monotonic()
    r = CliRunner().invoke(rectify_cli, ["mosaic", *map(str, inputs), "-o", str(d / "m.tif")])
    assert time.monotonic() - t0 < 20
    _one_line_error(r, "output grid would be", "above the limit of 2e+09 px", "% of it")
    assert _hash(*inputs) == before and _tree(d) == names


# ----------------------------------------------------------------------------- partial outputs
def test_ortho_report_on_a_full_disk_leaves_nothing(tmp_path, small_disk):
    """The orthophoto fits, its report does not: neither is left (before: rep/residuals.csv and the ortho)."""
    _dem(tmp_path / "dem.tif")
    _rpc_scene(tmp_path)
    inputs = [tmp_path / n for n in ("dem.tif", "sat.tif", "gcps.csv")]
    before = _hash(*inputs)
    filler = _fill(small_disk, leave=48 * 1024)
    r = CliRunner().invoke(rectify_cli, ["ortho", str(tmp_path / "sat.tif"), "--dem", str(tmp_path / "dem.tif"),
                                         "--rpc", "-o", str(small_disk / "o.tif"), "--gcps", str(tmp_path / "gcps.csv"),
                                         "--resolution", "2", "--report", str(small_disk / "rep")])
    _one_line_error(r, "no space left on device")
    assert _entries(small_disk) == [filler.name] and _hash(*inputs) == before


def test_calibrate_report_on_a_full_disk_leaves_nothing(tmp_path, small_disk):
    """The camera JSON fits, the report does not: neither is left (before: cam.json)."""
    obs = _points_csv(tmp_path)
    before = _hash(obs)
    filler = _fill(small_disk, leave=16 * 1024)
    r = CliRunner().invoke(stereo_cli, ["calibrate", "--points", str(obs), "--size", "640x480", "-o",
                                        str(small_disk / "cam.json"), "--report", str(small_disk / "rep")])
    _one_line_error(r, "no space left on device")
    assert _entries(small_disk) == [filler.name] and _hash(obs) == before


@pytest.mark.parametrize("stage", ["_orient_ties", "match_rasters"])
def test_dense_interrupted_leaves_nothing(tmp_path, monkeypatch, stage):
    """The SIGTERM handler's SystemExit(143) raised while the normal case is built (before: the output folder,
    made before the matching, was left) or while the products are computed (deterministic: the step raises it):
    no output folder, no temporary, exit 143."""
    import stereo.actions.dense as dense

    d = _dense_pair(tmp_path / "in")

    def interrupted(*args, **kwargs):
        raise SystemExit(143)

    monkeypatch.setattr(dense, stage, interrupted)
    inputs = sorted(d.iterdir())
    before, names = _hash(*inputs), _tree(tmp_path)
    r = CliRunner().invoke(stereo_cli, _dense_args(d, tmp_path / "out"))
    assert r.exit_code == 143, r.output
    assert _hash(*inputs) == before and _tree(tmp_path) == names


@pytest.mark.parametrize("stage", ["matching", "products"])
def test_dense_killed_by_sigterm_leaves_nothing(tmp_path, stage):
    """A real SIGTERM (as from `timeout`) while `stereo dense` matches the photos (no --matches; before: the output
    folder made before the matching was left) or computes its products (the folder exists by then): exit 143, no
    traceback, no output folder."""
    d = _dense_pair(tmp_path / "in", size=1400)
    out = tmp_path / "out"
    inputs = sorted(d.iterdir())
    before = _hash(*inputs)
    args = _dense_args(d, out)
    if stage == "matching":
        args = [a for a in args if a not in ("--matches", str(d / "m.csv"))]
    proc = subprocess.Popen([sys.executable, "-c", "from stereo.cli.main import cli; cli()", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    if stage == "matching":
        time.sleep(3.0)  # imports done (about 1.5 s), the photos being matched (about 15 s)
    else:
        t0 = time.monotonic()
        while not out.exists() and proc.poll() is None and time.monotonic() - t0 < 120:
            time.sleep(0.02)
        time.sleep(0.3)
    if proc.poll() is not None:
        pytest.skip(f"the run ended before it could be interrupted (exit {proc.returncode})")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == -signal.SIGTERM:  # killed while still importing (a loaded machine): no handler yet
        assert not out.exists()
        pytest.skip("the process was still starting up when it was interrupted")
    if proc.returncode == 0:
        pytest.skip("the run committed before the signal came")  # a race with a fast machine
    assert proc.returncode == 143, err.decode()
    assert b"Traceback" not in err
    assert not out.exists()
    assert _hash(*inputs) == before


def test_dense_with_a_vertical_base_is_refused_by_name(tmp_path):
    """The right photo taken 300 m straight above the left one (the base along the viewing direction): no normal
    case exists; refused in one line before any output folder is made, inputs unchanged."""
    d = _dense_pair(tmp_path / "in")
    eo_l = json.loads((d / "l.json").read_text())
    eo_r = json.loads((d / "r.json").read_text())
    eo_r["position"] = list(eo_l["position"])
    eo_r["position"][2] += 300.0
    (d / "r_bad.json").write_text(json.dumps(eo_r))
    inputs = sorted(d.iterdir())
    before, names = _hash(*inputs), _tree(tmp_path)
    r = CliRunner().invoke(stereo_cli, _dense_args(d, tmp_path / "new" / "out", "r_bad.json"))
    _one_line_error(r, "viewing direction", "no normal case")
    assert _hash(*inputs) == before and _tree(tmp_path) == names
