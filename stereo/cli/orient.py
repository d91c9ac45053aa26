"""``stereo orient``: relative orientation of a stereo pair from tie points."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, matcher_opts, overwrite_opt, report_opt
from rectify.geometry.robust import ROBUST_METHODS
from stereo.actions.common import ORIENT_MATCHER, matcher_config
from stereo.actions.orient import OrientOptions, parse_focal_settings
from stereo.actions.orient import orient as orient_action
from stereo.relative import INITIAL_METHODS, METHOD_SYSTEMS, SYSTEMS

_D = OrientOptions()


@click.command(short_help="Relative orientation (coplanarity) of a stereo pair.")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("--camera", "camera_path", default=None, type=click.Path(),
              help="Camera (both images, or the left one with --camera-right): camera JSON, orthority int_param, "
                   "OpenCV calibration, COLMAP model or Metashape cameras XML, found by content (KIND:PATH: camera, "
                   "orthority, opencv, colmap, metashape). Required except with --system projective, which "
                   "without a camera writes the fundamental matrix (a projective pair, no metric elements).")
@click.option("--camera-right", "camera_right_path", type=click.Path(), default=None,
              help="Camera of the right image when it differs (any camera file, as --camera).")
@click.option("--focal-setting", "focal_setting", default=None,
              help="Focal setting of the images for a zoom camera (stereo calibrate --zoom): Z for both, or "
                   "ZLEFT,ZRIGHT. Default: each image's EXIF FocalLength.")
@click.option("--matches", "matches_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Matches CSV (id,col_left,row_left,col_right,row_right). Omit to match LEFT RIGHT first.")
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False),
              help="Relative orientation JSON to write.")
@click.option("--system", type=click.Choice([*SYSTEMS, *METHOD_SYSTEMS]), default=_D.system, show_default=True,
              help="System of elements; universal: linear iterations with the p, q, r matrices (seed 003, 3.2.1; "
                   "basis elements), projective: from the fundamental matrix (3.2.2; left-image elements, or no "
                   "metric elements without --camera).")
@click.option("--robust", type=click.Choice(list(ROBUST_METHODS)), default=_D.robust, show_default=True,
              help="M-estimator after the essential-matrix RANSAC (none: plain least squares).")
@click.option("--initial", type=click.Choice(list(INITIAL_METHODS)), default=_D.initial, show_default=True,
              help="Initial values: zero angles, OpenCV's five-point essential matrix, or zero then essential.")
@click.option("--matches-out", type=click.Path(dir_okay=False), default=None,
              help="With LEFT RIGHT: also write the matches CSV here.")
@matcher_opts(ORIENT_MATCHER)
@report_opt
@overwrite_opt
@handle_errors
def orient(images, camera_path, camera_right_path, focal_setting, matches_path, output, system, robust, initial,
           matches_out, detector, verify, refine, max_matches, max_keypoints, report_dir, overwrite):
    """Estimate the five elements of relative orientation.

    Either ``stereo orient --camera CAM.json --matches matches.csv -o ro.json``
    or ``stereo orient LEFT RIGHT --camera CAM.json -o ro.json`` (matches first
    with rectify.features). Prints a residual summary; ``--report DIR`` writes
    the residual table, plots and an HTML report.
    """
    if matches_path is None and len(images) != 2:
        raise click.UsageError("give either --matches FILE or the two images LEFT RIGHT")
    if matches_path is not None and images:
        raise click.UsageError("give either --matches FILE or LEFT RIGHT, not both")
    if matches_out and not images:
        raise click.UsageError("--matches-out needs LEFT RIGHT")
    result = orient_action(camera=camera_path, camera_right=camera_right_path, matches=matches_path,
                           images=tuple(images) if images else None, output=output, matches_out=matches_out,
                           report_dir=report_dir, overwrite=overwrite,
                           options=OrientOptions(system=system, robust=robust, initial=initial),
                           matcher=matcher_config(detector=detector, verify=verify, refine=refine,
                                                  max_matches=max_matches, max_keypoints=max_keypoints,
                                                  base=ORIENT_MATCHER),
                           focal_settings=parse_focal_settings(focal_setting))
    for line in result.summary_lines():
        echo(line)


__all__ = ["orient"]
