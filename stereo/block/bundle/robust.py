"""Robust weights of the bundle adjustment (:func:`stereo.block.bundle.adjust.adjust_bundle`).

Iteratively reweighted least squares on standardised residuals ``u = v / (sigma sqrt(r) s)``: ``r`` an
approximate redundancy of the observation, ``s`` the robust scale of the group
(:func:`rectify.geometry.robust.robust_scale`), fixed during one reweighting stage; the weights are
``psi(u) / u`` with a floor of 1e-4, which keeps a point determined when all its rays are rejected.

Seed 002's details (docs/robust.md): with ``BundleOptions.robust_scale = "weighted-median"`` the scale is
re-estimated at every reweighting from the second on as the weighted median of the standardised residuals
with the weights of the reweighting before (eq. 2.29, :func:`rectify.geometry.robust.weighted_scale`);
:func:`m_covariance_factor` is the factor of eq. 2.28 that turns the cofactors of the a-priori weights into
the covariance of the M-estimate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.mestimate import M_ALGORITHMS, NEWTON_METHODS
from rectify.geometry.robust import psi_covariance_factor, robust_scale, weighted_scale
from stereo.block.bundle import solve as bs

__all__ = ["ROBUST_SCALES", "check_robust_options", "local_redundancy", "m_covariance_factor", "mean_redundancy",
           "robust_scales", "robust_update", "standardised"]

#: the bundle's robust scale: of the least-squares residuals, held through a reweighting stage ("first"), or
#: re-estimated at every reweighting from the second on as the weighted median of eq. 2.29
ROBUST_SCALES: tuple[str, ...] = ("first", "weighted-median")

F64 = NDArray[np.float64]


def check_robust_options(algorithm: str, scale: str, newton: str) -> None:
    """Validate ``BundleOptions.robust_algorithm`` (:data:`rectify.geometry.mestimate.M_ALGORITHMS`: reweighting,
    the normal matrix with the robust weights, eq. 2.24; or modified residuals, the a-priori weights in the
    normal matrix and the residuals replaced by ``w v``, eqs. 2.25-2.27), ``robust_scale``
    (:data:`ROBUST_SCALES`) and ``newton`` (``full``: the reduced normal matrix factorised every iteration;
    ``modified``: factorised once and kept until a step fails, :mod:`stereo.block.bundle.newton`)."""
    for name, value, allowed in (("robust_algorithm", algorithm, M_ALGORITHMS), ("robust_scale", scale, ROBUST_SCALES),
                                 ("newton", newton, NEWTON_METHODS)):
        if value not in allowed:
            raise InvalidInputError(f"BundleOptions.{name} must be one of {list(allowed)}; got {value!r}")


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
                   rbar: float, *, weights: bs.Weights | None = None, psi: object = None) -> dict[str, float]:
    """Scale of each group: max(1, robust scale of the standardised residuals).

    Without ``weights`` the median of the absolute non-zero values (eq. 2.29, the first iteration); with
    the robust ``weights`` of the reweighting before and their ``psi``, the weighted median (eq. 2.29 from
    the second iteration on, :func:`rectify.geometry.robust.weighted_scale`)."""
    out = {}
    for g in groups:
        v, w0 = getattr(res, g), getattr(base, g)
        used = w0 > 0
        u = standardised(g, v, w0, rloc, rbar)
        if not used.any():
            s = 0.0
        elif weights is None or psi is None:
            s = robust_scale(u, mask=used)
        else:
            s = weighted_scale(u, getattr(weights, g), psi, mask=used)  # type: ignore[arg-type]
        out[g] = max(1.0, s)
    return out


def mean_redundancy(prob: bs.Problem) -> float:
    """The mean redundancy number of the observations (r / n), the standardisation of the groups other than
    the image coordinates."""
    nobs = 2 * len(prob.obs_pt) + prob.g_pos.size + prob.i_ang.size + int(np.isfinite(prob.c_sigma).sum())
    return max(nobs - prob.n_c - 3 * prob.n_points, 1) / nobs


def m_covariance_factor(psi: object, prob: bs.Problem, res: bs.Residuals, base: bs.Weights, robust_w: bs.Weights,
                        scales: Mapping[str, float], n_unknowns: int) -> float:
    """The factor of eq. 2.28 over every observation of the adjustment: covariance = factor * (A^T P A)^-1.

    ``P`` the a-priori weights (the group factors included, the robust weights not). Each observation
    contributes ``psi_i = w_i e_i`` and ``psi'_i``, ``e_i = v_i sqrt(p_i)`` its residual in a-priori
    standard deviations and ``w_i`` its robust weight: for a group with robust weights ``psi'`` of its
    standardised residual (an image measurement's two coordinates share the value of the measurement),
    for a least-squares group ``psi_i = e_i``, ``psi'_i = 1``. With least squares alone the factor is
    ``v^T P v / (n - u)``, the usual sigma0^2.
    """
    rloc, rbar = local_redundancy(prob), mean_redundancy(prob)
    ps, ds = [], []
    for g in ("image", "gnss", "ins", "control"):
        v, w0, rw = getattr(res, g), getattr(base, g), getattr(robust_w, g)
        if v.size == 0:
            continue
        used = w0 > 0
        e = v * np.sqrt(np.where(used, w0, 0.0))
        if g in scales and psi is not None:
            u = standardised(g, v, w0, rloc, rbar) / scales[g]
            ps.append((rw * e)[used])
            ds.append(np.asarray(psi.dpsi(u), dtype=np.float64)[used])  # type: ignore[attr-defined]
        else:
            ps.append(e[used])
            ds.append(np.ones(int(used.sum())))
    return psi_covariance_factor(np.concatenate(ps), np.concatenate(ds), n_unknowns)


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
