"""Faults and bad input (issue 12): every case exits non-zero with a one-line message naming the
problem and the value, leaves nothing at any output path and leaves the inputs untouched."""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import stat
import subprocess
from pathlib import Path

import numpy as np
import pytest
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli as rectify_cli
from rectify.raster.io import write_raster


def _hash(*paths: Path) -> list[str]:
    return [hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths]


def _entries(d: Path) -> list[str]:
    """Every name in ``d`` (hidden temporaries included)."""
    return sorted(p.name for p in Path(d).iterdir())


def _one_line_error(r) -> None:
    assert r.exit_code != 0
    assert "Traceback" not in r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("Error")]
    assert len(err) == 1, r.output


@pytest.fixture()
def noise_scene(tmp_path):
    """A 400 x 400 RGB noise frame (does not compress) and 5 GCPs of a metre grid in UTM 18N."""
    rng = np.random.default_rng(0)
    img = (rng.random((400, 400, 3)) * 255).astype(np.uint8)
    src = tmp_path / "noise.tif"
    write_raster(src, img, Affine(1, 0, 0, 0, 1.0000001, 0), None)
    pix = np.array([[2, 3], [390, 4], [5, 390], [380, 395], [200, 200]], float)
    lines = ["# crs=EPSG:32618", "id,col,row,x,y"] + [
        f"p{i},{c:g},{r:g},{500000.0 + c:.1f},{4400000.0 - r:.1f}" for i, (c, r) in enumerate(pix)]
    gcps = tmp_path / "gcps.csv"
    gcps.write_text("\n".join(lines) + "\n")
    return tmp_path, src, gcps


def _fill(d: Path, leave: int = 0) -> Path:
    """Fill the file system of ``d`` up to ``leave`` bytes with one file (an existing, unrelated file)."""
    filler = d / "filler.bin"
    with open(filler, "wb", buffering=0) as fh, contextlib.suppress(OSError):
        while True:
            fh.write(b"\0" * 4096)
    if leave:
        os.truncate(filler, max(0, filler.stat().st_size - leave))
    return filler


# --- 1. writers
@pytest.mark.parametrize("cog", [False, True])
def test_warp_disk_full_fails_and_cleans_up(noise_scene, small_disk, cog):
    d, src, gcps = noise_scene
    before = _hash(src, gcps)
    out = small_disk / "out.tif"
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(out), "--gcps", str(gcps), "--method", "affine"]
                           + (["--cog"] if cog else []))
    _one_line_error(r)
    # without --cog the write itself fails (ENOSPC); a COG (body + copy) is refused before work
    assert ("no space left on device" if not cog else "space left on device") in r.output and str(out) in r.output
    assert ".part" not in r.output  # the destination is named, not the temporary file
    assert _entries(small_disk) == []
    assert _hash(src, gcps) == before


def test_fit_json_disk_full(noise_scene, small_disk):
    d, src, gcps = noise_scene
    before = _hash(gcps)
    filler = _fill(small_disk)
    out = small_disk / "t.json"
    r = CliRunner().invoke(rectify_cli, ["fit", str(gcps), "-o", str(out), "--method", "affine"])
    _one_line_error(r)
    assert "no space left on device" in r.output and "t.json" in r.output
    assert _entries(small_disk) == [filler.name]
    assert _hash(gcps) == before


def test_csv_and_ply_writers_disk_full(small_disk):
    from rectify.errors import RasterIOError
    from rectify.formats.tables import write_matches
    from rectify.geometry.points import Matches
    from stereo.formats.points import write_ply

    filler = _fill(small_disk)
    n = 2000
    m = Matches(np.array([f"m{i}" for i in range(n)]), np.zeros((n, 2)), np.ones((n, 2)))
    with pytest.raises(RasterIOError, match="no space left on device"):
        write_matches(small_disk / "m.csv", m)
    with pytest.raises(RasterIOError, match="no space left on device"):
        write_ply(small_disk / "p.ply", np.zeros((n, 3)))
    assert _entries(small_disk) == [filler.name]


# --- 2. umask
@pytest.mark.parametrize("mask", [0o022, 0o002])
def test_outputs_follow_the_umask(noise_scene, mask):
    d, src, gcps = noise_scene
    old = os.umask(mask)
    try:
        r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(d / "o.tif"), "--gcps", str(gcps),
                                             "--method", "affine", "--report", str(d / "rep")])
        assert r.exit_code == 0, r.output
        r = CliRunner().invoke(rectify_cli, ["fit", str(gcps), "-o", str(d / "t.json"), "--method", "affine"])
        assert r.exit_code == 0, r.output
    finally:
        os.umask(old)
    for p in (d / "o.tif", d / "t.json", d / "rep" / "report.html"):
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask, p
    assert stat.S_IMODE((d / "rep").stat().st_mode) == 0o777 & ~mask


# --- 3. outputs vs inputs, all or none, SIGTERM
def _stereo_cli():
    from stereo.cli.main import cli

    return cli


def test_output_equal_to_an_input_is_refused_even_with_overwrite(noise_scene):
    d, src, gcps = noise_scene
    (d / "x.csv").write_text("id,x_left,y_left,x_right,y_right\n")
    (d / "ro.json").write_text("{}")
    (d / "cam.json").write_text("{}")
    inputs = [src, gcps, d / "x.csv", d / "ro.json", d / "cam.json"]
    before = _hash(*inputs)
    names = _entries(d)
    cases = [
        (rectify_cli, ["fit", str(gcps), "-o", str(gcps), "--overwrite"], gcps),
        (rectify_cli, ["warp", str(src), str(src), "--gcps", str(gcps), "--overwrite"], src),
        (rectify_cli, ["warp", str(src), str(gcps), "--gcps", str(gcps), "--overwrite"], gcps),
        (rectify_cli, ["match", str(src), str(src), "-o", str(src), "--overwrite"], src),
        (rectify_cli, ["match", str(src), str(gcps), "-o", str(gcps), "--overwrite"], gcps),
        # a derived sibling: `stereo model -o X.ply` writes X.csv, here the matches input
        (_stereo_cli(), ["model", str(d / "ro.json"), "--matches", str(d / "x.csv"), "-o", str(d / "x.ply"),
                         "--overwrite"], d / "x.csv"),
        (_stereo_cli(), ["orient", "--camera", str(d / "cam.json"), "--matches", str(d / "x.csv"),
                         "-o", str(d / "cam.json"), "--overwrite"], d / "cam.json"),
        (_stereo_cli(), ["orient", str(src), str(src), "--camera", str(d / "cam.json"),
                         "-o", str(d / "new.json"), "--matches-out", str(src), "--overwrite"], src),
    ]
    for cli, args, clash in cases:
        r = CliRunner().invoke(cli, args)
        assert r.exit_code != 0, (args, r.output)
        _one_line_error(r)
        if clash is not None:
            assert "is also an input" in r.output and str(clash) in r.output, (args, r.output)
        assert _entries(d) == names, args
    assert _hash(*inputs) == before


def test_fit_with_a_failing_report_writes_nothing(noise_scene, monkeypatch):
    import rectify.report.builder

    d, src, gcps = noise_scene

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(rectify.report.builder, "write_fit_report", boom)  # imported when the fit writes its report
    monkeypatch.setattr(rectify.report.builder, "write_warp_report", boom)
    names = _entries(d)
    r = CliRunner().invoke(rectify_cli, ["fit", str(gcps), "-o", str(d / "t.json"), "--report", str(d / "rep")])
    assert r.exit_code != 0 and _entries(d) == names
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(d / "o.tif"), "--gcps", str(gcps), "--method",
                                         "affine", "--report", str(d / "rep")])
    assert r.exit_code != 0 and _entries(d) == names


def test_stale_temporaries_are_ignored(noise_scene):
    d, src, gcps = noise_scene
    stale = d / ".o.tif.abcd1234.tif.part"
    stale.write_bytes(b"left by a killed run")
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(d / "o.tif"), "--gcps", str(gcps), "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert stale.read_bytes() == b"left by a killed run"


def test_sigterm_removes_temporaries(tmp_path):
    """A warp killed with SIGTERM (as by `timeout`) exits 143 and leaves neither output nor temporary file."""
    import signal
    import sys
    import time

    rng = np.random.default_rng(1)
    img = (rng.random((1500, 1500, 3)) * 255).astype(np.uint8)
    src = tmp_path / "big.tif"
    write_raster(src, img, Affine(1, 0, 0, 0, 1.0000001, 0), None)
    gcps = tmp_path / "g.csv"
    gcps.write_text("# crs=EPSG:32618\nid,col,row,x,y\n" + "\n".join(
        f"p{i},{c},{r},{500000.0 + c:.1f},{4400000.0 - r:.1f}"
        for i, (c, r) in enumerate([(0, 0), (1499, 0), (0, 1499), (1499, 1499), (700, 800)])) + "\n")
    out = tmp_path / "out" / "o.tif"
    out.parent.mkdir()
    before = _hash(src, gcps)
    proc = subprocess.Popen([sys.executable, "-c", "from rectify.cli.main import cli; cli()", "warp", str(src),
                             str(out), "--gcps", str(gcps), "--method", "affine", "--resolution", "0.2",
                             "--resampling", "lanczos", "--threads", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    while not any(out.parent.iterdir()) and proc.poll() is None and time.monotonic() - t0 < 120:
        time.sleep(0.05)
    if proc.poll() is not None:
        pytest.skip(f"the warp ended before it could be interrupted (exit {proc.returncode})")
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err.decode()
    assert b"Traceback" not in err
    assert _entries(out.parent) == []
    assert _hash(src, gcps) == before


_SWALLOWED_SIGTERM = """
import gc, os, signal, sys
from pathlib import Path
from rectify.actions.workspace import Workspace
from rectify.atomic import atomic_output
from rectify.cli.options import install_sigterm_handler
install_sigterm_handler()
def cb(phase, info):  # SIGTERM delivered inside a gc callback: Python reports and drops its SystemExit
    if phase == "start" and not getattr(cb, "done", False):
        cb.done = True
        os.kill(os.getpid(), signal.SIGTERM)
        sum(range(1000))
gc.callbacks.append(cb)
gc.collect()
gc.callbacks.remove(cb)
print("ran on", file=sys.stderr)
out = Path(sys.argv[2])
if sys.argv[1] == "atomic":
    with atomic_output(out) as t:
        t.write_text("x")
else:
    ws = Workspace(out.parent)
    with ws.transaction():
        ws.write_text(out, "x")
print("committed")
"""


@pytest.mark.parametrize("how", ["atomic", "transaction"])
def test_a_swallowed_sigterm_still_stops_the_commit(tmp_path, how):
    """SIGTERM whose SystemExit Python drops (raised in a gc callback, as Dask's diagnostics run one): the run
    goes on, but no output is committed, nothing is printed, and the exit status is still 143."""
    import sys

    out = tmp_path / "o.txt"
    r = subprocess.run([sys.executable, "-c", _SWALLOWED_SIGTERM, how, str(out)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 143, r.stderr
    assert r.stderr == "ran on\n" and r.stdout == ""  # the handler's exception dropped, and not printed
    assert _entries(tmp_path) == []


# --- 7. wrong JSON types, option ranges
_CAM = {"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": 1000, "height": 800}


@pytest.mark.parametrize("bad, key", [
    ({"principal_point_mm": 0.1}, "principal_point_mm"),
    ({"principal_point_mm": "0.1, 0.2"}, "principal_point_mm"),
    ({"distortion": [0.1, 0.0, 0.0]}, "distortion"),
    ({"distortion": {"k1": "abc"}}, "k1"),
    ({"focal_length_mm": "50"}, "focal_length_mm"),
    ({"width": "1000"}, "width"),
])
def test_camera_json_with_wrong_types(tmp_path, bad, key):
    import json

    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({**_CAM, **bad}))
    m = tmp_path / "m.csv"
    m.write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"t{i},{100 + 50 * i},{200 + 30 * i},{90 + 50 * i},{205 + 30 * i}\n" for i in range(12)))
    before, names = _hash(cam, m), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["orient", "--camera", str(cam), "--matches", str(m),
                                           "-o", str(tmp_path / "ro.json")])
    _one_line_error(r)
    assert "CalibrationError" in r.output and key in r.output and "TypeError" not in r.output
    assert _entries(tmp_path) == names and _hash(cam, m) == before


@pytest.mark.parametrize("key, value", [("base", "1, 0, 0"), ("base", [1, 0]), ("rotation_left", 1.0),
                                        ("rotation_right", [[1, 0, 0], [0, 1, 0], [0, 0, "x"]]),
                                        ("focal_length_mm", "150"), ("sigma0_mm", "small")])
def test_relative_json_with_wrong_types(tmp_path, key, value):
    import json

    doc = {"format": "rectify-stereo/relative-orientation", "version": 1,
           "rotation_left": np.eye(3).tolist(), "rotation_right": np.eye(3).tolist(), "base": [1.0, 0.0, 0.0],
           "focal_length_mm": 150.0, "camera": _CAM, key: value}
    ro = tmp_path / "ro.json"
    ro.write_text(json.dumps(doc))
    m = tmp_path / "m.csv"
    m.write_text("id,col_left,row_left,col_right,row_right\nt0,1,2,3,4\n")
    before, names = _hash(ro, m), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["model", str(ro), "--matches", str(m), "-o", str(tmp_path / "p.ply")])
    _one_line_error(r)
    assert "InvalidInputError" in r.output and f"`{key}`" in r.output, r.output
    assert _entries(tmp_path) == names and _hash(ro, m) == before


def test_exterior_json_with_wrong_types(tmp_path):
    import json

    from rectify.errors import InvalidInputError
    from stereo.formats.orientation import read_exterior

    p = tmp_path / "eo.json"
    for key, value in [("position", "1,2,3"), ("focal_length_mm", "150"), ("principal_point_mm", 0.0)]:
        doc = {"format": "rectify-stereo/exterior-orientation", "version": 1, "position": [1.0, 2.0, 3.0],
               "rotation": np.eye(3).tolist(), "focal_length_mm": 150.0, key: value}
        p.write_text(json.dumps(doc))
        with pytest.raises(InvalidInputError, match=f"`{key}`"):
            read_exterior(p)


@pytest.mark.parametrize("cli_name, args", [
    ("rectify", ["compare", "--seed", "-1"]),
    ("rectify", ["compare", "--speed-points", "1000000000000"]),
    ("rectify", ["compare", "--trials", "0"]),
    ("rectify", ["fit", "g.csv", "-o", "t.json", "--max-rows", "-1"]),
    ("rectify", ["warp", "a.tif", "b.tif", "--gcps", "g.csv", "--resolution", "-5"]),
    ("stereo", ["demo", "--seed", "-1"]),
    ("stereo", ["demo", "--size", "10"]),
    ("stereo", ["run", "a.tif", "b.tif", "--camera", "c.json", "-o", "out", "--control-sigma-px", "0"]),
])
def test_numeric_options_out_of_range(tmp_path, monkeypatch, cli_name, args):
    monkeypatch.chdir(tmp_path)
    for f in ("a.tif", "b.tif", "c.json", "g.csv"):
        (tmp_path / f).write_text("x")
    names = _entries(tmp_path)
    r = CliRunner().invoke(rectify_cli if cli_name == "rectify" else _stereo_cli(), args)
    assert r.exit_code == 2, r.output
    assert "Invalid value" in r.output and "Traceback" not in r.output
    assert _entries(tmp_path) == names


# --- 4. check before working
def _pair(tmp_path, size=(400, 300)):
    """Two small noise photos and a camera of their size."""
    import json

    rng = np.random.default_rng(3)
    paths = []
    for name in ("l.tif", "r.tif"):
        img = (rng.random((size[1], size[0])) * 255).astype(np.uint8)
        write_raster(tmp_path / name, img, Affine(1, 0, 0, 0, 1.0000001, 0), None)
        paths.append(tmp_path / name)
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": size[0], "height": size[1]}))
    return paths[0], paths[1], cam


def test_report_folder_under_a_file_is_refused_before_work(noise_scene):
    d, src, gcps = noise_scene
    (d / "afile").write_text("x")
    names, before = _entries(d), _hash(src, gcps)
    r = CliRunner().invoke(rectify_cli, ["fit", str(gcps), "-o", str(d / "t.json"), "--report",
                                         str(d / "afile" / "rep")])
    _one_line_error(r)
    assert "report folder" in r.output and "is a file" in r.output
    assert _entries(d) == names and _hash(src, gcps) == before


def test_report_folder_on_a_read_only_mount(noise_scene, small_disk):
    d, src, gcps = noise_scene
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    names = _entries(d)
    r = CliRunner().invoke(rectify_cli, ["fit", str(gcps), "-o", str(d / "t.json"), "--report",
                                         str(small_disk / "rep")])
    _one_line_error(r)
    assert "report folder" in r.output and "not writable" in r.output
    assert _entries(d) == names and _entries(small_disk) == []


def test_stereo_run_control_crs_checked_before_matching(tmp_path):
    left, right, cam = _pair(tmp_path)
    ctrl = tmp_path / "ctrl.csv"
    ctrl.write_text("# crs=EPSG:999999\nid,col_left,row_left,col_right,row_right,x,y,z\nc1,10,10,5,10,1,2,3\n")
    before, names = _hash(left, right, cam, ctrl), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["run", str(left), str(right), "--camera", str(cam), "--control", str(ctrl),
                                           "-o", str(tmp_path / "out")])
    _one_line_error(r)
    assert "CRSError" in r.output and "EPSG:999999" in r.output and "ctrl.csv" in r.output
    assert _entries(tmp_path) == names and _hash(left, right, cam, ctrl) == before
    # UTM metres labelled EPSG:4326
    ctrl.write_text("# crs=EPSG:4326\nid,col_left,row_left,col_right,row_right,x,y,z\n"
                    "c1,10,10,5,10,500100,4400200,30\n")
    r = CliRunner().invoke(_stereo_cli(), ["run", str(left), str(right), "--camera", str(cam), "--control", str(ctrl),
                                           "-o", str(tmp_path / "out")])
    _one_line_error(r)
    assert "c1" in r.output and "not a longitude/latitude" in r.output
    assert _entries(tmp_path) == names


def test_stereo_run_failure_leaves_no_folder(tmp_path):
    """Noise photos give no tie points: the run fails after matching and leaves no output folder."""
    left, right, cam = _pair(tmp_path)
    before, names = _hash(left, right, cam), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["run", str(left), str(right), "--camera", str(cam),
                                           "-o", str(tmp_path / "new" / "out")])
    _one_line_error(r)
    assert _entries(tmp_path) == names and _hash(left, right, cam) == before


# --- 5. inconsistent geometry
def test_camera_size_differs_from_the_images(tmp_path):
    left, right, cam = _pair(tmp_path, size=(400, 300))
    import json

    cam.write_text(json.dumps({"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": 300, "height": 400}))
    before, names = _hash(left, right, cam), _entries(tmp_path)
    for args in (["orient", str(left), str(right), "--camera", str(cam), "-o", str(tmp_path / "ro.json")],
                 ["run", str(left), str(right), "--camera", str(cam), "-o", str(tmp_path / "out")]):
        r = CliRunner().invoke(_stereo_cli(), args)
        _one_line_error(r)
        assert "300 x 400 px" in r.output and "400 x 300 px" in r.output and "l.tif" in r.output
        assert _entries(tmp_path) == names
    assert _hash(left, right, cam) == before


def test_tie_points_outside_the_camera_frame(tmp_path):
    import json

    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": 400, "height": 300}))
    m = tmp_path / "m.csv"
    m.write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"t{i},{100 + 40 * i},{50 + 20 * i},{90 + 40 * i},{55 + 20 * i}\n" for i in range(12)))
    before, names = _hash(cam, m), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["orient", "--camera", str(cam), "--matches", str(m),
                                           "-o", str(tmp_path / "ro.json")])
    _one_line_error(r)
    assert "outside the camera's 400 x 300 px frame" in r.output and "t8" in r.output
    assert _entries(tmp_path) == names and _hash(cam, m) == before


@pytest.mark.parametrize("crs, message", [("EPSG:4326", "not a longitude/latitude"), ("EPSG:999999", "unknown CRS"),
                                          ("EPSG:32633", "outside the area of use")])
def test_gcp_crs_checked_when_read(noise_scene, crs, message):
    d, src, gcps = noise_scene
    text = gcps.read_text().replace("# crs=EPSG:32618", f"# crs={crs}")
    if crs == "EPSG:32633":  # metres of the northern zone with the sign of the southern hemisphere
        text = text.replace(",43", ",-43").replace(",44", ",-44")
    gcps.write_text(text)
    before, names = _hash(src, gcps), _entries(d)
    for cli, args in ((rectify_cli, ["fit", str(gcps), "-o", str(d / "t.json")]),
                      (rectify_cli, ["warp", str(src), str(d / "o.tif"), "--gcps", str(gcps)])):
        r = CliRunner().invoke(cli, args)
        _one_line_error(r)
        assert "CRSError" in r.output and message in r.output and "gcps.csv" in r.output, r.output
    assert _entries(d) == names and _hash(src, gcps) == before


def test_resect_gcp_crs_checked_when_read(tmp_path):
    import json

    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": 400, "height": 300}))
    g = tmp_path / "g.csv"
    g.write_text("# crs=EPSG:4326\nid,col,row,x,y,z\n" + "".join(
        f"p{i},{50 + 60 * i},{40 + 30 * i},{500000 + 10 * i},{4400000 + 7 * i},{100 + i}\n" for i in range(6)))
    before, names = _hash(cam, g), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["resect", "--camera", str(cam), "--gcps", str(g), "-o",
                                           str(tmp_path / "eo.json")])
    _one_line_error(r)
    assert "not a longitude/latitude" in r.output and "p0" in r.output
    assert _entries(tmp_path) == names and _hash(cam, g) == before


# --- 6. planned outputs
def test_warp_refuses_a_grid_above_max_pixels(noise_scene):
    d, src, gcps = noise_scene
    before, names = _hash(src, gcps), _entries(d)
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(d / "o.tif"), "--gcps", str(gcps), "--method", "affine",
                                         "--resolution", "0.001"])
    _one_line_error(r)
    assert "400000 x 400000" in r.output and "2e+09" in r.output and "--max-pixels" in r.output
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(d / "o.tif"), "--gcps", str(gcps), "--method", "affine",
                                         "--max-pixels", "1000"])
    _one_line_error(r)
    assert "401 x 401" in r.output
    assert _entries(d) == names and _hash(src, gcps) == before


def test_warp_refuses_an_output_larger_than_the_free_space(noise_scene, small_disk):
    d, src, gcps = noise_scene
    before = _hash(src, gcps)
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(small_disk / "o.tif"), "--gcps", str(gcps),
                                         "--method", "affine", "--resolution", "0.25"])
    _one_line_error(r)
    assert "not enough space left on device" in r.output and "MB are free" in r.output
    assert re.search(r"output grid of \d+ x \d+ px", r.output)
    assert _entries(small_disk) == [] and _hash(src, gcps) == before


def test_warp_refuses_a_horizon_inside_the_frame(noise_scene):
    from rectify.formats.transform import write_transform
    from rectify.geometry.transforms import Homography

    d, src, gcps = noise_scene
    t = d / "t.json"
    write_transform(t, Homography(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.01, -1.0]])))
    before, names = _hash(src, t), _entries(d)
    r = CliRunner().invoke(rectify_cli, ["warp", str(src), str(d / "o.tif"), "--transform", str(t)])
    _one_line_error(r)
    assert "horizon of the transform crosses the source frame" in r.output and "400 x 400" in r.output
    assert _entries(d) == names and _hash(src, t) == before


# --- 10. one sigma0 for relative orientation
def test_orient_console_and_report_print_one_sigma0(tmp_path):
    import json

    from rectify.geometry.camera import Camera
    from tests.support.stereo_support import simulate_pair

    sim = simulate_pair("vertical", n=120, noise_px=0.5, outlier_fraction=0.05, rng=7)
    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)
    lp, rp = cam.pixel_from_photo(sim.left_mm), cam.pixel_from_photo(sim.right_mm)
    inside = ((lp >= 0) & (lp <= [639, 1151]) & (rp >= 0) & (rp <= [639, 1151])).all(axis=1)
    lp, rp = lp[inside], rp[inside]
    m = tmp_path / "m.csv"
    m.write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"t{i},{a[0]!r},{a[1]!r},{b[0]!r},{b[1]!r}\n" for i, (a, b) in enumerate(zip(lp.tolist(), rp.tolist(),
                                                                                  strict=True))))
    cj = tmp_path / "cam.json"
    cj.write_text(json.dumps(cam.to_dict()))
    r = CliRunner().invoke(_stereo_cli(), ["orient", "--camera", str(cj), "--matches", str(m), "-o",
                                           str(tmp_path / "ro.json"), "--robust", "tukey", "--report",
                                           str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    got = re.search(r"sigma0 ([0-9.]+) um = ([0-9.]+) px \(vertical parallax, (\d+) - 5 redundancy", r.output)
    assert got, r.output
    um, px, n_used = float(got.group(1)), float(got.group(2)), int(got.group(3))
    doc = json.loads((tmp_path / "rep" / "report.json").read_text())
    table = doc["tables"][0]["summary"]
    assert table["n_fit"] == n_used and table["units"] == "px"
    assert abs(table["sigma0"] - px) < 0.0006
    assert abs(doc["summary"]["sigma0_mm"] * 1000 - um) < 0.006
    assert n_used < len(lp)  # the outliers are excluded


# --- 9. library warnings, a huge blank raster
def test_not_georeferenced_warning_hidden_unless_verbose(tmp_path):
    import sys

    img = (np.random.default_rng(5).random((64, 64)) * 255).astype(np.uint8)
    import rasterio

    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8") as ds:
        ds.write(img, 1)
    gcps = tmp_path / "g.csv"
    gcps.write_text("id,col,row,x,y\n" + "".join(f"p{i},{c},{r},{2 * c},{2 * r}\n" for i, (c, r) in
                                                  enumerate([(1, 1), (60, 2), (3, 60), (62, 61), (30, 30)])))
    base = [sys.executable, "-c", "from rectify.cli.main import cli; cli()"]
    args = ["warp", str(plain), str(tmp_path / "o.tif"), "--gcps", str(gcps), "--method", "affine"]
    quiet = subprocess.run(base + args, capture_output=True, text=True)
    assert quiet.returncode == 0, quiet.stderr
    assert "Warning" not in quiet.stderr, quiet.stderr
    loud = subprocess.run(base + ["-v"] + args + ["--overwrite"], capture_output=True, text=True)
    assert loud.returncode == 0 and "NotGeoreferencedWarning" in loud.stderr


def test_huge_blank_raster_fails_fast(tmp_path):
    import time

    from rectify.raster.io import MaskPolicy, TiledWriter

    blank = tmp_path / "blank.tif"
    z = np.full((1024, 1024, 1), 7, np.uint8)
    with TiledWriter(blank, 6000, 6000, 1, "uint8", Affine(1, 0, 0, 0, 1.0000001, 0), None, MaskPolicy("none"),
                     tile=1024) as w:
        for r in range(0, 6000, 1024):
            for c in range(0, 6000, 1024):
                w.write(z[:min(1024, 6000 - r), :min(1024, 6000 - c)], c, r)
    before, names = _hash(blank), _entries(tmp_path)
    t0 = time.perf_counter()
    r = CliRunner().invoke(rectify_cli, ["match", str(blank), str(blank), "-o", str(tmp_path / "m.csv")])
    dt = time.perf_counter() - t0
    _one_line_error(r)
    assert "is blank" in r.output and "blank.tif" in r.output and " 7;" in r.output
    assert dt < 20  # the coarse pass (a full read) is never started
    assert _entries(tmp_path) == names and _hash(blank) == before


# --- 8. degenerate cases named
def _matches_csv(path, left, right):
    path.write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"t{i},{a[0]!r},{a[1]!r},{b[0]!r},{b[1]!r}\n" for i, (a, b) in enumerate(zip(left.tolist(), right.tolist(),
                                                                                  strict=True))))


@pytest.mark.parametrize("kind", ["identical", "rotation"])
def test_orient_without_base_is_named(tmp_path, kind):
    import json

    from rectify.geometry.camera import Camera
    from rectify.geometry.rotation import matrix_from_angles

    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)
    rng = np.random.default_rng(2)
    left_mm = rng.uniform([-40, -75], [40, 75], (150, 2))
    if kind == "identical":
        right_mm = left_mm.copy()
    else:  # the camera turned about its projection centre
        rays = np.column_stack([left_mm, np.full(len(left_mm), -120.0)]) @ matrix_from_angles(0.01, -0.02, 0.05)
        right_mm = -120.0 * rays[:, :2] / rays[:, 2:3] + rng.normal(0, 0.144 * 0.1, left_mm.shape)
    m = tmp_path / "m.csv"
    _matches_csv(m, cam.pixel_from_photo(left_mm), cam.pixel_from_photo(right_mm))
    cj = tmp_path / "cam.json"
    cj.write_text(json.dumps(cam.to_dict()))
    before, names = _hash(m, cj), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["orient", "--camera", str(cj), "--matches", str(m), "-o",
                                           str(tmp_path / "ro.json")])
    _one_line_error(r)
    assert "no base: the images show no parallax" in r.output
    assert ("identical images" if kind == "identical" else "pure rotation") in r.output
    assert _entries(tmp_path) == names and _hash(m, cj) == before


def test_relative_orientation_of_real_pairs_is_not_called_baseless():
    from stereo.relative.degenerate import check_base
    from tests.support.stereo_support import simulate_pair

    for kind in ("vertical", "convergent", "kappa180"):
        sim = simulate_pair(kind, n=150, noise_px=0.5, outlier_fraction=0.1, rng=4)
        check_base(sim.left_mm, sim.right_mm, 120.0, 0.144)  # no exception


def test_stereo_run_on_one_photo_twice(tmp_path):
    import shutil

    rng = np.random.default_rng(9)
    img = (rng.random((300, 400)) * 255).astype(np.uint8)
    import cv2

    img = cv2.GaussianBlur(img, (0, 0), 1.5)
    left = tmp_path / "l.tif"
    write_raster(left, img, Affine(1, 0, 0, 0, 1.0000001, 0), None)
    right = tmp_path / "r.tif"
    shutil.copy(left, right)
    cam = tmp_path / "cam.json"
    cam.write_text('{"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": 400, "height": 300}')
    before, names = _hash(left, right, cam), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["run", str(left), str(right), "--camera", str(cam), "-o",
                                           str(tmp_path / "out")])
    _one_line_error(r)
    assert "no base: the images show no parallax (identical images" in r.output, r.output
    assert _entries(tmp_path) == names and _hash(left, right, cam) == before


def test_resect_with_collinear_control(tmp_path):
    cam = tmp_path / "cam.json"
    cam.write_text('{"focal_length_mm": 50.0, "pixel_size_mm": 0.01, "width": 400, "height": 300}')
    g = tmp_path / "g.csv"
    g.write_text("# crs=EPSG:32618\nid,col,row,x,y,z\n" + "".join(
        f"p{i},{50 + 50 * i},{40 + 30 * i},{500000 + 10 * i},{4400000 + 7 * i},{100 + 2 * i}\n" for i in range(6)))
    before, names = _hash(cam, g), _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["resect", "--camera", str(cam), "--gcps", str(g), "-o",
                                           str(tmp_path / "eo.json")])
    _one_line_error(r)
    assert "collinear" in r.output
    assert _entries(tmp_path) == names and _hash(cam, g) == before


def test_non_convergence_names_the_largest_residuals():
    from rectify.errors import ConvergenceError
    from rectify.geometry.rotation import matrix_from_angles
    from stereo.pair.absolute import AbsoluteOrientation
    from stereo.pair.resection import ExteriorOrientation

    rng = np.random.default_rng(1)
    model = rng.uniform(-1, 1, (8, 3))
    R = matrix_from_angles(0.3, -0.2, 1.0)
    ground = 500.0 * model @ R.T + [1000.0, 2000.0, 300.0]
    ground[5] += [40.0, -30.0, 25.0]  # one bad control point
    ids = [f"G{i}" for i in range(8)]
    with pytest.raises(ConvergenceError, match=r"largest residuals: G5 ") as e:
        AbsoluteOrientation.from_points(model, ground, ids=ids, max_iterations=2, tol=0.0)
    assert e.value.iterations == 2
    f = 120.0
    G = np.column_stack([rng.uniform(-500, 500, (8, 2)), rng.uniform(0, 80, 8)])
    C = np.array([20.0, -30.0, 1500.0])
    d = G - C
    photo = -f * d[:, :2] / d[:, 2:3]
    photo[3] += [0.5, -0.4]
    with pytest.raises(ConvergenceError, match=r"largest residuals: G3 .* mm"):
        ExteriorOrientation.from_points(photo, G, focal_length_mm=f, ids=ids, max_iterations=2, tol=0.0)


def test_concurrent_runs_commit_one_after_the_other(tmp_path, monkeypatch):
    """Two jobs writing one output set with --overwrite: each commits all its files under a folder lock,
    so the set ends up from one run, never a mix."""
    import threading
    import time

    import rectify.actions.workspace as wsmod
    from rectify.actions.workspace import Workspace

    order: list[tuple[str, str]] = []
    real_replace = os.replace

    def slow_replace(a, b):
        order.append((threading.current_thread().name, Path(b).name))
        time.sleep(0.05)
        real_replace(a, b)

    monkeypatch.setattr(wsmod.os, "replace", slow_replace)
    barrier = threading.Barrier(2)

    def job(tag: str) -> None:
        ws = Workspace(overwrite=True)
        with ws.transaction():
            for name in ("a.txt", "b.txt", "c.txt"):
                ws.write_text(tmp_path / name, tag)
            barrier.wait()  # both commit at the same moment

    threads = [threading.Thread(target=job, args=(t,), name=t) for t in ("one", "two")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    who = [w for w, _ in order]
    assert who in (["one"] * 3 + ["two"] * 3, ["two"] * 3 + ["one"] * 3), order
    contents = {(tmp_path / n).read_text() for n in ("a.txt", "b.txt", "c.txt")}
    assert len(contents) == 1
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_stereo_run_failing_while_writing_leaves_no_half_filled_folder(tmp_path, monkeypatch):
    """The run gets as far as writing (matches stubbed with a simulated pair); the report then fails:
    no file of the layout stays and the output folder the run created is removed."""
    import json
    from types import SimpleNamespace

    import stereo.actions.run
    from rectify.geometry.camera import Camera
    from rectify.geometry.points import Matches
    from tests.support.stereo_support import simulate_pair

    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)
    sim = simulate_pair("vertical", n=150, noise_px=0.3, rng=3)
    lp, rp = cam.pixel_from_photo(sim.left_mm), cam.pixel_from_photo(sim.right_mm)
    inside = ((lp >= 0) & (lp <= [639, 1151]) & (rp >= 0) & (rp <= [639, 1151])).all(axis=1)
    m = Matches(tuple(f"t{i}" for i in range(int(inside.sum()))), lp[inside], rp[inside])
    monkeypatch.setattr(stereo.actions.run, "match_photos", lambda *a, **k: SimpleNamespace(matches=m, rmse_px=0.3))

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(stereo.actions.run, "write_pair_report", boom)
    z = np.zeros((1152, 640), np.uint8)
    for name in ("l.tif", "r.tif"):
        write_raster(tmp_path / name, z, Affine(1, 0, 0, 0, 1.0000001, 0), None)
    cj = tmp_path / "cam.json"
    cj.write_text(json.dumps(cam.to_dict()))
    names = _entries(tmp_path)
    r = CliRunner().invoke(_stereo_cli(), ["run", str(tmp_path / "l.tif"), str(tmp_path / "r.tif"), "--camera",
                                           str(cj), "-o", str(tmp_path / "new" / "out")])
    _one_line_error(r)
    assert "no space left on device" in r.output
    assert _entries(tmp_path) == names
    # into an existing folder: nothing of the layout is left in it
    (tmp_path / "existing").mkdir()
    r = CliRunner().invoke(_stereo_cli(), ["run", str(tmp_path / "l.tif"), str(tmp_path / "r.tif"), "--camera",
                                           str(cj), "-o", str(tmp_path / "existing")])
    _one_line_error(r)
    assert _entries(tmp_path / "existing") == []


def test_report_on_a_full_disk(noise_scene, small_disk):
    """The report cannot be written: one line naming the space, no transform, no report folder left."""
    d, src, gcps = noise_scene
    filler = _fill(small_disk)
    names, before = _entries(d), _hash(gcps)
    r = CliRunner().invoke(rectify_cli, ["fit", str(gcps), "-o", str(d / "t.json"), "--method", "affine",
                                         "--report", str(small_disk / "rep")])
    _one_line_error(r)
    assert "no space left on device" in r.output and "rep" in r.output
    assert _entries(d) == names and _entries(small_disk) == [filler.name] and _hash(gcps) == before


# --- 11. the workspace: outputs against inputs resolved, the report staged with the transaction (issue 32)
@pytest.mark.parametrize("how", ["symlink", "hardlink", "dotdot", "folder_symlink"])
def test_workspace_refuses_an_output_that_resolves_to_an_input(tmp_path, how):
    from rectify.actions.workspace import Workspace
    from rectify.errors import InvalidInputError

    src = tmp_path / "in" / "gcps.csv"
    src.parent.mkdir()
    src.write_text("id,col,row,x,y\n")
    out = {"symlink": tmp_path / "link.csv", "hardlink": tmp_path / "hard.csv",
           "dotdot": tmp_path / "new" / ".." / "in" / "gcps.csv",
           "folder_symlink": tmp_path / "alias" / "gcps.csv"}[how]
    if how == "symlink":
        out.symlink_to(src)
    elif how == "hardlink":
        os.link(src, out)
    elif how == "folder_symlink":
        (tmp_path / "alias").symlink_to(src.parent, target_is_directory=True)
    names = sorted(p.name for p in tmp_path.rglob("*"))
    for overwrite in (False, True):
        ws = Workspace(overwrite=overwrite, inputs=[src])
        with pytest.raises(InvalidInputError, match="is also an input"):
            ws.plan(out)
        with pytest.raises(InvalidInputError, match="is also an input"):
            ws.write_text(out, "x")
    assert src.read_text() == "id,col,row,x,y\n" and sorted(p.name for p in tmp_path.rglob("*")) == names
    Workspace(inputs=[src]).plan(tmp_path / "other.csv")  # another file is fine


def test_report_folder_is_staged_with_the_transaction(tmp_path):
    """The report is written into a hidden folder beside the report folder and moved in at the commit, with the
    other outputs: an error (or SIGTERM's SystemExit) leaves neither, and removes the parents made for it."""
    from rectify.actions.workspace import Workspace
    from rectify.errors import InvalidInputError

    rep = tmp_path / "a" / "b" / "rep"
    ws = Workspace(report_dir=rep)
    for exc in (RuntimeError("boom"), SystemExit(143)):
        with pytest.raises(type(exc)), ws.transaction():
            ws.write_text(tmp_path / "out.json", "{}")
            with ws.report_folder() as stage:
                (stage / "report.html").write_text("<html></html>")
                (stage / "residuals.csv").write_text("id\n")
            assert not rep.exists() and stage.parent == rep.parent  # staged beside it, not yet in place
            raise exc
        assert _entries(tmp_path) == []  # no output, no staging folder, no parent folder left
    with ws.transaction():
        ws.write_text(tmp_path / "out.json", "{}")
        with ws.report_folder() as stage:
            (stage / "report.html").write_text("<html>1</html>")
            (stage / "report.json").write_text('{"files": ["report.html", "old.png"]}')
            (stage / "old.png").write_bytes(b"x")
    assert _entries(rep) == ["old.png", "report.html", "report.json"] and _entries(rep.parent) == ["rep"]
    # a second report (with --overwrite) replaces the files and removes those only the previous one listed
    ws2 = Workspace(report_dir=rep, overwrite=True)
    with ws2.transaction():
        with ws2.report_folder() as stage:
            (stage / "report.html").write_text("<html>2</html>")
            (stage / "report.json").write_text('{"files": ["report.html"]}')
    assert _entries(rep) == ["report.html", "report.json"] and (rep / "report.html").read_text() == "<html>2</html>"
    # without --overwrite an existing report file is refused at the commit and nothing moves
    with pytest.raises(InvalidInputError, match="exists|appeared"), Workspace(report_dir=rep).transaction() as ws3:
        with ws3.report_folder() as stage:
            (stage / "report.html").write_text("<html>3</html>")
    assert (rep / "report.html").read_text() == "<html>2</html>" and _entries(rep.parent) == ["rep"]


def test_report_commit_never_replaces_an_input(tmp_path):
    """The commit checks every staged destination against the inputs again (report files are named only when
    written): an input in the report folder under a report file's name is refused, with --overwrite too."""
    from rectify.actions.workspace import Workspace
    from rectify.errors import InvalidInputError

    rep = tmp_path / "rep"
    rep.mkdir()
    mine = rep / "residuals.csv"
    mine.write_text("my GCPs\n")
    ws = Workspace(report_dir=rep, overwrite=True, inputs=[mine])
    with pytest.raises(InvalidInputError, match="is also an input"), ws.transaction():
        with ws.report_folder() as stage:
            (stage / "residuals.csv").write_text("id\n")
    assert mine.read_text() == "my GCPs\n" and _entries(rep) == ["residuals.csv"] and _entries(tmp_path) == ["rep"]
