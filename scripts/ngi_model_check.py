"""Real pair check: NGI strip 05 (0182/0184) -> stereo model -> heights against the DEM.

Control: DEM points projected into both photos with the aero-triangulated EO of the README
(``--n-control`` of them, default 8). Everything else (matching, relative orientation,
intersection, absolute orientation) runs on the real images; every matched point then becomes a
check: its height after absolute orientation is compared with the DEM at its XY.

    python scripts/ngi_model_check.py [--shared ../shared/data] [--out /tmp/ngi_model]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository's tests.support, run from anywhere

from rectify.geometry.residuals import rms  # noqa: E402
from stereo.actions.run import run  # noqa: E402
from stereo.pair.model import ModelOptions  # noqa: E402
from tests.support.ngi_pair import dem_control, dem_sampler, ngi_camera  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--out", default="/tmp/ngi_model")
    ap.add_argument("--n-control", type=int, default=8)
    ap.add_argument("--frame", default="topocentric")
    a = ap.parse_args()
    d = Path(a.shared) / "ngi_strip05"
    cam = ngi_camera()
    dem_h = dem_sampler(d)
    # left = 0182: which image is left? 0184 lies west of 0182 and kappa ~ 180: image x points west
    left, right = "0182", "0184"
    ctrl, pts = dem_control(d, a.n_control, left, right)
    out = Path(a.out)
    m = run(d / f"3324c_2015_1004_05_{left}_RGB.tif", d / f"3324c_2015_1004_05_{right}_RGB.tif", camera=cam,
            out_dir=out, control=ctrl, options=ModelOptions(frame=a.frame), overwrite=True,
            title="NGI strip 05 model").model
    tie = ~m.is_control & ~np.isin(np.array(m.ids), ctrl.ids)
    dz = m.ground[tie, 2] - dem_h(m.ground[tie, :2])
    ok = np.isfinite(dz)
    res = {"n_control": len(pts), "n_check_points": int(ok.sum()), "frame": a.frame,
           "dem_rmse_m": rms(dz[ok]), "dem_mean_m": float(np.mean(dz[ok])),
           "dem_median_abs_m": float(np.median(np.abs(dz[ok]))),
           "ground_pixel_m": 5.6, "rmse_in_ground_pixels": rms(dz[ok]) / 5.6,
           "absolute_sigma0": m.absolute.sigma0, "rmse_control_m": m.summary["rmse_control_m"],
           "frame_difference": m.frame_difference, "ro_sigma0_mm": m.summary["ro_sigma0_mm"],
           "n_matches": m.summary["n_matches"]}
    print(json.dumps(res, indent=2))
    ok_ = res["dem_rmse_m"] <= 1.5 * 5.6
    print(f"check heights vs DEM: RMSE {res['dem_rmse_m']:.2f} m over {res['n_check_points']} points "
          f"({res['rmse_in_ground_pixels']:.2f} ground pixels): {'PASS' if ok_ else 'FAIL'} (target <= 1.5 px)")


if __name__ == "__main__":
    main()
