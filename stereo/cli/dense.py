"""``stereo dense``: normal case, dense matching, point cloud and DSM of an oriented pair."""

from __future__ import annotations

import dataclasses

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, scheduler_opt
from stereo.actions.dense import DenseOptions, run_dense
from stereo.actions.orient import parse_focal_settings
from stereo.dense.dsm import STATISTICS

_D = DenseOptions()


@click.command(short_help="Dense matching of an oriented pair: normal case, disparity, point cloud, DSM.")
@click.argument("orientation", type=click.Path(dir_okay=False))
@click.argument("left", type=click.Path(dir_okay=False))
@click.argument("right", type=click.Path(dir_okay=False))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (normal-case photos, disparity, confidence, points, dsm.tif, dense.json, report/).")
@click.option("--right-orientation", type=click.Path(dir_okay=False), default=None,
              help="Right exterior orientation JSON, when ORIENTATION is the left one's.")
@click.option("--left-id", default=None,
              help="With a block orientation (orientation.json of `stereo block`): LEFT's image id in it "
                   "[default: the block image named as LEFT's file, with or without extension].")
@click.option("--right-id", default=None, help="With a block orientation: RIGHT's image id in it [default: as "
                                               "--left-id, from RIGHT's file name].")
@click.option("--camera", type=click.Path(), default=None,
              help="Camera (default: the camera stored in ORIENTATION): camera JSON, orthority int_param, OpenCV "
                   "calibration, COLMAP model or Metashape cameras XML, found by content (KIND:PATH: camera, "
                   "orthority, opencv, colmap, metashape).")
@click.option("--focal-setting", "focal_setting", default=None,
              help="With a zoom camera (--camera of `stereo calibrate --zoom`): the photos' focal setting, Z (both) "
                   "or ZLEFT,ZRIGHT, in the unit of the zoom calibration [default: each photo's EXIF FocalLength].")
@click.option("--matches", type=click.Path(dir_okay=False), default=None,
              help="Tie points CSV (default: match the photos).")
@click.option("--control", type=click.Path(dir_okay=False), default=None,
              help="Stereo control CSV: products in the control's ground frame.")
@click.option("--cloud", type=click.Choice(["las", "laz", "copc", "ply", "none"]), default=_D.cloud_format,
              show_default=True, help="Point cloud format (copc: points.copc.laz, needs copclib). LAS/LAZ/COPC carry "
              "sigma_z, the height standard error of each point.")
@click.option("--dsm-cell", type=float, default=None, help="DSM cell (ground units; default the ground pixel).")
@click.option("--dsm-stat", type=click.Choice(list(STATISTICS)), default=_D.dsm_statistic, show_default=True,
              help="Cell statistic.")
@click.option("--fill-holes", type=int, default=0, show_default=True,
              help="Interpolate DSM holes of at most this many cells (flagged in band 3).")
@click.option("--min-confidence", type=float, default=0.0, show_default=True,
              help="Leave out points of lower matching confidence (0..1).")
@click.option("--reference-dem", type=click.Path(dir_okay=False), default=None,
              help="Compare the DSM with this DEM (RMSE, NMAD, blunders, histogram).")
@click.option("--despike", type=float, default=_D.despike_cells, show_default=True,
              help="Drop DSM cells farther than this many cell sides from their 5 x 5 median (0: off).")
@click.option("--tile", type=int, default=_D.matching.tile, show_default=True,
              help="Core side of the matcher's tiles, pixels (a multiple of 16, at least 64; each tile is matched "
                   "with a 48 px overlap).")
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item of the DSM and the point cloud, OUTDIR/item.stac.json.")
@scheduler_opt
@overwrite_opt
@handle_errors
def dense(orientation, left, right, out_dir, right_orientation, left_id, right_id, camera, focal_setting, matches,
          control, cloud, dsm_cell, dsm_stat, fill_holes, min_confidence, reference_dem, despike, tile, stac, scheduler,
          overwrite):
    """Resample LEFT and RIGHT into the normal case from ORIENTATION (ro.json of `stereo orient`, the
    left exterior orientation with --right-orientation, or the orientation.json of `stereo block`),
    match them densely and write the point cloud and the DSM."""
    opts = DenseOptions(matching=dataclasses.replace(_D.matching, tile=tile), cloud_format=cloud, dsm_cell=dsm_cell,
                        dsm_statistic=dsm_stat, fill_holes=fill_holes, min_confidence=min_confidence,
                        reference_dem=reference_dem, despike_cells=despike, scheduler=scheduler, stac=stac)
    result = run_dense(orientation, left, right, out_dir, right_orientation=right_orientation, camera=camera,
                       matches=matches, control=control, options=opts, overwrite=overwrite, left_id=left_id,
                       right_id=right_id, focal_settings=parse_focal_settings(focal_setting))
    for line in result.summary_lines():
        echo(line)
