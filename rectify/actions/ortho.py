"""``rectify ortho``: orthorectify an RPC or frame image over a DEM, optionally refined or checked by GCPs.

The file step of :func:`rectify.raster.ortho.orthorectify`: the sensor model from the image's RPC or
an RPC file (:mod:`rectify.formats.rpc`), or from a camera and an exterior orientation of any file
:mod:`rectify.formats.detect` recognises (an EO JSON; one image of a block orientation JSON, a
position/angle CSV, orthority's exterior parameters, a COLMAP model or a Metashape XML; the camera from
a camera JSON, orthority's int_param, an OpenCV calibration, COLMAP or Metashape:
:func:`rectify.formats.detect.read_frame_source_any`); GCPs of any file it recognises
(:func:`rectify.formats.detect.read_gcp_file`: the image's GCPs of orthority's, ODM's or Metashape's
files; heights from the file or the DEM) refine an RPC (:class:`rectify.geometry.rpc.RPCRefinement`) or
check a frame model; the report (:func:`rectify.report.ortho.write_ortho_report`); the STAC Item
(:mod:`rectify.actions.products`), staged with the orthophoto and the report.

Heights. Every height reaches the model's vertical frame once, by one stated conversion
(:func:`model_heights`): the model takes WGS 84 ellipsoidal heights (RPC) or its exterior orientation's
heights (frame camera: ellipsoidal when the DEM is converted by ``--undulation``/``--geoid`` or the
orientation's CRS declares ellipsoidal heights; else the vertical datum its CRS or the DEM's CRS
declares; else undeclared, the DEM's heights taken as they are). The DEM's file heights are converted
by :class:`rectify.raster.dem.Dem`; the GCP heights by :func:`gcp_heights`, from the datum given by
``--gcp-heights`` (``ellipsoidal``, ``dem`` or a vertical CRS) or declared by the GCP file's CRS
(``# crs=EPSG:4979``, ``# crs=EPSG:4326+3855``); GCP heights of no stated datum are taken in the
DEM's datum only when the DEM's heights are not converted, and refused otherwise.

GCP errors on the ground (:func:`ground_errors`): each GCP's observed pixel placed on the DEM by the
model (the orthophoto's own geometry), against the GCP's coordinates, in metres; for an RPC
refinement the leave-one-out model of each fit point is used, so the figure is the error an
independent point would have on the orthophoto.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.actions.common import Progress
from rectify.actions.products import options_of, raster_grid, raster_roles, residual_accuracy, stac_path, write_stac
from rectify.actions.workspace import Workspace
from rectify.errors import CRSError, InvalidInputError
from rectify.formats.detect import GCP_PIXEL, input_paths, read_frame_source_any, read_gcp_file
from rectify.formats.rpc import read_rpc, rpc_from_raster
from rectify.formats.stac import StacAsset
from rectify.geometry.accuracy import AccuracyStatement
from rectify.geometry.crs import (
    VerticalDatum,
    geoid_height,
    horizontal_crs,
    same_crs,
    transform_xy,
    unit_label,
    utm_crs,
    vertical_datum,
)
from rectify.geometry.points import GcpTable
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.rpc import RPCRefinement
from rectify.geometry.sensors import RPCModel, SensorModel
from rectify.raster.dem import Dem, ground_on_dem
from rectify.raster.engine import COMPRESSIONS, JPEG_QUALITY
from rectify.raster.io import bound_gdal_cache, raster_info
from rectify.raster.ortho import OrthoOptions, OrthoResult, orthorectify

__all__ = ["COMPRESSIONS", "JPEG_QUALITY",
           "OrthoOptions", "OrthoRunOptions", "OrthoRun", "GCP_HEIGHTS", "GCP_PIXEL", "ModelHeights", "ortho",
           "ortho_from_files", "gcp_heights", "ground_errors"]

#: the named datums of ``--gcp-heights`` (any vertical CRS, ``EPSG:5773``, is accepted too)
GCP_HEIGHTS = ("ellipsoidal", "dem")

_REPORT_FILES = ("ortho_report.json", "residuals.csv", "relief_shift.tif", "report.json", "report.html",
                 "fig_relief_shift.png")


@dataclass(frozen=True)
class OrthoRunOptions:
    """Options of :func:`ortho`.

    Attributes
    ----------
    eo_crs : str, optional
        CRS of the exterior orientation (overrides the file's ``crs``).
    refinement : str
        RPC bias model fitted to the GCPs: ``shift``, ``drift`` or ``affine``.
    dst_crs : str, optional
        Output CRS (default: the EO CRS, or the UTM zone of the image centre for RPC images).
    resolution : float, optional
        Output pixel size, output CRS units (default: as GDAL suggests).
    undulation : float, optional
        Geoid undulation N added to the DEM heights (h = H + N), metres.
    geoid : str, optional
        Geoid of the DEM heights (``EPSG:5773``; needs the PROJ grid).
    gcp_heights : str, optional
        Datum of the GCP heights: ``ellipsoidal``, ``dem`` (the DEM file's) or a vertical CRS
        (``EPSG:5773``); default the GCP file's CRS, else the DEM's when the DEM is not converted.
    image_id : str, optional
        The image of a file of several orientations (a block orientation JSON, a position/angle CSV,
        orthority's exterior parameters, a COLMAP model, a Metashape XML; default the source's file
        name or stem).
    camera_id : str, optional
        The camera of a camera file of several (orthority, COLMAP, Metashape; default the one the
        exterior orientation names, else the only one).
    focal_setting : float, optional
        The image's focal setting for a zoom camera (``stereo calibrate --zoom``; default the image's EXIF
        FocalLength); refused with another camera or an RPC.
    gcp_pixel : str, optional
        Pixel convention of GCPs embedded in a GeoTIFF: ``corner`` (GDAL's, the default) or ``centre``
        (orthority's).
    stac : bool
        Write the STAC Item ``<output stem>.stac.json`` beside the orthophoto.
    dem_height : float, optional
        A constant ground height (m) instead of a DEM file (``--dem-height``; exclusive with the DEM): in
        the model's heights, WGS 84 ellipsoidal for an RPC, the exterior orientation's heights for a frame
        camera; no datum conversion (``undulation``/``geoid`` refused with it).
    engine : OrthoOptions
        Resampling, tiles, threads, compression, COG, true ortho, scheduler.
    """

    eo_crs: str | None = None
    refinement: str = "shift"
    dst_crs: str | None = None
    resolution: float | None = None
    undulation: float | None = None
    geoid: str | None = None
    gcp_heights: str | None = None
    image_id: str | None = None
    camera_id: str | None = None
    focal_setting: float | None = None
    gcp_pixel: str | None = None
    stac: bool = True
    dem_height: float | None = None
    engine: OrthoOptions = field(default_factory=OrthoOptions)


@dataclass(frozen=True)
class ModelHeights:
    """The vertical frame of the sensor model's heights.

    ``kind``: ``ellipsoidal`` (WGS 84 ellipsoidal heights), ``vertical`` (heights above ``vertical``)
    or ``undeclared`` (a frame camera whose heights are the DEM's, of no declared datum).
    """

    kind: str
    label: str
    vertical: VerticalDatum | None = None

    def undulation(self, lonlat: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """N (m) of the model's heights at WGS 84 lon/lat (h_ellipsoidal = H + N); None when undeclared."""
        if self.kind == "ellipsoidal":
            return np.zeros(len(lonlat))
        if self.kind == "vertical" and self.vertical is not None and self.vertical.crs is not None:
            return geoid_height(self.vertical.crs, lonlat)
        return None


@dataclass(frozen=True)
class OrthoRun:
    """What :func:`ortho` did: the ortho, the height statements, and the GCP residuals when GCPs were given."""

    result: OrthoResult
    residuals: Any = None  # ResidualTable (px) or None
    model_kind: str = ""
    report_files: list[Path] | None = None
    heights: dict[str, str] = field(default_factory=dict)
    ground: dict[str, Any] | None = None
    source: str = ""
    gcp_source: str = ""
    stac: Path | None = None

    def summary_lines(self) -> list[str]:
        out = []
        if self.source:
            out.append(f"orientation: {self.source}")
        if self.gcp_source:
            out.append(f"GCPs: {self.gcp_source}")
        out += [f"{k}: {v}" for k, v in self.heights.items()]
        if self.residuals is not None:
            out.append(f"{self.residuals.step}: {self.residuals.summary_line()}")
            loo = self.residuals.extra.get("loo_rmse_px")
            raw = self.residuals.extra.get("rpc_only_rmse_px")
            if raw is not None:
                out.append(f"GCP error of the RPC alone: RMSE {raw:.4g} px" +
                           (f"; leave-one-out check RMSE after refinement {loo:.4g} px" if loo is not None else ""))
        if self.ground:
            for key in ("leave_one_out", "check"):
                g = self.ground.get(key)
                if g:
                    out.append(g["line"])
                    out.extend(g.get("accuracy_statement", {}).get("lines", ()))
        out += self.result.summary_lines()
        if self.report_files:
            out.append(f"report: {', '.join(str(p) for p in self.report_files)}")
        if self.stac is not None:
            out.append(f"wrote {self.stac} (STAC Item)")
        return out


def model_heights(use_rpc: bool, eo_vertical: VerticalDatum | None, dem: Dem) -> ModelHeights:
    """The model's vertical frame, given the orientation's declared heights and the DEM (module docstring).

    Raises
    ------
    InvalidInputError
        A frame orientation declaring heights above one vertical datum and a DEM converted to, or
        declaring, another.
    """
    if use_rpc:
        return ModelHeights("ellipsoidal", "WGS 84 ellipsoidal heights (what an RPC takes)")
    if dem.constant is not None:
        if eo_vertical is not None and eo_vertical.ellipsoidal:
            return ModelHeights("ellipsoidal", "ellipsoidal heights (declared by the exterior orientation's CRS)")
        if eo_vertical is not None:
            return ModelHeights("vertical", f"{eo_vertical.label} (declared by the exterior orientation's CRS)",
                                eo_vertical)
        return ModelHeights("undeclared", "the exterior orientation's heights (--dem-height is taken in them)")
    converted = dem.undulation != 0.0 or dem.geoid is not None
    if eo_vertical is not None and eo_vertical.ellipsoidal:
        return ModelHeights("ellipsoidal", "ellipsoidal heights (declared by the exterior orientation's CRS)")
    if eo_vertical is not None:
        if converted or (dem.declared is not None and not _same_vertical(dem.declared, eo_vertical)):
            raise InvalidInputError(f"the exterior orientation's heights are above {eo_vertical.label} (its CRS) "
                                    f"but the DEM's become other heights ({dem.datum}): give the DEM in "
                                    f"{eo_vertical.label} heights, or convert one of them")
        return ModelHeights("vertical", f"{eo_vertical.label} (declared by the exterior orientation's CRS)",
                            eo_vertical)
    if converted:
        return ModelHeights("ellipsoidal", "ellipsoidal heights (the exterior orientation's, as --undulation/--geoid "
                                           "say)")
    if dem.declared is not None and not dem.declared.ellipsoidal:
        return ModelHeights("vertical", f"{dem.declared.label}, the DEM's (the exterior orientation's CRS declares "
                                        f"no heights)", dem.declared)
    if dem.declared is not None:
        return ModelHeights("ellipsoidal", "ellipsoidal heights, the DEM's (the exterior orientation's CRS declares "
                                           "no heights)")
    return ModelHeights("undeclared", "the exterior orientation's heights, taken to be the DEM's (neither CRS "
                                      "declares a vertical datum)")


def _same_vertical(a: VerticalDatum, b: VerticalDatum) -> bool:
    if a.ellipsoidal or b.ellipsoidal:
        return a.ellipsoidal == b.ellipsoidal
    return a.crs is not None and b.crs is not None and same_crs(a.crs, b.crs)


def _gcp_datum(option: str | None, gcps: GcpTable, path: str | Path) -> tuple[str, VerticalDatum | None, str]:
    """(``ellipsoidal`` | ``dem`` | ``vertical`` | ``undeclared``, the vertical datum, where it was stated)."""
    if option is not None:
        opt = option.strip()
        if opt.lower() in GCP_HEIGHTS:
            return opt.lower(), None, f"--gcp-heights {opt.lower()}"
        try:
            v = vertical_datum(opt)
        except CRSError as err:
            raise InvalidInputError(f"--gcp-heights {opt!r} is neither 'ellipsoidal', 'dem' nor a vertical CRS: "
                                    f"{err}") from err
        if v is None:
            raise InvalidInputError(f"--gcp-heights {opt!r} declares no heights; give 'ellipsoidal', 'dem' or a "
                                    f"vertical CRS such as EPSG:5773")
        return ("ellipsoidal" if v.ellipsoidal else "vertical"), v, f"--gcp-heights {opt}"
    v = vertical_datum(gcps.crs) if gcps.crs else None
    if v is not None:
        return ("ellipsoidal" if v.ellipsoidal else "vertical"), v, f"the CRS of {str(path)!r}"
    return "undeclared", None, ""


def gcp_heights(gcps: GcpTable, path: str | Path, lonlat: NDArray[np.float64], dem: Dem, target: ModelHeights,
                option: str | None) -> tuple[NDArray[np.float64], str]:
    """The GCP heights in the model's vertical frame, and the one-line statement of their conversion.

    Raises
    ------
    InvalidInputError
        Heights of no stated datum while the DEM's heights are converted; ellipsoidal or geoid heights
        for a model of undeclared heights (the message names ``--gcp-heights``).
    CRSError
        A geoid grid the conversion needs is not installed.
    """
    assert gcps.z is not None
    z = np.asarray(gcps.z, dtype=np.float64)
    kind, v, stated = _gcp_datum(option, gcps, path)
    dem_converted = dem.undulation != 0.0 or dem.geoid is not None
    if kind == "undeclared":
        if dem_converted:
            raise InvalidInputError(
                f"the GCP heights of {str(path)!r} state no datum while the DEM's heights are converted "
                f"({dem.datum}): say which heights the GCPs hold with --gcp-heights ellipsoidal|dem|EPSG:nnnn "
                f"(or a vertical CRS in the file's '# crs=' line, e.g. EPSG:4979 or EPSG:4326+5773)")
        return z, "no datum stated: taken in the DEM's datum, used as they are"
    if kind == "dem":
        off = dem.offset(lonlat)
        how = "used as they are" if not dem_converted else \
            f"converted as the DEM's (+ {float(off.min()):.2f} .. {float(off.max()):.2f} m)"
        return z + off, f"in the DEM's datum ({stated}), {how}"
    name = "ellipsoidal" if kind == "ellipsoidal" else f"above {v.label if v else '?'}"
    if kind == "vertical" and target.kind == "vertical" and v is not None and target.vertical is not None \
            and _same_vertical(v, target.vertical):
        return z, f"{name} ({stated}), the model's heights: used as they are"
    if kind == "ellipsoidal" and target.kind == "ellipsoidal":
        return z, f"{name} ({stated}), the model's heights: used as they are"
    n_model = target.undulation(lonlat)
    if n_model is None:
        raise InvalidInputError(f"GCP heights {name} ({stated}) cannot become the model's heights: {target.label}; "
                                f"give the GCPs in the DEM's heights (--gcp-heights dem)")
    n_gcp = np.zeros(len(z)) if kind == "ellipsoidal" else geoid_height(v.crs, lonlat)  # type: ignore[union-attr]
    off = n_gcp - n_model
    return z + off, (f"{name} ({stated}), converted to {target.label}: {float(off.min()):+.2f} .. "
                     f"{float(off.max()):+.2f} m")


def _gcp_ground(gcps: GcpTable, path: str | Path, dem: Dem, crs: str, target: ModelHeights,
                option: str | None) -> tuple[NDArray[np.float64], str]:
    """GCP ground points (N, 3) in ``crs``: x, y from the file (its CRS), z from the file or the DEM; the statement."""
    src_crs = horizontal_crs(gcps.crs) if gcps.crs else crs
    xy = transform_xy(src_crs, crs, gcps.target) if gcps.crs else np.asarray(gcps.target, dtype=np.float64)
    if gcps.z is not None:
        lonlat = xy if same_crs(crs, "EPSG:4326") else transform_xy(crs, "EPSG:4326", xy)
        z, how = gcp_heights(gcps, path, lonlat, dem, target, option)
    else:
        if option is not None:
            raise InvalidInputError(f"--gcp-heights {option} given but {str(path)!r} has no heights (z): they come "
                                    f"from the DEM")
        z = dem.sample(xy, crs)
        if not np.isfinite(z).all():
            i = int(np.flatnonzero(~np.isfinite(z))[0])
            raise InvalidInputError(f"GCP {gcps.ids[i]!r} has no z and lies outside the DEM")
        how = "none in the file: taken from the DEM"
    return np.column_stack([xy, z]), how


def _metric(crs: str, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points in metres: as they are in a metric CRS, else in the UTM zone of their centre."""
    if unit_label(crs) == "m" or not len(xy):
        return xy
    ll = xy if same_crs(crs, "EPSG:4326") else transform_xy(crs, "EPSG:4326", xy)
    lon, lat = (float(v) for v in np.nanmean(ll, axis=0))
    return transform_xy("EPSG:4326", utm_crs(lon, lat), ll)


def _errors_line(what: str, ids: list[str], d: NDArray[np.float64], n_missed: int) -> dict[str, Any]:
    ok = np.isfinite(d)
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("nan")
    dmax = float(d[ok].max()) if ok.any() else float("nan")
    worst = ids[int(np.nanargmax(np.where(ok, d, -1.0)))] if ok.any() else None
    line = (f"{what}: RMSE {rmse:.3f} m, max {dmax:.3f} m ({worst}) over {int(ok.sum())} GCPs"
            + (f"; {n_missed} off the DEM" if n_missed else ""))
    return {"line": line, "rmse_m": rmse, "max_m": dmax, "n": int(ok.sum()), "missed": n_missed,
            "errors_m": {i: (float(v) if np.isfinite(v) else None) for i, v in zip(ids, d, strict=True)}}


def ground_errors(model: SensorModel, dem: Dem, gcps: GcpTable, ground: NDArray[np.float64],
                  table: ResidualTable) -> dict[str, Any]:
    """GCP errors on the orthophoto, metres: each observed pixel placed on the DEM by the model, against the GCP.

    For an RPC refinement, fit points use their leave-one-out model (``leave_one_out``) and check
    points the refined model (``check``); for a frame model every GCP is a check point. The
    leave-one-out model of point i differs from the full one by a bias; its ground point is that of
    the observed pixel minus the bias difference at the point (exact for ``shift``, to the change of
    that difference across the pixel's displacement otherwise).
    """
    obs = np.asarray(gcps.pixel, dtype=np.float64)
    ids = [str(i) for i in gcps.ids]
    chk = np.asarray(table.check if table.check is not None else np.zeros(len(ids), bool), dtype=bool)
    out: dict[str, Any] = {}

    def errors(pixels: NDArray[np.float64], rows: NDArray[np.intp]) -> tuple[NDArray[np.float64], int]:
        """(N, 2) error vectors (east, north, m; NaN off the DEM) and the count off the DEM."""
        g = ground_on_dem(model, dem, pixels)
        ok = np.isfinite(g).all(axis=1)
        v = np.full((len(pixels), 2), np.nan)
        if ok.any():
            v[ok] = _error_vectors(model.crs, g[ok, :2], ground[rows[ok], :2])
        return v, int((~ok).sum())

    rpc = getattr(model, "rpc", None)
    loo = getattr(rpc, "loo_errors", None)
    if isinstance(rpc, RPCRefinement) and loo is not None:
        fit = np.flatnonzero(~chk)
        e = np.full((len(ids), 2), np.nan)
        e[fit] = loo
        adj = np.asarray(table.adjusted, dtype=np.float64)
        use = fit[np.isfinite(e[fit]).all(axis=1)]
        if len(use):
            shifted = obs[use] - ((obs[use] + e[use]) - adj[use])
            v, missed = errors(shifted, use)
            out["leave_one_out"] = _errors_line(
                "leave-one-out check on the orthophoto (each fit GCP placed on the DEM by the refinement fitted "
                "without it)", [ids[i] for i in use], np.hypot(v[:, 0], v[:, 1]), missed)
    if chk.any():
        sel = np.flatnonzero(chk)
        v, missed = errors(obs[sel], sel)
        label = "check points on the orthophoto (placed on the DEM by the model)" if rpc is not None \
            else "GCPs on the orthophoto (placed on the DEM by the frame model)"
        out["check"] = _errors_line(label, [ids[i] for i in sel], np.hypot(v[:, 0], v[:, 1]), missed)
        full = np.isfinite(v).all(axis=1)
        if full.any():   # the check points' planimetric accuracy in the standard forms (issue 27)
            out["check"]["accuracy_statement"] = AccuracyStatement.from_errors(v[full]).to_dict()
    return out


def _error_vectors(crs: str, a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Horizontal error vectors a - b (m, east and north) between points of a CRS (in the UTM zone of b's centre
    when the CRS is not metric)."""
    both = _metric(crs, np.vstack([b, a]))
    return np.asarray(both[len(b):] - both[:len(b)], dtype=np.float64)


def _height_check(ground: NDArray[np.float64], crs: str, dem: Dem, has_z: bool) -> str | None:
    """'GCP heights - DEM at the GCPs' statement (model heights both), or None without file heights."""
    if not has_z:
        return None
    h_dem = dem.sample(ground[:, :2], crs)
    ok = np.isfinite(h_dem)
    if not ok.any():
        return "GCP heights - DEM: no GCP on the DEM"
    d = ground[ok, 2] - h_dem[ok]
    return (f"median {float(np.median(d)):+.2f} m, largest |difference| {float(np.abs(d).max()):.2f} m at "
            f"{int(ok.sum())} GCPs on the DEM")


def _dem_of(dem_path: str | Path | None, o: OrthoRunOptions, convert: bool, crs: str) -> Dem:
    """The DEM file, or the constant height of ``o.dem_height`` (exactly one of them; one-line errors)."""
    if dem_path is not None and o.dem_height is not None:
        raise InvalidInputError(f"give a DEM (--dem {str(dem_path)!r}) or a constant height (--dem-height "
                                f"{o.dem_height!r}), not both")
    if dem_path is None and o.dem_height is None:
        raise InvalidInputError("give a DEM (--dem DEM.tif) or a constant ground height (--dem-height H, metres "
                                "in the model's heights)")
    if dem_path is None:
        if o.undulation is not None or o.geoid is not None:
            given = f"--undulation {o.undulation!r}" if o.undulation is not None else f"--geoid {o.geoid}"
            raise InvalidInputError(f"{given} converts a DEM file's heights; --dem-height {o.dem_height!r} is "
                                    f"already in the model's heights (leave {given.split()[0]} out)")
        return Dem.constant_height(o.dem_height, crs)  # type: ignore[arg-type]
    return Dem.from_path(dem_path, undulation=o.undulation, geoid=o.geoid, convert_declared=convert)


def ortho(ws: Workspace, src: str | Path, dst: str | Path, dem_path: str | Path | None, *,
          rpc: str | Path | bool = False,
          camera: str | Path | None = None, exterior: str | Path | None = None, gcps: str | Path | None = None,
          options: OrthoRunOptions = OrthoRunOptions(), progress: Progress = None) -> OrthoRun:
    """Orthorectify ``src`` with its RPC (``rpc=True``: from the image; a path: an RPC file) or a frame camera.

    With ``gcps`` (any GCP file ``rectify`` reads; z optional, taken from the
    DEM when absent): an RPC is refined (``options.refinement``: shift, drift,
    affine) and the residual table carries leave-one-out errors; a frame
    camera is only checked (image residuals of the GCPs). Both also give the GCP errors on the
    orthophoto in metres (:func:`ground_errors`). The overwrite policy and the report folder are the
    workspace's.

    ``dem_path`` None: the constant height ``options.dem_height`` instead (exactly one of them).

    Raises
    ------
    InvalidInputError
        Neither or both of ``rpc`` and ``camera``/``exterior``, neither or both of ``dem_path`` and
        ``options.dem_height`` (or a non-finite height), bad files, GCP heights of no stated datum with
        a converted DEM.
    """
    bound_gdal_cache()  # before any pixel IO
    if (dem_path is None) == (options.dem_height is None):  # before any file is read
        _dem_of(dem_path, options, False, "EPSG:4326")
    if options.dem_height is not None:
        Dem.constant_height(options.dem_height, "EPSG:4326")  # a bad height fails here, before any work
    report_dir = ws.report_dir
    use_rpc = bool(rpc)
    if use_rpc == (camera is not None or exterior is not None):
        raise InvalidInputError("give either an RPC (--rpc) or a frame camera (--camera and --exterior)")
    if not use_rpc and exterior is None:
        raise InvalidInputError("a frame camera needs both --camera CAM.json and --exterior EO.json (or --exterior "
                                "with a block's orientation.json, which holds the cameras)")
    if use_rpc and options.image_id is not None:
        raise InvalidInputError(f"--image-id {options.image_id!r} names an image of a block orientation or pose "
                                f"file (--exterior); an RPC image needs none")
    # the output plan (the orthophoto and every report file) against every input, before any work
    rpc_file = rpc if isinstance(rpc, (str, Path)) else None
    ws.add_inputs(*input_paths(src, dem_path, camera, exterior, gcps, rpc_file))
    item = stac_path(dst) if options.stac else None
    if report_dir is not None:
        rd = Path(report_dir)
        if rd.exists() and not rd.is_dir():
            raise InvalidInputError(f"report folder {str(rd)!r} is a file")
        ws.check_report_dir()
    ws.plan(dst, item, *((Path(report_dir) / n for n in _REPORT_FILES) if report_dir is not None else ()))
    o = options
    if o.gcp_heights is not None and gcps is None:
        raise InvalidInputError(f"--gcp-heights {o.gcp_heights} given without --gcps")
    table = None
    model: SensorModel
    source = ""
    eo_vertical = None
    if not use_rpc:
        fs = read_frame_source_any(camera, exterior, crs=o.eo_crs, image_id=o.image_id,  # type: ignore[arg-type]
                                   image_path=src, camera_id=o.camera_id, focal_setting=o.focal_setting)
        model, source, eo_vertical = fs.model, fs.description, fs.vertical
    elif o.camera_id is not None:
        raise InvalidInputError(f"--camera-id {o.camera_id!r} names a camera of a camera file; an RPC image needs none")
    elif o.focal_setting is not None:
        raise InvalidInputError(f"--focal-setting {o.focal_setting:g} goes with a zoom camera (--camera); an RPC "
                                "image needs none")
    gs = None
    if gcps is not None:  # any GCP file; one of several images: the source's (or --image-id's)
        gs = read_gcp_file(gcps, image=o.image_id or src, pixel=o.gcp_pixel, option="--image-id")
        gcps = gs.path
    elif o.gcp_pixel is not None:
        raise InvalidInputError(f"--gcp-pixel {o.gcp_pixel} given without --gcps")
    # a frame orientation in the DEM's declared heights keeps them; an RPC (or an ellipsoidal EO) converts them
    convert = use_rpc or (eo_vertical is not None and eo_vertical.ellipsoidal)
    dem = _dem_of(dem_path, o, convert, "EPSG:4326" if use_rpc else model.crs)
    target = model_heights(use_rpc, eo_vertical, dem)
    heights = {"heights": f"{dem.datum}; the model takes {target.label}"}
    ground_check = None
    if use_rpc:
        info = raster_info(src)
        r = rpc_from_raster(src) if rpc is True else read_rpc(rpc)  # type: ignore[arg-type]
        model_rpc: Any = r
        if gs is not None:
            g = gs.table
            ground, how = _gcp_ground(g, gs.path, dem, "EPSG:4326", target, o.gcp_heights)
            ref = RPCRefinement.from_gcps(r, g.pixel, ground, model=o.refinement, ids=list(g.ids), check=g.check)
            model_rpc, table = ref, ref.residuals
        model = RPCModel(model_rpc, info.width, info.height)
    elif gs is not None:
        g = gs.table
        ground, how = _gcp_ground(g, gs.path, dem, model.crs, target, o.gcp_heights)
        adj = model.project(ground)
        table = ResidualTable(step="GCP check (frame model)", ids=list(g.ids), observed=g.pixel, adjusted=adj,
                              units="px", check=np.ones(len(g.ids), bool), position_px=g.pixel)
    if gcps is not None and table is not None:
        heights["GCP heights"] = how
        diff = _height_check(ground, model.crs, dem, g.z is not None)
        if diff is not None:
            heights["GCP heights - DEM at the GCPs"] = diff
        ground_check = ground_errors(model, dem, g, ground, table)
    # the orthophoto and the report, all or none (a full disk, an error or SIGTERM leaves neither)
    with ws.transaction():
        with ws.output(dst, suffix=Path(dst).suffix or ".tif") as tmp:
            result = orthorectify(src, tmp, model, dem, dst_crs=o.dst_crs, resolution=o.resolution,
                                  options=o.engine, overwrite=True, progress=progress)
        result = dataclasses.replace(result, path=Path(dst))
        gcp_note = gs.description if gs is not None else ""
        run = OrthoRun(result, table, type(model).__name__, None, heights, ground_check, source, gcp_note)
        if report_dir is not None:
            # local: the report code and matplotlib load only when --report asks for them
            from rectify.report.ortho import write_ortho_report

            with ws.report_folder() as stage:
                written = write_ortho_report(stage, result, table, run.summary_lines(), model, dem, overwrite=True,
                                             heights=heights, gcp_ground=ground_check)
            paths = [Path(report_dir) / Path(q).relative_to(stage) for q in written]
            run = OrthoRun(result, table, type(model).__name__, paths, heights, ground_check, source, gcp_note)
        if item is not None:  # the STAC Item of the staged orthophoto, in the same transaction
            acc = residual_accuracy(table, "gcp")
            for key in ("leave_one_out", "check"):
                if ground_check and ground_check.get(key):
                    acc[f"gcp_{key}_rmse_m"] = ground_check[key]["rmse_m"]
            acc["max_relief_shift_m"] = result.max_relief_shift
            write_stac(ws, item, item_id=Path(dst).stem, grid=raster_grid(tmp), accuracy=acc, command="rectify ortho",
                       assets={"ortho": StacAsset(dst, raster_roles(tmp), "orthophoto", source=tmp)},
                       options=options_of(o, rpc=rpc_file or bool(rpc), camera=camera, exterior=exterior, gcps=gcps,
                                          dem=dem_path, model=type(model).__name__),
                       inputs=input_paths(src, dem_path, camera, exterior, gcps, rpc_file))
            run = dataclasses.replace(run, stac=item)
    return run


def ortho_from_files(src: str | Path, dst: str | Path, dem_path: str | Path | None, *,
                     rpc: str | Path | bool = False,
                     camera: str | Path | None = None, exterior: str | Path | None = None,
                     eo_crs: str | None = None, gcps: str | Path | None = None, refinement: str = "shift",
                     dst_crs: str | None = None, resolution: float | None = None, undulation: float | None = None,
                     geoid: str | None = None, gcp_heights: str | None = None, image_id: str | None = None,
                     options: OrthoOptions | None = None, overwrite: bool = False,
                     progress: Progress = None, report_dir: str | Path | None = None,
                     dem_height: float | None = None, stac: bool = True) -> OrthoRun:
    """:func:`ortho` in one call with keyword options (a workspace of ``overwrite`` and ``report_dir``)."""
    opts = OrthoRunOptions(eo_crs=eo_crs, refinement=refinement, dst_crs=dst_crs, resolution=resolution,
                           undulation=undulation, geoid=geoid, gcp_heights=gcp_heights, image_id=image_id,
                           engine=options or OrthoOptions(), dem_height=dem_height, stac=stac)
    return ortho(Workspace(overwrite=overwrite, report_dir=report_dir), src, dst, dem_path, rpc=rpc, camera=camera,
                 exterior=exterior, gcps=gcps, options=opts, progress=progress)
