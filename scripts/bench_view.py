"""Benchmark of ``rectify view`` (issue 31): time to first paint in Chromium and the server's memory.

Two folders, written here from the documented formats (docs/formats.md):

- ``ortho``: one 10 000 x 10 000 px, 3-band uint8 orthophoto, tiled (256 px), deflate, no overviews (as
  ``rectify ortho`` writes it without ``--cog``), and the same as a COG-like file with overviews
  (``--cog`` adds them);
- ``block``: a synthetic block of 500 photos (20 strips x 25, 60 % / 30 % overlap) without the photos
  themselves: ``orientation.json`` (block orientation, one camera), ``observations.csv`` (300 observations a
  photo, 150 000 rows, 1 % flagged), ``points.csv`` and a report folder with a control-point table.

For each folder the script starts ``rectify view DIR --no-browser --port P`` as a subprocess, opens the page
in headless Chromium through the DevTools protocol (a minimal WebSocket client below, standard library only)
and reads what the page records: ``data-ready-ms`` (``performance.now()`` when the first view has drawn with
its data: manifest and points, or the raster's first tiles requested) and ``data-first-tile-ms`` (the first
tile arrived), both from the start of navigation. The server's peak resident memory is its ``VmHWM`` in
``/proc/<pid>/status`` after the page loaded and after a sweep of 200 full-resolution tiles.

Usage: ``python scripts/bench_view.py [--work DIR] [--keep]`` (needs ``chromium``; writes about 300 MB
into the work folder, removed at the end unless ``--keep``).
"""

from __future__ import annotations

import argparse
import base64
import csv
import json
import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.transform import from_origin
from rasterio.windows import Window

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ data
def write_ortho(path: Path, n: int = 10_000, *, overviews: bool = False) -> None:
    prof = dict(driver="GTiff", width=n, height=n, count=3, dtype="uint8", tiled=True, blockxsize=256,
                blockysize=256, compress="deflate", crs="EPSG:32633", nodata=0,
                transform=from_origin(500000, 5_010_000, 0.5, 0.5))
    rng = np.random.default_rng(0)
    with rasterio.open(path, "w", **prof) as ds:
        for r in range(0, n, 1024):
            h = min(1024, n - r)
            yy, xx = np.mgrid[r:r + h, 0:n]
            a = np.stack([(xx // 7 + yy // 5) % 200 + 20, (xx // 13) % 200 + 30,
                          (yy // 11) % 200 + 25]).astype(np.uint8)
            a += rng.integers(0, 20, a.shape, dtype=np.uint8)
            ds.write(a, window=Window(0, r, n, h))
        if overviews:
            ds.build_overviews([2, 4, 8, 16, 32, 64], Resampling.average)


def write_block(d: Path, n_strips: int = 20, per_strip: int = 25, obs_per_image: int = 300) -> int:
    """A synthetic 500-photo block in the documented files; returns the number of observations."""
    rng = np.random.default_rng(1)
    d.mkdir(parents=True, exist_ok=True)
    w, h, pix, f = 6000, 4000, 0.004, 35.0
    height = 500.0
    gsd = pix / f * height
    base, strip = 0.4 * w * gsd, 0.7 * h * gsd
    images, obs_rows = [], []
    for s in range(n_strips):
        for k in range(per_strip):
            name = f"img_{s:02d}_{k:02d}.jpg"
            x, y = 500000 + k * base, 5_000_000 - s * strip
            images.append({"image": name, "camera": "cam", "position": [x, y, height + rng.normal(0, 0.5)],
                           "rotation": np.eye(3).tolist(), "angles_rad": {"omega": 0.0, "phi": 0.0, "kappa": 0.0},
                           "std_errors": {"omega": 1e-4, "phi": 1e-4, "kappa": 1e-4, "x": 0.03, "y": 0.03, "z": 0.05}})
            cols = rng.uniform(0, w - 1, obs_per_image)
            rows = rng.uniform(0, h - 1, obs_per_image)
            v = rng.normal(0, 0.3, (obs_per_image, 2))
            flagged = rng.random(obs_per_image) < 0.01
            v[flagged] *= 20
            for j in range(obs_per_image):
                pid = f"t{(s * per_strip + k) * 120 + j % 200}"  # ids shared with the neighbours: tracks
                obs_rows.append([name, pid, f"{cols[j]:.4f}", f"{rows[j]:.4f}", "0.5", f"{v[j, 0]:.5f}",
                                 f"{v[j, 1]:.5f}", "1.0" if not flagged[j] else "0.01", "1" if flagged[j] else "0"])
    doc = {"format": "rectify-stereo/block-orientation", "version": 1, "crs": "EPSG:32633",
           "frame": "EPSG:32633 (synthetic)", "angles": "omega-phi-kappa",
           "cameras": {"cam": {"focal_length_mm": f, "pixel_size_mm": pix, "width": w, "height": h}},
           "images": images, "sigma0": {"all": 1.0}, "datum": ["synthetic"],
           "summary": {"images": len(images), "observations": len(obs_rows)}}
    (d / "orientation.json").write_text(json.dumps(doc))
    with open(d / "observations.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["image", "id", "col", "row", "sigma_px", "residual_x_px", "residual_y_px", "weight", "flagged"])
        wr.writerows(obs_rows)
    ids = sorted({r[1] for r in obs_rows})
    with open(d / "points.csv", "w", newline="") as fh:
        fh.write("# crs=EPSG:32633\nid,x,y,z,residual_mm\n")
        for i, pid in enumerate(ids):
            fh.write(f"{pid},{500000 + (i % 3000) * 2.0:.3f},{5_000_000 - (i // 3000) * 50.0:.3f},100.0,0.002\n")
    rep = d / "report"
    rep.mkdir(exist_ok=True)
    (rep / "bundle_control_points.csv").write_text(
        "# step=bundle: control points; units=m; residual = adjusted - observed\n"
        "id,observed_0,observed_1,observed_2,adjusted_0,adjusted_1,adjusted_2,dX,dY,dZ,norm,normalised,weight,outlier,check\n"
        + "".join(f"C{k},{500000 + k * 300.0},{5_000_000 - k * 200.0},100,{500000 + k * 300.0 + 0.01},"
                  f"{5_000_000 - k * 200.0},100.02,0.01,0,0.02,0.0224,1.1,1,0,0\n" for k in range(10)))
    (rep / "report.json").write_text(json.dumps({
        "format": "rectify-stereo/report", "version": 2, "title": "synthetic block", "tables": [
            {"step": "bundle: control points", "slug": "bundle_control_points", "units": "m",
             "components": ["dX", "dY", "dZ"], "files": {"csv": "bundle_control_points.csv"}}],
        "figures": {}, "files": []}))
    return len(obs_rows)


# ------------------------------------------------------------------ DevTools protocol (minimal WebSocket client)
class DevTools:
    def __init__(self, ws_url: str) -> None:
        m = re.match(r"ws://([^:/]+):(\d+)(/.*)", ws_url)
        assert m, ws_url
        self.sock = socket.create_connection((m.group(1), int(m.group(2))), timeout=30)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET {m.group(3)} HTTP/1.1\r\nHost: {m.group(1)}:{m.group(2)}\r\n"
                           f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           "Sec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head
        self.n = 0

    def _send(self, text: str) -> None:
        data = text.encode()
        mask = os.urandom(4)
        hdr = bytes([0x81])
        ln = len(data)
        hdr += bytes([0x80 | ln]) if ln < 126 else (bytes([0x80 | 126]) + struct.pack(">H", ln) if ln < 65536
                                                     else bytes([0x80 | 127]) + struct.pack(">Q", ln))
        self.sock.sendall(hdr + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def _recv_exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("DevTools closed")
            buf += chunk
        return buf

    def _recv(self) -> str:
        b0, b1 = self._recv_exact(2)
        ln = b1 & 0x7F
        if ln == 126:
            ln = struct.unpack(">H", self._recv_exact(2))[0]
        elif ln == 127:
            ln = struct.unpack(">Q", self._recv_exact(8))[0]
        return self._recv_exact(ln).decode(errors="replace")

    def call(self, method: str, **params: object) -> dict:
        self.n += 1
        self._send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self._recv())
            if msg.get("id") == self.n:
                return msg

    def evaluate(self, expr: str) -> object:
        r = self.call("Runtime.evaluate", expression=expr, returnByValue=True)
        return r["result"]["result"].get("value")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def vm(pid: int, key: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    return math.nan


def wait_port(port: int, timeout: float = 60.0) -> float:
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return time.perf_counter() - t0
        except OSError:
            time.sleep(0.02)
    raise RuntimeError(f"server did not listen on {port}")


def measure(folder: Path, label: str, chromium: str, work: Path, *, sweep_raster: int | None = None) -> dict:
    port = free_port()
    t_start = time.perf_counter()
    srv = subprocess.Popen([sys.executable, "-c", "from rectify.cli.main import cli; cli()", "view", str(folder),
                            "--no-browser", "--port", str(port)], cwd=ROOT, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, start_new_session=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
    browser = None
    try:
        wait_port(port)
        t_listen = time.perf_counter() - t_start
        dport = free_port()
        prof = Path(tempfile.mkdtemp(dir=work))
        browser = subprocess.Popen([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                                    "--disable-background-networking", "--disable-extensions", "--mute-audio",
                                    f"--user-data-dir={prof}", "--window-size=1280,900",
                                    f"--remote-debugging-port={dport}", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        wait_port(dport)
        for _ in range(100):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{dport}/json/list", timeout=5) as r:
                    pages = [p for p in json.loads(r.read()) if p.get("type") == "page"]
                if pages:
                    break
            except OSError:
                pass
            time.sleep(0.05)
        dt = DevTools(pages[0]["webSocketDebuggerUrl"])
        dt.call("Page.enable")
        t_nav = time.perf_counter()
        dt.call("Page.navigate", url=f"http://127.0.0.1:{port}/")
        ready = tile = None
        while time.perf_counter() - t_nav < 60:
            st = dt.evaluate("(() => { const b = document.body; if (!b) return null; const d = b.dataset;"
                             " return [d.state, d.readyMs, d.firstTileMs, d.view]; })()")
            if st and st[0] == "ready" and (st[3] != "raster:0" or st[2]):
                ready, tile = st[1], st[2]
                break
            if st and st[0] == "failed":
                raise RuntimeError(f"page failed: {dt.evaluate('document.body.dataset.error')}")
            time.sleep(0.02)
        wall = time.perf_counter() - t_nav
        out = {"folder": label, "server_listening_s": round(t_listen, 2), "ready_ms": ready,
               "first_tile_ms": tile, "wall_to_ready_s": round(wall, 2),
               "server_rss_mb_after_load": round(vm(srv.pid, "VmRSS"), 1),
               "server_peak_mb_after_load": round(vm(srv.pid, "VmHWM"), 1)}
        if sweep_raster is not None:
            t0 = time.perf_counter()
            n = 0
            for ty in range(0, 40, 4):
                for tx in range(0, 40, 2):
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/tiles/{sweep_raster}/6/{tx}_{ty}.png",
                                                timeout=30) as r:
                        r.read()
                    n += 1
            out["full_res_tiles"] = n
            out["full_res_tile_ms_mean"] = round(1000 * (time.perf_counter() - t0) / n, 1)
        out["server_peak_mb"] = round(vm(srv.pid, "VmHWM"), 1)
        return out
    finally:
        if browser is not None:
            os.killpg(browser.pid, signal.SIGTERM)
            browser.wait(10)
        os.killpg(srv.pid, signal.SIGINT)
        try:
            srv.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(srv.pid, signal.SIGKILL)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--keep", action="store_true")
    args = ap.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        sys.exit("chromium is not installed")
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_view_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        results = []
        plain, cog = work / "ortho", work / "ortho_ovr"
        plain.mkdir(exist_ok=True)
        cog.mkdir(exist_ok=True)
        t = time.perf_counter()
        if not (plain / "ortho.tif").exists():
            write_ortho(plain / "ortho.tif")
        if not (cog / "ortho.tif").exists():
            shutil.copy(plain / "ortho.tif", cog / "ortho.tif")
            with rasterio.open(cog / "ortho.tif", "r+") as ds:
                ds.build_overviews([2, 4, 8, 16, 32, 64], Resampling.average)
        print(f"orthophotos written in {time.perf_counter() - t:.1f} s "
              f"({(plain / 'ortho.tif').stat().st_size / 2**20:.0f} MB, with overviews "
              f"{(cog / 'ortho.tif').stat().st_size / 2**20:.0f} MB)")
        t = time.perf_counter()
        n_obs = write_block(work / "block")
        print(f"block of 500 photos written in {time.perf_counter() - t:.1f} s ({n_obs} observations)")
        results.append(measure(plain, "10000^2 orthophoto, no overviews", chromium, work, sweep_raster=0))
        results.append(measure(cog, "10000^2 orthophoto, overviews", chromium, work, sweep_raster=0))
        results.append(measure(work / "block", "500-photo block (layout view)", chromium, work))
        for r in results:
            print(json.dumps(r))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
