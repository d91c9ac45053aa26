#!/usr/bin/env python
"""Benchmark ``rectify warp`` against GDAL's warper (``rasterio.warp.reproject``), file to file.

One run measures, each in its own subprocess (wall time and peak RSS):

1. ours: ``rectify warp SRC DST --transform affine.json --threads 2`` (bilinear);
2. peer: ``rasterio.warp.reproject(..., num_threads=2)`` from the same source
   (whose rotated geotransform encodes the same affine map) onto the same
   output grid, writing the same tiled ZSTD GeoTIFF, with the best settings
   found for GDAL (``warp_mem_limit`` 256 MB and 1024 MB + ``OPTIMIZE_SIZE``,
   a 512 MB block cache, ``GDAL_NUM_THREADS=2``): both are measured, the
   fastest is the peer;
3. ours with a homography (mild perspective) on the same source;
4. ours on a raster wider than 32767 px (peak RSS must stay < 2 GB).

Usage: python scripts/bench_warp.py [--size 10000] [--wide 40000] [--workdir DIR] [--keep] [--repeat N]

``--repeat N`` runs ours (affine) and GDAL's fastest settings N times each, alternating, and takes the
fastest of each for the ratio (the figure is otherwise at the mercy of a shared machine's load).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHILD = r"""
import resource, sys, time, json
t0 = time.perf_counter()
kind = sys.argv[1]
if kind == "ours":
    from rectify.cli.main import cli
    cli(sys.argv[2:], standalone_mode=False)
elif kind == "gdal":
    import rasterio
    from rasterio.warp import reproject
    from rasterio.enums import Resampling
    src, dst, ref, config = sys.argv[2:6]
    cfg = json.loads(config)
    with rasterio.open(ref) as r:
        prof = dict(driver="GTiff", width=r.width, height=r.height, count=r.count, dtype=r.dtypes[0],
                    crs=r.crs, transform=r.transform, nodata=r.nodata, tiled=True, blockxsize=512,
                    blockysize=512, compress="zstd", ZSTD_LEVEL="1", predictor=2, interleave="pixel",
                    BIGTIFF="IF_SAFER", NUM_THREADS="2")  # the same creation options as rectify warp
    # the warper's best settings found: large warp memory (chunks of whole output blocks), 2 warp threads,
    # a block cache that holds the source rows a chunk needs, threaded compression
    with rasterio.Env(GDAL_CACHEMAX=cfg["cache_mb"] * 1024 * 1024, GDAL_NUM_THREADS="2"), \
            rasterio.open(src) as s, rasterio.open(dst, "w", **prof) as d:
        reproject(rasterio.band(s, list(range(1, s.count + 1))), rasterio.band(d, list(range(1, d.count + 1))),
                  resampling=Resampling.bilinear, num_threads=2, warp_mem_limit=cfg["warp_mem_mb"],
                  src_nodata=s.nodata, dst_nodata=s.nodata, **cfg.get("warp_options", {}))
dt = time.perf_counter() - t0
print(json.dumps({"seconds": dt, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run_child(args: list[str]) -> dict:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"child failed: {args}\n{p.stdout}\n{p.stderr}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["wall_with_startup_s"] = wall
    return out


def make_source(path: Path, width: int, height: int, transform, crs: str, count: int = 3) -> None:
    """A textured uint8 raster (values 1..255, nodata 0), written in strips."""
    import rasterio

    prof = dict(driver="GTiff", width=width, height=height, count=count, dtype="uint8", crs=crs,
                transform=transform, nodata=0, tiled=True, blockxsize=512, blockysize=512, compress="deflate",
                interleave="pixel", BIGTIFF="IF_SAFER", NUM_THREADS="2")
    rng = np.random.default_rng(0)
    strip = 512
    xx = np.arange(width, dtype=np.float32)
    with rasterio.open(path, "w", **prof) as ds:
        for r0 in range(0, height, strip):
            h = min(strip, height - r0)
            yy = np.arange(r0, r0 + h, dtype=np.float32)[:, None]
            base = 128 + 60 * np.sin(xx / 37.0)[None, :] * np.cos(yy / 53.0) + 30 * np.sin((xx[None, :] + yy) / 11.0)
            for b in range(count):
                noise = rng.integers(-12, 13, (h, width), dtype=np.int16)
                band = np.clip(base + 10 * b + noise, 1, 255).astype(np.uint8)
                ds.write(band, b + 1, window=rasterio.windows.Window(0, r0, width, h))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=10000)
    ap.add_argument("--wide", type=int, default=40000, help="width of the >32767 px raster (0 = skip)")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run ours (affine) and GDAL's fastest settings this many times each, alternating; the "
                         "ratio uses the fastest of each (a shared machine's load varies from run to run)")
    a = ap.parse_args()
    from affine import Affine

    from rectify.formats.transform import write_transform
    from rectify.geometry.transforms import AffineTransform, Homography
    from rectify.raster.georef import world_from_pixel_matrix
    from rectify.raster.io import raster_info

    work = Path(a.workdir or tempfile.mkdtemp(prefix="bench_warp_"))
    work.mkdir(parents=True, exist_ok=True)
    n = a.size
    ang = math.radians(7.0)
    # source geotransform = the affine model (rotated grid, 1 m pixels, small offsets keep matrices well scaled)
    T = Affine(math.cos(ang), math.sin(ang), 1000.0, math.sin(ang), -math.cos(ang), 2000.0 + n)
    src = work / f"src_{n}.tif"
    if not src.exists():
        t0 = time.perf_counter()
        make_source(src, n, n, T, "EPSG:32618")
        print(f"made {src} ({n} x {n} x 3 uint8) in {time.perf_counter() - t0:.1f} s", flush=True)
    M = world_from_pixel_matrix(T)
    write_transform(work / "affine.json", AffineTransform(M), crs="EPSG:32618", overwrite=True)
    P = M.copy()
    P[2, :2] = [2e-6, 1e-6]  # mild perspective
    write_transform(work / "homography.json", Homography(P), crs="EPSG:32618", overwrite=True)

    results = {}
    ours = work / "ours_affine.tif"
    results["ours_affine"] = run_child(["ours", "-q", "warp", str(src), str(ours), "--transform",
                                        str(work / "affine.json"), "--threads", "2", "--overwrite"])
    print("ours affine:", results["ours_affine"], flush=True)
    gdal = work / "gdal_affine.tif"
    # GDAL's warper with the best settings found (each measured here; the fastest is the peer)
    configs = {"warp memory 256 MB, cache 512 MB": {"warp_mem_mb": 256, "cache_mb": 512},
               "warp memory 1024 MB, cache 512 MB, OPTIMIZE_SIZE": {"warp_mem_mb": 1024, "cache_mb": 512,
                                                                    "warp_options": {"OPTIMIZE_SIZE": "TRUE"}}}
    gdal_runs = {}
    for label, cfg in configs.items():
        gdal.unlink(missing_ok=True)
        gdal_runs[label] = run_child(["gdal", str(src), str(gdal), str(ours), json.dumps(cfg)])
        print(f"GDAL affine ({label}, 2 threads):", gdal_runs[label], flush=True)
    best = min(gdal_runs, key=lambda k: gdal_runs[k]["seconds"])
    results["gdal_affine"] = dict(gdal_runs[best], settings=best)
    results["gdal_runs"] = gdal_runs
    ours_times, gdal_times = [results["ours_affine"]["seconds"]], [results["gdal_affine"]["seconds"]]
    for _ in range(a.repeat - 1):
        r_o = run_child(["ours", "-q", "warp", str(src), str(ours), "--transform", str(work / "affine.json"),
                         "--threads", "2", "--overwrite"])
        gdal.unlink(missing_ok=True)
        r_g = run_child(["gdal", str(src), str(gdal), str(ours), json.dumps(configs[best])])
        ours_times.append(r_o["seconds"])
        gdal_times.append(r_g["seconds"])
        print(f"repeat: ours {r_o['seconds']:.2f} s, GDAL ({best}) {r_g['seconds']:.2f} s", flush=True)
        if r_o["seconds"] < results["ours_affine"]["seconds"]:
            results["ours_affine"] = r_o
        if r_g["seconds"] < results["gdal_affine"]["seconds"]:
            results["gdal_affine"] = dict(r_g, settings=best)
    results["ours_homography"] = run_child(["ours", "-q", "warp", str(src), str(work / "ours_h.tif"), "--transform",
                                            str(work / "homography.json"), "--threads", "2", "--overwrite"])
    print("ours homography:", results["ours_homography"], flush=True)
    # agreement of the two affine outputs (sampled rows)
    import rasterio
    with rasterio.open(ours) as o, rasterio.open(gdal) as g:
        rows = np.linspace(0, o.height - 1, 40).astype(int)
        diffs = []
        for r in rows:
            win = rasterio.windows.Window(0, int(r), o.width, 1)
            x, y = o.read(window=win).astype(int), g.read(window=win).astype(int)
            both = (x > 0).all(0) & (y > 0).all(0)
            diffs.append(np.abs(x[:, both] - y[:, both]).ravel())
        d = np.concatenate(diffs)
        results["affine_output_diff_dn"] = {"mean": float(d.mean()), "p99": float(np.percentile(d, 99)),
                                            "max": int(d.max())}
    if a.wide:
        wide = work / f"wide_{a.wide}.tif"
        if not wide.exists():
            make_source(wide, a.wide, 2000, Affine(1, 0, 1000, 0, -1, 4000), "EPSG:32618", count=1)
        Tw = Affine(math.cos(0.01), math.sin(0.01), 1000.0, math.sin(0.01), -math.cos(0.01), 4000.0)
        write_transform(work / "wide.json", AffineTransform(world_from_pixel_matrix(Tw)), crs="EPSG:32618",
                       overwrite=True)
        results["ours_wide"] = run_child(["ours", "-q", "warp", str(wide), str(work / "ours_wide.tif"), "--transform",
                                          str(work / "wide.json"), "--threads", "2", "--overwrite"])
        results["ours_wide"]["size"] = [raster_info(work / "ours_wide.tif").width,
                                        raster_info(work / "ours_wide.tif").height]
        print("ours wide:", results["ours_wide"], flush=True)

    oa, ga, oh = results["ours_affine"], results["gdal_affine"], results["ours_homography"]
    print()
    print(f"| {n} x {n} x 3 uint8, bilinear, 2 threads | wall s | peak RSS MB |")
    print("|---|---|---|")
    print(f"| rectify warp (affine) | {oa['seconds']:.2f} | {oa['peak_rss_mb']:.0f} |")
    for label, g in results["gdal_runs"].items():
        print(f"| GDAL reproject, {label}, 2 threads{' (peer: fastest)' if label == ga['settings'] else ''} | "
              f"{g['seconds']:.2f} | {g['peak_rss_mb']:.0f} |")
    print(f"| rectify warp (homography) | {oh['seconds']:.2f} | {oh['peak_rss_mb']:.0f} |")
    if "ours_wide" in results:
        w = results["ours_wide"]
        print(f"| rectify warp, {w['size'][0]} x {w['size'][1]} output from {a.wide} x 2000 | {w['seconds']:.2f} "
              f"| {w['peak_rss_mb']:.0f} |")
    print()
    print(f"time ratio ours/GDAL = {oa['seconds'] / ga['seconds']:.3f} (target <= 0.3; GDAL: {ga['settings']})"
          + (f"; fastest of {a.repeat} alternating runs each: ours {', '.join(f'{t:.2f}' for t in ours_times)} s, "
             f"GDAL {', '.join(f'{t:.2f}' for t in gdal_times)} s" if a.repeat > 1 else ""))
    print(f"RSS ratio ours/GDAL = {oa['peak_rss_mb'] / ga['peak_rss_mb']:.3f} (target <= 1)")
    print(f"homography/affine time = {oh['seconds'] / oa['seconds']:.3f} (target <= 1.2)")
    if "ours_wide" in results:
        print(f"wide raster peak RSS = {results['ours_wide']['peak_rss_mb']:.0f} MB (target < 2048)")
    print(f"affine outputs ours vs GDAL: |diff| mean {results['affine_output_diff_dn']['mean']:.3f} DN, "
          f"p99 {results['affine_output_diff_dn']['p99']:.0f}, max {results['affine_output_diff_dn']['max']}")
    (work / "bench_warp.json").write_text(json.dumps(results, indent=2))
    if not a.keep:
        for p in work.glob("*.tif"):
            p.unlink()


if __name__ == "__main__":
    main()
