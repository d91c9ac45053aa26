"""Normal equations of the bundle adjustment: assembly, Schur complement, solution, cofactors.

Unknowns are split into the *camera side* (6 orientation elements per image, omega, phi, kappa,
Cx, Cy, Cz, then the self-calibrated interior parameters of each camera) and the object points
(3 per point). The 3x3 point blocks are eliminated (Schur complement) and the reduced camera
system ``S = N_cc - W C^-1 W^T`` is assembled per image pair (:func:`normal`: the points grouped
by track length, one batched product per pair of track positions, summed by fixed sparse 0/1
matrices; index structures built once per problem, :func:`_structure`) and solved by a banded
Cholesky factorisation (images in reverse Cuthill-McKee order) when that is at least
:data:`BANDED_MIN_GAIN` times cheaper, else by a dense Cholesky factorisation when it is small
and by a sparse LU factorisation (:func:`scipy.sparse.linalg.splu`) otherwise; the full normal
matrix is never formed. The per-observation work runs on cache-sized pieces (:data:`CHUNK`,
:data:`EVAL_CHUNK`), optionally on threads (``Problem.threads``).

Cofactors (``Q = N^-1``) come from ``Q_cc = S^-1`` and the per-point back-substitution
``Q_pp,j = C_j^-1 + C_j^-1 W_j^T Q_cc W_j C_j^-1``, evaluated over the observation pairs of each
track (vectorised, in chunks).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.sparse.csgraph import reverse_cuthill_mckee
from threadpoolctl import ThreadpoolController

from rectify.errors import EstimationError
from stereo.block.bundle.model import project, rotation_axes, rotations
from stereo.block.bundle.systematic import PoseModel, add_reduced, pose_normal, pose_rows

__all__: list[str] = []

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Gauss-Newton steps of the point intersection after every camera step (:func:`refine_points`)
REFINE_STEPS = 1
#: the reduced system is factorised as a banded matrix (images in reverse Cuthill-McKee order) when that
#: needs this many times fewer flops than a dense Cholesky ...
BANDED_MIN_GAIN = 4.0
#: ... and at most this many
BANDED_MAX_FLOPS = 5e10
#: dense factorisations from this order on run on the caller's BLAS threads, smaller ones on one
BLAS_THREADS_MIN_UNKNOWNS = 1500
#: the model evaluation and the normal-equation assembly run on threads from this many observations on
THREADS_MIN_OBSERVATIONS = 100_000
#: observations per piece of the model evaluation
EVAL_CHUNK = 5_000
#: observations per piece of the vectorised model evaluation and normal-equation assembly (cache-sized)
CHUNK = 20_000

T_ = TypeVar("T_")
A_ = TypeVar("A_")
_POOL: dict[int, ThreadPoolExecutor] = {}
_POOL_LOCK = threading.Lock()
_CONTROLLER: dict[str, ThreadpoolController] = {}


def _pool(k: int) -> ThreadPoolExecutor:
    with _POOL_LOCK:
        ex = _POOL.get(k)
        if ex is None:
            ex = _POOL[k] = ThreadPoolExecutor(max_workers=k, thread_name_prefix="bundle")
        return ex


def _pmap(threads: int, fn: Callable[[A_], T_], items: Sequence[A_]) -> list[T_]:
    """``[fn(x) for x in items]`` on ``threads`` threads (numpy and scipy release the GIL in their loops)."""
    if threads <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    return list(_pool(threads).map(fn, items))


def _psum(threads: int, fn: Callable[[A_], tuple[F64, ...]], items: Sequence[A_]) -> tuple[F64, ...]:
    """Sums of the arrays ``fn(x)`` returns over ``items``, each thread summing its share in place."""
    k = max(1, min(threads, len(items)))

    def work(share: Sequence[A_]) -> tuple[F64, ...] | None:
        acc: list[F64] | None = None
        for x in share:
            got = fn(x)
            if acc is None:
                acc = [np.array(a, dtype=np.float64) for a in got]
            else:
                for a, b in zip(acc, got, strict=True):
                    a += b
        return None if acc is None else tuple(acc)

    parts = [p for p in _pmap(k, work, [items[i::k] for i in range(k)]) if p is not None]
    out = list(parts[0])
    for p in parts[1:]:
        for a, b in zip(out, p, strict=True):
            a += b
    return tuple(out)


@dataclass
class Problem:
    """Everything fixed during the adjustment (validated inputs, indices, a-priori sigmas)."""

    n_images: int
    cam_of_image: I64            # (n,)
    pixel_size: F64              # (ncam,)
    centre: F64                  # (ncam, 2)
    sel: I64                     # (c,) indices into the 10 interior parameters
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
    #: threads of the model evaluation and the normal-equation assembly
    threads: int = 1
    #: BLAS threads of large dense factorisations (:func:`blas`)
    blas_threads: int = 1
    #: index structures of the reduced camera system (built once, :func:`_structure`)
    cache: dict[str, object] = field(default_factory=dict, repr=False, compare=False)
    #: full GNSS/INS covariances and systematic unknowns (:mod:`stereo.block.bundle.systematic`), or None
    pose_model: PoseModel | None = None
    #: systematic unknowns, the last ones of the camera side
    n_sys: int = 0

    @property
    def n_cams(self) -> int:
        return len(self.pixel_size)

    @property
    def c(self) -> int:
        return len(self.sel)

    @property
    def n_c(self) -> int:
        return 6 * self.n_images + self.c * self.n_cams + self.n_sys

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
    systematic: F64 = field(default_factory=lambda: np.zeros(0))   # (n_sys,)

    def copy(self) -> State:
        return State(self.angles.copy(), self.centres.copy(), self.interior.copy(), self.points.copy(),
                     self.systematic.copy())


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
    Ji: F64 | None = None     # (i, 3, 6) INS pose Jacobian (None: the identity on the angles)
    Jgs: F64 | None = None    # (g, 3, n_sys) GNSS Jacobian by the systematic unknowns
    Jis: F64 | None = None    # (i, 3, n_sys) INS Jacobian by the systematic unknowns


def wrap(a: F64) -> F64:
    """Angles wrapped to (-pi, pi]."""
    return np.asarray(-((-a + np.pi) % (2 * np.pi) - np.pi), dtype=np.float64)


def evaluate(prob: Problem, st: State, *, jacobian: bool, points_only: bool = False) -> Linear:
    """Residuals (and Jacobians) of all groups at ``st``; with ``points_only`` the image Jacobian by the
    points alone (``Jc`` is then empty)."""
    R = rotations(st.angles)
    axes = rotation_axes(st.angles)
    oi = prob.obs_img
    want_c = jacobian and not points_only
    M, d = len(oi), 6 + prob.c
    pix = np.empty((M, 2))
    depth = np.empty(M)
    Jpt = np.empty((M, 2, 3)) if jacobian else np.zeros((0, 2, 3))
    Jc = np.empty((M, 2, d)) if want_c else np.zeros((0, 2, 6))

    def part(r: tuple[int, int]) -> None:
        a, b = r
        o = oi[a:b]
        if prob.n_cams == 1:  # one camera: its constants broadcast
            intr, psz, cen = st.interior[:1], prob.pixel_size[:1], prob.centre[:1]
        else:
            cam = prob.cam_of_image[o]
            intr, psz, cen = st.interior[cam], prob.pixel_size[cam], prob.centre[cam]
        px, dp, Jpose, Jp_, Jint = project(np.take(R, o, axis=0), np.take(st.centres, o, axis=0),
                                           np.take(axes, o, axis=0) if want_c else axes[:0], intr, psz, cen,
                                           np.take(st.points, prob.obs_pt[a:b], axis=0), jacobian=jacobian,
                                           pose=want_c, intrinsic=want_c and prob.c > 0)
        pix[a:b] = px
        depth[a:b] = dp
        if jacobian:
            Jpt[a:b] = Jp_
        if want_c:
            Jc[a:b, :, :6] = Jpose
            if prob.c:
                Jc[a:b, :, 6:] = Jint[:, :, prob.sel]

    _pmap(prob.threads, part, [(a, min(M, a + EVAL_CHUNK)) for a in range(0, M, EVAL_CHUNK)])
    v = prob.obs_px - pix
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
    if prob.pose_model is not None:  # full covariances, systematic unknowns
        vg, Jg, vi, Ji, Jgs, Jis = pose_rows(prob, st, R, axes, vg, Jg, vi)
        return Linear(Residuals(v, vg, vi, vc, depth), Jc, Jpt, Jg, R, Ji, Jgs, Jis)
    return Linear(Residuals(v, vg, vi, vc, depth), Jc, Jpt, Jg, R)


@dataclass
class Banded:
    """A symmetric banded matrix in LAPACK's lower storage, its unknowns reordered.

    ``ab[i - j, j] = S[order[i], order[j]]`` for ``0 <= i - j <= b`` (``order[k]`` is the original
    index of reordered unknown k).
    """

    ab: F64          # (b + 1, n)
    order: I64       # (n,)

    def diagonal(self) -> F64:
        out = np.empty(self.ab.shape[1])
        out[self.order] = self.ab[0]
        return out


@dataclass
class Normal:
    """Normal equations in Schur form."""

    S: F64 | sp.csc_matrix | Banded   # reduced camera system (damped)
    rhs_c: F64                 # (n_c,)
    Cinv: F64                  # (P, 3, 3) inverse damped point blocks
    bp: F64                    # (P, 3)
    Et: F64                    # (M, 3, d) W blocks per observation, transposed (Jp^T W Jc)
    Gc: F64                    # (M, d, 3) E C^-1
    cidx: I64                  # (M, d)
    diag_c: F64                # (n_c,) undamped diagonal of N_cc
    diag_p: F64                # (P, 3) undamped diagonal of the point blocks
    starts: I64                # (P,) first observation of each point
    point_sum: sp.csr_matrix   # (P, M) sums observations per point

    @property
    def E(self) -> F64:
        """(M, d, 3) W blocks per observation (a view)."""
        return np.asarray(self.Et.transpose(0, 2, 1), dtype=np.float64)

    @property
    def G(self) -> F64:
        """(M, d, 3) E C^-1."""
        return self.Gc


def _seg_sum(a: F64, prob: Problem) -> F64:
    """Sum rows of ``a`` (M, ...) over the observations of each point (a sparse aggregation, far faster
    than ``np.add.reduceat`` over rows)."""
    A = _point_sum(prob)
    return np.asarray(A @ a.reshape(len(a), -1), dtype=np.float64).reshape((A.shape[0],) + a.shape[1:])


def _point_sum(prob: Problem) -> sp.csr_matrix:
    """(P, M) 0/1 matrix summing observations per point (cached)."""
    got = prob.cache.get("point_sum")
    if got is None:
        M = len(prob.obs_pt)
        got = sp.csr_matrix((np.ones(M), (prob.obs_pt, np.arange(M))), shape=(prob.n_points, M))
        prob.cache["point_sum"] = got
    return got


@dataclass
class _Group:
    """Points of one track length ``m`` (a chunk of them) and their observation pairs a < b."""

    obs: I64              # (k * m,) observations, point-major
    m: int
    ia: I64               # (q,) pair slots a < b within a track
    ib: I64
    agg: sp.csr_matrix    # (K, q * k) image pair of every (slot, point), slot-major


@dataclass
class _Structure:
    """Index structures of the reduced camera system, fixed for a problem.

    The reduced system ``S = N_cc - sum_j W_j C_j^-1 W_j^T`` has, per point j, the blocks
    ``G_a E_b^T`` of every pair (a, b) of its observations. Those of the pairs a < b are summed per
    image pair (``groups``: the points grouped by track length, so each pair slot is one batched
    product, summed into the image pairs by a sparse 0/1 matrix), those of a = b with ``N_cc`` per
    image (``img_sum``); ``S`` is then one scatter (``rows``, ``cols``) of the image blocks, the
    image-pair blocks and their transposes.
    """

    cidx: I64                  # (M, d) camera-side unknowns of each observation
    n_pairs: int               # K image pairs
    groups: list[_Group]
    img_sum: list[tuple[int, int, sp.csr_matrix]]   # observation ranges and their (n, o1 - o0) image sums
    img_first: I64             # (n, d) camera-side unknowns of each image
    pieces: list[tuple[int, int, int, sp.csr_matrix]]   # observation ranges, their first point, point sums
    rows: I64                  # (L,) row of every entry of S scattered (image blocks, pair blocks, transposes)
    cols: I64                  # (L,)
    flat: I64                  # (L,) rows * n_c + cols
    band: tuple[I64, I64, int] | None = None   # banded lower storage: entries kept, their flat index, bandwidth
    band_order: I64 | None = None              # reordered unknowns (original index of each)
    band_gain: float = 1.0     # flops of a dense Cholesky / of the banded one


def _structure(prob: Problem, chunk: int | None = None) -> _Structure:
    got = prob.cache.get("structure")
    if isinstance(got, _Structure):
        return got
    chunk = CHUNK if chunk is None else chunk
    cidx = prob.cidx()
    d = cidx.shape[1]
    M, n = len(prob.obs_pt), prob.n_images
    img = prob.obs_img
    parts = []
    for m in np.unique(prob.pt_count):
        if m < 2:
            continue
        st = prob.pt_start[prob.pt_count == m]
        ia, ib = np.triu_indices(int(m), 1)
        step = max(1, chunk // len(ia))
        for k0 in range(0, len(st), step):
            obs = (st[k0:k0 + step, None] + np.arange(m)).astype(np.int64)   # (k, m)
            keys = (img[obs[:, ia]] * n + img[obs[:, ib]]).T.ravel()          # slot-major
            parts.append((obs.ravel(), int(m), ia.astype(np.int64), ib.astype(np.int64), keys))
    allkeys = np.concatenate([p[4] for p in parts]) if parts else np.zeros(0, np.int64)
    uk, inv = np.unique(allkeys, return_inverse=True)
    K = len(uk)
    groups, pos = [], 0
    for obs, m, ia, ib, keys in parts:
        q = len(keys)
        agg = sp.csr_matrix((np.ones(q), (inv[pos:pos + q], np.arange(q))), shape=(K, q))
        groups.append(_Group(obs, m, ia, ib, agg))
        pos += q
    img_sum = []
    for o0 in range(0, M, chunk):
        o1 = min(M, o0 + chunk)
        img_sum.append((o0, o1, sp.csr_matrix((np.ones(o1 - o0), (img[o0:o1], np.arange(o1 - o0))),
                                              shape=(n, o1 - o0))))
    pieces = []
    for o0 in range(0, M, chunk):
        o1 = min(M, o0 + chunk)
        p0 = int(prob.obs_pt[o0])
        pts = prob.obs_pt[o0:o1] - p0
        pieces.append((o0, o1, p0, sp.csr_matrix((np.ones(o1 - o0), (pts, np.arange(o1 - o0))),
                                                 shape=(int(pts[-1]) + 1, o1 - o0))))
    # entries of S: the image blocks (d x d), the pair blocks and their transposes
    cam_of = prob.cam_of_image
    first = np.concatenate([6 * np.arange(n)[:, None] + np.arange(6),
                            6 * n + prob.c * cam_of[:, None] + np.arange(prob.c)], axis=1).astype(np.int64)
    ra, rb = first[uk // n], first[uk % n]                # (K, d)
    rows = np.concatenate([np.broadcast_to(first[:, :, None], (n, d, d)).ravel(),
                           np.broadcast_to(ra[:, :, None], (K, d, d)).ravel(),
                           np.broadcast_to(rb[:, None, :], (K, d, d)).ravel()])
    cols = np.concatenate([np.broadcast_to(first[:, None, :], (n, d, d)).ravel(),
                           np.broadcast_to(rb[:, None, :], (K, d, d)).ravel(),
                           np.broadcast_to(ra[:, :, None], (K, d, d)).ravel()])
    out = _Structure(cidx, K, groups, img_sum, first, pieces, rows.astype(np.int64), cols.astype(np.int64),
                     (rows * prob.n_c + cols).astype(np.int64))
    if prob.c == 0 and n > 2:
        _band(out, n, uk // n, uk % n)
    prob.cache["structure"] = out
    return out


def _band(sx: _Structure, n: int, ia: I64, ib: I64) -> None:
    """Banded storage of S (no interior unknowns): images in reverse Cuthill-McKee order of the image graph."""
    A = sp.csr_matrix((np.ones(len(ia)), (ia, ib)), shape=(n, n))
    perm = np.asarray(reverse_cuthill_mckee((A + A.T + sp.eye(n)).tocsr(), symmetric_mode=True), dtype=np.int64)
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    bw = int(np.abs(inv[ia] - inv[ib]).max(initial=0))
    nc = 6 * n
    b = 6 * bw + 5
    order = (6 * perm[:, None] + np.arange(6)).ravel().astype(np.int64)
    pos = np.empty(nc, np.int64)
    pos[order] = np.arange(nc)
    r, c = pos[sx.rows], pos[sx.cols]
    keep = np.flatnonzero(r >= c).astype(np.int64)
    sx.band = (keep, ((r[keep] - c[keep]) * nc + c[keep]).astype(np.int64), b)
    sx.band_order = order
    sx.band_gain = (nc ** 3 / 3.0) / max(nc * (b + 1) ** 2, 1)


def use_banded(prob: Problem) -> bool:
    """Whether the iterations factorise the reduced system as a banded matrix: no self-calibration (its
    interior unknowns couple every image of a camera), at least :data:`BANDED_MIN_GAIN` times fewer flops
    than a dense Cholesky, and at most :data:`BANDED_MAX_FLOPS`."""
    sx = _structure(prob)
    if sx.band is None or prob.n_sys:
        return False
    b = sx.band[2]
    return sx.band_gain >= BANDED_MIN_GAIN and prob.n_c * (b + 1) ** 2 <= BANDED_MAX_FLOPS


def normal(prob: Problem, lin: Linear, w: Weights, mu: float, *, dense: bool, banded: bool = False) -> Normal:
    """Assemble the damped normal equations (``N + mu diag(N)``) and reduce them to the cameras.

    The reduced system is dense (``dense``), a sparse CSC matrix, or with ``banded`` (when
    :func:`use_banded` allows) a :class:`Banded` matrix."""
    nc, n = prob.n_c, prob.n_images
    sx = _structure(prob)
    cidx = sx.cidx
    d = cidx.shape[1]
    Jc, Jp, wi, v = lin.Jc, lin.Jp, w.image, lin.res.image
    M = len(Jc)
    Et = np.empty((M, 3, d))    # Jp^T W Jc

    def obs_part(r: tuple[int, int, int, sp.csr_matrix]) -> tuple[int, F64, F64, F64]:
        """Et of the piece; its sums per point of Jp^T W Jp and Jp^T W v, its camera-side Jc^T W v."""
        a, b, p0, agg = r
        # (batched products are several times faster on contiguous operands than on transposed views)
        wjpt = np.ascontiguousarray((Jp[a:b] * wi[a:b, :, None]).transpose(0, 2, 1))   # (m, 3, 2)
        np.matmul(wjpt, Jc[a:b], out=Et[a:b])
        wv = (wi[a:b] * v[a:b])[:, None, :]
        bc = np.matmul(wv, Jc[a:b])[:, 0, :]
        return (p0, agg @ np.matmul(wjpt, Jp[a:b]).reshape(-1, 9), agg @ np.matmul(wv, Jp[a:b])[:, 0, :],
                np.bincount(cidx[a:b].ravel(), weights=bc.ravel(), minlength=nc).astype(np.float64))

    Cp: F64 = np.zeros((prob.n_points, 3, 3))
    bp = np.zeros((prob.n_points, 3))
    rhs = np.zeros(nc)
    cp9 = Cp.reshape(-1, 9)
    for p0, cp_k, bp_k, rc_k in _pmap(prob.threads, obs_part, sx.pieces):
        cp9[p0:p0 + len(cp_k)] += cp_k  # pieces are contiguous in the points (observations sorted by point)
        bp[p0:p0 + len(bp_k)] += bp_k
        rhs += rc_k
    # pose-only groups: GNSS positions and INS angles, 6x6 blocks per image
    pose_blocks = np.zeros((n, 6, 6))
    pose_rhs = np.zeros((n, 6))
    if len(prob.g_img):
        WJg = lin.Jg * w.gnss[:, :, None]
        np.add.at(pose_blocks, prob.g_img, np.einsum("gri,grj->gij", WJg, lin.Jg))
        np.add.at(pose_rhs, prob.g_img, np.einsum("gri,gr->gi", lin.Jg, w.gnss * lin.res.gnss))
    if len(prob.i_img) and lin.Ji is None:
        idx = np.arange(3)
        np.add.at(pose_blocks, (prob.i_img[:, None], idx, idx), w.ins)
        np.add.at(pose_rhs, (prob.i_img[:, None], idx), w.ins * lin.res.ins)
    sysn = pose_normal(prob, lin, w, pose_blocks, pose_rhs)  # general INS rows; systematic unknowns
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
    G = np.empty((M, d, 3))     # E C^-1

    def g_part(r: tuple[int, int, int, sp.csr_matrix]) -> F64:
        """G of the piece; its camera-side right-hand side G b_p, to be subtracted."""
        a, b = r[0], r[1]
        pt = prob.obs_pt[a:b]
        gt = np.matmul(np.take(Cinv, pt, axis=0), Et[a:b])                # (m, 3, d) = (E C^-1)^T
        G[a:b] = gt.transpose(0, 2, 1)
        gb = np.matmul(np.take(bp, pt, axis=0)[:, None, :], gt)[:, 0, :]
        return np.asarray(np.bincount(cidx[a:b].ravel(), weights=gb.ravel(), minlength=nc), dtype=np.float64)

    for rc_k in _pmap(prob.threads, g_part, sx.pieces):
        rhs -= rc_k
    rhs[: 6 * n] += pose_rhs.ravel()
    if sysn is not None:
        rhs[nc - prob.n_sys:] += sysn.rhs
    # image blocks: sum over the image's observations of Jc^T W Jc - G E^T
    dd = d * d

    def img_part(r: tuple[int, int, sp.csr_matrix]) -> tuple[F64, F64]:
        o0, o1, agg = r
        jc = Jc[o0:o1]
        wjt = np.ascontiguousarray((jc * wi[o0:o1, :, None]).transpose(0, 2, 1))
        return (agg @ np.matmul(wjt, jc).reshape(-1, dd), agg @ np.matmul(G[o0:o1], Et[o0:o1]).reshape(-1, dd))

    img_n, img_r = _psum(prob.threads, img_part, sx.img_sum)
    # undamped diagonal of N_cc
    diag_c: F64 = np.bincount(sx.img_first.ravel(), weights=img_n[:, ::d + 1].ravel(), minlength=nc).astype(np.float64)
    diag_c[: 6 * n] += np.diagonal(pose_blocks, axis1=1, axis2=2).ravel()
    if sysn is not None:
        diag_c[nc - prob.n_sys:] += np.diag(sysn.nss)
    img_blk = img_n - img_r
    img_blk = img_blk.reshape(n, d, d)
    img_blk[:, :6, :6] += pose_blocks
    # image-pair blocks: sum over the pairs a < b of the tracks of G_a E_b^T (one product per pair slot)

    def pair_part(g: _Group) -> tuple[F64]:
        k = len(g.obs) // g.m
        Gm = np.take(G, g.obs, axis=0).reshape(k, g.m, d, 3)
        Em = np.take(Et, g.obs, axis=0).reshape(k, g.m, 3, d)
        buf = np.empty((len(g.ia), k, d, d))
        for s_, (a_, b_) in enumerate(zip(g.ia, g.ib, strict=True)):
            np.matmul(Gm[:, a_], Em[:, b_], out=buf[s_])
        return (g.agg @ buf.reshape(-1, dd),)

    pair_blk = _psum(prob.threads, pair_part, sx.groups)[0] if sx.groups else np.zeros((sx.n_pairs, dd))
    vals = np.concatenate([img_blk.ravel(), -pair_blk.ravel(), -pair_blk.ravel()])
    S: F64 | sp.csc_matrix | Banded
    if banded and sx.band is not None and sx.band_order is not None:
        keep, flat, b = sx.band
        ab: F64 = np.bincount(flat, weights=vals[keep], minlength=(b + 1) * nc).astype(np.float64, copy=False)
        ab = ab.reshape(b + 1, nc)
        if mu > 0:
            ab[0] += mu * diag_c[sx.band_order]
        S = Banded(ab, sx.band_order)
    elif dense:
        S = np.bincount(sx.flat, weights=vals, minlength=nc * nc).astype(np.float64, copy=False)
        S = S.reshape(nc, nc)
        if mu > 0:
            S[np.diag_indices(nc)] += mu * diag_c
    else:
        S = (sp.csr_matrix((vals, (sx.rows, sx.cols)), shape=(nc, nc)) + sp.diags(mu * diag_c)).tocsc()
    if sysn is not None and not isinstance(S, Banded):
        S = add_reduced(S, sysn, nc - prob.n_sys)
    return Normal(S, rhs, Cinv, bp, Et, G, cidx, diag_c, diag_p, prob.pt_start, _point_sum(prob))


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


def controller() -> ThreadpoolController:
    """The thread-pool controller of the loaded BLAS libraries (found once, when this module is imported:
    finding them takes some 30 ms)."""
    with _POOL_LOCK:
        got = _CONTROLLER.get("c")
        if got is None:
            got = _CONTROLLER["c"] = ThreadpoolController()
        return got


def blas(threads: int, n: int) -> AbstractContextManager[object]:
    """BLAS thread limit for a dense factorisation of order ``n``: ``threads`` from
    :data:`BLAS_THREADS_MIN_UNKNOWNS` unknowns on, else unchanged (the adjustment runs BLAS on one
    thread: its own threads call it on tiny matrices, where BLAS threads only spin)."""
    if n < BLAS_THREADS_MIN_UNKNOWNS or threads <= 1:
        return nullcontext()
    return controller().limit(limits=threads, user_api="blas")


def solve_reduced(ne: Normal, *, blas_threads: int = 1) -> tuple[F64, F64]:
    """Camera-side step (n_c,) and point step (P, 3) from the Schur form (a dense factorisation on
    ``blas_threads`` BLAS threads if it is large)."""
    S = ne.S
    dg = S.diagonal() if sp.issparse(S) or isinstance(S, Banded) else np.diag(S)
    if not (dg > 0).all():
        k = int(np.flatnonzero(~(dg > 0))[0])
        raise EstimationError(f"camera-side unknown {k} has no influence on the observations (diagonal {dg[k]!r})")
    s = 1.0 / np.sqrt(dg)
    if isinstance(S, Banded):
        so = s[S.order]
        b = S.ab.shape[0] - 1
        ab = S.ab * so[None, :]
        for k in range(1, b + 1):
            ab[k, :-k] *= so[k:]
        ab[0] *= so
        try:
            cb = scipy.linalg.cholesky_banded(ab, lower=True, overwrite_ab=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"reduced camera system is not positive definite ({err}); "
                                  "the datum is not defined or an image is not determined") from err
        xo = scipy.linalg.cho_solve_banded((cb, True), (ne.rhs_c * s)[S.order], check_finite=False)
        xc = np.empty_like(xo)
        xc[S.order] = xo
        xc *= s
    elif sp.issparse(S):
        Ss = sp.diags(s) @ S @ sp.diags(s)
        try:
            lu = spla.splu(sp.csc_matrix(Ss))
        except RuntimeError as err:
            raise EstimationError(f"reduced camera system is singular ({err}); the datum is not defined") from err
        xc = lu.solve(ne.rhs_c * s) * s
    else:
        Ss = S * s[:, None]
        Ss *= s[None, :]
        try:
            with blas(blas_threads, len(s)):
                cf = scipy.linalg.cho_factor(Ss, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"reduced camera system is not positive definite ({err}); "
                                  "the datum is not defined or an image is not determined") from err
        xc = scipy.linalg.cho_solve(cf, ne.rhs_c * s, check_finite=False) * s
    if not np.isfinite(xc).all():
        raise EstimationError("reduced camera system gave a non-finite solution; the datum is not defined")
    return xc, back_substitute(ne, xc)


def back_substitute(ne: Normal, xc: F64) -> F64:
    """Point steps dX_j = C_j^-1 (b_j - W_j^T dx_c), (P, 3)."""
    M = len(ne.Et)
    et = np.empty((M, 3))
    for a in range(0, M, CHUNK):  # in pieces: no (M, d) temporaries
        b = min(M, a + CHUNK)
        et[a:b] = np.matmul(ne.Et[a:b], np.take(xc, ne.cidx[a:b])[:, :, None])[:, :, 0]
    acc = ne.point_sum @ et
    return np.asarray(np.einsum("pab,pb->pa", ne.Cinv, ne.bp - acc), dtype=np.float64)


def refine_points(prob: Problem, st: State, w: Weights, *, iterations: int = REFINE_STEPS) -> State:
    """Gauss-Newton on the object points alone, the cameras held (intersection of every track).

    Run after each camera step once a step has been rejected (``bundle._iterate``), it settles the
    nonlinear point depths (two-ray points with small intersection angles) that otherwise force a
    large damping on the whole step, so the block's weak modes converge in a few iterations instead
    of linearly. A point whose 3x3 block is singular keeps its position. Returns a new state.
    """
    out = st.copy()
    eye = np.eye(3)
    for _ in range(iterations):
        lin = evaluate(prob, out, jacobian=True, points_only=True)
        Jp, wi, v = lin.Jp, w.image, lin.res.image
        Cp: F64 = _seg_sum(np.matmul((Jp * wi[:, :, None]).transpose(0, 2, 1), Jp), prob)
        bp = _seg_sum(np.matmul((wi * v)[:, None, :], Jp)[:, 0, :], prob)
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
        out.interior[:, prob.sel] += xc[6 * n:6 * n + prob.c * prob.n_cams].reshape(prob.n_cams, prob.c)
    if prob.n_sys:
        out.systematic = st.systematic + xc[prob.n_c - prob.n_sys:]
    out.points = st.points + xp
    return out


# ------------------------------------------------------------------ cofactors
def inverse_reduced(S: F64 | sp.csc_matrix, *, blas_threads: int = 1) -> F64:
    """Q_cc = S^-1 (dense), Jacobi-scaled for accuracy."""
    Sd = np.asarray(S.toarray() if sp.issparse(S) else S, dtype=np.float64)  # type: ignore[union-attr]
    s = 1.0 / np.sqrt(np.diag(Sd))
    with blas(blas_threads, len(s)):
        try:
            cf = scipy.linalg.cho_factor(Sd * s[:, None] * s[None, :], lower=True, overwrite_a=True,
                                         check_finite=False)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"reduced camera system is not positive definite ({err})") from err
        Q = scipy.linalg.cho_solve(cf, np.eye(len(s)), overwrite_b=True, check_finite=False)
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


controller()  # numpy's and scipy's BLAS are loaded (imported above)
