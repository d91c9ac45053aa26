"""The ``rectify demo`` run: the embedded Landsat scene seen by a tilted camera, rectified back.

1. The embedded Landsat GeoTIFF (``rectify/data/RGB.byte.tif``, EPSG:32618)
   is warped into a simulated tilted frame by a known homography
   (:data:`H_FRAME_FROM_LANDSAT`); the frame has no georeferencing.
2. GCPs are "picked" on the frame at well-spread valid pixels (with a
   simulated picking error of ``pick_sigma_px``); their map coordinates come
   from the truth. Four extra points are kept as check points.
3. The frame is rectified back with ``homography`` (bilinear) into a
   georeferenced GeoTIFF; the geolocation RMSE of the fitted model against
   the truth (over a dense grid of the frame) is reported in metres and in
   Landsat pixels, with the GCP residual report.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import numpy as np
from affine import Affine

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.errors import InvalidInputError, RasterIOError
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms.study import comparison_summary, summary_lines
from rectify.raster.georectify import georectify
from rectify.raster.georef import world_from_pixel
from rectify.raster.io import raster_info, read_window, write_raster
from rectify.raster.warp import WarpOptions, warp_array
from rectify.report.builder import write_warp_report

__all__ = ["demo_raster_path", "H_FRAME_FROM_LANDSAT", "DemoResult", "run_demo"]

logger = logging.getLogger(__name__)

#: Landsat pixel (col, row) -> tilted frame pixel: a projective view of the scene.
H_FRAME_FROM_LANDSAT = np.array([[0.9, 0.15, 40.0], [-0.1, 0.95, 60.0], [2e-4, 1e-4, 1.0]])
FRAME_SHAPE = (800, 900)


def demo_raster_path() -> Path:
    """Path of the embedded Landsat GeoTIFF (raises RasterIOError when missing)."""
    p = Path(str(files("rectify") / "data" / "RGB.byte.tif"))
    if not p.is_file():
        raise RasterIOError(f"embedded demo raster not found at {str(p)!r}")
    return p


@dataclass(frozen=True)
class DemoResult:
    """Figures of a demo run (all distances against the known truth)."""

    out_dir: Path
    frame: Path
    gcps: Path
    rectified: Path
    report: Path | None
    fit_summary: dict
    geolocation_rmse_m: float
    geolocation_max_m: float
    pixel_size_m: float
    compare_summary: dict | None
    #: the comparison as readable labelled lines (``rectify.geometry.transforms.study.summary_lines``),
    #: for the CLI to echo
    compare_lines: tuple[str, ...] = ()

    def summary_lines(self) -> list[str]:
        """The lines ``rectify demo`` prints: files, GCP fit (m), geolocation error, comparison, report."""
        s = self.fit_summary
        lines = [f"frame: {self.frame}",
                 f"GCPs: {self.gcps} ({s['n_fit']} control, {s['n_check']} check points)",
                 f"GCP fit (homography): RMSE {s['rmse']:.3f} m, sigma0 {s['sigma0']:.3f} m, "
                 f"check RMSE {s['rmse_check']:.3f} m",
                 f"rectified: {self.rectified}",
                 f"geolocation RMSE against the truth: {self.geolocation_rmse_m:.2f} m = "
                 f"{self.geolocation_rmse_m / self.pixel_size_m:.4f} Landsat px (max {self.geolocation_max_m:.2f} m)"]
        lines += [f"projective comparison: {line}" for line in self.compare_lines]
        lines.append(f"report: {self.report}")
        return lines


def _pick(valid: np.ndarray, n_x: int, n_y: int, margin: int = 40) -> np.ndarray:
    """One valid pixel near the centre of each of n_x * n_y cells (col, row)."""
    h, w = valid.shape
    pts = []
    ys, xs = np.nonzero(valid)
    for j in range(n_y):
        for i in range(n_x):
            cx = margin + (i + 0.5) * (w - 2 * margin) / n_x
            cy = margin + (j + 0.5) * (h - 2 * margin) / n_y
            k = int(np.argmin((xs - cx) ** 2 + (ys - cy) ** 2))
            pts.append((float(xs[k]), float(ys[k])))
    return np.array(pts)


def run_demo(out_dir: str | Path, *, overwrite: bool = False, pick_sigma_px: float = 0.15, seed: int = 4,
             with_compare: bool = True, progress: Callable[[int, int], None] | None = None) -> DemoResult:
    """Run the demo into ``out_dir`` (created when absent). See the module docstring.

    Every output (``tilted_frame.tif``, ``gcps.csv``, ``rectified.tif``, ``report/``) is checked
    before any work.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ws = Workspace(out, overwrite=overwrite, report_dir=out / "report")
    ws.prepare("tilted_frame.tif", "gcps.csv", "rectified.tif")
    src = demo_raster_path()
    info = raster_info(src)
    img, valid = read_window(src, 0, 0, info.width, info.height)
    hinv = np.linalg.inv(H_FRAME_FROM_LANDSAT)
    frame = warp_array(img, hinv, FRAME_SHAPE)
    fvalid = warp_array(valid.astype(np.uint8) * 255, hinv, FRAME_SHAPE, resampling="nearest") > 0
    frame[~fvalid] = 0
    frame_path = write_raster(out / "tilted_frame.tif", frame, Affine(1, 0, 0, 0, 1.0000001, 0), None, nodata=0,
                              overwrite=overwrite)

    def truth(p: np.ndarray) -> np.ndarray:  # frame pixel -> map (EPSG:32618)
        hp = np.c_[p, np.ones(len(p))] @ hinv.T
        return world_from_pixel(info.transform, hp[:, :2] / hp[:, 2:])

    inner = fvalid.copy()
    inner[:, :] = fvalid & (np.roll(fvalid, 25, 0) & np.roll(fvalid, -25, 0) & np.roll(fvalid, 25, 1)
                            & np.roll(fvalid, -25, 1))
    ctrl = _pick(inner, 4, 3)
    chk = _pick(inner, 2, 2, margin=200)
    rng = np.random.default_rng(seed)
    pix = np.vstack([ctrl, chk])
    tgt = truth(pix)
    picked = pix + rng.normal(0.0, pick_sigma_px, pix.shape)
    ids = tuple([f"gcp{i + 1}" for i in range(len(ctrl))] + [f"chk{i + 1}" for i in range(len(chk))])
    check = np.r_[np.zeros(len(ctrl), bool), np.ones(len(chk), bool)]
    gcps = GcpTable(ids, picked, tgt, None, check, info.crs)
    gcp_path = ws.save_gcps(out / "gcps.csv", gcps)

    res = georectify(frame_path, out / "rectified.tif", gcps, method="homography",
                     options=WarpOptions(resampling="bilinear"), overwrite=overwrite, progress=progress)
    # geolocation error of the fitted model against the truth over the valid frame
    ys, xs = np.nonzero(fvalid[::10, ::10])
    grid_pts = np.column_stack([xs * 10.0, ys * 10.0])
    err = np.linalg.norm(res.fit.model(grid_pts) - truth(grid_pts), axis=1)
    rmse = float(np.sqrt(np.mean(err ** 2)))
    pix_m = float(abs(info.transform.a))
    compare = None
    if with_compare:
        compare = _compare_summary()
    summary = {"geolocation_rmse_m": rmse, "geolocation_max_m": float(err.max()),
               "geolocation_rmse_landsat_px": rmse / pix_m, "pick_sigma_px": pick_sigma_px,
               "truth_homography_frame_from_landsat": H_FRAME_FROM_LANDSAT.tolist()}
    if compare:
        summary["projective_comparison"] = compare
    rep = write_warp_report(out / "report", res, source_shape=FRAME_SHAPE, title="rectify demo: Landsat tilted frame",
                            summary=summary, background=frame, overwrite=overwrite)
    return DemoResult(out, frame_path, gcp_path, res.warp.path, rep, res.fit.table.summary(), rmse,
                      float(err.max()), pix_m, compare, _compare_lines(compare))


def _compare_summary() -> dict | None:
    """The projective comparison of ``rectify.actions.compare`` with small settings (None when it fails)."""
    try:
        return comparison_summary(n_trials=5)
    except Exception as err:  # a side study: never let it break the demo
        logger.warning("projective comparison failed: %s", err)
        return None


def _compare_lines(summary: dict | None) -> tuple[str, ...]:
    """Readable lines of the projective comparison (empty when there is none)."""
    if not summary:
        return ()
    return tuple(summary_lines(summary)) or tuple(f"{k}: {v}" for k, v in summary.items())


@dataclass(frozen=True)
class DemoOptions:
    """Options of :func:`demo`: simulated GCP picking error (px), its seed, and the short comparison."""

    pick_sigma_px: float = 0.15
    seed: int = 4
    with_compare: bool = True


def demo(ws: Workspace, options: DemoOptions = DemoOptions(), *, progress: Progress = None) -> DemoResult:
    """The embedded Landsat scene through a tilted frame and back into ``ws.root`` (see :mod:`rectify.actions.demo`)."""
    if ws.root is None:
        raise InvalidInputError("the demo needs an output folder")

    return run_demo(ws.root, overwrite=ws.overwrite, pick_sigma_px=options.pick_sigma_px, seed=options.seed,
                    with_compare=options.with_compare, progress=progress)
