"""Vertical parallax of the tie points after normal-case resampling on the real NGI pair (issue 14).

Runs on ``../shared/data/ngi_strip05`` (see its README):

1. ``stereo run LEFT RIGHT --camera cam.json --dense`` (the relative orientation of the run, then
   the dense chain with its default options: its own Tukey relative orientation on the refined
   tie points);
2. the same dense chain on the run's ``relative.json`` used as given (``relative_robust=None``);
3. ``stereo dense`` on the aero-triangulated exterior orientations of the README.

and prints, for each, the parallax line of the dense chain (mapped, the orientation's own
residual, re-measured by LSM in the resampled photos; points used, outliers, unrefined matches).

    python scripts/ngi_dense_parallax.py [--shared ../shared/data] [--work /tmp/ngi_dense_parallax]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository's tests.support, run from anywhere

from stereo.actions.dense import DenseOptions, run_dense  # noqa: E402
from stereo.actions.run import run  # noqa: E402
from tests.support.ngi_pair import ngi_camera, write_ngi_exteriors  # noqa: E402


def photos(d: Path) -> tuple[Path, Path]:
    return d / "3324c_2015_1004_05_0182_RGB.tif", d / "3324c_2015_1004_05_0184_RGB.tif"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--work", default="/tmp/ngi_dense_parallax")
    ap.add_argument("--no-exterior", action="store_true", help="Skip the run on the aero-triangulated EOs.")
    a = ap.parse_args()
    d = Path(a.shared) / "ngi_strip05"
    left, right = photos(d)
    work = Path(a.work)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    cam_path = work / "cam.json"
    cam_path.write_text(json.dumps(ngi_camera().to_dict()))

    res = run(left, right, camera=cam_path, out_dir=work / "run", dense=DenseOptions(), report=False)
    s = res.ro.summary()
    print(f"stereo run: {s['n_points']} matches, relative orientation ({s['system']}, {s['robust']}) "
          f"{s['n_used']} used, {s['n_outliers']} outliers, residual parallax {s['rms_parallax_px']:.3f} px")
    assert res.dense is not None
    print("1. stereo run --dense:", res.dense.parallax.summary_line())

    r2 = run_dense(work / "run" / "relative.json", left, right, work / "given", matches=work / "run" / "matches.csv",
                   options=DenseOptions(relative_robust=None, cloud_format="none"))
    print("2. the run's orientation as given:", r2.parallax.summary_line())

    if not a.no_exterior:
        paths = write_ngi_exteriors(work)
        r3 = run_dense(paths[0], left, right, work / "exterior", right_orientation=paths[1],
                       options=DenseOptions(cloud_format="none", reference_dem=str(d / "dem.tif")))
        print("3. aero-triangulated EOs:", r3.parallax.summary_line())
        if r3.comparison is not None:
            print("   " + r3.comparison.summary_line(cell=r3.dsm_cell))


if __name__ == "__main__":
    main()
