#!/usr/bin/env python
"""Throughput of the cotangent four-point method against our homography.

Both transforms map the same 1e6 random points (a 10 000 x 10 000 px frame,
some outside it) through the same projective map, in one run, repeated and
interleaved (H, C, H, C, ...) so machine load affects both alike; the
median time of each is reported with the ratio. Target (README, benchmarks): the
cotangent method reaches at least 0.5x the homography's throughput.

OpenCV's ``cv2.perspectiveTransform`` (C++, no input validation) is timed
too, as an outside reference.

Usage: python scripts/bench_projective.py [--points 1000000] [--repeats 9]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from rectify.geometry.transforms.study import SPEED_FRAME_PX, speed_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    size = SPEED_FRAME_PX
    H, C, pts = speed_scene(args.points, rng)

    # agreement on the benchmark points
    diff = np.abs(C(pts) - H(pts)).max()
    times: dict[str, list[float]] = {"homography": [], "cotangent": [], "cv2": []}
    try:
        import cv2

        m = H.matrix.copy()

        def f_cv2(p: np.ndarray) -> np.ndarray:
            return cv2.perspectiveTransform(p[None], m)[0]
    except ImportError:  # pragma: no cover
        f_cv2 = None  # type: ignore[assignment]
    funcs = {"homography": H, "cotangent": C, "cv2": f_cv2}
    for f in funcs.values():
        if f is not None:
            f(pts[:1000])
    for _ in range(args.repeats):
        for name, f in funcs.items():
            if f is None:
                continue
            t0 = time.perf_counter()
            f(pts)
            times[name].append(time.perf_counter() - t0)

    med = {k: statistics.median(v) for k, v in times.items() if v}
    n = args.points
    print(f"bench_projective: {n:,} points, {args.repeats} interleaved repeats, median wall time")
    print(f"{'method':<34}{'time [ms]':>12}{'points/s':>16}")
    rows = [("homography (ours, numpy) [peer]", "homography"), ("cotangent four-point (ours)", "cotangent"),
            ("cv2.perspectiveTransform [ref]", "cv2")]
    for label, key in rows:
        if key in med:
            print(f"{label:<34}{med[key] * 1e3:>12.1f}{n / med[key]:>16,.0f}")
    ratio = med["homography"] / med["cotangent"]
    print(f"cotangent / homography throughput ratio: {ratio:.2f}  (target >= 0.5: "
          f"{'MET' if ratio >= 0.5 else 'NOT MET'})")
    print(f"max |cotangent - homography| on these points: {diff:.3g} px "
          f"({diff / size:.2g} of the 10 000 px frame)")


if __name__ == "__main__":
    main()
