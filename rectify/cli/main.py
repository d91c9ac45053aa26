"""``rectify``: the click group. Subcommands live one per module and are
registered explicitly below."""

from __future__ import annotations

import click

from .. import __version__
from .options import VerbosityGroup, setup_logging, verbosity_opts


@click.group(cls=VerbosityGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="rectify")
@verbosity_opts
@click.pass_context
def cli(ctx: click.Context, verbose: int, quiet: int) -> None:
    """Rectify tilted aerial and space images: tie points, projective and
    polynomial transforms (including the cotangent four-point method),
    resampling and georeferenced GeoTIFF output."""
    ctx.obj = {"verbose": verbose, "quiet": quiet}
    setup_logging(verbose, quiet)


# --- registered subcommands (one module each) ---
from .warp import warp  # noqa: E402

cli.add_command(warp)
from .fit import fit  # noqa: E402

cli.add_command(fit)
from .match import match  # noqa: E402

cli.add_command(match)
from .demo import demo  # noqa: E402

cli.add_command(demo)
from .compare import compare  # noqa: E402

cli.add_command(compare)
from .ortho import ortho  # noqa: E402

cli.add_command(ortho)
from .mosaic import mosaic  # noqa: E402

cli.add_command(mosaic)
