"""``stereo dense-rpc``: DSM and point cloud of an RPC (pushbroom satellite) pair by local epipolar tiles."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt
from stereo.actions.dense_rpc import RpcDenseOptions, run_dense_rpc

_D = RpcDenseOptions()


def _roi(ctx, param, value):
    if value is None:
        return None
    try:
        parts = [int(v) for v in value.split(",")]
    except ValueError:
        raise click.BadParameter(f"expected x,y,width,height (integers); got {value!r}") from None
    if len(parts) != 4:
        raise click.BadParameter(f"expected x,y,width,height (four integers); got {value!r}")
    return tuple(parts)


@click.command("dense-rpc", short_help="Dense matching of an RPC satellite pair: local epipolar tiles, DSM.")
@click.argument("left", type=click.Path(dir_okay=False))
@click.argument("right", type=click.Path(dir_okay=False))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (dsm.tif, points, dense_rpc.json, item.stac.json; report/ with --reference-dem).")
@click.option("--roi", callback=_roi, default=None, help="Region of interest of LEFT: x,y,width,height (pixels).")
@click.option("--tile", type=int, default=_D.tile, show_default=True,
              help="Nominal tile side, left pixels: the ROI is cut into round(width / tile) x round(height / tile) "
                   "equal tiles (a 700 px ROI gives two tiles of 350 px with 300).")
@click.option("--dsm-cell", type=float, default=None, help="DSM cell, metres (default: the ground pixel).")
@click.option("--fill-holes", type=int, default=0, show_default=True,
              help="Interpolate DSM holes of at most this many cells (flagged in band 3).")
@click.option("--cloud", type=click.Choice(["las", "laz", "ply", "none"]), default=_D.cloud_format,
              show_default=True, help="Point cloud format.")
@click.option("--reference-dem", type=click.Path(dir_okay=False), default=None,
              help="Compare the DSM with this DEM (RMSE, NMAD, blunders; report/ pictures). Its heights are taken "
                   "as they are: the DSM's are above the WGS 84 ellipsoid.")
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item of the DSM and the point cloud, OUTDIR/item.stac.json.")
@overwrite_opt
@handle_errors
def dense_rpc(left, right, out_dir, roi, tile, dsm_cell, fill_holes, cloud, reference_dem, stac, overwrite):
    """Match LEFT and RIGHT (images with RPCs) tile by tile after local epipolar resampling by affine
    camera approximation, and write the DSM (UTM, ellipsoidal heights) and the point cloud."""
    opts = RpcDenseOptions(tile=tile, dsm_cell=dsm_cell, fill_holes=fill_holes, cloud_format=cloud,
                           reference_dem=reference_dem, stac=stac)
    result = run_dense_rpc(left, right, out_dir, roi=roi, options=opts, overwrite=overwrite)
    for line in result.summary_lines():
        echo(line)
