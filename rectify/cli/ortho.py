"""``rectify ortho``: orthorectify an RPC or frame image with a DEM."""

from __future__ import annotations

import click

from rectify.actions.ortho import COMPRESSIONS, GCP_PIXEL, JPEG_QUALITY, OrthoOptions, OrthoRunOptions
from rectify.actions.ortho import ortho as run_ortho
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, output_opts, overwrite_opt, progress, scheduler_opt

report_opt = click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None,
                          help="Write report.html (the run's facts, GCP residuals, the relief-shift map), "
                               "report.json, ortho_report.json, residuals.csv and relief_shift.tif into this folder.")


@click.command(short_help="Orthorectify an image with a DEM (RPC or frame camera), optionally a true ortho.")
@click.argument("src", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "dst", type=click.Path(dir_okay=False), required=True, help="Output GeoTIFF.")
@click.option("--dem", "dem_path", type=click.Path(dir_okay=False), default=None,
              help="DEM GeoTIFF (any CRS and resolution; a compound CRS, e.g. EPSG:4326+3855, declares its heights). "
                   "Give --dem or --dem-height.")
@click.option("--dem-height", type=float, default=None,
              help="A constant ground height (m) when no DEM exists, in the model's heights (WGS 84 ellipsoidal for "
                   "an RPC, the exterior orientation's for a frame camera). Exclusive with --dem.")
@click.option("--rpc", "rpc", is_flag=False, flag_value="__image__", default=None,
              help="Use the image's RPC (bare --rpc) or an RPC file (_RPC.TXT, .RPB, DIMAP/DigitalGlobe XML).")
@click.option("--camera", type=click.Path(), default=None,
              help="Frame camera: camera JSON, orthority int_param.yaml, OpenCV calibration (.yml/.xml/.json), "
                   "COLMAP model (folder or cameras.txt) or Metashape cameras XML, found by content (KIND:PATH "
                   "names the kind: camera, orthority, opencv, colmap, metashape). Optional when --exterior holds "
                   "the cameras (block orientation.json, COLMAP, Metashape).")
@click.option("--camera-id", default=None,
              help="The camera of a file of several (default: the one the exterior orientation names, else the "
                   "only one).")
@click.option("--focal-setting", "focal_setting", type=float, default=None,
              help="The image's focal setting for a zoom camera (stereo calibrate --zoom), in the unit of its "
                   "calibration (EXIF focal length mm). Default: the image's EXIF FocalLength.")
@click.option("--exterior", type=click.Path(), default=None,
              help="Exterior orientation: EO JSON ('stereo resect'), a block's orientation.json or poses.csv "
                   "('stereo block'), orthority ext_param.geojson or xyz_opk/lla_rpy CSV (+ .prj), COLMAP model "
                   "or Metashape cameras XML, found by content (KIND:PATH: exterior, orthority, orthority-csv, "
                   "colmap, metashape). The image of a file of several by --image-id.")
@click.option("--image-id", default=None,
              help="Image of a file of several orientations or GCP images (its name or file stem; default: SRC's "
                   "file name).")
@click.option("--eo-crs", default=None, help="CRS of the exterior orientation (overrides the file's 'crs').")
@click.option("--gcps", type=click.Path(dir_okay=False), default=None,
              help="GCP file: refines an RPC (bias compensation) or checks a frame model. Any GCP file rectify "
                   "reads, orthority GCP GeoJSON (ji), ODM gcp_list.txt or Metashape markers XML (the image's "
                   "GCPs; KIND:PATH: gcps, orthority, odm, metashape).")
@click.option("--gcp-pixel", type=click.Choice(list(GCP_PIXEL)), default=None,
              help="Pixel convention of GCPs embedded in a GeoTIFF: corner (GDAL's; the default) or centre "
                   "(orthority's).")
@click.option("--refinement", type=click.Choice(["shift", "drift", "affine"]), default="shift", show_default=True,
              help="RPC bias model fitted to the GCPs.")
@click.option("--dst-crs", default=None, help="Output CRS (default: the EO CRS, or UTM for RPC images).")
@click.option("--resolution", type=float, default=None, help="Output pixel size in output CRS units.")
@click.option("--undulation", type=float, default=None,
              help="Geoid undulation N (m) added to the DEM heights (h = H + N; RPCs need ellipsoidal heights). "
                   "Default: the vertical datum the DEM's CRS declares, else none.")
@click.option("--geoid", default=None, help="Geoid of the DEM heights, e.g. EPSG:5773 (needs the PROJ grid).")
@click.option("--gcp-heights", default=None,
              help="Datum of the GCP heights: 'ellipsoidal', 'dem' (the DEM file's) or a vertical CRS (EPSG:5773). "
                   "Default: the GCP file's CRS; else the DEM's when its heights are not converted.")
@click.option("--resampling", type=click.Choice(["nearest", "bilinear", "cubic"]), default="bilinear",
              show_default=True)
@click.option("--true-ortho", is_flag=True, default=False,
              help="Occluded ground gets nodata; adds a visibility band (0 outside, 1 occluded, 2 visible).")
@output_opts(COMPRESSIONS, JPEG_QUALITY, jpeg_note=', not with --true-ortho')
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item <output stem>.stac.json beside the orthophoto.")
@click.option("--threads", type=click.IntRange(1, 256), default=None, help="Worker threads (default: all cores).")
@scheduler_opt
@report_opt
@overwrite_opt
@handle_errors
def ortho(src, dst, dem_path, dem_height, rpc, camera, camera_id, focal_setting, exterior, image_id, eo_crs, gcps,
          gcp_pixel, refinement, dst_crs, resolution, undulation, geoid, gcp_heights, resampling, true_ortho, cog,
          compress, jpeg_quality, stac, threads, scheduler, report_dir, overwrite):
    """Orthorectify SRC over a DEM (or a constant height) into the GeoTIFF given by -o."""

    engine = OrthoOptions(resampling=resampling, cog=cog, threads=threads, true_ortho=true_ortho, scheduler=scheduler,
                          compress=compress, quality=jpeg_quality)
    opts = OrthoRunOptions(eo_crs=eo_crs, refinement=refinement, dst_crs=dst_crs, resolution=resolution,
                           undulation=undulation, geoid=geoid, gcp_heights=gcp_heights, image_id=image_id,
                           camera_id=camera_id, focal_setting=focal_setting, gcp_pixel=gcp_pixel, stac=stac,
                           engine=engine, dem_height=dem_height)
    rpc_arg = True if rpc == "__image__" else (rpc or False)
    ws = Workspace(overwrite=overwrite, report_dir=report_dir)
    with progress("orthorectifying", enabled=True) as cb:
        run = run_ortho(ws, src, dst, dem_path, rpc=rpc_arg, camera=camera, exterior=exterior, gcps=gcps,
                        options=opts, progress=cb)
    for line in run.summary_lines():
        echo(line)
