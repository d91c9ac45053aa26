"""``stereo model``: model (and ground) points from a relative orientation and matches."""

from __future__ import annotations

from pathlib import Path

import click

from rectify.camera import Camera
from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt
from rectify.errors import InvalidInputError
from rectify.fileutil import check_output
from rectify.formats import read_control, read_matches

from ..formats import read_relative
from ..intersection import METHODS
from ..model import FRAMES, ModelOptions, run_model, save_model
from .run import print_tables


def outputs_for(points: str) -> tuple[Path, Path, Path]:
    """points.ply -> (points.ply, points.csv, points.orientation.json)."""
    p = Path(points)
    return p, p.with_suffix(".csv"), p.with_suffix(".orientation.json")


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
@click.option("--frame", type=click.Choice(list(FRAMES)), default="topocentric", show_default=True,
              help="Absolute orientation in a local topocentric frame or directly in map coordinates.")
@click.option("--method", type=click.Choice(list(METHODS)), default="least-squares", show_default=True,
              help="Intersection method.")
@click.option("--robust", type=click.Choice(["none", "huber", "tukey", "hampel", "andrews"]), default="none",
              show_default=True, help="Robust absolute orientation.")
@click.option("--deformation", type=click.Choice(["none", "2", "3"]), default="none", show_default=True,
              help="Polynomial correction of model deformation (order).")
@click.option("--control-sigma-px", type=float, default=None,
              help="Image precision of the control/check points, pixels (default: estimated from the absolute "
                   "orientation).")
@report_opt
@overwrite_opt
@handle_errors
def model(ro_json, matches_path, camera_path, output, control_path, check_ids, frame, method, robust, deformation,
          control_sigma_px, report_dir, overwrite):
    """Intersect the matches of RO_JSON's pair into model points and, with
    --control, orient the model to the ground (7-parameter similarity)."""
    ply, csv_path, orient_path = outputs_for(output)
    for p in (ply, csv_path, orient_path):
        check_output(p, overwrite=overwrite)
    geom = read_relative(ro_json)
    if camera_path is not None:
        cam = Camera.from_json(camera_path)
    elif isinstance(geom.raw.get("camera"), dict):  # written by `stereo orient`
        cam = Camera.from_dict(geom.raw["camera"])
    else:
        raise InvalidInputError(f"{ro_json!r} holds no camera (it was not written by `stereo orient`): pass "
                                "--camera CAM.json, pixels cannot be converted to photo mm without it")
    matches = read_matches(matches_path)
    ro_ids = {str(p.get("id")) for p in geom.raw.get("points", []) if isinstance(p, dict)}
    if ro_ids and not ro_ids & set(matches.ids):
        raise InvalidInputError(
            f"ids in {matches_path!r} do not match the points of {ro_json!r} (e.g. {sorted(matches.ids)[:3]} vs "
            f"{sorted(ro_ids)[:3]}): the files belong to different pairs")
    control = read_control(control_path) if control_path else None
    checks = tuple(s.strip() for s in check_ids.split(",") if s.strip())
    if checks and control is None:
        raise InvalidInputError("--check needs --control")
    opts = ModelOptions(intersection=method, frame=frame, robust=robust,
                        deformation_order=None if deformation == "none" else int(deformation), check_ids=checks,
                        control_sigma_px=control_sigma_px)
    m = run_model(geom, matches, cam, control=control, options=opts)
    save_model(m, points_path=ply, csv_path=csv_path, orientation_path=orient_path, overwrite=overwrite)
    s = m.summary
    echo(f"{len(m.ids)} points intersected ({method}); RMS vertical parallax "
         f"{s['rms_vertical_parallax_mm'] * 1000:.2f} um ({s.get('rms_vertical_parallax_px', float('nan')):.3f} px)")
    print_tables(m)
    echo(f"wrote {ply}, {csv_path}, {orient_path}")
    if report_dir:
        from ..model import write_pair_report

        path = write_pair_report(m, report_dir, title="stereo model", camera=cam, overwrite=overwrite)
        echo(f"report: {path}")
