"""``rectify compare``: the cotangent four-point method against the homography (issue 2 study)."""

from __future__ import annotations

import click

from rectify.actions.compare import CompareOptions
from rectify.actions.compare import compare as compare_action
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress


@click.command(short_help="Compare the cotangent four-point method with the homography (study).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="compare-output", show_default=True,
              help="Folder for study.md, study.json and the PNG plots.")
@click.option("--configs", type=click.IntRange(1, 100_000), default=None,
              help="Random configurations for the agreement test [quick preset: 500].")
@click.option("--trials", type=click.IntRange(1, 100_000), default=None,
              help="Monte Carlo trials per camera and noise level [quick preset: 60].")
@click.option("--speed-points", type=click.IntRange(1, 10_000_000), default=None,
              help="Points for the speed test [quick preset: 200000].")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=None, help="Random seed [0].")
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
    opts = CompareOptions(n_configs=configs, n_trials=trials, n_speed_points=speed_points, seed=seed, full=full)
    with progress("study", enabled=True) as cb:
        run = compare_action(Workspace(overwrite=overwrite), out_dir, opts, progress=cb)
    for line in run.summary_lines():
        echo(line)
