"""``rectify view``'s server: refusals (each case), loopback only, the answers against the step's own files,
lazy tiles of a large raster, the static export and the command's bad input.

The result folder is made by running ``stereo block`` on the rendered example block of tests/cli/test_block.py
(6 photos, control and check points); the known residuals are read back from its ``observations.csv`` and
report CSVs with the standard ``csv`` module, independently of the view's readers.
"""

from __future__ import annotations

import csv
import http.client
import json
import os
import socket
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from rasterio.transform import from_origin

from rectify.actions.view import ViewOptions, start_view
from rectify.cli.main import cli as rectify_cli
from rectify.errors import InvalidInputError, RasterIOError
from rectify.raster.viewtiles import TileSource, encode_png, hillshade, max_level_for
from rectify.view.data import bucket_of
from rectify.view.export import static_levels
from rectify.view.folder import Refused, resolve_inside, safe_parts
from stereo.cli.main import cli as stereo_cli
from tests.support.block_example import write_example_block


def make_block_output(base: Path) -> tuple[Path, Path]:
    """Run ``stereo block`` on the rendered example block; return (output folder, photo folder)."""
    photos = base / "photos"
    images, _, _ = write_example_block(photos)
    out = base / "out"
    r = CliRunner().invoke(stereo_cli, [
        "block", *map(str, images), "--camera", str(photos / "camera.json"), "--poses", str(photos / "poses.csv"),
        "--gnss-sigma", "0.05", "--control", str(photos / "control.csv"), "--check", "C1,C6,C10",
        "--control-sigma", "0.01", "-o", str(out)], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return out, photos


_SHARED: dict[Path, tuple[Path, Path]] = {}


def shared_block_output(factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """:func:`make_block_output` once per test session (the browser test uses the same folder)."""
    base = factory.getbasetemp() / "view-block"
    if base not in _SHARED:
        base.mkdir(exist_ok=True)
        _SHARED[base] = make_block_output(base)
    return _SHARED[base]


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    out, photos = shared_block_output(tmp_path_factory)
    base = tmp_path_factory.mktemp("viewblock")
    outside = base / "secret.json"
    outside.write_text('{"secret": 1}\n')
    (out / "link_out.json").symlink_to(outside)  # a symlink out of the folder
    (out / "linkdir").symlink_to(photos, target_is_directory=True)
    (out / ".hidden.json").write_text("{}\n")
    (out / "notes.py").write_text("print(1)\n")
    return out, photos, base


@pytest.fixture(scope="module")
def server(block):
    out, photos, _ = block
    session = start_view(out, ViewOptions(port=0, images=(str(photos),)))
    t = threading.Thread(target=session.serve_forever, daemon=True)
    t.start()
    yield session
    session.close()
    t.join(5)


def get(session, path: str, *, host: str | None = None, method: str = "GET") -> tuple[int, bytes, dict]:
    hostname, port = session.server.server_address[:2]
    conn = http.client.HTTPConnection(hostname, port, timeout=20)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        conn.putheader("Host", host if host is not None else f"{hostname}:{port}")
        conn.endheaders()
        r = conn.getresponse()
        return r.status, r.read(), dict(r.getheaders())
    finally:
        conn.close()


# ------------------------------------------------------------------ refusals
@pytest.mark.parametrize("path", [
    "/files/../orientation.json",              # '..'
    "/files/report/../../secret.json",
    "/files/%2e%2e/secret.json",               # encoded '..'
    "/files/report%2f..%2f..%2fsecret.json",   # encoded slashes
    "/files//etc/passwd",                      # absolute
    "/files/%2fetc%2fpasswd",                  # encoded absolute
    "/files/link_out.json",                    # a symlink pointing out
    "/files/linkdir/camera.json",              # a symlinked folder pointing out
    "/files/.hidden.json",                     # hidden (temporaries are hidden)
    "/files/notes.py",                         # not a served kind
    "/files/points.las",                       # a result, but not a served kind
    "/files/report\\..\\secret.json",          # back-slashes
])
def test_paths_outside_or_unserved_are_refused_403(server, path):
    status, body, _ = get(server, path)
    assert status == 403, (path, status, body)
    assert b"\"secret\": 1" not in body and b"root:" not in body


@pytest.mark.parametrize("path", ["/files/nosuch.json", "/files/%252e%252e/secret.json", "/nosuch",
                                  "/static/nosuch.js", "/api/obs/99.json", "/api/table/99.json",
                                  "/tiles/99/0/0_0.png", "/tiles/0/9/0_0.png", "/tiles/0/0/5_5.png"])
def test_missing_things_are_404(server, path):
    assert get(server, path)[0] == 404


def test_other_methods_and_hosts_are_refused(server):
    assert get(server, "/api/manifest.json", method="POST")[0] == 405
    assert get(server, "/api/manifest.json", method="PUT")[0] == 405
    assert get(server, "/api/manifest.json", host="evil.example:80")[0] == 403  # DNS rebinding
    status, body, headers = get(server, "/api/manifest.json", method="HEAD")
    assert status == 200 and body == b"" and int(headers["Content-Length"]) > 100


def test_served_files_and_page(server, block):
    out = block[0]
    status, body, headers = get(server, "/files/report/report.json")
    assert status == 200 and body == (out / "report" / "report.json").read_bytes()
    assert headers["X-Content-Type-Options"] == "nosniff"
    status, body, headers = get(server, "/")
    assert status == 200 and b'<canvas id="map"' in body and "default-src 'self'" in headers["Content-Security-Policy"]
    assert get(server, "/static/view.js")[0] == 200


def test_safe_parts_and_resolve_inside(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f.png").write_bytes(b"x")
    assert resolve_inside(tmp_path.resolve(), "a/f.png") == (tmp_path / "a" / "f.png").resolve()
    for bad in ("..", "a/../../x", "/etc", "C:/x", ".git/config", "a\x00b"):
        with pytest.raises(Refused) as e:
            safe_parts(bad)
        assert e.value.status == 403
    with pytest.raises(Refused) as e:
        resolve_inside(tmp_path.resolve(), "a/g.png")
    assert e.value.status == 404


def test_server_binds_loopback_only(server):
    host = server.server.server_address[0]
    assert host == "127.0.0.1"
    # an address of this machine other than loopback (no packet is sent to find it) must not answer
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.connect(("10.255.255.255", 1))
        mine = probe.getsockname()[0]
    except OSError:
        mine = None
    finally:
        probe.close()
    if mine and not mine.startswith("127."):
        with pytest.raises(OSError):
            socket.create_connection((mine, server.server.server_address[1]), timeout=2).close()


# ------------------------------------------------------------------ answers
def test_observation_answer_is_the_files_residual(server, block):
    out = block[0]
    rows = read_csv_rows(out / "observations.csv")
    man = json.loads(get(server, "/api/manifest.json")[1])
    assert man["kind"] == "block" and len(man["images"]) == 6 and all(im["raster"] is not None for im in man["images"])
    flagged = next(r for r in rows if r["flagged"] == "1")
    i = [im["name"] for im in man["images"]].index(flagged["image"])
    obs = json.loads(get(server, f"/api/obs/{i}.json")[1])
    k = obs["id"].index(flagged["id"])
    assert obs["vx"][k] == pytest.approx(float(flagged["residual_x_px"]), abs=1e-12)
    assert obs["vy"][k] == pytest.approx(float(flagged["residual_y_px"]), abs=1e-12)
    assert obs["flag"][k] == 1
    z = np.hypot(float(flagged["residual_x_px"]), float(flagged["residual_y_px"])) / float(flagged["sigma_px"])
    assert obs["z"][k] == pytest.approx(z, rel=1e-12)
    assert sum(1 for r in rows if r["image"] == flagged["image"]) == len(obs["id"])
    # the track of that point: every image that measured it, with the same residuals
    b = bucket_of(flagged["id"], man["n_buckets"])
    track = json.loads(get(server, f"/api/tracks/{b}.json")[1])["tracks"][flagged["id"]]
    mine = {(r["image"], float(r["residual_x_px"])) for r in rows if r["id"] == flagged["id"]}
    assert {(man["images"][o[0]]["name"], o[3]) for o in track["obs"]} == mine


def test_control_and_check_points_in_the_layout(server, block):
    out = block[0]
    check = read_csv_rows(out / "report" / "bundle_check_points_adjusted_given.csv")
    lay = json.loads(get(server, "/api/layout.json")[1])
    assert len(lay["images"]) == 6 and all(im["footprint"] for im in lay["images"])
    marks = {m["id"]: m for m in lay["marks"]}
    for r in check:
        m = marks[r["id"]]
        assert m["kind"] == "check"
        assert m["v"] == pytest.approx([float(r["dX"]), float(r["dY"]), float(r["dZ"])], abs=1e-12)
    # each footprint surrounds its projection centre (near-vertical photos)
    for im in lay["images"]:
        f = np.array(im["footprint"])
        assert f[:, 0].min() < im["position"][0] < f[:, 0].max()
        assert f[:, 1].min() < im["position"][1] < f[:, 1].max()


def test_table_answer(server, block):
    out = block[0]
    man = json.loads(get(server, "/api/manifest.json")[1])
    t = next(t for t in man["tables"] if t["step"].startswith("bundle: control"))
    rows = read_csv_rows(out / t["csv"])
    tab = json.loads(get(server, f"/api/table/{t['t']}.json")[1])
    assert [r[0] for r in tab["rows"]] == [r["id"] for r in rows]
    j = tab["columns"].index("normalised")
    assert tab["rows"][0][j] == pytest.approx(float(rows[0]["normalised"]))


def test_photo_tile_is_the_photo(server, block):
    _, photos, _ = block
    man = json.loads(get(server, "/api/manifest.json")[1])
    r = man["rasters"][man["images"][0]["raster"]]
    status, body, headers = get(server, f"/tiles/{r['id']}/{r['max_level']}/0_0.png")
    assert status == 200 and headers["Content-Type"] == "image/png" and body[:4] == b"\x89PNG"
    with rasterio.open(photos / man["images"][0]["name"]) as ds:
        truth = ds.read(1, window=((0, 256), (0, 256)))
    src = TileSource(str(photos / man["images"][0]["name"]))
    data, valid, s = src.tile_array(r["max_level"], 0, 0)
    assert s == 1 and valid.all() and np.array_equal(data[0], truth)


# ------------------------------------------------------------------ tiles
def test_tile_of_a_large_raster_reads_a_window_lazily(tmp_path):
    p = tmp_path / "huge.tif"
    n = 40_000  # 1.6 gigapixels; sparse: only the written blocks take space
    with rasterio.open(p, "w", driver="GTiff", width=n, height=n, count=3, dtype="uint8", tiled=True,
                       blockxsize=256, blockysize=256, compress="deflate", sparse_ok=True, nodata=0,
                       crs="EPSG:32633", transform=from_origin(500000, 5_000_000, 0.5, 0.5)) as ds:
        ds.write(np.full((3, 256, 256), 77, np.uint8), window=((20_000, 20_256), (20_224, 20_480)))
    assert p.stat().st_size < 5_000_000
    tracemalloc.start()
    t0 = time.perf_counter()
    src = TileSource(str(p))
    lay = src.layout
    assert lay.max_level == max_level_for(n, n) == 8
    png = src.tile_png(lay.max_level, 79, 78)  # columns 20224.., rows 19968..: half on the written block
    data, valid, s = src.tile_array(lay.max_level, 79, 78)
    mid = src.tile_png(lay.max_level - 2, 19, 19)  # scale 4: a 1024 px window decimated
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert png[:4] == b"\x89PNG" and mid[:4] == b"\x89PNG"
    assert s == 1 and data.shape == (3, 256, 256)
    assert (data[:, 32:, :] == 77).all() and not valid[:32].any()  # nodata above the written block
    assert src._preview is None  # no whole-raster read
    assert dt < 5.0, dt
    assert peak < 40 * 2**20, peak  # a few tiles, not the 4.8 GB raster


def test_preview_levels_match_a_decimated_read(tmp_path):
    p = tmp_path / "mid.tif"
    rng = np.random.default_rng(1)
    a = rng.integers(1, 255, (1, 3000, 2500), dtype=np.uint8)
    with rasterio.open(p, "w", driver="GTiff", width=2500, height=3000, count=1, dtype="uint8", tiled=True,
                       blockxsize=256, blockysize=256) as ds:
        ds.write(a)
    src = TileSource(str(p))
    assert src.layout.max_level == 4
    data, valid, s = src.tile_array(2, 1, 0)  # scale 4 >= the preview's 2: cut from the preview
    assert s == 4 and src._preview is not None
    # nearest sampling: the preview (factor 2) keeps pixels 2i + 1, the tile every second of those
    assert np.array_equal(data[0], a[0, 1:1024:4, 1025:2048:4])
    data, _, s = src.tile_array(4, 3, 2)  # full resolution: a window read
    assert s == 1 and np.array_equal(data[0], a[0, 512:768, 768:1024])


def test_hillshade_and_png():
    ok = np.ones((5, 5), bool)
    z = np.add.outer(np.arange(5.0), np.arange(5.0))  # rising to the south-east (rows down, columns right)
    flat = hillshade(np.zeros((5, 5)), ok, 1.0)
    assert flat[2, 2] == int(255 * np.sin(np.radians(45)))
    # the sun in the north-west: a slope facing north-west is lit, one facing south-east in shade
    assert hillshade(z, ok, 1.0)[2, 2] > flat[2, 2] > hillshade(-z, ok, 1.0)[2, 2]
    # slope 45 deg facing the sun: cos(0) = 1 -> 255 (sun altitude 45)
    assert hillshade(z / np.sqrt(2), ok, 1.0)[2, 2] == 255
    assert encode_png(np.zeros((3, 4, 3), np.uint8))[12:16] == b"IHDR"
    with pytest.raises(InvalidInputError):
        encode_png(np.zeros((3, 4), np.uint8))
    with pytest.raises(RasterIOError, match="cannot read raster"):
        TileSource(__file__)
    assert static_levels([{"id": 3, "width": 300, "height": 300, "tile": 256, "max_level": 1}], 10) == {3: 1}


# ------------------------------------------------------------------ command
def test_static_export_and_its_refusals(block, tmp_path):
    out, photos, _ = block
    dest = tmp_path / "site"
    r = CliRunner().invoke(rectify_cli, ["view", str(out), "--images", str(photos), "--static", str(dest)])
    assert r.exit_code == 0, r.output
    assert "static view:" in r.output and "every raster at full resolution" in r.output
    man = json.loads((dest / "api" / "manifest.json").read_text())
    assert man["static"]["levels"] and (dest / "index.html").is_file() and (dest / "static" / "view.js").is_file()
    assert (dest / "api" / "layout.json").is_file() and (dest / "api" / "obs" / "5.json").is_file()
    assert (dest / "tiles" / "0" / "1" / "1_0.png").is_file()
    assert (dest / "files" / man["figures"][0]["href"]).is_file()
    before = sorted(p.name for p in out.rglob("*"))
    # exists without --overwrite; inside the result folder; missing folder
    r = CliRunner().invoke(rectify_cli, ["view", str(out), "--static", str(dest)])
    assert r.exit_code == 1 and "exists; pass --overwrite" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(rectify_cli, ["view", str(out), "--static", str(out / "site")])
    assert r.exit_code == 1 and "inside the result folder" in r.output and not (out / "site").exists()
    r = CliRunner().invoke(stereo_cli, ["view", str(tmp_path / "nosuch"), "--static", str(tmp_path / "x")])
    assert r.exit_code == 2 and "does not exist" in r.output and not (tmp_path / "x").exists()
    assert sorted(p.name for p in out.rglob("*")) == before  # the result folder untouched
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left


def test_taken_port_is_one_line(block):
    out = block[0]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        r = CliRunner().invoke(rectify_cli, ["view", str(out), "--port", str(port), "--no-browser"])
    assert r.exit_code == 1 and f"cannot listen on 127.0.0.1:{port}" in r.output and "Traceback" not in r.output


def test_bad_options():
    with pytest.raises(InvalidInputError):
        ViewOptions(port=70000)
    with pytest.raises(InvalidInputError):
        ViewOptions(max_static_tiles=0)
    with pytest.raises(InvalidInputError):
        start_view(os.devnull)


def test_a_broken_result_file_is_one_line_before_serving(tmp_path):
    d = tmp_path / "broken"
    d.mkdir()
    (d / "observations.csv").write_text("image,id,col,row,sigma_px,residual_x_px,residual_y_px,weight,flagged\n"
                                        "a.tif,p1,10,20,0.5,0.1,x,1,0\n")
    r = CliRunner().invoke(rectify_cli, ["view", str(d), "--static", str(tmp_path / "site")])
    assert r.exit_code == 1 and "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1
    assert "observations.csv" in r.output and "line 2" in r.output and "'x'" in r.output
    assert not (tmp_path / "site").exists()
    (d / "observations.csv").unlink()
    (d / "orientation.json").write_text('{"format": "rectify-stereo/block-orientation", "version": 1, "images": 3}')
    r = CliRunner().invoke(stereo_cli, ["view", str(d), "--static", str(tmp_path / "site")])
    assert r.exit_code == 1 and "orientation.json" in r.output and "'images' must be a list" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "site").exists()
