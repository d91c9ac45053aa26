#!/usr/bin/env python
"""Study: the GNSS/INS observation model of the bundle (stereo.block.bundle.systematic) on synthetic blocks.

The blocks of ``tests/stereo/test_block_systematic.py`` (``tests.support.block_synthetic.make_block``),
adjusted with and without each part of the model:

1. GNSS shifts (0.3-1.05 m) and drifts (1.2-3 cm/s) per strip, 4 strips of 8 images, 5 control points:
   ``--gnss-drift none|shift|shift-drift``;
2. a boresight error of (0.05, -0.08, 0.12) deg in the INS angles: ``--boresight-unknown none|block|strip``;
3. GNSS errors correlated +0.995 (strip 0) and -0.995 (strip 1) between x and y, sigma 0.5 m, no control:
   full covariances against the diagonal sigmas.

The figures of docs/block.md ("GNSS/INS observations") are this script's output.

Usage::

    PYTHONPATH=. python scripts/gnss_ins_study.py
"""

from __future__ import annotations

import numpy as np

from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.result import BundleResult
from stereo.block.types import GnssObservations
from tests.support.block_synthetic import SyntheticBlock
from tests.support.gnss_scenes import BORESIGHT, DRIFT, SHIFT, boresight_block, correlated_gnss_block, drift_block


def run(blk: SyntheticBlock, g: GnssObservations, **kw: str) -> BundleResult:
    return adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, control=blk.control, gnss=g,
                         options=BundleOptions(image_sigma_px=0.5, **kw))  # type: ignore[arg-type]


def check_text(r: BundleResult) -> str:
    z = r.check_errors / r.check_std
    return (f"check RMS(err/std) {np.sqrt(np.mean(z ** 2, axis=0)).round(2).tolist()}, "
            f"check RMS {np.sqrt(np.mean(r.check_errors ** 2)):.3f} m, max |err/std| {np.abs(z).max():.2f}")


def drift_study() -> None:
    blk, gg = drift_block()
    for mode in ("none", "shift", "shift-drift"):
        r = run(blk, gg, gnss_drift=mode)
        line = f"GNSS shift+drift block, --gnss-drift {mode}: sigma0 {r.sigma0:.3f}, {check_text(r)}"
        if mode == "shift-drift":
            truth = np.concatenate([np.concatenate([SHIFT[k], DRIFT[k]]) for k in range(4)])
            z = (r.systematic - truth) / r.systematic_std
            line += f"; 24 unknowns: max |err/std| {np.abs(z).max():.2f}, RMS {np.sqrt(np.mean(z ** 2)):.2f}"
        print(line)


def boresight_study() -> None:
    blk, gg = boresight_block()
    beta = BORESIGHT
    for mode, k in (("none", 0), ("block", 1), ("strip", 3)):
        r = run(blk, gg, boresight_unknown=mode)
        line = (f"boresight block, --boresight-unknown {mode}: sigma0 {r.sigma0:.3f}, INS group sigma0 "
                f"{r.sigma0_groups['ins']:.2f}, {check_text(r)}")
        if k:
            z = (r.systematic - np.tile(beta, k)) / r.systematic_std
            line += (f"; err/std {z.round(2).tolist()}, std {np.degrees(r.systematic_std[:3]).round(4).tolist()} "
                     "deg")
        print(line)


def covariance_study() -> None:
    blk, g_full, g_diag = correlated_gnss_block()
    tc = np.array([p.position for p in blk.true_poses])
    for gg, name in ((g_full, "full covariances"), (g_diag, "diagonal sigmas")):
        r = run(blk, gg)
        sh = np.mean(np.array([p.position for p in r.poses]) - tc, axis=0)
        print(f"correlated GNSS, {name}: check plan RMS {np.sqrt(np.mean(r.check_errors[:, :2] ** 2)):.3f} m, "
              f"{check_text(r)}, block shift error x {sh[0]:+.3f} y {sh[1]:+.3f} m")


if __name__ == "__main__":
    drift_study()
    boresight_study()
    covariance_study()
