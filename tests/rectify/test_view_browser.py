"""``rectify view`` in headless Chromium: each view loads without a console message, a click on a known point
shows its known residual, zoom reaches full resolution, screenshots show the page's layout with its legend.

Debian's ``chromium`` is installed by ``.ci/run``; without it the tests skip and say so. The servers run in
this process (threads) on 127.0.0.1; Chromium loads the page from them with ``--dump-dom`` (the page records
what it rendered in ``data-*`` attributes: state, view, tile level, tiles loaded, the selected point's table
row) and ``--screenshot``. Console messages are read from Chromium's log (``--enable-logging=stderr``).
The click is a real ``click`` event dispatched by the page at the point's place on the canvas
(``?click=ID``), so it goes through the page's hit test like a mouse click.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from rectify.actions.view import ViewOptions, start_view
from tests.rectify.test_view_server import read_csv_rows, shared_block_output

RUN_TIMEOUT_S = 60
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--disable-default-apps", "--mute-audio", "--hide-scrollbars",
         "--enable-logging=stderr", "--v=0", "--window-size=1280,900"]
CONSOLE_RE = re.compile(r":CONSOLE[:(]")
LEGEND_GREEN = np.array([46, 158, 68]) / 255.0  # the class "< 1" of the legend (view.js CLASSES)
MAP_BACKGROUND = np.array([223, 227, 232]) / 255.0  # the canvas' background (#dfe3e8)


@pytest.fixture(scope="session")
def chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        exe = shutil.which(name)
        if exe:
            return exe
    pytest.skip("chromium is not installed (`.ci/run` installs it; or: apt-get install chromium)")


def _serve(folder: Path, images: tuple[str, ...] = ()):
    session = start_view(folder, ViewOptions(port=0, images=images))
    t = threading.Thread(target=session.serve_forever, daemon=True)
    t.start()
    return session, t


@pytest.fixture(scope="module")
def block_server(tmp_path_factory):
    out, photos = shared_block_output(tmp_path_factory)
    session, t = _serve(out, (str(photos),))
    yield session, out
    session.close()
    t.join(5)


@pytest.fixture(scope="module")
def raster_server(tmp_path_factory):
    """An orthophoto (2048 x 2048 px, 3 bands) and a DSM with the bands of docs/formats.md plus a sigma_Z band."""
    d = tmp_path_factory.mktemp("viewrasters")
    yy, xx = np.mgrid[0:2048, 0:2048]
    img = np.stack([(xx // 9) % 200 + 30, (yy // 7) % 200 + 30, ((xx + yy) // 11) % 200 + 30]).astype(np.uint8)
    with rasterio.open(d / "ortho.tif", "w", driver="GTiff", width=2048, height=2048, count=3, dtype="uint8",
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate", crs="EPSG:32633",
                       transform=from_origin(500000, 5000000, 0.5, 0.5)) as ds:
        ds.write(img)
    n = 600
    y, x = np.mgrid[0:n, 0:n] / n
    z = 50 + 40 * np.sin(6 * x) * np.cos(4 * y)
    z[:40, :40] = -9999
    bands = np.stack([z, np.full_like(z, 3), np.zeros_like(z), 0.05 + 0.2 * (x - 0.5) ** 2]).astype("float32")
    with rasterio.open(d / "dsm.tif", "w", driver="GTiff", width=n, height=n, count=4, dtype="float32", tiled=True,
                       blockxsize=256, blockysize=256, nodata=-9999, crs="EPSG:32633",
                       transform=from_origin(500000, 5000000, 2.5, 2.5)) as ds:
        ds.write(bands)
        for b, text in enumerate(["height: mean of the points' heights near the cell centre (m); nodata -9999",
                                  "count: points that made the cell's height (0 where none)",
                                  "filled: 1 where the height was interpolated over a hole (fill holes), else 0",
                                  "sigma_z: predicted standard deviation of the height, m"], start=1):
            ds.set_band_description(b, text)
    session, t = _serve(d)
    yield session, d
    session.close()
    t.join(5)


def _run(exe: str, args: list[str], profile: Path) -> subprocess.CompletedProcess:
    cmd = [exe, *FLAGS, f"--user-data-dir={profile}", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the browser we started and its children
        proc.communicate()
        pytest.fail(f"chromium did not finish within {RUN_TIMEOUT_S} s: {' '.join(cmd)}")
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def load(exe: str, url: str, work: Path, screenshot: Path | None = None) -> tuple[str, dict[str, str], list[str]]:
    """Load ``url``: the DOM, the body's data attributes and every console message (and a screenshot, taken by
    the same run)."""
    shot = [f"--screenshot={screenshot}"] if screenshot is not None else []
    r = _run(exe, ["--virtual-time-budget=8000", *shot, "--dump-dom", url], work / "profile")
    assert r.returncode == 0, f"chromium failed ({r.returncode}): {r.stderr[-2000:]}"
    console = [ln for ln in r.stderr.splitlines() if CONSOLE_RE.search(ln)]
    body = re.search(r"<body([^>]*)>", r.stdout)
    attrs = dict(re.findall(r'([\w-]+)="([^"]*)"', body.group(1))) if body else {}
    if screenshot is not None:
        assert screenshot.is_file(), f"no screenshot: {r.stderr[-2000:]}"
        extra = os.environ.get("RECTIFY_REPORT_SCREENSHOT_DIR")
        if extra:
            Path(extra).mkdir(parents=True, exist_ok=True)
            shutil.copy(screenshot, Path(extra) / f"view_{screenshot.name}")
    return r.stdout, attrs, console


def row_values(dom: str, table: str = "row") -> dict[str, str]:
    m = re.search(rf'<table id="{table}">(.*?)</table>', dom, re.S)
    assert m, f"no table #{table}"
    return dict(re.findall(r'<tr data-key="([^"]+)"[^>]*><th>[^<]*</th><td data-value="([^"]*)"', m.group(1)))


def assert_screenshot_layout(path: Path, *, legend: bool = True) -> None:
    """Header band dark, side panel light, map area not blank; the legend's first class colour in the panel."""
    from matplotlib.image import imread  # local: matplotlib only for reading the PNG

    rgb = imread(path)[..., :3]
    assert rgb.shape[:2] == (900, 1280)
    assert np.median(rgb[2:28, :]) < 0.3, "header band missing"
    side, main = rgb[40:, :350], rgb[40:, 370:]  # view.css: the side panel is 360 px wide
    assert side.mean() > 0.8, "side panel missing"
    drawn = np.abs(main - MAP_BACKGROUND).max(axis=-1) > 0.1
    assert drawn.mean() > 0.01, f"the map area is blank ({drawn.mean():.4f} of it drawn)"
    if legend:
        near = np.all(np.abs(side - LEGEND_GREEN) < 0.03, axis=-1)
        assert near.sum() > 50, "the legend's colour classes are missing"


def _manifest(session) -> dict:
    with urllib.request.urlopen(session.url + "api/manifest.json", timeout=20) as r:
        return json.loads(r.read())


def test_each_view_loads_without_console_messages(chromium, block_server, raster_server, tmp_path):
    bs, _ = block_server
    rs, _ = raster_server
    man = _manifest(bs)
    rman = _manifest(rs)
    views = [(bs, "layout&select=C1"), (bs, "image:2"), (bs, f"table:{man['tables'][0]['t']}")]
    views += [(rs, f"raster:{r['id']}") for r in rman["rasters"] if r["role"] in ("dsm", "raster")
              or r["label"].endswith("(sigma_z)")]
    assert len(views) == 6
    for k, (session, v) in enumerate(views):
        shot = tmp_path / f"view{k}.png"
        dom, attrs, console = load(chromium, f"{session.url}?view={v}", tmp_path / f"v{k}", screenshot=shot)
        assert_screenshot_layout(shot, legend=not v.startswith("raster"))
        assert console == [], (v, console)
        assert attrs.get("data-state") == "ready" and attrs.get("data-view") == v.split("&")[0], (v, attrs)
        assert "data-error" not in attrs and attrs.get("data-legend") == "yes", (v, attrs)
        if v.startswith("raster"):
            assert int(attrs["data-tiles-loaded"]) >= 1, (v, attrs)
        else:
            assert int(attrs["data-points"]) > 0, (v, attrs)


def test_click_on_a_known_point_shows_its_residual(chromium, block_server, tmp_path):
    session, out = block_server
    man = _manifest(session)
    rows = read_csv_rows(out / "observations.csv")
    known = max((r for r in rows if r["flagged"] == "1"), key=lambda r: float(r["residual_x_px"]) ** 2
                + float(r["residual_y_px"]) ** 2)  # the worst blunder: drawn on top, nothing hides it
    i = [im["name"] for im in man["images"]].index(known["image"])
    shot = tmp_path / "image.png"
    dom, attrs, console = load(chromium, f"{session.url}?view=image:{i}&click={known['id']}", tmp_path / "c",
                               screenshot=shot)
    assert console == [] and attrs["data-state"] == "ready"
    assert re.search(rf'<section id="detail"[^>]*data-selected="{re.escape(known["id"])}"', dom)
    row = row_values(dom)
    assert row["id"] == known["id"] and row["image"] == known["image"]
    assert float(row["vx"]) == float(known["residual_x_px"]) and float(row["vy"]) == float(known["residual_y_px"])
    assert float(row["sigma"]) == float(known["sigma_px"]) and row["flag"] == "1"
    # the track: one thumbnail per image that measured the point
    n_rays = sum(1 for r in rows if r["id"] == known["id"])
    assert len(re.findall(r'<div class="thumb', dom)) == n_rays
    assert_screenshot_layout(shot)


class DevTools:
    """A minimal client of Chromium's DevTools protocol over a WebSocket (standard library only): commands,
    their results, and the console and exception events seen meanwhile."""

    def __init__(self, ws_url: str) -> None:
        m = re.match(r"ws://([^:/]+):(\d+)(/.*)", ws_url)
        assert m, ws_url
        self.sock = socket.create_connection((m.group(1), int(m.group(2))), timeout=30)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET {m.group(3)} HTTP/1.1\r\nHost: {m.group(1)}:{m.group(2)}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
                           ).encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head
        self.n = 0
        self.console: list[str] = []

    def close(self) -> None:
        self.sock.close()

    def _exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("DevTools closed the connection")
            buf += chunk
        return buf

    def _recv(self) -> dict:
        _, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        return json.loads(self._exact(n))

    def call(self, method: str, **params: object) -> dict:
        self.n += 1
        data = json.dumps({"id": self.n, "method": method, "params": params}).encode()
        mask = os.urandom(4)
        n = len(data)
        hdr = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n))
        self.sock.sendall(hdr + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))
        while True:
            msg = self._recv()
            if msg.get("method") == "Runtime.consoleAPICalled":
                args = msg["params"].get("args", [])
                self.console.append(" ".join(str(a.get("value", a.get("description", ""))) for a in args))
            elif msg.get("method") == "Runtime.exceptionThrown":
                self.console.append(str(msg["params"]["exceptionDetails"].get("exception", {}).get("description")))
            if msg.get("id") == self.n:
                assert "error" not in msg, msg
                return msg["result"]

    def js(self, expr: str) -> object:
        return self.call("Runtime.evaluate", expression=expr, returnByValue=True)["result"].get("value")

    def wait(self, expr: str, timeout: float = 30.0) -> object:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < timeout:
            v = self.js(expr)
            if v:
                return v
            time.sleep(0.05)
        pytest.fail(f"the page never met {expr!r}")


@pytest.fixture
def devtools(chromium, tmp_path):
    """Chromium with the DevTools protocol on a free port (written by Chromium into its profile)."""
    profile = tmp_path / "cdp-profile"
    proc = subprocess.Popen([chromium, *FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
                             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        port_file = profile / "DevToolsActivePort"
        t0 = time.perf_counter()
        while not (port_file.is_file() and port_file.read_text().strip()):
            assert time.perf_counter() - t0 < RUN_TIMEOUT_S, "chromium did not open its DevTools port"
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        pages: list = []
        while not pages:
            assert time.perf_counter() - t0 < RUN_TIMEOUT_S, "chromium opened no page"
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [p for p in json.loads(r.read()) if p.get("type") == "page"]
        dt = DevTools(pages[0]["webSocketDebuggerUrl"])
        try:
            dt.call("Runtime.enable")
            dt.call("Page.enable")
            yield dt
        finally:
            dt.close()
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the browser we started and its children
        proc.wait(10)


def _open(dt: DevTools, url: str) -> None:
    dt.call("Page.navigate", url=url)
    dt.wait("document.body && document.body.dataset.state === 'ready'")


def test_native_click_and_wheel_zoom_through_devtools(devtools, block_server, raster_server):
    """A mouse click dispatched by the browser's input pipeline (DevTools ``Input.dispatchMouseEvent``) on a known
    point shows its residual; mouse-wheel zoom reaches full resolution on the orthophoto."""
    dt = devtools
    session, out = block_server
    man = _manifest(session)
    rows = read_csv_rows(out / "observations.csv")
    known = max((r for r in rows if r["flagged"] == "0"), key=lambda r: float(r["residual_x_px"]) ** 2
                + float(r["residual_y_px"]) ** 2)  # the largest residual not flagged
    i = [im["name"] for im in man["images"]].index(known["image"])
    _open(dt, f"{session.url}?view=image:{i}&worst=0")
    pid = json.dumps(known["id"])
    assert dt.js(f"rectifyView.centreOn({pid})")
    x, y = dt.js(f"rectifyView.screenOf({pid})")
    for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
        dt.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)
    dt.wait(f"document.getElementById('detail').dataset.selected === {pid} "
            "&& document.getElementById('detail').dataset.ready === 'yes'")
    row = dt.js("Object.fromEntries([...document.querySelectorAll('#row tr')].map("
                "(tr) => [tr.dataset.key, tr.querySelector('td').dataset.value]))")
    assert row["id"] == known["id"] and row["image"] == known["image"]
    assert float(row["vx"]) == float(known["residual_x_px"]) and float(row["vy"]) == float(known["residual_y_px"])
    assert row["flag"] == "0"
    assert dt.js("document.querySelectorAll('#track .thumb').length") == sum(1 for r in rows if r["id"] == known["id"])
    # the orthophoto: zoom in with the mouse wheel about the canvas centre until full resolution
    rs, _ = raster_server
    ortho = next(r for r in _manifest(rs)["rasters"] if r["label"] == "ortho.tif")
    _open(dt, f"{rs.url}?view=raster:{ortho['id']}")
    cx, cy = dt.js("(() => { const r = document.getElementById('map').getBoundingClientRect(); "
                   "return [r.left + r.width / 2, r.top + r.height / 2]; })()")
    assert dt.js("document.body.dataset.fullResolution") == "no"
    for _ in range(40):
        dt.call("Input.dispatchMouseEvent", type="mouseWheel", x=cx, y=cy, deltaX=0, deltaY=-400)
        if dt.js("rectifyView.scale() >= 1"):  # one screen pixel per image pixel or more
            break
    dt.wait("document.body.dataset.fullResolution === 'yes'")
    assert dt.js("document.body.dataset.level") == dt.js("document.body.dataset.maxLevel") == "3"
    assert dt.console == [], dt.console
