"""``rectify warp``: rectify a raster with GCPs or a saved transform into a GeoTIFF."""

from __future__ import annotations

import click

from ..warp import RESAMPLING_NAMES
from .options import echo, handle_errors, overwrite_opt, progress, report_opt

METHOD_NAMES = ("homography", "cotangent", "affine", "poly2", "poly3")


@click.command(short_help="Rectify a raster into a georeferenced GeoTIFF (GCPs or transform.json).")
@click.argument("src", type=click.Path(dir_okay=False))
@click.argument("dst", type=click.Path(dir_okay=False))
@click.option("--gcps", "gcps_path", type=click.Path(dir_okay=False), default=None,
              help="GCP CSV (id,col,row,x,y) or QGIS .points file.")
@click.option("--transform", "transform_path", type=click.Path(dir_okay=False), default=None,
              help="A transform.json written by 'rectify fit'.")
@click.option("--method", type=click.Choice(METHOD_NAMES), default="homography", show_default=True,
              help="Model fitted to the GCPs.")
@click.option("--gcp-crs", default=None, help="CRS of the GCP (or transform) coordinates, e.g. EPSG:4326; "
              "overrides the file's '# crs=' line.")
@click.option("--dst-crs", default=None, help="Output CRS (default: the GCP CRS).")
@click.option("--resolution", type=float, default=None, help="Output pixel size in output CRS units "
              "(default: estimated from the transform, as GDAL suggests).")
@click.option("--resampling", type=click.Choice(RESAMPLING_NAMES), default="bilinear", show_default=True)
@click.option("--cog", is_flag=True, default=False, help="Write a Cloud Optimized GeoTIFF (with overviews).")
@click.option("--threads", type=click.IntRange(1, 256), default=None, help="Worker threads (default: all cores).")
@report_opt
@overwrite_opt
@handle_errors
def warp(src, dst, gcps_path, transform_path, method, gcp_crs, dst_crs, resolution, resampling, cog, threads,
         report_dir, overwrite):
    """Rectify SRC into the GeoTIFF DST.

    The transform comes from GCPs (--gcps, fitted with --method) or from a
    saved transform (--transform). The output grid is north-up, covers the
    transformed footprint and is aligned to the resolution. Pixels outside
    the footprint are nodata (or masked / alpha 0, following the source).
    """
    import os

    # GDAL reads GDAL_CACHEMAX once, at its first block access: bound it before any pixel IO
    os.environ.setdefault("GDAL_CACHEMAX", "64")
    from ..fileutil import check_output
    from ..io import raster_info
    from ..warp import WarpOptions, georectify, rectify_with_transform, transform_file_crs, write_warp_report

    if (gcps_path is None) == (transform_path is None):
        raise click.UsageError("give exactly one of --gcps or --transform")
    if report_dir is not None and transform_path is not None:
        raise click.UsageError("--report needs --gcps (a saved transform has no residuals to report)")
    opts = WarpOptions(resampling=resampling, cog=cog, threads=threads)
    check_output(dst, overwrite=overwrite)
    info = raster_info(src)
    with progress("warping", enabled=True) as cb:
        if gcps_path is not None:
            from ..tables import read_gcps

            gcps = read_gcps(gcps_path)
            result = georectify(src, dst, gcps, method=method, gcp_crs=gcp_crs, dst_crs=dst_crs,
                                resolution=resolution, options=opts, overwrite=overwrite, progress=cb)
        else:
            from ..transforms import load_transform

            model = load_transform(transform_path)
            m_crs = gcp_crs or transform_file_crs(transform_path)
            result = rectify_with_transform(src, dst, model, model_crs=m_crs, dst_crs=dst_crs,
                                            resolution=resolution, options=opts, overwrite=overwrite, progress=cb)
    g = result.warp.grid
    if result.fit is not None:
        echo(result.fit.table.summary_line())
    echo(f"wrote {dst}: {g.width} x {g.height} px, {g.resolution[0]:.6g} units/px, CRS {result.crs or 'none'}, "
         f"{resampling}, {'COG' if cog else 'tiled GeoTIFF'}, {result.warp.seconds:.2f} s")
    if report_dir is not None:
        path = write_warp_report(report_dir, result, source_shape=(info.height, info.width),
                                 overwrite=overwrite)
        echo(f"report: {path}")
