"""Satellite benchmark (issue 28): the Marseille Pleiades triplet, ours before and after the RPC adjustment,
against CNES CARS run in the same script on the same crops.

Data: ``../shared/data/pleiades_triplet`` (s2p's test crops: ``img_01..03.tif`` with RPC tags and
``config.json``: the reference image ``img_02`` first, its region of interest 700 x 700 px at (150, 150)).
The shared data hold no s2p DSM, so the peer is run here.

Ours: ``stereo dense-rpc img_02 img_01 img_03 --roi 150,150,700,700`` (:func:`run_dense_rpc_multi`) twice:
``--no-adjust`` and with the RPC adjustment (shift biases, no GCPs). Printed: each pair's median height over
the ROI and the median / NMAD of pair (02, 01) minus pair (02, 03) over their common cells (the pairs'
agreement; target within 0.3 m after the adjustment), the adjustment's sigma0, biases and refit error, the
fused DSM's ROI coverage with its default hole filling (``--fill-holes``, as ``stereo dense-rpc``) and
without the filled cells (target >= 95 %), its 1st-99th percentile heights (s2p's own triplet DSM: 85-260 m,
``../shared/data/README.md``), the roughness (NMAD of the second differences of the heights along rows and
columns, cells with all three heights; also without the filled cells) and the time.

Peer: CARS (PyPI ``cars``; the ``bench`` extra of ``pyproject.toml``) in its own environment (its pins of
numpy, rasterio and others differ from ours): ``--cars PATH`` names its ``cars`` command (default: ``cars``
on the PATH). Configured by ``cars-starter``'s defaults for the three sensors (geometric models from the RPC
tags, no initial DEM), the pairs (02, 01) and (02, 03) as ours, 0.5 m resolution, heights above the
ellipsoid as ours (``"geoid": false``; CARS' default is EGM96 heights, about 49 m lower here), the sequential
orchestrator (one process: the machine has 2 cores). Its DSM (``OUT/cars/out/dsm/dsm.tif``) is compared on
its own grid for the roughness and the ROI coverage (cells whose centre, at its height, projects into the ROI
of ``img_02``; CARS interpolates some cells when it rasterises, flagged 3 in its ``filling.tif``: its coverage
is given with and without them), and resampled bilinearly onto our grid for ours minus CARS (median, NMAD).

Usage:
    nice python scripts/bench_satellite.py [--out /tmp/bench_satellite] [--cars /path/to/venv/bin/cars]
                                           [--no-peer] [--reuse-peer] [--fill-holes N]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rectify.formats.rpc import rpc_from_raster  # noqa: E402  (after the sys.path set-up)
from rectify.geometry.crs import transform_xy  # noqa: E402
from rectify.raster.io import reproject_band  # noqa: E402
from stereo.actions.dense_rpc import RpcDenseOptions  # noqa: E402
from stereo.actions.dense_rpc_multi import FUSED_FILL_CELLS, MultiRpcOptions, run_dense_rpc_multi  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "pleiades_triplet"
S2P_BAND_M = (85.0, 260.0)


def roughness(z: np.ndarray) -> float:
    """NMAD of the second differences of a height grid along rows and columns (NaN = no height), metres."""
    d = np.concatenate([(z[:, :-2] - 2 * z[:, 1:-1] + z[:, 2:]).ravel(), (z[:-2] - 2 * z[1:-1] + z[2:]).ravel()])
    d = d[np.isfinite(d)]
    return float(1.4826 * np.median(np.abs(d - np.median(d)))) if len(d) else float("nan")


def roi_mask(z: np.ndarray, transform, crs: str, rpc, roi) -> np.ndarray:
    """Cells whose centre, at its height (the median where none), projects into the ROI of the RPC's image."""
    H, W = z.shape
    rr, cc = np.mgrid[0:H, 0:W]
    x = transform.c + (cc.ravel() + 0.5) * transform.a
    y = transform.f + (rr.ravel() + 0.5) * transform.e
    zz = z.ravel()
    med = float(np.nanmedian(zz))
    ll = transform_xy(crs, "EPSG:4326", np.column_stack([x, y]))
    p = rpc.project(np.column_stack([ll, np.where(np.isfinite(zz), zz, med)]))
    x0, y0, w, h = roi
    inside = (p[:, 0] >= x0 - 0.5) & (p[:, 0] < x0 + w - 0.5) & (p[:, 1] >= y0 - 0.5) & (p[:, 1] < y0 + h - 0.5)
    return inside.reshape(H, W)


def read_dsm(path: Path) -> tuple[np.ndarray, Any, str]:
    """Band 1 of a DSM as float64 with NaN for nodata, its transform and CRS."""
    import rasterio  # local: the bench reads a peer's file; the packages read rasters through rectify.raster

    with rasterio.open(path) as ds:
        z = ds.read(1).astype(np.float64)
        nd = ds.nodata
        if nd is not None:
            z[z == nd] = np.nan
        z[~np.isfinite(z)] = np.nan
        return z, ds.transform, ds.crs.to_string()


def ours(images, out: Path, roi, adjust: bool, fill_holes: int = FUSED_FILL_CELLS) -> dict:
    t = time.perf_counter()
    r = run_dense_rpc_multi(images, out, roi=roi, overwrite=True,
                            options=MultiRpcOptions(adjust=adjust, fill_holes=fill_holes, pair=RpcDenseOptions(
                                cloud_format="none", stac=False)))
    sec = time.perf_counter() - t
    z = np.where(r.dsm.valid, r.dsm.height.astype(np.float64), np.nan)
    mask = roi_mask(z, r.dsm.transform, r.crs, rpc_from_raster(images[0]), roi)
    zr = np.where(mask, z, np.nan)
    pairs = []
    for k, pr in enumerate(r.pair_results):
        pz = np.where(pr.dsm.valid, pr.dsm.height.astype(np.float64), np.nan)
        pairs.append({"pair": f"{r.names[0]} + {r.names[r.pairs[k].right]}", "median_m": pr.roi_stats["median_m"],
                      "coverage": pr.roi_stats["coverage"], "roughness_m": roughness(pz)})
    a = r.adjustment
    return {"result": r, "seconds": sec, "pairs": pairs, "agreement": r.agreement, "coverage": r.roi_stats["coverage"],
            "coverage_measured": r.measured_coverage, "roughness_measured_m": roughness(np.where(mask & ~r.dsm.filled,
                                                                                                zr, np.nan)),
            "p01": r.roi_stats["p01_m"], "p99": r.roi_stats["p99_m"], "roughness_m": roughness(zr),
            "sigma0": None if a is None else a.sigma0, "refit_max_px": r.refit_max_px,
            "biases": None if a is None else a.params[:, :, 0].tolist(), "adjust_seconds": r.adjust_seconds}


def run_cars(cars: str, images, out: Path) -> float:
    """Write the CARS configuration and run it; returns the seconds."""
    out.mkdir(parents=True, exist_ok=True)
    conf = {"input": {"sensors": {str(k): {"image": str(p)} for k, p in enumerate(images)},
                      "pairing": [["0", "1"], ["0", "2"]]},
            "output": {"directory": str(out / "out"), "resolution": 0.5, "geoid": False},
            "orchestrator": {"mode": "sequential"}}
    (out / "config.json").write_text(json.dumps(conf, indent=2))
    t = time.perf_counter()
    with open(out / "cars.log", "w") as log:
        subprocess.run([cars, str(out / "config.json")], check=True, stdout=log, stderr=subprocess.STDOUT)
    return time.perf_counter() - t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_satellite"))
    ap.add_argument("--cars", default="cars", help="the CARS command (its own environment)")
    ap.add_argument("--no-peer", action="store_true", help="skip CARS")
    ap.add_argument("--reuse-peer", action="store_true", help="use the CARS DSM of an earlier run in OUT/cars")
    ap.add_argument("--fill-holes", type=int, default=FUSED_FILL_CELLS,
                    help="ours: interpolate the fused DSM's holes of at most N cells (0: off; default as "
                         "stereo dense-rpc)")
    a = ap.parse_args(argv)
    if not (a.data / "config.json").is_file():
        print(f"no Pleiades triplet at {a.data}", file=sys.stderr)
        return 1
    cfg = json.loads((a.data / "config.json").read_text())
    roi = tuple(int(cfg["roi"][k]) for k in ("x", "y", "w", "h"))
    images = [a.data / im["img"] for im in cfg["images"]]  # img_02 (the reference), img_01, img_03
    print(f"Marseille Pleiades triplet, reference {images[0].name}, ROI {roi}"
          + f"; ours with --fill-holes {a.fill_holes}")
    res = {}
    for name, adjust in (("before", False), ("after", True)):
        res[name] = o = ours(images, a.out / f"ours_{name}", roi, adjust, a.fill_holes)
        print(f"\nours, {'with' if adjust else 'without'} the RPC adjustment ({o['seconds']:.0f} s"
              + (f", of which the adjustment {o['adjust_seconds']:.0f} s" if adjust else "") + "):")
        if adjust:
            print(f"  adjustment: sigma0 {o['sigma0']:.3f}, biases (col, row) px "
                  + "; ".join(f"({b[0]:+.3f}, {b[1]:+.3f})" for b in o["biases"])
                  + f"; refit error max {o['refit_max_px']:.1e} px")
        for p in o["pairs"]:
            print(f"  pair {p['pair']}: median {p['median_m']:.2f} m, ROI coverage {100 * p['coverage']:.1f} %, "
                  f"roughness {p['roughness_m']:.3f} m")
        for i, j, med, nmad, n in o["agreement"]:
            print(f"  pair {i} - pair {j}: median {med:+.3f} m, NMAD {nmad:.3f} m ({n} cells)"
                  + (f" -> target |median| <= 0.3 m: {'met' if abs(med) <= 0.3 else 'NOT met'}" if adjust else ""))
        print(f"  fused: ROI coverage {100 * o['coverage']:.2f} % ({100 * o['coverage_measured']:.2f} % without "
              f"the filled cells; target >= 95 %: "
              f"{'met' if o['coverage'] >= 0.95 else 'NOT met'}), heights 1-99 % {o['p01']:.1f}-{o['p99']:.1f} m "
              f"(s2p {S2P_BAND_M[0]:.0f}-{S2P_BAND_M[1]:.0f} m), roughness {o['roughness_m']:.3f} m "
              f"({o['roughness_measured_m']:.3f} m without the filled cells)")
    if a.no_peer:
        return 0
    peer_dir = a.out / "cars"
    dsm = peer_dir / "out" / "dsm" / "dsm.tif"
    peer_sec = float("nan")
    if not a.reuse_peer:
        if shutil.which(a.cars) is None and not Path(a.cars).is_file():
            print(f"\nCARS not found ({a.cars!r}): install the bench extra in its own environment", file=sys.stderr)
            return 1
        peer_sec = run_cars(a.cars, images, peer_dir)
    if not dsm.is_file():
        print(f"\nno CARS DSM at {dsm}", file=sys.stderr)
        return 1
    zc, tc, crs_c = read_dsm(dsm)
    rpc0 = rpc_from_raster(images[0])
    mc = roi_mask(zc, tc, crs_c, rpc0, roi)
    cov_c = float(np.isfinite(zc[mc]).mean())
    fill = dsm.parent / "filling.tif"
    cov_matched = float("nan")
    if fill.is_file():
        fz, _t, _c = read_dsm(fill)
        cov_matched = float((np.isfinite(zc) & (fz == 1))[mc].mean())
    rough_c = roughness(np.where(mc, zc, np.nan))
    p01, p99 = np.nanpercentile(zc[mc], [1, 99])
    print(f"\nCARS ({'reused' if a.reuse_peer else f'{peer_sec:.0f} s'}; cell {tc.a:g} m): ROI coverage "
          f"{100 * cov_c:.2f} % ({100 * cov_matched:.2f} % not interpolated), heights 1-99 % {p01:.1f}-{p99:.1f} m, "
          f"roughness {rough_c:.3f} m")
    for name, o in res.items():
        r = o["result"]
        z = np.where(r.dsm.valid, r.dsm.height.astype(np.float64), np.nan)
        ref = reproject_band(dsm, z.shape, r.dsm.transform, r.crs, what="CARS DSM")
        m = roi_mask(z, r.dsm.transform, r.crs, rpc0, roi)
        d = (z - ref)[m]
        d = d[np.isfinite(d)]
        med = float(np.median(d))
        nmad = float(1.4826 * np.median(np.abs(d - med)))
        dm = (z - ref)[m & ~r.dsm.filled]
        dm = dm[np.isfinite(dm)]
        med_m = float(np.median(dm))
        nmad_m = float(1.4826 * np.median(np.abs(dm - med_m)))
        ratio = o["roughness_m"] / rough_c
        print(f"  ours {name} the adjustment minus CARS: median {med:+.3f} m, NMAD {nmad:.3f} m ({len(d)} cells; "
              f"without our filled cells {med_m:+.3f} m, {nmad_m:.3f} m, {len(dm)} cells); "
              f"roughness {ratio:.2f} x CARS' (target <= 1.2: {'met' if ratio <= 1.2 else 'NOT met'}); coverage "
              f"{100 * o['coverage']:.2f} % vs {100 * cov_c:.2f} % ({'met' if o['coverage'] >= cov_c else 'NOT met'}"
              f"; without filled cells {100 * o['coverage_measured']:.2f} % vs {100 * cov_matched:.2f} %);"
              f" time {o['seconds']:.0f} s vs {peer_sec:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
