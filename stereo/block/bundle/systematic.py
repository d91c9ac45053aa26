"""GNSS/INS observations of the bundle: full covariances and systematic unknowns (seed 002, 3.64-3.69).

Seed 002 (section 3.3.3) observes each image's projection centre and angles directly: the
correction equations (3.64) ``v_X0 = dX0 - (X0_GPS - X0^0)`` (and Y, Z) for the linear elements,
(3.65) the same for the angles, joined into the 6-vector equation (3.66)-(3.67) per image with its
full 6 x 6 covariance matrix ``K_j`` (3.68), whose inverse is that image's weight matrix; the
normal equations (3.69) then gain ``P_j = K_j^-1`` on the image's 6 x 6 pose block. This module
implements (3.64)-(3.69) with two extensions:

full covariances
    A (3, 3) position covariance, or a (6, 6) covariance of position and angles, per image
    (:attr:`stereo.block.types.GnssObservations.covariance`). It is applied by decorrelation: with
    ``K_pp = L_p L_p^T`` the GNSS residual becomes ``L_p^-1 v_p`` (unit weight); with a 6 x 6
    ``K`` the angle residual is conditioned on the position residual,
    ``v_a|p = v_a - K_ap K_pp^-1 v_p`` of covariance ``K_aa - K_ap K_pp^-1 K_pa = L_a L_a^T``, and
    becomes ``L_a^-1 v_a|p``. The sum of the two squared decorrelated residuals is
    ``v^T K^-1 v`` exactly (the block Cholesky factorisation of ``K``), so the normal equations are
    those of (3.69) with the full weight matrix, while every observation group keeps diagonal unit
    weights (the robust weights, variance components and redundancy numbers of
    :mod:`stereo.block.bundle.adjust` then refer to the decorrelated residuals).
systematic unknowns (additional unknowns on the camera side, after the interior parameters)
    ``gnss_drift="shift"``: a GNSS shift ``a_s`` (3 unknowns, m) per strip; ``"shift-drift"``: also
    a drift ``b_s`` (3 unknowns, m/s) per strip, linear in the exposure time about the strip's mean
    time ``t_s``. The antenna equation of (3.64) becomes
    ``X_GNSS = C + R l + a_s + b_s (t - t_s) + v``.
    ``boresight="block"`` or ``"strip"``: a boresight correction ``beta`` (3 small rotations, rad, in
    the camera frame) for the block or per strip. The INS gives the camera rotation through the
    nominal boresight ``B0``; the true camera rotation is ``R = R_INS exp([beta]x)``, so the
    observed angles are those of ``R exp(-[beta]x)`` and (3.65) becomes
    ``angles_INS = angles(R exp(-[beta]x)) + v``. (The lever arm is not rotated by ``beta``: a 1 m
    lever arm and a 0.1 deg correction move the antenna by 2 mm.)

The strips come from :attr:`GnssObservations.strip` (the pose file's ``strip`` column), the times
from :attr:`GnssObservations.time`. A GNSS shift per strip takes the block's translation away from
the GNSS: control points are then needed (at least one plan and one height point).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.rotation import angles_from_matrix
from stereo.block.bundle.model import rotation_axes, rotations

if TYPE_CHECKING:
    from stereo.block.bundle.solve import Linear, Problem, State, Weights
    from stereo.block.types import GnssObservations

__all__ = ["BORESIGHT_MODES", "DRIFT_MODES", "PoseModel", "check_inputs", "check_modes", "configure",
           "frame_covariance", "summary_dict"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: GNSS systematic unknowns per strip: none, a shift, a shift and a linear drift in time
DRIFT_MODES: tuple[str, ...] = ("none", "shift", "shift-drift")
#: boresight unknowns: none, one for the block, one per strip
BORESIGHT_MODES: tuple[str, ...] = ("none", "block", "strip")
#: rows of the hat matrix evaluated at once (:func:`pose_hat`)
HAT_CHUNK = 256


def check_modes(gnss_drift: str, boresight: str) -> None:
    """Raise :class:`InvalidInputError` naming an unknown ``gnss_drift`` or ``boresight`` mode."""
    if gnss_drift not in DRIFT_MODES:
        raise InvalidInputError(f"unknown GNSS drift model {gnss_drift!r}; expected one of {list(DRIFT_MODES)}")
    if boresight not in BORESIGHT_MODES:
        raise InvalidInputError(f"unknown boresight model {boresight!r}; expected one of {list(BORESIGHT_MODES)}")


def check_inputs(gnss: GnssObservations | None, gnss_drift: str, boresight: str) -> None:
    """What the systematic unknowns need from the observations, checked before any work: the strips (a shift or
    drift per strip, a boresight per strip), the times (a drift), the INS angles (a boresight).

    Raises
    ------
    InvalidInputError
        Naming the option and the missing column.
    """
    check_modes(gnss_drift, boresight)
    if gnss_drift == "none" and boresight == "none":
        return
    if gnss is None:
        raise InvalidInputError(f"--gnss-drift {gnss_drift} / --boresight-unknown {boresight} need GNSS/INS "
                                "observations (a pose file with standard deviations, or --gnss-sigma)")
    if (gnss_drift != "none" or boresight == "strip") and gnss.strip is None:
        what = f"--gnss-drift {gnss_drift}" if gnss_drift != "none" else "--boresight-unknown strip"
        raise InvalidInputError(f"{what} needs the strip of every image: give a 'strip' column in the pose file")
    if gnss_drift == "shift-drift" and gnss.time is None:
        raise InvalidInputError(f"--gnss-drift {gnss_drift} needs the exposure time of every image: give a 'time' "
                                "column in the pose file (or --trajectory with image times)")
    if boresight != "none" and gnss.angles is None:
        raise InvalidInputError(f"--boresight-unknown {boresight} needs INS angles (angle standard deviations in "
                                "the pose file, or --ins-sigma)")


@dataclass
class PoseModel:
    """The GNSS/INS observation model of one adjustment (built by :func:`configure`).

    The first ``g0`` rows of ``Problem.g_img`` (and of ``Problem.i_img`` when there are angles)
    are the observations; systematic unknowns are numbered from ``offset`` on the camera side.
    """

    g0: int
    i0: int
    offset: int
    g_L: F64 | None = None       # (g0, 3, 3) Cholesky factor of each position covariance
    g_wh: F64 | None = None      # (g0, 3, 3) its inverse
    i_wh: F64 | None = None      # (i0, 3, 3) inverse Cholesky factor of the conditional angle covariance
    i_K: F64 | None = None       # (i0, 3, 3) K_ap K_pp^-1
    names: tuple[str, ...] = ()  # systematic unknowns
    g_base: I64 | None = None    # (g0, T) first unknown (local index) of each GNSS term
    g_coef: F64 | None = None    # (g0, T) its coefficient (1 for a shift, t - t_s for a drift)
    i_base: I64 | None = None    # (i0,) first boresight unknown of each INS row

    @property
    def n_sys(self) -> int:
        return len(self.names)

    def raw_gnss(self, v: F64) -> F64:
        """GNSS residuals (g, 3) back in metres (the decorrelated rows multiplied by their factor)."""
        out = np.array(v, dtype=np.float64, copy=True)
        if self.g_L is not None and len(out):
            out[: self.g0] = np.einsum("gij,gj->gi", self.g_L, out[: self.g0])
        return out


def configure(prob: Problem, st: State, gnss: GnssObservations, *, gnss_drift: str, boresight: str,
              n_plan: int, n_height: int) -> None:
    """Attach the GNSS/INS model of ``gnss`` to ``prob`` (rows ``prob.g_img`` set from it, before any
    minimum constraint) and its systematic unknowns to ``st``; nothing when neither a covariance nor a
    systematic unknown is asked for.

    Raises
    ------
    InvalidInputError
        A systematic unknown without the strips, a drift without times, a boresight without angles.
    EstimationError
        A GNSS shift per strip without control (>= 1 plan and >= 1 height point).
    """
    check_modes(gnss_drift, boresight)
    if gnss.covariance is None and gnss_drift == "none" and boresight == "none":
        return
    g0 = len(prob.g_img)
    i0 = len(prob.i_img)
    pm = PoseModel(g0=g0, i0=i0, offset=6 * prob.n_images + prob.c * prob.n_cams)
    if gnss.covariance is not None:
        _covariance(pm, prob, np.asarray(gnss.covariance, dtype=np.float64))
    strips: tuple[str, ...] = ()
    if gnss_drift != "none" or boresight == "strip":
        if gnss.strip is None:
            what = f"--gnss-drift {gnss_drift}" if gnss_drift != "none" else "--boresight-unknown strip"
            raise InvalidInputError(f"{what} needs the strip of every image: give a 'strip' column in the pose file")
        strips = tuple(dict.fromkeys(gnss.strip))
    names: list[str] = []
    if gnss_drift != "none":
        if n_plan < 1 or n_height < 1:
            raise EstimationError(f"a GNSS shift per strip (--gnss-drift {gnss_drift}) leaves the block's translation "
                                  f"to the control points; got {n_plan} plan and {n_height} height control points, "
                                  "need at least 1 of each")
        lab = np.array([strips.index(s) for s in gnss.strip or ()], dtype=np.int64)
        T = 1 if gnss_drift == "shift" else 2
        base = np.zeros((g0, T), np.int64)
        coef = np.ones((g0, T))
        per = 3 * T
        base[:, 0] = per * lab
        for s in strips:
            names += [f"gnss shift {s} {a}" for a in "xyz"]
            if T == 2:
                names += [f"gnss drift {s} {a}" for a in "xyz"]
        if T == 2:
            if gnss.time is None:
                raise InvalidInputError(f"--gnss-drift {gnss_drift} needs the exposure time of every image: give a "
                                        "'time' column in the pose file (or --trajectory with image times)")
            t = np.asarray(gnss.time, dtype=np.float64)
            tmid = np.array([t[lab == k].mean() for k in range(len(strips))])
            base[:, 1] = per * lab + 3
            coef[:, 1] = t - tmid[lab]
            flat = [s for k, s in enumerate(strips) if np.ptp(t[lab == k]) <= 0]
            if flat:
                raise InvalidInputError(f"--gnss-drift shift-drift: every image of strip {flat[0]!r} has the same "
                                        "time; a drift needs times that differ")
        pm.g_base, pm.g_coef = base, coef
    if boresight != "none":
        if gnss.angles is None or i0 == 0:
            raise InvalidInputError(f"--boresight-unknown {boresight} needs INS angles (angle standard deviations in "
                                    "the pose file, or --ins-sigma)")
        first = len(names)
        if boresight == "block":
            names += [f"boresight {a}" for a in ("omega", "phi", "kappa")]
            pm.i_base = np.full(i0, first, np.int64)
        else:
            lab = np.array([strips.index(s) for s in gnss.strip or ()], dtype=np.int64)
            for s in strips:
                names += [f"boresight {s} {a}" for a in ("omega", "phi", "kappa")]
            pm.i_base = (first + 3 * lab).astype(np.int64)
    pm.names = tuple(names)
    prob.pose_model = pm
    prob.n_sys = pm.n_sys
    st.systematic = np.zeros(pm.n_sys)


def _covariance(pm: PoseModel, prob: Problem, cov: F64) -> None:
    """Decorrelating factors of the (g0, 3, 3) or (g0, 6, 6) covariances; the rows' sigmas become 1."""
    g0 = pm.g0
    Kpp = cov[:, :3, :3]
    Lp = np.asarray(np.linalg.cholesky(Kpp), dtype=np.float64)
    pm.g_L, pm.g_wh = Lp, np.asarray(np.linalg.inv(Lp), dtype=np.float64)
    prob.g_sigma = np.array(prob.g_sigma, dtype=np.float64, copy=True)
    prob.g_sigma[:g0] = 1.0
    if cov.shape[-1] == 6 and pm.i0:
        Kap = cov[:, 3:, :3]
        K = np.einsum("gij,gjk->gik", Kap, np.linalg.inv(Kpp))
        cond = cov[:, 3:, 3:] - np.einsum("gij,gkj->gik", K, Kap)
        pm.i_K, pm.i_wh = K, np.asarray(np.linalg.inv(np.linalg.cholesky(cond)), dtype=np.float64)
        prob.i_sigma = np.array(prob.i_sigma, dtype=np.float64, copy=True)
        prob.i_sigma[: pm.i0] = 1.0


def frame_covariance(cov: F64 | None, T: F64, angles_in: F64 | None = None, angles_out: F64 | None = None
                     ) -> F64 | None:
    """Observation covariances (n, 3, 3) or (n, 6, 6) carried into another frame.

    Parameters
    ----------
    cov : (n, 3, 3) or (n, 6, 6), or None
        Covariances of position (m) and omega, phi, kappa (rad) in the first frame (None: None).
    T : (n, 3, 3)
        Rotation of position differences into the new frame at each image.
    angles_in, angles_out : (n, 3), rad
        Omega, phi, kappa of each image's rotation before and after (needed for a 6 x 6 ``cov``).

    Returns
    -------
    (n, k, k) or None
        ``J cov J^T`` with ``J = diag(T, A(a_out)^-1 M A(a_in))``, ``M = R(a_out) R(a_in)^T`` the rotation of
        the image's frame and ``A`` the matrix of the ground-frame axes of the three angles.
    """
    if cov is None:
        return None
    c = np.asarray(cov, dtype=np.float64)
    n, k = c.shape[0], c.shape[-1]
    J = np.zeros((n, k, k))
    J[:, :3, :3] = T
    if k == 6:
        if angles_in is None or angles_out is None:
            raise InvalidInputError("a 6 x 6 covariance needs the angles before and after the change of frame")
        ai, ao = np.asarray(angles_in, dtype=np.float64), np.asarray(angles_out, dtype=np.float64)
        M = rotations(ao) @ np.transpose(rotations(ai), (0, 2, 1))
        J[:, 3:, 3:] = np.linalg.solve(_axes_matrix(rotation_axes(ao)), M @ _axes_matrix(rotation_axes(ai)))
    return np.asarray(J @ c @ np.transpose(J, (0, 2, 1)), dtype=np.float64)


# ---------------------------------------------------------------------------- model
def _wrap(a: F64) -> F64:
    """Angles wrapped to (-pi, pi] (as :func:`stereo.block.bundle.solve.wrap`)."""
    return np.asarray(-((-a + np.pi) % (2 * np.pi) - np.pi), dtype=np.float64)


def _axes_matrix(axes: F64) -> F64:
    """(n, 3, 3) matrices whose columns are the ground-frame axes of omega, phi, kappa."""
    return np.asarray(np.transpose(axes, (0, 2, 1)), dtype=np.float64)


def pose_rows(prob: Problem, st: State, R: F64, axes: F64, vg: F64, Jg: F64, vi: F64
              ) -> tuple[F64, F64, F64, F64, F64 | None, F64 | None]:
    """The GNSS and INS rows of :func:`stereo.block.bundle.solve.evaluate` under the model.

    Parameters
    ----------
    R, axes : (n, 3, 3)
        Rotations and rotation axes of the images (:func:`stereo.block.bundle.model.rotations`,
        :func:`~stereo.block.bundle.model.rotation_axes`).
    vg, Jg, vi : (g, 3), (g, 3, 6), (i, 3)
        The plain GNSS residuals and Jacobian (lever arm included) and INS residuals.

    Returns
    -------
    vg, Jg : (g, 3), (g, 3, 6)
        Decorrelated GNSS residuals (observed - computed) and pose Jacobian of the computed values.
    vi, Ji : (i, 3), (i, 3, 6)
        Decorrelated INS residuals and their pose Jacobian.
    Jgs, Jis : (g, 3, s), (i, 3, s) or None
        Jacobians by the systematic unknowns (None without them).
    """
    pm: PoseModel = prob.pose_model  # type: ignore[assignment]
    g0, i0, ns = pm.g0, pm.i0, pm.n_sys
    s = st.systematic
    vg = np.array(vg, dtype=np.float64, copy=True)
    Jg = np.array(Jg, dtype=np.float64, copy=True)
    vi = np.array(vi, dtype=np.float64, copy=True)
    Ji = np.zeros((len(vi), 3, 6))
    Ji[:, :, :3] = np.eye(3)
    Jgs = np.zeros((len(vg), 3, ns)) if ns else None
    Jis = np.zeros((len(vi), 3, ns)) if ns else None
    rows = np.arange(g0)
    if pm.g_base is not None and pm.g_coef is not None and Jgs is not None:
        for t in range(pm.g_base.shape[1]):
            idx = pm.g_base[:, t, None] + np.arange(3)          # (g0, 3)
            c = pm.g_coef[:, t]
            vg[:g0] -= c[:, None] * s[idx]
            for k in range(3):
                Jgs[rows, k, idx[:, k]] = c
    if pm.i_base is not None and Jis is not None and i0:
        img = prob.i_img[:i0]
        beta = s[pm.i_base[:, None] + np.arange(3)]              # (i0, 3)
        Rc = R[img] @ Rotation.from_rotvec(-beta).as_matrix()
        ac = np.asarray(angles_from_matrix(Rc, "omega-phi-kappa"), dtype=np.float64).reshape(i0, 3)
        vi[:i0] = _wrap(prob.i_ang[:i0] - ac)
        Ac = _axes_matrix(rotation_axes(ac))
        Ji[:i0, :, :3] = np.linalg.solve(Ac, _axes_matrix(axes[img]))
        Jb = -np.linalg.solve(Ac, Rc)                           # d angles / d beta
        ir = np.arange(i0)
        for k in range(3):
            Jis[ir[:, None], np.arange(3)[None, :], pm.i_base[:, None] + k] = Jb[:, :, k]
    if pm.i_K is not None and pm.i_wh is not None and i0:
        K, Wa = pm.i_K, pm.i_wh
        vi[:i0] = np.einsum("gij,gj->gi", Wa, vi[:i0] - np.einsum("gij,gj->gi", K, vg[:g0]))
        Ji[:i0] = Wa @ (Ji[:i0] - K @ Jg[:g0])
        if Jis is not None and Jgs is not None:
            Jis[:i0] = Wa @ (Jis[:i0] - K @ Jgs[:g0])
    if pm.g_wh is not None and g0:
        W = pm.g_wh
        vg[:g0] = np.einsum("gij,gj->gi", W, vg[:g0])
        Jg[:g0] = W @ Jg[:g0]
        if Jgs is not None:
            Jgs[:g0] = W @ Jgs[:g0]
    return vg, Jg, vi, Ji, Jgs, Jis


# ---------------------------------------------------------------------------- normal equations
@dataclass
class SystematicNormal:
    """The systematic unknowns' part of the normal equations."""

    cross: F64      # (n, 6, s) pose x systematic blocks of each image
    nss: F64        # (s, s)
    rhs: F64        # (s,)


def pose_normal(prob: Problem, lin: Linear, w: Weights, pose_blocks: F64, pose_rhs: F64) -> SystematicNormal | None:
    """Add the INS rows (general Jacobian) to ``pose_blocks`` (n, 6, 6) and ``pose_rhs`` (n, 6) in place, and
    return the systematic unknowns' blocks (None without them)."""
    if len(prob.i_img) and lin.Ji is not None:
        WJi = lin.Ji * w.ins[:, :, None]
        np.add.at(pose_blocks, prob.i_img, np.einsum("gri,grj->gij", WJi, lin.Ji))
        np.add.at(pose_rhs, prob.i_img, np.einsum("gri,gr->gi", lin.Ji, w.ins * lin.res.ins))
    ns = prob.n_sys
    if not ns:
        return None
    n = prob.n_images
    cross = np.zeros((n, 6, ns))
    nss = np.zeros((ns, ns))
    rhs = np.zeros(ns)
    for img, Jp, Js, ww, v in ((prob.g_img, lin.Jg, lin.Jgs, w.gnss, lin.res.gnss),
                               (prob.i_img, lin.Ji, lin.Jis, w.ins, lin.res.ins)):
        if Js is None or Jp is None or not len(img):
            continue
        WJs = Js * ww[:, :, None]
        np.add.at(cross, img, np.einsum("gri,grj->gij", Jp * ww[:, :, None], Js))
        nss += np.einsum("gri,grj->ij", WJs, Js)
        rhs += np.einsum("gri,gr->i", Js, ww * v)
    return SystematicNormal(cross, nss, rhs)


def add_reduced(S: F64 | sp.csc_matrix, sn: SystematicNormal, offset: int) -> F64 | sp.csc_matrix:
    """The reduced camera system ``S`` (dense or sparse, its systematic rows and columns still empty) with the
    blocks of ``sn`` added (a dense ``S`` in place)."""
    n = sn.cross.shape[0]
    ns = sn.nss.shape[0]
    C = sn.cross.reshape(6 * n, ns)
    if isinstance(S, np.ndarray):
        S[: 6 * n, offset:offset + ns] += C
        S[offset:offset + ns, : 6 * n] += C.T
        S[offset:offset + ns, offset:offset + ns] += sn.nss
        return S
    nc = S.shape[0]
    r, c = np.nonzero(np.abs(C) > 0)
    rows = np.concatenate([r, c + offset])
    cols = np.concatenate([c + offset, r])
    vals = np.concatenate([C[r, c], C[r, c]])
    rs, cs = np.nonzero(np.ones((ns, ns), bool))
    extra = sp.csr_matrix((np.concatenate([vals, sn.nss.ravel()]),
                           (np.concatenate([rows, rs + offset]), np.concatenate([cols, cs + offset]))), shape=(nc, nc))
    return (S + extra).tocsc()


def pose_hat(prob: Problem, Qcc: F64, img: I64, Jp: F64, Js: F64 | None) -> F64:
    """(g, 3) diagonal of the hat matrix ``J Q J^T`` of pose-only rows: pose Jacobian ``Jp`` (g, 3, 6) of
    image ``img`` (g,) and systematic Jacobian ``Js`` (g, 3, s) or None; ``Qcc`` the camera-side cofactors."""
    out = np.zeros((len(img), 3))
    off = prob.n_c - prob.n_sys
    sidx = off + np.arange(prob.n_sys)
    for a in range(0, len(img), HAT_CHUNK):
        b = min(len(img), a + HAT_CHUNK)
        pidx = 6 * img[a:b, None] + np.arange(6)
        if Js is None:
            idx, J = pidx, Jp[a:b]
        else:
            idx = np.concatenate([pidx, np.broadcast_to(sidx, (b - a, len(sidx)))], axis=1)
            J = np.concatenate([Jp[a:b], Js[a:b]], axis=2)
        Q = Qcc[idx[:, :, None], idx[:, None, :]]
        out[a:b] = np.einsum("gri,gij,grj->gr", J, Q, J)
    return out


def systematic_estimates(prob: Problem, st: State, Qcc: F64 | None, s0v: float
                         ) -> tuple[tuple[str, ...], F64, F64]:
    """Names, values and standard deviations (``s0v`` times the cofactors; NaN without them) of the systematic
    unknowns (m, m/s, rad)."""
    pm = prob.pose_model
    if pm is None or not prob.n_sys:
        return (), np.zeros(0), np.zeros(0)
    off = prob.n_c - prob.n_sys
    if Qcc is None:
        sd = np.full(prob.n_sys, np.nan)
    else:
        sd = np.sqrt(np.clip(s0v * np.diag(Qcc)[off:off + prob.n_sys], 0, None))
    return tuple(pm.names), np.array(st.systematic, dtype=np.float64), sd


def summary_lines(names: Sequence[str], values: F64, std: F64) -> list[str]:
    """One line per systematic unknown: value +- std, in mm, mm/s or degrees."""
    out = []
    for nm, v, s in zip(names, values, std, strict=True):
        if nm.startswith("boresight"):
            out.append(f"{nm}: {np.degrees(v):+.5f} +- {np.degrees(s):.5f} deg")
        elif nm.startswith("gnss drift"):
            out.append(f"{nm}: {1000 * v:+.3f} +- {1000 * s:.3f} mm/s")
        else:
            out.append(f"{nm}: {1000 * v:+.1f} +- {1000 * s:.1f} mm")
    return out


def summary_dict(names: Sequence[str], values: F64, std: F64) -> dict[str, dict[str, dict[str, float]]]:
    """``{"systematic": {name: {"value", "std"}}}`` for a report's summary (m, m/s, rad); empty without unknowns."""
    if not len(names):
        return {}
    return {"systematic": {n: {"value": float(v), "std": float(s)} for n, v, s in zip(names, values, std, strict=True)}}
