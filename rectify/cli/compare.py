"""``rectify compare``: the cotangent four-point method against the homography (issue 2 study)."""

from __future__ import annotations

import click

from .options import echo, handle_errors, overwrite_opt, progress


@click.command(short_help="Compare the cotangent four-point method with the homography (study).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="compare-output", show_default=True,
              help="Folder for study.md, study.json and the PNG plots.")
@click.option("--configs", type=click.IntRange(1), default=None,
              help="Random configurations for the agreement test [quick preset: 500].")
@click.option("--trials", type=click.IntRange(1), default=None,
              help="Monte Carlo trials per camera and noise level [quick preset: 60].")
@click.option("--speed-points", type=click.IntRange(1), default=None,
              help="Points for the speed test [quick preset: 200000].")
@click.option("--seed", type=int, default=None, help="Random seed [0].")
@click.option("--full", is_flag=True, default=False,
              help="Use the full sizes of scripts/compare_cotangent_homography.py instead of the quick preset.")
@overwrite_opt
@handle_errors
def compare(out_dir, configs, trials, speed_points, seed, full, overwrite):
    """Run the comparison study of the cotangent four-point method (seed 001)
    and the 8-parameter homography: agreement on exact data, Monte Carlo
    accuracy for Resurs-F and aerial tilted frames, first-order error
    propagation, conditioning near degeneracy and speed. Writes a Markdown
    table and PNG plots into --out."""
    from ..compare import StudyConfig, run_study, write_study

    over = dict(n_configs=configs, n_trials=trials, n_speed_points=speed_points, seed=seed)
    if full:
        cfg = StudyConfig(**{k: v for k, v in over.items() if v is not None})
    else:
        cfg = StudyConfig.quick(**over)
    _check_outputs(out_dir, overwrite)
    with progress("study", enabled=True) as cb:
        res = run_study(cfg, progress=cb)
    path = write_study(res, out_dir, overwrite=overwrite)
    a, s = res.agreement, res.speed
    echo(f"agreement: {a['n_configs']} configurations, max |cotangent - homography| = "
         f"{a['max_rel']:.2e} of the image size (eq. 2 as printed: median error {a['printed_median_rel']:.2f})")
    shown = 1.0 if any(r["sigma_px"] == 1.0 for r in res.noise) else max(r["sigma_px"] for r in res.noise)
    for r in res.noise:
        if r["sigma_px"] == shown:
            echo(f"noise {r['sigma_px']:g} px, {r['camera']}: RMSE cotangent {r['rmse_cotangent']:.3f} px, "
                 f"homography(4) {r['rmse_homography4']:.3f} px, homography LSQ {r['rmse_homography_lsq']:.3f} px")
    echo(f"speed: homography {s['homography_pts_per_s']:,.0f} pts/s, cotangent {s['cotangent_pts_per_s']:,.0f} "
         f"pts/s, ratio {s['ratio']:.2f}")
    echo(f"wrote {path}")


def _check_outputs(out_dir: str, overwrite: bool) -> None:
    from pathlib import Path

    from ..errors import InvalidInputError

    p = Path(out_dir)
    if (p / "study.md").exists() and not overwrite:
        raise InvalidInputError(f"{str(p / 'study.md')!r} exists; pass --overwrite to replace it")
