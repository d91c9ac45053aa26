"""``rectify warp``: georectify a raster by GCPs or a fitted transform into a GeoTIFF/COG."""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

from rectify.actions.common import Progress, check_method
from rectify.actions.workspace import Workspace, check_table_crs
from rectify.errors import InvalidInputError
from rectify.formats.gcps import has_embedded_gcps
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms.quality import GcpGeometry, geographic_lines, judge_gcp_geometry
from rectify.raster.georectify import GeoRectification, georectify, rectify_with_transform
from rectify.raster.io import raster_info
from rectify.raster.warp import DEFAULT_MAX_PIXELS, RESAMPLING_NAMES, WarpOptions

#: the command's choices (the list lives in :mod:`rectify.raster.warp`)
__all__ = ["RESAMPLING_NAMES", "WarpRunOptions", "WarpRun", "warp"]


@dataclass(frozen=True)
class WarpRunOptions:
    """Options of :func:`warp`.

    Attributes
    ----------
    method : str
        Model fitted to GCPs (a key of ``rectify.geometry.transforms.METHODS``).
    gcp_crs : str, optional
        CRS of the GCP (or transform) coordinates; overrides the file's.
    dst_crs : str, optional
        Output CRS (default: the GCP CRS).
    resolution : float, optional
        Output pixel size, output CRS units (default: estimated from the transform).
    resampling : str
        One of :data:`RESAMPLING_NAMES`.
    cog : bool
        Cloud Optimized GeoTIFF with overviews.
    threads : int, optional
        Worker threads (default: all cores).
    max_pixels : float
        Refuse an output grid with more pixels (default :data:`rectify.raster.warp.DEFAULT_MAX_PIXELS`, 2e9).
    scheduler : str, optional
        Where the tiles run: ``threads``, ``processes[:N]`` or ``tcp://HOST:PORT`` (default:
        ``$RECTIFY_SCHEDULER``, else ``threads``; :mod:`rectify.raster.distributed`).
    """

    method: str = "homography"
    gcp_crs: str | None = None
    dst_crs: str | None = None
    resolution: float | None = None
    resampling: str = "bilinear"
    cog: bool = False
    threads: int | None = None
    max_pixels: float = DEFAULT_MAX_PIXELS
    scheduler: str | None = None


@dataclass(frozen=True, eq=False)
class WarpRun:
    """Result of :func:`warp`: the georectification, the output and the report."""

    result: GeoRectification
    options: WarpRunOptions
    output: Path
    report: Path | None = None
    geometry: GcpGeometry | None = None

    def summary_lines(self) -> list[str]:
        """GCP fit summary (when fitted), output grid, CRS, resampling, format and time, report."""
        r, o = self.result, self.options
        g = r.warp.grid
        lines = [r.fit.table.summary_line()] if r.fit is not None else []
        if r.fit is not None and r.fit.table.units.startswith("degree"):
            lines.append(geographic_lines(r.fit.table, max_rows=0)[-1])
        lines += list(r.notes)
        if self.geometry is not None:
            lines += self.geometry.summary_lines()
        lines.append(f"wrote {self.output}: {g.width} x {g.height} px, {g.resolution[0]:.6g} units/px, "
                     f"CRS {r.crs or 'none'}, {o.resampling}, {'COG' if o.cog else 'tiled GeoTIFF'}, "
                     f"{r.warp.seconds:.2f} s")
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return lines


def warp(ws: Workspace, src: str | Path, dst: str | Path, *, gcps_path: str | Path | None = None,
         transform_path: str | Path | None = None, options: WarpRunOptions = WarpRunOptions(),
         progress: Progress = None) -> WarpRun:
    """Rectify ``src`` into the GeoTIFF ``dst`` with GCPs (fitted with ``options.method``) or a saved transform.

    GCP files: CSV, QGIS ``.points``, matches CSV, GeoJSON, GeoPackage, or a GeoTIFF's embedded GCPs
    (:func:`rectify.formats.gcps.read_gcps`). With neither ``gcps_path`` nor ``transform_path``, the GCPs
    embedded in ``src`` are used when it carries some.

    Raises
    ------
    InvalidInputError
        Neither (and no embedded GCPs) or both of ``gcps_path`` and ``transform_path``; a report without
        GCPs; bad paths.
    """
    if gcps_path is None and transform_path is None:
        if not has_embedded_gcps(src):
            raise InvalidInputError(f"give exactly one of --gcps or --transform ({str(src)!r} carries no "
                                    "embedded GCPs)")
        gcps_path = src  # the GCPs embedded in the source GeoTIFF
    if gcps_path is not None and transform_path is not None:
        raise InvalidInputError("give exactly one of --gcps or --transform")
    if ws.report_dir is not None and transform_path is not None:
        raise InvalidInputError("--report needs --gcps (a saved transform has no residuals to report)")
    if gcps_path is not None:
        check_method(options.method)
    # GDAL reads GDAL_CACHEMAX once, at its first block access: bound it before any pixel IO
    os.environ.setdefault("GDAL_CACHEMAX", "64")
    ws.add_inputs(src, gcps_path, transform_path)
    ws.plan(dst)
    ws.check_report_dir()
    info = raster_info(src)
    wopts = WarpOptions(resampling=options.resampling, cog=options.cog, threads=options.threads,
                        max_pixels=options.max_pixels, scheduler=options.scheduler)
    if gcps_path is not None:
        gcps = ws.load_gcps(gcps_path)
        if options.gcp_crs:  # --gcp-crs overrides the file's CRS: the coordinates must fit it too
            check_table_crs(gcps_path, options.gcp_crs, gcps.target, gcps.ids)
        result = georectify(src, dst, gcps, method=options.method, gcp_crs=options.gcp_crs, dst_crs=options.dst_crs,
                            resolution=options.resolution, options=wopts, overwrite=ws.overwrite, progress=progress)
    else:
        assert transform_path is not None
        tf = ws.load_transform(transform_path)
        result = rectify_with_transform(src, dst, tf.model, model_crs=options.gcp_crs or tf.crs,
                                        dst_crs=options.dst_crs, resolution=options.resolution, options=wopts,
                                        overwrite=ws.overwrite, progress=progress)
    geometry = None
    if result.fit is not None:
        t = result.fit.table
        fitted = GcpTable(t.ids, t.position_px, t.observed, None, t.check, result.crs)
        geometry = judge_gcp_geometry(fitted, options.method, info.width, info.height, units=t.units)
    report = None
    if ws.report_dir is not None:
        try:
            # local: the report (matplotlib, 0.24 s) loads only when --report asks for it
            from rectify.report.builder import write_warp_report

            report = write_warp_report(ws.report_dir, result, source_shape=(info.height, info.width),
                                       overwrite=ws.overwrite)
        except BaseException:  # all or none: the GeoTIFF this run wrote goes too
            with contextlib.suppress(OSError):
                Path(dst).unlink()
            raise
    return WarpRun(result, options, Path(dst), report, geometry)
