"""Normal equations of the bundle adjustment: assembly, Schur complement, solution, cofactors.

Unknowns are split into the *camera side* (6 orientation elements per image, omega, phi, kappa,
Cx, Cy, Cz, then the self-calibrated interior parameters of each camera) and the object points
(3 per point). The 3x3 point blocks are eliminated (Schur complement) and the reduced camera
system ``S = N_cc - W C^-1 W^T`` is solved by a dense Cholesky factorisation when it is small
and by a sparse LU factorisation (:func:`scipy.sparse.linalg.splu`) otherwise; the full normal
matrix is never formed.

Cofactors (``Q = N^-1``) come from ``Q_cc = S^-1`` and the per-point back-substitution
``Q_pp,j = C_j^-1 + C_j^-1 W_j^T Q_cc W_j C_j^-1``, evaluated over the observation pairs of each
track (vectorised, in chunks).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from rectify.errors import EstimationError

from .bundle_model import project, rotation_axes, rotations

__all__: list[str] = []

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class Problem:
    """Everything fixed during the adjustment (validated inputs, indices, a-priori sigmas)."""

    n_images: int
    cam_of_image: I64            # (n,)
    pixel_size: F64              # (ncam,)
    centre: F64                  # (ncam, 2)
    sel: I64                     # (c,) indices into the 8 interior parameters
    obs_img: I64                 # (M,)
    obs_pt: I64                  # (M,) sorted
    obs_px: F64                  # (M, 2)
    obs_sigma: F64               # (M,) a-priori sigma without the group factor, px
    pt_start: I64                # (P,) first observation of each point
    pt_count: I64                # (P,)
    g_img: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    g_pos: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    g_sigma: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    lever: F64 | None = None
    i_img: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    i_ang: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    i_sigma: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    c_pt: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    c_xyz: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    c_sigma: F64 = field(default_factory=lambda: np.zeros((0, 3)))   # inf = component not observed
    obs_mark: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))  # (M,) control/check image obs
    dense_limit: int = 4000

    @property
    def n_cams(self) -> int:
        return len(self.pixel_size)

    @property
    def c(self) -> int:
        return len(self.sel)

    @property
    def n_c(self) -> int:
        return 6 * self.n_images + self.c * self.n_cams

    @property
    def n_points(self) -> int:
        return len(self.pt_start)

    def cidx(self) -> I64:
        """(M, 6 + c) camera-side unknown index of each observation's Jacobian columns."""
        pose = 6 * self.obs_img[:, None] + np.arange(6)
        intr = 6 * self.n_images + self.c * self.cam_of_image[self.obs_img][:, None] + np.arange(self.c)
        return np.concatenate([pose, intr], axis=1).astype(np.int64)


@dataclass
class State:
    """Current values of the unknowns."""

    angles: F64     # (n, 3)
    centres: F64    # (n, 3)
    interior: F64   # (ncam, 8)
    points: F64     # (P, 3)

    def copy(self) -> State:
        return State(self.angles.copy(), self.centres.copy(), self.interior.copy(), self.points.copy())


@dataclass
class Weights:
    """Weights (1 / sigma^2 times the robust weight) of every observation group."""

    image: F64      # (M, 2)
    gnss: F64       # (g, 3)
    ins: F64        # (i, 3)
    control: F64    # (k, 3)


@dataclass
class Residuals:
    """Observed minus computed of every group (image px, GNSS m, INS rad, control m)."""

    image: F64
    gnss: F64
    ins: F64
    control: F64
    depth: F64

    def cost(self, w: Weights) -> float:
        return float(np.sum(w.image * self.image ** 2) + np.sum(w.gnss * self.gnss ** 2)
                     + np.sum(w.ins * self.ins ** 2) + np.sum(w.control * self.control ** 2))


@dataclass
class Linear:
    """The linearised problem at one state."""

    res: Residuals
    Jc: F64         # (M, 2, d)
    Jp: F64         # (M, 2, 3)
    Jg: F64         # (g, 3, 6)
    R: F64          # (n, 3, 3)


def wrap(a: F64) -> F64:
    """Angles wrapped to (-pi, pi]."""
    return np.asarray(-((-a + np.pi) % (2 * np.pi) - np.pi), dtype=np.float64)


def evaluate(prob: Problem, st: State, *, jacobian: bool) -> Linear:
    """Residuals (and Jacobians) of all groups at ``st``."""
    R = rotations(st.angles)
    axes = rotation_axes(st.angles)
    oi = prob.obs_img
    cam = prob.cam_of_image[oi]
    pix, depth, Jpose, Jpt, Jint = project(R[oi], st.centres[oi], axes[oi], st.interior[cam],
                                           prob.pixel_size[cam], prob.centre[cam], st.points[prob.obs_pt],
                                           jacobian=jacobian)
    v = prob.obs_px - pix
    Jc = np.concatenate([Jpose, Jint[:, :, prob.sel]], axis=2) if jacobian else Jpose
    gi = prob.g_img
    Jg = np.zeros((len(gi), 3, 6))
    if len(gi):
        if prob.lever is not None:
            Rl = np.einsum("nij,j->ni", R[gi], prob.lever)
            vg = prob.g_pos - (st.centres[gi] + Rl)
            for a in range(3):
                Jg[:, :, a] = np.cross(axes[gi, a], Rl)
        else:
            vg = prob.g_pos - st.centres[gi]
        Jg[:, :, 3:] = np.eye(3)
    else:
        vg = np.zeros((0, 3))
    vi = wrap(prob.i_ang - st.angles[prob.i_img]) if len(prob.i_img) else np.zeros((0, 3))
    vc = prob.c_xyz - st.points[prob.c_pt] if len(prob.c_pt) else np.zeros((0, 3))
    vc = np.where(np.isfinite(prob.c_sigma), vc, 0.0)
    return Linear(Residuals(v, vg, vi, vc, depth), Jc, Jpt, Jg, R)


@dataclass
class Normal:
    """Normal equations in Schur form."""

    S: F64 | sp.csc_matrix     # reduced camera system (damped)
    rhs_c: F64                 # (n_c,)
    Cinv: F64                  # (P, 3, 3) inverse damped point blocks
    bp: F64                    # (P, 3)
    E: F64                     # (M, d, 3) W blocks per observation
    G: F64                     # (M, d, 3) E C^-1
    cidx: I64                  # (M, d)
    diag_c: F64                # (n_c,) undamped diagonal of N_cc
    diag_p: F64                # (P, 3) undamped diagonal of the point blocks
    starts: I64                # (P,) first observation of each point


def _seg_sum(a: F64, prob: Problem) -> F64:
    """Sum rows of ``a`` (M, ...) over the observations of each point (sorted, contiguous)."""
    return np.asarray(np.add.reduceat(a, prob.pt_start, axis=0), dtype=np.float64)


def normal(prob: Problem, lin: Linear, w: Weights, mu: float, *, dense: bool) -> Normal:
    """Assemble the damped normal equations (``N + mu diag(N)``) and reduce them to the cameras."""
    nc, P = prob.n_c, prob.n_points
    cidx = prob.cidx()
    d = cidx.shape[1]
    Jc, Jp, wi, v = lin.Jc, lin.Jp, w.image, lin.res.image
    WJc = Jc * wi[:, :, None]
    Ncc_o = np.einsum("mri,mrj->mij", WJc, Jc)
    E = np.einsum("mri,mrj->mij", WJc, Jp)
    Cp: F64 = _seg_sum(np.einsum("mri,mrj->mij", Jp * wi[:, :, None], Jp), prob)
    bp = _seg_sum(np.einsum("mri,mr->mi", Jp, wi * v), prob)
    bc_o = np.einsum("mri,mr->mi", Jc, wi * v)
    rhs: F64 = np.bincount(cidx.ravel(), weights=bc_o.ravel(), minlength=nc).astype(np.float64)
    # pose-only groups: GNSS positions and INS angles, 6x6 blocks per image
    pose_blocks = np.zeros((prob.n_images, 6, 6))
    pose_rhs = np.zeros((prob.n_images, 6))
    if len(prob.g_img):
        WJg = lin.Jg * w.gnss[:, :, None]
        np.add.at(pose_blocks, prob.g_img, np.einsum("gri,grj->gij", WJg, lin.Jg))
        np.add.at(pose_rhs, prob.g_img, np.einsum("gri,gr->gi", lin.Jg, w.gnss * lin.res.gnss))
    if len(prob.i_img):
        idx = np.arange(3)
        np.add.at(pose_blocks, (prob.i_img[:, None], idx, idx), w.ins)
        np.add.at(pose_rhs, (prob.i_img[:, None], idx), w.ins * lin.res.ins)
    rhs[: 6 * prob.n_images] += pose_rhs.ravel()
    if len(prob.c_pt):
        idx = np.arange(3)
        np.add.at(Cp, (prob.c_pt[:, None], idx, idx), w.control)
        np.add.at(bp, prob.c_pt, w.control * lin.res.control)
    diag_p = np.diagonal(Cp, axis1=1, axis2=2).copy()
    if mu > 0:
        Cp = Cp + mu * diag_p[:, :, None] * np.eye(3)
    Cinv = inv3(Cp)
    with np.errstate(all="ignore"):
        rel = np.linalg.det(Cp) / np.prod(np.diagonal(Cp, axis1=1, axis2=2), axis=1)
    bad = ~np.isfinite(Cinv).all(axis=(1, 2)) | ~(rel > 1e-13)
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise EstimationError(f"object point index {j} is not determined by its rays (singular 3x3 normal block, "
                              f"relative determinant {rel[j]:.3g})")
    G = np.einsum("mia,mab->mib", E, Cinv[prob.obs_pt])
    rhs -= np.bincount(cidx.ravel(), weights=np.einsum("mia,ma->mi", G, bp[prob.obs_pt]).ravel(), minlength=nc)
    shape3 = (len(cidx), d, 3)
    rows = np.broadcast_to(cidx[:, :, None], shape3).ravel()
    cols_r = np.broadcast_to((3 * prob.obs_pt[:, None] + np.arange(3))[:, None, :], shape3).ravel()
    Es = sp.csr_matrix((E.ravel(), (rows, cols_r)), shape=(nc, 3 * P))
    Gs = sp.csr_matrix((G.ravel(), (rows, cols_r)), shape=(nc, 3 * P))
    red = (Gs @ Es.T).tocoo()
    pb = np.arange(6 * prob.n_images).reshape(-1, 6)
    pr = np.repeat(pb, 6, axis=1).ravel()
    pc = np.tile(pb, (1, 6)).ravel()
    if dense:
        flat = (cidx[:, :, None] * nc + cidx[:, None, :]).ravel()
        Ncc = np.asarray(np.bincount(flat, weights=Ncc_o.ravel(), minlength=nc * nc).reshape(nc, nc), dtype=np.float64)
        Ncc[pr, pc] += pose_blocks.ravel()
        diag_c = np.diag(Ncc).copy()
        S: F64 | sp.csc_matrix = Ncc
        S[red.row, red.col] -= red.data  # the product has unique entries
        if mu > 0:
            S[np.diag_indices(nc)] += mu * diag_c
    else:
        r2 = np.broadcast_to(cidx[:, :, None], Ncc_o.shape).ravel()
        c2 = np.broadcast_to(cidx[:, None, :], Ncc_o.shape).ravel()
        Ncc_s = sp.csr_matrix((np.concatenate([Ncc_o.ravel(), pose_blocks.ravel()]),
                               (np.concatenate([r2, pr]), np.concatenate([c2, pc]))), shape=(nc, nc))
        diag_c = Ncc_s.diagonal().copy()
        S = (Ncc_s - red.tocsr() + sp.diags(mu * diag_c)).tocsc()
    return Normal(S, rhs, Cinv, bp, E, G, cidx, diag_c, diag_p, prob.pt_start)


def inv3(A: F64) -> F64:
    """Inverses of (P, 3, 3) matrices by the adjugate (NaN for a singular one, never raises)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    co = np.stack([e * i - f * h, c * h - b * i, b * f - c * e,
                   f * g - d * i, a * i - c * g, c * d - a * f,
                   d * h - e * g, b * g - a * h, a * e - b * d], axis=1).reshape(-1, 3, 3)
    det = a * co[:, 0, 0] + b * co[:, 1, 0] + c * co[:, 2, 0]
    with np.errstate(all="ignore"):
        out = co / det[:, None, None]
    out[~(np.abs(det) > 0)] = np.nan
    return np.asarray(out, dtype=np.float64)


def solve_reduced(ne: Normal) -> tuple[F64, F64]:
    """Camera-side step (n_c,) and point step (P, 3) from the Schur form."""
    S = ne.S
    dg = S.diagonal() if sp.issparse(S) else np.diag(S)
    if not (dg > 0).all():
        k = int(np.flatnonzero(~(dg > 0))[0])
        raise EstimationError(f"camera-side unknown {k} has no influence on the observations (diagonal {dg[k]!r})")
    s = 1.0 / np.sqrt(dg)
    if sp.issparse(S):
        Ss = sp.diags(s) @ S @ sp.diags(s)
        try:
            lu = spla.splu(sp.csc_matrix(Ss))
        except RuntimeError as err:
            raise EstimationError(f"reduced camera system is singular ({err}); the datum is not defined") from err
        xc = lu.solve(ne.rhs_c * s) * s
    else:
        Ss = S * s[:, None] * s[None, :]
        try:
            cf = scipy.linalg.cho_factor(Ss, lower=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"reduced camera system is not positive definite ({err}); "
                                  "the datum is not defined or an image is not determined") from err
        xc = scipy.linalg.cho_solve(cf, ne.rhs_c * s, check_finite=False) * s
    if not np.isfinite(xc).all():
        raise EstimationError("reduced camera system gave a non-finite solution; the datum is not defined")
    return xc, back_substitute(ne, xc)


def back_substitute(ne: Normal, xc: F64) -> F64:
    """Point steps dX_j = C_j^-1 (b_j - W_j^T dx_c), (P, 3)."""
    et = np.einsum("mia,mi->ma", ne.E, xc[ne.cidx])
    acc = np.add.reduceat(et, ne.starts, axis=0)  # observations are sorted by point
    return np.asarray(np.einsum("pab,pb->pa", ne.Cinv, ne.bp - acc), dtype=np.float64)


def refine_points(prob: Problem, st: State, w: Weights, *, iterations: int = 2) -> State:
    """Gauss-Newton on the object points alone, the cameras held (intersection of every track).

    Run after each camera step, it settles the nonlinear point depths (two-ray points with small
    intersection angles) that otherwise force a large damping on the whole step, so the block's
    weak modes converge in a few iterations instead of linearly. A point whose 3x3 block is
    singular keeps its position. Returns a new state.
    """
    out = st.copy()
    eye = np.eye(3)
    for _ in range(iterations):
        lin = evaluate(prob, out, jacobian=True)
        Jp, wi, v = lin.Jp, w.image, lin.res.image
        Cp: F64 = _seg_sum(np.einsum("mri,mrj->mij", Jp * wi[:, :, None], Jp), prob)
        bp = _seg_sum(np.einsum("mri,mr->mi", Jp, wi * v), prob)
        if len(prob.c_pt):
            idx = np.arange(3)
            np.add.at(Cp, (prob.c_pt[:, None], idx, idx), w.control)
            np.add.at(bp, prob.c_pt, w.control * lin.res.control)
        Cp = Cp + 1e-12 * np.diagonal(Cp, axis1=1, axis2=2)[:, :, None] * eye
        Ci = inv3(Cp)
        dx = np.einsum("pab,pb->pa", Ci, bp)
        dx[~np.isfinite(dx).all(axis=1)] = 0.0
        out.points = out.points + dx
    return out


def apply_step(prob: Problem, st: State, xc: F64, xp: F64) -> State:
    """New state after the step (camera side xc, points xp)."""
    out = st.copy()
    n = prob.n_images
    pose = xc[: 6 * n].reshape(n, 6)
    out.angles = st.angles + pose[:, :3]
    out.centres = st.centres + pose[:, 3:]
    if prob.c:
        out.interior[:, prob.sel] += xc[6 * n:].reshape(prob.n_cams, prob.c)
    out.points = st.points + xp
    return out


# ------------------------------------------------------------------ cofactors
def inverse_reduced(S: F64 | sp.csc_matrix) -> F64:
    """Q_cc = S^-1 (dense), Jacobi-scaled for accuracy."""
    Sd = np.asarray(S.toarray() if sp.issparse(S) else S, dtype=np.float64)  # type: ignore[union-attr]
    s = 1.0 / np.sqrt(np.diag(Sd))
    try:
        cf = scipy.linalg.cho_factor(Sd * s[:, None] * s[None, :], lower=True, check_finite=False)
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"reduced camera system is not positive definite ({err})") from err
    Q = scipy.linalg.cho_solve(cf, np.eye(len(s)), check_finite=False)
    return np.asarray(Q * s[:, None] * s[None, :], dtype=np.float64)


def track_cofactors(prob: Problem, ne: Normal, Qcc: F64, points: I64, *, chunk_pairs: int = 400_000
                    ) -> tuple[F64, F64, I64]:
    """Cofactor blocks along the tracks of ``points``.

    Returns
    -------
    Qpp : (len(points), 3, 3)
        Point cofactor blocks C^-1 + C^-1 W^T Q_cc W C^-1.
    T : (m, d, 3)
        Q_cc[idx_i, :] W_j C_j^-1 for every observation i of these points (Q_cp,i = -T_i).
    obs : (m,)
        The observation indices of T.
    """
    starts, counts = prob.pt_start[points], prob.pt_count[points]
    obs = (np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())).astype(np.int64)
    m_of_obs = np.repeat(counts, counts)
    start_of_obs = np.repeat(starts, counts)
    d = ne.cidx.shape[1]
    T = np.zeros((len(obs), d, 3))
    pos = 0
    while pos < len(obs):
        # take observations until the pair count reaches the chunk size
        csum = np.cumsum(m_of_obs[pos:])
        stop = pos + max(1, int(np.searchsorted(csum, chunk_pairs, side="right")))
        o = obs[pos:stop]
        m = m_of_obs[pos:stop]
        rep = np.repeat(np.arange(len(o)), m)
        first = np.cumsum(m) - m
        k = np.repeat(start_of_obs[pos:stop], m) + (np.arange(m.sum()) - np.repeat(first, m))
        ci = ne.cidx[o][rep]
        ck = ne.cidx[k]
        Qik = Qcc[ci[:, :, None], ck[:, None, :]]
        prod = np.einsum("lab,lbc->lac", Qik, ne.G[k])
        T[pos:stop] = np.add.reduceat(prod, first, axis=0)
        pos = stop
    GtT = np.einsum("mia,mib->mab", ne.G[obs], T)
    pstart = np.cumsum(counts) - counts
    Qpp = ne.Cinv[points] + np.add.reduceat(GtT, pstart, axis=0)
    return Qpp, T, obs
