"""``stereo run``: the whole pair pipeline from two images."""

from __future__ import annotations

import click

from rectify.camera import Camera
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress
from rectify.formats import read_control

from ..intersection import METHODS
from ..model import FRAMES, ModelOptions, Workspace, run_pair


def _intersection_line(m, tie_note: str) -> str:
    """Intersection summary with the point count broken down (tie points kept by the RO + control file)."""
    s = m.summary
    t = next(t for t in m.tables if t.step == "intersection")
    ts = t.summary()
    parts = [f"{s['n_tie_points']} tie points {tie_note}".rstrip()]
    if s.get("n_control_file_points"):
        n_c, n_k = s["n_control_points"], s["n_check_points"]
        n_other = s["n_control_file_points"] - n_c - n_k
        parts.append(f"{n_c} control + {n_k} check" + (f" + {n_other} other" if n_other else "")
                     + " points from the control file")
    return (f"intersection: {ts['n_fit']} points ({' + '.join(parts)}), photo residual RMSE "
            f"{ts['rmse'] * 1000:.2f} um, RMS vertical parallax {s['rms_vertical_parallax_mm'] * 1000:.2f} um")


def print_model_summary(m, ws: Workspace) -> None:
    s = m.summary
    n_ctrl_file = s.get("n_control_file_points", 0)
    echo(f"{s['n_matches']} matches; relative orientation ({s['ro_system']}) on "
         f"{s['n_matches'] + n_ctrl_file} points ({s['n_matches']} matches + {n_ctrl_file} control-file points): "
         f"{s['ro_n_used']} used, sigma0 {s['ro_sigma0_mm'] * 1000:.2f} um")
    print_tables(m, tie_note="kept by the relative orientation")
    echo(f"outputs in {ws.root}: points.ply, points.csv, orientation.json, relative.json, matches.csv, report/")


def print_tables(m, tie_note: str = "from the matches") -> None:
    """Residual summary of every table, absolute orientation details, check points (units named)."""
    s = m.summary
    for t in m.tables:
        if t.step == "intersection":
            echo(_intersection_line(m, tie_note))
        elif m.absolute is not None and t is m.absolute.residuals:
            ts = t.summary()
            u = t.units
            line = f"{t.step}: {ts['n_fit']} control points, RMSE {ts['rmse']:.3f} {u}"
            if ts["n_check"]:
                line += f"; {ts['n_check']} check points, RMSE {ts['rmse_check']:.3f} {u}"
            if ts["n_outliers"]:
                line += f"; {ts['n_outliers']} outliers"
            line += f"; sigma0 {m.absolute.sigma0:.3f}" + ("" if s.get("absolute_weighted") else f" {u}")
            if s.get("control_sigma_source") == "estimated":
                line += " (1 by construction: the control image precision is scaled to it)"
            echo(line)
        else:
            echo(f"{t.step}: {t.summary_line()}")
    if m.absolute is not None:
        u = s.get("ground_unit", "ground units")
        echo(f"absolute orientation ({m.frame['name']} frame): scale {m.absolute.scale:.6g}")
        if s.get("control_sigma_px") is not None:
            how = "estimated from the absolute orientation" if s["control_sigma_source"] == "estimated" else "given"
            echo(f"image precision: tie points {s['tie_sigma_px']:.4f} px (RO sigma0), control/check points "
                 f"{s['control_sigma_px']:.3f} px ({how})")
        d = m.frame_difference
        if d and "rms_xyz_m" in d:
            echo(f"{d['other_frame']} frame instead: points differ by RMS {d['rms_xyz_m']:.3f} m "
                 f"(max {d['max_xyz_m']:.3f} m)")
        if s.get("rmse_check_xyz_m"):
            x, y, z = s["rmse_check_xyz_m"]
            echo(f"check points: RMSE X {x:.3f} {u}, Y {y:.3f} {u}, Z {z:.3f} {u}")
        if "rms_normalised_check_error" in s:
            echo(f"check points: RMS of error / predicted std {s['rms_normalised_check_error']:.3f}")


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
@click.option("--control-sigma-px", type=float, default=None,
              help="Image precision of the control/check points, pixels (default: estimated from the absolute "
                   "orientation).")
@overwrite_opt
@handle_errors
def run(left, right, camera_path, out_dir, control_path, check_ids, frame, method, robust, control_sigma_px,
        overwrite):
    """Run the stereo pipeline on LEFT and RIGHT into OUTDIR."""
    cam = Camera.from_json(camera_path)
    control = read_control(control_path) if control_path else None
    checks = tuple(s.strip() for s in check_ids.split(",") if s.strip())
    opts = ModelOptions(intersection=method, frame=frame, robust=robust, check_ids=checks,
                        control_sigma_px=control_sigma_px)
    ws = Workspace(out_dir, overwrite=overwrite)
    with progress("matching") as cb:
        m = run_pair(left, right, cam, out_dir, control=control, options=opts, overwrite=overwrite,
                     progress=cb)
    print_model_summary(m, ws)
