"""``rectify fit``: fit a planar transform to GCPs and save it as JSON."""

from __future__ import annotations

import click

from rectify.actions.common import METHOD_NAMES
from rectify.actions.fit import GCP_PIXEL, FitOptions
from rectify.actions.fit import fit as fit_action
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt

_D = FitOptions()


@click.command(short_help="Fit a transform (homography, cotangent, affine, poly2, poly3) to GCPs.")
@click.argument("gcps_path", metavar="GCPS", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output", type=click.Path(dir_okay=False), required=True,
              help="Transform JSON to write.")
@click.option("--method", type=click.Choice(list(METHOD_NAMES)), default=_D.method, show_default=True,
              help="Model: 8-parameter homography, Kushtin's cotangent four-point method, affine, "
                   "or polynomial of order 2/3.")
@click.option("--max-rows", type=click.IntRange(0), default=_D.max_rows, show_default=True,
              help="Residual rows printed.")
@click.option("--image", type=click.Path(dir_okay=False), default=None,
              help="The source image (only its size is read): judge the GCP geometry over it (convex hull share, "
                   "predicted error at the corners); its file name picks the GCPs of a file of several images. "
                   "Default: the GCP file when it is a GeoTIFF.")
@click.option("--gcp-pixel", type=click.Choice(list(GCP_PIXEL)), default=None,
              help="Pixel convention of GCPs embedded in a GeoTIFF: corner (GDAL's; the default) or centre "
                   "(orthority's).")
@report_opt
@overwrite_opt
@handle_errors
def fit(gcps_path, output, method, max_rows, image, gcp_pixel, report_dir, overwrite):
    """Fit a transform from source pixels to target coordinates.

    GCPS is a CSV (id,col,row,x,y[,check]), a QGIS .points file, a matches CSV
    (fits the right image onto the left), GeoJSON, GeoPackage, a GeoTIFF
    with embedded GCPs, orthority's GCP GeoJSON (ji), ODM's gcp_list.txt or a
    Metashape markers XML (the GCPs of --image), found by content; KIND:GCPS
    names the kind (gcps, orthority, odm, metashape; see docs/formats.md). Rows with
    check = 1 are withheld from the fit and reported as check points. Prints
    the per-point residuals dx, dy, |v| (target units) and the RMSE.
    """
    ws = Workspace(overwrite=overwrite, inputs=[image], report_dir=report_dir)
    run = fit_action(ws, gcps_path, output, FitOptions(method=method, max_rows=max_rows, image=image,
                                                       gcp_pixel=gcp_pixel))
    for line in run.summary_lines():
        echo(line)
