#!/usr/bin/env python
"""Benchmark: the point cloud writer (``stereo.formats.cloud``) as LAS, LAZ and COPC (issue 27).

A dense-matching-like cloud: ``--points`` points (default 1e6) on a 0.1 m grid over a rolling
surface (heights +-15 m, a 1 cm Gaussian noise), in UTM 33N, with RGB and the project's three extra
dimensions (``sigma_z`` float32 from 2 to 20 cm, ``pair`` uint16 from 12 pairs in strips,
``count`` uint16 1..4). Each format is written streamed in ``--chunk``-point chunks (as
``stereo dense`` does) and once whole; the script prints the write time, the file size, the bytes
per point, and checks that laspy reads every point and extra value back (COPC: through
``laspy.CopcReader``, matching the points by their coordinates).

Usage: ``python scripts/bench_point_cloud.py [--points 1000000] [--chunk 65536] [--out DIR]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

from stereo.formats.cloud import CloudChunk, copc_available, laz_available, write_cloud

DIMS = ["sigma_z", "pair", "count"]


def scene(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    k = np.arange(n)
    x = 500000.0 + 0.1 * (k % side)
    y = 5500000.0 + 0.1 * (k // side)
    z = 300 + 15 * np.sin(x / 37.0) * np.cos(y / 53.0) + rng.normal(0, 0.01, n)
    xyz = np.column_stack([x, y, z])
    colors = np.clip(np.column_stack([z - 200, z - 220, z - 240]) * 1.5, 0, 255).astype(np.uint8)
    extra = {"sigma_z": rng.uniform(0.02, 0.2, n), "pair": (k // side * 12 // side).astype(np.uint16),
             "count": rng.integers(1, 5, n)}
    return xyz, colors, extra


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--chunk", type=int, default=65536)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    out = a.out or Path(tempfile.mkdtemp(prefix="bench_cloud_"))
    out.mkdir(parents=True, exist_ok=True)
    xyz, colors, extra = scene(a.points)
    offset = np.floor(xyz.min(axis=0))
    fmts = [".las"] + ([".laz"] if laz_available() else []) + ([".copc.laz"] if copc_available() else [])
    print(f"{a.points} points, chunks of {a.chunk}, extra dims {DIMS}, folder {out}")
    print(f"{'file':<24}{'mode':<9}{'write s':>9}{'MB':>9}{'B/point':>9}  check")
    for suffix in fmts:
        for mode in ("chunked", "whole"):
            p = out / f"cloud_{mode}{suffix}"
            t = time.perf_counter()
            if mode == "whole":
                write_cloud(p, xyz, colors=colors, extra=extra, crs_wkt="EPSG:32633", offset=offset, overwrite=True)
            else:
                chunks = (CloudChunk(xyz[i:i + a.chunk], colors[i:i + a.chunk],
                                     {k: v[i:i + a.chunk] for k, v in extra.items()})
                          for i in range(0, a.points, a.chunk))
                write_cloud(p, chunks, extra_dims=DIMS, crs_wkt="EPSG:32633", offset=offset, overwrite=True)
            dt = time.perf_counter() - t
            size = p.stat().st_size
            if suffix == ".copc.laz":
                with laspy.CopcReader.open(p) as cr:
                    pts = cr.query()
            else:
                pts = laspy.read(p).points
            got = np.column_stack([pts.X, pts.Y, pts.Z]).astype(np.int64)
            want = np.rint((xyz - offset) / 0.001).astype(np.int64)
            og = np.lexsort(got.T[::-1])
            ow = np.lexsort(want.T[::-1])
            ok = (np.array_equal(got[og], want[ow])
                  and np.array_equal(np.asarray(pts["sigma_z"])[og], extra["sigma_z"].astype(np.float32)[ow])
                  and np.array_equal(np.asarray(pts["pair"])[og], extra["pair"][ow]))
            print(f"{p.name:<24}{mode:<9}{dt:>9.2f}{size / 1e6:>9.1f}{size / a.points:>9.1f}  "
                  f"{'all points and extra values read back' if ok else 'MISMATCH'}")


if __name__ == "__main__":
    main()
