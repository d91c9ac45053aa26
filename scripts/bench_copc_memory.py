#!/usr/bin/env python
"""Benchmark: the memory of the COPC octree build, in one piece against by batches (issue 27).

A surface-like cloud (``stereo surface``'s: one point per DSM cell): a ``--side`` x ``--side`` grid of
0.25 m cells over a rolling surface in UTM 33N with ``sigma_z``, ``pair`` and ``count``, streamed in
256-row chunks into ``points.copc.laz`` twice: with ``COPC_BATCH`` at its default (a cloud of more
points is built by batches of whole octree nodes) and with ``COPC_BATCH`` above the cloud's size (the
build in one piece). Prints the write time, the file size, and the peak anonymous memory (``RssAnon``
of ``/proc/self/status``, sampled every 20 ms) of the copclib child process, which builds the octree.

Usage: ``python scripts/bench_copc_memory.py [--side 4000] [--out DIR]`` (Linux; copclib installed)
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

import stereo.formats.cloud as cloud


def chunks(side: int):
    for r0 in range(0, side, 256):
        rr, cc = np.mgrid[r0:min(r0 + 256, side), 0:side]
        x = 350000 + 0.25 * cc.ravel()
        y = 5800000 - 0.25 * rr.ravel()
        z = 100 + 5 * np.sin(x / 20) + 3 * np.cos(y / 30)
        m = len(x)
        yield cloud.CloudChunk(np.column_stack([x, y, z]), None,
                               {"sigma_z": np.full(m, 0.05), "pair": np.zeros(m), "count": np.ones(m)})


def _rss_anon_kb() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1])
    return 0


def measured_body(real):
    """``_copc_body`` wrapped to report the child's peak anonymous memory on stderr (MB)."""
    def body(*args):
        peak, stop = [0], threading.Event()

        def sample():
            while not stop.is_set():
                peak[0] = max(peak[0], _rss_anon_kb())
                stop.wait(0.02)

        t = threading.Thread(target=sample, daemon=True)
        t.start()
        try:
            real(*args)
        finally:
            stop.set()
            t.join()
            os.write(2, f"  copclib child: peak RssAnon {peak[0] / 1024:.0f} MB\n".encode())
    return body


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=4000)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    if not cloud.copc_available():
        raise SystemExit("copclib is not installed")
    cloud._copc_body = measured_body(cloud._copc_body)
    default = cloud.COPC_BATCH
    with tempfile.TemporaryDirectory() as td:
        out = (a.out or Path(td)) / "points.copc.laz"
        for label, batch in (("by batches", default), ("in one piece", a.side ** 2 + 1)):
            cloud.COPC_BATCH = batch
            out.unlink(missing_ok=True)
            t = time.perf_counter()
            cloud.write_cloud(out, chunks(a.side), extra_dims=["sigma_z", "pair", "count"], crs_wkt="EPSG:32633")
            print(f"{a.side ** 2} points, {label} (COPC_BATCH {batch}): {time.perf_counter() - t:.1f} s, "
                  f"{out.stat().st_size / 1e6:.1f} MB", flush=True)


if __name__ == "__main__":
    main()
