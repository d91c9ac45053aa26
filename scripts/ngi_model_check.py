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
from pathlib import Path

import numpy as np
import rasterio
from scipy import ndimage

from rectify.geometry.camera import Camera
from rectify.geometry.points import ControlTable
from rectify.geometry.residuals import rms
from rectify.geometry.rotation import matrix_from_angles
from stereo.actions.run import run
from stereo.pair.model import ModelOptions
from stereo.pair.resection import ExteriorOrientation

LO25 = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m"
EO = {"0182": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702),
      "0184": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--out", default="/tmp/ngi_model")
    ap.add_argument("--n-control", type=int, default=8)
    ap.add_argument("--frame", default="topocentric")
    a = ap.parse_args()
    d = Path(a.shared) / "ngi_strip05"
    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)
    eos = {k: ExteriorOrientation(position=v[:3], rotation=matrix_from_angles(*np.radians(v[3:])),
                                  focal_length_mm=120.0) for k, v in EO.items()}
    with rasterio.open(d / "dem.tif") as src:
        dem = src.read(1).astype(float)
        T = src.transform

    def dem_h(xy):
        col, row = ~T * (xy[:, 0], xy[:, 1])
        return ndimage.map_coordinates(dem, [np.asarray(row) - 0.5, np.asarray(col) - 0.5], order=1,
                                       mode="constant", cval=np.nan)

    # left = 0182: which image is left? 0184 lies west of 0182 and kappa ~ 180: image x points west
    left, right = "0182", "0184"
    rng = np.random.default_rng(0)
    pts = []
    while len(pts) < a.n_control:
        c = (eos[left].position[:2] + eos[right].position[:2]) / 2 + rng.uniform(-2500, 2500, 2) * [0.6, 1.0]
        g = np.array([c[0], c[1], dem_h(c[None])[0]])
        pl = cam.pixel_from_photo(eos[left].project(g[None]))[0]
        pr = cam.pixel_from_photo(eos[right].project(g[None]))[0]
        if np.isfinite(g[2]) and all(30 < p[0] < 610 and 30 < p[1] < 1122 for p in (pl, pr)):
            pts.append((g, pl, pr))
    ctrl = ControlTable(tuple(f"dem{i}" for i in range(len(pts))), np.array([p[1] for p in pts]),
                        np.array([p[2] for p in pts]), np.array([p[0] for p in pts]), crs=LO25)
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
