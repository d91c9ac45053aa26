"""sigma_Z calibration of ``stereo surface`` on rendered blocks with known surfaces (issue 27).

Per seed a ``--strips`` x ``--per-strip`` block of 240 x 180 px frames (0.25 m ground pixel, 100 m
above the terrain, 60 % forward and 30 % side overlap; ``tests/support/block_surface.py``) is
rendered, its orientation written (the true poses, or with ``--pose-sigma ANGLE_RAD POS_M`` poses
perturbed by those standard errors, which the orientation states), and ``run_surface`` fuses its
pairs. The fused DSM is compared with the terrain at the cell centres: RMSE (in ground pixels), the
RMS of (error / sigma_Z) overall, and the reliability table: per sigma_Z decile the cells' sigma
range, the RMS of their errors, the RMS of their sigma_Z and RMS(error / sigma_Z) (calibrated: 0.67
to 1.5). The pooled table over all seeds closes the output.

``--via-block``: the perturbed poses (``--pose-sigma``, default here 0.5 mrad and 5 cm) go with the
camera into ``stereo block`` (tie points, bundle with GNSS at ``--gnss-sigma``), and ``stereo surface``
reads its output folder; ``--orientation-sigma`` chooses the orientation's share of sigma_Z.

Usage:
    nice python scripts/surface_sigma_study.py [--seeds 5 6 7] [--strips 3] [--per-strip 4]
        [--pose-sigma 0.0002 0.02] [--via-block [--gnss-sigma 0.05]] [--orientation-sigma auto] [--work DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from click.testing import CliRunner  # noqa: E402  (after the sys.path set-up)

from stereo.actions.surface import ORIENTATION_SIGMA, SurfaceOptions, run_surface  # noqa: E402
from stereo.cli.main import cli  # noqa: E402
from stereo.formats.block import read_block_orientation  # noqa: E402
from stereo.formats.poses import pose_csv_text  # noqa: E402
from tests.support.block_surface import CAMERA, GSD, Z0, make_surface_block, read_dsm, truth_on  # noqa: E402


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
    pose_sigma = tuple(args.pose_sigma) if args.pose_sigma else ((0.0005, 0.05) if args.via_block else (0.0, 0.0))
    blk = make_surface_block(work / f"block{seed}", strips=args.strips, per_strip=args.per_strip, seed=seed,
                             supersample=args.supersample, pose_sigma=pose_sigma)
    match = dataclasses.replace(SurfaceOptions().matching, **({} if args.refine_radius is None else
                                                              {"refine_radius": args.refine_radius}))
    folder, opts = blk.folder, SurfaceOptions(ground_z=Z0, orientation_sigma=args.orientation_sigma, matching=match)
    if args.via_block:
        bo = read_block_orientation(blk.folder / "orientation.json")
        (work / f"poses{seed}.csv").write_text(pose_csv_text(bo.poses, crs=None))
        (work / f"camera{seed}.json").write_text(json.dumps(CAMERA.to_dict()))
        folder = work / f"bundle{seed}"
        t0 = time.perf_counter()
        r = CliRunner().invoke(cli, ["block", *[str(blk.images / n) for n in blk.names], "--camera",
                                     str(work / f"camera{seed}.json"), "--poses", str(work / f"poses{seed}.csv"),
                                     "--gnss-sigma", str(args.gnss_sigma), "-o", str(folder)])
        if r.exit_code != 0:
            raise SystemExit(r.output)
        print(f"seed {seed}: stereo block {time.perf_counter() - t0:.1f} s")
        opts = SurfaceOptions(images=str(blk.images), orientation_sigma=args.orientation_sigma, matching=match)
    t0 = time.perf_counter()
    res = run_surface(folder, work / f"out{seed}", options=opts)
    dt = time.perf_counter() - t0
    bands, tr, _ = read_dsm(work / f"out{seed}" / "dsm.tif")
    err = bands[0] - truth_on(tr, bands[0].shape, blk.terrain)
    ok = np.isfinite(err) & np.isfinite(bands[1])
    e, s = err[ok], bands[1][ok]
    print(f"seed {seed}: {len(res.pairs)} pairs, {ok.sum()} cells, RMSE {np.sqrt(np.mean(e ** 2)):.3f} m = "
          f"{np.sqrt(np.mean(e ** 2)) / GSD:.2f} GSD, median error {np.median(e):+.3f} m, RMS(err/sigma_Z) "
          f"{np.sqrt(np.mean((e / s) ** 2)):.2f}, variance factor {res.variance_factor:.3f}, orientation share "
          f"{res.orientation_sigma}, {dt:.1f} s")
    print_table(reliability(e, s))
    return e, s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 6, 7])
    ap.add_argument("--strips", type=int, default=3)
    ap.add_argument("--per-strip", type=int, default=4)
    ap.add_argument("--supersample", type=int, default=1)
    ap.add_argument("--pose-sigma", type=float, nargs=2, default=None, metavar=("ANGLE_RAD", "POS_M"))
    ap.add_argument("--via-block", action="store_true")
    ap.add_argument("--gnss-sigma", type=float, default=0.05)
    ap.add_argument("--orientation-sigma", choices=ORIENTATION_SIGMA, default="auto")
    ap.add_argument("--refine-radius", type=int, default=None, help="the matcher's sub-pixel window radius")
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
