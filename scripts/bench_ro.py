#!/usr/bin/env python
"""Benchmark: relative orientation in our three systems vs OpenCV's five-point
essential matrix (``cv2.findEssentialMat(USAC_MAGSAC)`` + ``cv2.recoverPose``)
on the same synthetic matches with known truth.

For each scene (vertical aerial, relative kappa = 180 deg, convergent 30 deg)
and each trial, the same noisy matches (0.3 px per coordinate, optionally 20 %
gross errors) go to every method; we report the median rotation error and
base-direction error (degrees) against the truth and the median wall time.
Ours: ``robust="none"`` on clean data, ``robust="tukey"`` (its RANSAC filter
is OpenCV's five-point USAC, then IRLS) with outliers. Targets (README, benchmarks):
error <= OpenCV's; time <= 3x OpenCV's.

Usage::

    python scripts/bench_ro.py [--n 500] [--trials 20] [--outliers 0.2]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from stereo.relative import SYSTEMS, RelativeOrientation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests.support
from tests.support.stereo_support import simulate_pair  # noqa: E402


def rot_err_deg(Ra, Rb):
    return math.degrees(2 * math.asin(min(1.0, np.linalg.norm(Ra - Rb) / (2 * math.sqrt(2)))))


def vec_err_deg(a, b):
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def opencv(left_mm, right_mm, f, pix):
    """The peer: five-point essential matrix with USAC MAGSAC, then recoverPose (normalised coordinates)."""
    n1 = np.column_stack([left_mm[:, 0], -left_mm[:, 1]]) / f
    n2 = np.column_stack([right_mm[:, 0], -right_mm[:, 1]]) / f
    E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.999, threshold=pix / f)
    _, R, t, _ = cv2.recoverPose(E[:3], n1, n2, np.eye(3), mask=mask)
    D = np.diag([1.0, -1.0, -1.0])
    return D @ R.T @ D, -(D @ R.T @ t.reshape(3))


def timed(fn, repeats):
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=500, help="matches per pair")
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--outliers", type=float, default=0.2)
    ap.add_argument("--noise", type=float, default=0.3, help="px per coordinate")
    ap.add_argument("--repeats", type=int, default=3, help="timing: best of this many runs")
    a = ap.parse_args(argv)
    f, pix = 120.0, 0.144
    cv2.setRNGSeed(0)
    print(f"# bench_ro: {a.n} matches, {a.noise} px noise, {a.trials} trials per scene; "
          f"median errors vs truth (deg) and median time (best of {a.repeats}) per pair")
    print(f"OpenCV {cv2.__version__}; threads {cv2.getNumThreads()}\n")
    print("| scene | outliers | method | rot err (deg) | base err (deg) | time (ms) | time / OpenCV | err / OpenCV |")
    print("|---|---|---|---|---|---|---|---|")
    for kind in ("vertical", "kappa180", "convergent"):
        for frac in (0.0, a.outliers):
            rows: dict[str, list] = {}
            for trial in range(a.trials):
                sp = simulate_pair(kind, n=a.n, noise_px=a.noise, outlier_fraction=frac, rng=1000 + trial)
                (R, b), t = timed(lambda sp=sp: opencv(sp.left_mm, sp.right_mm, f, pix), a.repeats)
                rows.setdefault("OpenCV 5-pt MAGSAC + recoverPose", []).append(
                    (rot_err_deg(R, sp.R_rel), vec_err_deg(b, sp.base_left), t))
                robust = "none" if frac == 0 else "tukey"
                for system in SYSTEMS:
                    ro, t = timed(lambda sp=sp, system=system, robust=robust: RelativeOrientation.from_points(
                        sp.left_mm, sp.right_mm, focal_length_mm=f, system=system, robust=robust,
                        pixel_size_mm=pix), a.repeats)
                    rows.setdefault(f"ours {system} ({robust}, start {ro.initial_method})", []).append(
                        (rot_err_deg(ro.relative_rotation, sp.R_rel), vec_err_deg(ro.base_left, sp.base_left), t))
            med = {k: np.median(np.array(v), axis=0) for k, v in rows.items()}
            ref = med["OpenCV 5-pt MAGSAC + recoverPose"]
            for k, (er, eb, t) in med.items():
                print(f"| {kind} | {frac:.0%} | {k} | {er:.4f} | {eb:.4f} | {1000 * t:.2f} | {t / ref[2]:.2f} | "
                      f"{er / ref[0]:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
