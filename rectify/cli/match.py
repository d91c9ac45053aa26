"""``rectify match LEFT RIGHT -o matches.csv``: tie points between two images."""

from __future__ import annotations

import click

from rectify.actions.match import DETECTORS, VERIFY_METHODS, MatchOptions
from rectify.actions.match import match as match_action
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress, report_opt, scheduler_opt

_D = MatchOptions()


@click.command(short_help="Find tie points between two images.")
@click.argument("left", type=click.Path(dir_okay=False))
@click.argument("right", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Matches CSV to write.")
@click.option("--detector", type=click.Choice(list(DETECTORS)), default=_D.detector, show_default=True)
@click.option("--verify", type=click.Choice(list(VERIFY_METHODS)), default=_D.verify, show_default=True,
              help="Geometric verification (OpenCV USAC MAGSAC++).")
@click.option("--refine/--no-refine", default=_D.refine, show_default=True,
              help="Least-squares matching refinement of the positions.")
@click.option("--max-matches", type=click.IntRange(1), default=None,
              help="At most this many matches, spread evenly (default 20000).")
@click.option("--threshold", "threshold_px", type=click.FloatRange(min=0, min_open=True), default=None,
              help="USAC inlier threshold, px (default 1.5).")
@report_opt
@scheduler_opt
@overwrite_opt
@handle_errors
def match(left, right, output, detector, verify, refine, max_matches, threshold_px, report_dir, scheduler, overwrite):
    """Match LEFT against RIGHT and write the verified tie points to a CSV
    (id,col_left,row_left,col_right,row_right,score; pixel centres at integers).

    Large images (a side above 4096 px) are matched coarse-to-fine by tiles
    with bounded memory (their tiles on Dask with --scheduler). Prints the counts (detected, matched, verified) and
    the verification residual RMSE.
    """
    opts = MatchOptions(detector=detector, verify=verify, refine=refine, max_matches=max_matches,
                        threshold_px=threshold_px, scheduler=scheduler)
    ws = Workspace(overwrite=overwrite, report_dir=report_dir)
    with progress("matching") as cb:
        run = match_action(ws, left, right, output, opts, progress=cb)
    for line in run.summary_lines():
        echo(line)
