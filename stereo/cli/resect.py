"""``stereo resect``: space resection of one photo from ground control."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt
from stereo.actions.resect import ResectOptions
from stereo.actions.resect import resect as resect_action
from stereo.pair.resection import INITIAL_METHODS

_D = ResectOptions()


@click.command(short_help="Space resection (exterior orientation) from GCPs with z.")
@click.option("--camera", "camera_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Camera JSON.")
@click.option("--gcps", "gcps_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="GCP CSV id,col,row,x,y,z[,check] (ground x, y, z).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="EO JSON to write.")
@click.option("--initial", type=click.Choice(list(INITIAL_METHODS)), default=_D.initial, show_default=True,
              help="Direct solution for the initial values: OpenCV solvePnP (SQPnP) or DLT (>= 6 points).")
@click.option("--free-interior", is_flag=True, default=_D.free_interior,
              help="Also estimate f, x0, y0 (>= 5 points; weak over flat ground).")
@report_opt
@overwrite_opt
@handle_errors
def resect(camera_path, gcps_path, output, initial, free_interior, report_dir, overwrite):
    """Estimate omega, phi, kappa, X, Y, Z of one photo by collinearity least squares."""
    result = resect_action(camera=camera_path, gcps=gcps_path, output=output, report_dir=report_dir,
                           overwrite=overwrite, options=ResectOptions(initial=initial, free_interior=free_interior))
    for line in result.summary_lines():
        echo(line)
