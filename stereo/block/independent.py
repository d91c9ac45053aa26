"""Initial orientation of a block without poses, by independent models (seed 002, ch. 3; seed 003, 3.4).

A block of images with multi-image tie points (:class:`~stereo.block.types.Tracks`) and no
exterior orientation is put together pair by pair:

1. **Pairs.** The image graph has an edge between two images weighted by the number of tracks
   they share. Unless the pairs are given, the models are the edges of a maximum spanning tree
   of that graph (Prim's algorithm, started from the pair with the most common points), so both
   the forward overlap along a strip and the links across strips are used, always the strongest.
2. **Models.** Each pair is oriented by :meth:`stereo.relative.RelativeOrientation.from_points`
   on the photo coordinates of its common tracks (robust by default; should the essential-matrix
   start fail, by least squares from photo frames turned to the base, with trimming) and its
   model points are intersected (:func:`stereo.pair.intersection.intersect`). A model's frame has its
   origin at the left projection centre and a unit base.
3. **Join.** The first model's frame is the block frame. Each next model shares one image with
   the block (its left image, following the tree); a 7-parameter spatial similarity (model ->
   block) is estimated on the tie points already in the block (the mean of their earlier model
   estimates) plus the shared projection centre, weighted by the inverse covariance of the
   intersected points and robust (trimmed closed form, then
   :meth:`stereo.pair.absolute.AbsoluteOrientation.from_points` with a psi function). The new image's
   pose and the model's points are then carried into the block frame.
4. **Adjustment.** All models are then adjusted together (seed 002, 3.1.2): the similarity of
   every model but the first and the block coordinates of the tie points and projection centres,
   by weighted least squares on the model coordinates, outliers rejected. Each image's rotation
   is the mean of its models' rotations.
5. **Points.** At the end every track is intersected with all oriented rays (linear least squares,
   the point closest to all rays); observations with large image residuals are rejected one per
   track and round, and points left with fewer than two rays or a small intersection angle are
   NaN.

The result is an initial orientation for a bundle adjustment: the errors of each relative
orientation (model deformation) stay in the block.

Steps 2 to 4 (the models, their join and adjustment) and the options
(:class:`~stereo.block.models.IndependentOptions`) live in :mod:`stereo.block.models`; this module
has the image graph (step 1), the final intersection (step 5, also :func:`triangulate_tracks`
through known poses) and :func:`to_ground`.

:func:`to_ground` then brings the whole block into the ground frame by one 7-parameter similarity
to control points and/or GNSS projection centres.

Frames
------
model (block)
    The first model's frame: its left projection centre at the origin, axes as its system of
    relative orientation sets them, its base of length 1. Right-handed; arbitrary scale.
ground
    The frame of the control and GNSS positions (right-handed, metric or not).
photo
    mm from the principal point, x right, y up; image vector (x, y, -f). Pose rotations take it
    into the block (or ground) frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from rectify.errors import (
    EstimationError,
    InvalidInputError,
    ShapeError,
    StereoError,
)
from rectify.geometry.camera import Camera
from rectify.geometry.residuals import ResidualTable, rms
from rectify.geometry.robust import ROBUST_METHODS, robust_scale
from stereo.block.model_dependent import dependent_model, join_dependent
from stereo.block.models import (
    IndependentOptions,
    Model,
    ModelAdjustment,
    ModelJoin,
    _adjust_models,
    _BlockPoints,
    _join,
    _model,
    _orthonormal,
)
from stereo.block.types import Pose, Tracks
from stereo.pair.absolute import AbsoluteOrientation

logger = logging.getLogger(__name__)

__all__ = ["GroundBlock", "ModelBlock", "independent_models", "to_ground", "triangulate_tracks"]


@dataclass(frozen=True, eq=False)
class ModelBlock:
    """A block oriented by independent models, in its own (arbitrary) model frame.

    Attributes
    ----------
    poses : tuple of Pose
        One per image, in the order of ``tracks.images``; positions and rotations in the block
        frame (see the module docstring), block units.
    point_ids : tuple of str
        The track ids (P).
    points : (P, 3) float64
        Multi-ray intersection of every track, block frame; NaN where a track could not be
        triangulated (fewer than two accepted rays, or too small an angle).
    n_rays : (P,) int64
        Rays used for each point (0 where NaN).
    residual_px : (P,) float64
        RMS image residual of each point over its accepted rays, pixels (NaN where NaN).
    obs_used : (M,) bool
        Observations (rows of the tracks) accepted in the final intersection.
    tree : tuple of (int, int)
        The models in join order as image indices (left, right): ``left`` in the block already,
        ``right`` new (for the first model both new).
    joins : tuple of ModelJoin
        One per model, in ``tree`` order (the sequential join).
    adjustment : ModelAdjustment or None
        The simultaneous adjustment of all models (``options.adjust``; None with one model).
    models : tuple of Model
        The models themselves, in ``tree`` order (their points in their own frames): the input of
        :func:`stereo.block.model_adjust.adjust_models` and of the strip polynomials.
    """

    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: NDArray[np.float64]
    n_rays: NDArray[np.int64]
    residual_px: NDArray[np.float64]
    obs_used: NDArray[np.bool_]
    tree: tuple[tuple[int, int], ...]
    joins: tuple[ModelJoin, ...]
    adjustment: ModelAdjustment | None = None
    models: tuple[Model, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "models", tuple(self.models))
        for name in ("points", "n_rays", "residual_px", "obs_used"):
            a = np.array(getattr(self, name), copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        object.__setattr__(self, "poses", tuple(self.poses))
        object.__setattr__(self, "tree", tuple((int(a), int(b)) for a, b in self.tree))
        object.__setattr__(self, "joins", tuple(self.joins))

    @property
    def images(self) -> tuple[str, ...]:
        return tuple(p.image for p in self.poses)

    @property
    def n_points(self) -> int:
        """Tracks with a point (not NaN)."""
        return int(np.isfinite(self.points).all(axis=1).sum())

    def summary_lines(self) -> list[str]:
        """Short text summary: counts, then one line per model."""
        res = self.residual_px[np.isfinite(self.residual_px)]
        lines = [f"independent models: {len(self.poses)} images, {len(self.joins)} models, "
                 f"{self.n_points} of {len(self.point_ids)} points triangulated, "
                 f"{int(self.obs_used.sum())} of {len(self.obs_used)} observations used",
                 f"image residuals: RMS {rms(res) if res.size else float('nan'):.3f} px"]
        adj = self.adjustment
        if adj is not None:
            lines.append(f"model adjustment: {adj.iterations} iterations, sigma0 {adj.sigma0:.3g}, "
                         f"{adj.n_rejected} of {adj.n_observations} model points rejected, largest model RMS "
                         f"{float(np.max(adj.rms_base)):.3g} of the base")
        for j in self.joins:
            lines.append(f"  model {j.left}-{j.right}: {j.n_relative} points "
                         f"({j.n_relative_outliers} rejected), join on {j.n_join} points "
                         f"({j.n_join_outliers} rejected), RMS {j.rms:.4g} ({j.rms_base:.3g} of the base)")
        return lines


@dataclass(frozen=True, eq=False)
class GroundBlock:
    """A model block brought into the ground frame by one spatial similarity.

    Attributes
    ----------
    poses : tuple of Pose
        Ground frame (``G = s R m + T`` applied to the positions, ``R`` to the rotations).
    point_ids : tuple of str
    points : (P, 3) float64
        Ground frame; NaN where the model block has none.
    similarity : AbsoluteOrientation
        Block frame -> ground frame; its residual table covers control (ids as given) and
        GNSS centres (ids ``"gnss:<image>"``).
    control_ids : tuple of str
        Control points used (those triangulated in the block).
    gnss_images : tuple of str
        Images whose GNSS positions were used.
    control_residuals : (n_control, 3) float64
        Transformed minus given, ground units.
    gnss_residuals : (n_gnss, 3) float64
        Transformed minus given projection centre, ground units.
    """

    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: NDArray[np.float64]
    similarity: AbsoluteOrientation
    control_ids: tuple[str, ...]
    gnss_images: tuple[str, ...]
    control_residuals: NDArray[np.float64]
    gnss_residuals: NDArray[np.float64]

    def __post_init__(self) -> None:
        for name in ("points", "control_residuals", "gnss_residuals"):
            a = np.array(getattr(self, name), dtype=np.float64, copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        object.__setattr__(self, "poses", tuple(self.poses))

    @property
    def residuals(self) -> ResidualTable:
        """The similarity's residual table (control and GNSS)."""
        return self.similarity.residuals

    def summary_lines(self) -> list[str]:
        """Short text summary of the absolute orientation of the block."""
        sim = self.similarity
        lines = [f"block to ground: scale {sim.scale:.6g}, {len(self.control_ids)} control points, "
                 f"{len(self.gnss_images)} GNSS centres, sigma0 {sim.sigma0:.4g}"]
        if len(self.control_ids):
            lines.append(f"  control RMS {rms(np.linalg.norm(self.control_residuals, axis=1)):.4g}")
        if len(self.gnss_images):
            lines.append(f"  GNSS RMS {rms(np.linalg.norm(self.gnss_residuals, axis=1)):.4g}")
        return lines


# --------------------------------------------------------------------------- public functions
def independent_models(
    cameras: Mapping[str, Camera],
    camera_of: Sequence[str],
    tracks: Tracks,
    *,
    pairs: Sequence[tuple[int, int]] | None = None,
    options: IndependentOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ModelBlock:
    """Orient a block without poses by independent models joined into one model frame.

    Parameters
    ----------
    cameras : mapping str -> Camera
        Interior orientation by camera id.
    camera_of : sequence of str
        Camera id of each image, in the order of ``tracks.images``.
    tracks : Tracks
        Multi-image tie points, pixels.
    pairs : sequence of (int, int), optional
        The models as image index pairs. They must connect all images; they are joined in the
        order given, each next one sharing one image with the block so far (pairs closing a
        loop are skipped). Default: the maximum spanning tree of the image graph weighted by the
        number of common tracks.
    options : IndependentOptions, optional
    progress : callable (done, total), optional
        Called after each model and after the final intersection.

    Returns
    -------
    ModelBlock
        Poses and points in the frame of the first model (arbitrary scale).

    Raises
    ------
    InvalidInputError, ShapeError
        Malformed input: camera ids, pair indices, fewer than two images.
    StereoError
        A pair with too few common points (named), a disconnected image graph (its components
        named), a failed relative orientation or intersection (the pair named, the reason passed
        on), a model sharing too few points with the block.
    """
    opts = options or IndependentOptions()
    cams = _cameras_of_images(cameras, camera_of, tracks)
    names = tracks.images
    n = len(names)
    if n < 2:
        raise InvalidInputError(f"a block needs at least 2 images; got {n} ({list(names)})")
    obs_mm = _photo_mm(cams, camera_of, tracks)
    per_image = _obs_by_image(tracks, n)
    counts = _covisibility(tracks, n)
    tree = (_given_tree(pairs, counts, names, opts) if pairs is not None
            else _spanning_tree(counts, names, opts.min_common))
    total = len(tree) + 1
    P = tracks.n_points
    block = _BlockPoints.empty(P)
    positions: dict[int, NDArray[np.float64]] = {}
    rotations: dict[int, NDArray[np.float64]] = {}
    joins: list[ModelJoin] = []
    models: list[Model] = []
    sims: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []
    for k, (a, b) in enumerate(tree):
        if k > 0 and opts.dependent:  # seed 002, 3.2: the left image keeps its block rotation
            model = dependent_model(a, b, rotations[a], cams, tracks, obs_mm, per_image, opts)
        else:
            model = _model(a, b, cams, tracks, obs_mm, per_image, opts)
        if k == 0:
            s, R, T = 1.0, np.eye(3), np.zeros(3)
            positions[a] = np.zeros(3)
            rotations[a] = model.rotation_left
            join = ModelJoin(names[a], names[b], model.n_relative, model.n_relative_outliers, model.sigma0_mm,
                             model.condition_number, 0, 0, 1.0, 0.0, 0.0, 0.0)
            keep = np.ones(len(model.tracks), dtype=bool)
        elif opts.dependent:
            s, R, T, keep, join = join_dependent(model, names[a], names[b], positions[a], block, opts)
        else:
            s, R, T, keep, join = _join(model, names[a], names[b], positions[a], block, opts)
        positions[b] = s * R @ model.base + T
        rotations[b] = R @ model.rotation_right
        g = s * model.points[keep] @ R.T + T
        block.add(model.tracks[keep], g, s * s * np.einsum("ij,njk,lk->nil", R, model.covariance[keep], R))
        joins.append(join)
        models.append(model)
        sims.append((s, R, T))
        logger.info("model %s-%s: %d points, join RMS %.3g of the base", names[a], names[b], model.n_relative,
                    join.rms_base)
        if progress is not None:
            progress(k + 1, total)
    adjustment = None
    if opts.adjust and len(models) > 1:
        try:
            adjustment, positions, rotations = _adjust_models(tree, models, sims, block, positions, opts)
        except StereoError as err:
            # the simultaneous adjustment only improves the sequential joins; the block stands without it
            logger.warning("%s; the sequential joins are kept", err)
    poses = tuple(Pose(names[i], camera_of[i], positions[i], _orthonormal(rotations[i])) for i in range(n))
    points, n_rays, res_px, used = _multiray(poses, cams, tracks, obs_mm, opts)
    if progress is not None:
        progress(total, total)
    return ModelBlock(poses=poses, point_ids=tracks.point_ids, points=points, n_rays=n_rays, residual_px=res_px,
                      obs_used=used, tree=tuple(tree), joins=tuple(joins), adjustment=adjustment,
                      models=tuple(models))


def to_ground(
    block: ModelBlock,
    *,
    control: tuple[Sequence[str], ArrayLike] | None = None,
    gnss: tuple[Sequence[str], ArrayLike] | None = None,
    robust: str = "tukey",
) -> GroundBlock:
    """Absolute orientation of a whole model block by one 7-parameter spatial similarity.

    Parameters
    ----------
    block : ModelBlock
    control : (ids, xyz), optional
        Control point ids (track ids of the block) and their ground coordinates (n, 3); a row
        with X and Y NaN is a height point. Control points the block could not triangulate are
        left out.
    gnss : (images, positions), optional
        Image names and their projection centres in the ground frame (n, 3).
    robust : str
        Psi function of the similarity (:data:`rectify.geometry.robust.ROBUST_METHODS`).

    Returns
    -------
    GroundBlock

    Raises
    ------
    InvalidInputError, ShapeError
        Unknown point ids or image names (named), malformed coordinates, unknown ``robust``.
    EstimationError
        Fewer than 3 points in total, or the points all on one line (as for GNSS of one strip).
    """
    if robust not in ROBUST_METHODS:
        raise InvalidInputError(f"unknown robust option {robust!r}; expected one of {list(ROBUST_METHODS)}")
    c_ids, c_model, c_ground = _control_rows(block, control)
    g_imgs, g_model, g_ground = _gnss_rows(block, gnss)
    model = np.vstack([c_model, g_model])
    ground = np.vstack([c_ground, g_ground])
    ids = [*c_ids, *(f"gnss:{i}" for i in g_imgs)]
    full = np.isfinite(ground).all(axis=1)
    nf = int(full.sum())
    if len(ids) < 3:
        raise EstimationError(f"too few points for the block's absolute orientation: {len(c_ids)} control "
                              f"point(s) and {len(g_imgs)} GNSS centre(s); at least 3 non-collinear are needed")
    if nf == len(ids) or nf < 2:
        for what, pts in (("block", model[full]), ("ground", ground[full])):
            sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False) if nf else np.zeros(3)
            if nf < 3 or not sv[0] > 0 or sv[1] <= 1e-6 * sv[0]:
                raise EstimationError(
                    f"the control points and GNSS centres {ids} are collinear or too few in the {what} frame "
                    f"(singular values {np.round(sv, 6).tolist()}): the rotation about their line is "
                    "undetermined; add control off that line")
    ao = AbsoluteOrientation.from_points(model, ground, ids=ids, robust=robust)
    s, R, T = ao.scale, ao.rotation, ao.translation
    poses = tuple(Pose(p.image, p.camera, s * R @ p.position + T, _orthonormal(R @ p.rotation)) for p in block.poses)
    pts = s * block.points @ R.T + T
    pred = s * model @ R.T + T
    return GroundBlock(poses=poses, point_ids=block.point_ids, points=pts, similarity=ao,
                       control_ids=tuple(c_ids), gnss_images=tuple(g_imgs),
                       control_residuals=(pred - ground)[: len(c_ids)].reshape(-1, 3),
                       gnss_residuals=(pred - ground)[len(c_ids):].reshape(-1, 3))


# --------------------------------------------------------------------------- input
def triangulate_tracks(cameras: Mapping[str, Camera], poses: Sequence[Pose], tracks: Tracks, *,
                       options: IndependentOptions | None = None
                       ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Intersect every track through known poses (linear multi-ray intersection with rejection).

    The same intersection as the last step of :func:`independent_models`: each round drops the
    worst observation of every track whose normalised image residual exceeds
    ``options.max_residual_sigma`` times the robust scale; points with fewer than two accepted rays
    or a largest intersection angle under ``options.min_angle_rad`` are NaN.

    Parameters
    ----------
    cameras : mapping camera id -> Camera
    poses : sequence of Pose
        One per image of ``tracks`` (same order), ground frame.
    tracks : Tracks

    Returns
    -------
    points : (P, 3) float64
        Ground frame; NaN where a track could not be intersected.
    used : (M,) bool
        Observations accepted.

    Raises
    ------
    InvalidInputError
        ``poses`` do not match ``tracks.images``, or a pose names an unknown camera.
    """
    opts = options or IndependentOptions()
    if [p.image for p in poses] != list(tracks.images):
        raise InvalidInputError(f"poses name images {[p.image for p in poses][:4]}, the tracks "
                                f"{list(tracks.images)[:4]}: one pose per image, in the tracks' order")
    camera_of = [p.camera for p in poses]
    cams = _cameras_of_images(cameras, camera_of, tracks)
    points, _n, _res, used = _multiray(poses, cams, tracks, _photo_mm(cams, camera_of, tracks), opts)
    return points, used


def _cameras_of_images(cameras: Mapping[str, Camera], camera_of: Sequence[str], tracks: Tracks) -> list[Camera]:
    if isinstance(camera_of, str):
        raise InvalidInputError(f"`camera_of` must be a sequence of camera ids, one per image; got the string "
                                f"{camera_of!r}")
    ids = list(camera_of)
    if len(ids) != len(tracks.images):
        raise ShapeError(f"`camera_of` must name one camera per image ({len(tracks.images)}); got {len(ids)}",
                         actual_shape=(len(ids),), expected_shape=(len(tracks.images),))
    out = []
    for name, cid in zip(tracks.images, ids, strict=True):
        if cid not in cameras:
            raise InvalidInputError(f"image {name!r} names camera {cid!r}, which is not given "
                                    f"(cameras: {sorted(cameras)})")
        out.append(cameras[cid])
    return out


def _photo_mm(cams: list[Camera], camera_of: Sequence[str], tracks: Tracks) -> NDArray[np.float64]:
    """(M, 2) photo coordinates of every observation, distortion removed, mm."""
    out = np.empty((tracks.n_obs, 2))
    ids = np.array(list(camera_of), dtype=object)
    for cid in sorted(set(camera_of)):
        imgs = np.flatnonzero(ids == cid)
        m = np.isin(tracks.obs_image, imgs)
        if m.any():
            out[m] = cams[int(imgs[0])].photo_from_pixel(tracks.obs_pixel[m])
    return out


def _obs_by_image(tracks: Tracks, n: int) -> list[tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """Per image: (track indices ascending, their observation rows)."""
    order = np.argsort(tracks.obs_image, kind="stable")   # stable: rows stay sorted by track
    bounds = np.concatenate([[0], np.cumsum(np.bincount(tracks.obs_image, minlength=n))])
    out = []
    for i in range(n):
        rows = order[bounds[i]:bounds[i + 1]]
        out.append((tracks.obs_point[rows], rows))
    return out


def _covisibility(tracks: Tracks, n: int) -> NDArray[np.int64]:
    """(n, n) number of tracks seen in both images (0 on the diagonal)."""
    A = sparse.csr_matrix((np.ones(tracks.n_obs), (tracks.obs_image, tracks.obs_point)),
                          shape=(n, max(tracks.n_points, 1)))
    C = np.asarray((A @ A.T).toarray()).round().astype(np.int64)
    np.fill_diagonal(C, 0)
    return C


# --------------------------------------------------------------------------- pairs
def _components_text(adj: NDArray[np.bool_], names: Sequence[str]) -> tuple[int, str]:
    ncomp, lab = connected_components(sparse.csr_matrix(adj.astype(np.int8)), directed=False)
    groups = sorted(sorted(names[int(i)] for i in np.flatnonzero(lab == c)) for c in range(ncomp))
    return ncomp, "; ".join(str(g) for g in groups)


def _spanning_tree(counts: NDArray[np.int64], names: Sequence[str], min_common: int) -> list[tuple[int, int]]:
    """Maximum spanning tree (Prim) over edges with >= ``min_common`` common tracks, in join order.

    Ties are broken by image name, so the tree does not depend on the order of the images.
    """
    n = len(names)
    adj = counts >= min_common
    ncomp, text = _components_text(adj, names)
    if ncomp > 1:
        _, lab = connected_components(sparse.csr_matrix(adj.astype(np.int8)), directed=False)
        W = np.where(lab[:, None] != lab[None, :], counts, 0)
        i, j = (int(v) for v in np.unravel_index(int(np.argmax(W)), W.shape))
        best = (f"; the strongest link between them is {names[i]!r}-{names[j]!r} with {int(W[i, j])} common "
                "points" if W[i, j] > 0 else "; no track links them")
        raise StereoError(f"the image graph is disconnected (a model needs >= {min_common} common points): "
                          f"{ncomp} components {text}{best}")
    rank = np.empty(n, dtype=np.int64)
    rank[np.argsort(np.array(names, dtype=object), kind="stable")] = np.arange(n)
    # first pair: most common points, ties by the names' ranks
    iu, ju = np.triu_indices(n, 1)
    lo = np.minimum(rank[iu], rank[ju])
    hi = np.maximum(rank[iu], rank[ju])
    k = int(np.lexsort((hi, lo, -counts[iu, ju]))[0])
    a, b = int(iu[k]), int(ju[k])
    if rank[b] < rank[a]:
        a, b = b, a
    tree = [(a, b)]
    inside = np.zeros(n, dtype=bool)
    inside[[a, b]] = True
    best_w = np.full(n, -1, dtype=np.int64)
    best_from = np.full(n, -1, dtype=np.int64)

    def update(node: int) -> None:
        w = np.where(adj[node] & ~inside, counts[node], -1)
        better = (w > best_w) | ((w == best_w) & (w >= 0) & (rank[node] < rank[np.maximum(best_from, 0)]))
        best_w[better] = w[better]
        best_from[better] = node

    update(a)
    update(b)
    while not inside.all():
        cand = np.flatnonzero(~inside & (best_w >= 0))
        nxt = int(cand[np.lexsort((rank[cand], -best_w[cand]))[0]])
        tree.append((int(best_from[nxt]), nxt))
        inside[nxt] = True
        best_w[nxt] = -1
        update(nxt)
    return tree


def _given_tree(pairs: Sequence[tuple[int, int]], counts: NDArray[np.int64], names: Sequence[str],
                opts: IndependentOptions) -> list[tuple[int, int]]:
    n = len(names)
    prs: list[tuple[int, int]] = []
    for p in pairs:
        try:
            a, b = (int(v) for v in p)
        except (TypeError, ValueError) as err:
            raise InvalidInputError(f"each pair must be two image indices; got {p!r}") from err
        if not (0 <= a < n and 0 <= b < n) or a == b:
            raise InvalidInputError(f"pair {p!r}: image indices must be two different values in 0..{n - 1}")
        if counts[a, b] < opts.min_common:
            raise StereoError(f"pair {names[a]!r}-{names[b]!r} has {int(counts[a, b])} common points; "
                              f"at least {opts.min_common} are needed for a model")
        prs.append((a, b))
    if not prs:
        raise InvalidInputError("`pairs` is empty; give at least one pair or None for the spanning tree")
    adj = np.zeros((n, n), dtype=bool)
    for a, b in prs:
        adj[a, b] = adj[b, a] = True
    ncomp, text = _components_text(adj, names)
    if ncomp > 1:
        raise StereoError(f"the given pairs leave the image graph disconnected: {ncomp} components {text}")
    tree = [prs[0]]
    inside = np.zeros(n, dtype=bool)
    inside[list(prs[0])] = True
    rest = prs[1:]
    while not inside.all():
        for k, (a, b) in enumerate(rest):
            if inside[a] != inside[b]:
                tree.append((a, b) if inside[a] else (b, a))
                inside[[a, b]] = True
                del rest[k]
                break
    return tree


# --------------------------------------------------------------------------- final intersection
def _multiray(poses: Sequence[Pose], cams: list[Camera], tracks: Tracks, obs_mm: NDArray[np.float64],
              opts: IndependentOptions
              ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
    """Intersect every track with all its rays; reject large residuals; NaN where not possible."""
    P, M = tracks.n_points, tracks.n_obs
    img = tracks.obs_image
    pt = tracks.obs_point
    Rs = np.stack([p.rotation for p in poses])[img]               # (M, 3, 3)
    Cs = np.stack([p.position for p in poses])[img]               # (M, 3)
    f = np.array([c.focal_length_mm for c in cams])[img]
    pix = np.array([c.pixel_size_mm for c in cams])[img]
    v = np.column_stack([obs_mm, -f])
    d = np.einsum("mij,mj->mi", Rs, v)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    used = np.ones(M, dtype=bool)
    points = np.full((P, 3), np.nan)
    norm_res = np.zeros(M)
    res_px = np.zeros(M)
    for rnd in range(int(opts.max_rejection_rounds) + 1):
        n_rays = np.bincount(pt[used], minlength=P)
        angle = _max_angle(d, pt, used, P)
        solvable = (n_rays >= 2) & (angle >= max(opts.min_angle_rad, 1e-9))
        points = _solve_points(d, Cs, pt, used & solvable[pt], P, solvable)
        # image residuals of every observation whose point exists
        p = np.einsum("mji,mj->mi", Rs, points[pt] - Cs)          # R.T @ (X - C)
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]])
            res_px = np.linalg.norm(proj - obs_mm, axis=1) / pix
            res_px[p[:, 2] >= 0] = np.inf                          # behind the camera
        norm_res = res_px / tracks.obs_sigma_px
        live = used & solvable[pt]
        if rnd == int(opts.max_rejection_rounds) or not live.any():
            break
        fin = live & np.isfinite(norm_res)
        sc = robust_scale(norm_res[fin]) if fin.any() else 0.0
        thr = opts.max_residual_sigma * max(1.0, sc)
        worst = np.full(P, -1.0)
        np.maximum.at(worst, pt[live], np.where(np.isfinite(norm_res[live]), norm_res[live], 1e300))
        bad_pt = worst > thr
        if not bad_pt.any():
            break
        # drop the worst observation of each bad track
        cand = live & bad_pt[pt] & (np.where(np.isfinite(norm_res), norm_res, 1e300) >= worst[pt])
        first = np.zeros(M, dtype=bool)
        idx = np.flatnonzero(cand)
        _, u = np.unique(pt[idx], return_index=True)
        first[idx[u]] = True
        used &= ~first
    live = used & np.isfinite(points[pt]).all(axis=1)
    n_rays = np.bincount(pt[live], minlength=P).astype(np.int64)
    ok = n_rays >= 2
    points[~ok] = np.nan
    live &= ok[pt]
    sq = np.bincount(pt[live], weights=res_px[live] ** 2, minlength=P)
    with np.errstate(divide="ignore", invalid="ignore"):
        rp = np.where(ok, np.sqrt(sq / np.maximum(n_rays, 1)), np.nan)
    n_rays[~ok] = 0
    return points, n_rays, rp, live


def _max_angle(d: NDArray[np.float64], pt: NDArray[np.int64], used: NDArray[np.bool_], P: int
               ) -> NDArray[np.float64]:
    """(P,) largest angle between the used rays of each track (two sweeps: exact in a plane), rad."""
    M = len(pt)
    idx = np.flatnonzero(used)
    ref = np.full(P, -1, dtype=np.int64)
    # first used ray of each track
    _, u = np.unique(pt[idx], return_index=True)
    ref[pt[idx[u]]] = idx[u]
    angle = np.zeros(P)
    for _ in range(2):
        has = ref[pt] >= 0
        cosv = np.full(M, 1.0)
        sel = used & has
        cosv[sel] = np.clip(np.einsum("mi,mi->m", d[sel], d[ref[pt[sel]]]), -1.0, 1.0)
        ang = np.arccos(cosv)
        angle = np.zeros(P)
        np.maximum.at(angle, pt[sel], ang[sel])
        # the ray farthest from the reference becomes the next reference
        far = sel & (ang >= angle[pt])
        fi = np.flatnonzero(far)
        _, u = np.unique(pt[fi], return_index=True)
        ref[pt[fi[u]]] = fi[u]
    return angle


def _solve_points(d: NDArray[np.float64], C: NDArray[np.float64], pt: NDArray[np.int64], use: NDArray[np.bool_],
                  P: int, solvable: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Linear least squares: the point closest to all used rays of each solvable track."""
    out = np.full((P, 3), np.nan)
    if not solvable.any():
        return out
    dd = d[use]
    Mi = np.eye(3)[None] - dd[:, :, None] * dd[:, None, :]          # (m, 3, 3)
    A = np.zeros((P, 3, 3))
    b = np.zeros((P, 3))
    np.add.at(A, pt[use], Mi)
    np.add.at(b, pt[use], np.einsum("mij,mj->mi", Mi, C[use]))
    out[solvable] = np.linalg.solve(A[solvable], b[solvable][:, :, None])[:, :, 0]
    return out


# --------------------------------------------------------------------------- to_ground input
def _control_rows(block: ModelBlock, control: tuple[Sequence[str], ArrayLike] | None
                  ) -> tuple[list[str], NDArray[np.float64], NDArray[np.float64]]:
    if control is None:
        return [], np.zeros((0, 3)), np.zeros((0, 3))
    ids_in, xyz_in = control
    ids = [str(i) for i in ids_in]
    xyz = np.array(xyz_in, dtype=np.float64).reshape(-1, 3) if np.size(xyz_in) else np.zeros((0, 3))
    if xyz.shape != (len(ids), 3):
        raise ShapeError(f"control coordinates must have shape ({len(ids)}, 3), one row per id; got "
                         f"{np.shape(xyz_in)}", actual_shape=np.shape(xyz_in), expected_shape=(len(ids), 3))
    if len(set(ids)) != len(ids):
        raise InvalidInputError(f"duplicate control point ids: {sorted({i for i in ids if ids.count(i) > 1})}")
    index = {p: k for k, p in enumerate(block.point_ids)}
    unknown = [i for i in ids if i not in index]
    if unknown:
        raise InvalidInputError(f"control point(s) {unknown[:10]} are not tracks of the block")
    rows = np.array([index[i] for i in ids], dtype=np.int64)
    m = block.points[rows] if len(rows) else np.zeros((0, 3))
    ok = np.isfinite(m).all(axis=1)
    return [ids[k] for k in np.flatnonzero(ok).tolist()], m[ok], xyz[ok]


def _gnss_rows(block: ModelBlock, gnss: tuple[Sequence[str], ArrayLike] | None
               ) -> tuple[list[str], NDArray[np.float64], NDArray[np.float64]]:
    if gnss is None:
        return [], np.zeros((0, 3)), np.zeros((0, 3))
    imgs_in, pos_in = gnss
    imgs = [str(i) for i in imgs_in]
    pos = np.array(pos_in, dtype=np.float64).reshape(-1, 3) if np.size(pos_in) else np.zeros((0, 3))
    if pos.shape != (len(imgs), 3) or not np.isfinite(pos).all():
        raise ShapeError(f"GNSS positions must be finite with shape ({len(imgs)}, 3), one row per image; got "
                         f"{np.shape(pos_in)}", actual_shape=np.shape(pos_in), expected_shape=(len(imgs), 3))
    if len(set(imgs)) != len(imgs):
        raise InvalidInputError(f"duplicate GNSS image names: {sorted({i for i in imgs if imgs.count(i) > 1})}")
    index = {p.image: k for k, p in enumerate(block.poses)}
    unknown = [i for i in imgs if i not in index]
    if unknown:
        raise InvalidInputError(f"GNSS image(s) {unknown[:10]} are not images of the block")
    m = np.array([block.poses[index[i]].position for i in imgs]).reshape(-1, 3)
    return imgs, m, pos

