#!/usr/bin/env python
"""Seed 001's processing of space images, steps 1-6, on the embedded Landsat scene.

A simulated pair of vertical (rectified) satellite frames, f = 1000 mm, flying
height 700 km (scale about 1:700 000, so the 200 km scene fits the 300 x 300 mm frame of
the Resurs-F cameras of the seed),
looks at ground points taken on the Landsat grid (UTM 18N) with synthetic
ellipsoidal heights. pyproj does every datum and projection computation; the
seed's closed formulas are evaluated beside it.

1. UTM + heights -> geodetic (B, L, H) -> geocentric X, Y, Z (pyproj, and seed formula);
   then the local topocentric frame (ENU at the scene centre, seed 004 eq. 5), where the
   frames are horizontal.
2. Coordinates of the control points on the rectified images:
   x0 = f (X - XS) / (ZS - Z), y0 = f (Y - YS) / (ZS - Z)   (mm);
   and their pixels in the embedded GeoTIFF (rectify.raster.georef).
3. Coordinates of determined points from the image by the cotangent four-point
   method (rectify.geometry.transforms) fitted on four control points (a plane: the mean height).
4. Stereo intersection with the seed's factor N = (Bx + x2 Bz / f) / (x1 - x2):
   X = N x1, Y = N y1, Z = -N f (from the left projection centre).
5. X, Y, Z -> B, L, H by the seed's formulas (iterated tg B) and by pyproj.
6. B, L, H -> UTM (pyproj); compared with the starting coordinates.

Usage: python scripts/satellite_workflow.py
"""

from __future__ import annotations

import math

import numpy as np

from rectify.actions.demo import demo_raster_path
from rectify.geometry.geodesy import (
    blh_from_geocentric_formula,
    ecef_from_enu,
    ecef_from_geodetic,
    ellipsoid_of,
    enu_from_ecef,
    geocentric_from_blh_formula,
    geodetic_from_ecef,
    geodetic_from_map,
    map_from_geodetic,
)
from rectify.geometry.transforms import CotangentFourPoint
from rectify.raster.georef import pixel_from_world, world_from_pixel
from rectify.raster.io import raster_info

F_MM = 1000.0
FLYING_HEIGHT_M = 700_000.0
CRS = "EPSG:32618"


def rms(a) -> float:
    a = np.asarray(a, dtype=float)
    return float(np.sqrt(np.mean(a * a)))


def main() -> None:
    info = raster_info(demo_raster_path())
    rng = np.random.default_rng(1)
    # ground points on the Landsat grid with synthetic heights (m, ellipsoidal)
    pix = np.column_stack([rng.uniform(50, info.width - 50, 40), rng.uniform(50, info.height - 50, 40)])
    en = world_from_pixel(info.transform, pix)
    h = 200.0 + 300.0 * np.sin(en[:, 0] / 20000.0) * np.cos(en[:, 1] / 25000.0) + 50.0 * rng.random(40)
    xyh = np.column_stack([en, h])

    print("step 1: UTM 18N + heights -> geodetic -> geocentric")
    llh = geodetic_from_map(xyh, CRS)
    xyz = ecef_from_geodetic(llh, crs=CRS)
    ell = ellipsoid_of(CRS)
    blh = np.column_stack([np.radians(llh[:, 1]), np.radians(llh[:, 0]), llh[:, 2]])
    xyz_seed = geocentric_from_blh_formula(blh, ell)
    print(f"  seed formula (4) vs pyproj: max |dXYZ| = {np.abs(xyz_seed - xyz).max():.2e} m")
    centre_ll = geodetic_from_map([[en[:, 0].mean(), en[:, 1].mean(), 0.0]], CRS)[0]
    origin = (centre_ll[0], centre_ll[1], 0.0)
    enu = enu_from_ecef(xyz, origin, crs=CRS)
    print(f"  topocentric origin lon {origin[0]:.5f} deg, lat {origin[1]:.5f} deg; "
          f"points span {np.ptp(enu[:, 0]) / 1e3:.0f} x {np.ptp(enu[:, 1]) / 1e3:.0f} km, "
          f"Earth-curvature drop at the edge {-enu[:, 2].min() + h.max():.0f} m")

    print("step 2: control points on the rectified images (horizontal frames)")
    S1 = np.array([-10_000.0, 0.0, FLYING_HEIGHT_M])
    S2 = np.array([+10_000.0, 0.0, FLYING_HEIGHT_M + 150.0])  # Bx = 20 km, Bz = 150 m
    f_m = F_MM / 1000.0

    def image_mm(S):
        d = S[2] - enu[:, 2]
        return np.column_stack([f_m * (enu[:, 0] - S[0]) / d, f_m * (enu[:, 1] - S[1]) / d]) * 1000.0

    p1, p2 = image_mm(S1), image_mm(S2)
    print(f"  image 1: x0 in [{p1[:, 0].min():.1f}, {p1[:, 0].max():.1f}] mm, "
          f"y0 in [{p1[:, 1].min():.1f}, {p1[:, 1].max():.1f}] mm (300 x 300 mm frame)")
    back = pixel_from_world(info.transform, en)
    print(f"  pixels in the GeoTIFF (rectify.raster.georef round trip): max error {np.abs(back - pix).max():.1e} px")

    print("step 3: determined points from image 1 by the cotangent four-point method")
    ctrl = [int(np.argmin(p1[:, 0] + p1[:, 1])), int(np.argmax(p1[:, 0] - p1[:, 1])),
            int(np.argmax(p1[:, 0] + p1[:, 1])), int(np.argmin(p1[:, 0] - p1[:, 1]))]
    cot = CotangentFourPoint.from_points(p1[ctrl], enu[ctrl, :2])
    est = cot(p1)
    err = np.linalg.norm(est - enu[:, :2], axis=1)
    print(f"  plan error (relief displacement not modelled): RMSE {rms(err):.1f} m over {len(err)} points; "
          f"heights vary by {np.ptp(enu[:, 2]):.0f} m")

    print("step 4: stereo intersection, N = (Bx + x2 Bz / f) / (x1 - x2)")
    B = S2 - S1
    x1, y1, x2 = p1[:, 0] / 1000.0, p1[:, 1] / 1000.0, p2[:, 0] / 1000.0
    N = (B[0] + x2 * B[2] / f_m) / (x1 - x2)
    model = np.column_stack([N * x1, N * y1, -N * f_m]) + S1
    print(f"  intersected vs truth: RMSE dX {rms(model[:, 0] - enu[:, 0]):.2e} m, "
          f"dY {rms(model[:, 1] - enu[:, 1]):.2e} m, dZ {rms(model[:, 2] - enu[:, 2]):.2e} m")

    print("step 5: X, Y, Z -> B, L, H (seed formulas, iterated) and pyproj")
    xyz_i = ecef_from_enu(model, origin, crs=CRS)
    blh_seed = blh_from_geocentric_formula(xyz_i, ell)
    llh_p = geodetic_from_ecef(xyz_i, crs=CRS)
    dB = np.degrees(blh_seed[:, 0]) - llh_p[:, 1]
    dL = np.degrees(blh_seed[:, 1]) - llh_p[:, 0]
    print(f"  seed vs pyproj: max |dB| {np.abs(dB).max() * 3600:.1e} arcsec, max |dL| "
          f"{np.abs(dL).max() * 3600:.1e} arcsec, max |dH| {np.abs(blh_seed[:, 2] - llh_p[:, 2]).max():.1e} m")

    print("step 6: B, L, H -> UTM 18N (pyproj) vs the starting coordinates")
    back_map = map_from_geodetic(np.column_stack([np.degrees(blh_seed[:, 1]), np.degrees(blh_seed[:, 0]),
                                                  blh_seed[:, 2]]), CRS)
    d = back_map - xyh
    print(f"  RMSE dE {rms(d[:, 0]):.2e} m, dN {rms(d[:, 1]):.2e} m, dH {rms(d[:, 2]):.2e} m")
    ok = max(np.abs(d).max(), 0.0) < 1e-3
    print("workflow closes to < 1 mm" if ok else "workflow does NOT close")
    assert math.isfinite(rms(d))


if __name__ == "__main__":
    main()
