"""``stereo block``'s adjustment frame: inputs converted into it, results converted back (:mod:`stereo.block.frames`).

The action (:mod:`stereo.actions.block`) reads its inputs in the CRS of the files, matches tie
points there, then converts the poses, the GNSS/INS observations and the control into the frame
(:func:`choose_frame`, :func:`poses_to_frame`, :func:`gnss_to_frame`, :func:`control_to_frame`),
adjusts, and converts the bundle's result back (:func:`result_to_map`) before anything is written.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles
from stereo.block.bundle.result import BundleResult
from stereo.block.bundle.systematic import frame_covariance
from stereo.block.frames import AdjustmentFrame, curvature_warning, default_frame_kind
from stereo.block.types import BlockControl, GnssObservations, Pose, Tracks
from stereo.formats.detect import read_pose_file
from stereo.formats.observations import ObservationTable, read_observations

__all__ = ["choose_frame", "control_to_frame", "frame_lines", "gnss_to_frame", "observation_images",
           "observation_tracks", "poses_to_frame", "result_to_map"]

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def choose_frame(kind: str | None, crs: str | None, positions: Sequence[F64]) -> AdjustmentFrame:
    """The adjustment frame of a block: ``kind`` (None: topocentric with a CRS, the local map frame without).

    ``positions`` are (N, 3) arrays of map coordinates (projection centres, control) whose mean
    is the topocentric origin; NaN rows are skipped.
    """
    k = kind or default_frame_kind(crs)
    pts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in positions if p is not None]
    xyh = np.vstack(pts) if pts else np.zeros((0, 3))
    xyh = xyh[np.isfinite(xyh).all(axis=1)]
    return AdjustmentFrame.from_points(k, crs, xyh)


def _positions(inp: Any) -> F64:
    """(N, 3) map positions of a block's inputs (``stereo.actions.block._Inputs``): poses, control, geo.txt."""
    parts = [np.array([q.position for q in inp.poses or []], dtype=np.float64).reshape(-1, 3)]
    if inp.control is not None:
        parts.append(np.asarray(inp.control.xyz, dtype=np.float64).reshape(-1, 3))
    if inp.geo is not None:
        parts.append(np.asarray(inp.geo.position, dtype=np.float64).reshape(-1, 3))
    return np.vstack(parts)


def frame_for(inp: Any, kind: str | None) -> AdjustmentFrame:
    """The adjustment frame of a block's inputs (``stereo.actions.block._Inputs``), about their centre."""
    return choose_frame(kind, inp.crs, [_positions(inp)])


def frame_lines(frame: AdjustmentFrame, inp: Any) -> tuple[str, ...]:
    """The summary line of the frame, and the curvature warning of a map frame over a wide block (logged at info)."""
    warn = None
    if frame.kind == "map":
        p = _positions(inp)
        warn = curvature_warning(p[np.isfinite(p).all(axis=1)], frame.crs)
        if warn is not None:  # printed with the summary lines; logged now for a long run (-v)
            logger.info(warn)
    return (f"adjustment frame: {frame.description()}",) + ((f"warning: {warn}",) if warn else ())


def poses_to_frame(frame: AdjustmentFrame, poses: Sequence[Pose] | None, *, navigation: bool) -> list[Pose] | None:
    """Poses in map coordinates (rotations in the local grid, or local ENU for ``navigation``) -> frame."""
    if poses is None:
        return None
    if frame.is_identity and not navigation:
        return list(poses)
    c = np.array([p.position for p in poses]).reshape(-1, 3)
    R = np.array([p.rotation for p in poses]).reshape(-1, 3, 3)
    cf = frame.frame_from_map(c)
    Rf = frame.rotations_in(R, c, navigation=navigation)
    return [Pose(p.image, p.camera, cf[i], _orthonormal(Rf[i])) for i, p in enumerate(poses)]


def _orthonormal(R: F64) -> F64:
    u, _, vt = np.linalg.svd(R)
    return np.asarray(u @ vt, dtype=np.float64)


def _sigma_rotated(T: F64, s: F64) -> F64:
    """(N, 3) per-axis sigmas after rotating diag(s^2) by T (N, 3, 3): sqrt(diag(T S T^T))."""
    return np.sqrt(np.einsum("nij,nj->ni", T ** 2, s ** 2))


def gnss_to_frame(frame: AdjustmentFrame, gnss: GnssObservations | None, *, navigation: bool
                  ) -> GnssObservations | None:
    """GNSS antenna positions (and INS omega-phi-kappa angles) in map coordinates -> frame.

    Position sigmas are rotated as diagonal covariances (exact when sx = sy = sz); angle sigmas are kept.
    """
    if gnss is None or (frame.is_identity and (gnss.angles is None or not navigation)):
        return gnss
    pos = np.asarray(gnss.position, dtype=np.float64)
    T = frame.frame_from_grid_at(pos)
    pf = frame.frame_from_map(pos)
    sig = _sigma_rotated(T, np.asarray(gnss.sigma_m, dtype=np.float64))
    ang = None
    if gnss.angles is not None:
        a = np.asarray(gnss.angles, dtype=np.float64)
        R = np.asarray(matrix_from_angles(a[:, 0], a[:, 1], a[:, 2], "omega-phi-kappa")).reshape(-1, 3, 3)
        Rf = frame.rotations_in(R, pos, navigation=navigation)
        ang = np.array([angles_from_matrix(_orthonormal(r), "omega-phi-kappa") for r in Rf]).reshape(-1, 3)
    # a full covariance (stereo.block.bundle.systematic) is carried into the frame with the positions and angles
    cov = frame_covariance(gnss.covariance, T, gnss.angles, ang if ang is not None else gnss.angles)
    return replace(gnss, position=pf, sigma_m=sig, angles=ang if ang is not None else gnss.angles, covariance=cov)


def control_to_frame(frame: AdjustmentFrame, ctrl: BlockControl | None, estimates: F64 | None = None
                     ) -> BlockControl | None:
    """Control (map coordinates) -> frame.

    A height-only point needs a plan position and a plan-only point a height to be converted:
    they are taken from ``estimates`` ((K, 3) frame coordinates of the same points, e.g. the
    intersected initial points; NaN rows allowed) or else from the mean of the full points. The
    frame keeps the given components only (z of a height point, x, y of a plan point), whose error
    from a wrong filled-in component is that component's error times the slope of the level
    surface in the frame (s / R: 0.2 % at 14 km from the origin; an estimate within 1 m costs 2 mm).
    Sigmas are rotated as diagonal covariances.
    """
    if ctrl is None or frame.is_identity:
        return ctrl
    xyz = np.array(ctrl.xyz, dtype=np.float64, copy=True)
    kinds = np.array(ctrl.kind)
    full = kinds == "full"
    fill = np.nanmean(xyz[full], axis=0) if full.any() else np.nanmean(xyz, axis=0)
    fill = np.where(np.isfinite(fill), fill, 0.0)
    est_map = None
    if estimates is not None:
        e = np.asarray(estimates, dtype=np.float64).reshape(-1, 3)
        ok = np.isfinite(e).all(axis=1)
        est_map = np.full_like(e, np.nan)
        if ok.any():
            est_map[ok] = frame.map_from_frame(e[ok])
    for i, k in enumerate(ctrl.kind):
        cols = [0, 1] if k == "height" else ([2] if k == "plan" else [])
        for c in cols:
            v = est_map[i, c] if est_map is not None and np.isfinite(est_map[i, c]) else fill[c]
            xyz[i, c] = v
    if not np.isfinite(xyz).all():
        raise InvalidInputError("control coordinates must be finite to be converted into the adjustment frame")
    xf = frame.frame_from_map(xyz)
    sig = _sigma_rotated(frame.frame_from_grid_at(xyz), np.asarray(ctrl.sigma_m, dtype=np.float64))
    return replace(ctrl, xyz=xf, sigma_m=sig)


def _rotate_nan(G: F64, v: F64) -> F64:
    """Rotate (N, 3) vectors with NaN components (NaN read as 0; NaN kept where the input had it)."""
    vv = np.where(np.isfinite(v), v, 0.0)
    out = np.einsum("nij,nj->ni", G, vv)
    return np.where(np.isfinite(v), out, np.nan)


def result_to_map(frame: AdjustmentFrame, res: BundleResult, gnss: GnssObservations | None = None) -> BundleResult:
    """The bundle's result in the frame -> in the CRS of the inputs.

    Positions and points exactly (through PROJ); rotations into the local grid at each camera
    (:mod:`stereo.block.frames`); standard errors, covariances, residuals and check-point errors
    rotated into the local grid at their point (grid east, grid north, up; metres). The pose
    covariance's angle block is rotated like a vector of small rotations (exact for the small
    angles of a near-vertical camera); the correlation matrix is left in the frame. GNSS residuals are
    rotated at the positions of ``gnss`` (frame coordinates, the adjustment's; else at the poses, in order).
    """
    if frame.is_identity:
        return res
    poses = list(res.poses)
    C = np.array([p.position for p in poses]).reshape(-1, 3)
    R = np.array([p.rotation for p in poses]).reshape(-1, 3, 3)
    C_map = frame.map_from_frame(C)
    R_map = frame.rotations_out(R, C)
    new_poses = tuple(Pose(p.image, p.camera, C_map[i], _orthonormal(R_map[i])) for i, p in enumerate(poses))
    Gc = frame.grid_from_frame(C)
    pcov = np.asarray(res.pose_covariance, dtype=np.float64)
    pose_cov = pcov
    pose_std = np.asarray(res.pose_std, dtype=np.float64)
    if pcov.shape == (len(poses), 6, 6):
        T = np.zeros((len(poses), 6, 6))
        T[:, :3, :3] = Gc
        T[:, 3:, 3:] = Gc
        pose_cov = T @ np.where(np.isfinite(pcov), pcov, 0.0) @ np.swapaxes(T, -1, -2)
        finite_cov = np.asarray(np.isfinite(pcov).all(axis=(1, 2)), dtype=bool)
        pose_cov = np.where(finite_cov[:, None, None], pose_cov, np.nan)
        with np.errstate(invalid="ignore"):
            pose_std = np.where(np.isfinite(pose_std), np.sqrt(np.maximum(np.diagonal(pose_cov, axis1=1, axis2=2), 0)),
                                np.nan)
    X = np.asarray(res.points, dtype=np.float64)
    ok = np.isfinite(X).all(axis=1)
    X_map = np.full_like(X, np.nan)
    G = np.broadcast_to(np.eye(3), (len(X), 3, 3)).copy()
    if ok.any():
        X_map[ok] = frame.map_from_frame(X[ok])
        G[ok] = frame.grid_from_frame(X[ok])
    point_cov = res.point_covariance
    pstd = np.asarray(res.point_std, dtype=np.float64)
    if point_cov is not None:
        pc = np.asarray(point_cov, dtype=np.float64)
        point_cov = G @ pc @ np.swapaxes(G, -1, -2)
        with np.errstate(invalid="ignore"):
            point_std = np.sqrt(np.maximum(np.diagonal(point_cov, axis1=1, axis2=2), 0))
        point_std = np.where(np.isfinite(pstd), point_std, np.nan)
    else:
        point_std = np.where(np.isfinite(pstd), _sigma_rotated(G, np.where(np.isfinite(pstd), pstd, 0.0)), np.nan)
    pid = {p: k for k, p in enumerate(res.point_ids)}
    crows = np.array([pid[i] for i in res.control_ids], dtype=np.int64)
    ctrl_res = np.asarray(res.control_residuals, dtype=np.float64).reshape(-1, 3)
    if len(crows):
        ctrl_res = _rotate_nan(G[crows], ctrl_res)
    krows = np.array([pid[i] for i in res.check_ids], dtype=np.int64)
    chk_err = np.asarray(res.check_errors, dtype=np.float64).reshape(-1, 3)
    chk_std = np.asarray(res.check_std, dtype=np.float64).reshape(-1, 3)
    if len(krows):
        chk_err = np.einsum("nij,nj->ni", G[krows], chk_err)
        given_var = np.maximum(chk_std ** 2 - pstd[krows] ** 2, 0.0)  # the check points' own a-priori variance
        if res.point_covariance is not None:
            cov = np.asarray(res.point_covariance, dtype=np.float64)[krows] + np.stack([np.diag(v) for v in given_var])
            cov = G[krows] @ cov @ np.swapaxes(G[krows], -1, -2)
            chk_std = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0))
        else:
            chk_std = _sigma_rotated(G[krows], chk_std)
    gres = np.asarray(res.gnss_residuals, dtype=np.float64).reshape(-1, 3)
    if len(gres):
        Gg = (frame.grid_from_frame(np.asarray(gnss.position, dtype=np.float64)[: len(gres)]) if gnss is not None
              and len(gnss.position) >= len(gres) else Gc[: len(gres)])
        gres = np.einsum("nij,nj->ni", Gg, gres)
    return replace(res, poses=new_poses, points=X_map, pose_std=pose_std, pose_covariance=pose_cov,
                   point_std=point_std, point_covariance=point_cov, control_residuals=ctrl_res,
                   check_errors=chk_err, check_std=chk_std, gnss_residuals=gres)


# --------------------------------------------------------------------------- measurements as input
def observation_images(images: Sequence[object], poses: object, observations: object) -> list[str]:
    """The block's image names when it is adjusted from an observations CSV: the pose file's, in its order.

    Raises
    ------
    InvalidInputError
        IMAGES given too, or no pose file.
    """
    if images:
        raise InvalidInputError(f"give either IMAGES or --observations {str(observations)!r}, not both (the "
                                "observations CSV names the images; its measurements need no image file)")
    if poses is None:
        raise InvalidInputError("--observations needs --poses: the pose file names the images and gives their "
                                "initial orientation")
    pf = read_pose_file(poses)  # type: ignore[arg-type]
    if pf.geo is not None:
        return list(pf.geo.images)
    return [p.image for p in pf.poses]


def observation_tracks(path: object, inp: Any, names: Sequence[str], check_ids: Sequence[str],
                       default_sigma_px: float) -> tuple[Tracks, str]:
    """The tie tracks of an observations CSV and its summary line.

    Points the control file measures itself are left out of the CSV's measurements (the control
    file's measurements win: an earlier run's observations.csv holds them too); control and check
    points the control file gives coordinates of but measures in no image are taken from the CSV.
    A check or control point measured in fewer than two images (CSV and control file together)
    is an error.
    """
    sizes = {n: (inp.cameras[k].width, inp.cameras[k].height) for n, k in zip(names, inp.camera_of, strict=True)}
    c = inp.control
    control_measured = () if c is None else tuple(c.meas_id)
    control_ids = () if c is None else [i for i, k in zip(c.ids, c.kind, strict=True) if k != "tie"]
    obs: ObservationTable = read_observations(path, names, sizes, default_sigma_px=default_sigma_px)  # type: ignore
    t = obs.tracks
    own = set(control_measured)
    drop = np.array([t.point_ids[i] in own for i in t.obs_point], dtype=bool)
    line = obs.summary_line()
    if drop.any():
        t = t.subset(~drop)
        line += (f"; {int(drop.sum())} measurements of {len(own & set(obs.tracks.point_ids))} control point(s) taken "
                 "from the control file instead")
    counts: dict[str, int] = {}
    for pid in control_measured:
        counts[pid] = counts.get(pid, 0) + 1
    rays = dict(zip(t.point_ids, t.rays_per_point().tolist(), strict=True))
    short = [c for c in control_ids if counts.get(c, 0) + rays.get(c, 0) < 2]
    short_checks = [c for c in check_ids if c in short]
    if short_checks:
        raise InvalidInputError(f"check point(s) {short_checks[:5]} are measured in fewer than two images (neither "
                                f"{str(path)!r} nor the control file measures them twice): they cannot be checked")
    if short:
        raise InvalidInputError(f"control point(s) {short[:5]} are measured in fewer than two images (neither "
                                f"{str(path)!r} nor the control file measures them twice): measure them, or leave "
                                "them out of the control file")
    return t, line
