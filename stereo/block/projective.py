"""Blocks of images without a known camera: models and their joint affine or projective orientation
(seed 003, 3.4.1-3.4.3).

A block of N images whose interior orientation is unknown (archives, scanned films, zoom lenses,
phone images) is built in three steps here, before the projective bundle
(:mod:`stereo.block.projective_bundle`, seed 003, 3.4.4):

1. **Models** (:func:`form_models`): every image pair that shares at least
   :data:`stereo.pair.projective.MIN_POINTS_F` tracks gives one model. Its fundamental matrix
   (:func:`stereo.pair.projective.fundamental_from_points`) gives the canonical projective cameras
   ``P1 = [I | 0]``, ``P2 = [[e']x F | e']``. The ``projective`` method keeps this projective model,
   made quasi-affine (the plane sent to infinity separates no model point from the others: a small
   linear programme over the points whose signs are fixed by their depth in the first camera) and
   normalised (centroid 0, RMS distance sqrt 3). The ``affine`` method forms a "similar" model with a
   nominal camera (principal point at the image centre, focal length ``focal_guess_px``): the
   essential matrix ``E = K^T F K`` gives the relative rotation and base; with a wrong nominal
   camera the model is affine to the object in the normal case (the rays are mapped by
   ``K_nominal^-1 K_true``, the same linear map for both images) and nearly so otherwise.
2. **Chaining**: the models are brought one by one into the frame of the strongest one by a 3D
   affine (12 parameters, :class:`stereo.pair.projective.Affine3D`) or projective
   (15 parameters, :class:`stereo.pair.projective.Projective3D`) transformation fitted to the points
   they share with the models already joined.
3. **Joint orientation** (:func:`join_models`, seed 003, 3.4.1 affine and 3.4.2 projective): all
   transformations (the first model's held: the datum) and the block coordinates of every point are
   adjusted together by least squares on the model coordinates, ``v = T_m(x_model) - X_block``.

Virtual control by vector products (seed 003, 3.4.3, :func:`virtual_point`): three points of a model
give ``V = P1 + (a x b) / sqrt(|a x b|)``, ``a = P2 - P1``, ``b = P3 - P1``. Under a similarity
``x -> s R x + t`` it is carried exactly (``(sRa) x (sRb) = s^2 R (a x b)``, divided by
``sqrt(s^2 |a x b|)``), so the same construction in the model and in the block frame gives a
corresponding pair of points off the plane of the three. Under a general affinity
``(A a) x (A b) = det(A) A^-T (a x b)``: the virtual point then holds the out-of-plane column of the
12-parameter transformation to the similarity of its in-plane part. That is what the affine method
needs when the tie points of a model are nearly coplanar (flat ground): without it the third column
of ``A`` is not determined. It is used by the ``affine`` method only (a vector product has no
meaning under a projective transformation).

Frames: pixel coordinates as everywhere (x = column right, y = row down); internally each image's
pixels are normalised, ``u = (px - c) / s`` with ``c`` the image centre and ``s = max(W, H) / 2``
(:func:`pixel_normaliser`), and the cameras of this module map block points to those normalised
coordinates. The block frame is a projective (or, for ``affine``, an affine) image of the object.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.optimize
import scipy.sparse
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError
from stereo.block.types import Tracks
from stereo.pair.projective import (
    MIN_CONTROL_AFFINE,
    MIN_CONTROL_PROJECTIVE,
    MIN_POINTS_F,
    Affine3D,
    Projective3D,
    cameras_from_fundamental,
    fundamental_from_points,
    triangulate_projective,
)

__all__ = ["BLOCK_METHODS", "MIN_IMAGE_POINTS", "MIN_IMAGES", "ModelBlock", "ProjectiveModel", "form_models",
           "join_models", "pixel_normaliser", "resect_cameras", "virtual_point"]

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: the methods of a block of images without a known camera
BLOCK_METHODS: tuple[str, ...] = ("affine", "projective")
#: images of a block (one model)
MIN_IMAGES = 2
#: tracks an image must observe: its 3 x 4 camera has 11 parameters (6 points, 12 coordinates)
MIN_IMAGE_POINTS = 6
#: the nominal focal length of the affine method's models, in units of max(width, height)
NOMINAL_FOCAL = 1.0
#: weight of a virtual point relative to a tie point in the joint affine orientation
VIRTUAL_WEIGHT = 1.0
#: residuals beyond this many robust standard deviations (1.4826 x median) are outliers (wrong matches along
#: an epipolar line pass the fundamental matrix but not the joint orientation or the bundle)
OUTLIER_FACTOR = 5.0


def pixel_normaliser(width: int, height: int) -> F64:
    """(3, 3) N: homogeneous pixel -> normalised image coordinates ``u = (px - c) / s``, c the image centre
    ((W - 1) / 2, (H - 1) / 2), s = max(W, H) / 2."""
    s = max(width, height) / 2.0
    return np.array([[1.0 / s, 0.0, -(width - 1) / 2.0 / s], [0.0, 1.0 / s, -(height - 1) / 2.0 / s],
                     [0.0, 0.0, 1.0]])


def _normalised(px: F64, N: F64) -> F64:
    return px @ N[:2, :2].T + N[:2, 2]


@dataclass(frozen=True, eq=False)
class ProjectiveModel:
    """One model of a block: a pair of images and the points they share, in the model's own frame.

    Attributes
    ----------
    images : (2,) int
        Indices of the left and right image (into ``Tracks.images``).
    points : (K,) int64
        Indices of the model's tracks (into ``Tracks.point_ids``).
    xyz : (K, 3) float64
        Model coordinates (normalised: centroid 0, RMS distance sqrt 3), the model frame.
    cameras : (2, 3, 4) float64
        Model point (homogeneous) -> normalised image coordinates of the two images
        (:func:`pixel_normaliser`).
    rms_px : float
        RMS Sampson distance of the fundamental matrix, px.
    """

    images: tuple[int, int]
    points: I64
    xyz: F64
    cameras: F64
    rms_px: float


@dataclass(frozen=True, eq=False)
class ModelBlock:
    """The models joined into one block frame (seed 003, 3.4.1-3.4.2).

    Attributes
    ----------
    method : str
        ``affine`` or ``projective``.
    cameras : (n, 3, 4) float64
        Block point (homogeneous) -> normalised image coordinates of every image.
    points : (P, 3) float64
        Block coordinates of every track (NaN for a track in no model).
    models : list of ProjectiveModel
    transforms : (m, 4, 4) float64
        Model frame -> block frame of each model (the first is the identity: the datum).
    rms_model : float
        RMS of the model coordinate residuals of the joint orientation (model units: the models are
        normalised to an RMS distance of sqrt 3 from their centroid).
    sigma0_model : float
        Its sigma0 (sqrt of v^T v over the redundancy), model units.
    redundancy : int
    n_virtual : int
        Virtual points used (affine method).
    """

    method: str
    cameras: F64
    points: F64
    models: list[ProjectiveModel]
    transforms: F64
    rms_model: float
    sigma0_model: float
    redundancy: int
    n_virtual: int


# ------------------------------------------------------------------------- models
def _quasi_affine(X: F64, P1: F64) -> F64:
    """(4, 4) T taking homogeneous model points X (K, 4) to a frame where all are finite and on one side
    of the plane at infinity (signs by the depth in camera P1), then centred and scaled."""
    s = np.sign(X @ P1[2])
    s[s == 0] = 1.0
    return _frame(X * s[:, None])


def _frame(X: F64) -> F64:
    """(4, 4) G = S Hq: Hq sends to infinity a plane that leaves every signed homogeneous point X (K, 4) on
    its positive side (a linear programme: maximise t with pi . x_k >= t), S centres and scales."""
    Xs = X / np.linalg.norm(X, axis=1, keepdims=True)
    # maximise t: pi . X_k >= t, |pi_i| <= 1
    k = len(Xs)
    res = scipy.optimize.linprog(c=[0, 0, 0, 0, -1.0], A_ub=np.column_stack([-Xs, np.ones(k)]), b_ub=np.zeros(k),
                                 bounds=[(-1, 1)] * 4 + [(None, 1)], method="highs")
    if not res.success or res.x[4] <= 0:
        raise EstimationError("the projective model's points are not on one side of any plane (outliers among "
                              "the tie points, or points behind a camera)")
    pi = res.x[:4] / np.linalg.norm(res.x[:4])
    null = np.linalg.svd(pi[None])[2][1:]  # (3, 4) orthonormal complement of pi
    Hq = np.vstack([null, pi])
    Y = Xs @ Hq.T
    E = Y[:, :3] / Y[:, 3:4]
    return _similarity_normaliser(E) @ Hq


def _similarity_normaliser(E: F64) -> F64:
    """(4, 4) S: centroid to 0, RMS distance sqrt 3."""
    c = E.mean(axis=0)
    d = float(np.sqrt(np.mean(np.sum((E - c) ** 2, axis=1)))) or 1.0
    S = np.eye(4)
    S[:3, :3] *= math.sqrt(3.0) / d
    S[:3, 3] = -c * math.sqrt(3.0) / d
    return S


def _essential_cameras(Fn: F64, f: float, ua: F64, ub: F64) -> tuple[F64, F64, F64]:
    """The affine method's similar model: cameras K[I|0], K[R|t] from E = K^T Fn K (K = diag(f, f, 1),
    normalised coordinates), the cheirality-checked solution; returns P1, P2, X (K, 4)."""
    K = np.diag([f, f, 1.0])
    E = K.T @ Fn @ K
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    best = None
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        for t in (U[:, 2], -U[:, 2]):
            P2 = K @ np.hstack([R, t[:, None]])
            X = triangulate_projective([P1, P2], [ua, ub])
            d1 = (X @ P1[2]) * X[:, 3]
            d2 = (X @ P2[2]) * X[:, 3]
            score = int(np.sum((d1 > 0) & (d2 > 0)))
            if best is None or score > best[0]:
                best = (score, P2, X)
    assert best is not None
    return P1, best[1], best[2]


def form_models(tracks: Tracks, sizes: Sequence[tuple[int, int]], *, method: str = "projective",
                focal_guess_px: float | None = None, min_points: int = MIN_POINTS_F,
                outlier_px: float | None = 3.0) -> list[ProjectiveModel]:
    """The models of a block: one per image pair sharing at least ``min_points`` tracks.

    Parameters
    ----------
    tracks : Tracks
        Image observations, pixels.
    sizes : sequence of (width, height)
        Image size of every image of ``tracks.images``, px.
    method : str
        ``projective`` (projective models, made quasi-affine) or ``affine`` (similar models formed with
        a nominal camera of focal length ``focal_guess_px``, default max(W, H)).
    min_points : int
        Tracks a pair must share (at least :data:`stereo.pair.projective.MIN_POINTS_F`).
    outlier_px : float or None
        Sampson distance beyond which a pair's points are left out of its model.

    Returns
    -------
    list of ProjectiveModel
        Strongest (most points) first.

    Raises
    ------
    InvalidInputError
        Unknown method, wrong sizes.
    EstimationError
        No pair shares enough points; a pair's points are coplanar (its fundamental matrix is
        undetermined) -- the message names the pair.
    """
    if method not in BLOCK_METHODS:
        raise InvalidInputError(f"unknown block method {method!r}; expected one of {list(BLOCK_METHODS)}")
    n = len(tracks.images)
    if len(sizes) != n:
        raise InvalidInputError(f"{len(sizes)} image sizes for {n} images")
    min_points = max(int(min_points), MIN_POINTS_F)
    norms = [pixel_normaliser(int(w), int(h)) for w, h in sizes]
    # observation lookup: (image, point) -> pixel
    table = np.full((n, tracks.n_points), -1, dtype=np.int64)
    table[tracks.obs_image, tracks.obs_point] = np.arange(tracks.n_obs)
    seen = table >= 0
    common = seen.astype(np.int64) @ seen.T.astype(np.int64)
    pairs = [(int(common[i, j]), i, j) for i in range(n) for j in range(i + 1, n) if common[i, j] >= min_points]
    if not pairs:
        best = max(((int(common[i, j]), i, j) for i in range(n) for j in range(i + 1, n)), default=(0, 0, 1))
        raise EstimationError(f"no image pair shares {min_points} tracks (the fundamental matrix of a model needs "
                              f"at least {MIN_POINTS_F}); the best pair, {tracks.images[best[1]]!r} and "
                              f"{tracks.images[best[2]]!r}, shares {best[0]}")
    pairs.sort(reverse=True)
    out = []
    for _, i, j in pairs:
        pts = np.flatnonzero(seen[i] & seen[j])
        a_px = tracks.obs_pixel[table[i, pts]]
        b_px = tracks.obs_pixel[table[j, pts]]
        try:
            F, fit = fundamental_from_points(a_px, b_px, outlier_px=outlier_px)
        except EstimationError as err:
            raise EstimationError(f"model of images {tracks.images[i]!r} and {tracks.images[j]!r}: {err}") from err
        keep = fit.inliers
        pts, a_px, b_px = pts[keep], a_px[keep], b_px[keep]
        Na, Nb = norms[i], norms[j]
        Fn = np.linalg.inv(Nb).T @ F @ np.linalg.inv(Na)
        Fn /= np.linalg.norm(Fn)
        ua, ub = _normalised(a_px, Na), _normalised(b_px, Nb)
        if method == "projective":
            P1, P2 = cameras_from_fundamental(Fn)
            X = triangulate_projective([P1, P2], [ua, ub])
            T = _quasi_affine(X, P1)
        else:
            wa, ha = sizes[i]
            f = (focal_guess_px if focal_guess_px is not None else NOMINAL_FOCAL * max(wa, ha)) * Na[0, 0]
            P1, P2, X = _essential_cameras(Fn, f, ua, ub)
            ok = np.abs(X[:, 3]) > 1e-12
            E = np.where(ok[:, None], X[:, :3] / np.where(ok, X[:, 3], 1.0)[:, None], np.nan)
            if not np.isfinite(E).all():
                raise EstimationError(f"model of images {tracks.images[i]!r} and {tracks.images[j]!r}: a point at "
                                      "infinity (no base)")
            T = _similarity_normaliser(E)
        Y = X @ T.T
        xyz = Y[:, :3] / Y[:, 3:4]
        Ti = np.linalg.inv(T)
        cams = np.stack([P1 @ Ti, P2 @ Ti])
        cams /= np.linalg.norm(cams.reshape(2, -1), axis=1)[:, None, None]
        out.append(ProjectiveModel((i, j), pts.astype(np.int64), xyz, cams, float(fit.rms_px)))
    return out


# ------------------------------------------------------------------ virtual control
def virtual_point(p1: F64, p2: F64, p3: F64) -> F64:
    """Virtual point by a vector product (seed 003, 3.4.3): ``p1 + (a x b) / sqrt(|a x b|)``,
    ``a = p2 - p1``, ``b = p3 - p1``; (3,) arrays (or (K, 3) for K triangles). Carried exactly by a
    similarity transformation of the three points."""
    a, b = np.asarray(p2) - np.asarray(p1), np.asarray(p3) - np.asarray(p1)
    c = np.cross(a, b)
    n = np.sqrt(np.linalg.norm(c, axis=-1, keepdims=True))
    return np.asarray(p1 + c / np.where(n > 0, n, 1.0), dtype=np.float64)


def _triangle(E: F64) -> tuple[int, int, int]:
    """Indices of three well-spread points of E (K, 3): the farthest pair, then the farthest from their line."""
    c = E.mean(axis=0)
    i = int(np.argmax(np.linalg.norm(E - c, axis=1)))
    j = int(np.argmax(np.linalg.norm(E - E[i], axis=1)))
    d = E[j] - E[i]
    d = d / (np.linalg.norm(d) or 1.0)
    r = (E - E[i]) - np.outer((E - E[i]) @ d, d)
    k = int(np.argmax(np.linalg.norm(r, axis=1)))
    return i, j, k


# ------------------------------------------------------------------ joint orientation
def _fit_once(method: str, src: F64, dst: F64, virtual: bool) -> F64:
    if method == "projective":
        return np.asarray(Projective3D.from_points(src, dst).H, dtype=np.float64)
    if virtual and len(src) >= 3:
        i, j, k = _triangle(src)
        src = np.vstack([src, virtual_point(src[i], src[j], src[k])])
        dst = np.vstack([dst, virtual_point(dst[i], dst[j], dst[k])])
    return np.asarray(Affine3D.from_points(src, dst).matrix, dtype=np.float64)


def _fit(method: str, src: F64, dst: F64, virtual: bool) -> F64:
    """(4, 4) model -> block transformation fitted to corresponding points (with a virtual point pair); points
    farther than :data:`OUTLIER_FACTOR` robust standard deviations are left out and the fit repeated."""
    good = np.ones(len(src), dtype=bool)
    T = _fit_once(method, src, dst, virtual)
    for _ in range(3):
        e = np.linalg.norm(_apply(T, src) - dst, axis=1)
        lim = OUTLIER_FACTOR * 1.4826 * float(np.median(e[good])) + 1e-12
        new = np.asarray(e <= lim, dtype=bool)
        if new.sum() < len(src) // 2 or (new == good).all():
            break
        good = new
        T = _fit_once(method, src[good], dst[good], virtual)
    return T


def _apply(T: F64, x: F64) -> F64:
    y = x @ T[:3, :3].T + T[:3, 3]
    w = x @ T[3, :3] + T[3, 3]
    return np.asarray(y / w[:, None], dtype=np.float64)


def join_models(models: Sequence[ProjectiveModel], n_points: int, n_images: int, *, method: str = "projective",
                virtual: bool = True, max_iterations: int = 30) -> ModelBlock:
    """Join the models into one block: chaining, then the joint orientation of all models.

    Parameters
    ----------
    models : sequence of ProjectiveModel
        From :func:`form_models` (the first, the strongest, is the datum).
    n_points, n_images : int
        Tracks and images of the block.
    method : str
        ``affine`` (12-parameter transformations, seed 003, 3.4.1) or ``projective`` (15, 3.4.2).
    virtual : bool
        Use a virtual point by vector products per model (affine method only, seed 003, 3.4.3).

    Raises
    ------
    EstimationError
        A model shares too few points with the others (the minimum is named), an image is in no
        model, or the adjustment fails.
    """
    if method not in BLOCK_METHODS:
        raise InvalidInputError(f"unknown block method {method!r}; expected one of {list(BLOCK_METHODS)}")
    use_virtual = virtual and method == "affine"
    need = MIN_CONTROL_PROJECTIVE if method == "projective" else (3 if use_virtual else MIN_CONTROL_AFFINE)
    n_par = 15 if method == "projective" else 12
    ms = list(models)
    if not ms:
        raise EstimationError("no models to join")
    # the block points as signed homogeneous vectors: a projective join may carry a new model's points
    # across the plane at infinity of the block frame, which is then chosen again (quasi-affine)
    block_h = np.full((n_points, 4), np.nan)
    block_h[ms[0].points] = np.column_stack([ms[0].xyz, np.ones(len(ms[0].xyz))])
    T = {0: np.eye(4)}
    order = [0]
    left = set(range(1, len(ms)))
    while left:
        block = block_h[:, :3] / block_h[:, 3:4]
        cand = [(int(np.isfinite(block[ms[m].points, 0]).sum()), m) for m in left]
        k, m = max(cand)
        if k < need:
            joined = {im for q in order for im in ms[q].images}
            weak = [q for q in left if set(ms[q].images) <= joined]
            if weak:  # models whose images are all in the block already: left out (they add no image)
                left.difference_update(weak)
                continue
            bad = ms[m]
            raise EstimationError(f"the models cannot be joined: the best remaining one (images {bad.images}) shares "
                                  f"{k} points with the joined models; the joint {method} orientation needs at least "
                                  f"{need} common points ({n_par} parameters)")
        sel = np.isfinite(block[ms[m].points, 0])
        Tm = _fit(method, ms[m].xyz[sel], block[ms[m].points[sel]], use_virtual)
        Y = np.column_stack([ms[m].xyz, np.ones(len(ms[m].xyz))]) @ Tm.T
        Tm = Tm * np.sign(np.median(Y[sel, 3]))  # its common points keep the side of the block's points
        T[m] = Tm
        new = ~sel
        block_h[ms[m].points[new]] = np.column_stack([ms[m].xyz[new], np.ones(int(new.sum()))]) @ Tm.T
        order.append(m)
        left.discard(m)
        fin = np.isfinite(block_h[:, 0])
        if method == "projective" and np.min(block_h[fin, 3] / np.linalg.norm(block_h[fin], axis=1)) < 0.05:
            try:
                G = _frame(block_h[fin])
            except EstimationError:  # no plane leaves every point on one side (outliers): keep the frame
                G = np.eye(4)
            block_h[fin] = block_h[fin] @ G.T
            block_h[fin] /= block_h[fin, 3:4]
            T = {q: G @ Tq for q, Tq in T.items()}
    in_model = np.zeros(n_images, dtype=bool)
    for q in order:
        in_model[list(ms[q].images)] = True
    if not in_model.all():
        raise EstimationError(f"image(s) {np.flatnonzero(~in_model).tolist()} are in no joined model (fewer than "
                              f"{MIN_POINTS_F} tracks shared with any other image)")
    ms = [ms[q] for q in order]  # the joined models, in the order of joining (the datum first)
    T = {j: T[q] for j, q in enumerate(order)}
    if not np.allclose(T[0], np.eye(4)):  # the block frame was chosen again: the datum model takes it
        G = T[0] / T[0][3, 3]
        Y = np.column_stack([ms[0].xyz, np.ones(len(ms[0].xyz))]) @ G.T
        cams0 = ms[0].cameras @ np.linalg.inv(G)
        ms[0] = replace(ms[0], xyz=Y[:, :3] / Y[:, 3:4], cameras=cams0 / np.linalg.norm(cams0.reshape(2, -1),
                                                                                          axis=1)[:, None, None])
        T[0] = np.eye(4)  # the other models' transformations already end in the block frame
    block = np.full((n_points, 3), np.nan)
    for j, mo in enumerate(ms):
        miss = ~np.isfinite(block[mo.points, 0])
        block[mo.points[miss]] = _apply(T[j], mo.xyz[miss])
    Ts, X, rms, s0, red, nv = _adjust_joint(ms, list(range(len(ms))), T, block, method, use_virtual, max_iterations)
    cams = np.full((n_images, 3, 4), np.nan)
    best = np.zeros(n_images)
    for mo, Tm in zip(ms, Ts, strict=True):
        Ti = np.linalg.inv(Tm)
        for side, im in enumerate(mo.images):
            if len(mo.points) > best[im]:
                best[im] = len(mo.points)
                P = mo.cameras[side] @ Ti
                cams[im] = P / np.linalg.norm(P)
    return ModelBlock(method, cams, X, ms, Ts, rms, s0, red, nv)


def _params_of(T: F64, method: str) -> F64:
    H = T / T[3, 3]
    return H.reshape(-1)[:15].copy() if method == "projective" else H[:3].reshape(-1).copy()


def _matrix_of(p: F64, method: str) -> F64:
    if method == "projective":
        return np.append(p, 1.0).reshape(4, 4)
    return np.vstack([p.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])


def _adjust_joint(ms: list[ProjectiveModel], order: list[int], T: dict[int, F64], block: F64, method: str,
                  virtual: bool, max_iterations: int) -> tuple[F64, F64, float, float, int, int]:
    """The simultaneous adjustment of the model transformations (first model held) and block points."""
    k = 15 if method == "projective" else 12
    free = [m for m in range(len(ms)) if m != 0]
    pos = {m: q for q, m in enumerate(free)}
    used = np.flatnonzero(np.isfinite(block[:, 0]))
    pidx = np.full(len(block), -1, dtype=np.int64)
    pidx[used] = np.arange(len(used))
    nt = k * len(free)
    # observations: (model, point, model xyz)
    om = np.concatenate([np.full(len(mo.points), m) for m, mo in enumerate(ms)]).astype(np.int64)
    op = np.concatenate([pidx[mo.points] for mo in ms]).astype(np.int64)
    ox = np.vstack([mo.xyz for mo in ms])
    # virtual points: one per model (but the datum), from three of its points
    vm, vtri, vx = [], [], []
    if virtual:
        for m in free:
            mo = ms[m]
            i, j, q = _triangle(mo.xyz)
            vm.append(m)
            vtri.append(pidx[mo.points[[i, j, q]]])
            vx.append(virtual_point(mo.xyz[i], mo.xyz[j], mo.xyz[q]))
    vm_a = np.asarray(vm, dtype=np.int64)
    vtri_a = np.asarray(vtri, dtype=np.int64).reshape(-1, 3)
    vx_a = np.asarray(vx, dtype=np.float64).reshape(-1, 3)
    x0 = np.concatenate([np.concatenate([_params_of(T[m], method) for m in free]) if free else np.zeros(0),
                         block[used].reshape(-1)])

    def mats(x: F64) -> list[F64]:
        return [np.eye(4)] + [_matrix_of(x[k * pos[m]:k * pos[m] + k], method) for m in free]

    oxh = np.column_stack([ox, np.ones(len(ox))])
    vxh = np.column_stack([vx_a, np.ones(len(vx_a))])

    def fun(x: F64) -> F64:
        Tl = np.stack(mats(x))
        X = x[nt:].reshape(-1, 3)
        y = np.einsum("nij,nj->ni", Tl[om], oxh)
        r = y[:, :3] / y[:, 3:4] - X[op]
        if not len(vm_a):
            return r.reshape(-1)
        Vb = virtual_point(X[vtri_a[:, 0]], X[vtri_a[:, 1]], X[vtri_a[:, 2]])
        yv = np.einsum("nij,nj->ni", Tl[vm_a], vxh)
        rv = yv[:, :3] / yv[:, 3:4] - Vb
        return np.concatenate([r.reshape(-1), VIRTUAL_WEIGHT * rv.reshape(-1)])

    rows: list[int] = []
    cols: list[int] = []
    for q, (m, p) in enumerate(zip(om, op, strict=True)):
        for c in range(3):
            r = 3 * q + c
            if m != 0:
                rows.extend([r] * k)
                cols.extend(range(k * pos[int(m)], k * pos[int(m)] + k))
            rows.append(r)
            cols.append(nt + 3 * int(p) + c)
    base = 3 * len(om)
    for q, m in enumerate(vm_a):
        for c in range(3):
            r = base + 3 * q + c
            rows.extend([r] * k)
            cols.extend(range(k * pos[int(m)], k * pos[int(m)] + k))
            for p in vtri_a[q]:
                rows.extend([r] * 3)
                cols.extend(nt + 3 * int(p) + np.arange(3))
    n_res = base + 3 * len(vm_a)
    sparsity = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_res, len(x0))).tocsr()
    sparsity.data[:] = 1.0
    r0 = np.linalg.norm(fun(x0)[:base].reshape(-1, 3), axis=1)
    scale = 1.4826 * float(np.median(r0)) + 1e-12
    sol = scipy.optimize.least_squares(fun, x0, jac_sparsity=sparsity, method="trf", x_scale="jac",
                                       loss="soft_l1", f_scale=2.0 * scale, max_nfev=max_iterations,
                                       xtol=1e-10, ftol=1e-10)
    if not np.isfinite(sol.x).all():
        raise EstimationError(f"the joint {method} orientation of the models diverged")
    r = sol.fun[:base].reshape(-1, 3)
    e = np.linalg.norm(r, axis=1)
    inl = e <= OUTLIER_FACTOR * 1.4826 * float(np.median(e)) / math.sqrt(3.0) * math.sqrt(3.0) + 1e-12
    red = int(3 * inl.sum() - nt - 3 * len(used))
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
    s0 = float(np.sqrt(np.sum(r[inl] ** 2) / red)) if red > 0 else float("nan")
    X = np.full_like(block, np.nan)
    X[used] = sol.x[nt:].reshape(-1, 3)
    logger.debug("joint %s orientation: %d models, rms %.3g, sigma0 %.3g, %d evaluations (%s)", method, len(ms), rms,
                 s0, sol.nfev, sol.message)
    return np.stack(mats(sol.x)), X, rms, s0, red, len(vm_a)


# ------------------------------------------------------------------ resection
def _dlt_linear(X: F64, u: F64) -> F64:
    """(3, 4) linear DLT of block points X (K, 3) to normalised image points u (K, 2) (points normalised)."""
    c = X.mean(axis=0)
    d = float(np.sqrt(np.mean(np.sum((X - c) ** 2, axis=1)))) or 1.0
    T = np.eye(4)
    T[:3, :3] *= math.sqrt(3.0) / d
    T[:3, 3] = -c * math.sqrt(3.0) / d
    Xh = np.column_stack([X, np.ones(len(X))]) @ T.T
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -u[:, :1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -u[:, 1:] * Xh
    P = np.linalg.svd(A)[2][-1].reshape(3, 4) @ T
    return np.asarray(P / np.linalg.norm(P), dtype=np.float64)


def _reprojection(P: F64, X: F64, u: F64) -> F64:
    q = np.column_stack([X, np.ones(len(X))]) @ P.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.linalg.norm(q[:, :2] / q[:, 2:3] - u, axis=1), dtype=np.float64)


def resect_cameras(tracks: Tracks, sizes: Sequence[tuple[int, int]], points: F64, *, outlier_px: float = 5.0,
                   initial: F64 | None = None) -> tuple[F64, NDArray[np.bool_]]:
    """Projective resection (11-parameter DLT) of every image on the block points, with rejection.

    The cameras of the joined models carry the weakly determined part of each model's transformation
    (with nearly coplanar model points, the out-of-plane projective elements); a resection of every
    image on all the block points it observes gives the projective bundle a consistent start.

    Parameters
    ----------
    tracks : Tracks
    sizes : sequence of (width, height)
    points : (P, 3) float64
        Block points (NaN: not in the block).
    outlier_px : float
        Observations farther than this from the resected camera (and than 5 robust standard
        deviations) are rejected, px.
    initial : (n, 3, 4) float64, optional
        The cameras of the joined models: an image keeps its model camera when that reprojects its
        points with a smaller median error than the resected one.

    Returns
    -------
    cameras : (n, 3, 4) float64
        Block point -> normalised image coordinates.
    inlier : (M,) bool
        Observations kept.

    Raises
    ------
    EstimationError
        An image observes fewer than :data:`MIN_IMAGE_POINTS` block points, or they are coplanar.
    """
    n = len(tracks.images)
    cams = np.zeros((n, 3, 4))
    keep = np.asarray(np.isfinite(points[tracks.obs_point]).all(axis=1), dtype=bool)
    for i in range(n):
        N = pixel_normaliser(*sizes[i])
        s = 1.0 / N[0, 0]
        obs = np.flatnonzero((tracks.obs_image == i) & keep)
        if len(obs) < MIN_IMAGE_POINTS:
            raise EstimationError(f"image {tracks.images[i]!r} observes {len(obs)} block points; the resection of a "
                                  f"projective camera (11 parameters) needs at least {MIN_IMAGE_POINTS}")
        X = points[tracks.obs_point[obs]]
        sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
        if sv[2] < 1e-6 * sv[0]:
            raise EstimationError(f"the block points of image {tracks.images[i]!r} are coplanar: a projective camera "
                                  "needs points off one plane")
        u = _normalised(tracks.obs_pixel[obs], N)
        good = np.ones(len(obs), dtype=bool)
        P = _dlt_linear(X, u)
        for rnd in range(4):
            e = _reprojection(P, X, u) * s
            lim = max(outlier_px, OUTLIER_FACTOR * 1.4826 * float(np.median(e[good])))
            new = np.asarray(e <= lim, dtype=bool)
            if new.sum() < MIN_IMAGE_POINTS:
                raise EstimationError(f"the resection of image {tracks.images[i]!r} keeps {int(new.sum())} of "
                                      f"{len(obs)} points within {lim:.3g} px; at least {MIN_IMAGE_POINTS} needed")
            if rnd and (new == good).all():
                break
            good = new
            P = _dlt_linear(X[good], u[good])

        def fun(p: F64, X_: F64 = X[good], u_: F64 = u[good], s_: float = s) -> F64:
            q = np.column_stack([X_, np.ones(len(X_))]) @ p.reshape(3, 4).T
            return np.asarray((q[:, :2] / q[:, 2:3] - u_).reshape(-1) * s_, dtype=np.float64)

        sol = scipy.optimize.least_squares(fun, P.reshape(-1), loss="soft_l1", f_scale=outlier_px / 2, method="trf",
                                           max_nfev=30)
        cams[i] = sol.x.reshape(3, 4) / np.linalg.norm(sol.x)
        if initial is not None and np.isfinite(initial[i]).all():
            e_new = float(np.median(_reprojection(cams[i], X, u)))
            e_old = float(np.median(_reprojection(initial[i], X, u)))
            if not e_new <= e_old:
                cams[i] = initial[i] / np.linalg.norm(initial[i])
                e = _reprojection(cams[i], X, u) * s
                good = e <= max(outlier_px, OUTLIER_FACTOR * 1.4826 * float(np.median(e)))
        keep[obs[~good]] = False
    return cams, keep
