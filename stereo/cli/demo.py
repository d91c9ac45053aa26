"""``stereo demo``: the whole chain on a synthetic pair with known truth."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, progress
from stereo.actions.demo import demo as demo_action


@click.command(short_help="Run the whole stereo chain on a synthetic pair and compare with the truth.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="demo-output", show_default=True)
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True,
              help="Scene seed (deterministic).")
@click.option("--size", "size_px", type=click.IntRange(64, 8192), default=480, show_default=True,
              help="Photo side, pixels.")
@overwrite_opt
@handle_errors
def demo(out_dir, seed, size_px, overwrite):
    """Render a synthetic stereo pair (DEM + texture + two cameras), then match, orient
    relatively, intersect, orient to 10 control points and report the accuracy on check
    points and on every model point against the DEM."""
    with progress("demo") as cb:
        result = demo_action(out_dir, seed=seed, size_px=size_px, overwrite=overwrite, progress=cb)
    for line in result.summary_lines():
        echo(line)
