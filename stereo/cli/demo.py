"""``stereo demo``: the whole chain on a synthetic pair with known truth."""

from __future__ import annotations

from pathlib import Path

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, progress

from ..model import Workspace
from .run import print_model_summary


@click.command(short_help="Run the whole stereo chain on a synthetic pair and compare with the truth.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="demo-output", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Scene seed (deterministic).")
@click.option("--size", "size_px", type=int, default=480, show_default=True, help="Photo side, pixels.")
@overwrite_opt
@handle_errors
def demo(out_dir, seed, size_px, overwrite):
    """Render a synthetic stereo pair (DEM + texture + two cameras), then match, orient
    relatively, intersect, orient to 10 control points and report the accuracy on check
    points and on every model point against the DEM."""
    from ..synthetic import run_demo

    with progress("demo") as cb:
        m, truth = run_demo(Path(out_dir), seed=seed, size_px=size_px, overwrite=overwrite, progress=cb)
    print_model_summary(m, Workspace(out_dir))
    echo("accuracy against the truth:")
    x, y, z = truth["check_rmse_xyz_m"]
    echo(f"  {truth['n_check']} check points: RMSE X {x:.3f} m, Y {y:.3f} m, Z {z:.3f} m; RMS of error / "
         f"predicted std {truth['check_normalised_rms']:.3f} (target 0.67-1.5); per axis "
         + ", ".join(f"{v:.2f}" for v in truth["check_normalised_rms_xyz"]))
    echo(f"  control/check image noise: simulated {truth['pixel_noise_px']:.3f} px, estimated "
         f"{m.summary.get('control_sigma_px', float('nan')):.3f} px")
    echo(f"  all {truth['n_points']} points vs DEM height: RMSE {truth['dem_rmse_m']:.3f} m "
         f"({truth['dem_rmse_m'] / truth['ground_pixel_m']:.2f} ground pixels of {truth['ground_pixel_m']:.2f} m)")
    echo(f"report: {Path(out_dir) / 'report' / 'report.html'}")
