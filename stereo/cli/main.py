"""``stereo``: the click group. Subcommands are registered by name below and imported when they run."""

from __future__ import annotations

import click

from rectify.cli.options import VerbosityGroup, defer_import, setup_logging, verbosity_opts
from stereo import __version__

defer_import("boto3")  # rasterio imports it for AWS sessions; loaded only if one is used


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


# --- registered subcommands (one module each, imported when run) ---
for _name, _module in (("orient", "orient"), ("model", "model"), ("resect", "resect"), ("run", "run"),
                       ("demo", "demo"), ("calibrate", "calibrate"), ("dense", "dense"),
                       ("dense-rpc", "dense_rpc"), ("disparity", "disparity"), ("block", "block"),
                       ("view", "view"), ("sat-intersect", "sat_intersect"), ("surface", "surface")):
    cli.add_lazy(_name, f"stereo.cli.{_module}:{_module}")
