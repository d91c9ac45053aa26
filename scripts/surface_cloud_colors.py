"""The colours of ``stereo surface``'s point cloud against the rendered texture (issue 27).

    python3 scripts/surface_cloud_colors.py [--strips 3] [--per-strip 4] [--seed 5] [OUTDIR]

A rendered block with known surface and texture (``tests/support/block_surface.py``, in EPSG:32633) runs
through ``stereo surface`` twice: with the orthomosaic (each point's RGB its nearest mosaic pixel) and with
``--no-ortho`` (each point projected into the left image of its pair, bilinear). Printed per run: points,
points without a colour, and the grey value (red / 257) against the truth ``20 + 215 t`` of the texture at
the point's x, y (median |d|, RMS, mean, 90th percentile, grey levels); for the mosaic run whether every
colour is the mosaic pixel x 257; for the image run its difference from the mosaic run's colours; then
``write_cloud`` alone (LAZ and COPC, without colours, from the mosaic, from the images; three runs each:
seconds and bytes). docs/surface.md quotes its figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import rasterio

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereo.actions.surface import SurfaceOptions, run_surface  # noqa: E402
from stereo.actions.surface_outputs import PairView, write_cloud  # noqa: E402
from stereo.formats.block import read_block_orientation  # noqa: E402
from stereo.formats.cloud import copc_available  # noqa: E402
from tests.support.block_surface import make_surface_block  # noqa: E402

CRS = "EPSG:32633"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=None)
    ap.add_argument("--strips", type=int, default=3)
    ap.add_argument("--per-strip", type=int, default=4)
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    root = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="surface-colors-"))
    blk = make_surface_block(root / "orient", strips=a.strips, per_strip=a.per_strip, seed=a.seed,
                             images=root / "images", supersample=1)
    doc = json.loads((root / "orient" / "orientation.json").read_text())
    doc["crs"] = CRS
    (root / "orient" / "orientation.json").write_text(json.dumps(doc))
    grey: dict[str, np.ndarray] = {}
    for name, ortho in (("mosaic", True), ("images", False)):
        t0 = time.perf_counter()
        res = run_surface(root / "orient", root / name,
                          options=SurfaceOptions(images=str(root / "images"), ground_z=50.0, ortho=ortho))
        las = laspy.read(root / name / "points.laz")
        x, y = np.asarray(las.x), np.asarray(las.y)
        grey[name] = np.asarray(las.red).astype(np.float64) / 257
        truth = 20 + 215 * blk.terrain._sample(blk.terrain.texture, np.column_stack([x, y]))
        d = grey[name] - truth
        colors = json.loads((root / name / "pairs.json").read_text())["cloud"]["colors"]
        secs = time.perf_counter() - t0
        print(f"{name}: {res.cloud_points} points, {colors['uncolored']} without a colour, run {secs:.1f} s")
        print(f"  against the texture: median |d| {np.median(np.abs(d)):.2f}, RMS {np.sqrt(np.mean(d ** 2)):.2f}, "
              f"mean {d.mean():+.2f}, p90 {np.percentile(np.abs(d), 90):.2f} grey levels "
              f"(texture std {truth.std():.1f})")
        if name == "mosaic":
            with rasterio.open(root / name / "ortho.tif") as ds:
                m, tr = ds.read(1), ds.transform
            c, r = ~tr * (x, y)
            pix = m[np.floor(r).astype(int), np.floor(c).astype(int)].astype(np.int64) * 257
            print(f"  every colour the mosaic pixel x 257: {np.array_equal(pix, np.asarray(las.red).astype(np.int64))}")
        else:
            dm = grey["images"] - grey["mosaic"]
            print(f"  against the mosaic run's colours: median |d| {np.median(np.abs(dm)):.2f}, "
                  f"RMS {np.sqrt(np.mean(dm ** 2)):.2f}")
    doc = json.loads((root / "images" / "pairs.json").read_text())
    bo = read_block_orientation(root / "orient" / "orientation.json")
    poses = {p.image: p for p in bo.poses}
    cam = next(iter(bo.cameras.values()))
    views = [PairView(Path(p["left_file"]), cam, poses[p["left"]]) for p in doc["pairs"]]
    dsm = root / "mosaic" / "dsm.tif"
    for fmt in ("laz", "copc") if copc_available() else ("laz",):
        for name, mosaic, vs in (("none", None, None), ("mosaic", root / "mosaic" / "ortho.tif", None),
                                 ("images", None, views)):
            ts = []
            dst = root / f"write_cloud_{name}.{fmt}"
            for _ in range(3):
                dst.unlink(missing_ok=True)
                t0 = time.perf_counter()
                write_cloud(dsm, dst, fmt, CRS, mosaic=mosaic, views=vs)
                ts.append(time.perf_counter() - t0)
            print(f"write_cloud {fmt}, colours {name}: {dst.stat().st_size} bytes, "
                  + ", ".join(f"{t:.3f}" for t in ts) + " s")
    print(f"files in {root}")


if __name__ == "__main__":
    main()
