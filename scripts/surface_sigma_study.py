"""sigma_Z calibration of ``stereo surface`` on rendered blocks with known surfaces (issue 27).

Per seed a ``--strips`` x ``--per-strip`` block of 240 x 180 px frames (0.25 m ground pixel, 100 m
above the terrain, 60 % forward and 30 % side overlap; ``tests/support/block_surface.py``) is
rendered, its orientation written (the true poses, or with ``--pose-sigma ANGLE_RAD POS_M`` poses
perturbed by those standard errors, which the orientation states), and ``run_surface`` fuses its
pairs. The fused DSM is compared with the terrain at the cell centres: RMSE (in ground pixels), the
RMS of (error / sigma_Z) overall, and the reliability table: per sigma_Z decile the cells' sigma
range, the RMS of their errors, the RMS of their sigma_Z and RMS(error / sigma_Z) (calibrated: 0.67
to 1.5). The pooled table over all seeds closes the output.

Usage:
    nice python scripts/surface_sigma_study.py [--seeds 5 6 7] [--strips 3] [--per-strip 4]
        [--pose-sigma 0.0002 0.02] [--work DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereo.actions.surface import SurfaceOptions, run_surface  # noqa: E402  (after the sys.path set-up)
from tests.support.block_surface import GSD, Z0, make_surface_block, read_dsm, truth_on  # noqa: E402


def reliability(err: np.ndarray, sigma: np.ndarray, bins: int = 10) -> list[tuple[float, float, float, float, float,
                                                                                  int]]:
    """Per sigma quantile bin: (sigma lo, sigma hi, RMS error, RMS sigma, RMS(error / sigma), cells)."""
    q = np.quantile(sigma, np.linspace(0, 1, bins + 1))
    rows = []
    for i in range(bins):
        m = (sigma >= q[i]) & ((sigma < q[i + 1]) if i < bins - 1 else (sigma <= q[i + 1]))
        z = err[m] / sigma[m]
        rows.append((float(q[i]), float(q[i + 1]), float(np.sqrt(np.mean(err[m] ** 2))),
                     float(np.sqrt(np.mean(sigma[m] ** 2))), float(np.sqrt(np.mean(z ** 2))), int(m.sum())))
    return rows


def print_table(rows: list[tuple[float, float, float, float, float, int]]) -> None:
    print("  decile  sigma_Z range (m)    RMS error (m)  RMS sigma_Z (m)  RMS(err/sigma)  cells")
    for i, (lo, hi, re, rs, rz, n) in enumerate(rows):
        flag = "" if 0.67 <= rz <= 1.5 else "  <- outside 0.67-1.5"
        print(f"  {i + 1:6d}  {lo:.3f} .. {hi:.3f}       {re:.3f}          {rs:.3f}            {rz:.2f}       "
              f"{n:6d}{flag}")


def one(seed: int, work: Path, args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    blk = make_surface_block(work / f"block{seed}", strips=args.strips, per_strip=args.per_strip, seed=seed,
                             supersample=args.supersample, pose_sigma=tuple(args.pose_sigma))
    t0 = time.perf_counter()
    res = run_surface(blk.folder, work / f"out{seed}", options=SurfaceOptions(ground_z=Z0))
    dt = time.perf_counter() - t0
    bands, tr, _ = read_dsm(work / f"out{seed}" / "dsm.tif")
    err = bands[0] - truth_on(tr, bands[0].shape, blk.terrain)
    ok = np.isfinite(err) & np.isfinite(bands[1])
    e, s = err[ok], bands[1][ok]
    print(f"seed {seed}: {len(res.pairs)} pairs, {ok.sum()} cells, RMSE {np.sqrt(np.mean(e ** 2)):.3f} m = "
          f"{np.sqrt(np.mean(e ** 2)) / GSD:.2f} GSD, median error {np.median(e):+.3f} m, RMS(err/sigma_Z) "
          f"{np.sqrt(np.mean((e / s) ** 2)):.2f}, variance factor {res.variance_factor:.3f}, {dt:.1f} s")
    print_table(reliability(e, s))
    return e, s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 6, 7])
    ap.add_argument("--strips", type=int, default=3)
    ap.add_argument("--per-strip", type=int, default=4)
    ap.add_argument("--supersample", type=int, default=1)
    ap.add_argument("--pose-sigma", type=float, nargs=2, default=[0.0, 0.0], metavar=("ANGLE_RAD", "POS_M"))
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        es, ss = [], []
        for seed in args.seeds:
            e, s = one(seed, work, args)
            es.append(e)
            ss.append(s)
        e, s = np.concatenate(es), np.concatenate(ss)
        print(f"all seeds: {len(e)} cells, RMSE {np.sqrt(np.mean(e ** 2)) / GSD:.2f} GSD, RMS(err/sigma_Z) "
              f"{np.sqrt(np.mean((e / s) ** 2)):.2f}")
        print_table(reliability(e, s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
