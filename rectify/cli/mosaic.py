"""``rectify mosaic``: one GeoTIFF/COG from several orthophotos (nearest-nadir or least-transformed seams,
averaging, radiometric balancing, feathering, a provenance raster)."""

from __future__ import annotations

import click

from rectify.actions.mosaic import COMPRESSIONS, JPEG_QUALITY, MosaicOptions, MosaicRunOptions
from rectify.actions.mosaic import mosaic as run_mosaic
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, output_opts, overwrite_opt, progress, scheduler_opt


@click.command(short_help="Mosaic orthophotos: seamlines (nadir or least-transformed), balancing, feathering.")
@click.argument("orthos", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "dst", type=click.Path(dir_okay=False), required=True, help="Output GeoTIFF.")
@click.option("--resolution", type=float, default=None, help="Output pixel size (default: the finest input).")
@click.option("--dsm", type=click.Path(dir_okay=False), default=None,
              help="DSM/DEM of the surface (the orthophotos' heights): rays and normals for --seams normal.")
@click.option("--seams", type=click.Choice(["nadir", "normal"]), default=None,
              help="nadir: nearest nadir point; normal: the least-transformed image per zone (nadir and "
                   "surface-normal angles; needs --dsm and projection centres). Default: normal with --dsm.")
@click.option("--normal-weight", type=click.FloatRange(0, 1), default=0.5, show_default=True,
              help="Weight of the angle to the surface normal against the nadir angle (--seams normal).")
@click.option("--zone", "zone_px", type=click.IntRange(1, 4096), default=8, show_default=True,
              help="Zone size of the seam choice, output pixels.")
@click.option("--smooth", type=click.IntRange(0, 64), default=2, show_default=True,
              help="Smoothing of the zone choice, zones: Gaussian sigma of the criterion and majority filter "
                   "radius (0: the raw choice).")
@click.option("--blend", type=click.Choice(["seams", "average"]), default="seams", show_default=True,
              help="seams: one image per pixel, feathered; average: the mean of every valid image.")
@click.option("--balance", type=click.Choice(["none", "mean", "reference"]), default="none", show_default=True,
              help="Radiometric balancing (gain and offset per image and band from the overlaps): mean gain 1 "
                   "and offset 0, or the first orthophoto kept as reference.")
@click.option("--feather", type=click.FloatRange(0, None), default=16.0, show_default=True,
              help="Blend width across seams, output pixels (0: hard seams).")
@click.option("--provenance", is_flag=True, default=False,
              help="Also write <output stem>.source.tif: the 1-based input number of every pixel (0: none).")
@output_opts(COMPRESSIONS, JPEG_QUALITY)
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item <output stem>.stac.json beside the mosaic.")
@click.option("--threads", type=click.IntRange(1, 256), default=None, help="Worker threads (default: all cores).")
@scheduler_opt
@overwrite_opt
@handle_errors
def mosaic(orthos, dst, resolution, dsm, seams, normal_weight, zone_px, smooth, blend, balance, feather, provenance,
           cog, compress, jpeg_quality, stac, threads, scheduler, overwrite):
    """Mosaic the orthophotos ORTHOS (one CRS) into the GeoTIFF given by -o."""

    opts = MosaicRunOptions(resolution, MosaicOptions(feather_px=feather, cog=cog, compress=compress,
                                                      quality=jpeg_quality, threads=threads,
                                                      scheduler=scheduler, seams=seams, dsm=dsm,
                                                      normal_weight=normal_weight, zone_px=zone_px, smooth=smooth,
                                                      blend=blend, balance=balance),
                            stac=stac, provenance=provenance)
    with progress("mosaicking", enabled=True) as cb:
        run = run_mosaic(Workspace(overwrite=overwrite), list(orthos), dst, opts, progress=cb)
    for line in run.summary_lines():
        echo(line)
