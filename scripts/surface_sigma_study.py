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
reads its output folder; ``--orientation-sigma`` chooses the orientation's share of sigma_Z. The
orientation's share is then split off (``orientation_split``): per cell, the realised orientation
error of the cell's provenance pair (the true surface point projected with the true poses, the two
rays intersected with the bundle's poses: what a perfect matcher would give) against the share's
sigma (the block points' field, as ``stereo surface`` takes it), and the reliability table of the
rest, ``(error - realised orientation error) / sqrt(sigma_Z^2 - orientation sigma^2)``: the per-cell
(disparity) model through the bundle. The bundle's variance factors are printed too, and with
``--full-covariance`` the bundle is run once more in-process and its covariance of all poses (the
correlations included) propagated to the cells (``orientation_sigma_from_covariance``), against the
field of its points' std_z.

Usage:
    nice python scripts/surface_sigma_study.py [--seeds 5 6 7] [--strips 3] [--per-strip 4]
        [--pose-sigma 0.0002 0.02] [--via-block [--gnss-sigma 0.05] [--full-covariance]] [--orientation-sigma auto]
        [--work DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from click.testing import CliRunner  # noqa: E402  (after the sys.path set-up)

from stereo.actions.block import BlockOptions, run_block  # noqa: E402
from stereo.actions.surface import ORIENTATION_SIGMA, SurfaceOptions, SurfaceResult, run_surface  # noqa: E402
from stereo.cli.main import cli  # noqa: E402
from stereo.dense.precision import PointSigmaField  # noqa: E402
from stereo.formats.block import read_block_orientation  # noqa: E402
from stereo.formats.points import read_points_csv  # noqa: E402
from stereo.formats.poses import pose_csv_text  # noqa: E402
from tests.support.block_render import strip_poses  # noqa: E402
from tests.support.block_surface import CAMERA, GSD, H_FLY, Z0, SurfaceBlock, make_surface_block, read_dsm, truth_on  # noqa: E402
from tests.support.surface_truth import (  # noqa: E402
    orientation_sigma_from_covariance,
    realised_orientation_error,
    reliability,
)


def print_table(rows: list[tuple[float, float, float, float, float, int]]) -> None:
    print("  decile  sigma_Z range (m)    RMS error (m)  RMS sigma_Z (m)  RMS(err/sigma)  cells")
    for i, (lo, hi, re, rs, rz, n) in enumerate(rows):
        flag = "" if 0.67 <= rz <= 1.5 else "  <- outside 0.67-1.5"
        print(f"  {i + 1:6d}  {lo:.3f} .. {hi:.3f}       {re:.3f}          {rs:.3f}            {rz:.2f}       "
              f"{n:6d}{flag}")


def orientation_split(blk: SurfaceBlock, bundle: Path, res: SurfaceResult, tr: Affine, prov: np.ndarray,
                      ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per valid cell: the realised orientation error of its provenance pair and the orientation share's sigma
    (the bundle points' field, as ``stereo surface`` takes it)."""
    dz, xy = realised_orientation_error(blk, CAMERA, bundle / "orientation.json",
                                        [(p.left, p.right) for p in res.pairs], tr, prov, ok)
    pts = read_points_csv(bundle / "points.csv")
    assert pts.std is not None
    return dz, PointSigmaField.from_points(pts.xyz[:, :2], pts.std[:, 2])(xy)


def _variance_factors(report: Path) -> dict | None:
    def find(o):  # noqa: ANN001, ANN202
        if isinstance(o, dict):
            if "variance_factors" in o:
                return o["variance_factors"]
            for v in o.values():
                r = find(v)
                if r is not None:
                    return r
        return None
    return find(json.loads(report.read_text())) if report.is_file() else None


def one(seed: int, work: Path, args: argparse.Namespace) -> dict:
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
    rel = reliability(e, s)
    print_table(rel)
    row = {"seed": seed, "cells": int(ok.sum()), "rmse": float(np.sqrt(np.mean(e ** 2))), "z": float(np.sqrt(np.mean(
        (e / s) ** 2))), "deciles": (min(r[4] for r in rel), max(r[4] for r in rel)), "vf": res.variance_factor,
        "e": e, "s": s, "er": np.zeros(0), "sr": np.zeros(0)}
    if not args.via_block or res.orientation_sigma != "points":
        return row
    dz, so = orientation_split(blk, folder, res, tr, bands[3], ok)
    vf = _variance_factors(folder / "report" / "report.json")
    row["orient"] = (float(np.sqrt(np.mean(dz ** 2))), float(np.mean(dz)), float(np.sqrt(np.mean(so ** 2))),
                     float(np.sqrt(np.mean((dz / so) ** 2))), (vf or {}).get("gnss", math.nan))
    print(f"seed {seed}: the bundle's variance factors (sigma multipliers) {vf}; orientation share: realised error "
          f"RMS {row['orient'][0]:.4f} m (mean {row['orient'][1]:+.4f}), its sigma RMS {row['orient'][2]:.4f} m, "
          f"RMS(realised / sigma) {row['orient'][3]:.2f}")
    sd = np.sqrt(np.maximum(s ** 2 - so ** 2, 1e-12))
    rest = reliability(e - dz, sd)
    row.update(er=e - dz, sr=sd, rest=(float(np.sqrt(np.mean(((e - dz) / sd) ** 2))), min(r[4] for r in rest),
                                       max(r[4] for r in rest)))
    print(f"seed {seed}: the rest (error - realised orientation error) / sqrt(sigma_Z^2 - orientation sigma^2): RMS "
          f"{row['rest'][0]:.2f}")
    print_table(rest)
    if args.full_covariance:
        full_covariance_check(seed, work, blk, res, tr, bands[3], ok, args)
    return row


def full_covariance_check(seed: int, work: Path, blk: SurfaceBlock, res: SurfaceResult, tr: Affine,
                          prov: np.ndarray, ok: np.ndarray, args: argparse.Namespace) -> None:
    """The bundle run in-process (its covariance of all poses, correlations included): that covariance
    propagated to each cell through its provenance pair against the field of the bundle's points' std_z."""
    out = work / f"bundle{seed}_cov"
    b = run_block([blk.images / n for n in blk.names], out_dir=out, camera=work / f"camera{seed}.json",
                  poses=work / f"poses{seed}.csv", options=BlockOptions(gnss_sigma_m=(args.gnss_sigma,) * 3),
                  overwrite=True).bundle
    n = len(b.poses)
    sd = np.asarray(b.pose_std, dtype=np.float64).reshape(-1)
    cov = np.asarray(b.correlation, dtype=np.float64)[:6 * n, :6 * n] * np.outer(sd, sd)
    pairs = [(p.left, p.right) for p in res.pairs]
    s_cov = orientation_sigma_from_covariance(blk, CAMERA, b.poses, cov, pairs, tr, prov, ok)
    pts = read_points_csv(out / "points.csv")
    assert pts.std is not None
    _dz, xy = realised_orientation_error(blk, CAMERA, out / "orientation.json", pairs, tr, prov, ok)
    s_field = PointSigmaField.from_points(pts.xyz[:, :2], pts.std[:, 2])(xy)
    print(f"seed {seed}: the bundle's full pose covariance at the cells: RMS {np.sqrt(np.mean(s_cov ** 2)):.4f} m; the "
          f"points' std_z field there: RMS {np.sqrt(np.mean(s_field ** 2)):.4f} m; median field / covariance "
          f"{np.median(s_field / s_cov):.3f}")


def common_share_band(args: argparse.Namespace, draws: int = 20000) -> tuple[float, ...]:
    """Quantiles 5, 50, 95 % of one block's RMS(error / sigma) for an error common to the whole block whose
    sigma is exact: the datum a GNSS fix gives (``--gnss-sigma`` on every projection centre of the block
    layout, the 7-parameter similarity they fit), its height error over the ground the images cover against the
    similarity's propagated sigma, in ``draws`` draws (seeded)."""
    blk_poses = strip_poses(CAMERA, n_strips=args.strips, n_per_strip=args.per_strip, flying_height_m=H_FLY,
                            ground_z=Z0, angle_sigma_rad=0.0)
    c = np.array([p.position for p in blk_poses])
    c0 = c.mean(axis=0)

    def design(p: np.ndarray) -> np.ndarray:  # d(position) / d(shift, small rotation, scale)
        d = p - c0
        a = np.zeros((len(p), 3, 7))
        a[:, :, :3] = np.eye(3)
        a[:, 0, 4], a[:, 0, 5] = d[:, 2], -d[:, 1]
        a[:, 1, 3], a[:, 1, 5] = -d[:, 2], d[:, 0]
        a[:, 2, 3], a[:, 2, 4] = d[:, 1], -d[:, 0]
        a[:, :, 6] = d
        return a.reshape(-1, 7)

    A = design(c)
    half = np.array([CAMERA.width, CAMERA.height]) * GSD / 2   # the ground the images cover
    lo, hi = c[:, :2].min(axis=0) - half, c[:, :2].max(axis=0) + half
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 15), np.linspace(lo[1], hi[1], 11))
    g = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, Z0)])
    az = design(g)[2::3]
    sd = args.gnss_sigma ** 2 * np.linalg.inv(A.T @ A)
    sig = np.sqrt(np.einsum("ni,ij,nj->n", az, sd, az))
    e = np.random.default_rng(0).normal(0.0, args.gnss_sigma, (draws, A.shape[0])) @ np.linalg.pinv(A).T
    r = np.sqrt(np.mean((e @ az.T / sig) ** 2, axis=1))
    return tuple(float(v) for v in np.quantile(r, [0.05, 0.5, 0.95]))


def summary(rows: list[dict], args: argparse.Namespace) -> None:
    """The per-seed lines of docs/surface.md's tables, and the orientation share over the blocks."""
    print("| seed | cells | RMSE | RMS(error / sigma_Z) | deciles | variance factor |")
    for r in rows:
        print(f"| {r['seed']} | {r['cells']:,} | {r['rmse']:.3f} m = {r['rmse'] / GSD:.2f} GSD | {r['z']:.2f} | "
              f"{r['deciles'][0]:.2f}-{r['deciles'][1]:.2f} | {r['vf']:.3f} |".replace(",", " "))
    ors = [r for r in rows if "orient" in r]
    if not ors:
        return
    print("| seed | orientation error RMS (mean) | its sigma RMS | RMS(error / sigma) | bundle GNSS factor | "
          "the rest: RMS(error / sigma), deciles |")
    for r in ors:
        o, t = r["orient"], r["rest"]
        print(f"| {r['seed']} | {o[0]:.3f} m ({o[1]:+.3f}) | {o[2]:.3f} m | {o[3]:.2f} | {o[4]:.2f} | {t[0]:.2f}, "
              f"{t[1]:.2f}-{t[2]:.2f} |")
    per = np.array([r["orient"][3] for r in ors])
    print(f"orientation share over {len(per)} blocks: RMS(realised / sigma) per block from {per.min():.2f} to "
          f"{per.max():.2f}, pooled {np.sqrt(np.mean(per ** 2)):.2f}")
    q = common_share_band(args)
    print(f"an error common to the block with an exact sigma (the GNSS datum of this layout): one block's RMS(error / "
          f"sigma) 5 % {q[0]:.2f}, median {q[1]:.2f}, 95 % {q[2]:.2f}")


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
    ap.add_argument("--full-covariance", action="store_true",
                    help="with --via-block: the bundle once more in-process, its pose covariance at the cells")
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        rows = [one(seed, work, args) for seed in args.seeds]
        e, s, er, sr = (np.concatenate([r[k] for r in rows]) for k in ("e", "s", "er", "sr"))
        print(f"all seeds: {len(e)} cells, RMSE {np.sqrt(np.mean(e ** 2)) / GSD:.2f} GSD, RMS(err/sigma_Z) "
              f"{np.sqrt(np.mean((e / s) ** 2)):.2f}")
        print_table(reliability(e, s))
        if len(er):
            print(f"all seeds, without the realised orientation error: RMS {np.sqrt(np.mean((er / sr) ** 2)):.2f}")
            print_table(reliability(er, sr))
        summary(rows, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
