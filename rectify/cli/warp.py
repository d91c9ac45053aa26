"""``rectify warp``: rectify a raster with GCPs or a saved transform into a GeoTIFF."""

from __future__ import annotations

import click

from rectify.actions.common import METHOD_NAMES
from rectify.actions.warp import GCP_PIXEL, RESAMPLING_NAMES, WarpRunOptions
from rectify.actions.warp import warp as warp_action
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress, report_opt, scheduler_opt

_D = WarpRunOptions()


@click.command(short_help="Rectify a raster into a georeferenced GeoTIFF (GCPs or transform.json).")
@click.argument("src", type=click.Path(dir_okay=False))
@click.argument("dst", type=click.Path(dir_okay=False))
@click.option("--gcps", "gcps_path", type=click.Path(dir_okay=False), default=None,
              help="GCPs: CSV (id,col,row,x,y), QGIS .points, matches CSV, GeoJSON, GeoPackage, a GeoTIFF "
                   "with embedded GCPs, orthority GCP GeoJSON (ji), ODM gcp_list.txt or Metashape markers XML "
                   "(SRC's GCPs), found by content (KIND:PATH: gcps, orthority, odm, metashape). Default: the GCPs "
                   "embedded in SRC, when it has some.")
@click.option("--gcp-pixel", type=click.Choice(list(GCP_PIXEL)), default=None,
              help="Pixel convention of GCPs embedded in a GeoTIFF: corner (GDAL's; the default) or centre "
                   "(orthority's).")
@click.option("--transform", "transform_path", type=click.Path(dir_okay=False), default=None,
              help="A transform.json written by 'rectify fit'.")
@click.option("--method", type=click.Choice(list(METHOD_NAMES)), default=_D.method, show_default=True,
              help="Model fitted to the GCPs.")
@click.option("--gcp-crs", default=None, help="CRS of the GCP (or transform) coordinates, e.g. EPSG:4326; "
              "overrides the file's '# crs=' line.")
@click.option("--dst-crs", default=None, help="Output CRS (default: the GCP CRS).")
@click.option("--resolution", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Output pixel size in output CRS units "
              "(default: estimated from the transform, as GDAL suggests).")
@click.option("--resampling", type=click.Choice(list(RESAMPLING_NAMES)), default=_D.resampling, show_default=True)
@click.option("--cog", is_flag=True, default=False, help="Write a Cloud Optimized GeoTIFF (with overviews).")
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item <DST stem>.stac.json beside DST.")
@click.option("--threads", type=click.IntRange(1, 256), default=None, help="Worker threads (default: all cores).")
@click.option("--max-pixels", type=click.FloatRange(min=1), default=_D.max_pixels, show_default=True,
              help="Refuse an output grid with more pixels than this (before any work).")
@scheduler_opt
@report_opt
@overwrite_opt
@handle_errors
def warp(src, dst, gcps_path, gcp_pixel, transform_path, method, gcp_crs, dst_crs, resolution, resampling, cog, stac,
         threads, max_pixels, scheduler, report_dir, overwrite):
    """Rectify SRC into the GeoTIFF DST.

    The transform comes from GCPs (--gcps, fitted with --method), from a
    saved transform (--transform), or, with neither, from the GCPs embedded
    in SRC. The output grid is north-up, covers the
    transformed footprint and is aligned to the resolution. Pixels outside
    the footprint are nodata (or masked / alpha 0, following the source).
    """
    if gcps_path is not None and transform_path is not None:
        raise click.UsageError("give exactly one of --gcps or --transform")
    if report_dir is not None and transform_path is not None:
        raise click.UsageError("--report needs --gcps (a saved transform has no residuals to report)")
    opts = WarpRunOptions(method=method, gcp_crs=gcp_crs, dst_crs=dst_crs, resolution=resolution,
                          resampling=resampling, cog=cog, threads=threads, max_pixels=max_pixels,
                          scheduler=scheduler, gcp_pixel=gcp_pixel, stac=stac)
    ws = Workspace(overwrite=overwrite, report_dir=report_dir)
    with progress("warping", enabled=True) as cb:
        run = warp_action(ws, src, dst, gcps_path=gcps_path, transform_path=transform_path, options=opts,
                          progress=cb)
    for line in run.summary_lines():
        echo(line)
