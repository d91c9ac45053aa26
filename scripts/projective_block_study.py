"""Blocks without a known camera against the metric bundle with the true camera (docs/projective_block.md).

For each seed a synthetic block (3 strips x 4 images, fx 1500, fy 1545, skew 15 px, principal point
(1019.5, 779.5) px; 150 m relief from 1000 m; 0.5 px image noise; 6 check points) is oriented three ways:
the metric bundle with the true camera held (the reference), and ``stereo.block.projective_bundle.
uncalibrated_block`` with ``--method projective`` and ``affine`` (no camera). Printed per run: the RMS 3D
check-point error of each, their ratio, and the recovered fx, fy, skew, cx, cy as (estimate - truth) /
standard error.

    python scripts/projective_block_study.py --seeds 0 6 --extra-control 4
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository's tests.support, run from anywhere

from rectify.errors import RectifyError  # noqa: E402
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle  # noqa: E402
from stereo.block.projective_bundle import uncalibrated_block  # noqa: E402
from tests.stereo.test_block_projective import CAM, SIZES, TRUTH, more_control  # noqa: E402
from tests.support.block_synthetic import make_block  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 6), help="first and last + 1 seed")
    ap.add_argument("--points", type=int, default=300, help="object points drawn (those seen twice are kept)")
    ap.add_argument("--extra-control", type=int, default=4,
                    help="full control points added to the 5 of the layout (the lowest and highest tie points)")
    a = ap.parse_args()
    ratios: dict[str, list[float]] = {"projective": [], "affine": []}
    fails = {"projective": 0, "affine": 0}
    for seed in range(*a.seeds):
        b = make_block(seed, strips=3, images_per_strip=4, camera=CAM, relief_m=150.0, n_points=a.points,
                       image_noise_px=0.5)
        if a.extra_control:
            b = dataclasses.replace(b, control=more_control(b, a.extra_control))
        ref = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control,
                            options=BundleOptions(max_iterations=50))
        e0 = float(np.sqrt(np.mean(np.sum(np.asarray(ref.check_errors) ** 2, axis=1))))
        for method in ("projective", "affine"):
            t0 = time.perf_counter()
            try:
                r = uncalibrated_block(b.tracks, SIZES, b.control, method=method)
            except RectifyError as err:
                fails[method] += 1
                print(f"seed {seed} {method:10s} refused: {err}")
                continue
            e = float(np.sqrt(np.mean(np.sum(np.asarray(r.bundle.check_errors) ** 2, axis=1))))
            ratios[method].append(e / e0)
            z = " ".join(f"{k[:-3]} {(v - TRUTH[k]) / s:+.2f}" for k, (v, s) in r.interior.items())
            print(f"seed {seed} {method:10s} check RMS 3D: true camera {e0:.3f} m, ours {e:.3f} m, ratio {e / e0:.2f}; "
                  f"(estimate - truth) / std: {z}; {time.perf_counter() - t0:.1f} s", flush=True)
    for method, rs in ratios.items():
        if rs:
            print(f"{method}: {len(rs)} runs, {fails[method]} refused; ratio median {np.median(rs):.2f}, "
                  f"max {np.max(rs):.2f}")


if __name__ == "__main__":
    main()
