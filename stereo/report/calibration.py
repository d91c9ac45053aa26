"""Figures of a calibration and its report folder.

* residual vectors per view (small multiples over the frame),
* the distortion map: radial and decentering displacement over the frame,
* the correlation matrix of the interior elements,
* the coverage of the frame by target points (all views).

Figures are built without :mod:`matplotlib.pyplot` (Agg canvas, no global state),
like :mod:`rectify.report.figures`.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from rectify.atomic import atomic_write_text
from rectify.geometry.residuals import ResidualTable
from rectify.report.builder import write_report
from rectify.report.figures import correlation_heatmap_figure, nice_number
from stereo.calibration.result import Calibration

logger = logging.getLogger(__name__)

__all__ = ["residual_views_figure", "distortion_figure", "coverage_figure", "correlation_figure",
           "residual_table", "write_calibration_report"]


def _frame(ax: Any, w: int, h: int) -> None:
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")


def residual_views_figure(cal: Calibration, *, max_views: int = 30) -> Figure:
    """Residual vectors (exaggerated, common scale) of each view over the frame."""
    views = cal.views[:max_views]
    n = len(views)
    cols = min(5, n)
    rows = math.ceil(n / cols)
    w, h = cal.intrinsics.width, cal.intrinsics.height
    fig = Figure(figsize=(3.0 * cols, 3.0 * rows * h / w + 0.8), dpi=100)
    allr = np.concatenate([v.residuals for v in views])
    p95 = float(np.percentile(np.linalg.norm(allr, axis=1), 95)) or 1.0
    scale = nice_number(0.06 * w / p95)
    for k, v in enumerate(views):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.plot(v.pixel[:, 0], v.pixel[:, 1], ".", ms=2, color="0.5")
        ax.quiver(v.pixel[:, 0], v.pixel[:, 1], v.residuals[:, 0] * scale, v.residuals[:, 1] * scale,
                  angles="xy", scale_units="xy", scale=1, color="C3", width=0.006)
        _frame(ax, w, h)
        ax.set_title(f"{v.name}: RMS {v.rms_px:.3f} px", fontsize=8)
        ax.tick_params(labelsize=6)
    fig.suptitle(f"Residuals (adjusted - observed) x{scale:g}; {len(cal.views)} views", fontsize=10)
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.06, top=0.9, wspace=0.3, hspace=0.35)
    return fig


def distortion_figure(cal: Calibration, *, grid: int = 15) -> Figure:
    """Radial and decentering displacement over the frame (arrows, true direction; colour = length, px)."""
    i = cal.intrinsics
    w, h = i.width, i.height
    xs, ys = np.meshgrid(np.linspace(0, w - 1, grid + 1), np.linspace(0, h - 1, int(grid * h / w) + 1))
    p = np.column_stack([xs.ravel(), ys.ravel()])
    radial, dec = i.distortion_px(p)
    fig = Figure(figsize=(11, 4.6 * h / w + 0.9), dpi=100)
    for k, (d, name) in enumerate(((radial, "radial (k1, k2, k3)"), (dec, "decentering (p1, p2)"))):
        ax = fig.add_subplot(1, 2, k + 1)
        mag = np.linalg.norm(d, axis=1)
        top = float(mag.max()) or 1.0
        s = 0.8 * (w / grid) / top
        q = ax.quiver(p[:, 0], p[:, 1], d[:, 0] * s, d[:, 1] * s, mag, angles="xy", scale_units="xy", scale=1,
                      cmap="viridis")
        cb = fig.colorbar(q, ax=ax, shrink=0.8)
        cb.set_label("displacement (px)")
        ax.plot([i.cx], [i.cy], "k+", ms=12)
        if i.sx is not None and i.sy is not None:
            ax.plot([i.sx], [i.sy], "rx", ms=8)
        _frame(ax, w, h)
        ax.set_title(f"{name}: max {top:.2f} px", fontsize=10)
        ax.set_xlabel("column (px)")
        ax.set_ylabel("row (px)")
    fig.suptitle("Distortion over the frame (+ principal point)", fontsize=11)
    return fig


def coverage_figure(cal: Calibration) -> Figure:
    """All target points of all views over the frame, and the share of a 8 x 6 grid that they cover."""
    w, h = cal.intrinsics.width, cal.intrinsics.height
    pts = np.concatenate([v.pixel for v in cal.views])
    gx, gy = 8, 6
    cells = np.zeros((gy, gx), dtype=int)
    ix = np.clip((pts[:, 0] + 0.5) / w * gx, 0, gx - 1).astype(int)
    iy = np.clip((pts[:, 1] + 0.5) / h * gy, 0, gy - 1).astype(int)
    np.add.at(cells, (iy, ix), 1)
    fig = Figure(figsize=(6.5, 6.5 * h / w + 0.7), dpi=100)
    ax = fig.add_subplot()
    ax.imshow(cells > 0, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="Greens", vmin=0, vmax=3, alpha=0.6)
    for k, v in enumerate(cal.views):
        ax.plot(v.pixel[:, 0], v.pixel[:, 1], ".", ms=2, color=f"C{k % 10}")
    _frame(ax, w, h)
    ax.set_title(f"Coverage: {100 * np.mean(cells > 0):.0f}% of {gx} x {gy} cells have target points", fontsize=10)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    return fig


def correlation_figure(cal: Calibration) -> Figure:
    return correlation_heatmap_figure(list(cal.names), cal.correlation,
                                      title="Correlation of the interior orientation elements")


def residual_table(cal: Calibration) -> ResidualTable:
    """All image residuals as one table (ids ``view:point``)."""
    ids = [f"{v.name}:{p}" for v in cal.views for p in v.ids]
    obs = np.concatenate([v.pixel for v in cal.views])
    res = np.concatenate([v.residuals for v in cal.views])
    wts = np.concatenate([v.weights for v in cal.views])
    return ResidualTable("calibration", ids, obs, obs + res, "px", weights=wts, outlier=wts < 0.05,
                         position_px=obs, sigma0=cal.sigma0_px, n_params=len(cal.adjustment.names))


def calibration_dict(cal: Calibration, *, corners: dict[str, Any] | None = None) -> dict[str, Any]:
    """Everything of a calibration as JSON-able data (interior, covariance, views' EO; the corner check)."""
    out: dict[str, Any] = {
        "camera": cal.camera_dict(),
        "names": list(cal.names),
        "correlation": cal.correlation.tolist(),
        "covariance": cal.interior_covariance.tolist(),
        "rms_px": cal.rms_px,
        "sigma0_px": cal.sigma0_px,
        "start": cal.start_method,
        "robust": cal.robust,
        "condition_number": cal.adjustment.condition_number,
        "views": [{"name": v.name, "rms_px": v.rms_px, "omega_phi_kappa_rad": v.angles.tolist(),
                   "std_omega_phi_kappa_rad": v.std_angles.tolist(), "centre": v.centre.tolist(),
                   "std_centre": v.std_centre.tolist(), "rotation": v.rotation.tolist()} for v in cal.views],
    }
    if corners is not None:
        out["corners"] = corners
    return out


def write_calibration_report(out_dir: str | Path, cal: Calibration, *, title: str = "stereo calibrate",
                             overwrite: bool = False, corners: dict[str, Any] | None = None) -> Path:
    """Write figures, the residual table, ``calibration.json`` and ``report.html`` into ``out_dir``.

    ``corners`` (chessboard images): the refinement method, the corners found and kept, and each
    rejected corner (view, index, name, position, reason); the RMS is over the kept corners only.
    """
    figs = {"calibration_residuals_per_view": residual_views_figure(cal),
            "calibration_distortion": distortion_figure(cal),
            "calibration_coverage": coverage_figure(cal)}
    if len(cal.names) > 1:
        figs["calibration_correlation"] = correlation_figure(cal)
    summary = {"views": len(cal.views), "points": cal.n_points, "rms_px": cal.rms_px, "sigma0_px": cal.sigma0_px,
               "start": cal.start_method}
    summary.update({f"{n}": cal.value(n) for n in cal.names})
    summary.update({f"std_{n}": s for n, s in cal.std_errors.items()})
    if corners is not None:
        summary["corner_refinement"] = corners["method"]
        summary["corners_found"] = corners["found"]
        summary["corners_kept"] = corners["kept"]
        summary["corners_rejected"] = "; ".join(f"{r['view']} corner {r['corner']} (#{r['index']}): {r['reason']}"
                                                for r in corners["rejected"]) or "none"
    path = write_report(out_dir, title=title, tables=[residual_table(cal)], figures=figs, summary=summary,
                        overwrite=overwrite, image_shapes={"calibration": (cal.intrinsics.height,
                                                                           cal.intrinsics.width)},
                        principal_point_px=[cal.intrinsics.cx, cal.intrinsics.cy])
    atomic_write_text(Path(out_dir) / "calibration.json", json.dumps(calibration_dict(cal, corners=corners), indent=2),
                      overwrite=True)
    return path
