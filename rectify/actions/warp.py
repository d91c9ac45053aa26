"""``rectify warp``: georectify a raster by GCPs or a fitted transform into a GeoTIFF/COG."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from rectify.actions.common import Progress, check_method
from rectify.actions.products import (
    options_of,
    raster_grid,
    raster_roles,
    residual_accuracy,
    stac_path,
    staged,
    write_stac,
)
from rectify.actions.workspace import Workspace, check_table_crs
from rectify.errors import InvalidInputError
from rectify.formats.detect import GCP_PIXEL, input_paths, read_gcp_file
from rectify.formats.gcps import has_embedded_gcps
from rectify.formats.stac import StacAsset
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms.quality import GcpGeometry, geographic_lines, judge_gcp_geometry
from rectify.raster.georectify import GeoRectification, georectify, rectify_with_transform
from rectify.raster.io import raster_info
from rectify.raster.warp import DEFAULT_MAX_PIXELS, RESAMPLING_NAMES, WarpOptions

#: the command's choices (the list lives in :mod:`rectify.raster.warp`)
__all__ = ["RESAMPLING_NAMES", "GCP_PIXEL", "WarpRunOptions", "WarpRun", "warp"]


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
    gcp_pixel : str, optional
        Pixel convention of GCPs embedded in a GeoTIFF: ``corner`` (GDAL's, the default) or ``centre``
        (orthority's).
    stac : bool
        Write the STAC Item ``<output stem>.stac.json`` beside the output, in the same transaction.
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
    gcp_pixel: str | None = None
    stac: bool = True


@dataclass(frozen=True, eq=False)
class WarpRun:
    """Result of :func:`warp`: the georectification, the output and the report."""

    result: GeoRectification
    options: WarpRunOptions
    output: Path
    report: Path | None = None
    geometry: GcpGeometry | None = None
    gcp_source: str = ""
    stac: Path | None = None

    def summary_lines(self) -> list[str]:
        """GCP fit summary (when fitted), output grid, CRS, resampling, format and time, report."""
        r, o = self.result, self.options
        g = r.warp.grid
        lines = [f"GCPs: {self.gcp_source}"] if self.gcp_source else []
        lines += [r.fit.table.summary_line()] if r.fit is not None else []
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
        if self.stac is not None:
            lines.append(f"wrote {self.stac} (STAC Item)")
        return lines


def warp(ws: Workspace, src: str | Path, dst: str | Path, *, gcps_path: str | Path | None = None,
         transform_path: str | Path | None = None, options: WarpRunOptions = WarpRunOptions(),
         progress: Progress = None) -> WarpRun:
    """Rectify ``src`` into the GeoTIFF ``dst`` with GCPs (fitted with ``options.method``) or a saved transform.

    GCP files: CSV, QGIS ``.points``, matches CSV, GeoJSON, GeoPackage, or a GeoTIFF's embedded GCPs
    (:func:`rectify.formats.gcps.read_gcps`; ``options.gcp_pixel`` their pixel convention), and the
    GCPs of ``src`` in orthority's GCP GeoJSON, ODM's ``gcp_list.txt`` or a Metashape markers XML
    (:func:`rectify.formats.detect.read_gcp_file`). With neither ``gcps_path`` nor ``transform_path``,
    the GCPs embedded in ``src`` are used when it carries some. The output, the report and the STAC
    Item are written all or none.

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
    elif options.gcp_pixel is not None:
        raise InvalidInputError(f"--gcp-pixel {options.gcp_pixel} applies to GCPs; a saved transform has none")
    # GDAL reads GDAL_CACHEMAX once, at its first block access: bound it before any pixel IO
    os.environ.setdefault("GDAL_CACHEMAX", "64")
    ws.add_inputs(*input_paths(src, gcps_path, transform_path))
    item = stac_path(dst) if options.stac else None
    ws.plan(dst, item)
    ws.check_report_dir()
    info = raster_info(src)
    wopts = WarpOptions(resampling=options.resampling, cog=options.cog, threads=options.threads,
                        max_pixels=options.max_pixels, scheduler=options.scheduler)
    gs = None
    if gcps_path is not None:  # any GCP file; of one of several images: SRC's
        gs = read_gcp_file(gcps_path, image=src, pixel=options.gcp_pixel, option="the source image's file name")
        gcps = gs.table
        check_table_crs(gs.path, gcps.crs, gcps.target, gcps.ids)
        if options.gcp_crs:  # --gcp-crs overrides the file's CRS: the coordinates must fit it too
            check_table_crs(gs.path, options.gcp_crs, gcps.target, gcps.ids)
    else:
        assert transform_path is not None
        tf = ws.load_transform(transform_path)
    report = None
    with staged(ws, dst) as tmp:  # the GeoTIFF, the report and the STAC Item: all or none
        if gs is not None:
            result = georectify(src, tmp, gcps, method=options.method, gcp_crs=options.gcp_crs,
                                dst_crs=options.dst_crs, resolution=options.resolution, options=wopts, overwrite=True,
                                progress=progress)
        else:
            result = rectify_with_transform(src, tmp, tf.model, model_crs=options.gcp_crs or tf.crs,
                                            dst_crs=options.dst_crs, resolution=options.resolution, options=wopts,
                                            overwrite=True, progress=progress)
        geometry = None
        if result.fit is not None:
            t = result.fit.table
            fitted = GcpTable(t.ids, t.position_px, t.observed, None, t.check, result.crs)
            geometry = judge_gcp_geometry(fitted, options.method, info.width, info.height, units=t.units)
        if ws.report_dir is not None:
            # local: the report (matplotlib, 0.24 s) loads only when --report asks for it
            from rectify.report.builder import write_warp_report

            report = write_warp_report(ws.report_dir, result, source_shape=(info.height, info.width),
                                       overwrite=ws.overwrite)
        if item is not None:
            write_stac(ws, item, item_id=Path(dst).stem, grid=raster_grid(tmp),
                       accuracy=residual_accuracy(result.fit.table if result.fit is not None else None, "gcp"),
                       assets={"image": StacAsset(dst, raster_roles(tmp), "georectified image", source=tmp)},
                       command="rectify warp",
                       options=options_of(options, gcps=gcps_path, transform=transform_path),
                       inputs=input_paths(src, gcps_path, transform_path))
    return WarpRun(result, options, Path(dst), report, geometry, gs.description if gs is not None else "",
                   item)
