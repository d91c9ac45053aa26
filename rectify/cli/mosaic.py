"""``rectify mosaic``: one GeoTIFF/COG from several orthophotos (nearest-nadir seams, feathering)."""

from __future__ import annotations

import click

from rectify.actions.mosaic import MosaicOptions, MosaicRunOptions
from rectify.actions.mosaic import mosaic as run_mosaic
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress, scheduler_opt


@click.command(short_help="Mosaic orthophotos: nearest-nadir seamlines, feathering, one GeoTIFF or COG.")
@click.argument("orthos", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "dst", type=click.Path(dir_okay=False), required=True, help="Output GeoTIFF.")
@click.option("--resolution", type=float, default=None, help="Output pixel size (default: the finest input).")
@click.option("--feather", type=click.FloatRange(0, None), default=16.0, show_default=True,
              help="Blend width across seams, output pixels (0: hard seams).")
@click.option("--cog", is_flag=True, default=False, help="Write a Cloud Optimized GeoTIFF.")
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item <output stem>.stac.json beside the mosaic.")
@click.option("--threads", type=click.IntRange(1, 256), default=None, help="Worker threads (default: all cores).")
@scheduler_opt
@overwrite_opt
@handle_errors
def mosaic(orthos, dst, resolution, feather, cog, stac, threads, scheduler, overwrite):
    """Mosaic the orthophotos ORTHOS (one CRS) into the GeoTIFF given by -o."""

    opts = MosaicRunOptions(resolution, MosaicOptions(feather_px=feather, cog=cog, threads=threads,
                                                      scheduler=scheduler), stac=stac)
    with progress("mosaicking", enabled=True) as cb:
        run = run_mosaic(Workspace(overwrite=overwrite), list(orthos), dst, opts, progress=cb)
    for line in run.summary_lines():
        echo(line)
