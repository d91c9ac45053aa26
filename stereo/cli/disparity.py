"""``stereo disparity``: the dense disparity of an already rectified pair."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt
from stereo.actions.disparity import DisparityOptions
from stereo.actions.disparity import disparity as disparity_action


@click.command(short_help="Dense disparity of a rectified pair (the dense chain's matcher).")
@click.argument("left", type=click.Path(dir_okay=False))
@click.argument("right", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Disparity GeoTIFF to write (float32 col_left - col_right, px; nodata -9999).")
@click.option("--min-disparity", type=int, default=None,
              help="Smallest disparity searched, px (with --num-disparities).")
@click.option("--num-disparities", type=int, default=None,
              help="Disparities searched from --min-disparity on (a multiple of 16). Without both: a range per "
                   "tile from a coarse pass of the pair.")
@overwrite_opt
@handle_errors
def disparity(left, right, output, min_disparity, num_disparities, overwrite):
    """Match LEFT and RIGHT, an already rectified pair (rows are epipolar lines), with the dense chain's
    matcher (tiled SGBM, occlusion test, sub-pixel step) and write the disparity of every LEFT pixel."""
    opts = DisparityOptions(min_disparity=min_disparity, num_disparities=num_disparities)
    result = disparity_action(left, right, output, options=opts, overwrite=overwrite)
    for line in result.summary_lines():
        echo(line)
