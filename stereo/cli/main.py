"""``stereo``: the click group. Subcommands are registered explicitly below."""

from __future__ import annotations

import click

from rectify.cli.options import setup_logging, verbosity_opts

from .. import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="stereo")
@verbosity_opts
@click.pass_context
def cli(ctx: click.Context, verbose: int, quiet: int) -> None:
    """Stereo photogrammetry: relative orientation (three systems of
    elements), intersection, absolute orientation, resection and stereo
    models with full precision reports."""
    ctx.obj = {"verbose": verbose, "quiet": quiet}
    setup_logging(verbose, quiet)


# --- registered subcommands (one module each) ---
from .orient import orient  # noqa: E402

cli.add_command(orient)
from .model import model  # noqa: E402

cli.add_command(model)
from .resect import resect  # noqa: E402

cli.add_command(resect)
from .run import run  # noqa: E402

cli.add_command(run)
from .demo import demo  # noqa: E402

cli.add_command(demo)
from .calibrate import calibrate

cli.add_command(calibrate)
from .dense import dense

cli.add_command(dense)
