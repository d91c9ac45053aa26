"""``rectify view``: a step's results in the browser (local server on 127.0.0.1, or a static folder)."""

from __future__ import annotations

import click

from rectify.actions.view import ViewOptions, export_view, start_view
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress


def view_options(f):  # noqa: ANN001, ANN201 (a click decorator)
    """The options of ``rectify view`` (``stereo view`` takes the same)."""
    f = overwrite_opt(f)
    f = click.option("--max-tiles", type=click.IntRange(1, 10_000_000), default=ViewOptions.max_static_tiles,
                     show_default=True, help="With --static: the most tiles written (all rasters together).")(f)
    f = click.option("--static", "static_dir", type=click.Path(file_okay=False), default=None,
                     help="Write the view as a static folder DIR (any web server can serve it) instead of serving.")(f)
    f = click.option("--images", multiple=True, type=click.Path(exists=True, file_okay=False),
                     help="Folder of a block's photos (the inputs of the step), to show them under their "
                          "points; repeatable.")(f)
    f = click.option("--no-browser", is_flag=True, default=False,
                     help="Do not open a browser; only print the address.")(f)
    f = click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True,
                     help="Port on 127.0.0.1 (0: any free port).")(f)
    return click.argument("outdir", type=click.Path(exists=True, file_okay=False))(f)


def run_view(outdir, port, no_browser, images, static_dir, max_tiles, overwrite):  # noqa: ANN001, ANN201
    """The body of ``rectify view`` and ``stereo view``."""
    opts = ViewOptions(port=port, images=tuple(images), max_static_tiles=max_tiles)
    if static_dir is not None:
        with progress("tiles", enabled=True) as cb:
            run = export_view(Workspace(overwrite=overwrite), outdir, static_dir, opts, progress=cb)
        for line in run.summary_lines():
            echo(line)
        return
    session = start_view(outdir, opts)
    for line in session.summary_lines():
        echo(line)
    if not no_browser:
        session.open_browser()
    try:
        session.serve_forever()
    except KeyboardInterrupt:
        echo("stopped")
    finally:
        session.server.server_close()


@click.command(short_help="Show a step's results in the browser: residuals on the images, tiles, figures.")
@view_options
@handle_errors
def view(outdir, port, no_browser, images, static_dir, max_tiles, overwrite):
    """Open the results in OUTDIR (of match, fit, warp, ortho, or stereo orient, run,
    block, calibrate, dense) in the browser: images and orthophotos zoomable to
    full resolution, points with residual vectors coloured by standardised
    residual, blunders marked, the block layout, the DSM as hillshade, the report
    figures. Served on 127.0.0.1 only, from OUTDIR only; --static DIR writes a
    folder any web server can serve instead."""
    run_view(outdir, port, no_browser, images, static_dir, max_tiles, overwrite)
