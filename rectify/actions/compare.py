"""``rectify compare``: the cotangent vs homography study, written as ``study.md``, ``study.json`` and plots."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.atomic import atomic_output, atomic_write_text
from rectify.errors import InvalidInputError
from rectify.geometry.transforms.study import StudyConfig, StudyResults, run_study
from rectify.report.figures import study_figures


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

    res = run_study(cfg, progress=progress)
    path = write_study(res, out_dir, overwrite=ws.overwrite)
    return CompareRun(res, path)


def write_study(results: StudyResults, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``study.md``, ``study.json`` and ``fig_<part>.png`` into ``out_dir``; return the .md path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md = results.to_markdown()
    figs = study_figures(results)
    names = [f"fig_{k}.png" for k in figs]
    md += "\n## Figures\n\n" + "\n".join(f"![{n}]({n})" for n in names) + "\n"
    for name, fig in figs.items():
        with atomic_output(out / f"fig_{name}.png", overwrite=overwrite) as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    atomic_write_text(out / "study.json", json.dumps(results.to_dict(), indent=2) + "\n", overwrite=overwrite)
    return atomic_write_text(out / "study.md", md, overwrite=overwrite)
