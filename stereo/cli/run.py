"""``stereo run``: the whole pair pipeline from two images."""

from __future__ import annotations

import click

from rectify.camera import Camera
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress
from rectify.tables import read_control

from ..intersection import METHODS
from ..model import FRAMES, ModelOptions, Workspace, run_pair


def print_model_summary(m, ws: Workspace) -> None:
    s = m.summary
    echo(f"{s['n_matches']} matches; relative orientation ({s['ro_system']}): {s['ro_n_used']} used, "
         f"sigma0 {s['ro_sigma0_mm'] * 1000:.2f} um")
    for t in m.tables:
        echo(f"{t.step}: {t.summary_line()}")
    if m.absolute is not None:
        echo(f"absolute orientation ({m.frame['name']} frame): scale {m.absolute.scale:.6g}")
        d = m.frame_difference
        if d and "rms_xyz_m" in d:
            echo(f"{d['other_frame']} frame instead: points differ by RMS {d['rms_xyz_m']:.3f} m "
                 f"(max {d['max_xyz_m']:.3f} m)")
        if s.get("rmse_check_xyz_m"):
            x, y, z = s["rmse_check_xyz_m"]
            echo(f"check points: RMSE X {x:.3f}, Y {y:.3f}, Z {z:.3f} (ground units)")
    echo(f"outputs in {ws.root}: points.ply, points.csv, orientation.json, relative.json, matches.csv, report/")


@click.command(short_help="Match, orient, intersect and orient to ground: everything with a QA report.")
@click.argument("left", type=click.Path(exists=True, dir_okay=False))
@click.argument("right", type=click.Path(exists=True, dir_okay=False))
@click.option("--camera", "camera_path", required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option("--control", "control_path", type=click.Path(exists=True, dir_okay=False), default=None)
@click.option("--check", "check_ids", default="", help="Comma-separated control ids used only as checks.")
@click.option("--frame", type=click.Choice(list(FRAMES)), default="topocentric", show_default=True)
@click.option("--method", type=click.Choice(list(METHODS)), default="least-squares", show_default=True)
@click.option("--robust", type=click.Choice(["none", "huber", "tukey", "hampel", "andrews"]), default="none",
              show_default=True, help="Robust absolute orientation.")
@overwrite_opt
@handle_errors
def run(left, right, camera_path, out_dir, control_path, check_ids, frame, method, robust, overwrite):
    """Run the stereo pipeline on LEFT and RIGHT into OUTDIR."""
    cam = Camera.from_json(camera_path)
    control = read_control(control_path) if control_path else None
    checks = tuple(s.strip() for s in check_ids.split(",") if s.strip())
    opts = ModelOptions(intersection=method, frame=frame, robust=robust, check_ids=checks)
    ws = Workspace(out_dir, overwrite=overwrite)
    with progress("matching") as cb:
        m = run_pair(left, right, cam, out_dir, control=control, options=opts, overwrite=overwrite,
                     progress=cb)
    print_model_summary(m, ws)
