"""Figures and the QA report of a block adjustment.

Figures (each a new :class:`matplotlib.figure.Figure`, no pyplot):

- the block layout: image footprints on the median point height
  (:func:`stereo.block.tracks_pairs.footprints`), projection centres, tie points coloured by the
  number of rays;
- rays per point (histogram) and tie points per image (bars);
- image residuals per image (RMS bars, pixels) with the count of flagged observations;
- precision per image (standard errors of the position and angles);
- error ellipses in plan: the 1-sigma position ellipse of every projection centre and of the
  check points, magnified to be visible, with the check-point errors as vectors;
- the correlation matrix of the orientation elements (the first images when the block is large).

The report page itself is written by :func:`rectify.report.builder.write_report` (residual tables as CSV
with histogram and Q-Q plots, the figures, ``report.json`` and ``report.html``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse, Polygon
from numpy.typing import ArrayLike, NDArray

from rectify.geometry.camera import Camera
from rectify.geometry.residuals import ResidualTable
from rectify.report.builder import write_report
from rectify.report.figures import _new_figure, correlation_heatmap_figure, readable_map_ticks
from stereo.block.tracks_pairs import footprints
from stereo.block.types import Pose, Tracks

__all__ = [
    "block_layout_figure",
    "ellipse_figure",
    "image_precision_figure",
    "image_residuals_figure",
    "rays_figure",
    "write_block_report",
]

#: at most this many orientation elements are drawn in the correlation heat map
MAX_CORRELATION_ELEMENTS = 60
_ANGLE_NAMES = ("omega", "phi", "kappa")


def _plan_axes(ax: Any, units: str, title: str) -> None:
    """Equal-scale plan axes X, Y in ground units, readable map ticks, legend and title."""
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"X ({units})")
    ax.set_ylabel(f"Y ({units})")
    readable_map_ticks(ax)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=11)


def block_layout_figure(cameras: Mapping[str, Camera], poses: Sequence[Pose], points: ArrayLike,
                        rays: ArrayLike, *, units: str = "m", control_xy: ArrayLike | None = None,
                        check_xy: ArrayLike | None = None) -> Figure:
    """Plan view: footprints on the mean point height, projection centres, tie points by rays.

    Parameters
    ----------
    points : (P, 3) array_like
        Adjusted object points, ground frame (NaN rows are skipped).
    rays : (P,) array_like
        Number of images that see each point.
    control_xy, check_xy : (K, 2) array_like, optional
        Plan positions of control and check points.
    """
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(rays, dtype=np.float64).reshape(-1)
    ok = np.isfinite(X).all(axis=1)
    z = float(np.median(X[ok, 2])) if ok.any() else 0.0
    fig = _new_figure(8.0, 7.0)
    ax = fig.add_subplot()
    for p, fp in zip(poses, footprints(poses, cameras, z), strict=True):
        if np.isfinite(fp).all():
            ax.add_patch(Polygon(fp, closed=True, fill=False, lw=0.8, ec="#555555", alpha=0.7))
        ax.annotate(p.image, (float(p.position[0]), float(p.position[1])), fontsize=6, ha="center",
                    va="bottom", color="#333333")
    C = np.array([p.position for p in poses]).reshape(-1, 3)
    if ok.any():
        sc = ax.scatter(X[ok, 0], X[ok, 1], c=r[ok], s=3, cmap="viridis", vmin=2, vmax=max(3.0, float(r[ok].max())),
                        label=f"tie points ({int(ok.sum())})")
        fig.colorbar(sc, ax=ax, shrink=0.8).set_label("rays per point")
    ax.plot(C[:, 0], C[:, 1], "k^", ms=5, label=f"projection centres ({len(C)})")
    for xy, style, label in ((control_xy, "rs", "control"), (check_xy, "bD", "check")):
        if xy is not None and len(np.asarray(xy)):
            a = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
            ax.plot(a[:, 0], a[:, 1], style, ms=6, mfc="none", label=f"{label} ({len(a)})")
    _plan_axes(ax, units, f"Block layout: footprints on Z = {z:.1f} {units}, tie points by rays")
    return fig


def rays_figure(tracks: Tracks) -> Figure:
    """Histogram of rays per point and bars of tie points per image."""
    fig = _new_figure(10.0, 4.0)
    a1, a2 = fig.subplots(1, 2)
    rays = tracks.rays_per_point()
    if len(rays):
        bins = np.arange(1.5, rays.max() + 1.5)
        a1.hist(rays, bins=bins, color="#4c72b0", edgecolor="white")
    a1.set_xlabel("rays per point")
    a1.set_ylabel("points")
    a1.set_title(f"{tracks.n_points} points, {tracks.n_obs} observations", fontsize=10)
    per = tracks.points_per_image()
    a2.bar(range(len(per)), per, color="#55a868")
    a2.set_xticks(range(len(per)), tracks.images, rotation=90, fontsize=6 if len(per) > 20 else 8)
    a2.set_ylabel("observations")
    a2.set_title("tie points per image", fontsize=10)
    return fig


def image_residuals_figure(tracks: Tracks, residual_px: ArrayLike, flagged: ArrayLike) -> Figure:
    """RMS image residual (pixels) per image, and the number of flagged observations above each bar."""
    v = np.asarray(residual_px, dtype=np.float64).reshape(-1, 2)
    fl = np.asarray(flagged, dtype=bool).reshape(-1)
    n = len(tracks.images)
    ok = ~fl & np.isfinite(v).all(axis=1)
    ss = np.bincount(tracks.obs_image[ok], weights=np.sum(v[ok] ** 2, axis=1), minlength=n)
    cnt = np.bincount(tracks.obs_image[ok], minlength=n)
    with np.errstate(divide="ignore", invalid="ignore"):
        rms_img = np.sqrt(ss / np.maximum(cnt, 1))  # of |v| (both coordinates)
    nfl = np.bincount(tracks.obs_image[fl], minlength=n)
    fig = _new_figure(max(6.0, 0.25 * n + 2.0), 4.0)
    ax = fig.add_subplot()
    ax.bar(range(n), rms_img, color="#4c72b0")
    for i in np.flatnonzero(nfl):
        ax.annotate(f"{nfl[i]}", (i, rms_img[i]), ha="center", va="bottom", fontsize=7, color="#d62728")
    ax.set_xticks(range(n), tracks.images, rotation=90, fontsize=6 if n > 20 else 8)
    ax.set_ylabel("RMS |v| of unflagged observations (px)")
    ax.set_title("Image residuals per image (red: flagged observations)", fontsize=10)
    return fig


def image_precision_figure(poses: Sequence[Pose], std: ArrayLike, *, units: str = "m") -> Figure:
    """Standard errors of each image's position (ground units) and angles (degrees)."""
    s = np.asarray(std, dtype=np.float64).reshape(-1, 6)
    n = len(poses)
    names = [p.image for p in poses]
    fig = _new_figure(max(6.0, 0.25 * n + 2.0), 6.0)
    a1, a2 = fig.subplots(2, 1, sharex=True)
    w = 0.27
    x = np.arange(n)
    for k, (lab, col) in enumerate(zip(("X", "Y", "Z"), ("#4c72b0", "#55a868", "#c44e52"), strict=True)):
        a1.bar(x + (k - 1) * w, s[:, 3 + k], width=w, color=col, label=f"s{lab}")
        a2.bar(x + (k - 1) * w, np.degrees(s[:, k]) * 3600.0, width=w, color=col, label=f"s{_ANGLE_NAMES[k]}")
    a1.set_ylabel(f"position std ({units})")
    a2.set_ylabel("angle std (arc seconds)")
    a1.legend(fontsize=8)
    a2.legend(fontsize=8)
    a2.set_xticks(x, names, rotation=90, fontsize=6 if n > 20 else 8)
    a1.set_title("Precision per image (a-posteriori standard errors)", fontsize=10)
    return fig


def ellipse_figure(poses: Sequence[Pose], pose_cov_xy: ArrayLike, *, check_xy: ArrayLike | None = None,
                   check_cov_xy: ArrayLike | None = None, check_error_xy: ArrayLike | None = None,
                   units: str = "m") -> Figure:
    """Error ellipses in plan: 1-sigma ellipses of the projection centres and check points.

    Parameters
    ----------
    pose_cov_xy : (n, 2, 2) array_like
        Covariance of each projection centre's X, Y, ground units squared.
    check_xy, check_cov_xy, check_error_xy : optional
        Check points: plan position (K, 2), covariance (K, 2, 2) of the estimated point and the
        error (estimated - given) (K, 2).

    The ellipses and vectors are magnified by one factor (stated in the title) so that the largest
    is a tenth of the block's extent.
    """
    C = np.array([p.position[:2] for p in poses]).reshape(-1, 2)
    cov = np.asarray(pose_cov_xy, dtype=np.float64).reshape(-1, 2, 2)
    allxy = [C]
    semi = [np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0, None)).max(axis=1)] if len(cov) else []
    if check_xy is not None and len(np.asarray(check_xy)):
        kxy = np.asarray(check_xy, dtype=np.float64).reshape(-1, 2)
        allxy.append(kxy)
        if check_cov_xy is not None:
            semi.append(np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(check_cov_xy).reshape(-1, 2, 2)), 0,
                                        None)).max(axis=1))
        if check_error_xy is not None:
            semi.append(np.linalg.norm(np.asarray(check_error_xy, dtype=np.float64).reshape(-1, 2), axis=1))
    pts = np.vstack(allxy)
    extent = float(np.ptp(pts, axis=0).max()) if len(pts) > 1 else 1.0
    biggest = max((float(np.nanmax(s)) for s in semi if len(s)), default=0.0)
    mag = 1.0 if not (biggest > 0 and math.isfinite(biggest)) else 0.1 * max(extent, 1e-9) / biggest
    fig = _new_figure(8.0, 7.0)
    ax = fig.add_subplot()

    def draw(xy: NDArray, cv: NDArray, colour: str) -> None:
        for c0, cc in zip(xy, cv, strict=True):
            w, V = np.linalg.eigh(cc)
            w = np.sqrt(np.clip(w, 0, None)) * mag
            ang = math.degrees(math.atan2(V[1, 1], V[0, 1]))
            ax.add_patch(Ellipse(tuple(c0), 2 * w[1], 2 * w[0], angle=ang, fill=False, ec=colour, lw=1.0))

    draw(C, cov, "#4c72b0")
    ax.plot(C[:, 0], C[:, 1], "k^", ms=4, label="projection centres (1-sigma ellipses, blue)")
    if check_xy is not None and len(np.asarray(check_xy)):
        kxy = np.asarray(check_xy, dtype=np.float64).reshape(-1, 2)
        if check_cov_xy is not None:
            draw(kxy, np.asarray(check_cov_xy, dtype=np.float64).reshape(-1, 2, 2), "#c44e52")
        ax.plot(kxy[:, 0], kxy[:, 1], "rD", ms=4, mfc="none", label="check points (ellipses red, errors black)")
        if check_error_xy is not None:
            e = np.asarray(check_error_xy, dtype=np.float64).reshape(-1, 2) * mag
            ax.quiver(kxy[:, 0], kxy[:, 1], e[:, 0], e[:, 1], angles="xy", scale_units="xy", scale=1.0, width=0.003)
    ax.margins(0.1)
    _plan_axes(ax, units, f"Error ellipses in plan (1 sigma), magnified x{mag:.3g}")
    return fig


def correlation_figure(poses: Sequence[Pose], correlation: ArrayLike) -> Figure:
    """The correlation matrix of the orientation elements (of the first images when the block is large)."""
    c = np.asarray(correlation, dtype=np.float64)
    names = [f"{p.image}:{n}" for p in poses for n in ("om", "ph", "ka", "X", "Y", "Z")]
    m = min(len(names), MAX_CORRELATION_ELEMENTS, c.shape[0])
    m -= m % 6
    sub = np.clip(np.nan_to_num(c[:m, :m]), -1.0, 1.0)
    if m <= 24:
        return correlation_heatmap_figure(names[:m], sub, title="Correlation of the orientation elements")
    fig = _new_figure(9.0, 8.0)
    ax = fig.add_subplot()
    im = ax.imshow(sub, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(2, m, 6), [p.image for p in poses[: m // 6]], rotation=90, fontsize=7)
    ax.set_yticks(range(2, m, 6), [p.image for p in poses[: m // 6]], fontsize=7)
    fig.colorbar(im, ax=ax, shrink=0.85).set_label("correlation coefficient (unitless)")
    ax.set_title(f"Correlation of the orientation elements (omega, phi, kappa, X, Y, Z per image; "
                 f"{m // 6} of {len(poses)} images)", fontsize=10)
    return fig


def write_block_report(out_dir: str | os.PathLike, *, title: str, cameras: Mapping[str, Camera],
                       poses: Sequence[Pose], points: ArrayLike, tracks: Tracks, tables: Sequence[ResidualTable],
                       residual_px: ArrayLike, flagged: ArrayLike, pose_std: ArrayLike | None = None,
                       pose_cov: ArrayLike | None = None, correlation: ArrayLike | None = None,
                       control_xy: ArrayLike | None = None, check_xy: ArrayLike | None = None,
                       check_cov_xy: ArrayLike | None = None, check_error_xy: ArrayLike | None = None,
                       summary: Mapping[str, Any] | None = None, crs: str | None = None,
                       ground_xy: Mapping[str, ArrayLike] | None = None, units: str = "m",
                       overwrite: bool = False) -> Path:
    """Write the QA report of a block adjustment into ``out_dir``; return the path of ``report.html``.

    Parameters
    ----------
    tables : sequence of ResidualTable
        Image residuals (px), GNSS residuals, control residuals, check-point errors (ground units).
    residual_px, flagged : (M, 2), (M,)
        Image residuals and blunder flags of every observation of ``tracks``.
    pose_std : (n, 6), optional
        omega, phi, kappa (rad), X, Y, Z standard errors per image.
    pose_cov : (n, 6, 6), optional
        Their covariance (the X, Y block draws the ellipses).
    correlation : (6n, 6n), optional
        Correlation of all orientation elements.
    crs, ground_xy : optional
        Ground CRS and, per table step, the plan coordinates (N, 2) of its points: those tables are
        also written as GeoJSON. Without ``ground_xy`` the CRS is not passed on.
    """
    figs: dict[str, Figure] = {
        "block layout": block_layout_figure(cameras, poses, points, tracks.rays_per_point(), units=units,
                                            control_xy=control_xy, check_xy=check_xy),
        "rays and tie points per image": rays_figure(tracks),
        "image residuals per image": image_residuals_figure(tracks, residual_px, flagged),
    }
    if pose_std is not None:
        figs["precision per image"] = image_precision_figure(poses, pose_std, units=units)
    if pose_cov is not None:
        cxy = np.asarray(pose_cov, dtype=np.float64).reshape(-1, 6, 6)[:, 3:5, 3:5]
        figs["error ellipses in plan"] = ellipse_figure(poses, cxy, check_xy=check_xy, check_cov_xy=check_cov_xy,
                                                        check_error_xy=check_error_xy, units=units)
    if correlation is not None and np.asarray(correlation).size:
        figs["correlation of the orientation elements"] = correlation_figure(poses, correlation)
    return write_report(out_dir, title=title, tables=list(tables), figures=figs, summary=dict(summary or {}),
                        crs=crs if ground_xy else None, ground_xy=dict(ground_xy) if ground_xy else None,
                        overwrite=overwrite)
