"""``rectify fit``: a planar transform fitted to GCPs, written as a transform JSON (and a report)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rectify.actions.common import check_method
from rectify.actions.workspace import Workspace, check_table_crs
from rectify.formats.detect import GCP_PIXEL, input_paths, read_gcp_file
from rectify.formats.gcps import TIFF_SUFFIXES
from rectify.geometry.accuracy import check_point_statement
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms import METHODS, FitResult, fit_gcps
from rectify.geometry.transforms.quality import GcpGeometry, geographic_lines, judge_gcp_geometry
from rectify.raster.io import raster_info


@dataclass(frozen=True)
class FitOptions:
    """Options of :func:`fit`: the model (a key of :data:`rectify.geometry.transforms.METHODS`), rows printed, the
    source image (its size judges the GCP geometry; its file name picks the GCPs of a file of several images)
    and the pixel convention of GCPs embedded in a GeoTIFF (``corner``, GDAL's, by default; ``centre``)."""

    method: str = "homography"
    max_rows: int = 50
    image: str | Path | None = None
    gcp_pixel: str | None = None


@dataclass(frozen=True, eq=False)
class FitRun:
    """Result of :func:`fit`: the fitted model with its residual table (target units), files written."""

    fit: FitResult
    gcps: GcpTable
    options: FitOptions
    output: Path
    report: Path | None = None
    geometry: GcpGeometry | None = None
    gcp_source: str = ""

    def summary_lines(self) -> list[str]:
        """The residual table (degrees and metres in a geographic CRS), the cotangent control points, RMSE
        (fit and check), the GCP geometry (with the image size) and the files."""
        table = self.fit.table
        if table.units.startswith("degree"):
            lines = geographic_lines(table, max_rows=self.options.max_rows)
        else:
            lines = [table.format_text(max_rows=self.options.max_rows)]
        if self.gcp_source:
            lines.insert(0, f"GCPs: {self.gcp_source}")
        if "control_ids" in table.extra:
            lines.append(f"cotangent method: control points {', '.join(table.extra['control_ids'])} "
                         "(best-conditioned quadrilateral); the other fit rows are reported as check points")
        s = table.summary()
        n_params = METHODS[self.options.method].n_params
        lines.append(f"RMSE {s['rmse']:.4g} {table.units} (fit, n={s['n_fit']}, {n_params} parameters)"
                     + (f"; check RMSE {s['rmse_check']:.4g} {table.units} (n={s['n_check']})"
                        if s["n_check"] else ""))
        acc = check_point_statement(table)
        if acc is not None:
            lines += acc.lines()
        if self.geometry is not None:
            lines += self.geometry.summary_lines()
        elif 2 * s["n_fit"] <= n_params:
            lines.append(f"no redundancy: {s['n_fit']} GCPs determine the {n_params} {self.options.method} "
                         "parameters exactly; the residuals are zero by construction and no error can be estimated")
        lines.append(f"wrote {self.output}")
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return lines


__all__ = ["GCP_PIXEL", "FitOptions", "FitRun", "fit"]


def fit(ws: Workspace, gcps_path: str | Path, output: str | Path, options: FitOptions = FitOptions()) -> FitRun:
    """Fit a transform (source pixels -> target) to the GCP file ``gcps_path``; write the transform JSON.

    Check points (``check = 1``) are withheld from the fit and reported separately. With the source image
    (``options.image``, or the GCP file itself when it is a GeoTIFF with embedded GCPs) the GCP geometry
    is judged over the image (:func:`rectify.geometry.transforms.quality.judge_gcp_geometry`).
    """
    check_method(options.method)
    image = options.image
    gcp_file = input_paths(gcps_path)[0]
    if image is None and gcp_file.suffix.lower() in TIFF_SUFFIXES:
        image = gcp_file
    ws.add_inputs(gcp_file, image)
    size = None
    if image is not None:
        info = raster_info(image)
        size = (info.width, info.height)
    ws.plan(output)
    ws.check_report_dir()
    # any GCP file; of a file of several images, the GCPs of --image's
    gs = read_gcp_file(gcps_path, image=options.image, pixel=options.gcp_pixel, option="--image")
    gcps = gs.table
    check_table_crs(gs.path, gcps.crs, gcps.target, gcps.ids)
    result = fit_gcps(gcps, options.method)
    geometry = None
    if size is not None:
        geometry = judge_gcp_geometry(gcps, options.method, *size, units=result.table.units)
    report = None
    with ws.transaction():  # the transform and the report, all or none
        out = ws.save_transform(output, result.model, table=result.table, crs=gcps.crs)
        if ws.report_dir is not None:
            # local: the report (matplotlib, 0.24 s) loads only when --report asks for it
            from rectify.report.builder import write_fit_report

            report = write_fit_report(ws.report_dir, result, gcps, gcps_path=gs.path, transform_path=out,
                                      overwrite=ws.overwrite)
    return FitRun(result, gcps, options, out, report, geometry, gs.description)
