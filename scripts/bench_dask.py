#!/usr/bin/env python
"""Benchmark the tiled steps on Dask: a warp and an orthophoto on 1 and 2 local worker processes, in one run.

For each job (a SIZE x SIZE x 3 uint8 warp with an affine transform, bilinear, as ``scripts/bench_warp.py``;
an RPC + DEM orthophoto of a SIZE x SIZE image, as ``scripts/bench_ortho.py``; with ``--jobs ...,dense``
the dense matching (``stereo.dense.matching.match_rasters``, 1024 px tiles, one tile per task) of the
synthetic normal-case pair of ``scripts/bench_dense.py``, ``--dense-size`` px) and each scheduler, a child
process starts a ``distributed.LocalCluster`` of N worker processes (one thread each), imports the
engine on the workers, then times the library call with ``scheduler=<the cluster's address>``
(cluster start-up is reported apart). Peak memory: each worker's VmHWM (its peak resident set since it
started), and the driver's, which assembles the GeoTIFF. The local thread pool (``threads``, today's
default path, 2 threads) is run too, for reference. Outputs of every run are compared with the
``threads`` output: they must be identical.

    nice python scripts/bench_dask.py --size 10000 --workdir /tmp/bench_dask
    python scripts/bench_dask.py --size 3000            # quick
    python scripts/bench_dask.py --jobs dense --size 3000   # dense matching tiles

The speedup printed is (time on 1 worker) / (time on 2 workers); target >= 1.8.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
sys.path.insert(0, str(ROOT))

CHILD = r"""
import json, os, sys, time
sys.path.insert(0, {root!r})
os.environ.setdefault("GDAL_CACHEMAX", "64")

def vmhwm_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")

def cpu_s():
    import resource
    u = resource.getrusage(resource.RUSAGE_SELF)
    return u.ru_utime + u.ru_stime

def warm():
    # the imports are not part of the job
    import rectify.raster.ortho, rectify.raster.warp, stereo.dense.matching  # noqa: F401
    return vmhwm_mb()

if __name__ == "__main__":
    cfg = json.loads({cfg!r})
    warm()
    client = cluster = None
    t_start = 0.0
    if cfg["workers"]:
        import distributed
        import dask
        t0 = time.perf_counter()
        # the settings of rectify's own processes:N cluster (rectify.raster.distributed.LOCAL_CLUSTER_CONFIG)
        from rectify.raster.distributed import LOCAL_CLUSTER_CONFIG
        with dask.config.set(LOCAL_CLUSTER_CONFIG):
            cluster = distributed.LocalCluster(n_workers=cfg["workers"], threads_per_worker=1, processes=True,
                                               dashboard_address=":0")
        client = distributed.Client(cluster)
        client.run(warm)
        t_start = time.perf_counter() - t0
        scheduler = cluster.scheduler_address
    else:
        scheduler = "threads"
    cpu0 = sorted(client.run(cpu_s).items()) if client is not None else []
    cpu_driver0 = cpu_s()
    t0 = time.perf_counter()
    if cfg["job"] == "warp":
        from rectify.formats.transform import read_transform
        from rectify.raster.georectify import rectify_with_transform
        from rectify.raster.warp import WarpOptions
        tf = read_transform(cfg["transform"])
        rectify_with_transform(cfg["src"], cfg["out"], tf.model, model_crs=tf.crs,
                               options=WarpOptions(threads=2, scheduler=scheduler), overwrite=True)
    elif cfg["job"] == "dense":
        from stereo.dense.matching import match_rasters
        match_rasters(cfg["left"], cfg["right"], cfg["out"], cfg["out"][:-4] + "_conf.tif",
                      disparity_range=(0, 48), scheduler=scheduler)
    else:
        from affine import Affine
        import rasterio
        from rectify.raster.dem import Dem
        from rectify.raster.georef import Grid
        from rectify.geometry.sensors import RPCModel
        from rectify.raster.ortho import OrthoOptions, orthorectify
        from rectify.formats.rpc import rpc_from_raster
        rpc = rpc_from_raster(cfg["src"])
        with rasterio.open(cfg["src"]) as ds:
            w, h = ds.width, ds.height
        grid = Grid(cfg["width"], cfg["height"], Affine(*cfg["transform_ortho"]), cfg["crs"])
        orthorectify(cfg["src"], cfg["out"], RPCModel(rpc, w, h), Dem.from_path(cfg["dem"]), grid=grid,
                     options=OrthoOptions(threads=2, scheduler=scheduler), overwrite=True)
    seconds = time.perf_counter() - t0
    cpu_driver = cpu_s() - cpu_driver0
    workers = sorted(client.run(vmhwm_mb).values()) if client is not None else []
    cpu1 = dict(client.run(cpu_s)) if client is not None else {{}}
    worker_cpu = [cpu1[k] - v for k, v in cpu0 if k in cpu1]
    if client is not None:
        client.close()
        cluster.close()
    print(json.dumps({{"seconds": seconds, "startup_s": t_start, "driver_rss_mb": vmhwm_mb(),
                      "worker_rss_mb": workers, "driver_cpu_s": cpu_driver, "worker_cpu_s": worker_cpu}}))
"""


def run_child(cfg: dict) -> dict:
    code = CHILD.format(root=str(ROOT), cfg=json.dumps(cfg))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    if p.returncode != 0:
        raise SystemExit(f"child failed: {cfg['job']} {cfg['workers']}\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def same_pixels(a: str, b: str) -> bool:
    """True when the two GeoTIFFs hold the same pixels and masks (compared window by window)."""
    import numpy as np
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(a) as A, rasterio.open(b) as B:
        if (A.width, A.height, A.count) != (B.width, B.height, B.count) or A.transform != B.transform:
            return False
        for r in range(0, A.height, 1024):
            w = Window(0, r, A.width, min(1024, A.height - r))
            if not (np.array_equal(A.read(window=w), B.read(window=w))
                    and np.array_equal(A.read_masks(1, window=w), B.read_masks(1, window=w))):
                return False
    return True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=10000, help="source side in pixels (warp and ortho)")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--jobs", default="warp,ortho", help="comma-separated: warp, ortho, dense")
    ap.add_argument("--dense-size", type=int, default=None,
                    help="side of the dense matching pair (default --size; scripts/bench_dense.py's pair)")
    ap.add_argument("--keep", action="store_true", help="keep the outputs")
    a = ap.parse_args()
    import tempfile

    import bench_dense
    import bench_ortho
    import bench_warp
    from affine import Affine

    from rectify.formats.transform import write_transform
    from rectify.geometry.transforms import AffineTransform
    from rectify.raster.georef import world_from_pixel_matrix

    work = a.workdir or Path(tempfile.mkdtemp(prefix="bench_dask_"))
    work.mkdir(parents=True, exist_ok=True)
    n = a.size
    jobs = [j.strip() for j in a.jobs.split(",") if j.strip()]
    cfg: dict = {}
    t0 = time.perf_counter()
    if "warp" in jobs:
        ang = math.radians(7.0)
        T = Affine(math.cos(ang), math.sin(ang), 1000.0, math.sin(ang), -math.cos(ang), 2000.0 + n)
        src = work / f"warp_src_{n}.tif"
        if not src.exists():
            bench_warp.make_source(src, n, n, T, "EPSG:32618")
        write_transform(work / "affine.json", AffineTransform(world_from_pixel_matrix(T)), crs="EPSG:32618",
                        overwrite=True)
        cfg["warp"] = {"src": str(src), "transform": str(work / "affine.json")}
    if "ortho" in jobs:
        o = bench_ortho.build(work, n)
        cfg["ortho"] = {"src": o["src"], "dem": o["dem"], "width": o["width"], "height": o["height"],
                        "transform_ortho": o["transform"], "crs": o["crs"]}
    if "dense" in jobs:
        dn = a.dense_size or n
        (work / f"dense_{dn}").mkdir(exist_ok=True)
        lp, rp = bench_dense.make_pair(work / f"dense_{dn}", dn)
        cfg["dense"] = {"left": str(lp), "right": str(rp)}
    print(f"inputs built in {time.perf_counter() - t0:.1f} s in {work}", flush=True)

    from rectify.raster.distributed import GUIDED_MAX, GUIDED_MIN

    tile, per_task = 512, GUIDED_MAX
    rows = []
    for job in jobs:
        ref = None
        for workers in (0, 1, 2):
            label = "threads (2)" if workers == 0 else f"{workers} worker process{'es' if workers > 1 else ''}"
            out = work / f"{job}_{workers}.tif"
            r = run_child(dict(cfg[job], job=job, workers=workers, out=str(out)))
            r.update(job=job, workers=workers, label=label)
            if workers == 0:
                ref = out
            else:
                r["identical"] = same_pixels(str(ref), str(out))
            rows.append(r)
            print(f"{job}, {label}: {r}", flush=True)
        if not a.keep:
            for w in (1, 2):
                (work / f"{job}_{w}.tif").unlink(missing_ok=True)
                (work / f"{job}_{w}_conf.tif").unlink(missing_ok=True)

    chunk_mb = per_task * tile * tile * 3 / 1e6
    print()
    print(f"| {n} x {n} source | scheduler | job s | cluster start s | CPU s: driver / workers | "
          f"peak RSS per worker MB | driver MB | identical to threads |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        wr = ", ".join(f"{v:.0f}" for v in r["worker_rss_mb"]) or "-"
        wc = " + ".join(f"{v:.1f}" for v in r["worker_cpu_s"]) or "-"
        ident = "-" if r["workers"] == 0 else ("yes" if r["identical"] else "NO")
        print(f"| {r['job']} | {r['label']} | {r['seconds']:.2f} | {r['startup_s']:.1f} | "
              f"{r['driver_cpu_s']:.1f} / {wc} | {wr} | {r['driver_rss_mb']:.0f} | {ident} |")
    print()
    for job in jobs:
        t = {r["workers"]: r["seconds"] for r in rows if r["job"] == job}
        cpu = {r["workers"]: r["driver_cpu_s"] + sum(r["worker_cpu_s"]) for r in rows if r["job"] == job}
        print(f"{job}: speedup 2 workers vs 1 = {t[1] / t[2]:.2f} (target >= 1.8); "
              f"2 workers vs local threads = {t[0] / t[2]:.2f}; CPU used per wall second: "
              f"1 worker {cpu[1] / t[1]:.2f}, 2 workers {cpu[2] / t[2]:.2f} (of {os.cpu_count()} cores)")
    if "dense" in jobs:
        print("dense: one task = one matching tile (1024 px core + 48 px overlap), its disparity block written by "
              "the worker; the driver does the coarse pass and writes disparity.tif and confidence.tif")
    print(f"chunk (warp, ortho): one task = {GUIDED_MIN} to {per_task} output tiles of {tile} x {tile} px (up to "
          f"{chunk_mb:.1f} MB of uint8 RGB output; tasks shrink towards the end), computed and compressed one at a "
          f"time by the worker (one decoded tile plus its source window in memory: the peak per worker does not "
          f"grow with the task); the driver copies the compressed tiles into the GeoTIFF")
    (work / "bench_dask.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
