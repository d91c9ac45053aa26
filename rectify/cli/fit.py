"""``rectify fit``: fit a planar transform to GCPs and save it as JSON."""

from __future__ import annotations

import click

from .options import echo, handle_errors, overwrite_opt, report_opt

METHOD_NAMES = ("homography", "cotangent", "affine", "poly2", "poly3")


@click.command(short_help="Fit a transform (homography, cotangent, affine, poly2, poly3) to GCPs.")
@click.argument("gcps_path", metavar="GCPS", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "output", type=click.Path(dir_okay=False), required=True,
              help="Transform JSON to write.")
@click.option("--method", type=click.Choice(METHOD_NAMES), default="homography", show_default=True,
              help="Model: 8-parameter homography, Kushtin's cotangent four-point method, affine, "
                   "or polynomial of order 2/3.")
@click.option("--max-rows", type=int, default=50, show_default=True, help="Residual rows printed.")
@report_opt
@overwrite_opt
@handle_errors
def fit(gcps_path, output, method, max_rows, report_dir, overwrite):
    """Fit a transform from source pixels to target coordinates.

    GCPS is a CSV (id,col,row,x,y[,check]) or a QGIS .points file. Rows with
    check = 1 are withheld from the fit and reported as check points. Prints
    the per-point residuals dx, dy, |v| (target units) and the RMSE.
    """
    from ..fileutil import check_output
    from ..tables import read_gcps
    from ..transforms import METHODS, fit_gcps, save_transform

    model_info = METHODS[method]  # the click Choice guarantees the key
    check_output(output, overwrite=overwrite)
    gcps = read_gcps(gcps_path)
    result = fit_gcps(gcps, method)
    table = result.table
    echo(table.format_text(max_rows=max_rows))
    if "control_ids" in table.extra:
        echo(f"cotangent method: control points {', '.join(table.extra['control_ids'])} (best-conditioned "
             "quadrilateral); the other fit rows are reported as check points")
    s = table.summary()
    echo(f"RMSE {s['rmse']:.4g} {table.units} (fit, n={s['n_fit']}, {model_info.n_params} parameters)"
         + (f"; check RMSE {s['rmse_check']:.4g} {table.units} (n={s['n_check']})" if s["n_check"] else ""))
    save_transform(output, result.model, table=table, crs=gcps.crs, overwrite=overwrite)
    echo(f"wrote {output}")
    if report_dir is not None:
        from ..report import write_report

        ground = {table.step: gcps.target} if gcps.crs else None
        path = write_report(report_dir, title=f"rectify fit: {method} on {gcps_path}", tables=[table],
                            summary={"method": method, "gcps": str(gcps_path), "transform": str(output),
                                     **{k: v for k, v in s.items() if k != "step"}},
                            crs=gcps.crs, ground_xy=ground, overwrite=overwrite)
        echo(f"report: {path}")
