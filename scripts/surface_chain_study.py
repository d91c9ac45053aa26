"""The block -> DSM + orthomosaic + cloud chain of ``stereo surface`` on the NGI pair as a block of two.

    python3 scripts/surface_chain_study.py [OUTDIR]

The two NGI frames with their AT orientations (orthority's files, read by the project's readers) become a
block orientation of two; ``stereo surface --reference-dem dem.tif --keep-orthophotos`` runs on it; then
printed: the DSM against dem.tif (RMSE, NMAD, coverage, LE90 from pairs.json), the point cloud, and the
orthomosaic against the two single true orthophotos (phase correlation per 32 px patch taken wholly from
one image by the provenance raster: median and maximum shift, px). Needs ``../shared/data/ngi_strip05``
(or ``$RECTIFY_SHARED_DATA``). docs/surface.md quotes its figures.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import laspy
import numpy as np
import rasterio

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rectify.formats.orthority import read_ext_param, read_int_param  # noqa: E402
from stereo.block.types import Pose  # noqa: E402
from stereo.formats.block import block_orientation_text  # noqa: E402
from tests.support.shared_data import shared_data_dir  # noqa: E402


def mosaic_shifts(out: Path, patch: int = 32) -> list[float]:
    doc = json.loads((out / "pairs.json").read_text())
    names = doc["ortho"]["images"]
    with rasterio.open(out / "ortho.tif") as ds:
        mos = ds.read(1).astype(np.float64)
        mt = ds.transform
    with rasterio.open(out / "ortho.source.tif") as ds:
        src = ds.read(1)
    win = cv2.createHanningWindow((patch, patch), cv2.CV_64F)
    shifts = []
    for r0 in range(0, mos.shape[0] - patch, patch):
        for c0 in range(0, mos.shape[1] - patch, patch):
            s = src[r0:r0 + patch, c0:c0 + patch]
            k = int(s[0, 0])
            if k == 0 or not (s == k).all():
                continue
            a = mos[r0:r0 + patch, c0:c0 + patch]
            with rasterio.open(out / f"ortho_{Path(names[k - 1]).stem}.tif") as ds:
                cc, rr = ~ds.transform * (mt * (c0, r0))
                b = ds.read(1, window=((round(rr), round(rr) + patch), (round(cc), round(cc) + patch)),
                            boundless=True, fill_value=0).astype(np.float64)
            if (b == 0).any() or a.std() < 3:
                continue
            (dx, dy), _ = cv2.phaseCorrelate(a, b, win)
            shifts.append(math.hypot(dx, dy))
    return shifts


def main() -> None:
    ngi = shared_data_dir() / "ngi_strip05"
    if not (ngi / "dem.tif").is_file():
        sys.exit(f"no NGI data in {ngi}")
    work = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="surface-chain-"))
    cams = read_int_param(ngi / "orthority_int_param.yaml")
    ext = read_ext_param(ngi / "orthority_ext_param.geojson")
    poses = [Pose(name, e["camera"] or next(iter(cams)), np.asarray(e["position"]), np.asarray(e["rotation"]))
             for name, e in ext.items()]
    crs = next(iter(ext.values()))["crs"]
    (work / "o").mkdir(parents=True, exist_ok=True)
    (work / "o" / "orientation.json").write_text(block_orientation_text(cams, poses, crs=crs))
    with rasterio.open(ngi / "dem.tif") as ds:
        dem = ds.read(1)
    ground_z = float(np.median(dem[np.isfinite(dem) & (dem > -1000)]))
    out = work / "out"
    cmd = ["stereo", "surface", str(work / "o"), "-o", str(out), "--images", str(ngi), "--ground-z", f"{ground_z:.2f}",
           "--reference-dem", str(ngi / "dem.tif"), "--keep-orthophotos", "--overwrite"]
    print("$", " ".join(cmd))
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    print(f"wall time {time.perf_counter() - t0:.1f} s")
    doc = json.loads((out / "pairs.json").read_text())
    c = doc["comparison"]
    print(f"DSM vs dem.tif: RMSE {c['rmse']:.2f} m, NMAD {c['nmad']:.2f} m, median {c['median']:+.2f} m, "
          f"coverage {100 * c['coverage']:.1f}%, LE90 {c['le90']:.2f} m (observed {c['le90_observed']:.2f} m), "
          f"cell {doc['grid']['cell']:g} m")
    las = laspy.read(out / "points.laz")
    print(f"cloud: {len(las.points)} points, dims {list(las.point_format.extra_dimension_names)}, median sigma_z "
          f"{float(np.median(las.sigma_z)):.2f} m")
    sh = mosaic_shifts(out)
    if sh:
        print(f"orthomosaic vs single orthophotos: {len(sh)} patches of 32 px, shift median {np.median(sh):.4f} px, "
              f"max {max(sh):.4f} px")
    else:
        print("orthomosaic vs single orthophotos: no patch")


if __name__ == "__main__":
    main()
