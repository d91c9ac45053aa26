"""``stereo block``: block triangulation (tie points, independent models or known poses, bundle adjustment)."""

from __future__ import annotations

import math

import click

from rectify.cli.options import echo, handle_errors, matcher_opts, overwrite_opt, progress
from rectify.geometry.mestimate import M_ALGORITHMS, NEWTON_METHODS
from rectify.geometry.robust import ROBUST_METHODS
from stereo.actions.block import FRAME_KINDS, BlockExports, BlockOptions, run_block
from stereo.actions.block_models import ModelMethodOptions
from stereo.actions.block_projective import ProjectiveBlockOptions, run_block_projective
from stereo.actions.block_surface import CLOUD_FORMATS, plan_block_surface, refuse_zoom_settings, run_block_surface
from stereo.actions.common import matcher_config
from stereo.block.bundle.adjust import INTERIOR_NAMES, BundleOptions
from stereo.block.bundle.robust import ROBUST_SCALES
from stereo.block.bundle.systematic import BORESIGHT_MODES, DRIFT_MODES
from stereo.block.projective import BLOCK_METHODS
from stereo.block.projective_bundle import DEFAULT_CALIBRATE
from stereo.features.tracks import BLOCK_MATCHER, PAIR_STRATEGIES, BlockMatchOptions

_B = BundleOptions()
_O = BlockOptions()
#: interior elements estimated by --self-calibrate without --calibrate
DEFAULT_SELF_CALIBRATION = ("f", "x0", "y0", "k1", "k2", "p1", "p2")


class Floats(click.ParamType):
    """One number (used for all three) or three comma-separated numbers, each > 0."""

    name = "V|VX,VY,VZ"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        parts = [s.strip() for s in str(value).split(",")]
        try:
            nums = [float(s) for s in parts]
        except ValueError:
            self.fail(f"{value!r} is not one number or three comma-separated numbers", param, ctx)
        if len(nums) == 1:
            nums = nums * 3
        if len(nums) != 3 or not all(math.isfinite(v) and v > 0 for v in nums):
            self.fail(f"{value!r} must be one number or three comma-separated numbers, each > 0", param, ctx)
        return tuple(nums)


class Triple(click.ParamType):
    """Three comma-separated finite numbers (any sign)."""

    name = "A,B,C"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        try:
            nums = tuple(float(s) for s in str(value).split(","))
        except ValueError:
            self.fail(f"{value!r} is not three comma-separated numbers", param, ctx)
        if len(nums) != 3 or not all(math.isfinite(v) for v in nums):
            self.fail(f"{value!r} must be three comma-separated finite numbers", param, ctx)
        return nums


def _radians(deg: tuple[float, float, float]) -> tuple[float, float, float]:
    return (math.radians(deg[0]), math.radians(deg[1]), math.radians(deg[2]))


def _ids(text: str) -> tuple[str, ...]:
    return tuple(s.strip() for s in text.split(",") if s.strip())


@click.command(short_help="Block triangulation: tie points, independent models, bundle adjustment with GNSS/INS.")
@click.argument("images", nargs=-1, required=False, type=click.Path(exists=True, dir_okay=False))
@click.option("--camera", "camera_path", type=click.Path(), default=None,
              help="Camera file: camera JSON, orthority int_param (cameras by id), OpenCV calibration, COLMAP model "
                   "or Metashape cameras XML, found by content (KIND:PATH: camera, orthority, opencv, colmap, "
                   "metashape). Optional when --poses holds the cameras (OpenSfM, COLMAP, Metashape).")
@click.option("--focal-settings", "focal_settings", type=click.Path(dir_okay=False), default=None,
              help="With a zoom camera (--camera of `stereo calibrate --zoom`): CSV image,setting of the images' focal "
                   "settings [default: each image's EXIF FocalLength]. The block gets one camera per setting.")
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option("--poses", "poses_path", type=click.Path(), default=None,
              help="Known poses: position/angle CSV, OpenSfM/ODM reconstruction.json (in its own frame: OpenSfM's "
                   "topocentric one, ODM's UTM one), COLMAP model (with its tracks as tie points), Metashape "
                   "cameras XML, orthority ext_param.geojson or CSV (+ .prj), or ODM geo.txt (positions only: GNSS "
                   "observations), found by content (KIND:PATH: poses, opensfm, colmap, metashape, orthority, "
                   "orthority-csv, odm-geo; see docs/block.md).")
@click.option("--control", "control_path", type=click.Path(dir_okay=False), default=None,
              help="Control: block control CSV (id,image,col,row,x,y,z[,sx,sy,sz]), ODM gcp_list.txt or Metashape "
                   "markers XML, found by content (KIND:PATH: control, odm, metashape).")
@click.option("--observations", "observations_path", type=click.Path(dir_okay=False), default=None,
              help="Image measurements made elsewhere: an observations CSV (image,id,col,row[,sigma_px], as "
                   "stereo block writes it). The block is adjusted without images (give no IMAGES; --poses names "
                   "the images, --camera gives their size).")
@click.option("--method", "method", type=click.Choice(["bundle", "independent-models", "affine", "projective"]),
              default="bundle",
              show_default=True,
              help="bundle: a known camera (--camera). independent-models: the models of the pairs adjusted together "
                   "with the control instead of the bundle (seed 002, 3.1-3.2; see --strip-polynomial, "
                   "--dependent-models). affine, projective: images without a known camera (no "
                   "--camera; seed 003, 3.4): models joined by a joint affine (with virtual control) or projective "
                   "orientation, a projective bundle, the metric upgrade by --control (at least 5 full control "
                   "points) and the bundle with self-calibration of fx, fy, skew and the principal point "
                   "(docs/projective_block.md).")
@click.option("--strip-polynomial", "strip_polynomial", type=click.IntRange(1, 3), default=None,
              help="--method independent-models: join the models into strips, orient each by its control and remove "
                   "its deformation by polynomials of this degree (seed 002, 3.8-3.15; degree 2 needs 6 control points "
                   "per strip, 3 needs 8). Default: the models adjusted together with the control (seed 002, 3.1.2).")
@click.option("--dependent-models", "dependent_models", is_flag=True, default=False,
              help="--method independent-models: partially dependent models (seed 002, 3.2): each pair keeps the "
                   "rotation its left image got from the previous pair.")
@click.option("--focal-guess", "focal_guess", type=click.FloatRange(min=0, min_open=True), default=None,
              help="--method affine: the nominal focal length of its models, px (default max(width, height)).")
@click.option("--frame", "frame", type=click.Choice(list(FRAME_KINDS)), default=None,
              help="Adjustment frame: topocentric (local east-north-up about the block's centre; the default with a "
                   "CRS), geocentric (ECEF) or map (the CRS as given; the default without a CRS). Results are "
                   "written in the CRS of the inputs.")
@click.option("--check", "check_ids", default="", help="Comma-separated control ids used only as check points.")
@click.option("--gnss-sigma", type=Floats(), default=None,
              help="A-priori std of the GNSS projection centres, m (one value or sx,sy,sz): the pose file's "
                   "positions become observations (a reconstruction.json's gps_position, else its centres; "
                   "without the option its gps_position is observed with its gps_dop).")
@click.option("--ins-sigma", type=Floats(), default=None,
              help="A-priori std of the pose file's angles, degrees (one value or three): the angles become "
                   "observations.")
@click.option("--control-sigma", type=Floats(), default=",".join(map(str, _O.control_sigma_m)), show_default=True,
              help="A-priori std of control coordinates where the file gives none, ground units.")
@click.option("--control-sigma-px", type=click.FloatRange(min=0, min_open=True), default=_O.control_sigma_px,
              show_default=True, help="A-priori std of the control points' image measurements, px.")
@click.option("--self-calibrate", is_flag=True, default=False,
              help="Estimate the interior orientation too (default elements: " + ",".join(DEFAULT_SELF_CALIBRATION)
                   + ").")
@click.option("--calibrate", "calibrate_names", default=None,
              help=f"Comma-separated interior elements to estimate (of {','.join(INTERIOR_NAMES)}); implies "
                   "--self-calibrate.")
@click.option("--robust", type=click.Choice(list(ROBUST_METHODS)), default=_O.bundle.robust, show_default=True,
              help="Robust M-estimation of the image observations.")
@click.option("--robust-algorithm", type=click.Choice(list(M_ALGORITHMS)), default=_B.robust_algorithm,
              show_default=True, help="Reweighting (seed 002 eq. 2.24) or modified residuals (eqs. 2.25-2.27).")
@click.option("--robust-scale", type=click.Choice(list(ROBUST_SCALES)), default=_B.robust_scale, show_default=True,
              help="Robust scale: of the least-squares residuals, held; or the weighted median of every "
                   "reweighting (eq. 2.29).")
@click.option("--newton", type=click.Choice(list(NEWTON_METHODS)), default=_B.newton, show_default=True,
              help="Newton-Raphson: normal matrix factorised every iteration, or once (modified; docs/robust.md).")
@click.option("--variance-components/--no-variance-components", default=_O.bundle.variance_components,
              show_default=True, help="Estimate a variance factor per observation group.")
@click.option("--blunder-threshold", type=click.FloatRange(min=0, min_open=True), default=_B.blunder_threshold,
              show_default=True, help="Flag observations whose standardised residual exceeds this.")
@click.option("--max-iterations", type=click.IntRange(min=1), default=_O.bundle.max_iterations, show_default=True,
              help="Iteration limit of the bundle adjustment, over all its variance-component rounds (a free "
                   "network gets at least 300).")
@click.option("--free-network", is_flag=True, default=False,
              help="Allow a block without control and GNSS (datum from the initial projection centres).")
@click.option("--lever-arm", type=Triple(), default=None, help="GNSS antenna offset in the camera frame, m: lx,ly,lz.")
@click.option("--boresight", type=Triple(), default=None,
              help="Boresight angles of the camera in the INS body frame, degrees (navigation pose files).")
@click.option("--trajectory", "trajectory_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="GNSS/INS trajectory CSV (time,x,y,z,heading,pitch,roll[,sx,...]): --poses is then an image-times "
                   "CSV (image,time[,strip]) and each image's pose is the trajectory at its time (cubic positions, "
                   "SLERP attitude; docs/block.md).")
@click.option("--gnss-drift", type=click.Choice(list(DRIFT_MODES)), default=_B.gnss_drift, show_default=True,
              help="GNSS unknowns per strip (the pose file's strip column): a shift, or a shift and a drift linear "
                   "in time (its time column); seed 002 3.64.")
@click.option("--boresight-unknown", type=click.Choice(list(BORESIGHT_MODES)), default=_B.boresight_unknown,
              show_default=True, help="Boresight correction unknowns: for the block, or per strip (needs INS angles).")
@click.option("--ground-z", type=float, default=None, help="Mean terrain height for the footprints (default: "
                                                           "from control).")
@click.option("--pairs", "pair_strategy", type=click.Choice(list(PAIR_STRATEGIES)),
              default=BlockMatchOptions().pair_strategy, show_default=True, help="How image pairs are chosen.")
@click.option("--report/--no-report", "report", default=True, show_default=True, help="Write OUTDIR/report.")
@click.option("--rematch", is_flag=True, default=False,
              help="Match tie points even when --poses brings tracks (a COLMAP model's).")
@click.option("--stac/--no-stac", default=True, show_default=True,
              help="Write the STAC Item of the point cloud, OUTDIR/item.stac.json.")
@click.option("--colmap", "colmap_dir", type=click.Path(file_okay=False), default=None,
              help="Also write the adjusted block as a COLMAP text model into this folder.")
@click.option("--opensfm", "opensfm_dir", type=click.Path(file_okay=False), default=None,
              help="Also write it as OpenSfM reconstruction.json and camera_models.json into this folder "
                   "(topocentric about the mean projection centre when the block has a CRS).")
@click.option("--orthority", "orthority_dir", type=click.Path(file_okay=False), default=None,
              help="Also write orthority's int_param.yaml and ext_param.geojson (xyz_opk.csv without a projected "
                   "CRS) into this folder.")
@click.option("--surface", "surface", is_flag=True, default=False,
              help="Then run `stereo surface` on OUTDIR into OUTDIR/surface (one DSM with sigma_Z, the true "
                   "orthomosaic, the point cloud; its defaults; the --check points of a control CSV check the DSM).")
@click.option("--surface-cloud-format", type=click.Choice(list(CLOUD_FORMATS)), default="laz", show_default=True,
              help="With --surface: the point cloud's file (as stereo surface --cloud-format): points.laz, "
                   "points.las or points.copc.laz.")
@click.option("--surface-cloud-colors/--no-surface-cloud-colors", default=True, show_default=True,
              help="With --surface: the cloud's RGB (as stereo surface --cloud-colors).")
@matcher_opts(BLOCK_MATCHER)
@overwrite_opt
@handle_errors
def block(images, camera_path, focal_settings, out_dir, poses_path, control_path, observations_path, method,
          strip_polynomial, dependent_models, focal_guess, frame,
          check_ids, gnss_sigma,
          ins_sigma, control_sigma,
          control_sigma_px, self_calibrate, calibrate_names, robust, robust_algorithm, robust_scale, newton,
          variance_components, blunder_threshold,
          max_iterations, free_network, lever_arm, boresight, trajectory_path, gnss_drift, boresight_unknown,
          ground_z, pair_strategy, report, rematch, stac,
          colmap_dir, opensfm_dir, orthority_dir, surface, surface_cloud_format,
          surface_cloud_colors, detector, verify, refine, max_matches,
          max_keypoints, overwrite):
    """Orient the block IMAGES... (or the measurements of --observations) into OUTDIR: orientation.json,
    poses.csv, points (PLY, CSV, LAS), observations.csv and the report."""
    calib: tuple[str, ...] = ()
    if calibrate_names:
        calib = _ids(calibrate_names)
    elif self_calibrate:
        calib = DEFAULT_SELF_CALIBRATION
    matcher = matcher_config(detector=detector, verify=verify, refine=refine, max_matches=max_matches,
                             max_keypoints=max_keypoints, base=BLOCK_MATCHER)
    opts = BlockOptions(
        gnss_sigma_m=gnss_sigma,
        ins_sigma_rad=None if ins_sigma is None else _radians(ins_sigma),
        control_sigma_m=control_sigma, control_sigma_px=control_sigma_px, check_ids=_ids(check_ids),
        lever_arm_m=lever_arm,
        boresight_rad=None if boresight is None else _radians(boresight),
        ground_z=ground_z,
        match=BlockMatchOptions(matcher=matcher, pair_strategy=pair_strategy),
        bundle=BundleOptions(robust=robust, robust_algorithm=robust_algorithm, robust_scale=robust_scale,
                             newton=newton, self_calibrate=calib, variance_components=variance_components,
                             blunder_threshold=blunder_threshold, free_network=free_network,
                             max_iterations=max_iterations, gnss_drift=gnss_drift,
                             boresight_unknown=boresight_unknown),
        report=report, reuse_tracks=not rematch, stac=stac,
        exports=BlockExports(colmap=colmap_dir, opensfm=opensfm_dir, orthority=orthority_dir), frame=frame,
        trajectory=trajectory_path, method="bundle" if method in BLOCK_METHODS else method,
        focal_settings=focal_settings,
        models=ModelMethodOptions(strip_polynomial=strip_polynomial, dependent=dependent_models,
                                  robust=robust != "none"))
    plan = (plan_block_surface(images, projective=method in BLOCK_METHODS, method=method, control=control_path,
                               check_ids=opts.check_ids, cloud_format=surface_cloud_format,
                               cloud_colors=surface_cloud_colors) if surface else None)
    if method in BLOCK_METHODS:  # images without a known camera: stereo.actions.block_projective
        refuse_zoom_settings(method, focal_settings)
        popts = ProjectiveBlockOptions(method=method, check_ids=opts.check_ids, control_sigma_m=control_sigma,
                                       control_sigma_px=control_sigma_px, calibrate=calib or DEFAULT_CALIBRATE,
                                       focal_guess_px=focal_guess, match=opts.match,
                                       bundle=opts.bundle)  # its self_calibrate is --calibrate's
        with progress("block") as cb:
            presult = run_block_projective(list(images), out_dir=out_dir, control=control_path, options=popts,
                                           overwrite=overwrite, progress=cb, observations=observations_path,
                                           camera=camera_path, poses=poses_path)
        for line in presult.summary_lines():
            echo(line)
        return
    with progress("block") as cb:
        result = run_block(list(images), out_dir=out_dir, camera=camera_path, poses=poses_path,
                           control=control_path, options=opts, overwrite=overwrite, progress=cb,
                           observations=observations_path)
    for line in result.summary_lines():
        echo(line)
    if plan is not None:  # stereo surface on the block's output folder (docs/surface.md)
        with progress("surface") as cb:
            sres = run_block_surface(out_dir, plan, overwrite=overwrite, progress=cb)
        for line in sres.summary_lines() + ([plan.note] if plan.note else []):
            echo(f"surface: {line}")
