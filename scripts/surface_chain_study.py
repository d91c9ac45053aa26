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
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import rasterio

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.support.shared_data import shared_data_dir  # noqa: E402
from tests.support.surface_checks import mosaic_shifts, write_orthority_orientation  # noqa: E402


def main() -> None:
    ngi = shared_data_dir() / "ngi_strip05"
    if not (ngi / "dem.tif").is_file():
        sys.exit(f"no NGI data in {ngi}")
    work = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="surface-chain-"))
    write_orthority_orientation(ngi, work / "o")
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
