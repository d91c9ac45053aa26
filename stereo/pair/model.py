"""The stereo model of a pair: seed 002's double resection in four stages.

1. relative orientation (:mod:`stereo.relative`) from tie points;
2. model points by intersection (:mod:`stereo.pair.intersection`);
3. absolute orientation of the model to ground control (:mod:`stereo.pair.absolute`);
4. ground coordinates of every point, with predicted standard errors.

Absolute orientation happens by default in a local topocentric (ENU) frame
at the middle of the block (seed 004): control map coordinates (E, N, h) go
to geocentric and then to ENU at the control centroid (:mod:`rectify.geometry.geodesy`),
the similarity is estimated there, and ground points come back to the map
CRS. A map CRS is not a Cartesian frame (scale factor, Earth curvature), so
a similarity fitted directly in map coordinates (``frame="map"``) absorbs
part of the distortion; the pipeline runs both when the control has a CRS
and reports the difference. Heights are treated as ellipsoidal in the
conversion; for a geoid-referenced height the undulation, constant over a
block, cancels on the way back.

:func:`build_model` is the geometry (stages 2-4) on photo coordinates; the files of a run are
owned by :class:`stereo.actions.workspace.PairWorkspace`, the steps by :mod:`stereo.actions.common`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CRSError, EstimationError, InvalidInputError
from rectify.geometry.accuracy import AccuracyStatement
from rectify.geometry.camera import Camera
from rectify.geometry.crs import unit_label
from rectify.geometry.geodesy import enu_from_map, geodetic_from_map, map_from_enu
from rectify.geometry.points import ControlTable, as_ids
from rectify.geometry.residuals import ResidualTable, rms
from stereo.pair.absolute import AbsoluteOrientation
from stereo.pair.intersection import METHODS, Intersection, intersect
from stereo.relative import RelativeGeometry

logger = logging.getLogger(__name__)

__all__ = ["FRAMES", "ModelOptions", "StereoModel", "build_model", "ground_unit", "match_control"]

FRAMES = ("topocentric", "map")


@dataclass(frozen=True)
class ModelOptions:
    """Options of the pair pipeline.

    Attributes
    ----------
    intersection : str
        Intersection method (see :data:`stereo.pair.intersection.METHODS`).
    frame : {"topocentric", "map"}
        Where absolute orientation is estimated (see the module docstring).
    robust : str
        Robust absolute orientation: none, huber, tukey (default since issue 12: two bad control points
        gave 4.1 m check RMSE without, 0.20 m with it), hampel, andrews.
    deformation_order : int or None
        Seed 002's polynomial deformation correction (2 or 3).
    ro_system : str
        System of relative orientation elements for :func:`stereo.actions.run.run`.
    ro_robust : str
        Robust relative orientation for :func:`stereo.actions.run.run`.
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
    robust: str = "tukey"
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

    def intersection_line(self, tie_note: str) -> str:
        """Intersection summary with the point count broken down (tie points + control-file points)."""
        s = self.summary
        t = next(t for t in self.tables if t.step == "intersection")
        ts = t.summary()
        parts = [f"{s['n_tie_points']} tie points {tie_note}".rstrip()]
        if s.get("n_control_file_points"):
            n_c, n_k = s["n_control_points"], s["n_check_points"]
            n_other = s["n_control_file_points"] - n_c - n_k
            parts.append(f"{n_c} control + {n_k} check" + (f" + {n_other} other" if n_other else "")
                         + " points from the control file")
        return (f"intersection: {ts['n_fit']} points ({' + '.join(parts)}), photo residual RMSE "
                f"{ts['rmse'] * 1000:.2f} um, RMS vertical parallax {s['rms_vertical_parallax_mm'] * 1000:.2f} um")

    def summary_lines(self, tie_note: str = "from the matches") -> list[str]:
        """Residual summary of every table, absolute orientation details, check points (units named)."""
        s = self.summary
        out = []
        for t in self.tables:
            if t.step == "intersection":
                out.append(self.intersection_line(tie_note))
            elif self.absolute is not None and t is self.absolute.residuals:
                ts = t.summary()
                u = t.units
                line = f"{t.step}: {ts['n_fit']} control points, RMSE {ts['rmse']:.3f} {u}"
                if ts["n_check"]:
                    line += f"; {ts['n_check']} check points, RMSE {ts['rmse_check']:.3f} {u}"
                if ts["n_outliers"]:
                    line += f"; {ts['n_outliers']} outlier" + ("s" if ts["n_outliers"] > 1 else "")
                line += f"; sigma0 {self.absolute.sigma0:.3f}" + ("" if s.get("absolute_weighted") else f" {u}")
                if s.get("control_sigma_source") == "estimated":
                    if abs(self.absolute.sigma0 - 1.0) < 1e-6:
                        line += " (1 by construction: the control image precision is scaled to it)"
                    else:  # a robust fit reweights after the precision was scaled on the least-squares fit
                        line += (" (the control image precision is scaled to give 1 in a least-squares fit; "
                                 "the robust fit's reweighting moves it)")
                out.append(line)
                why = self.absolute.outlier_text()
                if why is not None:
                    out.append(f"robust absolute orientation, {why}")
            else:
                out.append(f"{t.step}: {t.summary_line()}")
        if self.absolute is not None:
            u = s.get("ground_unit", "ground units")
            out.append(f"absolute orientation ({self.frame['name']} frame): scale {self.absolute.scale:.6g}")
            if s.get("control_sigma_px") is not None:
                how = ("estimated from the absolute orientation" if s["control_sigma_source"] == "estimated"
                       else "given")
                out.append(f"image precision: tie points {s['tie_sigma_px']:.4f} px (RO sigma0), control/check "
                           f"points {s['control_sigma_px']:.3f} px ({how})")
            d = self.frame_difference
            if d and "rms_xyz_m" in d:
                out.append(f"{d['other_frame']} frame instead: points differ by RMS {d['rms_xyz_m']:.3f} m "
                           f"(max {d['max_xyz_m']:.3f} m)")
            if s.get("rmse_check_xyz_m"):
                x, y, z = s["rmse_check_xyz_m"]
                out.append(f"check points: RMSE X {x:.3f} {u}, Y {y:.3f} {u}, Z {z:.3f} {u}")
            if "rms_normalised_check_error" in s:
                out.append(f"check points: RMS of error / predicted std {s['rms_normalised_check_error']:.3f}")
            out.extend(s.get("accuracy_statement", {}).get("lines", ()))
        return out


def _combine(ids_t: Sequence[str], left_mm: NDArray, right_mm: NDArray, control: ControlTable | None,
             control_mm: tuple[NDArray, NDArray] | None
             ) -> tuple[tuple[str, ...], NDArray, NDArray, NDArray, NDArray]:
    """Tie points + control points (control rows replace ties of the same id)."""
    xyz = np.full((len(ids_t), 3), np.nan)
    if control is None:
        return tuple(ids_t), left_mm, right_mm, xyz, np.zeros(len(ids_t), bool)
    assert control_mm is not None  # given with the control (checked by the caller)
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
            cov_rows: NDArray | None, units: str, min_scale: float | None = None) -> AbsoluteOrientation:
    """Similarity fit; with model covariances, a second pass weights every control point by the inverse
    of its intersection covariance rotated to ground, a full 3x3 matrix (model heights are about three
    times noisier than plan coordinates in aerial stereo, and X and Z are correlated through the
    x-parallax), so sigma0 is unitless (~1 when the image precision assumed for the control points is
    right) and the parameter covariance sigma0^2 (A^T P A)^-1 reflects the real, anisotropic noise.
    ``min_scale`` is the weighted pass's smallest robust scale (see
    :meth:`AbsoluteOrientation.from_points`)."""
    ao = AbsoluteOrientation.from_points(model_rows, g_rows, ids=ids, check=chk, robust=opts.robust,
                                         deformation_order=opts.deformation_order, units=units)
    if cov_rows is None:
        return ao
    sR = ao.scale * ao.rotation
    cg = np.einsum("ij,njk,lk->nil", sR, cov_rows, sR)
    w = np.linalg.inv(cg + 1e-30 * np.eye(3))
    return AbsoluteOrientation.from_points(model_rows, g_rows, ids=ids, check=chk, robust=opts.robust,
                                           deformation_order=opts.deformation_order, weights=w, units=units,
                                           min_scale=min_scale)


def _orient(model_pts: NDArray, xyz: NDArray, use: NDArray, check: NDArray, ids: tuple[str, ...], crs: str | None,
            frame: str, opts: ModelOptions, model_cov: NDArray | None, min_scale: float | None = None
            ) -> tuple[AbsoluteOrientation, NDArray, NDArray | None, dict[str, Any]]:
    """Absolute orientation in ``frame``; returns (ao, ground (N, 3) map, std (N, 3), frame info)."""
    rows = np.flatnonzero(use | check)
    chk = check[rows]
    cov_rows = None if model_cov is None else model_cov[rows]
    rid = [ids[i] for i in rows]
    if frame == "topocentric":
        assert crs is not None  # the topocentric frame needs the control's CRS (checked by build_model)
        ctrl = xyz[use]
        mid = np.concatenate([ctrl[:, :2].mean(0), [ctrl[:, 2].mean()]])
        origin = geodetic_from_map(mid[None], crs)[0]
        g_frame = enu_from_map(xyz[rows], crs, origin)
        ao = _fit_ao(model_pts[rows], g_frame, rid, chk, opts, cov_rows, "m", min_scale)
        enu = ao(model_pts)
        ground = map_from_enu(enu, crs, origin)
        info = {"name": "topocentric", "origin_lon_lat_h": origin.tolist(),
                "note": "absolute orientation in local ENU at the control centroid (seed 004)"}
        Jm = _enu_jacobian(crs, origin)
    else:
        ao = _fit_ao(model_pts[rows], xyz[rows], rid, chk, opts, cov_rows, ground_unit(crs, "map"), min_scale)
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
    pts = _validate(left_mm, right_mm, ids=ids, control=control, control_mm=control_mm, options=opts)
    inter, tables, summary, sigma = _intersect(pts, geometry, opts, pixel_size_mm)
    ground = std = ao = None
    frame_info: dict[str, Any] = {"name": "model"}
    diff = None
    crs = control.crs if control is not None else None
    if control is not None:
        frame = opts.frame
        if frame == "topocentric" and not crs:
            logger.warning("control has no CRS (# crs=...): absolute orientation in its own frame")
            frame = "map"
        model_cov = _model_covariance(pts, inter, sigma, crs, frame, opts, pixel_size_mm, summary)
        ao, ground, std, frame_info, diff = _absolute(pts, inter, model_cov, crs, frame, opts, summary)
        tables.append(ao.residuals)
    summary["elapsed_s"] = time.perf_counter() - t0
    return StereoModel(ids=pts.ids, intersection=inter, ground=ground, ground_std=std, absolute=ao,
                       frame=frame_info, frame_difference=diff, is_control=pts.is_ctrl & ~pts.is_check,
                       is_check=pts.is_check, crs=crs, tables=tables, summary=summary)


# ------------------------------------------------------------------ stages of build_model
@dataclass(frozen=True, eq=False)
class _Points:
    """Stage 1: tie and control points of the model, combined (control rows replace ties of the same id)."""

    ids: tuple[str, ...]
    left_mm: NDArray[np.float64]     # (N, 2)
    right_mm: NDArray[np.float64]    # (N, 2)
    xyz: NDArray[np.float64]         # (N, 3) ground coordinates of control points, NaN for ties
    is_ctrl: NDArray[np.bool_]
    is_check: NDArray[np.bool_]
    use: NDArray[np.bool_]           # control points used in the absolute orientation
    from_file: NDArray[np.bool_]     # rows of the control file


def _validate(left_mm: ArrayLike, right_mm: ArrayLike, *, ids: Sequence[str] | None, control: ControlTable | None,
              control_mm: tuple[ArrayLike, ArrayLike] | None, options: ModelOptions) -> _Points:
    """Stage 1: shapes, control photo coordinates, check ids; tie and control points combined."""
    l = np.array(left_mm, dtype=np.float64, copy=True).reshape(-1, 2)  # noqa: E741
    r = np.array(right_mm, dtype=np.float64, copy=True).reshape(-1, 2)
    ids_t = as_ids(ids, len(l))
    cmm = None
    if control is not None:
        if control_mm is None:
            raise InvalidInputError("`control_mm` (photo coordinates of the control points) is required with "
                                    "`control`")
        cmm = (np.asarray(control_mm[0], float).reshape(-1, 2), np.asarray(control_mm[1], float).reshape(-1, 2))
    all_ids, L, R, xyz, is_ctrl = _combine(ids_t, l, r, control, cmm)
    unknown = sorted(set(options.check_ids) - set(all_ids))
    if unknown:
        raise InvalidInputError(f"check point id(s) {unknown} are not among the control points")
    is_check = np.array([i in set(options.check_ids) for i in all_ids]) & np.isfinite(xyz).all(1)
    use = is_ctrl & ~is_check
    from_file = np.zeros(len(all_ids), bool) if control is None else np.isin(
        np.array(all_ids, dtype=object), np.array(control.ids, dtype=object))
    return _Points(all_ids, L, R, xyz, is_ctrl, is_check, use, from_file)


def _intersect(pts: _Points, geometry: RelativeGeometry, opts: ModelOptions, pixel_size_mm: float | None
               ) -> tuple[Intersection, list[ResidualTable], dict[str, Any], float | None]:
    """Stage 2: model points by intersection, their residual table and summary; also the tie sigma (mm)."""
    L, R, all_ids = pts.left_mm, pts.right_mm, pts.ids
    sigma = geometry.sigma0_mm if geometry.sigma0_mm and math.isfinite(geometry.sigma0_mm) else None
    inter = intersect(L, R, rotation_left=geometry.rotation_left, rotation_right=geometry.rotation_right,
                      base=geometry.base, focal_length_mm=geometry.focal_length_mm, method=opts.intersection,
                      sigma_mm=sigma)
    obs = np.hstack([L, R])
    tables = [ResidualTable(step="intersection", ids=all_ids, observed=obs, adjusted=obs + inter.residuals_mm,
                            units="mm", components=("dx1", "dy1", "dx2", "dy2"), n_params=3 * len(L),
                            extra={"method": opts.intersection,
                                   "rms_vertical_parallax_mm": rms(inter.vertical_parallax_mm)})]
    summary: dict[str, Any] = {
        "n_points": len(all_ids), "n_tie_points": int((~pts.from_file).sum()),
        "n_control_file_points": int(pts.from_file.sum()), "n_control_points": int(pts.use.sum()),
        "n_check_points": int(pts.is_check.sum()), "intersection_method": opts.intersection,
        "rms_vertical_parallax_mm": rms(inter.vertical_parallax_mm),
        "median_miss_distance_model": float(np.median(inter.miss_distance)) if len(L) else None,
        "n_behind_camera": int(np.sum((inter.scale_left <= 0) | (inter.scale_right <= 0))),
    }
    if pixel_size_mm:
        summary["rms_vertical_parallax_px"] = summary["rms_vertical_parallax_mm"] / pixel_size_mm
    return inter, tables, summary, sigma


def _model_covariance(pts: _Points, inter: Intersection, sigma: float | None, crs: str | None, frame: str,
                      opts: ModelOptions, pixel_size_mm: float | None, summary: dict[str, Any]) -> NDArray | None:
    """Stage 3: covariance of the model points with the control points' own variance component."""
    model_cov = inter.covariance
    if model_cov is None or sigma is None:
        return model_cov
    # control and check points are measured apart from the matcher (by hand, or projected from
    # a DEM), usually far less precisely than matched tie points: their own variance component
    if opts.control_sigma_px is not None:
        if not pixel_size_mm:
            raise InvalidInputError("`control_sigma_px` needs `pixel_size_mm`")
        sigma_c = opts.control_sigma_px * pixel_size_mm
        source = "given"
    else:
        # the variance component by least squares: a robust fit's down-weighting of good control points
        # would under-estimate it (predicted check errors 2x too small with Tukey); outliers inflate it, which
        # errs on the safe side, and the final fit is robust
        s0 = _control_sigma0(pts, inter, crs, frame, opts, model_cov)
        sigma_c = sigma * max(1.0, s0)
        source = "estimated"
    model_cov = model_cov.copy()
    model_cov[pts.from_file] *= (sigma_c / sigma) ** 2
    summary.update({"tie_sigma_mm": sigma, "control_sigma_mm": sigma_c, "control_sigma_source": source})
    if pixel_size_mm:
        summary.update({"tie_sigma_px": sigma / pixel_size_mm, "control_sigma_px": sigma_c / pixel_size_mm})
    return model_cov


def _control_sigma0(pts: _Points, inter: Intersection, crs: str | None, frame: str, opts: ModelOptions,
                    model_cov: NDArray) -> float:
    """The sigma0 of the control points at the tie points' image precision, by least squares on the
    control points that are not confirmed blunders.

    By least squares because a robust fit's down-weighting of good control points would under-estimate
    it (predicted check errors 2x too small with Tukey). Blunders would inflate it, and with it the
    final robust fit's scale (at least 1, the a-priori one: :func:`_absolute`), so that they would pass:
    the points a robust fit flags (at the residuals' own robust scale, which also flags good points when
    it shrinks onto a subset of the control) are left out of a least-squares fit, and those whose
    residual under that fit exceeds 3 of its predicted standard deviations (the withheld point's own and
    the fit's, at that fit's precision) are blunders; the others come back.
    """
    def ls(use: NDArray, cov: NDArray = model_cov) -> tuple[AbsoluteOrientation, NDArray, NDArray | None]:
        ao, ground, std, _ = _orient(inter.points, pts.xyz, use, pts.is_check, pts.ids, crs, frame,
                                     replace(opts, robust="none"), cov)
        return ao, ground, std

    def sigma0(ao: AbsoluteOrientation) -> float:
        return ao.sigma0 if math.isfinite(ao.sigma0) else 1.0

    s0_all = sigma0(ls(pts.use)[0])
    if opts.robust == "none":
        return s0_all
    try:
        aor, _, _, _ = _orient(inter.points, pts.xyz, pts.use, pts.is_check, pts.ids, crs, frame, opts, model_cov)
        flagged = np.isin(np.array(pts.ids, dtype=object), np.array(
            [r["id"] for r in aor.residuals.rows() if r["outlier"] and not r["check"]], dtype=object)) & pts.use
        if not flagged.any():
            return s0_all
        ao_k, _, _ = ls(pts.use & ~flagged)
        cov_k = model_cov.copy()
        cov_k[pts.from_file] *= max(1.0, sigma0(ao_k)) ** 2
        _, ground, std = ls(pts.use & ~flagged, cov_k)
        assert std is not None  # with model covariances
        z = np.max(np.abs(ground - pts.xyz) / std, axis=1)
        blunder = flagged & (z > 3.0)
        return sigma0(ls(pts.use & ~blunder)[0]) if blunder.any() else s0_all
    except EstimationError:  # too few control points without the flagged ones: all of them
        return s0_all


def _absolute(pts: _Points, inter: Intersection, model_cov: NDArray | None, crs: str | None, frame: str,
              opts: ModelOptions, summary: dict[str, Any]
              ) -> tuple[AbsoluteOrientation, NDArray, NDArray | None, dict[str, Any], dict[str, Any] | None]:
    """Stage 4: absolute orientation in ``frame`` (and the other frame for comparison), ground points and
    their standard errors, check-point figures; returns (ao, ground, std, frame info, frame difference)."""
    xyz, is_check = pts.xyz, pts.is_check
    # weights are inverse covariances (the control's image precision given or estimated): a residual within
    # 3 predicted standard deviations is never flagged, whatever the residuals' own robust scale
    floor = 1.0 if model_cov is not None else None
    ao, ground, std, frame_info = _orient(inter.points, xyz, pts.use, is_check, pts.ids, crs, frame, opts,
                                          model_cov, floor)
    diff = None
    if crs:
        other = "map" if frame == "topocentric" else "topocentric"
        try:
            _, g2, _, _ = _orient(inter.points, xyz, pts.use, is_check, pts.ids, crs, other, opts, model_cov,
                                  floor)
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
        full = np.isfinite(e).all(axis=1)
        if summary["ground_unit"] in ("m", "metre", "meter") and full.any():   # ground lengths only
            summary["accuracy_statement"] = AccuracyStatement.from_errors(e[full]).to_dict()
    if diff is not None:
        summary["frame_difference"] = diff
    return ao, ground, std, frame_info, diff


def match_control(control: ControlTable, camera: Camera) -> tuple[NDArray, NDArray]:
    """Photo coordinates (mm) of the control points in both images."""
    return camera.photo_from_pixel(control.left), camera.photo_from_pixel(control.right)
