"""Strips of a model block oriented by control with their polynomial deformation removed (seed 002, 3.1.1).

:func:`correct_strips` takes a block joined model by model (independent models, or partially
dependent ones, 3.2: :func:`stereo.block.independent.independent_models`), splits it into strips
(:func:`stereo.block.strip_polynomial.find_strips`) and, for every strip:

1. orients the strip's points and projection centres by a 7-parameter spatial similarity to the
   control points of the strip (eq. 3.3, at least two full points and a third height);
2. fits seed 002's polynomial correction (eqs. 3.8-3.15) to the control's remaining
   discrepancies and applies it to every point and projection centre of the strip; each image
   rotation is turned by the rotation part of the correction's derivative at its centre.

A point in several strips (the side overlap) gets the mean of its corrected positions; points and
images in no strip keep the block's single similarity to all control. Check points are compared
with their given coordinates before (similarity only) and after the correction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError, RectifyError
from rectify.geometry.residuals import rms
from stereo.block.independent import ModelBlock, to_ground
from stereo.block.model_adjust import check_model_datum
from stereo.block.models import _orthonormal
from stereo.block.strip_polynomial import Strip, StripPolynomial, check_strip_control, find_strips
from stereo.block.types import BlockControl, Pose
from stereo.pair.absolute import AbsoluteOrientation

__all__ = ["StripsCorrected", "correct_strips"]

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class StripsCorrected:
    """A model block corrected strip by strip (seed 002, 3.1.1).

    Attributes
    ----------
    poses : tuple of Pose
        Ground frame, one per image of the block.
    point_ids : tuple of str
    points : (P, 3) float64
        Corrected ground coordinates (NaN where the block has none).
    point_std : (P, 3) float64
        Standard error of each point: the fit's sigma0 combined with the variance of its strip's
        correction (an estimate that ignores the model noise between control points).
    strips : tuple of Strip
    polynomials : tuple of StripPolynomial
        One per strip.
    similarities : tuple of AbsoluteOrientation
        Block frame -> ground of each strip (before its polynomial).
    degree : int
    control_ids : tuple of str
    control_residuals : (c, 3) float64
        Given minus corrected (NaN for components not given); of the first strip holding the point.
    check_ids : tuple of str
    check_before, check_errors, check_std : (k, 3) float64
        Adjusted minus given after the similarity only and after the polynomial, and the standard error.
    """

    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: F64
    point_std: F64
    strips: tuple[Strip, ...]
    polynomials: tuple[StripPolynomial, ...]
    similarities: tuple[AbsoluteOrientation, ...]
    degree: int
    control_ids: tuple[str, ...]
    control_residuals: F64
    check_ids: tuple[str, ...]
    check_before: F64
    check_errors: F64
    check_std: F64

    def __post_init__(self) -> None:
        for name in ("points", "point_std", "control_residuals", "check_before", "check_errors", "check_std"):
            a = np.array(getattr(self, name), dtype=np.float64, copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    def summary_lines(self) -> list[str]:
        """One line for the method, one per strip, the check points before and after."""
        lines = [f"strip polynomial (seed 002, 3.1.1, eqs. 3.8-3.15): degree {self.degree}, {len(self.strips)} "
                 f"strip(s), {len(self.control_ids)} control points"]
        for k, (st, pol) in enumerate(zip(self.strips, self.polynomials, strict=True)):
            r = pol.residuals[np.isfinite(pol.residuals)]
            lines.append(f"  strip {k + 1}: {len(st.images)} images, {len(st.models)} models, control "
                         f"{int(pol.n_control.max())} points, RMS control residual {rms(r):.4g}, sigma0 "
                         f"{pol.sigma0:.4g}")
        if len(self.check_ids):
            b, e = self.check_before, self.check_errors
            lines.append(f"check: {len(self.check_ids)} points, RMS error x {rms(e[:, 0]):.3f} y {rms(e[:, 1]):.3f} "
                         f"z {rms(e[:, 2]):.3f} (similarity only: x {rms(b[:, 0]):.3f} y {rms(b[:, 1]):.3f} "
                         f"z {rms(b[:, 2]):.3f})")
        return lines


def _given(control: BlockControl) -> F64:
    """(K, 3) given coordinates with NaN for the components a kind does not give."""
    mask = np.array([{"full": (1, 1, 1), "height": (0, 0, 1), "plan": (1, 1, 0)}[k] for k in control.kind],
                    dtype=bool).reshape(-1, 3)
    return np.where(mask, control.xyz, np.nan)


def correct_strips(block: ModelBlock, control: BlockControl, *, degree: int = 2, robust: bool = False
                   ) -> StripsCorrected:
    """Orient each strip of ``block`` by its control and remove its polynomial deformation.

    Parameters
    ----------
    block : ModelBlock
        A block joined model by model (its model frame).
    control : BlockControl
        Control and check points (``check``), ground frame.
    degree : int
        Of the polynomial (:data:`stereo.block.strip_polynomial.STRIP_DEGREES`).
    robust : bool
        Refit the polynomials with Huber weights.

    Raises
    ------
    EstimationError
        Too little control in a strip (the strip, the count and the named minimum), control that
        does not determine the polynomial.
    InvalidInputError
        Control ids that are not tracks of the block, an unknown degree.
    """
    check_strip_control(np.full(3, 1 << 30), degree, "")  # the degree, before any work
    index = {p: k for k, p in enumerate(block.point_ids)}
    unknown = [i for i in control.ids if i not in index]
    if unknown:
        raise InvalidInputError(f"control point(s) {unknown[:5]} are not tracks of the block")
    rows = np.array([index[i] for i in control.ids], dtype=np.int64)
    given = _given(control)
    use = ~np.asarray(control.check, dtype=bool) & np.isfinite(block.points[rows]).all(axis=1)
    chk = np.asarray(control.check, dtype=bool) & np.isfinite(block.points[rows]).all(axis=1)
    # the block's single similarity: the strips' directions and everything outside the strips
    fh = use & np.isfinite(given[:, 2])
    xyz0 = given[fh].copy()
    xyz0[~np.isfinite(xyz0[:, :2]).all(axis=1), :2] = np.nan
    n_plan, n_height = int((use & np.isfinite(given[:, 0])).sum()), int(fh.sum())
    check_model_datum(n_plan, n_height, block.points[rows[fh], :2] if n_height else np.zeros((0, 2)),
                      f"{int(use.sum())} control points")
    gb = to_ground(block, control=([control.ids[k] for k in np.flatnonzero(fh)], xyz0), robust="none")
    pos_g = np.array([p.position for p in gb.poses]).reshape(-1, 3)
    strips = find_strips(block.tree, pos_g)
    P, n = len(block.point_ids), len(block.poses)
    acc = np.zeros((P, 3))
    var = np.zeros((P, 3))
    cnt = np.zeros(P)
    before = np.full((P, 3), np.nan)
    poses = list(gb.poses)
    pols, sims = [], []
    names = [p.image for p in block.poses]
    for k, st in enumerate(strips):
        label = f"strip {k + 1} ({names[st.images[0]]} .. {names[st.images[-1]]})"
        tr = np.unique(np.concatenate([block.models[j].tracks for j in st.models]))
        in_strip = np.zeros(P, bool)
        in_strip[tr] = True
        cs = use & in_strip[rows]
        c_fh = cs & np.isfinite(given[:, 2])
        c_plan = cs & np.isfinite(given[:, 0])
        check_strip_control(np.isfinite(given[cs]).sum(axis=0), degree, label)
        check_model_datum(int(c_plan.sum()), int(c_fh.sum()), block.points[rows[c_fh], :2],
                          f"{label}: {int(cs.sum())} control points")
        g_sim = given[c_fh].copy()
        g_sim[~np.isfinite(g_sim[:, :2]).all(axis=1), :2] = np.nan
        try:
            sim = AbsoluteOrientation.from_points(block.points[rows[c_fh]], g_sim, robust="none")
        except RectifyError as err:
            raise EstimationError(f"the similarity of {label} to its control failed: {err}") from err
        s, R, T = sim.scale, sim.rotation, sim.translation
        pts = s * block.points[tr] @ R.T + T
        cen = np.array([s * R @ block.poses[i].position + T for i in st.images])
        ax = np.linalg.svd(cen[:, :2] - cen[:, :2].mean(axis=0))[2][0] if len(cen) > 1 else np.array([1.0, 0.0])
        origin = cen[:, :2].mean(axis=0)
        half = float(max(np.abs((np.vstack([pts[:, :2], cen[:, :2]]) - origin) @ ax).max(), 1e-9))
        deformed = s * block.points[rows[cs]] @ R.T + T
        pol = StripPolynomial.from_points(deformed, given[cs], degree=degree, origin=origin, axis=ax,
                                          half_length=half, robust=robust, label=label)
        corr = pol.correct(pts)
        acc[tr] += corr
        s0 = pol.sigma0 if math.isfinite(pol.sigma0) else 0.0
        var[tr] += pol.variance(pts) + s0 ** 2
        cnt[tr] += 1
        before[tr] = np.where(np.isfinite(before[tr]), before[tr], pts)
        J = pol.jacobian(cen)
        ccen = pol.correct(cen)
        for q, i in enumerate(st.images):
            p = block.poses[i]
            poses[i] = Pose(p.image, p.camera, ccen[q], _orthonormal(J[q]) @ _orthonormal(R @ p.rotation))
        pols.append(pol)
        sims.append(sim)
    out = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], np.asarray(gb.points))
    std = np.where(cnt[:, None] > 0, np.sqrt(var / np.maximum(cnt, 1)[:, None] ** 2), np.nan)
    before = np.where(np.isfinite(before), before, np.asarray(gb.points))
    c_ids = tuple(control.ids[k] for k in np.flatnonzero(use))
    k_idx = np.flatnonzero(chk)
    return StripsCorrected(
        poses=tuple(poses[:n]), point_ids=block.point_ids, points=out, point_std=std, strips=tuple(strips),
        polynomials=tuple(pols), similarities=tuple(sims), degree=degree, control_ids=c_ids,
        control_residuals=(given[use] - out[rows[use]]).reshape(-1, 3),
        check_ids=tuple(control.ids[k] for k in k_idx),
        check_before=(before[rows[k_idx]] - control.xyz[k_idx]).reshape(-1, 3),
        check_errors=(out[rows[k_idx]] - control.xyz[k_idx]).reshape(-1, 3),
        check_std=std[rows[k_idx]].reshape(-1, 3))
