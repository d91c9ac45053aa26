"""``rectify demo``: the embedded Landsat scene through a tilted frame and back."""

from __future__ import annotations

import click

from .options import echo, handle_errors, overwrite_opt, progress


@click.command(short_help="Rectify a simulated tilted frame of the embedded Landsat scene.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="demo-output", show_default=True,
              help="Folder for the outputs and the report.")
@overwrite_opt
@handle_errors
def demo(out_dir, overwrite):
    """Warp the embedded Landsat GeoTIFF into a tilted frame with a known
    homography, pick GCPs, rectify it back and report the error against the truth."""
    from ..demo import run_demo

    with progress("rectifying") as cb:
        r = run_demo(out_dir, overwrite=overwrite, progress=cb)
    s = r.fit_summary
    echo(f"frame: {r.frame}")
    echo(f"GCPs: {r.gcps} ({s['n_fit']} control, {s['n_check']} check points)")
    echo(f"GCP fit (homography): RMSE {s['rmse']:.3f} m, sigma0 {s['sigma0']:.3f} m, "
         f"check RMSE {s['rmse_check']:.3f} m")
    echo(f"rectified: {r.rectified}")
    echo(f"geolocation RMSE against the truth: {r.geolocation_rmse_m:.2f} m = "
         f"{r.geolocation_rmse_m / r.pixel_size_m:.4f} Landsat px (max {r.geolocation_max_m:.2f} m)")
    for line in r.compare_lines:
        echo(f"projective comparison: {line}")
    echo(f"report: {r.report}")
