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
from scipy.spatial.transform import Rotation

from rectify.geometry.rotation import angles_from_matrix
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.result import BundleResult
from stereo.block.types import GnssObservations
from tests.support.block_synthetic import SyntheticBlock, make_block

SHIFT = np.array([[0.9, -0.6, 0.75], [-0.75, 0.45, -0.9], [0.3, 0.9, 0.6], [-0.6, -0.3, 1.05]])     # m
DRIFT = np.array([[0.03, -0.015, 0.024], [-0.018, 0.03, 0.012], [0.0, -0.024, 0.03], [0.015, 0.015, -0.03]])  # m/s


def strips(names: tuple[str, ...]) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """Strip labels, strip index and exposure time (600 s between strips, 4 s between images)."""
    strip = tuple(n.split("_")[0] for n in names)
    lab = np.array([int(s[1:]) for s in strip])
    order = np.array([int(n.split("_")[1]) for n in names])
    return strip, lab, 600.0 * lab + 4.0 * order


def run(blk: SyntheticBlock, g: GnssObservations, **kw: str) -> BundleResult:
    return adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, control=blk.control, gnss=g,
                         options=BundleOptions(image_sigma_px=0.5, **kw))  # type: ignore[arg-type]


def check_text(r: BundleResult) -> str:
    z = r.check_errors / r.check_std
    return (f"check RMS(err/std) {np.sqrt(np.mean(z ** 2, axis=0)).round(2).tolist()}, "
            f"check RMS {np.sqrt(np.mean(r.check_errors ** 2)):.3f} m, max |err/std| {np.abs(z).max():.2f}")


def drift_study() -> None:
    blk = make_block(3, strips=4, images_per_strip=8, n_points=900, gnss_noise_m=0.05, ins_noise_rad=2e-4,
                     n_check=8)
    g = blk.gnss
    strip, lab, t = strips(g.images)
    tm = np.array([t[lab == k].mean() for k in range(4)])
    pos = g.position + SHIFT[lab] + DRIFT[lab] * (t - tm[lab])[:, None]
    gg = GnssObservations(g.images, pos, g.sigma_m, g.lever_arm_m, g.angles, g.sigma_rad, time=t, strip=strip)
    for mode in ("none", "shift", "shift-drift"):
        r = run(blk, gg, gnss_drift=mode)
        line = f"GNSS shift+drift block, --gnss-drift {mode}: sigma0 {r.sigma0:.3f}, {check_text(r)}"
        if mode == "shift-drift":
            truth = np.concatenate([np.concatenate([SHIFT[k], DRIFT[k]]) for k in range(4)])
            z = (r.systematic - truth) / r.systematic_std
            line += f"; 24 unknowns: max |err/std| {np.abs(z).max():.2f}, RMS {np.sqrt(np.mean(z ** 2)):.2f}"
        print(line)


def boresight_study() -> None:
    blk = make_block(5, strips=3, images_per_strip=8, n_points=900, gnss_noise_m=0.05, ins_noise_rad=2e-4,
                     n_check=8)
    g = blk.gnss
    strip, _, _ = strips(g.images)
    beta = np.radians([0.05, -0.08, 0.12])
    R = np.array([p.rotation for p in blk.true_poses])
    Ro = R @ Rotation.from_rotvec(-beta).as_matrix()
    ang = np.asarray(angles_from_matrix(Ro, "omega-phi-kappa")).reshape(-1, 3)
    ang = ang + np.random.default_rng(1).normal(0, 2e-4, ang.shape)
    gg = GnssObservations(g.images, g.position, g.sigma_m, g.lever_arm_m, ang, g.sigma_rad, strip=strip)
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
    blk = make_block(11, strips=2, images_per_strip=10, n_points=1500, gnss_noise_m=0.0, ins_noise_rad=2e-5,
                     control_layout="none", n_check=8, forward_overlap=0.8, side_overlap=0.5)
    g = blk.gnss
    _, lab, _ = strips(g.images)
    rng = np.random.default_rng(4)
    s, rho = 0.5, 0.995
    cov = np.zeros((len(lab), 3, 3))
    err = np.zeros((len(lab), 3))
    for i, k in enumerate(lab):
        r_ = rho if k == 0 else -rho
        cov[i] = [[s * s, r_ * s * s, 0.0], [r_ * s * s, s * s, 0.0], [0.0, 0.0, 0.05 ** 2]]
        err[i] = np.linalg.cholesky(cov[i]) @ rng.normal(size=3)
    pos = g.position + err
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    tc = np.array([p.position for p in blk.true_poses])
    for c, name in ((cov, "full covariances"), (None, "diagonal sigmas")):
        r = run(blk, GnssObservations(g.images, pos, sig, None, g.angles, g.sigma_rad, covariance=c))
        sh = np.mean(np.array([p.position for p in r.poses]) - tc, axis=0)
        print(f"correlated GNSS, {name}: check plan RMS {np.sqrt(np.mean(r.check_errors[:, :2] ** 2)):.3f} m, "
              f"{check_text(r)}, block shift error x {sh[0]:+.3f} y {sh[1]:+.3f} m")


if __name__ == "__main__":
    drift_study()
    boresight_study()
    covariance_study()
