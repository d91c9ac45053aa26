"""``stereo orient``: relative orientation of a stereo pair from tie points."""

from __future__ import annotations

import math

import click

from rectify.camera import Camera
from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt
from rectify.errors import InvalidInputError
from rectify.fileutil import check_output

from ..formats import write_relative
from ..relative import ROBUST_METHODS, SYSTEMS, RelativeOrientation


@click.command(short_help="Relative orientation (coplanarity) of a stereo pair.")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("--camera", "camera_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Camera JSON (both images, or the left one with --camera-right).")
@click.option("--camera-right", "camera_right_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Camera JSON of the right image when it differs.")
@click.option("--matches", "matches_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Matches CSV (id,col_left,row_left,col_right,row_right). Omit to match LEFT RIGHT first.")
@click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False),
              help="Relative orientation JSON to write.")
@click.option("--system", type=click.Choice(list(SYSTEMS)), default="left-image", show_default=True,
              help="System of elements.")
@click.option("--robust", type=click.Choice(list(ROBUST_METHODS)), default="none", show_default=True,
              help="M-estimator after the essential-matrix RANSAC (none: plain least squares).")
@click.option("--initial", type=click.Choice(["auto", "zero", "essential"]), default="auto", show_default=True,
              help="Initial values: zero angles, OpenCV's five-point essential matrix, or zero then essential.")
@click.option("--matches-out", type=click.Path(dir_okay=False), default=None,
              help="With LEFT RIGHT: also write the matches CSV here.")
@report_opt
@overwrite_opt
@handle_errors
def orient(images, camera_path, camera_right_path, matches_path, output, system, robust, initial, matches_out,
           report_dir, overwrite):
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
    check_output(output, overwrite=overwrite)
    if matches_out:
        check_output(matches_out, overwrite=overwrite)
    cam = Camera.from_json(camera_path)
    cam_r = Camera.from_json(camera_right_path) if camera_right_path else None
    if images:
        from rectify.features import MatcherConfig, match_images
        from rectify.formats import write_matches

        res = match_images(images[0], images[1], config=MatcherConfig(verify="fundamental"))
        matches = res.matches
        echo(f"matched {len(matches)} tie points (verification RMSE {res.rmse_px:.3g} px)")
        if matches_out:
            write_matches(matches_out, matches, overwrite=overwrite)
    else:
        from rectify.formats import read_matches

        matches = read_matches(matches_path)
    if len(matches) == 0:
        raise InvalidInputError("no tie points")
    ro = RelativeOrientation.from_pixels(matches.left, matches.right, cam, camera_right=cam_r, system=system,
                                         robust=robust, initial=initial, ids=matches.ids)
    # the cameras travel with the orientation, so `stereo model` needs no --camera
    cams = {"camera": cam.to_dict(), **({"camera_right": cam_r.to_dict()} if cam_r else {})}
    write_relative(output, ro, extra=cams, overwrite=overwrite)
    s = ro.summary()
    echo(f"relative orientation ({system}), {s['n_used']} of {s['n_points']} points used, "
         f"{s['n_outliers']} outliers, {s['iterations']} iterations"
         + (f" + {s['irls_iterations']} reweightings ({robust})" if robust != "none" else "")
         + f", start: {s['initial']}")
    sig = "n/a (no redundancy)" if ro.sigma0_mm is None else \
        f"{ro.sigma0_mm * 1000:.2f} um = {ro.sigma0_mm / cam.pixel_size_mm:.3f} px"
    echo(f"residual vertical parallax: RMSE {s['rms_parallax_px']:.3f} px ({s['rms_parallax_mm'] * 1000:.2f} um); "
         f"sigma0 {sig}; condition number {ro.condition_number:.3g}")
    std = ro.std_errors
    for i, name in enumerate(ro.names):
        se = "" if std is None else f" +- {math.degrees(std[i]):.5f}"
        echo(f"  {name:>7} = {math.degrees(ro.elements[i]):11.5f}{se} deg")
    wf = ro.western()
    echo(f"  relative omega, phi, kappa = {math.degrees(wf.omega):.5f}, {math.degrees(wf.phi):.5f}, "
         f"{math.degrees(wf.kappa):.5f} deg; base (1, {wf.by:.5f}, {wf.bz:.5f})")
    echo(f"wrote {output}")
    if report_dir:
        from ..report import write_stereo_report

        table = ro.residual_table()
        corr = ro.correlation
        path = write_stereo_report(
            report_dir, title=f"stereo orient: relative orientation ({system})", relative=table,
            correlation=None if corr is None else (list(ro.names), corr),
            summary={**s, "elements_rad": ro.element_dict, "sigma0_mm": ro.sigma0_mm},
            left_image_shape=(cam.height, cam.width), principal_point_px=cam.principal_point_px,
            overwrite=overwrite)
        echo(f"report: {path}")


__all__ = ["orient"]
