"""Datum analysis of a bundle adjustment: which observations fix the datum, and how weak it is.

The statement is built from numbers computed at the solution: the predicted height standard
deviations of the tie points against those at the control points, and the smallest eigenvalue
of the Jacobi-scaled reduced camera system with its eigenvector classified against the seven
similarity motions of the block (shift x/y/z, rotation about x/y/z, scale).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from stereo.block.bundle.model import rotation_axes
from stereo.block.bundle.solve import Normal, Problem, State
from stereo.block.types import BlockControl

__all__ = ["datum_analysis", "similarity_generators"]

#: largest reduced system whose eigenvalues are computed for the datum statement
EIGEN_LIMIT = 2000
MOTIONS = ("shift x", "shift y", "shift z", "rotation about x", "rotation about y", "rotation about z", "scale")


def similarity_generators(prob: Problem, st: State) -> NDArray[np.float64]:
    """(7, n_c) camera-side changes of an infinitesimal shift, rotation and scale of the block."""
    n = prob.n_images
    c0 = st.centres.mean(axis=0)
    dC = st.centres - c0
    axes = rotation_axes(st.angles)
    out = np.zeros((7, prob.n_c))
    for k in range(3):
        g = np.zeros((n, 6))
        g[:, 3 + k] = 1.0
        out[k, : 6 * n] = g.ravel()
        u = np.zeros(3)
        u[k] = 1.0
        g = np.zeros((n, 6))
        g[:, 3:] = np.cross(u, dC)
        g[:, :3] = np.linalg.solve(np.transpose(axes, (0, 2, 1)), np.broadcast_to(u, (n, 3))[..., None])[..., 0]
        out[3 + k, : 6 * n] = g.ravel()
    g = np.zeros((n, 6))
    g[:, 3:] = dC
    out[6, : 6 * n] = g.ravel()
    return out


def datum_analysis(prob: Problem, st: State, free: bool, Qcc: NDArray | None, ne: Normal | None,
                   point_std: NDArray[np.float64], s0v: float, control: BlockControl | None,
                   control_rows: NDArray[np.int64], n_gnss: int, *, control_ok: NDArray[np.bool_] | None = None,
                   determined: NDArray[np.bool_] | None = None
                   ) -> tuple[list[str], list[str], float, list[str]]:
    """Datum lines, the groups that define the datum, the condition number and warning lines.

    ``control_ok`` (k,) marks the control points counted (not rejected); ``determined`` (P,) the points
    whose precision is stated (the points written: at least two rays not flagged). Default: all.
    """
    lines: list[str] = []
    warns: list[str] = []
    groups: list[str] = []
    ok_c = np.ones(len(prob.c_pt), bool) if control_ok is None else np.asarray(control_ok, dtype=bool)
    c_pt = prob.c_pt[ok_c]
    used = np.isfinite(prob.c_sigma)[ok_c] if len(prob.c_pt) else np.zeros((0, 3), bool)
    n_full = int(np.sum(used.all(axis=1)))
    n_h = int(np.sum(used[:, 2] & ~used[:, 0]))
    n_p = int(np.sum(used[:, 0] & ~used[:, 2]))
    k = len(c_pt)
    has_ctrl = k > 0
    has_gnss = n_gnss > 0
    if has_ctrl:
        groups.append("control")
    if has_gnss:
        groups.append("gnss")
    if len(prob.i_img):
        groups.append("ins")
    ctrl_txt = f"control at {k} points ({n_full} full, {n_h} height, {n_p} plan)"
    if free:
        groups.append("free network")
        lines.append("datum: free network (no control, no GNSS): shift, rotation and scale are set by seven "
                     "minimum constraints (the first image's pose and the distance to the second image, from the "
                     "initial values); coordinates are in that model frame, not in the ground frame")
    elif has_gnss and not has_ctrl:
        lines.append(f"datum: GNSS positions of {n_gnss} images, no control")
        lines.append("GNSS and no control: the datum rests on GNSS alone; a GNSS bias would shift the whole "
                     "block undetected")
    elif has_ctrl and not has_gnss:
        lines.append(f"datum: no GNSS, {ctrl_txt}")
    else:
        lines.append(f"datum: GNSS positions of {n_gnss} images and {ctrl_txt}; the control checks the GNSS "
                     "datum for a bias")
    if not free and k < len(prob.c_pt) and n_gnss < 3 and (n_full + n_p < 2 or n_full + n_h < 3):
        warns.append(f"after the rejected control points, {n_full + n_p} plan and {n_full + n_h} height control "
                     "points are left, too few to fix the datum (>= 2 plan, >= 3 height): the block rests on the "
                     "initial values and the weak rays of the rejected points")
    # heights in the interior vs at the control points, over the points that are written
    det = np.ones(len(st.points), bool) if determined is None else np.asarray(determined, dtype=bool)
    if has_ctrl and not free:
        xy = st.points[det, :2] if det.any() else st.points[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        cxy = st.points[c_pt, :2]
        inner = np.all(np.abs(cxy - mid) < 0.5 * half, axis=1)
        where = "control only at the block edge" if not inner.any() else "control in the block interior too"
        sz = point_std[:, 2]
        if np.isfinite(sz[det]).all():
            hmask = used[:, 2]
            sz_ctrl = float(np.median(sz[c_pt[hmask]])) if hmask.any() else float("nan")
            others = np.setdiff1d(np.flatnonzero(det), c_pt)
            # the 95th percentile, not the maximum: a stray two-ray point far outside the block would
            # otherwise speak for the whole block
            q95 = float(np.percentile(sz[others], 95)) if len(others) else float("nan")
            j = int(others[np.argmin(np.abs(sz[others] - q95))]) if len(others) else 0
            med = float(np.median(sz[others])) if len(others) else float("nan")
            d = float(np.min(np.linalg.norm(cxy - st.points[j, :2], axis=1))) if len(cxy) else float("nan")
            tail = ("heights in the block interior rest on the tie-point geometry; " if not has_gnss else
                    "heights between the control points rest on the tie-point geometry and GNSS; ")
            lines.append(f"{where}: {tail}predicted height std of the {len(others)} tie points written: median "
                         f"{med:.3f} m, 95th percentile {q95:.3f} m ({d:.0f} m from the nearest control point); "
                         f"{sz_ctrl:.3f} m at the control points")
        else:
            lines.append(f"{where}: point precision not computed (covariance='full' gives predicted height std)")
    # conditioning and the weakest motion
    cond = float("nan")
    if Qcc is not None and ne is not None and prob.n_c <= EIGEN_LIMIT:
        S = ne.S.toarray() if hasattr(ne.S, "toarray") else np.asarray(ne.S)
        sd = np.sqrt(np.diag(S))
        Ss = S / np.outer(sd, sd)
        ev, vec = np.linalg.eigh(Ss)
        cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
        gen = similarity_generators(prob, st) * sd[None, :]
        v0 = vec[:, 0]
        cos = np.abs(gen @ v0) / np.maximum(np.linalg.norm(gen, axis=1), 1e-300)
        best = int(np.argmax(cos))
        kind = f"mostly {MOTIONS[best]} of the block (|cos| {cos[best]:.2f})" if cos[best] > 0.5 else \
            f"a deformation of the block (largest similarity share: {MOTIONS[best]}, |cos| {cos[best]:.2f})"
        lines.append(f"reduced camera system: condition number {cond:.3g}; weakest direction: {kind}")
        if not free and cond > 1e12:
            warns.append(f"ill-conditioned reduced camera system (condition number {cond:.3g}): {kind} is "
                         "barely determined; add control or GNSS")
    elif Qcc is None:
        lines.append("reduced camera system: conditioning not computed (covariance='none')")
    del s0v, control, control_rows
    return lines, groups, cond, warns
