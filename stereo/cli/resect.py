"""``stereo resect``: space resection of one photo from ground control."""

from __future__ import annotations

import math

import click

from rectify.camera import Camera
from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt
from rectify.errors import InvalidInputError
from rectify.fileutil import check_output
from rectify.formats import read_gcps

from ..formats import exterior_dict, write_exterior
from ..resection import INITIAL_METHODS
from ..resection import resect as resect_fn


@click.command(short_help="Space resection (exterior orientation) from GCPs with z.")
@click.option("--camera", "camera_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Camera JSON.")
@click.option("--gcps", "gcps_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="GCP CSV id,col,row,x,y,z[,check] (ground x, y, z).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="EO JSON to write.")
@click.option("--initial", type=click.Choice(list(INITIAL_METHODS)), default="pnp", show_default=True,
              help="Direct solution for the initial values: OpenCV solvePnP (SQPnP) or DLT (>= 6 points).")
@click.option("--free-interior", is_flag=True, default=False,
              help="Also estimate f, x0, y0 (>= 5 points; weak over flat ground).")
@report_opt
@overwrite_opt
@handle_errors
def resect(camera_path, gcps_path, output, initial, free_interior, report_dir, overwrite):
    """Estimate omega, phi, kappa, X, Y, Z of one photo by collinearity least squares."""
    check_output(output, overwrite=overwrite)
    cam = Camera.from_json(camera_path)
    g = read_gcps(gcps_path)
    if g.z is None:
        raise InvalidInputError(f"{gcps_path!r} has no z column: space resection needs ground heights")
    import numpy as np

    ground = np.column_stack([g.target, g.z])
    eo = resect_fn(cam.photo_from_pixel(g.pixel), ground, focal_length_mm=cam.focal_length_mm,
                   principal_point_mm=(0.0, 0.0), ids=g.ids, check=g.check, free_interior=free_interior,
                   initial=initial, crs=g.crs)
    d = exterior_dict(eo, camera=cam.to_dict())
    write_exterior(output, eo, camera=cam.to_dict(), overwrite=overwrite)
    om, ph, ka = (math.degrees(a) for a in eo.angles)
    se = eo.std_errors
    echo(f"omega {om:.4f} deg +- {math.degrees(se['omega']):.4f}, phi {ph:.4f} +- {math.degrees(se['phi']):.4f}, "
         f"kappa {ka:.4f} +- {math.degrees(se['kappa']):.4f}")
    echo(f"X {eo.position[0]:.3f} +- {se['x']:.3f}, Y {eo.position[1]:.3f} +- {se['y']:.3f}, "
         f"Z {eo.position[2]:.3f} +- {se['z']:.3f}")
    if free_interior:
        echo(f"f {eo.focal_length_mm:.4f} mm +- {se['f']:.4f}, x0 {eo.principal_point_mm[0]:.4f} mm, "
             f"y0 {eo.principal_point_mm[1]:.4f} mm")
    t = eo.residuals
    echo(f"{t.step}: {t.summary_line()} ({t.summary()['rmse'] / cam.pixel_size_mm:.3f} px)")
    echo(f"wrote {output}")
    if report_dir:
        from rectify.report import write_report

        path = write_report(report_dir, title="stereo resect", tables=[t], summary=d, overwrite=overwrite)
        echo(f"report: {path}")
