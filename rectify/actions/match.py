"""``rectify match``: tie points between two images, written as a matches CSV (and a report)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.features import DETECTORS, VERIFY_METHODS, MatcherConfig, MatchResult, match_images
from rectify.raster.distributed import check_scheduler

#: the command's choices (the lists live in :mod:`rectify.features`)
__all__ = ["DETECTORS", "VERIFY_METHODS", "MatchOptions", "MatchRun", "match"]


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
            n_fig = len(res.matches) - res.n_unrefined
            line = f"verification RMSE: {res.rmse_px:.3f} px ({metric}, n={n_fig}"
            line += " refined)" if o.refine else ")"
            if o.refine:
                line += f"; raw positions {res.rmse_raw_px:.3f} px"
            lines.append(line)
            if res.n_unrefined:
                unref = (f"{res.rmse_unrefined_px:.3f} px" if res.rmse_unrefined_px == res.rmse_unrefined_px
                         else "n/a")
                lines.append(f"unrefined: {res.n_unrefined} matches kept at their detector positions, RMSE {unref} "
                             "(not in the figure above; written with an empty score)")
            if res.n_screened:
                lines.append(f"screened: {res.n_screened} refined matches whose residual exceeded their precision "
                             "(kept at their raw positions or dropped)")
            if res.n_turns:
                lines.append(f"right image matched turned back by {res.n_turns * 90} deg")
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
    # the scheduler (or $RECTIFY_SCHEDULER) is checked before any work, even when a small pair will not tile
    sched = check_scheduler(options.scheduler)

    cfg = options.config()
    # the Dask tasks' block files go beside the output (on a cluster, a folder the workers share)
    res = match_images(left, right, config=cfg, progress=progress, scheduler=sched,
                       workdir=Path(output).resolve().parent)
    report = None
    with ws.transaction():  # the matches and the report, all or none
        out = ws.save_matches(output, res.matches)
        if ws.report_dir is not None:
            # local: the report (matplotlib, 0.24 s) loads only when --report asks for it
            from rectify.report.builder import write_match_report

            report = write_match_report(ws.report_dir, res, left, right, overwrite=ws.overwrite)
    return MatchRun(res, options, cfg, out, report)
