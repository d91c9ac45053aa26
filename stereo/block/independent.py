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
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from rectify.errors import (
    EstimationError,
    InvalidInputError,
    RectifyError,
    ShapeError,
    StereoError,
    WeakGeometryWarning,
)
from rectify.geometry.camera import Camera
from rectify.geometry.residuals import ResidualTable, rms
from rectify.geometry.robust import ROBUST_METHODS, robust_scale
from rectify.geometry.rotation import rot_z
from stereo.block.types import Pose, Tracks
from stereo.pair.absolute import AbsoluteOrientation, similarity_from_points
from stereo.pair.intersection import intersect
from stereo.relative import RelativeOrientation
from stereo.relative.solver import RelativeOptions
from stereo.relative.systems import get_system

logger = logging.getLogger(__name__)

__all__ = ["GroundBlock", "IndependentOptions", "ModelBlock", "ModelJoin", "independent_models", "to_ground",
           "triangulate_tracks"]


@dataclass(frozen=True)
class IndependentOptions:
    """Options of :func:`independent_models`.

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

    def __post_init__(self) -> None:
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
    models: list[_Model] = []
    sims: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []
    for k, (a, b) in enumerate(tree):
        model = _model(a, b, cams, tracks, obs_mm, per_image, opts)
        if k == 0:
            s, R, T = 1.0, np.eye(3), np.zeros(3)
            positions[a] = np.zeros(3)
            rotations[a] = model.rotation_left
            join = ModelJoin(names[a], names[b], model.n_relative, model.n_relative_outliers, model.sigma0_mm,
                             model.condition_number, 0, 0, 1.0, 0.0, 0.0, 0.0)
            keep = np.ones(len(model.tracks), dtype=bool)
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
                      obs_used=used, tree=tuple(tree), joins=tuple(joins), adjustment=adjustment)


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


# --------------------------------------------------------------------------- models
@dataclass(frozen=True, eq=False)
class _Model:
    tracks: NDArray[np.int64]            # (K,) track indices of the model points
    points: NDArray[np.float64]          # (K, 3) model frame
    rotation_left: NDArray[np.float64]
    rotation_right: NDArray[np.float64]
    base: NDArray[np.float64]            # (3,) unit, model frame
    covariance: NDArray[np.float64]      # (K, 3, 3) of the points for one pixel of image noise, model frame
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
           per_image: list[tuple[NDArray[np.int64], NDArray[np.int64]]], opts: IndependentOptions) -> _Model:
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
    return _Model(common[ok][good], inter.points[good], R1, R2, B, cov[good], len(common), int((~ok).sum()),
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
        return _Relative(ro.rotation_left, ro.rotation_right, ro.base, ok, ro.sigma0_mm, ro.condition_number)
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


def _join(model: _Model, left: str, right: str, centre: NDArray[np.float64], block: _BlockPoints,
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


def _rodrigues(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrix exp([w]x) of a rotation vector (3,), rad."""
    t = float(np.linalg.norm(w))
    K = _skew(w[None])[0]
    if t < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(t) / t * K + (1 - math.cos(t)) / (t * t) * K @ K


def _adjust_models(tree: Sequence[tuple[int, int]], models: Sequence[_Model],
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
        R = np.stack([_rodrigues(dp[k, 1:4]) @ R[k] for k in range(n_models)])
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

