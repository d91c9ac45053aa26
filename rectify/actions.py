"""One function per step of the image side: ``match``, ``fit``, ``warp``, ``compare``, ``demo``.

Each action takes a :class:`~rectify.workspace.Workspace` (the job's files, overwrite policy and
report folder), the step's paths and an options dataclass (whose defaults are the command-line
defaults), checks every planned output and the report folder before any work, runs the step and
returns a frozen result whose :meth:`summary_lines` are the lines the command prints. The
``rectify`` commands (``rectify/cli``) only parse options, call one action and print those lines.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import InvalidInputError
from .formats import TIFF_SUFFIXES, GcpTable, has_embedded_gcps
from .io import raster_info
from .transforms import METHODS, FitResult, fit_gcps
from .transforms.quality import GcpGeometry, geographic_lines, judge_gcp_geometry
from .warp import (
    DEFAULT_MAX_PIXELS,
    RESAMPLING_NAMES,
    GeoRectification,
    WarpOptions,
    georectify,
    rectify_with_transform,
)
from .workspace import Workspace, check_table_crs

if TYPE_CHECKING:  # matplotlib comes with these: imported where used, so `rectify warp` starts faster
    from .compare import StudyConfig, StudyResults
    from .demo import DemoResult
    from .features import DETECTORS, VERIFY_METHODS, MatcherConfig, MatchResult
    from .mosaic import MosaicOptions, MosaicResult
    from .mosaic import mosaic as mosaic
    from .ortho import OrthoOptions
    from .ortho import ortho_from_files as ortho

#: names served from the modules that hold them, imported on first use (a command imports only its own
#: step's code: ``rectify warp`` does not load the matcher, the orthophoto or the mosaic code)
_LAZY = {"DETECTORS": ("features", "DETECTORS"), "VERIFY_METHODS": ("features", "VERIFY_METHODS"),
         "ortho": ("ortho", "ortho_from_files"), "OrthoOptions": ("ortho", "OrthoOptions"),
         "mosaic": ("mosaic", "mosaic"), "MosaicOptions": ("mosaic", "MosaicOptions"),
         "MosaicResult": ("mosaic", "MosaicResult")}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(f"{__package__}.{module}"), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "ortho", "OrthoOptions", "mosaic", "MosaicOptions", "MosaicResult",
    "DETECTORS", "VERIFY_METHODS", "METHOD_NAMES", "RESAMPLING_NAMES",
    "MatchOptions", "MatchRun", "match",
    "FitOptions", "FitRun", "fit",
    "WarpRunOptions", "WarpRun", "warp",
    "CompareOptions", "CompareRun", "compare",
    "DemoOptions", "demo",
]

#: The transform methods, in the order the commands list them.
METHOD_NAMES: tuple[str, ...] = tuple(METHODS)

Progress = Callable[[int, int], None] | None


# --------------------------------------------------------------------------- match
@dataclass(frozen=True)
class MatchOptions:
    """Options of :func:`match`: detector, verification model, refinement, cap and USAC threshold (px).

    ``max_matches`` and ``threshold_px`` left at ``None`` take :class:`~rectify.features.MatcherConfig`'s
    defaults (20000 matches, 1.5 px). ``scheduler`` says where the tiles of a large pair are searched
    (``threads``, ``processes[:N]``, ``tcp://HOST:PORT``; ``None``: ``$RECTIFY_SCHEDULER``, else threads).
    """

    detector: str = "sift"
    verify: str = "homography"
    refine: bool = True
    max_matches: int | None = None
    threshold_px: float | None = None
    scheduler: str | None = None

    def config(self) -> MatcherConfig:
        """The matcher configuration."""
        from .features import MatcherConfig

        kw: dict[str, Any] = {"detector": self.detector, "verify": self.verify, "refine": self.refine}
        if self.max_matches is not None:
            kw["max_matches"] = self.max_matches
        if self.threshold_px is not None:
            kw["threshold_px"] = self.threshold_px
        return MatcherConfig(**kw)


@dataclass(frozen=True, eq=False)
class MatchRun:
    """Result of :func:`match`: the matcher's result, the file written and the report."""

    result: MatchResult
    options: MatchOptions
    config: MatcherConfig
    output: Path
    report: Path | None = None

    def summary_lines(self) -> list[str]:
        """Counts (detected, matched, refined, verified, kept), verification RMSE (px), files."""
        res, o = self.result, self.options
        s = res.summary()
        lines = [f"detected: {s['n_detected_left']} left, {s['n_detected_right']} right keypoints "
                 f"({o.detector}{', tiled' if res.tiled else ''})",
                 f"matched: {s['n_matched']} (ratio test + mutual check)"]
        keep = self.config.keep_unrefined and not res.tiled
        refined = (f"refined: {s['n_refined']} converged, {s['n_refine_failed']} "
                   f"{'kept unrefined (empty score)' if keep else 'dropped'} (least-squares matching"
                   f"{', per tile, before verification' if res.tiled else ''})")
        if o.refine and res.tiled:  # tiled path: candidates are refined in their tile, then verified together
            lines.append(refined)
        lines.append(f"verified: {s['n_verified']} ({o.verify})")
        if o.refine and not res.tiled:
            lines.append(refined)
        expected = s["n_verified"] - (s["n_refine_failed"] if o.refine and not res.tiled and not keep else 0)
        if res.n_duplicates:
            lines.append(f"duplicates: {res.n_duplicates} removed (a left or right position used twice; "
                         "the output is one-to-one, best score kept)")
            expected -= res.n_duplicates
        if len(res.matches) != expected:
            lines.append(f"kept: {len(res.matches)} of the verified matches (evenly spread, --max-matches "
                         f"{self.config.max_matches}, re-verified)")
        if o.verify != "none":
            metric = "transfer error" if o.verify == "homography" else "Sampson distance"
            line = f"verification RMSE: {res.rmse_px:.3f} px ({metric}, n={len(res.matches)})"
            if o.refine:
                line += f"; raw positions {res.rmse_raw_px:.3f} px"
            lines.append(line)
            if res.verification.table is not None:
                lines.append(res.verification.table.summary_line())
        lines.append(f"wrote {len(res.matches)} matches to {self.output}")
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return lines


def match(ws: Workspace, left: str | Path, right: str | Path, output: str | Path,
          options: MatchOptions = MatchOptions(), *, progress: Progress = None) -> MatchRun:
    """Match ``left`` against ``right`` and write the verified tie points to the matches CSV ``output``.

    Returns
    -------
    MatchRun
        With the report path when the workspace has a report folder.
    """
    ws.add_inputs(left, right)
    ws.plan(output)
    ws.check_report_dir()
    from .features import match_images

    cfg = options.config()
    # the Dask tasks' block files go beside the output (on a cluster, a folder the workers share)
    res = match_images(left, right, config=cfg, progress=progress, scheduler=options.scheduler,
                       workdir=Path(output).resolve().parent)
    report = None
    with ws.transaction():  # the matches and the report, all or none
        out = ws.save_matches(output, res.matches)
        if ws.report_dir is not None:
            from .report import write_match_report

            report = write_match_report(ws.report_dir, res, left, right, overwrite=ws.overwrite)
    return MatchRun(res, options, cfg, out, report)


# --------------------------------------------------------------------------- fit
@dataclass(frozen=True)
class FitOptions:
    """Options of :func:`fit`: the model (a key of ``rectify.transforms.METHODS``) and the residual rows printed."""

    method: str = "homography"
    max_rows: int = 50
    image: str | Path | None = None


@dataclass(frozen=True, eq=False)
class FitRun:
    """Result of :func:`fit`: the fitted model with its residual table (target units), files written."""

    fit: FitResult
    gcps: GcpTable
    options: FitOptions
    output: Path
    report: Path | None = None
    geometry: GcpGeometry | None = None

    def summary_lines(self) -> list[str]:
        """The residual table (degrees and metres in a geographic CRS), the cotangent control points, RMSE
        (fit and check), the GCP geometry (with the image size) and the files."""
        table = self.fit.table
        if table.units.startswith("degree"):
            lines = geographic_lines(table, max_rows=self.options.max_rows)
        else:
            lines = [table.format_text(max_rows=self.options.max_rows)]
        if "control_ids" in table.extra:
            lines.append(f"cotangent method: control points {', '.join(table.extra['control_ids'])} "
                         "(best-conditioned quadrilateral); the other fit rows are reported as check points")
        s = table.summary()
        n_params = METHODS[self.options.method].n_params
        lines.append(f"RMSE {s['rmse']:.4g} {table.units} (fit, n={s['n_fit']}, {n_params} parameters)"
                     + (f"; check RMSE {s['rmse_check']:.4g} {table.units} (n={s['n_check']})"
                        if s["n_check"] else ""))
        if self.geometry is not None:
            lines += self.geometry.summary_lines()
        elif 2 * s["n_fit"] <= n_params:
            lines.append(f"no redundancy: {s['n_fit']} GCPs determine the {n_params} {self.options.method} "
                         "parameters exactly; the residuals are zero by construction and no error can be estimated")
        lines.append(f"wrote {self.output}")
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return lines


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise InvalidInputError(f"unknown method {method!r}; expected one of {sorted(METHODS)}")


def fit(ws: Workspace, gcps_path: str | Path, output: str | Path, options: FitOptions = FitOptions()) -> FitRun:
    """Fit a transform (source pixels -> target) to the GCP file ``gcps_path``; write the transform JSON.

    Check points (``check = 1``) are withheld from the fit and reported separately. With the source image
    (``options.image``, or the GCP file itself when it is a GeoTIFF with embedded GCPs) the GCP geometry
    is judged over the image (:func:`rectify.transforms.quality.judge_gcp_geometry`).
    """
    _check_method(options.method)
    image = options.image
    if image is None and Path(gcps_path).suffix.lower() in TIFF_SUFFIXES:
        image = gcps_path
    ws.add_inputs(gcps_path, image)
    size = None
    if image is not None:
        info = raster_info(image)
        size = (info.width, info.height)
    ws.plan(output)
    ws.check_report_dir()
    gcps = ws.load_gcps(gcps_path)
    result = fit_gcps(gcps, options.method)
    geometry = None
    if size is not None:
        geometry = judge_gcp_geometry(gcps, options.method, *size, units=result.table.units)
    report = None
    with ws.transaction():  # the transform and the report, all or none
        out = ws.save_transform(output, result.model, table=result.table, crs=gcps.crs)
        if ws.report_dir is not None:
            from .report import write_fit_report

            report = write_fit_report(ws.report_dir, result, gcps, gcps_path=gcps_path, transform_path=out,
                                      overwrite=ws.overwrite)
    return FitRun(result, gcps, options, out, report, geometry)


# --------------------------------------------------------------------------- warp
@dataclass(frozen=True)
class WarpRunOptions:
    """Options of :func:`warp`.

    Attributes
    ----------
    method : str
        Model fitted to GCPs (a key of ``rectify.transforms.METHODS``).
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
        Refuse an output grid with more pixels (default :data:`rectify.warp.DEFAULT_MAX_PIXELS`, 2e9).
    scheduler : str, optional
        Where the tiles run: ``threads``, ``processes[:N]`` or ``tcp://HOST:PORT`` (default:
        ``$RECTIFY_SCHEDULER``, else ``threads``; :mod:`rectify.distributed`).
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


@dataclass(frozen=True, eq=False)
class WarpRun:
    """Result of :func:`warp`: the georectification, the output and the report."""

    result: GeoRectification
    options: WarpRunOptions
    output: Path
    report: Path | None = None
    geometry: GcpGeometry | None = None

    def summary_lines(self) -> list[str]:
        """GCP fit summary (when fitted), output grid, CRS, resampling, format and time, report."""
        r, o = self.result, self.options
        g = r.warp.grid
        lines = [r.fit.table.summary_line()] if r.fit is not None else []
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
        return lines


def warp(ws: Workspace, src: str | Path, dst: str | Path, *, gcps_path: str | Path | None = None,
         transform_path: str | Path | None = None, options: WarpRunOptions = WarpRunOptions(),
         progress: Progress = None) -> WarpRun:
    """Rectify ``src`` into the GeoTIFF ``dst`` with GCPs (fitted with ``options.method``) or a saved transform.

    GCP files: CSV, QGIS ``.points``, matches CSV, GeoJSON, GeoPackage, or a GeoTIFF's embedded GCPs
    (:func:`rectify.formats.read_gcps`). With neither ``gcps_path`` nor ``transform_path``, the GCPs
    embedded in ``src`` are used when it carries some.

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
        _check_method(options.method)
    # GDAL reads GDAL_CACHEMAX once, at its first block access: bound it before any pixel IO
    os.environ.setdefault("GDAL_CACHEMAX", "64")
    ws.add_inputs(src, gcps_path, transform_path)
    ws.plan(dst)
    ws.check_report_dir()
    info = raster_info(src)
    wopts = WarpOptions(resampling=options.resampling, cog=options.cog, threads=options.threads,
                        max_pixels=options.max_pixels, scheduler=options.scheduler)
    if gcps_path is not None:
        gcps = ws.load_gcps(gcps_path)
        if options.gcp_crs:  # --gcp-crs overrides the file's CRS: the coordinates must fit it too
            check_table_crs(gcps_path, options.gcp_crs, gcps.target, gcps.ids)
        result = georectify(src, dst, gcps, method=options.method, gcp_crs=options.gcp_crs, dst_crs=options.dst_crs,
                            resolution=options.resolution, options=wopts, overwrite=ws.overwrite, progress=progress)
    else:
        assert transform_path is not None
        tf = ws.load_transform(transform_path)
        result = rectify_with_transform(src, dst, tf.model, model_crs=options.gcp_crs or tf.crs,
                                        dst_crs=options.dst_crs, resolution=options.resolution, options=wopts,
                                        overwrite=ws.overwrite, progress=progress)
    geometry = None
    if result.fit is not None:
        t = result.fit.table
        fitted = GcpTable(t.ids, t.position_px, t.observed, None, t.check, result.crs)
        geometry = judge_gcp_geometry(fitted, options.method, info.width, info.height, units=t.units)
    report = None
    if ws.report_dir is not None:
        try:
            from .report import write_warp_report

            report = write_warp_report(ws.report_dir, result, source_shape=(info.height, info.width),
                                       overwrite=ws.overwrite)
        except BaseException:  # all or none: the GeoTIFF this run wrote goes too
            with contextlib.suppress(OSError):
                Path(dst).unlink()
            raise
    return WarpRun(result, options, Path(dst), report, geometry)


# --------------------------------------------------------------------------- compare
@dataclass(frozen=True)
class CompareOptions:
    """Options of :func:`compare`: sizes and seed (``None`` = the preset's), and the preset.

    ``full`` uses the sizes of ``scripts/compare_cotangent_homography.py`` instead of the quick preset.
    """

    n_configs: int | None = None
    n_trials: int | None = None
    n_speed_points: int | None = None
    seed: int | None = None
    full: bool = False

    def config(self) -> StudyConfig:
        """The study configuration."""
        from .compare import StudyConfig

        over: dict[str, Any] = {"n_configs": self.n_configs, "n_trials": self.n_trials,
                                "n_speed_points": self.n_speed_points, "seed": self.seed}
        if self.full:
            return StudyConfig(**{k: v for k, v in over.items() if v is not None})
        return StudyConfig.quick(**over)


@dataclass(frozen=True, eq=False)
class CompareRun:
    """Result of :func:`compare`: the study results and ``study.md``."""

    results: StudyResults
    output: Path

    def summary_lines(self) -> list[str]:
        """Agreement, the 1 px noise rows (px) and the speed of both methods."""
        res = self.results
        a, s = res.agreement, res.speed
        lines = [f"agreement: {a['n_configs']} configurations, max |cotangent - homography| = "
                 f"{a['max_rel']:.2e} of the image size (eq. 2 as printed: median error "
                 f"{a['printed_median_rel']:.2f})"]
        shown = 1.0 if any(r["sigma_px"] == 1.0 for r in res.noise) else max(r["sigma_px"] for r in res.noise)
        for r in res.noise:
            if r["sigma_px"] == shown:
                lines.append(f"noise {r['sigma_px']:g} px, {r['camera']}: RMSE cotangent {r['rmse_cotangent']:.3f} px, "
                             f"homography(4) {r['rmse_homography4']:.3f} px, homography LSQ "
                             f"{r['rmse_homography_lsq']:.3f} px")
        lines.append(f"speed: homography {s['homography_pts_per_s']:,.0f} pts/s, cotangent "
                     f"{s['cotangent_pts_per_s']:,.0f} pts/s, ratio {s['ratio']:.2f}")
        lines.append(f"wrote {self.output}")
        return lines


def compare(ws: Workspace, out_dir: str | Path, options: CompareOptions = CompareOptions(), *,
            progress: Progress = None) -> CompareRun:
    """Run the cotangent/homography study and write ``study.md``, ``study.json`` and the plots into ``out_dir``."""
    cfg = options.config()
    md = Path(out_dir) / "study.md"
    if md.exists() and not ws.overwrite:
        raise InvalidInputError(f"{str(md)!r} exists; pass --overwrite to replace it")
    from .compare import run_study, write_study

    res = run_study(cfg, progress=progress)
    path = write_study(res, out_dir, overwrite=ws.overwrite)
    return CompareRun(res, path)


# --------------------------------------------------------------------------- demo
@dataclass(frozen=True)
class DemoOptions:
    """Options of :func:`demo`: simulated GCP picking error (px), its seed, and the short comparison."""

    pick_sigma_px: float = 0.15
    seed: int = 4
    with_compare: bool = True


def demo(ws: Workspace, options: DemoOptions = DemoOptions(), *, progress: Progress = None) -> DemoResult:
    """The embedded Landsat scene through a tilted frame and back into ``ws.root`` (see :mod:`rectify.demo`)."""
    if ws.root is None:
        raise InvalidInputError("the demo needs an output folder")
    from .demo import run_demo

    return run_demo(ws.root, overwrite=ws.overwrite, pick_sigma_px=options.pick_sigma_px, seed=options.seed,
                    with_compare=options.with_compare, progress=progress)
