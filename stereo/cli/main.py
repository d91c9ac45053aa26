"""``stereo``: the click group. Subcommands are registered explicitly below."""

from __future__ import annotations

import click

from rectify.cli.options import VerbosityGroup, setup_logging, verbosity_opts

from .. import __version__
from .block import block
from .calibrate import calibrate
from .demo import demo
from .dense import dense
from .dense_rpc import dense_rpc
from .model import model
from .orient import orient
from .resect import resect
from .run import run


@click.group(cls=VerbosityGroup, context_settings={"help_option_names": ["-h", "--help"]})
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
for _command in (orient, model, resect, run, demo, calibrate, dense, dense_rpc, block):
    cli.add_command(_command)
