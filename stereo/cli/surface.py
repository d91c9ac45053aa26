"""``stereo surface``: a block's orientation -> one fused DSM (sigma_Z, count, provenance), orthomosaic, point cloud."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, scheduler_opt
from rectify.raster.engine import COMPRESSIONS
from rectify.raster.mosaic import BALANCES
from stereo.actions.surface import CLOUD_FORMATS, ORIENTATION_SIGMA, SurfaceOptions, run_surface

_D = SurfaceOptions()


@click.command(short_help="One DSM from a block's orientation: stereo pairs, dense matching, robust fusion, sigma_Z.")
@click.argument("orientation", type=click.Path())
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (dsm.tif: height, sigma_Z, count, provenance; pairs.json; ortho.tif and "
                   "ortho.source.tif; points.laz, .las or .copc.laz).")
@click.option("--images", type=click.Path(file_okay=False), default=None,
              help="Folder of the images named in the orientation [default: the orientation's folder].")
@click.option("--camera", type=click.Path(), default=None,
              help="Camera file for another tool's pose file that holds no cameras (orthority int_param, "
                   "camera JSON, OpenCV, COLMAP, Metashape; KIND:PATH names a kind).")
@click.option("--cell", type=float, default=None,
              help="DSM cell, ground units [default: the ground pixel, 2 significant digits; at least a tenth of it].")
@click.option("--ground-z", type=float, default=None,
              help="Mean terrain height [default: the median height of the block's points.csv, else of "
                   "--reference-dem under the images].")
@click.option("--relief", type=float, default=None,
              help="Height range about --ground-z for the disparity search [default: the block points' range plus a "
                   "tenth of the flying height].")
@click.option("--min-overlap", type=float, default=_D.min_overlap, show_default=True,
              help="Smallest footprint overlap of a pair (share of the smaller footprint).")
@click.option("--base-height", nargs=2, type=float, default=(_D.min_base_height, _D.max_base_height),
              show_default=True, help="Range of the pairs' base-to-height ratio.")
@click.option("--angle", nargs=2, type=float, default=(_D.min_angle_deg, _D.max_angle_deg), show_default=True,
              help="Range of the pairs' intersection angle, degrees.")
@click.option("--pairs-per-area", type=int, default=_D.pairs_per_area, show_default=True,
              help="Pairs kept per area (an 8 x 8 grid over the block), best first.")
@click.option("--k-sigma", type=float, default=_D.k_sigma, show_default=True,
              help="Pair heights farther than this many sigma from the others are rejected.")
@click.option("--reference-dem", type=click.Path(dir_okay=False), default=None,
              help="Compare the DSM with this DEM (RMSE, NMAD, coverage; in pairs.json and the summary).")
@click.option("--orientation-sigma", type=click.Choice(list(ORIENTATION_SIGMA)), default=_D.orientation_sigma,
              show_default=True,
              help="The orientation's share of sigma_Z: the block points' height standard errors (points.csv), the "
                   "pose standard errors taken as independent (poses), none; auto: points, else poses, else none.")
@click.option("--check", type=click.Path(dir_okay=False), default=None,
              help="Check points (CSV with id,x,y,z; the block control CSV does): the DSM's vertical accuracy "
                   "statement (RMSE_z with its interval, LE90, ASPRS 2023).")
@click.option("--ortho/--no-ortho", default=_D.ortho, show_default=True,
              help="Write the true orthomosaic ortho.tif over the fused DSM (COG; seams of the least-transformed "
                   "image).")
@click.option("--keep-orthophotos", is_flag=True, default=False,
              help="Keep every image's true orthophoto as ortho_<image>.tif.")
@click.option("--ortho-compress", type=click.Choice(list(COMPRESSIONS)), default=_D.ortho_compress,
              show_default=True, help="Compression of ortho.tif (jpeg: JPEG-in-TIFF with a mask).")
@click.option("--balance", type=click.Choice(list(BALANCES)), default=_D.balance, show_default=True,
              help="Radiometric balancing of the orthomosaic (as rectify mosaic --balance).")
@click.option("--feather", "feather_px", type=click.FloatRange(0, 4096), default=_D.feather_px, show_default=True,
              help="Feathering width of the orthomosaic's seams, output pixels.")
@click.option("--cloud/--no-cloud", default=_D.cloud, show_default=True,
              help="Write the point cloud: one point per DSM cell with sigma_z, pair and count.")
@click.option("--cloud-format", type=click.Choice(list(CLOUD_FORMATS)), default=_D.cloud_format, show_default=True,
              help="The cloud's file: laz = points.laz (points.las without a LAZ backend), las = points.las, "
                   "copc = points.copc.laz (Cloud Optimized Point Cloud; needs copclib).")
@click.option("--cloud-colors/--no-cloud-colors", default=_D.cloud_colors, show_default=True,
              help="The cloud's RGB: from the orthomosaic (nearest pixel), else from the left image of each point's "
                   "pair (bilinear).")
@scheduler_opt
@overwrite_opt
@handle_errors
def surface(orientation, out_dir, images, camera, cell, ground_z, relief, min_overlap, base_height, angle,
            pairs_per_area, k_sigma, reference_dem, orientation_sigma, check, ortho, keep_orthophotos, ortho_compress,
            balance, feather_px, cloud, cloud_format, cloud_colors, scheduler, overwrite):
    """Fuse the dense surfaces of a block's stereo pairs into one DSM, then the true orthomosaic over it
    and the point cloud of it. ORIENTATION is the output folder of
    `stereo block` (its orientation.json), a block orientation JSON, or another tool's poses (orthority
    ext_param or CSV, COLMAP model, Metashape XML, OpenSfM/ODM reconstruction.json, pose CSV; with --camera
    when they hold no cameras); the images are found by the names it records, in --images."""
    opts = SurfaceOptions(images=images, camera=camera, cell=cell, ground_z=ground_z, relief=relief,
                          min_overlap=min_overlap,
                          min_base_height=base_height[0], max_base_height=base_height[1], min_angle_deg=angle[0],
                          max_angle_deg=angle[1], pairs_per_area=pairs_per_area, k_sigma=k_sigma,
                          reference_dem=reference_dem, orientation_sigma=orientation_sigma,
                          scheduler=scheduler, check=check, ortho=ortho, keep_orthophotos=keep_orthophotos,
                          ortho_compress=ortho_compress, balance=balance, feather_px=feather_px, cloud=cloud,
                          cloud_format=cloud_format, cloud_colors=cloud_colors)
    result = run_surface(orientation, out_dir, options=opts, overwrite=overwrite)
    for line in result.summary_lines():
        echo(line)
