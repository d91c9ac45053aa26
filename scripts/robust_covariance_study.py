#!/usr/bin/env python
"""Seed 002's estimation details, measured (docs/robust.md).

1. Covariance of M-estimates (eq. 2.28): Monte Carlo std of the estimates / the predicted std, with 10 %
   outliers, for a quadratic fit (n observations, N(0, 1) errors, 10 % of them N(0, 10^2)): every psi
   function, both algorithms (reweighting, modified residuals) and both scales (median, weighted median
   of eq. 2.29). Beside it the usual IRLS figure ``sigma0^2 (A^T W A)^-1`` (sigma0 from the weighted
   residuals) for comparison.
2. The same ratio for the bundle adjustment (``stereo.block.bundle``): a synthetic block with 10 % of its
   image observations given blunders of 15-40 px, Tukey's psi; the pose errors against the predicted pose
   std, over noise seeds.
3. Modified Newton-Raphson against the full one on a synthetic block: iterations and seconds, least
   squares and robust.

Usage: python scripts/robust_covariance_study.py [--trials 4000] [--block-trials 20] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rectify.geometry.mestimate import m_estimate_linear  # noqa: E402
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle  # noqa: E402
from tests.support.block_synthetic import make_block  # noqa: E402


def quadratic(n: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(-1.0, 1.0, n)
    return np.column_stack([np.ones(n), t, t * t]), np.array([1.0, 2.0, 0.5])


def irls_sigma0_std(A: np.ndarray, b: np.ndarray, x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The usual IRLS precision: sigma0^2 (A^T W A)^-1 with sigma0^2 = v^T W v / (n_used - u)."""
    v = b - A @ x
    used = w > 1e-3
    s0sq = float(np.sum(w * v * v) / max(int(used.sum()) - A.shape[1], 1))
    return np.sqrt(np.diag(s0sq * np.linalg.inv(A.T @ (A * w[:, None]))))


def part1(trials: int, n: int) -> None:
    print(f"1. quadratic fit, n = {n}, 10 % outliers N(0, 10^2), {trials} trials: MC std / predicted std "
          "(intercept, slope, curvature)")
    A, x_true = quadratic(n)
    print(f"   {'psi':8s} {'algorithm':19s} {'scale':16s} {'eq. 2.28':>24s} {'IRLS sigma0^2 Q_w':>24s} {'iter':>5s}"
          f" {'s':>6s}")
    for psi in ("huber", "tukey", "hampel", "andrews"):
        for algorithm in ("reweighting", "modified-residuals"):
            for scale in ("weighted-median", "median"):
                if psi in ("hampel", "andrews") and (algorithm, scale) != ("reweighting", "weighted-median"):
                    continue
                rng = np.random.default_rng(12345)
                err, pred, pred_w, its = [], [], [], []
                t0 = time.perf_counter()
                for _ in range(trials):
                    e = rng.normal(0.0, 1.0, n)
                    k = rng.random(n) < 0.1
                    e[k] = rng.normal(0.0, 10.0, int(k.sum()))
                    b = A @ x_true + e
                    r = m_estimate_linear(A, b, psi=psi, algorithm=algorithm, scale=scale, max_iterations=500)
                    err.append(r.x - x_true)
                    pred.append(r.std_errors)
                    pred_w.append(irls_sigma0_std(A, b, r.x, r.weights))
                    its.append(r.iterations)
                dt = time.perf_counter() - t0
                mc = np.std(np.array(err), axis=0)
                ratio = mc / np.sqrt(np.mean(np.array(pred) ** 2, axis=0))
                ratio_w = mc / np.sqrt(np.mean(np.array(pred_w) ** 2, axis=0))
                print(f"   {psi:8s} {algorithm:19s} {scale:16s} {np.array2string(ratio, precision=3):>24s} "
                      f"{np.array2string(ratio_w, precision=3):>24s} {np.mean(its):5.1f} {dt:6.1f}")


def _pose_err(r, truth) -> np.ndarray:
    e = np.array([np.r_[p.angles - q.angles, p.position - q.position] for p, q in zip(r.poses, truth, strict=True)])
    e[:, :3] = (e[:, :3] + np.pi) % (2 * np.pi) - np.pi
    return e


def part2(trials: int) -> None:
    print(f"2. bundle adjustment, 18 images, 10 % blunders (15-40 px) on the image observations, Tukey, "
          f"{trials} noise seeds: RMS over images and seeds of pose error / predicted std")
    for algorithm in ("reweighting", "modified-residuals"):
        z, s0, fl = [], [], []
        for k in range(trials):
            b = make_block(0, blunder_fraction=0.1, noise_seed=k)
            r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                              options=BundleOptions(robust="tukey", image_sigma_px=0.5, robust_algorithm=algorithm,
                                                    max_iterations=200))
            z.append(_pose_err(r, b.true_poses) / r.pose_std)
            s0.append(r.sigma0)
            fl.append(len(set(b.blunder_obs.tolist()) - set(r.flagged_obs.tolist())))
        zz = np.array(z).reshape(-1, 6)
        rat = np.sqrt(np.mean(zz ** 2, axis=0))
        print(f"   {algorithm:19s} omega, phi, kappa, X, Y, Z: {np.array2string(rat, precision=2)}; mean sigma0 "
              f"{np.mean(s0):.3f}; blunders missed {sum(fl)}")


def part3(strips: int, per_strip: int) -> None:
    b = make_block(1, strips=strips, images_per_strip=per_strip, n_points=120 * strips * per_strip // 3,
                   blunder_fraction=0.03)
    std = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                        options=BundleOptions(robust="tukey", image_sigma_px=0.5)).point_std
    print(f"3. modified Newton-Raphson: block of {strips * per_strip} images, {b.tracks.n_obs} image observations, "
          f"3 % blunders; median point std {np.nanmedian(std):.3f} m")
    print(f"   {'estimator':34s} {'iterations':>10s} {'seconds':>8s} {'max |dX| vs full, m':>23s} "
          f"{'points not determined alike':>28s}")
    for robust in ("none", "tukey"):
        ref = None
        for newton in ("full", "modified"):
            for algorithm in (("reweighting", "modified-residuals") if robust != "none" else ("reweighting",)):
                opts = BundleOptions(robust=robust, image_sigma_px=0.5, newton=newton, robust_algorithm=algorithm,
                                     max_iterations=400, covariance="none")
                t0 = time.perf_counter()
                r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control,
                                  gnss=b.gnss, options=opts)
                dt = time.perf_counter() - t0
                if ref is None:
                    ref = r
                ok = ref.points_determined & r.points_determined
                d = float(np.nanmax(np.abs(r.points - ref.points)[ok]))
                odd = int(np.sum(ref.points_determined != r.points_determined))
                name = f"{robust}, {newton}" + (f", {algorithm}" if robust != "none" else "")
                print(f"   {name:34s} {r.iterations:10d} {dt:8.2f} {d:23.2e} {odd:28d}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=4000)
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--block-trials", type=int, default=20)
    ap.add_argument("--strips", type=int, default=7)
    ap.add_argument("--per-strip", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="500 trials, 4 block seeds, a 4 x 8 block")
    ap.add_argument("--parts", default="123", help="which parts to run, e.g. 3")
    a = ap.parse_args()
    if a.quick:
        a.trials, a.block_trials, a.strips, a.per_strip = 500, 4, 4, 8
    if "1" in a.parts:
        part1(a.trials, a.n)
    if "2" in a.parts:
        part2(a.block_trials)
    if "3" in a.parts:
        part3(a.strips, a.per_strip)


if __name__ == "__main__":
    main()
