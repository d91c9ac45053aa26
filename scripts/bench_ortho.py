"""Benchmark ``rectify ortho`` against GDAL's warper (RPC + DEM) or orthority (frame cameras), in one run.

RPC mode (default): builds a synthetic RPC scene (an N x N uint8 tiled GeoTIFF with RPC tags, a DEM in
EPSG:4326), then runs each side in its own subprocess onto the same output grid (UTM, tiled 512, ZSTD
level 1, predictor 2, 2 threads) and prints wall time, peak RSS and the agreement of the two outputs.

    nice python scripts/bench_ortho.py --size 20000 --workdir /tmp/bench_ortho

Frame mode (``--frames DIR``): the frames of a folder holding orthority's own ``orthority_int_param.yaml``,
``orthority_ext_param.geojson`` and ``dem.tif`` (the NGI pair ``ngi_strip05`` of the shared data), every
frame orthorectified by ``rectify ortho`` (the action, reading orthority's files) and by orthority
(``pip install .[bench]``) in one process, alternating, ``--repeat`` times each; the fastest run of
each side counts. Both at the same resolution, bilinear image and DEM interpolation, 2 threads for
ours; orthority with its defaults otherwise (JPEG with internal overviews and mask). Prints the time
ratio (target ours/orthority <= 0.7), the output size ratio for each of our output options, the
pixel agreement (sub-pixel shift between the two orthophotos by phase correlation, and the mean
|difference| in DN where both hold data), ``--true-ortho`` against the plain orthophoto, and the load
average beside the figures (the machine may be shared).

    nice python scripts/bench_ortho.py --frames ../shared/data/ngi_strip05 --workdir /tmp/bench_oty --repeat 5

``--resolution`` takes several sizes (default 5.6 m, the frames' GSD, and 2 m): one table each.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
E0, N0 = 500_000.0, 5_000_000.0
CRS = "EPSG:32632"


def build(work: Path, n: int) -> dict:
    """Source image with RPC tags, DEM, and the output grid (same for both sides)."""
    import rasterio
    from affine import Affine
    from rasterio.windows import Window

    sys.path.insert(0, str(ROOT))
    from rectify.geometry.crs import transform_xy
    from rectify.geometry.rpc import RPC

    gsd = 1.0
    half = n / 2 * gsd
    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[E0, N0]])[0]
    m_lon, m_lat = 1.0 / (111_320 * np.cos(np.radians(lat0))), 1.0 / 111_320
    rpc = RPC.from_coefficients(offsets=(n / 2, n / 2, lat0, lon0, 300.0),
                                scales=(n / 2, n / 2, half * m_lat, half * m_lon, 300.0),
                                samp_num=[0.0, 1.0, 0.03, 300 * 0.25 / half, 0.001, 0.0, 0.0, 0.002],
                                samp_den=[1.0, 0.001], line_num=[0.0, 0.03, -1.0, 300 * 0.05 / half],
                                line_den=[1.0, 0.0, 0.001])
    src = work / f"src_{n}.tif"
    if not src.exists():
        tmp = src.with_suffix(".part.tif")
        with rasterio.open(tmp, "w", driver="GTiff", width=n, height=n, count=1, dtype="uint8", tiled=True,
                           blockxsize=512, blockysize=512, compress="deflate", rpcs=rpc.to_rasterio()) as ds:
            for r0 in range(0, n, 512):
                h = min(512, n - r0)
                rr, cc = np.mgrid[r0:r0 + h, 0:n]
                img = 128 + 60 * np.sin(cc / 7.0) * np.cos(rr / 5.0) + 40 * np.sin((cc + rr) / 31.0)
                ds.write(img.astype(np.uint8)[None], window=Window(0, r0, n, h))
        tmp.rename(src)
    dem = work / f"dem_{n}.tif"
    if not dem.exists():
        m = 1000
        span = 1.2 * half
        res_lon, res_lat = 2 * span * m_lon / m, 2 * span * m_lat / m
        yy, xx = np.mgrid[0:m, 0:m]
        z = 300 + 150 * np.sin(xx / 60.0) * np.cos(yy / 45.0) + 0.1 * xx
        with rasterio.open(dem, "w", driver="GTiff", width=m, height=m, count=1, dtype="float32", crs="EPSG:4326",
                           transform=Affine(res_lon, 0, lon0 - span * m_lon, 0, -res_lat, lat0 + span * m_lat),
                           tiled=True) as ds:
            ds.write(z.astype("float32"), 1)
    # output grid: the footprint at the DEM's heights, 1 m, aligned
    sys.path.insert(0, str(ROOT))
    from rectify.geometry.sensors import RPCModel
    from rectify.raster.dem import Dem
    from rectify.raster.ortho import ortho_grid

    grid = ortho_grid(RPCModel(rpc, n, n), Dem.from_path(dem), dst_crs=CRS, resolution=gsd)
    return {"src": str(src), "dem": str(dem), "width": grid.width, "height": grid.height,
            "transform": list(tuple(grid.transform)[:6]), "crs": CRS}


# peak RSS of this process image: VmHWM (ru_maxrss would carry the parent's peak across fork + exec on Linux)
PEAK = r"""
def peak_rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")
"""

CHILD_OURS = r"""
import json, os, sys, time
t0 = time.perf_counter()
{peak}
os.environ.setdefault("GDAL_CACHEMAX", "64")
sys.path.insert(0, {root!r})
from affine import Affine
from rectify.raster.dem import Dem
from rectify.raster.georef import Grid
from rectify.raster.ortho import OrthoOptions, RPCModel, orthorectify
from rectify.formats.rpc import rpc_from_raster
import rasterio
cfg = json.loads({cfg!r})
rpc = rpc_from_raster(cfg["src"])
with rasterio.open(cfg["src"]) as ds:
    w, h = ds.width, ds.height
grid = Grid(cfg["width"], cfg["height"], Affine(*cfg["transform"]), cfg["crs"])
orthorectify(cfg["src"], cfg["out"], RPCModel(rpc, w, h), Dem.from_path(cfg["dem"]), grid=grid,
             options=OrthoOptions(threads=2), overwrite=True)
print(json.dumps({{"seconds": time.perf_counter() - t0, "rss_mb": peak_rss_mb()}}))
"""

CHILD_GDAL = r"""
import json, os, sys, time
t0 = time.perf_counter()
{peak}
import rasterio
from affine import Affine
from rasterio.enums import Resampling
from rasterio.warp import reproject
cfg = json.loads({cfg!r})
prof = dict(driver="GTiff", width=cfg["width"], height=cfg["height"], count=1, dtype="uint8", crs=cfg["crs"],
            transform=Affine(*cfg["transform"]), nodata=0, tiled=True, blockxsize=512, blockysize=512,
            compress="zstd", predictor=2, ZSTD_LEVEL=1, BIGTIFF="IF_SAFER")
with rasterio.Env(GDAL_CACHEMAX=64 * 1024 * 1024, GDAL_NUM_THREADS=2):
    with rasterio.open(cfg["src"]) as src, rasterio.open(cfg["out"], "w", **prof) as dst:
        reproject(rasterio.band(src, 1), rasterio.band(dst, 1), rpcs=src.rpcs, src_crs="EPSG:4326",
                  dst_transform=dst.transform, dst_crs=dst.crs, dst_nodata=0, resampling=Resampling.bilinear,
                  num_threads=2, warp_mem_limit=64, RPC_DEM=cfg["dem"])
print(json.dumps({{"seconds": time.perf_counter() - t0, "rss_mb": peak_rss_mb()}}))
"""


def run_child(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"child failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def compare(a: str, b: str, n_windows: int = 16) -> dict:
    """|difference| of the two outputs over sample windows where both are valid."""
    import rasterio
    from rasterio.windows import Window

    diffs = []
    with rasterio.open(a) as A, rasterio.open(b) as B:
        rng = np.random.default_rng(0)
        for _ in range(n_windows):
            c = int(rng.integers(0, max(1, A.width - 256)))
            r = int(rng.integers(0, max(1, A.height - 256)))
            w = Window(c, r, min(256, A.width), min(256, A.height))
            x, y = A.read(1, window=w).astype(float), B.read(1, window=w).astype(float)
            ok = (x > 0) & (y > 0)
            diffs.append(np.abs(x - y)[ok])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    return {"mean": float(d.mean()) if d.size else float("nan"), "p99": float(np.percentile(d, 99)) if d.size
            else float("nan"), "n": int(d.size)}


# --------------------------------------------------------------------------- frame mode: orthority
OUR_OPTIONS = {  # label -> (compress, cog)
    "zstd (default)": ("zstd", False),
    "deflate": ("deflate", False),
    "zstd --cog": ("zstd", True),
    "jpeg --cog": ("jpeg", True),
    "jpeg": ("jpeg", False),
}


def _ours(frames: Path, image: Path, out: Path, res: float, compress: str = "zstd", cog: bool = False,
          true_ortho: bool = False) -> np.ndarray:
    """(wall s, CPU s of the process: every thread)."""
    sys.path.insert(0, str(ROOT))
    from rectify.actions.ortho import OrthoOptions, ortho_from_files

    t0, c0 = time.perf_counter(), time.process_time()
    ortho_from_files(image, out, frames / "dem.tif", camera=frames / "orthority_int_param.yaml",
                     exterior=frames / "orthority_ext_param.geojson", resolution=res, overwrite=True,
                     options=OrthoOptions(threads=2, compress=compress, cog=cog, true_ortho=true_ortho,
                                          resampling="bilinear"), stac=False)
    return np.array([time.perf_counter() - t0, time.process_time() - c0])


def _orthority(frames: Path, image: Path, out: Path, res: float, compress: str | None = None) -> np.ndarray:
    """(wall s, CPU s of the process: every thread)."""
    import orthority as oty

    t0, c0 = time.perf_counter(), time.process_time()
    cams = oty.FrameCameras(frames / "orthority_int_param.yaml", frames / "orthority_ext_param.geojson")
    ortho = oty.Ortho(image, frames / "dem.tif", camera=cams.get(image), crs=cams.crs)
    ortho.process(out, resolution=(res, res), interp="bilinear", dem_interp="bilinear", compress=compress,
                  overwrite=True, aligned_pixels=True)
    return np.array([time.perf_counter() - t0, time.process_time() - c0])


def agreement(a: Path, b: Path) -> dict:
    """Shift (px, phase correlation of the common area) and mean |difference| (DN) of two orthophotos."""
    import cv2
    import rasterio
    from rasterio.windows import from_bounds

    with rasterio.open(a) as A, rasterio.open(b) as B:
        bounds = (max(A.bounds.left, B.bounds.left), max(A.bounds.bottom, B.bounds.bottom),
                  min(A.bounds.right, B.bounds.right), min(A.bounds.top, B.bounds.top))
        wa = from_bounds(*bounds, transform=A.transform).round_offsets().round_lengths()
        wb = from_bounds(*bounds, transform=B.transform).round_offsets().round_lengths()
        h, w = min(wa.height, wb.height), min(wa.width, wb.width)
        wa, wb = wa.__class__(wa.col_off, wa.row_off, w, h), wb.__class__(wb.col_off, wb.row_off, w, h)
        x = A.read(window=wa).astype(np.float64).mean(axis=0)
        y = B.read(window=wb).astype(np.float64).mean(axis=0)
        ok = (A.dataset_mask(window=wa) > 0) & (B.dataset_mask(window=wb) > 0)
    # a box where both hold data (phase correlation needs no holes): the common area's bounding box, shrunk
    rr, cc = np.nonzero(ok)
    if not len(rr):
        return {"shift_px": float("nan"), "mean_abs_dn": float("nan"), "n": 0}
    r0, r1, c0, c1 = rr.min(), rr.max() + 1, cc.min(), cc.max() + 1
    while r1 - r0 > 32 and c1 - c0 > 32 and not ok[r0:r1, c0:c1].all():
        dr, dc = max(1, (r1 - r0) // 100), max(1, (c1 - c0) // 100)
        r0, r1, c0, c1 = r0 + dr, r1 - dr, c0 + dc, c1 - dc
    if not ok[r0:r1, c0:c1].all():
        return {"shift_px": float("nan"), "mean_abs_dn": float(np.abs(x - y)[ok].mean()), "n": int(ok.sum())}
    xs, ys = x[r0:r1, c0:c1], y[r0:r1, c0:c1]
    win = cv2.createHanningWindow(xs.shape[::-1], cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(xs, ys, win)
    (bx, by), _ = cv2.phaseCorrelate(xs, xs, win)  # the estimator's own bias on this crop (0.5 px on some sizes)
    dx, dy = dx - bx, dy - by
    return {"shift_px": float(np.hypot(dx, dy)), "dx": float(dx), "dy": float(dy),
            "mean_abs_dn": float(np.abs(x - y)[ok].mean()), "n": int(ok.sum())}


def bench_frames(frames: Path, work: Path, repeat: int, res: float) -> None:
    import os

    work.mkdir(parents=True, exist_ok=True)
    images = sorted(frames.glob("*_RGB.tif")) or sorted(p for p in frames.glob("*.tif") if p.name != "dem.tif")
    print(f"frames: {', '.join(p.name for p in images)}; DEM {frames / 'dem.tif'}; {res:g} m; "
          f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    t_ours: dict[str, np.ndarray] = {}
    t_peer: dict[str, np.ndarray] = {}
    sizes_ours: dict[str, int] = {}
    sizes_peer: dict[str, int] = {}
    peer_default = "orthority (default: jpeg + overviews)"

    def keep(d: dict, k: str, v: np.ndarray) -> None:  # the fastest wall time and the least CPU, separately
        d[k] = np.minimum(d[k], v) if k in d else v

    def run_all(fn) -> np.ndarray:
        return np.sum([fn(img) for img in images], axis=0)

    def ours_file(label: str, cog: bool, img: Path) -> Path:
        return work / f"ours_{label.split()[0]}{'_cog' if cog else ''}_{img.stem}.tif"

    # warm both (imports, caches), then alternate ours / orthority, every option of ours in the same rounds
    run_all(lambda img: _ours(frames, img, ours_file("zstd", False, img), res))
    run_all(lambda img: _orthority(frames, img, work / f"oty_{img.stem}.tif", res))
    for i in range(repeat):
        sides = ["ours", "peer", "peer_deflate", "true"] + [f"opt:{k}" for k in OUR_OPTIONS]
        for side in sides if i % 2 == 0 else sides[::-1]:
            if side == "ours" or side == "opt:zstd (default)":
                keep(t_ours, "zstd (default)", run_all(lambda img: _ours(frames, img, ours_file("zstd", False, img),
                                                                         res)))
            elif side == "peer":
                keep(t_peer, peer_default,
                     run_all(lambda img: _orthority(frames, img, work / f"oty_{img.stem}.tif", res)))
            elif side == "peer_deflate":
                keep(t_peer, "orthority --compress deflate",
                     run_all(lambda img: _orthority(frames, img, work / f"oty_deflate_{img.stem}.tif", res,
                                                    "deflate")))
            elif side == "true":
                keep(t_ours, "--true-ortho (zstd)", run_all(lambda img: _ours(
                    frames, img, work / f"ours_true_{img.stem}.tif", res, true_ortho=True)))
            else:
                label = side[4:]
                comp, cog = OUR_OPTIONS[label]
                keep(t_ours, label, run_all(lambda img, c=comp, g=cog, lb=label: _ours(
                    frames, img, ours_file(lb, g, img), res, c, g)))
    for label, (_, cog) in OUR_OPTIONS.items():
        sizes_ours[label] = sum(ours_file(label, cog, img).stat().st_size for img in images)
    sizes_peer[peer_default] = sum((work / f"oty_{img.stem}.tif").stat().st_size for img in images)
    sizes_peer["orthority --compress deflate"] = sum((work / f"oty_deflate_{img.stem}.tif").stat().st_size
                                                     for img in images)
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    peer = t_peer[peer_default]
    print(f"\n| {len(images)} frames, best of {repeat} (alternating) | wall s | / orthority | CPU s | / orthority "
          f"| bytes | / orthority |")
    print("|---|---|---|---|---|---|---|")
    for k, v in t_peer.items():
        print(f"| {k} | {v[0]:.3f} | {v[0] / peer[0]:.2f} | {v[1]:.3f} | {v[1] / peer[1]:.2f} | {sizes_peer[k]} | "
              f"{sizes_peer[k] / sizes_peer[peer_default]:.2f} |")
    for k, v in t_ours.items():
        size = sizes_ours.get(k)
        sz = f"{size} | {size / sizes_peer[peer_default]:.2f}" if size is not None else " | "
        print(f"| rectify ortho {k} | {v[0]:.3f} | {v[0] / peer[0]:.2f} | {v[1]:.3f} | {v[1] / peer[1]:.2f} | {sz} |")
    print(f"load average after: {load}")
    ours = t_ours["zstd (default)"]
    print(f"time ratio ours (zstd) / orthority: wall {ours[0] / peer[0]:.3f}, CPU {ours[1] / peer[1]:.3f} "
          f"(target <= 0.7); jpeg --cog (orthority's kind of output) / orthority: wall "
          f"{t_ours['jpeg --cog'][0] / peer[0]:.3f}, CPU {t_ours['jpeg --cog'][1] / peer[1]:.3f}")
    tr = t_ours["--true-ortho (zstd)"]
    print(f"--true-ortho / plain: wall {tr[0] / ours[0]:.2f}, CPU {tr[1] / ours[1]:.2f} (target <= 3)")
    for img in images:
        for label, fname in (("zstd", ours_file("zstd", False, img)), ("jpeg --cog", ours_file("jpeg", True, img))):
            c = agreement(fname, work / f"oty_deflate_{img.stem}.tif")
            print(f"{img.stem}: ours ({label}) vs orthority (deflate): shift {c['shift_px']:.4f} px "
                  f"(dx {c.get('dx', float('nan')):+.4f}, dy {c.get('dy', float('nan')):+.4f}), mean |diff| "
                  f"{c['mean_abs_dn']:.3f} DN over {c['n']} px")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=20000, help="source (and about the output) side in pixels")
    ap.add_argument("--workdir", type=Path, default=Path("bench_ortho_work"))
    ap.add_argument("--skip-gdal", action="store_true")
    ap.add_argument("--frames", type=Path, default=None,
                    help="folder of frames with orthority_int_param.yaml, orthority_ext_param.geojson, dem.tif: "
                         "compare with orthority instead of GDAL")
    ap.add_argument("--repeat", type=int, default=5, help="frame mode: runs of each side (fastest counts)")
    ap.add_argument("--resolution", type=float, nargs="+", default=[5.6, 2.0],
                    help="frame mode: output pixel size(s), m; one table each (default 5.6, the frames' own GSD, "
                         "and 2: a 7.9x larger output, where the per-run fixed costs weigh less)")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    if args.frames is not None:
        for res in args.resolution:
            bench_frames(args.frames, args.workdir / f"res_{res:g}", args.repeat, res)
        return
    t0 = time.perf_counter()
    cfg = build(args.workdir, args.size)
    print(f"inputs: {args.size} x {args.size} uint8 RPC image, 1000 x 1000 DEM (EPSG:4326); output "
          f"{cfg['width']} x {cfg['height']} px at 1 m, EPSG:32632 (built in {time.perf_counter() - t0:.1f} s)")
    rows = {}
    cfg_o = dict(cfg, out=str(args.workdir / "ours.tif"))
    rows["rectify ortho (RPC + DEM)"] = run_child(CHILD_OURS.format(root=str(ROOT), cfg=json.dumps(cfg_o), peak=PEAK))
    print(f"ours: {rows['rectify ortho (RPC + DEM)']}", flush=True)
    if not args.skip_gdal:
        cfg_g = dict(cfg, out=str(args.workdir / "gdal.tif"))
        rows["GDAL reproject, rpcs + RPC_DEM"] = run_child(CHILD_GDAL.format(cfg=json.dumps(cfg_g), peak=PEAK))
        print(f"GDAL: {rows['GDAL reproject, rpcs + RPC_DEM']}", flush=True)
    print(f"\n| {cfg['width']} x {cfg['height']} output, bilinear, 2 threads | wall s | peak RSS MB |")
    print("|---|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {v['seconds']:.2f} | {v['rss_mb']:.0f} |")
    if not args.skip_gdal:
        o, g = rows["rectify ortho (RPC + DEM)"], rows["GDAL reproject, rpcs + RPC_DEM"]
        print(f"time ratio ours/GDAL = {o['seconds'] / g['seconds']:.3f} (target <= 1)")
        print(f"RSS ratio ours/GDAL = {o['rss_mb'] / g['rss_mb']:.3f}")
        c = compare(cfg_o["out"], cfg_g["out"])
        print(f"outputs ours vs GDAL: |diff| mean {c['mean']:.3f} DN, p99 {c['p99']:.1f} DN over {c['n']} pixels")


if __name__ == "__main__":
    main()
