"""``stereo dense-rpc``: DSM and point cloud of an RPC (pushbroom satellite) pair by local epipolar tiles; with
three or more images, the RPC block adjustment, the pairs of the first image and one fused DSM."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt
from stereo.actions.dense_rpc import RpcDenseOptions, RpcDenseResult, run_dense_rpc
from stereo.actions.dense_rpc_multi import MultiRpcOptions, MultiRpcResult, run_dense_rpc_multi

_D = RpcDenseOptions()
_M = MultiRpcOptions()


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


@click.command("dense-rpc", short_help="Dense matching of RPC satellite images: local epipolar tiles, (fused) DSM.")
@click.argument("images", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (dsm.tif, points, dense_rpc.json, item.stac.json; report/ with --reference-dem).")
@click.option("--roi", callback=_roi, default=None,
              help="Region of interest of the first image: x,y,width,height (pixels).")
@click.option("--tile", type=int, default=_D.tile, show_default=True,
              help="Nominal tile side, left pixels: the ROI is cut into round(width / tile) x round(height / tile) "
                   "equal tiles (a 700 px ROI gives two tiles of 350 px with 300).")
@click.option("--dsm-cell", type=float, default=None, help="DSM cell, metres (default: the ground pixel).")
@click.option("--fill-holes", type=click.IntRange(min=0), default=None,
              help="Interpolate DSM holes of at most this many cells (0: off). Two images: default 0 (filled cells "
                   f"flagged in band 3). Three or more: the fused DSM's holes, default {_M.fill_holes} cells (filled "
                   "cells: sigma_Z nodata, count 0, provenance -1), and with a value given each pair's DSM too.")
@click.option("--cloud", type=click.Choice(["las", "laz", "ply", "none"]), default=_D.cloud_format,
              show_default=True, help="Point cloud format.")
@click.option("--reference-dem", type=click.Path(dir_okay=False), default=None,
              help="Compare the DSM with this DEM (RMSE, NMAD, blunders; report/ pictures). Its heights are taken "
                   "as they are: the DSM's are above the WGS 84 ellipsoid.")
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item of the DSM and the point cloud, OUTDIR/item.stac.json (two images).")
@click.option("--adjust/--no-adjust", default=_M.adjust, show_default=True,
              help="Three or more images: adjust the RPCs (image-space biases, tie points of every overlapping "
                   "pair) before matching.")
@click.option("--bias-model", type=click.Choice(["shift", "affine"]), default=_M.bias_model, show_default=True,
              help="Three or more images: the adjustment's bias model per image.")
@click.option("--min-angle", type=float, default=_M.min_angle_deg, show_default=True,
              help="Three or more images: the least intersection angle of a pair at the scene centre, degrees.")
@click.option("--max-angle", type=float, default=_M.max_angle_deg, show_default=True,
              help="Three or more images: the largest intersection angle of a pair, degrees.")
@click.option("--min-overlap", type=float, default=_M.min_overlap, show_default=True,
              help="Three or more images: the least share of the ROI the other image of a pair must see.")
@click.option("--gcps", type=click.Path(dir_okay=False), default=None,
              help="Three or more images: GCP CSV of the adjustment (id,image,col,row,lon,lat,h[,sigma_xy,sigma_h,"
                   "sigma]); without GCPs the adjustment fixes the relative pointing only.")
@overwrite_opt
@handle_errors
def dense_rpc(images, out_dir, roi, tile, dsm_cell, fill_holes, cloud, reference_dem, stac, adjust, bias_model,
              min_angle, max_angle, min_overlap, gcps, overwrite):
    """Match IMAGES (two or more images with RPCs) tile by tile after local epipolar resampling by affine
    camera approximation, and write the DSM (UTM, ellipsoidal heights).

    Two images: their DSM and point cloud. Three or more: the RPCs are adjusted (unless --no-adjust),
    the first image is paired with every other image whose intersection angle lies in
    --min-angle..--max-angle, and the pairs' DSMs are fused into one (bands: height, sigma_Z, count,
    provenance)."""
    if len(images) < 2:
        raise click.UsageError(f"dense-rpc needs at least two images; got {len(images)}")
    opts = RpcDenseOptions(tile=tile, dsm_cell=dsm_cell, fill_holes=fill_holes or 0, cloud_format=cloud,
                           reference_dem=reference_dem, stac=stac)
    result: RpcDenseResult | MultiRpcResult
    if len(images) == 2:
        if gcps is not None:
            raise click.UsageError("--gcps needs three or more images (two images: rectify rpc-adjust first)")
        result = run_dense_rpc(images[0], images[1], out_dir, roi=roi, options=opts, overwrite=overwrite)
    else:
        mopts = MultiRpcOptions(pair=RpcDenseOptions(tile=tile, dsm_cell=dsm_cell, fill_holes=fill_holes or 0,
                                                     cloud_format="none", stac=False),
                                fill_holes=_M.fill_holes if fill_holes is None else fill_holes,
                                adjust=adjust, bias_model=bias_model, min_angle_deg=min_angle,
                                max_angle_deg=max_angle, min_overlap=min_overlap, reference_dem=reference_dem,
                                gcps=gcps)
        result = run_dense_rpc_multi(images, out_dir, roi=roi, options=mopts, overwrite=overwrite)
    for line in result.summary_lines():
        echo(line)
