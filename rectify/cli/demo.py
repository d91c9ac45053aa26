"""``rectify demo``: the embedded Landsat scene through a tilted frame and back."""

from __future__ import annotations

import click

from rectify.actions.demo import demo as demo_action
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress


@click.command(short_help="Rectify a simulated tilted frame of the embedded Landsat scene.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="demo-output", show_default=True,
              help="Folder for the outputs and the report.")
@overwrite_opt
@handle_errors
def demo(out_dir, overwrite):
    """Warp the embedded Landsat GeoTIFF into a tilted frame with a known
    homography, pick GCPs, rectify it back and report the error against the truth."""
    with progress("rectifying") as cb:
        r = demo_action(Workspace(out_dir, overwrite=overwrite), progress=cb)
    for line in r.summary_lines():
        echo(line)
