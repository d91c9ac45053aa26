"""Earth curvature against block size (seed 004): the height and plan error of each model, 1-100 km.

For a point at the plan distance ``s = D / 2`` from the centre of a block ``D`` across (the
farthest point of a round block) and at the height ``h`` above the ellipsoid, the study prints

1. the exact topocentric position (the ellipsoid, through PROJ: geodesic distance ``s`` along an
   azimuth, geocentric coordinates, ENU at the centre; :func:`rectify.geometry.curvature.ellipsoid_exact`)
   and its height drop, against the sphere's ``R (1 - cos(s / R))`` with the Gaussian radius;
2. the plan and height error of each model (:data:`rectify.geometry.curvature.CURVATURE_MODELS`)
   against the exact ellipsoid, the larger of the two azimuths north and east:
   ``none`` (map coordinates taken as Cartesian: what ``stereo block --frame map`` does),
   seed 004's ``unrolling`` (eq. 1) and ``projection`` (eqs. 2-3, eq. 2 corrected), and
   ``sphere`` (the exact sphere of the Gaussian radius);
3. seed 004's claim that the laid-out arc differs from its orthogonal projection by at most
   0.03 m for a block up to 40 km across (``s - R sin(s / R)``), at the radius and across the
   diameter, and with the point 500 m and 2000 m above the level surface;
4. what is left of the curvature after a bundle adjustment in the map frame supported by GNSS at
   every image: the block bends with the GNSS heights, but the projection's scale ``k`` enters
   the model's scale and so the heights below the cameras: ``dz = (1 - k) (h_camera - h_point)``
   (UTM: ``k = 0.9996 (1 + x^2 / 2R^2)``, x the distance from the central meridian);
5. with ``--adjust``, the 140-image curved-Earth block of ``tests/support/block_curved.py``
   adjusted from its observations CSV in the three frames of ``stereo block --frame``: check-point
   RMS error, RMS(error / predicted std) per axis, and the mean height error against item 4.

    python scripts/curvature_study.py [--lat 48] [--adjust [--seeds 5]]

Units: metres, kilometres where labelled.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rectify.geometry.curvature import (  # noqa: E402
    arc_minus_chord,
    ellipsoid_exact,
    gaussian_radius,
    height_drop,
    model_coordinates,
    sphere_exact,
)
from rectify.geometry.geodesy import ellipsoid_of  # noqa: E402

SIZES_KM = (1, 2, 5, 10, 20, 28, 40, 60, 80, 100)
HEIGHTS_M = (0.0, 500.0, 2000.0)


def exact(lat: float, s: float, h: float) -> list[tuple[float, float]]:
    """(plan, up) of the exact ellipsoid along azimuths north and east."""
    out = []
    for az in (0.0, math.pi / 2):
        e = ellipsoid_exact(15.0, lat, az, s, h)
        out.append((float(math.hypot(e[0], e[1])), float(e[2])))
    return out


def model_table(lat: float) -> None:
    R = gaussian_radius(lat, ellipsoid_of("EPSG:4326"))
    print(f"Gaussian radius at {lat:g} deg: {R / 1000:.1f} km")
    print("\n1. height drop of the ellipsoid at s = D/2 (m): exact north / east, sphere R(1 - cos s/R)")
    print(f"{'D km':>6} {'north':>9} {'east':>9} {'sphere':>9}")
    for d in SIZES_KM:
        s = 500.0 * d
        ex = exact(lat, s, 0.0)
        print(f"{d:6g} {-ex[0][1]:9.3f} {-ex[1][1]:9.3f} {float(height_drop(s, R)):9.3f}")
    print("\n2. model minus exact ellipsoid at s = D/2, max over azimuths north and east (m): plan | height")
    for h in HEIGHTS_M:
        print(f"\n   h = {h:g} m")
        print(f"{'D km':>6} | {'none':>17} | {'unrolling (1)':>17} | {'projection (2-3)':>17} | {'sphere':>17}")
        for d in SIZES_KM:
            s = 500.0 * d
            ex = exact(lat, s, h)
            cells = []
            for m in ("none", "unrolling", "projection", "sphere"):
                if m == "sphere":
                    p, z = (float(v) for v in sphere_exact(s, h, R))
                else:
                    p, z = (float(v) for v in model_coordinates(m, s, h, R))
                dp = max(abs(p - e[0]) for e in ex)
                dz = max(abs(z - e[1]) for e in ex)
                cells.append(f"{dp:8.3f} {dz:8.3f}")
            print(f"{d:6g} | " + " | ".join(cells))
    print("\n3. seed 004: 'the laid-out arc differs from its orthogonal projection by at most 0.03 m up to 40 km'")
    for d in (20, 40, 60):
        s = 500.0 * d
        r = float(arc_minus_chord(s, R))
        full = 2 * r
        p5 = float(model_coordinates("unrolling", s, 500.0, R)[0] - sphere_exact(s, 500.0, R)[0])
        p2 = float(model_coordinates("unrolling", s, 2000.0, R)[0] - sphere_exact(s, 2000.0, R)[0])
        print(f"   D = {d:3d} km: at the radius {r:.4f} m, across the diameter {full:.4f} m; a point 500 m up "
              f"{p5:+.3f} m, 2000 m up {p2:+.3f} m")


def scale_table(flying_m: float) -> None:
    print(f"\n4. map frame with GNSS at every image: height bias (1 - k) x flying height ({flying_m:g} m), UTM")
    R = 6_381_000.0
    for x_km in (0, 10, 25, 50, 100, 180):
        k = 0.9996 * (1 + (x_km * 1000.0) ** 2 / (2 * R ** 2))
        print(f"   {x_km:4d} km from the central meridian: k = {k:.7f}, dz = {(1 - k) * flying_m:+.3f} m")


def adjust(frames: tuple[str, ...], seed: int = 0) -> None:
    from click.testing import CliRunner  # local: only --adjust runs the CLI

    from stereo.cli.main import cli  # local: only --adjust runs the CLI
    from tests.support.block_curved import make_curved_block, write_curved_block  # local: test support

    blk = make_curved_block(seed)
    print(f"\n5. the curved block (seed {seed}): {len(blk.images)} images, {len(blk.points)} points, "
          f"{len(blk.obs_point)} observations, {blk.extent_m[0] / 1000:.1f} x {blk.extent_m[1] / 1000:.1f} km, "
          "25 km east of 15 E")
    where = {p: k for k, p in enumerate(blk.point_ids)}
    truth = blk.points[[where[c] for c in blk.check_ids]]
    R = 6_381_000.0
    k = 0.9996 * (1 + (truth[:, 0] - 500_000.0) ** 2 / (2 * R ** 2))
    pred = (1 - k) * (blk.centres[:, 2].mean() - truth[:, 2])
    with tempfile.TemporaryDirectory() as tmp:
        files = write_curved_block(Path(tmp) / "in", blk)
        for fr in frames:
            out = Path(tmp) / fr
            args = ["block", "--observations", str(files["observations"]), "--camera", str(files["camera"]),
                    "--poses", str(files["poses"]), "--control", str(files["control"]), "--check",
                    ",".join(blk.check_ids), "-o", str(out), "--no-report", "--no-stac", "--frame", fr]
            t0 = time.perf_counter()
            r = CliRunner().invoke(cli, args)
            dt = time.perf_counter() - t0
            if r.exit_code != 0:
                print(f"   {fr}: failed: {r.output.strip()}")
                continue
            rows = {row["id"]: row for row in csv.DictReader(ln for ln in (out / "points.csv").read_text()
                                                              .splitlines() if not ln.startswith("#"))}
            got = np.array([[float(rows[c][a]) for a in "xyz"] for c in blk.check_ids])
            std = np.array([[float(rows[c][f"std_{a}"]) for a in "xyz"] for c in blk.check_ids])
            e = got - truth
            rmse = np.sqrt(np.mean(e ** 2, axis=0))
            ratio = np.sqrt(np.mean((e / std) ** 2, axis=0))
            print(f"   {fr:12s} ({dt:4.1f} s): check RMSE x {rmse[0]:.3f} y {rmse[1]:.3f} z {rmse[2]:.3f} m; "
                  f"RMS(e/std) x {ratio[0]:.2f} y {ratio[1]:.2f} z {ratio[2]:.2f}; max |e/std| "
                  f"{np.abs(e / std).max():.1f}; mean dz {e[:, 2].mean():+.3f} m (predicted for the map frame "
                  f"{pred.mean():+.3f} m)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lat", type=float, default=48.0, help="latitude of the block centre, degrees")
    ap.add_argument("--flying-height", type=float, default=2760.0, help="flying height above the ground, m")
    ap.add_argument("--adjust", action="store_true", help="also adjust the 140-image curved block (about 20 s)")
    ap.add_argument("--seeds", type=int, default=0,
                    help="with --adjust: also adjust seeds 1..N of the block in the topocentric and map frames")
    a = ap.parse_args(argv)
    model_table(a.lat)
    scale_table(a.flying_height)
    if a.adjust:
        adjust(("topocentric", "geocentric", "map"))
        for seed in range(1, a.seeds + 1):
            adjust(("topocentric", "map"), seed)


if __name__ == "__main__":
    main()
