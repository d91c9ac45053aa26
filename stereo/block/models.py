"""The models of a block oriented by independent models: relative orientation, join, adjustment.

Steps 2 to 4 of :func:`stereo.block.independent.independent_models` (seed 002, ch. 3; seed 003,
3.4; the method and its frames are described in :mod:`stereo.block.independent`), with their
options and records:

- :class:`IndependentOptions`, the options of the whole method;
- one model per image pair: relative orientation of the common tracks' photo coordinates and the
  intersected model points with their covariances (``_model``);
- the sequential join of each model to the block by a 7-parameter similarity (``_join``,
  :class:`ModelJoin`);
- the simultaneous adjustment of all models (``_adjust_models``, :class:`ModelAdjustment`).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError, RectifyError, StereoError, WeakGeometryWarning
from rectify.geometry.camera import Camera
from rectify.geometry.residuals import rms
from rectify.geometry.robust import ROBUST_METHODS, robust_scale
from rectify.geometry.rotation import rodrigues, rot_z
from stereo.block.types import Tracks
from stereo.pair.absolute import AbsoluteOrientation, similarity_from_points
from stereo.pair.intersection import intersect
from stereo.relative import RelativeOrientation
from stereo.relative.solver import RelativeOptions
from stereo.relative.systems import get_system

logger = logging.getLogger(__name__)

__all__ = ["IndependentOptions", "Model", "ModelAdjustment", "ModelJoin"]


#: a robust relative orientation that keeps fewer than this share of the points is taken as failed
#: (the least-squares fallback of :func:`_relative` runs instead)
MIN_INLIER_SHARE = 0.5


@dataclass(frozen=True)
class IndependentOptions:
    """Options of :func:`stereo.block.independent.independent_models`.

    Attributes
    ----------
    min_common : int
        Fewest common tracks for two images to form a model (an edge of the image graph).
    min_join_points : int
        Fewest tie points a model must share with the block so far (the shared projection
        centre comes on top).
    system : str
        System of relative orientation (see :mod:`stereo.relative`).
    robust : str
        Psi function of the relative orientations and of the joins (``"none"`` for plain least
        squares), one of :data:`rectify.geometry.robust.ROBUST_METHODS`.
    relative : RelativeOptions or None
        Numerical options of the relative orientations.
    outlier_floor_px : float
        A point flagged by the robust relative orientation is dropped only when its coplanarity
        residual also exceeds this, pixels (exact data has a robust scale of zero).
    join_trim : float
        Before the robust join, tie points farther than ``join_trim`` times the robust scale of
        the closed-form fit's residuals are dropped (three rounds).
    join_floor : float
        Join residuals below this fraction of the model's base never count as outliers.
    max_residual_sigma : float
        Final intersection: an observation is rejected when its image residual divided by its
        ``obs_sigma_px`` exceeds this times max(1, the robust scale of all such ratios).
    max_rejection_rounds : int
        Rounds of the final rejection (at most one observation per track and round).
    min_angle_rad : float
        Points whose rays meet at a smaller largest angle are left out (NaN), radians.
    adjust : bool
        After the sequential joins, adjust all models together (seed 002, 3.1.2): the 7
        similarity parameters of every model but the first (the datum) and the block coordinates
        of every tie point and projection centre, by weighted least squares on the model
        coordinates (see :func:`_adjust_models`).
    adjust_iterations : int
        Most Gauss-Newton iterations of that adjustment.
    dependent : bool
        Partially dependent models (seed 002, 3.2; :mod:`stereo.block.model_dependent`): each model
        after the first keeps the block rotation its left image already has, solves only the right
        image (the "left-image" system) and joins by scale and the shared centre.
    """

    min_common: int = 12
    min_join_points: int = 3
    system: str = "dobrynin-pimshina"
    robust: str = "tukey"
    relative: RelativeOptions | None = None
    outlier_floor_px: float = 0.5
    join_trim: float = 5.0
    join_floor: float = 1e-5
    max_residual_sigma: float = 5.0
    max_rejection_rounds: int = 5
    min_angle_rad: float = math.radians(1.0)
    adjust: bool = True
    adjust_iterations: int = 8
    dependent: bool = False

    def __post_init__(self) -> None:
        if int(self.min_common) < 5:
            raise InvalidInputError(f"`min_common` must be >= 5 (relative orientation needs 5 points); "
                                    f"got {self.min_common!r}")
        if int(self.min_join_points) < 2:
            raise InvalidInputError(f"`min_join_points` must be >= 2; got {self.min_join_points!r}")
        if self.robust not in ROBUST_METHODS:
            raise InvalidInputError(f"unknown robust option {self.robust!r}; expected one of "
                                    f"{list(ROBUST_METHODS)}")
        get_system(self.system)  # raises naming an unknown system
        for name in ("outlier_floor_px", "join_trim", "join_floor", "max_residual_sigma"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInputError(f"`{name}` must be a finite number > 0; got {v!r}")
        if not (math.isfinite(self.min_angle_rad) and 0 <= self.min_angle_rad < math.pi / 2):
            raise InvalidInputError(f"`min_angle_rad` must be in [0, pi/2); got {self.min_angle_rad!r}")
        if int(self.adjust_iterations) < 1:
            raise InvalidInputError(f"`adjust_iterations` must be >= 1; got {self.adjust_iterations!r}")
        if int(self.max_rejection_rounds) < 0:
            raise InvalidInputError(f"`max_rejection_rounds` must be >= 0; got {self.max_rejection_rounds!r}")


@dataclass(frozen=True)
class ModelJoin:
    """One model of the block and how it joined.

    Attributes
    ----------
    left, right : str
        Image names; ``left`` was in the block before (except for the first model), ``right`` is new.
    n_relative : int
        Common tracks of the pair (points of the relative orientation).
    n_relative_outliers : int
        Of them, rejected by the robust relative orientation.
    sigma0_mm : float or None
        sigma0 of the relative orientation (one photo coordinate), mm.
    condition_number : float
        Of the relative orientation's (column-scaled) normal matrix; large for a weak model (a
        narrow overlap), where a single pair would warn.
    n_join : int
        Tie points shared with the block and used for the join (the shared centre not counted).
    n_join_outliers : int
        Of them, rejected by the robust join.
    scale : float
        Block units per model unit (the model's base length in the block).
    rms : float
        RMS 3D residual of the join's tie points (not outliers), block units.
    rms_base : float
        ``rms`` relative to the model's base in the block (``rms / scale``): also the RMS in the
        model's own units, whose base is 1.
    centre_residual : float
        Distance between the shared projection centre of the block and of the joined model,
        block units.
    """

    left: str
    right: str
    n_relative: int
    n_relative_outliers: int
    sigma0_mm: float | None
    condition_number: float
    n_join: int
    n_join_outliers: int
    scale: float
    rms: float
    rms_base: float
    centre_residual: float


@dataclass(frozen=True, eq=False)
class ModelAdjustment:
    """The simultaneous adjustment of all models (seed 002, 3.1.2).

    Attributes
    ----------
    iterations : int
    converged : bool
    sigma0 : float
        Standard deviation of unit weight; the weights assume 1 pixel of image noise, so this
        reads as the image noise in pixels.
    n_observations : int
        Model points (tie points and projection centres) taking part, each 3 coordinates.
    n_rejected : int
        Model points rejected as outliers (beyond ``join_trim`` robust scales).
    rms : (n_models,) float64
        RMS 3D residual of each model's points after the adjustment, block units.
    rms_base : (n_models,) float64
        The same relative to each model's base in the block (its RMS in model units).
    """

    iterations: int
    converged: bool
    sigma0: float
    n_observations: int
    n_rejected: int
    rms: NDArray[np.float64]
    rms_base: NDArray[np.float64]

    def __post_init__(self) -> None:
        for name in ("rms", "rms_base"):
            a = np.array(getattr(self, name), dtype=np.float64, copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)


# --------------------------------------------------------------------------- models
@dataclass(frozen=True, eq=False)
class Model:
    """One independent model (seed 002, 3.1.1): a pair's intersected points in its own frame.

    Attributes
    ----------
    tracks : (K,) int64
        Track indices (into the block's ``Tracks``) of the model points.
    points : (K, 3) float64
        Model frame: origin at the left projection centre, base of length 1 (model units).
    rotation_left, rotation_right : (3, 3) float64
        Photo vector -> model frame of the left and right image.
    base : (3,) float64
        The right projection centre in the model frame (unit length).
    covariance : (K, 3, 3) float64
        Of the points for one pixel of image noise, model units squared.
    n_relative, n_relative_outliers, sigma0_mm, condition_number
        Of the relative orientation (as in :class:`ModelJoin`).
    """

    tracks: NDArray[np.int64]
    points: NDArray[np.float64]
    rotation_left: NDArray[np.float64]
    rotation_right: NDArray[np.float64]
    base: NDArray[np.float64]
    covariance: NDArray[np.float64]
    n_relative: int
    n_relative_outliers: int
    sigma0_mm: float | None
    condition_number: float


@dataclass(frozen=True, eq=False)
class _Relative:
    rotation_left: NDArray[np.float64]   # left photo vector -> model frame
    rotation_right: NDArray[np.float64]
    base: NDArray[np.float64]            # (3,) unit, model frame
    ok: NDArray[np.bool_]                # (N,) inliers
    sigma0_mm: float | None
    condition_number: float


def _model(a: int, b: int, cams: list[Camera], tracks: Tracks, obs_mm: NDArray[np.float64],
           per_image: list[tuple[NDArray[np.int64], NDArray[np.int64]]], opts: IndependentOptions) -> Model:
    names = tracks.images
    pa, ra = per_image[a]
    pb, rb = per_image[b]
    common, ia, ib = np.intersect1d(pa, pb, assume_unique=True, return_indices=True)
    left = obs_mm[ra[ia]]
    right = obs_mm[rb[ib]]
    ca, cb = cams[a], cams[b]
    f = (ca.focal_length_mm, cb.focal_length_mm)
    label = f"{names[a]!r}-{names[b]!r}"
    if len(common) < opts.min_common:
        raise StereoError(f"pair {label} has {len(common)} common points; at least {opts.min_common} are needed "
                          "for a model")
    try:
        ro = _relative(left, right, f, [tracks.point_ids[t] for t in common], ca.pixel_size_mm, opts)
    except RectifyError as err:
        raise StereoError(f"relative orientation of pair {label} failed: {err}") from err
    R1, R2, B, ok = ro.rotation_left, ro.rotation_right, ro.base, ro.ok
    try:
        inter = intersect(left[ok], right[ok], rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=f,
                          min_angle_rad=1e-9, sigma_mm=ca.pixel_size_mm)
    except RectifyError as err:
        raise StereoError(f"intersection of the model of pair {label} failed: {err}") from err
    good = (inter.scale_left > 0) & (inter.scale_right > 0) & np.isfinite(inter.points).all(axis=1)
    cov = inter.covariance if inter.covariance is not None else np.zeros((len(inter), 3, 3))
    return Model(common[ok][good], inter.points[good], R1, R2, B, cov[good], len(common), int((~ok).sum()),
                  ro.sigma0_mm, ro.condition_number)


def _relative(left: NDArray[np.float64], right: NDArray[np.float64], f: tuple[float, float], ids: list[str],
              pixel_size_mm: float, opts: IndependentOptions) -> _Relative:
    """Relative orientation of one model and its inliers.

    Robust estimation starts from the essential matrix (RANSAC). When that fails (a nearly flat
    scene can defeat the five-point solution), the photo coordinates are turned so that the
    base runs along +x and the right photo matches the left in kappa (a 2D fit of the two point
    sets), the pair is solved by plain least squares from the zero start, residuals beyond
    ``outlier_threshold`` robust scales (and ``outlier_floor_px``) are dropped and the rest is
    solved again, three rounds.
    """
    floor = opts.outlier_floor_px * pixel_size_mm
    rel = opts.relative or RelativeOptions()

    def fit(lm: NDArray[np.float64], rm: NDArray[np.float64], rows: NDArray[np.bool_], robust: str,
            initial: str | NDArray[np.float64], system: str) -> RelativeOrientation:
        with warnings.catch_warnings():
            # a weak model is reported in its ModelJoin (condition_number), not warned once per model
            warnings.simplefilter("ignore", WeakGeometryWarning)
            return RelativeOrientation.from_points(
                lm[rows], rm[rows], focal_length_mm=f, system=system, robust=robust, initial=initial,
                ids=[i for i, r in zip(ids, rows.tolist(), strict=True) if r], pixel_size_mm=pixel_size_mm,
                options=opts.relative)

    every = np.ones(len(left), dtype=bool)
    try:
        ro = fit(left, right, every, opts.robust, "auto", opts.system)
        ok = (ro.weights > 0) & ~(ro.outlier & (np.abs(ro.residual_mm) > floor))
        if opts.robust == "none" or ok.mean() >= MIN_INLIER_SHARE:
            return _Relative(ro.rotation_left, ro.rotation_right, ro.base, ok, ro.sigma0_mm, ro.condition_number)
        # most points called outliers: a wrong solution (a narrow base over flat ground), not bad matches
        first: RectifyError = StereoError(f"the robust relative orientation kept {int(ok.sum())} of {len(ok)} "
                                          "points")
    except RectifyError as err:
        if opts.robust == "none":
            raise
        first = err
    # fallback: turned photo frames, least squares from zero, trimming
    kappa = _kappa_2d(right, left)
    r_k = right @ _rot2(kappa).T
    d = np.median(left - r_k, axis=0)            # the points move against the base
    theta = math.atan2(float(d[1]), float(d[0]))
    lt = left @ _rot2(-theta).T
    rt = r_k @ _rot2(-theta).T
    try:
        ro = fit(lt, rt, every, "none", "zero", "left-image")
        keep = every
        for _ in range(3):
            q = np.abs(ro.residuals(lt, rt))
            sc = robust_scale(q[keep])
            new = q <= max(rel.outlier_threshold * sc, floor)
            if new.sum() < 5 or np.array_equal(new, keep):
                break
            keep = new
            ro = fit(lt, rt, keep, "none", np.asarray(ro.elements), "left-image")
    except RectifyError as err:
        raise StereoError(f"{first}; least squares from the zero start failed too: {err}") from err
    # photo vector v -> turned v' = Rz(-theta) v (left), Rz(kappa - theta) v (right)
    return _Relative(ro.rotation_left @ rot_z(-theta), ro.rotation_right @ rot_z(kappa - theta), ro.base, keep,
                     ro.sigma0_mm, ro.condition_number)


def _rot2(a: float) -> NDArray[np.float64]:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _kappa_2d(src: NDArray[np.float64], dst: NDArray[np.float64]) -> float:
    """Angle of the 2D rotation that best maps the centred ``src`` points onto ``dst``, rad."""
    a = src - np.median(src, axis=0)
    b = dst - np.median(dst, axis=0)
    return math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
                      float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))


@dataclass(frozen=True, eq=False)
class _BlockPoints:
    """Running estimates of the tie points in the block frame: the mean of the joined models."""

    sums: NDArray[np.float64]            # (P, 3)
    count: NDArray[np.int64]             # (P,)
    cov_sums: NDArray[np.float64]        # (P, 3, 3) sum of the models' covariances (block frame)

    @classmethod
    def empty(cls, n: int) -> _BlockPoints:
        return cls(np.zeros((n, 3)), np.zeros(n, dtype=np.int64), np.zeros((n, 3, 3)))

    def add(self, tracks: NDArray[np.int64], points: NDArray[np.float64], cov: NDArray[np.float64]) -> None:
        np.add.at(self.sums, tracks, points)
        np.add.at(self.count, tracks, 1)
        np.add.at(self.cov_sums, tracks, cov)

    def get(self, tracks: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        n = self.count[tracks].astype(np.float64)
        return self.sums[tracks] / n[:, None], self.cov_sums[tracks] / (n * n)[:, None, None]


def _join(model: Model, left: str, right: str, centre: NDArray[np.float64], block: _BlockPoints,
          opts: IndependentOptions
          ) -> tuple[float, NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], ModelJoin]:
    """Similarity model -> block on the shared tie points and projection centre (robust).

    Each tie point is weighted by the inverse of its covariance (the model's, carried into the
    block, plus that of the block's estimate), so the poorly determined depth of intersected
    points counts less than their plan position; the shared centre gets the median weight.
    """
    have = block.count[model.tracks] > 0
    nj = int(have.sum())
    if nj < opts.min_join_points:
        raise StereoError(f"model {left!r}-{right!r} shares {nj} tie points with the block so far; at least "
                          f"{opts.min_join_points} are needed to join it (add points in the triple overlap)")
    blk, blk_cov = block.get(model.tracks[have])
    m = np.vstack([np.zeros((1, 3)), model.points[have]])   # the left centre is the model origin
    g = np.vstack([centre[None, :], blk])
    use = np.ones(len(m), dtype=bool)
    try:
        for _ in range(3):
            s, R, T = similarity_from_points(m[use], g[use])
            cov = s * s * np.einsum("ij,njk,lk->nil", R, model.covariance[have], R) + blk_cov
            cov = np.concatenate([np.eye(3)[None] * np.median(np.trace(cov, axis1=1, axis2=2)) / 3, cov])
            W = np.linalg.inv(cov)
            v = s * m @ R.T + T - g
            r = np.sqrt(np.einsum("ni,nij,nj->n", v, W, v))
            sc = robust_scale(r[use])
            new = (r <= opts.join_trim * sc) | (np.linalg.norm(v, axis=1) <= opts.join_floor * s)
            new[0] = True
            if new.sum() < 4 or np.array_equal(new, use):
                break
            use = new
        ids = ["centre", *(str(t) for t in model.tracks[have])]
        W = W / np.median(np.trace(W, axis1=1, axis2=2))
        ao = AbsoluteOrientation.from_points(m[use], g[use], ids=[i for i, u in zip(ids, use, strict=True) if u],
                                             weights=W[use], robust=opts.robust)
    except RectifyError as err:
        raise StereoError(f"joining model {left!r}-{right!r} to the block failed: {err}") from err
    s, R, T = ao.scale, ao.rotation, ao.translation
    r = np.linalg.norm(s * m @ R.T + T - g, axis=1)
    outl = ~use.copy()
    outl[np.flatnonzero(use)] |= np.asarray(ao.residuals.outlier, dtype=bool)
    outl &= r > opts.join_floor * s
    outl[0] = False
    ties = ~outl[1:]
    rms_ = rms(r[1:][ties]) if ties.any() else float("nan")
    # model points: keep all but the join outliers among those already in the block
    keep = np.ones(len(model.tracks), dtype=bool)
    keep[np.flatnonzero(have)[outl[1:]]] = False
    join = ModelJoin(left, right, model.n_relative, model.n_relative_outliers, model.sigma0_mm,
                     model.condition_number, nj,
                     int(outl[1:].sum()), float(s), rms_, rms_ / s, float(r[0]))
    return float(s), np.asarray(R), np.asarray(T), keep, join


def _skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3) -> (N, 3, 3) cross-product matrices [v]x."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _adjust_models(tree: Sequence[tuple[int, int]], models: Sequence[Model],
                   sims: Sequence[tuple[float, NDArray[np.float64], NDArray[np.float64]]], block: _BlockPoints,
                   positions: dict[int, NDArray[np.float64]], opts: IndependentOptions
                   ) -> tuple[ModelAdjustment, dict[int, NDArray[np.float64]], dict[int, NDArray[np.float64]]]:
    """Simultaneous adjustment of independent models (seed 002, 3.1.2, eqs. 3.16-3.28).

    Every model point (tie points and the two projection centres) gives the observation equation
    ``X_i = s_j R_j m_ij + T_j`` in the block frame, weighted by the inverse covariance of the
    intersected point carried into the block (the centres, exact in their model, get the median
    variance of their model's points, as in the sequential join). The unknowns are the block
    coordinates X_i of the tie points seen in two or more models and of every projection centre,
    and the 7 parameters of every model but the first, which is held as the datum. Gauss-Newton;
    the points are eliminated from the normal equations (their 3 x 3 blocks are inverted), the
    reduced 7 (n - 1) system is solved and the points are back-substituted. Model points beyond
    ``join_trim`` robust scales of the normalised residual are rejected after each iteration.
    """
    n_models = len(models)
    P = len(block.count)
    # observations: (model, unknown, model coordinates, model covariance)
    rows_j, rows_u, rows_m, rows_c = [], [], [], []
    for j, (mdl, (a, b)) in enumerate(zip(models, tree, strict=True)):
        rows_j.append(np.full(len(mdl.tracks) + 2, j))
        rows_u.append(np.concatenate([mdl.tracks, [P + a, P + b]]))
        rows_m.append(np.vstack([mdl.points, np.zeros(3), mdl.base]))
        lam = np.trace(mdl.covariance, axis1=1, axis2=2) / 3 if len(mdl.covariance) else np.ones(1)
        c0 = np.eye(3) * max(float(np.median(lam)), 1e-300)
        rows_c.append(np.concatenate([mdl.covariance, c0[None], c0[None]]))
    oj = np.concatenate(rows_j)
    ou = np.concatenate(rows_u)
    om = np.concatenate(rows_m)
    oc = np.concatenate(rows_c)
    # only unknowns observed in two or more models constrain the models
    seen = np.bincount(ou, minlength=P + len(positions))
    keep = seen[ou] >= 2
    oj, ou, om, oc = oj[keep], ou[keep], om[keep], oc[keep]
    uniq, ou = np.unique(ou, return_inverse=True)
    n_u = len(uniq)
    s = np.array([x[0] for x in sims], dtype=np.float64)
    R = np.stack([x[1] for x in sims])
    T = np.stack([x[2] for x in sims])
    X = np.empty((n_u, 3))
    is_pt = uniq < P
    X[is_pt] = block.get(uniq[is_pt])[0]
    X[~is_pt] = np.array([positions[int(i - P)] for i in uniq[~is_pt]]).reshape(-1, 3)
    # weights in the block frame, from the sequential similarities (scaled for conditioning)
    Cb = (s[oj] ** 2)[:, None, None] * np.einsum("nij,njk,nlk->nil", R[oj], oc, R[oj])
    W = np.linalg.inv(Cb)
    W_unit = float(np.median(np.trace(W, axis1=1, axis2=2)))
    W = W / W_unit
    w = np.ones(len(oj))
    # pairs of observations of the same unknown (for the reduced normal matrix)
    order = np.argsort(ou, kind="stable")
    cnt = np.bincount(ou, minlength=n_u)
    pa_l, pb_l = [order], [order]
    for off in range(1, int(cnt.max())):
        same = ou[order[:-off]] == ou[order[off:]]
        pa_l += [order[:-off][same], order[off:][same]]
        pb_l += [order[off:][same], order[:-off][same]]
    pa, pb = np.concatenate(pa_l), np.concatenate(pb_l)
    eye3 = np.eye(3)
    converged = False
    iterations = 0
    for it in range(1, int(opts.adjust_iterations) + 1):
        iterations = it
        sRm = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om)
        r = sRm + T[oj] - X[ou]
        A = np.zeros((len(oj), 3, 7))
        A[:, :, 0] = sRm
        A[:, :, 1:4] = -_skew(sRm)
        A[:, :, 4:7] = eye3
        We = W * w[:, None, None]
        Y = np.einsum("nki,nkl->nil", A, We)                      # A^T W, (n, 7, 3)
        Npp = np.zeros((n_u, 3, 3))
        gp = np.zeros((n_u, 3))
        np.add.at(Npp, ou, We)
        np.add.at(gp, ou, np.einsum("nij,nj->ni", We, r))
        ok_u = np.linalg.det(Npp) > 0
        Q = np.zeros_like(Npp)
        Q[ok_u] = np.linalg.inv(Npp[ok_u])
        Z = np.einsum("nij,njk->nik", Y, Q[ou])                    # (n, 7, 3)
        S4 = np.zeros((n_models, n_models, 7, 7))
        diag = np.einsum("nij,njk->nik", Y, A)
        np.add.at(S4, (oj, oj), diag)
        np.add.at(S4, (oj[pa], oj[pb]), -np.einsum("nij,nkj->nik", Z[pa], Y[pb]))
        rhs = np.zeros((n_models, 7))
        np.add.at(rhs, oj, -np.einsum("nij,nj->ni", Y, r) + np.einsum("nij,nj->ni", Z, gp[ou]))
        S = S4.transpose(0, 2, 1, 3).reshape(7 * n_models, 7 * n_models)[7:, 7:]
        try:
            d = np.linalg.solve(S, rhs.reshape(-1)[7:])
        except np.linalg.LinAlgError as err:
            raise StereoError(f"the simultaneous adjustment of the {n_models} models is singular: {err}") from err
        dp = np.vstack([np.zeros(7), d.reshape(-1, 7)])
        back = gp.copy()
        np.add.at(back, ou, np.einsum("nji,nj->ni", Y, dp[oj]))
        dX = np.einsum("nij,nj->ni", Q, back)
        s = s * np.exp(dp[:, 0])
        R = np.stack([rodrigues(dp[k, 1:4])[0] @ R[k] for k in range(n_models)])
        T = T + dp[:, 4:7]
        X = X + dX
        step = max(float(np.abs(dp[:, :4]).max()),
                   float(np.abs(dp[:, 4:]).max() / max(s.max(), 1e-300)),
                   float(np.abs(dX).max() / max(s.max(), 1e-300)))
        # robust: reject model points far beyond the robust scale of the normalised residuals
        r = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om) + T[oj] - X[ou]
        e = np.sqrt(np.einsum("ni,nij,nj->n", r, W, r) / 3)
        if opts.robust != "none":
            live = w > 0
            sc = robust_scale(e[live]) if live.any() else 0.0
            far = (e > opts.join_trim * sc) & (np.linalg.norm(r, axis=1) > opts.join_floor * s[oj])
            changed = bool(np.any(far & live) or np.any(~far & ~live))
            w = np.where(far, 0.0, 1.0)
        else:
            changed = False
        if step < 1e-10 and not changed:
            converged = True
            break
    # results: residuals per model, sigma0, poses from the adjusted centres and model rotations
    r = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om) + T[oj] - X[ou]
    e2 = np.einsum("ni,nij,nj->n", r, W, r) * W_unit
    live = w > 0
    dof = 3 * int(live.sum()) - 7 * (n_models - 1) - 3 * int(np.unique(ou[live]).size)
    sigma0 = math.sqrt(float(e2[live].sum()) / dof) if dof > 0 else float("nan")
    d2 = np.linalg.norm(r, axis=1) ** 2
    rms_m = np.sqrt(np.bincount(oj[live], weights=d2[live], minlength=n_models)
                    / np.maximum(np.bincount(oj[live], minlength=n_models), 1))
    new_pos = dict(positions)
    for k, u in enumerate(uniq):
        if u >= P:
            new_pos[int(u - P)] = X[k].copy()
    rot_sum: dict[int, NDArray[np.float64]] = {}
    for j, (mdl, (a, b)) in enumerate(zip(models, tree, strict=True)):
        for img, Rm in ((a, mdl.rotation_left), (b, mdl.rotation_right)):
            rot_sum[img] = rot_sum.get(img, np.zeros((3, 3))) + R[j] @ Rm
    new_rot = {k: _orthonormal(v) for k, v in rot_sum.items()}
    result = ModelAdjustment(iterations=iterations, converged=converged, sigma0=sigma0, n_observations=int(len(oj)),
                             n_rejected=int((~live).sum()), rms=rms_m, rms_base=rms_m / s)
    logger.info("model adjustment: %d iterations, sigma0 %.3g, %d model points rejected", iterations, sigma0,
                result.n_rejected)
    return result, new_pos, new_rot


def _orthonormal(R: NDArray[np.float64]) -> NDArray[np.float64]:
    U, _, Vt = np.linalg.svd(R)
    out = U @ Vt
    if np.linalg.det(out) < 0:
        U[:, -1] *= -1
        out = U @ Vt
    return out
