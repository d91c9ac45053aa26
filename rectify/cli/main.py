"""``rectify``: the click group. Subcommands live one per module, are registered by name below and
imported when they run."""

from __future__ import annotations

import click

from rectify import __version__
from rectify.cli.options import VerbosityGroup, defer_import, setup_logging, verbosity_opts

defer_import("boto3")  # rasterio imports it for AWS sessions; loaded only if one is used


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


# --- registered subcommands (one module each, imported when run) ---
for _name in ("warp", "fit", "match", "demo", "compare", "ortho", "mosaic", "view"):
    cli.add_lazy(_name, f"rectify.cli.{_name}:{_name}")
cli.add_lazy("rpc-adjust", "rectify.cli.rpc_adjust:rpc_adjust")
