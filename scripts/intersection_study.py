"""Compare the intersection formulas under noise and near their singular configurations.

Tests seed 000's claim that its general N (projection on u = (1, 1, 1)) is more accurate for
aerial imagery than the classical aerial N (seed 001's general form, u = Y axis).

    python scripts/intersection_study.py
"""

from __future__ import annotations

import numpy as np

from rectify.geometry.rotation import matrix_from_angles
from stereo.pair.intersection import METHODS, intersect, project


def aerial(rng, n, sigma_mm):
    P = np.column_stack([rng.uniform(-1000, 3600, n), rng.uniform(-2000, 2000, n), rng.uniform(-5300, -4600, n)])
    R1, R2 = matrix_from_angles(0.01, -0.02, 0.03), matrix_from_angles(-0.02, 0.01, -0.01)
    B = np.array([2600.0, 30.0, -5.0])
    x1 = project(P, rotation=R1, centre=np.zeros(3), focal_length_mm=120.0) + rng.normal(0, sigma_mm, (n, 2))
    x2 = project(P, rotation=R2, centre=B, focal_length_mm=120.0) + rng.normal(0, sigma_mm, (n, 2))
    return P, x1, x2, R1, R2, B


def main() -> None:
    rng = np.random.default_rng(0)
    print("aerial pair (f 120 mm, B 2.6 km, H ~5 km), 200000 points; RMS error X, Y, Z (m)")
    for sigma in (0.002, 0.005, 0.02):
        P, x1, x2, R1, R2, B = aerial(rng, 200_000, sigma)
        print(f"  image noise {sigma * 1000:.0f} um:")
        for m in METHODS:
            r = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=120.0, method=m)
            e = np.sqrt(np.mean((r.points - P) ** 2, axis=0))
            print(f"    {m:14s} {e[0]:8.4f} {e[1]:8.4f} {e[2]:8.4f}")
    # near seed 000's singularity: epipolar plane containing (1, 1, 1) -> image y ~ -f in the normal case
    print("normal case, points near y = -f (seed 000's singular direction), 2 um noise; RMS error X, Y, Z")
    eye = np.eye(3)
    B = np.array([200.0, 0, 0])
    for y in (-50.0, -90.0, -99.0, -99.9):
        n = 20000
        P = np.column_stack([rng.uniform(0, 200, n), np.full(n, y * 10.0) + rng.uniform(-0.5, 0.5, n),
                             np.full(n, -1000.0)])
        x1 = project(P, rotation=eye, centre=np.zeros(3), focal_length_mm=100.0) + rng.normal(0, 0.002, (n, 2))
        x2 = project(P, rotation=eye, centre=B, focal_length_mm=100.0) + rng.normal(0, 0.002, (n, 2))
        out = []
        for m in METHODS:
            try:
                r = intersect(x1, x2, rotation_left=eye, rotation_right=eye, base=B, focal_length_mm=100.0, method=m)
                e = np.sqrt(np.mean((r.points - P) ** 2, axis=0))
                out.append(f"{m}: {e[0]:.3f} {e[1]:.3f} {e[2]:.3f}")
            except Exception as err:  # noqa: BLE001 - report the singularity
                out.append(f"{m}: {type(err).__name__}")
        print(f"  y = {y:6.1f} mm  " + " | ".join(out))


if __name__ == "__main__":
    main()
