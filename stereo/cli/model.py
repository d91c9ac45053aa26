"""``stereo model``: model (and ground) points from a relative orientation and matches."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt
from rectify.geometry.robust import ROBUST_METHODS
from stereo.actions.model import TRANSFORMS
from stereo.actions.model import model as model_action
from stereo.pair.absolute import DEFORMATION_ORDERS
from stereo.pair.intersection import METHODS
from stereo.pair.model import FRAMES, ModelOptions

_D = ModelOptions()


@click.command(short_help="Intersect matches into a model; orient it to ground control.")
@click.argument("ro_json", type=click.Path(exists=True, dir_okay=False))
@click.option("--matches", "matches_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Matches CSV (pixels).")
@click.option("--camera", "camera_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Camera JSON (pixels -> photo mm); default: the camera stored in RO_JSON by `stereo orient`.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="PLY to write; a CSV and <name>.orientation.json are written beside it.")
@click.option("--control", "control_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Stereo control CSV (id,col_left,row_left,col_right,row_right,x,y,z; '# crs=...').")
@click.option("--check", "check_ids", default="", help="Comma-separated control ids used only as checks.")
@click.option("--frame", type=click.Choice(list(FRAMES)), default=_D.frame, show_default=True,
              help="Absolute orientation in a local topocentric frame or directly in map coordinates.")
@click.option("--method", type=click.Choice(list(METHODS)), default=_D.intersection, show_default=True,
              help="Intersection method.")
@click.option("--robust", type=click.Choice(list(ROBUST_METHODS)), default=_D.robust, show_default=True,
              help="Robust absolute orientation.")
@click.option("--deformation", type=click.Choice(["none", *map(str, DEFORMATION_ORDERS)]), default="none",
              show_default=True, help="Polynomial correction of model deformation (order).")
@click.option("--control-sigma-px", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Image precision of the control/check points, pixels (default: estimated from the absolute "
                   "orientation).")
@click.option("--transform", type=click.Choice(list(TRANSFORMS)), default="similarity", show_default=True,
              help="Model-to-ground transformation: the 7-parameter similarity, or (seed 003, 3.3) the 12-parameter "
                   "affine (>= 4 non-coplanar control points) or the 15-parameter projective (>= 5 not all on one "
                   "plane; the only one for a projective pair written without a camera).")
@report_opt
@overwrite_opt
@handle_errors
def model(ro_json, matches_path, camera_path, output, control_path, check_ids, frame, method, robust, deformation,
          control_sigma_px, transform, report_dir, overwrite):
    """Intersect the matches of RO_JSON's pair into model points and, with
    --control, orient the model to the ground (7-parameter similarity, or the affine or projective
    transformation of --transform; RO_JSON may then also be the projective pair JSON of
    `stereo orient --system projective` without a camera)."""
    checks = tuple(s.strip() for s in check_ids.split(",") if s.strip())
    opts = ModelOptions(intersection=method, frame=frame, robust=robust,
                        deformation_order=None if deformation == "none" else int(deformation), check_ids=checks,
                        control_sigma_px=control_sigma_px)
    result = model_action(ro_json, matches=matches_path, output=output, camera=camera_path, control=control_path,
                          report_dir=report_dir, overwrite=overwrite, options=opts, transform=transform)
    for line in result.summary_lines():
        echo(line)
