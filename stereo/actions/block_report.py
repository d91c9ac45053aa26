"""The report of ``stereo block``: its residual tables (image observations, control, check points, GNSS
centres) and the HTML page (:func:`stereo.report.block.write_block_report`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.accuracy import AccuracyStatement
from rectify.geometry.residuals import ResidualTable, rms
from stereo.block.bundle.result import BundleResult
from stereo.block.types import GnssObservations, Tracks
from stereo.report.block import write_block_report

__all__ = ["block_report", "block_tables", "check_accuracy", "rms_labels"]


def check_accuracy(res: BundleResult) -> AccuracyStatement | None:
    """The accuracy statement of the block's check points (adjusted - given, ground units, in the local grid
    of the output CRS), from those with all three errors (plan-only or height-only check points are left
    out of it); None without check points."""
    e = np.asarray(res.check_errors, dtype=np.float64).reshape(-1, 3)
    full = np.isfinite(e).all(axis=1)
    return AccuracyStatement.from_errors(e[full]) if full.any() else None


def block_tables(res: BundleResult, tracks: Tracks, units: str, gnss: GnssObservations | None) -> list[ResidualTable]:
    """Residual tables of the report (residual = adjusted - observed): image observations, control, check
    points, GNSS centres."""
    ids = [f"{tracks.point_ids[p]}@{tracks.images[i]}" for p, i in zip(tracks.obs_point, tracks.obs_image,
                                                                       strict=True)]
    v = np.asarray(res.residuals_px, dtype=np.float64)  # observed - computed
    w = np.min(np.asarray(res.weights, dtype=np.float64).reshape(-1, 2), axis=1)
    out = [ResidualTable("bundle: image observations", ids, tracks.obs_pixel, tracks.obs_pixel - v, "px",
                         weights=w, outlier=res.flagged, position_px=tracks.obs_pixel, sigma0=res.sigma0,
                         extra={"sigma0_unit_weight": res.sigma0})]
    comps = ("dX", "dY", "dZ")
    pid = {p: k for k, p in enumerate(res.point_ids)}
    X = np.asarray(res.points, dtype=np.float64)
    if len(res.control_ids):
        adj = X[[pid[i] for i in res.control_ids]]
        r = np.asarray(res.control_residuals, dtype=np.float64)  # given - adjusted; NaN: not observed
        given = np.where(np.isfinite(r), adj + r, adj)
        out.append(ResidualTable("bundle: control points", res.control_ids, given, adj, units, components=comps,
                                 outlier=np.array([c in res.flagged_control for c in res.control_ids], dtype=bool),
                                 extra=rms_labels(adj - given)))
    if len(res.check_ids):
        e = np.asarray(res.check_errors, dtype=np.float64)
        adj = X[[pid[i] for i in res.check_ids]]
        sd = np.linalg.norm(np.asarray(res.check_std, dtype=np.float64).reshape(-1, 3), axis=1)
        out.append(ResidualTable("bundle: check points (adjusted - given)", res.check_ids, adj - e, adj, units,
                                 components=comps, check=np.ones(len(e), dtype=bool),
                                 std=np.where(sd > 0, sd, np.nan), extra=rms_labels(e)))
    if len(res.gnss_residuals) and gnss is not None:
        g = np.asarray(res.gnss_residuals, dtype=np.float64)  # observed - adjusted
        obs = np.asarray(gnss.position, dtype=np.float64)[: len(g)]
        out.append(ResidualTable("bundle: GNSS projection centres", list(gnss.images)[: len(g)], obs, obs - g, units,
                                 components=comps, extra=rms_labels(g)))
    return out


def rms_labels(v: NDArray[np.float64]) -> dict[str, float]:
    """The two RMS of (N, 3) residuals, labelled: per component (over x, y and z) and of the 3D length."""
    return {"rms_per_component_m": rms(v), "rms_3d_m": float(np.sqrt(np.mean(np.sum(v ** 2, axis=1))))
            if len(v) else float("nan")}


def block_report(out: Path, res: BundleResult, tracks: Tracks, crs: str | None, summary: dict[str, Any],
                 units: str, gnss: GnssObservations | None) -> Path:
    """Write the block's HTML report into ``out`` (a staged folder); return the page."""
    pid = {p: k for k, p in enumerate(res.point_ids)}
    X = np.asarray(res.points, dtype=np.float64)
    ctrl_xy = X[[pid[i] for i in res.control_ids if i in pid]][:, :2] if len(res.control_ids) else None
    chk_xy = chk_cov = chk_err = None
    if len(res.check_ids):
        rows = [pid[i] for i in res.check_ids]
        chk_xy = X[rows][:, :2]
        chk_err = np.asarray(res.check_errors, dtype=np.float64)[:, :2]
        if res.point_covariance is not None:
            chk_cov = np.asarray(res.point_covariance)[rows][:, :2, :2]
        else:
            s = np.asarray(res.check_std, dtype=np.float64)[:, :2]
            chk_cov = np.stack([np.diag(v ** 2) for v in s])
    ground: dict[str, Any] = {}
    if ctrl_xy is not None and len(ctrl_xy) == len(res.control_ids):
        ground["bundle: control points"] = ctrl_xy
    if chk_xy is not None:
        ground["bundle: check points (adjusted - given)"] = chk_xy
    rep = {**summary, "datum": " | ".join(res.datum), "warnings": list(res.warnings),
           "sigma0_groups": dict(res.sigma0_groups), "variance_factors": dict(res.variance_factors),
           "redundancy_groups": dict(res.redundancy_groups)}
    # the workspace refused an existing report without --overwrite before any work: the folder is this job's
    shown = np.where(np.asarray(res.determined, dtype=bool)[:, None], X, np.nan)
    return write_block_report(out, title=f"stereo block: {len(res.poses)} images", cameras=res.cameras,
                              poses=res.poses, points=shown, tracks=tracks,
                              tables=block_tables(res, tracks, units, gnss), residual_px=res.residuals_px,
                              flagged=res.flagged, pose_std=res.pose_std, pose_cov=res.pose_covariance,
                              correlation=res.correlation, control_xy=ctrl_xy, check_xy=chk_xy,
                              check_cov_xy=chk_cov, check_error_xy=chk_err, summary=rep,
                              crs=crs if ground else None, ground_xy=ground or None, units=units, overwrite=True)
