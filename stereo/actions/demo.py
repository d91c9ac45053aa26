"""``stereo demo``: the rendered synthetic pair through the whole chain, compared with the truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rectify.geometry.residuals import rms
from rectify.report.builder import json_safe
from stereo.actions.common import PathArg, Progress
from stereo.actions.run import RunResult, run
from stereo.actions.scene import make_scene, write_scene_inputs
from stereo.actions.workspace import PairWorkspace
from stereo.pair.model import ModelOptions


@dataclass(frozen=True, eq=False)
class DemoResult:
    """Result of :func:`demo`: the run and the comparison with the synthetic truth."""

    run: RunResult
    truth: dict[str, Any] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        t, m = self.truth, self.run.model
        x, y, z = t["check_rmse_xyz_m"]
        return self.run.summary_lines() + [
            "accuracy against the truth:",
            f"  {t['n_check']} check points: RMSE X {x:.3f} m, Y {y:.3f} m, Z {z:.3f} m; RMS of error / "
            f"predicted std {t['check_normalised_rms']:.3f} (target 0.67-1.5); per axis "
            + ", ".join(f"{v:.2f}" for v in t["check_normalised_rms_xyz"]),
            f"  control/check image noise: simulated {t['pixel_noise_px']:.3f} px, estimated "
            f"{m.summary.get('control_sigma_px', float('nan')):.3f} px",
            f"  all {t['n_points']} points vs DEM height: RMSE {t['dem_rmse_m']:.3f} m "
            f"({t['dem_rmse_m'] / t['ground_pixel_m']:.2f} ground pixels of {t['ground_pixel_m']:.2f} m)",
            f"report: {self.run.out_dir / 'report' / 'report.html'}",
        ]


def demo(out_dir: PathArg, *, seed: int = 0, size_px: int = 480, overwrite: bool = False,
         pixel_noise_px: float = 0.2, progress: Progress | None = None) -> DemoResult:
    """``stereo demo``: synthetic pair (:mod:`stereo.actions.scene`) -> :func:`run` -> accuracy against the truth.

    Writes the inputs into ``out_dir/input``, the run layout into ``out_dir`` and the comparison
    with the truth (check point RMSE per axis, RMS of normalised check errors, RMSE of all points'
    heights against the DEM) into ``out_dir/truth_comparison.json``.
    """
    out = Path(out_dir)
    PairWorkspace.for_run(out, overwrite=overwrite).plan_run()  # fail before rendering
    scene = make_scene(seed, size_px=size_px)
    inp = write_scene_inputs(scene, out / "input", seed=seed, pixel_noise_px=pixel_noise_px, overwrite=overwrite,
                             progress=progress)
    control = PairWorkspace().load_control(inp["control"])
    ground_px = scene.cell_m
    r = run(inp["left"], inp["right"], camera=scene.camera, out_dir=out, control=control, overwrite=overwrite,
            # robust="none": the demo's control is clean and its figures are the README's
            options=ModelOptions(check_ids=inp["check_ids"], robust="none"),
            title="stereo demo: synthetic pair with known truth",
            extra_summary={"scene_seed": seed, "ground_pixel_m": ground_px}, progress=progress)
    m = r.model
    assert m.ground is not None
    chk = m.is_check
    truth = np.array([inp["truth"][i] for i, c in zip(m.ids, chk, strict=True) if c])
    e = m.ground[chk] - truth
    dz = m.ground[:, 2] - scene.height(m.ground[:, :2])
    ok = np.isfinite(dz)
    nrm = e / m.ground_std[chk] if m.ground_std is not None else np.full_like(e, np.nan)
    res = {"n_check": int(chk.sum()), "check_rmse_xyz_m": [rms(e[:, k]) for k in range(3)],
           "check_normalised_rms": rms(nrm), "check_normalised_rms_xyz": [rms(nrm[:, k]) for k in range(3)],
           "pixel_noise_px": pixel_noise_px,
           "dem_rmse_m": rms(dz[ok]), "n_points": int(ok.sum()), "ground_pixel_m": ground_px}
    PairWorkspace(overwrite=overwrite).write_json(out / "truth_comparison.json", json_safe(res))
    return DemoResult(r, res)
