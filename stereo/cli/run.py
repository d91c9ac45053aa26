"""``stereo run``: the whole pair pipeline from two images."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, matcher_opts, overwrite_opt, progress, scheduler_opt
from rectify.geometry.robust import ROBUST_METHODS
from stereo.actions.common import PAIR_MATCHER, matcher_config
from stereo.actions.dense import DenseOptions
from stereo.actions.run import run as run_action
from stereo.pair.intersection import METHODS
from stereo.pair.model import FRAMES, ModelOptions

_D = ModelOptions()


@click.command(short_help="Match, orient, intersect and orient to ground: everything with a QA report.")
@click.argument("left", type=click.Path(exists=True, dir_okay=False))
@click.argument("right", type=click.Path(exists=True, dir_okay=False))
@click.option("--camera", "camera_path", required=True, type=click.Path(),
              help="Camera: camera JSON, orthority int_param, OpenCV calibration, COLMAP model or Metashape cameras "
                   "XML, found by content (KIND:PATH: camera, orthority, opencv, colmap, metashape).")
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option("--control", "control_path", type=click.Path(exists=True, dir_okay=False), default=None)
@click.option("--check", "check_ids", default="", help="Comma-separated control ids used only as checks.")
@click.option("--frame", type=click.Choice(list(FRAMES)), default=_D.frame, show_default=True)
@click.option("--method", type=click.Choice(list(METHODS)), default=_D.intersection, show_default=True)
@click.option("--robust", type=click.Choice(list(ROBUST_METHODS)), default=_D.robust, show_default=True,
              help="Robust absolute orientation (none: plain least squares).")
@click.option("--control-sigma-px", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Image precision of the control/check points, pixels (default: estimated from the absolute "
                   "orientation).")
@click.option("--dense", is_flag=True, default=False,
              help="Also run the dense chain (stereo dense, default options) into OUTDIR/dense: point cloud and DSM.")
@matcher_opts(PAIR_MATCHER)
@scheduler_opt
@overwrite_opt
@handle_errors
def run(left, right, camera_path, out_dir, control_path, check_ids, frame, method, robust, control_sigma_px,
        dense, detector, verify, refine, max_matches, max_keypoints, scheduler, overwrite):
    """Run the stereo pipeline on LEFT and RIGHT into OUTDIR."""
    if scheduler is not None and not dense:
        raise click.BadParameter("goes with --dense (the dense matching is the step that runs on Dask)",
                                 param_hint="'--scheduler'")
    checks = tuple(s.strip() for s in check_ids.split(",") if s.strip())
    opts = ModelOptions(intersection=method, frame=frame, robust=robust, check_ids=checks,
                        control_sigma_px=control_sigma_px)
    matcher = matcher_config(detector=detector, verify=verify, refine=refine, max_matches=max_matches,
                             max_keypoints=max_keypoints)
    with progress("matching") as cb:
        result = run_action(left, right, camera=camera_path, out_dir=out_dir, control=control_path, options=opts,
                            overwrite=overwrite, progress=cb, matcher=matcher,
                            dense=DenseOptions(scheduler=scheduler) if dense else None)
    for line in result.summary_lines():
        echo(line)
