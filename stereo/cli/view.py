"""``stereo view``: the same view as ``rectify view`` (a step's results in the browser)."""

from __future__ import annotations

import click

from rectify.cli.options import handle_errors
from rectify.cli.view import run_view, view_options


@click.command(short_help="Show a step's results in the browser (as rectify view).")
@view_options
@handle_errors
def view(outdir, port, no_browser, images, static_dir, max_tiles, overwrite):
    """Open the results in OUTDIR (of stereo orient, run, block, calibrate, dense,
    or any rectify step) in the browser: the photos with their points and residual
    vectors (give their folder with --images), the block layout, the DSM as
    hillshade, the report figures. Served on 127.0.0.1 only; --static DIR writes a
    static folder instead. Same as `rectify view`."""
    run_view(outdir, port, no_browser, images, static_dir, max_tiles, overwrite)
