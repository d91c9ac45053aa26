"""``stereo orient --system projective`` without a camera: the fundamental matrix of a pair (seed 003,
3.2.2) and its canonical projective cameras, written as a projective pair JSON
(:mod:`stereo.formats.projective`). With a camera, ``--system projective`` runs through
:mod:`stereo.actions.orient` like the other systems.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rectify.errors import InvalidInputError
from rectify.features import MatcherConfig
from stereo.actions.common import PathArg, given, pair_tie_points
from stereo.actions.workspace import PairWorkspace
from stereo.formats.projective import dump_projective_pair, projective_pair_dict
from stereo.pair.projective import FundamentalFit, cameras_from_fundamental, fundamental_from_points

__all__ = ["ProjectiveOrientResult", "orient_projective"]


@dataclass(frozen=True, eq=False)
class ProjectiveOrientResult:
    """Result of :func:`orient_projective`."""

    F: np.ndarray
    fit: FundamentalFit
    n_points: int
    output: Path
    n_matched: int | None = None
    match_rmse_px: float | None = None

    def summary_lines(self) -> list[str]:
        f = self.fit
        out = []
        if self.n_matched is not None:
            out.append(f"matched {self.n_matched} tie points (verification RMSE {self.match_rmse_px:.3g} px)")
        out.append(f"relative orientation (projective: fundamental matrix), {int(f.inliers.sum())} of "
                   f"{self.n_points} points used, {f.iterations} iterations (Sampson refinement)")
        s0 = "n/a" if f.sigma0_px is None else f"{f.sigma0_px:.3f} px"
        out.append(f"Sampson residual: RMSE {f.rms_px:.3f} px; sigma0 {s0} (redundancy {f.redundancy}); "
                   f"condition number {f.condition:.3g}")
        out.append("no camera: projective model only - no metric elements (rotations, base, focal length); "
                   "orient it to control with `stereo model --transform projective`")
        out.append(f"wrote {self.output}")
        return out


def orient_projective(*, output: PathArg, system: str = "projective", matches: PathArg | None = None,
                      images: tuple[PathArg, PathArg] | None = None, matches_out: PathArg | None = None,
                      report_dir: PathArg | None = None, overwrite: bool = False,
                      matcher: MatcherConfig | None = None) -> ProjectiveOrientResult:
    """The fundamental matrix of a pair from a matches CSV or from matching two images; no camera.

    Raises
    ------
    InvalidInputError
        A system other than ``projective`` (they need a camera), ``report_dir`` (the report shows metric
        figures), neither or both of ``matches`` and ``images``, outputs that exist.
    EstimationError
        Fewer than 8 tie points, a degenerate configuration (one plane, no base).
    """
    if system != "projective":
        raise InvalidInputError(f"system {system!r} needs a camera (--camera); only --system projective works "
                                "without one (fundamental matrix, projective model)")
    if report_dir is not None:
        raise InvalidInputError("--report needs a camera; without one there are no metric figures to report")
    if (matches is None) == (images is None):
        raise InvalidInputError("give either a matches CSV or the two images LEFT RIGHT")
    ws = PairWorkspace(overwrite=overwrite, inputs=given(matches, *(images or ())))
    ws.plan(output, matches_out)
    m, n_matched, rmse = pair_tie_points(images, matches, ws.load_matches, matcher)
    F, fit = fundamental_from_points(m.left, m.right)
    doc = projective_pair_dict(F, fit, cameras_from_fundamental(F), m.ids)
    with ws.transaction():
        if matches_out is not None:
            ws.save_matches(matches_out, m)
        with ws.output(output) as tmp:
            dump_projective_pair(tmp, doc)
    return ProjectiveOrientResult(F, fit, len(m), Path(output), n_matched, rmse)
