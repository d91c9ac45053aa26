#!/usr/bin/env python
"""Seed 003, 3.2.3: relative orientation by the universal and projective methods against the systems of
elements, over convergence angles up to the seed's 70 degrees (docs/universal.md).

For each convergence angle, pairs of ``tests/support/projective_scene.pair_scene`` (true camera
known, 0.5 px noise, omega ``--tilt`` and 3 degrees less, phi from the convergence) are oriented by
``left-image`` and ``basis`` from zero angles (``--initial zero``: no essential-matrix fallback), by
``universal`` (linear iterations from the identity) and by ``projective`` (the fundamental matrix).
Printed per method: how many of the trials converged, the median iterations, the median rotation
error against the truth (degrees) and the median sigma0 (px).

Usage::

    python scripts/universal_ro_study.py [--trials 10] [--tilt 2]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rectify.errors import EstimationError  # noqa: E402
from stereo.relative import RelativeOrientation  # noqa: E402
from tests.support.projective_scene import pair_scene  # noqa: E402

METHODS = (("left-image", "zero"), ("basis", "zero"), ("universal", "auto"), ("projective", "auto"))


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(Ra.T @ Rb) - 1) / 2))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--tilt", type=float, default=2.0, help="omega of the left image, degrees (right: 3 less)")
    a = ap.parse_args()
    print("| convergence (deg) | method | converged | iterations | rotation error (deg) | sigma0 (px) |")
    print("|---|---|---|---|---|---|")
    for conv in (0.0, 30.0, 50.0, 70.0):
        stats: dict[str, list[tuple[int, float, float]]] = {m: [] for m, _ in METHODS}
        for t in range(a.trials):
            sc = pair_scene(100 + t, n=80, noise_px=0.5, convergence_deg=conv, tilt_deg=a.tilt)
            for system, initial in METHODS:
                try:
                    ro = RelativeOrientation.from_pixels(sc.left, sc.right, sc.camera, system=system,
                                                         initial=initial)
                except EstimationError:
                    continue
                pix = sc.camera.pixel_size_mm
                stats[system].append((ro.iterations, _angle_deg(ro.relative_rotation, sc.R_rel),
                                      (ro.sigma0_mm or math.nan) / pix))
        for system, _ in METHODS:
            s = np.array(stats[system]) if stats[system] else np.full((1, 3), np.nan)
            ok = len(stats[system])
            print(f"| {conv:.0f} | {system} | {ok}/{a.trials} | {np.median(s[:, 0]):.0f} | "
                  f"{np.median(s[:, 1]):.4f} | {np.median(s[:, 2]):.3f} |")


if __name__ == "__main__":
    main()
