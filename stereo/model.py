"""The stereo model of a pair: seed 002's double resection in four stages.

1. relative orientation (:mod:`stereo.relative`) from tie points;
2. model points by intersection (:mod:`stereo.intersection`);
3. absolute orientation of the model to ground control (:mod:`stereo.absolute`);
4. ground coordinates of every point, with predicted standard errors.

Absolute orientation happens by default in a local topocentric (ENU) frame
at the middle of the block (seed 004): control map coordinates (E, N, h) go
to geocentric and then to ENU at the control centroid (:mod:`rectify.geodesy`),
the similarity is estimated there, and ground points come back to the map
CRS. A map CRS is not a Cartesian frame (scale factor, Earth curvature), so
a similarity fitted directly in map coordinates (``frame="map"``) absorbs
part of the distortion; the pipeline runs both when the control has a CRS
and reports the difference. Heights are treated as ellipsoidal in the
conversion; for a geoid-referenced height the undulation, constant over a
block, cancels on the way back.

:class:`Workspace` owns the output folder layout; :func:`run_pair` and
:func:`run_model` load, compute and save.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.camera import Camera
from rectify.crs import unit_label
from rectify.errors import CRSError, InvalidInputError
from rectify.fileutil import check_output
from rectify.points import as_ids
from rectify.residuals import ResidualTable, rms
from rectify.formats import ControlTable, Matches

from .absolute import AbsoluteOrientation
from .formats import orientation_dict, write_orientation, write_ply, write_points_csv, write_relative
from .intersection import METHODS, Intersection, intersect
from .relative import RelativeGeometry, RelativeOrientation

logger = logging.getLogger(__name__)

__all__ = ["ModelOptions", "StereoModel", "Workspace", "build_model", "match_control", "run_model", "run_pair",
           "FRAMES", "ground_unit", "write_pair_report"]

FRAMES = ("topocentric", "map")


@dataclass(frozen=True)
class ModelOptions:
    """Options of the pair pipeline.

    Attributes
    ----------
    intersection : str
        Intersection method (see :data:`stereo.intersection.METHODS`).
    frame : {"topocentric", "map"}
        Where absolute orientation is estimated (see the module docstring).
    robust : str
        Robust absolute orientation: none, huber, tukey, hampel, andrews.
    deformation_order : int or None
        Seed 002's polynomial deformation correction (2 or 3).
    ro_system : str
        System of relative orientation elements for :func:`run_pair`.
    ro_robust : str
        Robust relative orientation for :func:`run_pair`.
    check_ids : tuple of str
        Control points used only as checks.
    control_sigma_px : float or None
        Standard error (pixels, per image coordinate) of the control and check
        points' image measurements. None: estimated from the absolute
        orientation (a variance component: the RO sigma0 times the sigma0 of the
        absolute orientation weighted with it, at least the RO sigma0). Tie
        points always use the relative orientation's sigma0.
    """

    intersection: str = "least-squares"
    frame: str = "topocentric"
    robust: str = "none"
    deformation_order: int | None = None
    ro_system: str = "left-image"
    ro_robust: str = "huber"
    check_ids: tuple[str, ...] = ()
    control_sigma_px: float | None = None

    def __post_init__(self) -> None:
        if self.control_sigma_px is not None and not (math.isfinite(self.control_sigma_px)
                                                      and self.control_sigma_px > 0):
            raise InvalidInputError(f"`control_sigma_px` must be a finite number > 0; got {self.control_sigma_px!r}")
        if self.intersection not in METHODS:
            raise InvalidInputError(f"unknown intersection method {self.intersection!r}; expected {list(METHODS)}")
        if self.frame not in FRAMES:
            raise InvalidInputError(f"unknown frame {self.frame!r}; expected one of {list(FRAMES)}")


@dataclass(frozen=True, eq=False)
class StereoModel:
    """Result of the pair pipeline.

    Attributes
    ----------
    ids : tuple of str
        Tie points first, then control points not among them.
    intersection : Intersection
        Model points (model frame, arbitrary scale) and diagnostics.
    ground : (N, 3) float64 or None
        Ground coordinates in the control CRS (after absolute orientation).
    ground_std : (N, 3) float64 or None
        Their predicted standard errors (image noise of the intersection and
        the absolute orientation's parameter covariance).
    absolute : AbsoluteOrientation or None
        Estimated in the frame named by ``frame``.
    frame : dict
        ``name`` and, for the topocentric frame, the ``origin`` (lon, lat, h).
    frame_difference : dict or None
        Ground points from the other frame minus these: RMS and max, m.
    is_control, is_check : (N,) bool
    crs : str or None
    tables : list of ResidualTable
    summary : dict
    """

    ids: tuple[str, ...]
    intersection: Intersection
    ground: NDArray[np.float64] | None
    ground_std: NDArray[np.float64] | None
    absolute: AbsoluteOrientation | None
    frame: dict[str, Any]
    frame_difference: dict[str, Any] | None
    is_control: NDArray[np.bool_]
    is_check: NDArray[np.bool_]
    crs: str | None
    tables: list[ResidualTable]
    summary: dict[str, Any]

    @property
    def points(self) -> NDArray[np.float64]:
        """Ground points when oriented, model points otherwise, (N, 3)."""
        return self.intersection.points if self.ground is None else self.ground


def _combine(ids_t: Sequence[str], left_mm: NDArray, right_mm: NDArray, control: ControlTable | None,
             control_mm: tuple[NDArray, NDArray] | None
             ) -> tuple[tuple[str, ...], NDArray, NDArray, NDArray, NDArray]:
    """Tie points + control points (control rows replace ties of the same id)."""
    xyz = np.full((len(ids_t), 3), np.nan)
    if control is None:
        return tuple(ids_t), left_mm, right_mm, xyz, np.zeros(len(ids_t), bool)
    cl, cr = control_mm
    pos = {i: k for k, i in enumerate(ids_t)}
    L, R = [left_mm.copy()], [right_mm.copy()]  # control rows replace ties: never write into the inputs
    ids = list(ids_t)
    is_ctrl = np.zeros(len(ids_t), bool)
    add_l, add_r, add_x, add_c = [], [], [], []
    for k, cid in enumerate(control.ids):
        if cid in pos:
            j = pos[cid]
            L[0][j], R[0][j] = cl[k], cr[k]
            xyz[j] = control.xyz[k]
            is_ctrl[j] = control.is_control[k]
        else:
            ids.append(cid)
            add_l.append(cl[k])
            add_r.append(cr[k])
            add_x.append(control.xyz[k])
            add_c.append(control.is_control[k])
    if add_l:
        left_mm = np.vstack([L[0], np.array(add_l)])
        right_mm = np.vstack([R[0], np.array(add_r)])
        xyz = np.vstack([xyz, np.array(add_x)])
        is_ctrl = np.concatenate([is_ctrl, np.array(add_c, bool)])
    else:
        left_mm, right_mm = L[0], R[0]
    return tuple(ids), left_mm, right_mm, xyz, is_ctrl


def _enu_jacobian(crs: str, origin: NDArray) -> NDArray:
    """d(map E, N, h) / d(ENU) at the ENU origin, (3, 3) (for covariances)."""
    from rectify.geodesy import map_from_enu

    e = 1.0
    pts = np.array([[0, 0, 0], [e, 0, 0], [0, e, 0], [0, 0, e]], float)
    m = map_from_enu(pts, crs, origin)
    return (m[1:] - m[0]).T / e


def ground_unit(crs: str | None, frame: str = "map") -> str:
    """Short name of the ground unit: "m" for the topocentric frame and for CRSs whose first axis is in
    metres, the CRS's unit name for others, "ground units" without a CRS (or an unreadable one)."""
    if frame == "topocentric":
        return "m"
    return unit_label(crs, default="ground units")


def _fit_ao(model_rows: NDArray, g_rows: NDArray, ids: list[str], chk: NDArray, opts: ModelOptions,
            cov_rows: NDArray | None, units: str) -> AbsoluteOrientation:
    """Similarity fit; with model covariances, a second pass weights every control point by the inverse
    of its intersection covariance rotated to ground, a full 3x3 matrix (model heights are about three
    times noisier than plan coordinates in aerial stereo, and X and Z are correlated through the
    x-parallax), so sigma0 is unitless (~1 when the image precision assumed for the control points is
    right) and the parameter covariance sigma0^2 (A^T P A)^-1 reflects the real, anisotropic noise."""
    ao = AbsoluteOrientation.from_points(model_rows, g_rows, ids=ids, check=chk, robust=opts.robust,
                                         deformation_order=opts.deformation_order, units=units)
    if cov_rows is None:
        return ao
    sR = ao.scale * ao.rotation
    cg = np.einsum("ij,njk,lk->nil", sR, cov_rows, sR)
    w = np.linalg.inv(cg + 1e-30 * np.eye(3))
    return AbsoluteOrientation.from_points(model_rows, g_rows, ids=ids, check=chk, robust=opts.robust,
                                           deformation_order=opts.deformation_order, weights=w, units=units)


def _orient(model_pts: NDArray, xyz: NDArray, use: NDArray, check: NDArray, ids: tuple[str, ...], crs: str | None,
            frame: str, opts: ModelOptions, model_cov: NDArray | None
            ) -> tuple[AbsoluteOrientation, NDArray, NDArray | None, dict[str, Any]]:
    """Absolute orientation in ``frame``; returns (ao, ground (N, 3) map, std (N, 3), frame info)."""
    rows = np.flatnonzero(use | check)
    chk = check[rows]
    cov_rows = None if model_cov is None else model_cov[rows]
    rid = [ids[i] for i in rows]
    if frame == "topocentric":
        from rectify.geodesy import enu_from_map, geodetic_from_map, map_from_enu

        ctrl = xyz[use]
        mid = np.concatenate([ctrl[:, :2].mean(0), [ctrl[:, 2].mean()]])
        origin = geodetic_from_map(mid[None], crs)[0]
        g_frame = enu_from_map(xyz[rows], crs, origin)
        ao = _fit_ao(model_pts[rows], g_frame, rid, chk, opts, cov_rows, "m")
        enu = ao(model_pts)
        ground = map_from_enu(enu, crs, origin)
        info = {"name": "topocentric", "origin_lon_lat_h": origin.tolist(),
                "note": "absolute orientation in local ENU at the control centroid (seed 004)"}
        Jm = _enu_jacobian(crs, origin)
    else:
        ao = _fit_ao(model_pts[rows], xyz[rows], rid, chk, opts, cov_rows, ground_unit(crs, "map"))
        ground = ao(model_pts)
        info = {"name": "map", "note": "absolute orientation directly in map coordinates"}
        Jm = np.eye(3)
    std = None
    if model_cov is not None:
        C = ao.point_covariance(model_pts, model_cov)
        C = np.einsum("ij,njk,lk->nil", Jm, C, Jm)
        std = np.sqrt(np.einsum("nii->ni", C))
    return ao, ground, std, info


def build_model(
    left_mm: ArrayLike,
    right_mm: ArrayLike,
    geometry: RelativeGeometry,
    *,
    ids: Sequence[str] | None = None,
    control: ControlTable | None = None,
    control_mm: tuple[ArrayLike, ArrayLike] | None = None,
    options: ModelOptions | None = None,
    pixel_size_mm: float | None = None,
) -> StereoModel:
    """Stages 2-4: intersect, orient to control, ground coordinates.

    Parameters
    ----------
    left_mm, right_mm : (N, 2) array_like
        Photo coordinates (mm) of the tie points.
    geometry : RelativeGeometry
        The relative orientation (``RelativeGeometry.from_relative(ro)`` or
        :func:`load_relative`).
    ids : sequence of str, optional
    control : ControlTable, optional
        Ground control (map coordinates in ``control.crs``); rows with NaN
        x, y, z are extra tie points.
    control_mm : ((M, 2), (M, 2)), optional
        The control points' photo coordinates (mm), left and right; required
        with ``control``.
    options : ModelOptions, optional
    pixel_size_mm : float, optional
        For pixel figures in the summary.

    Raises
    ------
    InvalidInputError
        Control without photo coordinates, unknown check ids, a
        topocentric frame without a CRS.
    EstimationError, StereoError
        From intersection and absolute orientation (too few or collinear
        control, parallel rays).
    """
    t0 = time.perf_counter()
    opts = options or ModelOptions()
    l = np.array(left_mm, dtype=np.float64, copy=True).reshape(-1, 2)
    r = np.array(right_mm, dtype=np.float64, copy=True).reshape(-1, 2)
    ids_t = as_ids(ids, len(l))
    cmm = None
    if control is not None:
        if control_mm is None:
            raise InvalidInputError("`control_mm` (photo coordinates of the control points) is required with "
                                    "`control`")
        cmm = (np.asarray(control_mm[0], float).reshape(-1, 2), np.asarray(control_mm[1], float).reshape(-1, 2))
    all_ids, L, R, xyz, is_ctrl = _combine(ids_t, l, r, control, cmm)
    unknown = sorted(set(opts.check_ids) - set(all_ids))
    if unknown:
        raise InvalidInputError(f"check point id(s) {unknown} are not among the control points")
    is_check = np.array([i in set(opts.check_ids) for i in all_ids]) & np.isfinite(xyz).all(1)
    use = is_ctrl & ~is_check
    sigma = geometry.sigma0_mm if geometry.sigma0_mm and math.isfinite(geometry.sigma0_mm) else None
    inter = intersect(L, R, rotation_left=geometry.rotation_left, rotation_right=geometry.rotation_right,
                      base=geometry.base, focal_length_mm=geometry.focal_length_mm, method=opts.intersection,
                      sigma_mm=sigma)
    obs = np.hstack([L, R])
    tables = [ResidualTable(step="intersection", ids=all_ids, observed=obs, adjusted=obs + inter.residuals_mm,
                            units="mm", components=("dx1", "dy1", "dx2", "dy2"), n_params=3 * len(L),
                            extra={"method": opts.intersection,
                                   "rms_vertical_parallax_mm": rms(inter.vertical_parallax_mm)})]
    from_file = np.zeros(len(all_ids), bool) if control is None else np.isin(
        np.array(all_ids, dtype=object), np.array(control.ids, dtype=object))
    summary: dict[str, Any] = {
        "n_points": len(all_ids), "n_tie_points": int((~from_file).sum()),
        "n_control_file_points": int(from_file.sum()), "n_control_points": int(use.sum()),
        "n_check_points": int(is_check.sum()), "intersection_method": opts.intersection,
        "rms_vertical_parallax_mm": rms(inter.vertical_parallax_mm),
        "median_miss_distance_model": float(np.median(inter.miss_distance)) if len(L) else None,
        "n_behind_camera": int(np.sum((inter.scale_left <= 0) | (inter.scale_right <= 0))),
    }
    if pixel_size_mm:
        summary["rms_vertical_parallax_px"] = summary["rms_vertical_parallax_mm"] / pixel_size_mm
    ground = std = ao = None
    frame_info: dict[str, Any] = {"name": "model"}
    diff = None
    crs = control.crs if control is not None else None
    if control is not None:
        frame = opts.frame
        if frame == "topocentric" and not crs:
            logger.warning("control has no CRS (# crs=...): absolute orientation in its own frame")
            frame = "map"
        model_cov = inter.covariance
        if model_cov is not None:
            # control and check points are measured apart from the matcher (by hand, or projected from
            # a DEM), usually far less precisely than matched tie points: their own variance component
            if opts.control_sigma_px is not None:
                if not pixel_size_mm:
                    raise InvalidInputError("`control_sigma_px` needs `pixel_size_mm`")
                sigma_c = opts.control_sigma_px * pixel_size_mm
                source = "given"
            else:
                ao0, _, _, _ = _orient(inter.points, xyz, use, is_check, all_ids, crs, frame, opts, model_cov)
                s0 = ao0.sigma0 if math.isfinite(ao0.sigma0) else 1.0
                sigma_c = sigma * max(1.0, s0)
                source = "estimated"
            model_cov = model_cov.copy()
            model_cov[from_file] *= (sigma_c / sigma) ** 2
            summary.update({"tie_sigma_mm": sigma, "control_sigma_mm": sigma_c, "control_sigma_source": source})
            if pixel_size_mm:
                summary.update({"tie_sigma_px": sigma / pixel_size_mm, "control_sigma_px": sigma_c / pixel_size_mm})
        ao, ground, std, frame_info = _orient(inter.points, xyz, use, is_check, all_ids, crs, frame, opts,
                                              model_cov)
        tables.append(ao.residuals)
        if crs:
            other = "map" if frame == "topocentric" else "topocentric"
            try:
                _, g2, _, _ = _orient(inter.points, xyz, use, is_check, all_ids, crs, other, opts,
                                      model_cov)
                d = g2 - ground
                diff = {"other_frame": other, "rms_xyz_m": rms(np.linalg.norm(d, axis=1)),
                        "max_xyz_m": float(np.abs(np.linalg.norm(d, axis=1)).max()),
                        "rms_z_m": rms(d[:, 2]), "max_z_m": float(np.abs(d[:, 2]).max())}
            except CRSError as err:
                diff = {"other_frame": other, "error": str(err)}
        s = ao.residuals.summary()
        summary.update({"frame": frame_info["name"], "ground_unit": ground_unit(crs, "map"),
                        "absolute_unit": ao.residuals.units,
                        "absolute_sigma0": ao.sigma0, "absolute_weighted": model_cov is not None, "scale": ao.scale,
                        "n_control": s["n_fit"], "n_check": s["n_check"], "rmse_control_m": s["rmse"],
                        "rmse_check_m": s["rmse_check"]})
        if is_check.any():
            e = ground[is_check] - xyz[is_check]
            summary["rmse_check_xyz_m"] = [rms(e[:, k]) for k in range(3)]
            if std is not None:
                summary["rms_normalised_check_error"] = rms(e / std[is_check])
        if diff is not None:
            summary["frame_difference"] = diff
    summary["elapsed_s"] = time.perf_counter() - t0
    return StereoModel(ids=all_ids, intersection=inter, ground=ground, ground_std=std, absolute=ao,
                       frame=frame_info, frame_difference=diff, is_control=is_ctrl & ~is_check,
                       is_check=is_check, crs=crs, tables=tables, summary=summary)


def match_control(control: ControlTable, camera: Camera) -> tuple[NDArray, NDArray]:
    """Photo coordinates (mm) of the control points in both images."""
    return camera.photo_from_pixel(control.left), camera.photo_from_pixel(control.right)


class Workspace:
    """Output folder of a pair run; owns the file layout.

    ::

        OUTDIR/matches.csv          tie points (pixels)
        OUTDIR/relative.json        relative orientation (DESIGN.md contract)
        OUTDIR/orientation.json     absolute orientation, frame, summary
        OUTDIR/points.ply           ground (or model) points
        OUTDIR/points.csv           id,x,y,z,residual_mm[,std_*]
        OUTDIR/model_points.ply     model frame points
        OUTDIR/report/              QA report (rectify.report)
    """

    def __init__(self, root: str | Path, *, overwrite: bool = False) -> None:
        self.root = Path(root)
        self.overwrite = overwrite

    def prepare(self) -> None:
        if self.root.exists() and not self.root.is_dir():
            raise InvalidInputError(f"output {str(self.root)!r} exists and is not a folder")
        self.root.mkdir(parents=True, exist_ok=True)
        if not self.overwrite:
            for name in ("matches.csv", "relative.json", "orientation.json", "points.ply", "points.csv"):
                check_output(self.root / name, overwrite=False)

    def path(self, name: str) -> Path:
        return self.root / name

    @property
    def report_dir(self) -> Path:
        return self.root / "report"


def save_model(model: StereoModel, *, points_path: str | Path, csv_path: str | Path | None = None,
               orientation_path: str | Path | None = None, model_ply_path: str | Path | None = None,
               overwrite: bool = False, extra: dict[str, Any] | None = None) -> None:
    """Write PLY, CSV and orientation JSON of a model."""
    res = np.sqrt(np.mean(model.intersection.residuals_mm ** 2, axis=1))
    write_ply(points_path, model.points, overwrite=overwrite,
              comment="ground" if model.ground is not None else "model frame")
    if csv_path is not None:
        write_points_csv(csv_path, model.ids, model.points, res, std=model.ground_std, crs=model.crs,
                         overwrite=overwrite)
    if model_ply_path is not None:
        write_ply(model_ply_path, model.intersection.points, overwrite=overwrite, comment="model frame")
    if orientation_path is not None:
        write_orientation(orientation_path, orientation_dict(model, extra=extra), overwrite=overwrite)


def run_model(geometry: RelativeGeometry, matches: Matches, camera: Camera, *, control: ControlTable | None = None,
              options: ModelOptions | None = None) -> StereoModel:
    """``stereo model``: matches (pixels) + relative orientation -> model (+ ground) points."""
    l = camera.photo_from_pixel(matches.left)
    r = camera.photo_from_pixel(matches.right)
    cmm = match_control(control, camera) if control is not None else None
    return build_model(l, r, geometry, ids=matches.ids, control=control, control_mm=cmm, options=options,
                       pixel_size_mm=camera.pixel_size_mm)


def run_pair(left: str | Path, right: str | Path, camera: Camera, out_dir: str | Path, *,
             control: ControlTable | None = None, options: ModelOptions | None = None, overwrite: bool = False,
             report: bool = True, title: str = "stereo run", extra_summary: dict[str, Any] | None = None,
             progress: Callable[[int, int], None] | None = None) -> StereoModel:
    """``stereo run``: match, orient, intersect, orient absolutely, write everything into ``out_dir``."""
    from rectify.features import MatcherConfig, match_images
    from rectify.formats import write_matches
    opts = options or ModelOptions()
    ws = Workspace(out_dir, overwrite=overwrite)
    ws.prepare()
    t0 = time.perf_counter()
    import warnings

    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():  # plain photos have no geotransform, as expected
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        mr = match_images(left, right, config=MatcherConfig(verify="fundamental"), progress=progress)
    m = mr.matches
    t_match = time.perf_counter() - t0
    write_matches(ws.path("matches.csv"), m, overwrite=overwrite)
    l_all, r_all, ids_all = m.left, m.right, list(m.ids)
    if control is not None:  # control image points are tie points too
        l_all = np.vstack([l_all, control.left])
        r_all = np.vstack([r_all, control.right])
        ids_all += list(control.ids)
    ro = RelativeOrientation.from_pixels(l_all, r_all, camera, system=opts.ro_system, robust=opts.ro_robust,
                                         ids=ids_all)
    write_relative(ws.path("relative.json"), ro, overwrite=overwrite)
    keep = ~np.asarray(ro.outlier)[:len(m)]
    mk = Matches(tuple(np.asarray(m.ids)[keep]), m.left[keep], m.right[keep])
    model = run_model(RelativeGeometry.from_relative(ro), mk, camera, control=control, options=opts)
    summary = dict(model.summary)
    summary.update({"n_matches": len(m), "match_rmse_px": mr.rmse_px, "t_match_s": t_match,
                    "ro_sigma0_mm": ro.sigma0_mm, "ro_n_used": ro.n_used, "ro_system": ro.system})
    if extra_summary:
        summary.update(extra_summary)
    model = StereoModel(**{**model.__dict__, "summary": summary, "tables": [ro.residual_table()] + model.tables})
    save_model(model, points_path=ws.path("points.ply"), csv_path=ws.path("points.csv"),
               orientation_path=ws.path("orientation.json"), model_ply_path=ws.path("model_points.ply"),
               overwrite=overwrite)
    if report:
        write_pair_report(model, ws.report_dir, title=title, ro=ro, left_image=left, camera=camera,
                          overwrite=overwrite)
    return model


def write_pair_report(model: StereoModel, out_dir: str | Path, *, title: str, ro: Any = None,
                      left_image: str | Path | None = None, camera: Camera | None = None,
                      overwrite: bool = False) -> Path:
    """QA report of a pair run with :func:`stereo.report.write_stereo_report`.

    Relative orientation: vertical-parallax table over the left image (drawn on
    the photo when ``left_image`` can be read) and the correlation heat map of
    its elements; absolute orientation: residual table, plan vectors at the
    control points' ground positions (GeoJSON too when the model has a CRS,
    EPSG code or WKT) and height bars; the intersection table. ``model.tables``
    must start with ``ro.residual_table()`` when ``ro`` is given.
    """
    from .report import write_stereo_report

    tables = list(model.tables)
    rel = corr = None
    if ro is not None:
        rel = tables.pop(0)
        c = ro.correlation
        if c is not None and np.isfinite(c).all():
            corr = (list(ro.names), c)
    absolute = gxy = None
    if model.absolute is not None and model.ground is not None:
        absolute = model.absolute.residuals
        tables = [t for t in tables if t is not absolute]
        rows = [model.ids.index(i) for i in absolute.ids]
        gxy = model.ground[rows, :2]
    img = shape = pp = None
    if camera is not None:
        shape = (camera.height, camera.width)
        pp = camera.pixel_from_photo(np.zeros((1, 2)))[0]
    if left_image is not None:
        from rectify import io as rio

        # a bounded overview for the plot background (drawn over the full-resolution extent)
        data, valid, _ = rio.read_overview(left_image, 2048)
        img = rio.to_uint8(data, valid)
    return write_stereo_report(out_dir, title=title, relative=rel, correlation=corr, absolute=absolute,
                               absolute_ground_xy=gxy, tables=tables, summary=model.summary,
                               crs=model.crs or None, left_image_shape=shape, left_image=img,
                               principal_point_px=pp, overwrite=overwrite)
