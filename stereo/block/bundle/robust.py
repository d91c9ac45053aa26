"""Robust weights of the bundle adjustment (:func:`stereo.block.bundle.adjust.adjust_bundle`).

Iteratively reweighted least squares on standardised residuals ``u = v / (sigma sqrt(r) s)``: ``r`` an
approximate redundancy of the observation, ``s`` the robust scale of the group
(:func:`rectify.geometry.robust.robust_scale`), fixed during one reweighting stage; the weights are
``psi(u) / u`` with a floor of 1e-4, which keeps a point determined when all its rays are rejected.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.robust import robust_scale
from stereo.block.bundle import solve as bs

__all__ = ["local_redundancy", "robust_scales", "robust_update", "standardised"]

F64 = NDArray[np.float64]


def local_redundancy(prob: bs.Problem) -> F64:
    """(M, 1) approximate redundancy of an image coordinate: (2 m - 3) / (2 m) for a point with m rays."""
    m = prob.pt_count[prob.obs_pt].astype(np.float64)
    return np.asarray(((2 * m - 3) / (2 * m))[:, None], dtype=np.float64)


def standardised(g: str, v: F64, w0: F64, rloc: F64, rbar: float) -> F64:
    """Standardised residuals of a group before the robust scale: v / (sigma sqrt(r)); the image group gives
    one value per observation (the RMS of its two coordinates), so a measurement is reweighted as a whole."""
    if g == "image":
        u = v * np.sqrt(w0) / np.sqrt(rloc)
        return np.asarray(np.repeat(np.sqrt(np.mean(u ** 2, axis=1))[:, None], 2, axis=1), dtype=np.float64)
    return np.asarray(v * np.sqrt(w0) / math.sqrt(rbar), dtype=np.float64)


def robust_scales(res: bs.Residuals, base: bs.Weights, groups: tuple[str, ...], rloc: F64,
                   rbar: float) -> dict[str, float]:
    """Scale of each group: max(1, robust scale of the standardised residuals), fixed during one IRLS run."""
    out = {}
    for g in groups:
        v, w0 = getattr(res, g), getattr(base, g)
        used = w0 > 0
        s = robust_scale(standardised(g, v, w0, rloc, rbar), mask=used) if used.any() else 0.0
        out[g] = max(1.0, s)
    return out


def robust_update(psi: object, res: bs.Residuals, base: bs.Weights, scales: Mapping[str, float], rloc: F64,
                   rbar: float, old: bs.Weights) -> bs.Weights:
    """IRLS weights psi(u) / u of the standardised residuals u (divided by the group's scale)."""
    out = bs.Weights(old.image.copy(), old.gnss.copy(), old.ins.copy(), old.control.copy())
    for g, s in scales.items():
        v = getattr(res, g)
        w0 = getattr(base, g)
        if v.size == 0:
            continue
        used = w0 > 0
        u = standardised(g, v, w0, rloc, rbar) / s
        # a floor keeps every point determined when all its rays are rejected
        w = np.where(used, np.maximum(psi.weight(u), 1e-4), 1.0)  # type: ignore[attr-defined]
        setattr(out, g, w)
    return out
