"""``rectify ortho``: orthorectify an RPC or frame image over a DEM, optionally refined or checked by GCPs.

The file step of :func:`rectify.raster.ortho.orthorectify`: the sensor model from the image's RPC or
an RPC file (:mod:`rectify.formats.rpc`), or from a camera JSON and an exterior orientation JSON
(:func:`rectify.formats.exterior.read_frame_model`); GCPs (:func:`rectify.formats.gcps.read_gcps`,
heights from the file or the DEM) refine an RPC (:class:`rectify.geometry.rpc.RPCRefinement`) or check
a frame model; the report (:func:`rectify.report.ortho.write_ortho_report`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.atomic import check_output
from rectify.errors import InvalidInputError
from rectify.formats.exterior import read_frame_model
from rectify.formats.gcps import read_gcps
from rectify.formats.rpc import read_rpc, rpc_from_raster
from rectify.geometry.crs import transform_xy
from rectify.geometry.points import GcpTable
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.rpc import RPCRefinement
from rectify.geometry.sensors import RPCModel, SensorModel
from rectify.raster.dem import Dem
from rectify.raster.io import bound_gdal_cache, raster_info
from rectify.raster.ortho import OrthoOptions, OrthoResult, orthorectify
from rectify.report.ortho import write_ortho_report

__all__ = ["OrthoOptions", "OrthoRunOptions", "OrthoRun", "ortho", "ortho_from_files"]


@dataclass(frozen=True)
class OrthoRunOptions:
    """Options of :func:`ortho`.

    Attributes
    ----------
    eo_crs : str, optional
        CRS of the exterior orientation (overrides the JSON's ``crs``).
    refinement : str
        RPC bias model fitted to the GCPs: ``shift``, ``drift`` or ``affine``.
    dst_crs : str, optional
        Output CRS (default: the EO CRS, or the UTM zone of the image centre for RPC images).
    resolution : float, optional
        Output pixel size, output CRS units (default: as GDAL suggests).
    undulation : float
        Geoid undulation N added to the DEM heights (h = H + N), metres.
    geoid : str, optional
        Geoid of the DEM heights (``EPSG:5773``; needs the PROJ grid).
    engine : OrthoOptions
        Resampling, tiles, threads, compression, COG, true ortho, scheduler.
    """

    eo_crs: str | None = None
    refinement: str = "shift"
    dst_crs: str | None = None
    resolution: float | None = None
    undulation: float = 0.0
    geoid: str | None = None
    engine: OrthoOptions = field(default_factory=OrthoOptions)


@dataclass(frozen=True)
class OrthoRun:
    """What :func:`ortho` did: the ortho, and the GCP residuals when GCPs were given."""

    result: OrthoResult
    residuals: Any = None  # ResidualTable (px) or None
    model_kind: str = ""
    report_files: list[Path] | None = None

    def summary_lines(self) -> list[str]:
        out = []
        if self.residuals is not None:
            out.append(f"{self.residuals.step}: {self.residuals.summary_line()}")
            loo = self.residuals.extra.get("loo_rmse_px")
            raw = self.residuals.extra.get("rpc_only_rmse_px")
            if raw is not None:
                out.append(f"GCP error of the RPC alone: RMSE {raw:.4g} px" +
                           (f"; leave-one-out check RMSE after refinement {loo:.4g} px" if loo is not None else ""))
        out += self.result.summary_lines()
        if self.report_files:
            out.append(f"report: {', '.join(str(p) for p in self.report_files)}")
        return out


def _gcp_ground(gcps: GcpTable, dem: Dem, crs: str) -> NDArray[np.float64]:
    """GCP ground points (N, 3) in ``crs``: x, y from the file (its CRS), z from the file or the DEM."""
    src_crs = gcps.crs or crs
    xy = transform_xy(src_crs, crs, gcps.target) if gcps.crs else np.asarray(gcps.target, dtype=np.float64)
    if gcps.z is not None:
        z = np.asarray(gcps.z, dtype=np.float64) + dem.undulation
    else:
        z = dem.sample(xy, crs)
        if not np.isfinite(z).all():
            i = int(np.flatnonzero(~np.isfinite(z))[0])
            raise InvalidInputError(f"GCP {gcps.ids[i]!r} has no z and lies outside the DEM")
    return np.column_stack([xy, z])


def ortho(ws: Workspace, src: str | Path, dst: str | Path, dem_path: str | Path, *, rpc: str | Path | bool = False,
          camera: str | Path | None = None, exterior: str | Path | None = None, gcps: str | Path | None = None,
          options: OrthoRunOptions = OrthoRunOptions(), progress: Progress = None) -> OrthoRun:
    """Orthorectify ``src`` with its RPC (``rpc=True``: from the image; a path: an RPC file) or a frame camera.

    With ``gcps`` (any GCP file ``rectify`` reads; z optional, taken from the
    DEM when absent): an RPC is refined (``options.refinement``: shift, drift,
    affine) and the residual table carries leave-one-out errors; a frame
    camera is only checked (image residuals of the GCPs). The overwrite policy and the report
    folder are the workspace's.

    Raises
    ------
    InvalidInputError
        Neither or both of ``rpc`` and ``camera``/``exterior``, bad files.
    """
    bound_gdal_cache()  # before any pixel IO
    overwrite, report_dir = ws.overwrite, ws.report_dir
    use_rpc = bool(rpc)
    if use_rpc == (camera is not None or exterior is not None):
        raise InvalidInputError("give either an RPC (--rpc) or a frame camera (--camera and --exterior)")
    if not use_rpc and (camera is None or exterior is None):
        raise InvalidInputError("a frame camera needs both --camera CAM.json and --exterior EO.json")
    for p in (src, dem_path, camera, exterior, gcps, rpc if isinstance(rpc, (str, Path)) else None):
        if p is not None and Path(dst).exists() and Path(p).exists() and Path(dst).resolve() == Path(p).resolve():
            raise InvalidInputError(f"output {str(dst)!r} is an input; inputs are never modified")
    ws.add_inputs(src, dem_path, camera, exterior, gcps, rpc if isinstance(rpc, (str, Path)) else None)
    check_output(dst, overwrite=overwrite)
    if report_dir is not None:  # fail before the work, not after
        rd = Path(report_dir)
        if rd.exists() and not rd.is_dir():
            raise InvalidInputError(f"report folder {str(rd)!r} is a file")
        if rd.is_dir():
            for name in ("ortho_report.json", "residuals.csv", "relief_shift.tif"):
                check_output(rd / name, overwrite=overwrite)
    o = options
    dem = Dem.from_path(dem_path, undulation=o.undulation, geoid=o.geoid)
    info = raster_info(src)
    table = None
    model: SensorModel
    if use_rpc:
        r = rpc_from_raster(src) if rpc is True else read_rpc(rpc)  # type: ignore[arg-type]
        model_rpc: Any = r
        if gcps is not None:
            g = read_gcps(gcps)
            ground = _gcp_ground(g, dem, "EPSG:4326")
            ref = RPCRefinement.from_gcps(r, g.pixel, ground, model=o.refinement, ids=list(g.ids), check=g.check)
            model_rpc, table = ref, ref.residuals
        model = RPCModel(model_rpc, info.width, info.height)
    else:
        model = read_frame_model(str(camera), str(exterior), crs=o.eo_crs)
        if gcps is not None:
            g = read_gcps(gcps)
            ground = _gcp_ground(g, dem, model.crs)
            adj = model.project(ground)
            table = ResidualTable(step="GCP check (frame model)", ids=list(g.ids), observed=g.pixel, adjusted=adj,
                                  units="px", check=np.ones(len(g.ids), bool), position_px=g.pixel)
    result = orthorectify(src, dst, model, dem, dst_crs=o.dst_crs, resolution=o.resolution, options=o.engine,
                          overwrite=overwrite, progress=progress)
    run = OrthoRun(result, table, type(model).__name__)
    if report_dir is not None:
        paths = write_ortho_report(report_dir, result, table, run.summary_lines(), model, dem, overwrite=overwrite)
        run = OrthoRun(result, table, type(model).__name__, paths)
    return run


def ortho_from_files(src: str | Path, dst: str | Path, dem_path: str | Path, *, rpc: str | Path | bool = False,
                     camera: str | Path | None = None, exterior: str | Path | None = None,
                     eo_crs: str | None = None, gcps: str | Path | None = None, refinement: str = "shift",
                     dst_crs: str | None = None, resolution: float | None = None, undulation: float = 0.0,
                     geoid: str | None = None, options: OrthoOptions | None = None, overwrite: bool = False,
                     progress: Progress = None, report_dir: str | Path | None = None) -> OrthoRun:
    """:func:`ortho` in one call with keyword options (a workspace of ``overwrite`` and ``report_dir``)."""
    opts = OrthoRunOptions(eo_crs=eo_crs, refinement=refinement, dst_crs=dst_crs, resolution=resolution,
                           undulation=undulation, geoid=geoid, engine=options or OrthoOptions())
    return ortho(Workspace(overwrite=overwrite, report_dir=report_dir), src, dst, dem_path, rpc=rpc, camera=camera,
                 exterior=exterior, gcps=gcps, options=opts, progress=progress)
