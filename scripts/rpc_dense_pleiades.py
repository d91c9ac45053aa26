"""Issue 14, RPC pairs: the dense chain on the Pleiades crops of ../shared/data/pleiades_triplet.

Runs :func:`stereo.actions.dense_rpc.run_dense_rpc` on a pair of the triplet (default images 2
and 1, the first two of config.json) over the config's region of interest and prints the vertical
parallax of the tie points after local epipolar resampling (RMS, worst tile, and before the
pointing correction), the DSM's coverage of the ROI and the share of the ROI cells whose height
lies in the issue's band (2270-2380 m) and in the band of the scene's sparse tie points (their
RPC intersections, 1st-99th percentile widened by 20 m).

Usage:
    nice python scripts/rpc_dense_pleiades.py [--pair 2,1] [--tile 300] [--out /tmp/rpc_pleiades]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "pleiades_triplet"
ISSUE_BAND_M = (2270.0, 2380.0)


def main(argv: list[str] | None = None) -> int:
    from rectify.formats.rpc import rpc_from_raster
    from stereo.actions.dense_rpc import RpcDenseOptions, roi_statistics, run_dense_rpc, triangulate_rpc

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--pair", default="2,1", help="left,right image numbers (1..3)")
    ap.add_argument("--tile", type=int, default=300)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    if not (a.data / "config.json").is_file():
        print(f"no Pleiades triplet at {a.data}", file=sys.stderr)
        return 1
    cfg = json.loads((a.data / "config.json").read_text())
    roi = tuple(int(cfg["roi"][k]) for k in ("x", "y", "w", "h"))
    i, j = (int(v) for v in a.pair.split(","))
    left, right = a.data / f"img_0{i}.tif", a.data / f"img_0{j}.tif"
    out = a.out or Path(tempfile.mkdtemp(prefix="rpc_pleiades_"))
    res = run_dense_rpc(left, right, out / "dense", roi=roi, overwrite=True,
                        options=RpcDenseOptions(tile=a.tile, cloud_format="las"))
    for line in res.summary_lines():
        print(line)
    # the sparse band: tie points of the run's tiles, intersected by the RPCs
    rl, rr = rpc_from_raster(left), rpc_from_raster(right)
    doc = json.loads((out / "dense" / "dense_rpc.json").read_text())
    from rectify.features import MatcherConfig, match_images

    m = match_images(left, right, config=MatcherConfig(verify="fundamental", keep_unrefined=False)).matches
    g, r = triangulate_rpc(rl, rr, m.left, m.right)
    ok = r < 1.5
    lo, hi = np.percentile(g[ok, 2], [1, 99])
    band = (float(lo) - 20.0, float(hi) + 20.0)
    s_issue = roi_statistics(res.dsm, rl, roi, res.crs, ISSUE_BAND_M)
    s_band = roi_statistics(res.dsm, rl, roi, res.crs, band)
    print(f"pair img_0{i} / img_0{j}, ROI {roi}, {len(doc['tiles'])} tiles")
    print(f"vertical parallax after local epipolar resampling: RMS {res.parallax_rms_px:.3f} px, worst tile "
          f"{res.parallax_max_tile_rms_px:.3f} px; RPCs alone {res.parallax_before_rms_px:.3f} px")
    print(f"ROI coverage: {100 * s_band['coverage']:.1f}% of {int(s_band['n_cells'])} cells; heights p01 "
          f"{s_band['p01_m']:.1f}, median {s_band['median_m']:.1f}, p99 {s_band['p99_m']:.1f} m")
    print(f"sparse tie points ({int(ok.sum())}): heights {lo:.1f} .. {hi:.1f} m (1st-99th percentile)")
    print(f"share of ROI cells in {ISSUE_BAND_M[0]:.0f}-{ISSUE_BAND_M[1]:.0f} m (the issue's band): "
          f"{100 * s_issue['in_range']:.1f}%")
    print(f"share of ROI cells in {band[0]:.0f}-{band[1]:.0f} m (tie-point band +- 20 m): "
          f"{100 * s_band['in_range']:.1f}%")
    print(f"outputs in {out / 'dense'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
