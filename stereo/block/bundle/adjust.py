"""Bundle adjustment of a block of frame images.

:func:`adjust_bundle` estimates the exterior orientation of every image, the object points of the
tie-point tracks and, optionally, interior orientation parameters of the cameras (self-calibration)
from these observation groups, each with its own a-priori precision:

``image``
    Measured pixels of the tracks (residuals in pixels); sigma = ``Tracks.obs_sigma_px`` times the
    group sigma ``BundleOptions.image_sigma_px``.
``gnss``
    GNSS antenna positions (ground frame, m) with an optional lever arm in the camera frame.
``ins``
    Optional INS angles omega, phi, kappa (rad).
``control``
    Ground control points, full (x, y, z), height-only or plan-only. Check points are withheld:
    their coordinates are estimated from the image rays only and compared with the given ones.

The collinearity model is exactly :func:`stereo.block.types.project_pixel` (principal point and
Brown distortion in OpenCV's definition, :mod:`stereo.block.bundle.model`). The normal equations
are solved in Schur form (:mod:`stereo.block.bundle.solve`) with Levenberg-Marquardt damping.

Notes
-----
Robust estimation is iteratively reweighted least squares on standardised residuals
``u = v / (sigma s)`` with ``s`` the robust scale (:func:`rectify.geometry.robust.robust_scale`) of
``v / sigma`` in the group; plain least squares runs first until the corrections are below 1 %
of a standard deviation. An observation is flagged when its standardised residual
``|v| / (sigma0 sigma sqrt(r))`` (``r`` its redundancy number) exceeds
``BundleOptions.blunder_threshold`` or its robust weight is below 0.1.

Variance components (Foerstner): after convergence each group's variance factor
``v_k^T P_k v_k / r_k`` rescales its sigma, and the adjustment repeats until the factors are 1
within 1 %, in at most :data:`stereo.block.bundle.variance.VCE_MAX_ROUNDS` rounds and
``max_iterations`` iterations in all; a factor estimated from a redundancy below
:data:`stereo.block.bundle.variance.VCE_WARN_REDUNDANCY` is flagged. The group redundancies ``r_k``
are exact sums of the redundancy numbers ``r_i = 1 - p_i a_i^T Q a_i``, with Q from the inverse of
the reduced camera system and the per-point back-substitution (the robust weights:
:mod:`stereo.block.bundle.robust`).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError, ShapeError
from rectify.geometry.camera import Camera
from rectify.geometry.robust import ROBUST_METHODS, get_psi
from stereo.block.bundle import newton as bn
from stereo.block.bundle import solve as bs
from stereo.block.bundle.datum import datum_analysis
from stereo.block.bundle.model import INTERIOR_NAMES, camera_from_interior, interior_from_camera
from stereo.block.bundle.result import BundleResult
from stereo.block.bundle.robust import (
    check_robust_options,
    local_redundancy,
    m_covariance_factor,
    robust_scales,
    robust_update,
)
from stereo.block.bundle.systematic import check_modes, configure, pose_hat, systematic_estimates
from stereo.block.bundle.variance import VCE_FACTOR_BOUNDS, VCE_MAX_ROUNDS, VCE_MIN_REDUNDANCY, weak_components
from stereo.block.types import BlockControl, GnssObservations, Pose, Tracks, cameras_for

__all__ = ["BundleOptions", "COVARIANCE_MODES", "INTERIOR_NAMES", "adjust_bundle", "default_threads"]

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: what precision to compute: everything (poses, interior, points, redundancy numbers), poses only, nothing
COVARIANCE_MODES: tuple[str, ...] = ("full", "poses", "none")
#: observation groups: tie-point image coordinates, control/check-point image coordinates ("marks", measured by
#: hand or by a target detector with their own precision), GNSS centres, INS angles, control coordinates
GROUPS: tuple[str, ...] = ("image", "marks", "gnss", "ins", "control")
#: a free network's datum: the first image's pose and one coordinate of the second image's projection
#: centre are held by pseudo-observations of this relative sigma (times the distance of the two centres;
#: radians for the angles): seven minimum constraints, so the shape of the block is not constrained
FREE_NETWORK_RELATIVE_SIGMA = 1e-7
#: a free network iterates at least this often before it is declared not converged
FREE_NETWORK_MIN_ITERATIONS = 300
#: reweightings per IRLS stage (Huber, then the chosen psi) before the weights are frozen
IRLS_STAGE_ITERATIONS = 12
#: Levenberg-Marquardt: initial damping (relative to the diagonal of the normal matrix); divided by 10
#: after an accepted step, multiplied by 10 after a rejected one. Small, so a good start takes full
#: Gauss-Newton steps (1e-4 cost the synthetic benchmark blocks 3 extra iterations).
LM_INITIAL_DAMPING = 1e-8
#: converged also when the weighted sum of squares has settled (1e-8 relative) in an iteration whose
#: corrections were all below this many a-priori standard deviations (the benchmark's 49-image block
#: 7 -> 6 iterations)
SETTLED_STEP = 0.05
POSE_ELEMENTS: tuple[str, ...] = ("omega", "phi", "kappa", "x", "y", "z")
#: a point is determined by the images when at least this many of its rays are not flagged as blunders
MIN_RAYS_DETERMINED = 2


@dataclass(frozen=True)
class BundleOptions:
    """Options of :func:`adjust_bundle`.

    Parameters
    ----------
    image_sigma_px : float
        Group sigma of the image observations (multiplies ``Tracks.obs_sigma_px``), px.
    robust : str
        ``"none"`` or a psi function of :data:`rectify.geometry.robust.ROBUST_METHODS`.
    robust_groups : tuple of str
        Groups the robust weights apply to (``image``, ``gnss``, ``control``).
    self_calibrate : tuple of str
        Interior parameters estimated per camera, a subset of :data:`INTERIOR_NAMES`.
    variance_components : bool
        Estimate a variance factor per observation group (iteratively).
    max_iterations : int
        Limit of the Gauss-Newton/Levenberg-Marquardt iterations, over all variance-component rounds
        (a round that would need more is not run, or not kept: the solution of the round before is, with
        a warning).
    tolerance : float
        Converged when every correction is below ``tolerance`` times the unknown's a-priori
        standard deviation ``1 / sqrt(N_ii)``.
    blunder_threshold : float
        Flag an observation whose standardised residual exceeds this.
    covariance : str
        ``full`` (poses, interior, points, redundancy numbers), ``poses`` (poses and interior; points
        only at control and check points) or ``none``.
    free_network : bool
        Allow a block without control and GNSS: the datum is then set by seven minimum constraints
        (the first image's pose and the distance to the second image keep their initial values;
        :func:`_minimum_constraints`), as a pair's model frame. Such a block converges more slowly
        (its weak deformation modes are not damped by datum observations): it is given at least
        :data:`FREE_NETWORK_MIN_ITERATIONS` iterations.
    dense_limit : int
        Solve the reduced camera system with a dense Cholesky factorisation up to this size,
        with a sparse LU beyond (either replaced by a banded Cholesky, the images in reverse
        Cuthill-McKee order, when that needs at least 4 times fewer operations).
    gnss_drift : {"none", "shift", "shift-drift"}
        GNSS systematic unknowns per strip (:mod:`stereo.block.bundle.systematic`): none, a shift,
        a shift and a drift linear in time (needs the images' strips, and times for the drift).
    boresight_unknown : {"none", "block", "strip"}
        Boresight correction unknowns: none, one for the block, one per strip (needs INS angles).
    robust_algorithm, robust_scale, newton : str
        Seed 002's variants (:func:`stereo.block.bundle.robust.check_robust_options`, docs/robust.md).
    threads : int or None
        Threads of the model evaluation and the assembly of the normal equations (None: one; the
        work is many numpy operations on cache-sized pieces, and with two threads the 500-image
        benchmark block took 20 % more time, not less: the GIL is held between the operations).
        Used from ``stereo.block.bundle.solve.THREADS_MIN_OBSERVATIONS`` observations on. BLAS runs one thread,
        except in dense factorisations of reduced systems from
        ``stereo.block.bundle.solve.BLAS_THREADS_MIN_UNKNOWNS`` unknowns on, which get as many as BLAS is set to
        use (``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS``, else the CPU count).
    """

    image_sigma_px: float = 1.0
    robust: str = "none"
    robust_groups: tuple[str, ...] = ("image",)
    self_calibrate: tuple[str, ...] = ()
    variance_components: bool = False
    max_iterations: int = 50
    tolerance: float = 1e-4
    blunder_threshold: float = 4.0
    covariance: str = "full"
    free_network: bool = False
    dense_limit: int = 4000
    threads: int | None = None
    robust_algorithm: str = "reweighting"
    robust_scale: str = "first"
    newton: str = "full"
    gnss_drift: str = "none"
    boresight_unknown: str = "none"

    def __post_init__(self) -> None:
        check_modes(self.gnss_drift, self.boresight_unknown)
        def pos(name: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise InvalidInputError(f"BundleOptions.{name} must be a finite number > 0; got {v!r}")

        for name in ("image_sigma_px", "tolerance", "blunder_threshold"):
            pos(name)
        if self.robust not in ROBUST_METHODS:
            raise InvalidInputError(f"BundleOptions.robust must be one of {list(ROBUST_METHODS)}; got {self.robust!r}")
        bad = [g for g in self.robust_groups if g not in ("image", "gnss", "control")]
        if bad:
            raise InvalidInputError(f"BundleOptions.robust_groups: unknown group {bad[0]!r}; "
                                    "expected image, gnss, control")
        bad = [p for p in self.self_calibrate if p not in INTERIOR_NAMES]
        if bad:
            raise InvalidInputError(f"BundleOptions.self_calibrate: unknown parameter {bad[0]!r}; "
                                    f"expected a subset of {list(INTERIOR_NAMES)}")
        if len(set(self.self_calibrate)) != len(self.self_calibrate):
            raise InvalidInputError(f"BundleOptions.self_calibrate has duplicates: {self.self_calibrate!r}")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int)
                                         or self.threads < 1):
            raise InvalidInputError(f"BundleOptions.threads must be None or an integer >= 1; got {self.threads!r}")
        for name in ("max_iterations", "dense_limit"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"BundleOptions.{name} must be an integer >= 1; got {v!r}")
        check_robust_options(self.robust_algorithm, self.robust_scale, self.newton)
        if self.covariance not in COVARIANCE_MODES:
            raise InvalidInputError(f"BundleOptions.covariance must be one of {list(COVARIANCE_MODES)}; "
                                    f"got {self.covariance!r}")


# ---------------------------------------------------------------------------- main
def adjust_bundle(cameras: Mapping[str, Camera], poses: Sequence[Pose], tracks: Tracks, points: ArrayLike, *,
                  control: BlockControl | None = None, gnss: GnssObservations | None = None,
                  options: BundleOptions = BundleOptions(),
                  progress: Callable[[int, int], None] | None = None) -> BundleResult:
    """Adjust a block: poses, object points and optionally interior orientation.

    Parameters
    ----------
    cameras : mapping str -> Camera
        Interior orientation of each camera id named by the poses (initial values when
        self-calibrating).
    poses : sequence of Pose
        Initial exterior orientation of every image of ``tracks.images``.
    tracks : Tracks
        The image observations (pixels).
    points : (P, 3) array_like
        Initial object points, ground frame, m, in the order of ``tracks.point_ids``.
    control : BlockControl, optional
        Control and check points.
    gnss : GnssObservations, optional
        GNSS antenna positions and optional INS angles.
    options : BundleOptions
    progress : callable (done, total), optional
        Called after each iteration with (iteration, max_iterations).

    Returns
    -------
    BundleResult

    Raises
    ------
    InvalidInputError
        Inconsistent inputs (shapes, unknown ids or images, points behind cameras, tracks with
        fewer than two observations).
    EstimationError
        A datum defect (no control and no GNSS without ``free_network``) or a singular system.
    ConvergenceError
        No convergence within ``max_iterations``; names the worst observations.
    """
    prob, st0, info = _setup(cameras, poses, tracks, points, control, gnss, options)
    threads = options.threads if options.threads is not None else 1
    prob.blas_threads = default_threads()
    # below some 100 000 observations the pieces are too few and too small to gain from threads
    prob.threads = threads if len(prob.obs_pt) >= bs.THREADS_MIN_OBSERVATIONS else 1
    # our threads call BLAS on tiny matrices: one BLAS thread (large dense factorisations get more, bs.blas)
    with bs.controller().limit(limits=1, user_api="blas"):
        return _adjust(prob, st0, info, options, progress)


def default_threads() -> int:
    """BLAS threads of large dense factorisations: as many as BLAS is set to use, at most the usable CPUs."""
    blas = [int(i.get("num_threads", 1)) for i in bs.controller().info() if i.get("user_api") == "blas"]
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(max(blas, default=1), cpus))


def _adjust(prob: bs.Problem, st0: bs.State, info: _Info, options: BundleOptions,
            progress: Callable[[int, int], None] | None) -> BundleResult:
    factors = {g: 1.0 for g in GROUPS}
    psi = get_psi(options.robust) if options.robust != "none" else None
    st = st0
    total_it = 0
    limit = iteration_limit(options, info.free_network)
    rounds = VCE_MAX_ROUNDS if options.variance_components else 1
    robust_w = _ones_weights(prob)
    red = None
    notes: list[str] = []
    estimated_at: dict[str, float] = {}  # group -> redundancy of its latest variance-factor estimate
    scales_used: dict[str, float] = {}
    for rnd in range(rounds):
        budget = limit - total_it
        if budget <= 0:
            notes.append(f"variance components stopped at the iteration limit ({limit} iterations in all) after "
                         f"{rnd} round(s); the group factors of round {rnd} are kept")
            break
        kept = (st, robust_w, dict(factors))
        st, robust_w, it, converged = _iterate(prob, st, factors, psi, robust_w, options, progress, info,
                                               robust_from_start=rnd > 0, limit=budget, done=total_it,
                                               total=limit, must_converge=rnd == 0, scales_out=scales_used)
        total_it += it
        if not converged:
            # a later variance round ran out of the iteration budget: the solution of the previous round
            # (converged with its factors) is kept
            st, robust_w, old = kept
            factors.clear()
            factors.update(old)
            red = None
            converged = True
            notes.append(f"variance components stopped at the iteration limit ({limit} iterations in all) in round "
                         f"{rnd + 1}; the solution of round {rnd} and its group factors are kept")
            break
        if not options.variance_components:
            break
        red = _redundancy(prob, st, factors, robust_w, options, points_needed="all")
        new = {}
        for g in GROUPS:
            vtpv, r = red.vtpv[g], red.r[g]
            if r >= VCE_MIN_REDUNDANCY:
                new[g] = math.sqrt(vtpv / r)
                estimated_at[g] = r
        settled = all(abs(f - 1.0) < 0.01 for f in new.values())
        if settled:
            break
        if rnd == rounds - 1:
            worst = max(new, key=lambda g: abs(new[g] - 1.0))
            notes.append(f"variance components not settled after {rounds} rounds: the factor of group {worst} "
                         f"still changed by {100 * abs(new[worst] - 1.0):.0f} % in the last round")
            break
        if total_it >= limit:
            notes.append(f"variance components stopped at the iteration limit ({limit} iterations in all) after "
                         f"{rnd + 1} round(s); the factor of group {max(new, key=lambda g: abs(new[g] - 1.0))} "
                         f"would still change by {100 * max(abs(f - 1.0) for f in new.values()):.0f} %")
            break
        for g, f in new.items():
            # bounded: a group that fits (almost) exactly, e.g. error-free synthetic control, would
            # otherwise get a factor near 0 and an infinite weight
            factors[g] = min(max(factors[g] * f, VCE_FACTOR_BOUNDS[0]), VCE_FACTOR_BOUNDS[1])
        red = None
        logger.debug("variance components round %d: %s", rnd, new)
    want_points = "all" if options.covariance == "full" else ("control" if options.covariance == "poses" else "")
    if red is None or want_points != "all":
        red = _redundancy(prob, st, factors, robust_w, options, points_needed=want_points)
    if options.variance_components:
        notes.extend(weak_components(red.r, factors, estimated_at))
    mcov = None
    if psi is not None and red.Qcc is not None:
        # seed 002 eq. 2.28: the M-estimate's covariance, factor * the cofactors of the a-priori weights
        red_m = _redundancy(prob, st, factors, _ones_weights(prob), options, points_needed=want_points)
        mcov = (red_m, m_covariance_factor(psi, prob, red.res, _base_weights(prob, factors), robust_w,
                                           scales_used, red.n_unknowns))
    return _result(prob, st, info, factors, robust_w, red, options, total_it, converged, limit, notes,
                   estimated_at if options.variance_components else None, mcov=mcov)


def iteration_limit(options: BundleOptions, free_network: bool) -> int:
    """The iteration limit of an adjustment, over all its variance-component rounds: ``max_iterations``, at
    least :data:`FREE_NETWORK_MIN_ITERATIONS` for a free network (its weak deformation modes are damped by no
    datum observation, and the Levenberg-Marquardt damping of the nonlinear point depths makes them converge
    linearly)."""
    return max(options.max_iterations, FREE_NETWORK_MIN_ITERATIONS) if free_network else options.max_iterations


# ---------------------------------------------------------------------------- setup
@dataclass
class _Info:
    cam_ids: list[str]
    cams: list[Camera]
    images: tuple[str, ...]
    poses: list[Pose]
    tracks: Tracks
    control: BlockControl | None
    control_rows: NDArray[np.int64]      # rows of control used in the adjustment
    check_rows: NDArray[np.int64]
    check_pt: NDArray[np.int64]
    gnss: GnssObservations | None
    free_network: bool


def _setup(cameras: Mapping[str, Camera], poses: Sequence[Pose], tracks: Tracks, points: ArrayLike,
           control: BlockControl | None, gnss: GnssObservations | None, options: BundleOptions
           ) -> tuple[bs.Problem, bs.State, _Info]:
    if not isinstance(tracks, Tracks):
        raise InvalidInputError(f"`tracks` must be a Tracks; got {type(tracks).__name__}")
    if not isinstance(options, BundleOptions):
        raise InvalidInputError(f"`options` must be a BundleOptions; got {type(options).__name__}")
    poses = list(poses)
    if not all(isinstance(p, Pose) for p in poses):
        raise InvalidInputError("`poses` must be a sequence of Pose")
    by_name = {p.image: p for p in poses}
    if len(by_name) != len(poses):
        names = [p.image for p in poses]
        raise InvalidInputError(f"poses: duplicate image names {sorted({i for i in names if names.count(i) > 1})[:5]}")
    missing = [im for im in tracks.images if im not in by_name]
    if missing:
        raise InvalidInputError(f"tracks name image(s) without a pose: {missing[:5]}")
    ordered = [by_name[im] for im in tracks.images]
    extra = [p.image for p in poses if p.image not in set(tracks.images)]
    if extra:
        raise InvalidInputError(f"pose(s) of image(s) not in the tracks: {extra[:5]}")
    cams_of_pose = cameras_for(ordered, cameras)
    cam_ids = sorted({p.camera for p in ordered})
    cams = [cameras[c] for c in cam_ids]
    for cid, c in zip(cam_ids, cams, strict=True):
        if not isinstance(c, Camera):
            raise InvalidInputError(f"camera {cid!r} must be a rectify.geometry.camera.Camera; got {type(c).__name__}")
    del cams_of_pose
    cam_of_image = np.array([cam_ids.index(p.camera) for p in ordered], dtype=np.int64)
    n = len(ordered)
    P = tracks.n_points
    X = np.array(points, dtype=np.float64, copy=True)
    if X.shape != (P, 3):
        raise ShapeError(f"`points` must have shape ({P}, 3) (one row per track); got {X.shape}",
                         actual_shape=X.shape, expected_shape=(P, 3))
    if not np.isfinite(X).all():
        raise InvalidInputError(f"`points` must be finite; row {int(np.flatnonzero(~np.isfinite(X).all(1))[0])} is not")
    rays = tracks.rays_per_point()
    few = np.flatnonzero(rays < 2)
    if len(few):
        raise InvalidInputError(f"{len(few)} track(s) with fewer than 2 observations, e.g. "
                                f"{[tracks.point_ids[i] for i in few[:5]]} with {rays[few[:5]].tolist()}")
    ppi = tracks.points_per_image()
    sparse_img = np.flatnonzero(ppi < 3)
    if len(sparse_img):
        raise InvalidInputError(f"image(s) with fewer than 3 observations: "
                                f"{[(tracks.images[i], int(ppi[i])) for i in sparse_img[:5]]}")
    counts = rays.astype(np.int64)
    starts = (np.cumsum(counts) - counts).astype(np.int64)
    sel = np.array([INTERIOR_NAMES.index(p) for p in options.self_calibrate], dtype=np.int64)
    prob = bs.Problem(
        n_images=n, cam_of_image=cam_of_image,
        pixel_size=np.array([c.pixel_size_mm for c in cams]),
        centre=np.array([[(c.width - 1) / 2.0, (c.height - 1) / 2.0] for c in cams]),
        sel=sel, obs_img=tracks.obs_image.copy(), obs_pt=tracks.obs_point.copy(), obs_px=tracks.obs_pixel.copy(),
        obs_sigma=tracks.obs_sigma_px * options.image_sigma_px, pt_start=starts, pt_count=counts,
        dense_limit=options.dense_limit)
    st = bs.State(angles=np.array([p.angles for p in ordered]).reshape(n, 3),
                  centres=np.array([p.position for p in ordered]).reshape(n, 3),
                  interior=np.array([interior_from_camera(c) for c in cams]), points=X)
    img_index = {im: i for i, im in enumerate(tracks.images)}
    pt_index = {pid: i for i, pid in enumerate(tracks.point_ids)}
    control_rows = check_rows = check_pt = np.zeros(0, np.int64)
    if control is not None:
        if not isinstance(control, BlockControl):
            raise InvalidInputError(f"`control` must be a BlockControl; got {type(control).__name__}")
        unknown = [i for i in control.ids if i not in pt_index]
        if unknown:
            raise InvalidInputError(f"control point id(s) not in the tracks: {unknown[:5]}")
        cpt = np.array([pt_index[i] for i in control.ids], dtype=np.int64)
        used = ~control.check
        control_rows = np.flatnonzero(used).astype(np.int64)
        check_rows = np.flatnonzero(control.check).astype(np.int64)
        check_pt = cpt[check_rows]
        sig = control.used_sigma()
        prob.c_pt = cpt[control_rows]
        prob.c_xyz = control.xyz[control_rows].copy()
        prob.c_sigma = sig[control_rows]
    if gnss is not None:
        if not isinstance(gnss, GnssObservations):
            raise InvalidInputError(f"`gnss` must be a GnssObservations; got {type(gnss).__name__}")
        unknown = [i for i in gnss.images if i not in img_index]
        if unknown:
            raise InvalidInputError(f"GNSS image(s) not in the tracks: {unknown[:5]}")
        gi = np.array([img_index[i] for i in gnss.images], dtype=np.int64)
        prob.g_img, prob.g_pos, prob.g_sigma, prob.lever = gi, gnss.position.copy(), gnss.sigma_m.copy(), \
            gnss.lever_arm_m
        if gnss.angles is not None and gnss.sigma_rad is not None:
            prob.i_img, prob.i_ang, prob.i_sigma = gi.copy(), gnss.angles.copy(), gnss.sigma_rad.copy()
    free = False
    has_plan = int(np.sum(np.isfinite(prob.c_sigma[:, 0]))) if len(prob.c_pt) else 0
    has_height = int(np.sum(np.isfinite(prob.c_sigma[:, 2]))) if len(prob.c_pt) else 0
    if gnss is not None:  # full covariances, systematic unknowns (nothing when neither is asked for)
        configure(prob, st, gnss, gnss_drift=options.gnss_drift, boresight=options.boresight_unknown,
                  n_plan=has_plan, n_height=has_height)
    elif options.gnss_drift != "none" or options.boresight_unknown != "none":
        raise InvalidInputError("GNSS drift or boresight unknowns need GNSS/INS observations; got none")
    if len(prob.g_img) < 3 and (has_plan < 2 or has_height < 3):
        if prob.pose_model is not None:
            raise EstimationError(f"datum defect: {len(prob.g_img)} GNSS positions, {has_plan} plan and {has_height} "
                                  "height control points; a free network takes no GNSS covariance or systematic "
                                  "unknowns")
        if not options.free_network:
            raise EstimationError(
                f"datum defect: {len(prob.g_img)} GNSS positions, {has_plan} plan and {has_height} height control "
                "points cannot fix shift, rotation and scale of the block; give control points (>= 2 plan, >= 3 "
                "height) or GNSS positions (>= 3 images), or adjust a free network (--free-network)")
        free = True
        if prob.lever is not None:
            raise InvalidInputError("a free network (--free-network) with a GNSS lever arm is not supported; give no "
                                    "lever arm")
        _minimum_constraints(prob, st)
    # points in front of the cameras at the start
    lin = bs.evaluate(prob, st, jacobian=False)
    behind = np.flatnonzero(~(lin.res.depth > 0))
    if len(behind):
        i = int(behind[0])
        raise InvalidInputError(f"{len(behind)} observation(s) with the point behind the camera at the start, e.g. "
                                f"point {tracks.point_ids[tracks.obs_point[i]]!r} in image "
                                f"{tracks.images[tracks.obs_image[i]]!r} (depth {lin.res.depth[i]:.4g} m)")
    prob.obs_mark = np.isin(prob.obs_pt, np.concatenate([prob.c_pt, check_pt]))
    info = _Info(cam_ids, cams, tracks.images, ordered, tracks, control, control_rows, check_rows, check_pt, gnss,
                 free)
    return prob, st, info


def _minimum_constraints(prob: bs.Problem, st: bs.State) -> None:
    """Hold the datum of a free network with seven minimum constraints (the pair's model frame).

    Image 0 keeps its three angles and its projection centre; image 1 keeps the coordinate of its
    projection centre along which it lies farthest from image 0 (the scale). The pseudo-observations
    have sigma :data:`FREE_NETWORK_RELATIVE_SIGMA` times the distance of the two centres (metres) or
    times one (radians); the other two coordinates of image 1 get a sigma 1e12 times larger (free).
    """
    base = st.centres[1] - st.centres[0]
    d = float(np.linalg.norm(base))
    if not d > 0:
        raise EstimationError("free network: the first two images have the same projection centre; the scale "
                              "of the block is undefined")
    s = FREE_NETWORK_RELATIVE_SIGMA * d
    sig1 = np.full(3, s * 1e12)
    sig1[int(np.argmax(np.abs(base)))] = s
    prob.g_img = np.concatenate([prob.g_img, [0, 1]]).astype(np.int64)
    prob.g_pos = np.vstack([prob.g_pos, st.centres[:2]])
    prob.g_sigma = np.vstack([prob.g_sigma, np.full(3, s), sig1])
    prob.i_img = np.concatenate([prob.i_img, [0]]).astype(np.int64)
    prob.i_ang = np.vstack([prob.i_ang.reshape(-1, 3), st.angles[:1]])
    prob.i_sigma = np.vstack([prob.i_sigma.reshape(-1, 3), np.full((1, 3), FREE_NETWORK_RELATIVE_SIGMA)])


# ---------------------------------------------------------------------------- iterations
def _ones_weights(prob: bs.Problem) -> bs.Weights:
    return bs.Weights(np.ones((len(prob.obs_pt), 2)), np.ones((len(prob.g_img), 3)), np.ones((len(prob.i_img), 3)),
                      np.ones((len(prob.c_pt), 3)))


def _image_factor(prob: bs.Problem, factors: Mapping[str, float]) -> F64:
    """(M,) variance factor of each image observation: the tie points' or the control marks' group."""
    mark = prob.obs_mark if len(prob.obs_mark) == len(prob.obs_pt) else np.zeros(len(prob.obs_pt), bool)
    return np.where(mark, factors["marks"], factors["image"])


def _base_weights(prob: bs.Problem, factors: Mapping[str, float]) -> bs.Weights:
    si = prob.obs_sigma * _image_factor(prob, factors)
    wi = np.repeat((1.0 / si ** 2)[:, None], 2, axis=1)
    wg = 1.0 / (prob.g_sigma * factors["gnss"]) ** 2
    wn = 1.0 / (prob.i_sigma * factors["ins"]) ** 2
    wc = 1.0 / (prob.c_sigma * factors["control"]) ** 2  # inf sigma -> 0
    return bs.Weights(wi, wg, wn, wc)


def _combine(a: bs.Weights, b: bs.Weights) -> bs.Weights:
    return bs.Weights(a.image * b.image, a.gnss * b.gnss, a.ins * b.ins, a.control * b.control)


def _iterate(prob: bs.Problem, st: bs.State, factors: Mapping[str, float], psi: object | None,
             robust_w: bs.Weights, options: BundleOptions, progress: Callable[[int, int], None] | None,
             info: _Info, *, robust_from_start: bool, limit: int, done: int = 0, total: int | None = None,
             must_converge: bool = True, scales_out: dict[str, float] | None = None
             ) -> tuple[bs.State, bs.Weights, int, bool]:
    """One adjustment with fixed variance factors: at most ``limit`` iterations (``done`` of ``total`` used
    before, for the progress callback). Not converged within the limit: :class:`ConvergenceError` when
    ``must_converge``, else the last state with ``converged`` False."""
    base = _base_weights(prob, factors)
    dense = prob.n_c <= options.dense_limit
    banded = bs.use_banded(prob)
    mu = LM_INITIAL_DAMPING
    robust_on = psi is not None and robust_from_start
    frozen = False
    phase_it = 0
    prev_cost = math.inf
    settled = False
    # a redescending psi starts from Huber's (convex) solution
    cur_psi = psi if psi is None or robust_from_start or getattr(psi, "name", "") == "huber" else get_psi("huber")
    converged = False
    it = 0
    w = _combine(base, robust_w)
    nstep = math.inf
    nobs = 2 * len(prob.obs_pt) + prob.g_pos.size + prob.i_ang.size + int(np.isfinite(prob.c_sigma).sum())
    rbar = max(nobs - prob.n_c - 3 * prob.n_points, 1) / nobs
    scales: dict[str, float] | None = None
    rloc = local_redundancy(prob)
    flat, last_cost = 0, math.inf
    total = total if total is not None else limit
    lin: bs.Linear | None = None
    refine = False
    kept: bn.Frozen | None = None
    modres = psi is not None and options.robust_algorithm == "modified-residuals"
    stage_len = bn.MODIFIED_RESIDUALS_STAGE_ITERATIONS if modres else IRLS_STAGE_ITERATIONS
    for it in range(1, limit + 1):
        if lin is None:
            lin = bs.evaluate(prob, st, jacobian=True)
        dw = 0.0
        if robust_on:
            if scales is None or options.robust_scale == "weighted-median":  # eq. 2.29 from the 2nd reweighting
                scales = robust_scales(lin.res, base, options.robust_groups, rloc, rbar,
                                       weights=None if scales is None else robust_w, psi=cur_psi)
            new_rw = robust_update(cur_psi, lin.res, base, scales, rloc, rbar, robust_w)
            dw = max(float(np.max(np.abs(new_rw.image - robust_w.image), initial=0.0)),
                     float(np.max(np.abs(new_rw.gnss - robust_w.gnss), initial=0.0)),
                     float(np.max(np.abs(new_rw.control - robust_w.control), initial=0.0)))
            robust_w = new_rw
            w = _combine(base, robust_w)
        cost = lin.res.cost(w)
        accepted = False
        for _ in range(12):
            xc, xp, nstep, kept = bn.step(prob, lin, w, base, robust_w, mu, dense=dense, banded=banded, frozen=kept,
                                          modified_residuals_=modres and robust_on,
                                          modified_newton=options.newton == "modified")
            trial = bs.apply_step(prob, st, xc, xp)
            if refine:
                trial = bs.refine_points(prob, trial, w)
            # with the Jacobians: an accepted trial is the next iteration's linearisation
            tlin = bs.evaluate(prob, trial, jacobian=True)
            tres = tlin.res
            tcost = tres.cost(w) if (tres.depth > 0).all() else math.inf
            if tcost <= cost * (1 + 1e-12) or nstep < options.tolerance:
                st, lin = trial, tlin
                mu = max(mu / 10.0, 1e-10)
                accepted = True
                break
            mu *= 10.0
            kept = None  # the modified Newton-Raphson refactorises at the current point
            # a rejected step: from now on the points are intersected again after every camera step
            refine = True
        if progress is not None:
            progress(done + it, total)
        logger.debug("bundle iteration %d: cost %.12g, step %.3g sd, mu %.1e, weights change %.3g",
                     it, cost, nstep, mu, dw)
        if not accepted:
            break
        # settled: the corrections are below the tolerance, or (with the weights unchanged) the weighted
        # sum of squares has changed by at most 1e-8 relative in each of three iterations -- a weakly
        # determined unknown, such as the depth of a two-ray point with a small intersection angle, can
        # keep creeping by a few of its a-priori standard deviations without changing any residual --
        # or in one iteration whose corrections were all below SETTLED_STEP standard deviations (in the
        # weak modes of a block Gauss-Newton converges linearly, by a factor of some 0.2 per iteration:
        # what is left is a small fraction of a standard deviation and changes no residual)
        flat = flat + 1 if dw == 0.0 and abs(last_cost - cost) <= 1e-8 * max(cost, 1e-300) else 0
        last_cost = cost
        if psi is not None and not robust_on and not frozen and (nstep < 1e-2 or flat >= 3):
            robust_on, flat = True, 0  # least squares has settled: start reweighting
            continue
        if robust_on:
            phase_it += 1
            settled = (nstep < 1e-2 and dw < 1e-2) or (not modres and abs(prev_cost - cost) <= 1e-5 * cost
                                                          and dw < 0.05)
            prev_cost = cost
        if robust_on and (settled or phase_it >= stage_len):
            phase_it = 0
            if cur_psi is not psi:
                cur_psi = psi  # Huber has settled: switch to the redescending psi
                continue
            robust_on, frozen, flat = False, True, 0  # weights settled: converge with them fixed
        if (nstep < options.tolerance or flat >= 3 or (flat >= 1 and nstep < SETTLED_STEP)) and (psi is None or frozen):
            converged = True
            break
    if not converged and must_converge:
        res = bs.evaluate(prob, st, jacobian=False).res
        vn = np.linalg.norm(res.image, axis=1)
        worst = np.argsort(-vn)[:3]
        tr = info.tracks
        names = ", ".join(f"point {tr.point_ids[tr.obs_point[i]]!r} in {tr.images[tr.obs_image[i]]!r} "
                          f"{vn[i]:.3g} px" for i in worst)
        why = " (a free network's)" if total > options.max_iterations else " (--max-iterations)"
        raise ConvergenceError(f"bundle adjustment did not converge in {done + it} iterations, the limit{why}; "
                               f"last correction {nstep:.3g} standard deviations; largest residuals: {names}",
                               iterations=done + it)
    if scales_out is not None and scales:
        scales_out.update(scales)
    return st, robust_w, it, converged


# ---------------------------------------------------------------------------- precision
@dataclass
class _Red:
    vtpv: dict[str, float]
    r: dict[str, float]
    n: dict[str, int]
    Qcc: F64 | None
    Qpp: F64 | None                  # (P, 3, 3) or None
    Qpp_sel: dict[int, F64]          # point index -> 3x3 for control/check points
    r_img: F64                       # (M, 2)
    r_ctrl: F64                      # (k, 3)
    r_gnss: F64                      # (g, 3)
    res: bs.Residuals
    w: bs.Weights
    ne: bs.Normal | None
    n_unknowns: int


def _redundancy(prob: bs.Problem, st: bs.State, factors: Mapping[str, float], robust_w: bs.Weights,
                options: BundleOptions, *, points_needed: str) -> _Red:
    """Residuals, weights, cofactors and redundancy numbers at the solution."""
    base = _base_weights(prob, factors)
    w = _combine(base, robust_w)
    lin = bs.evaluate(prob, st, jacobian=bool(points_needed or options.variance_components))
    res = lin.res
    M = len(prob.obs_pt)
    u = prob.n_c + 3 * prob.n_points
    r_img = np.full((M, 2), np.nan)
    r_ctrl = np.full((len(prob.c_pt), 3), np.nan)
    r_gnss = np.full((len(prob.g_img), 3), np.nan)
    Qcc = Qpp = None
    Qsel: dict[int, F64] = {}
    ne = None
    if points_needed or options.variance_components:
        dense = prob.n_c <= options.dense_limit
        ne = bs.normal(prob, lin, w, 0.0, dense=dense)
        Qcc = bs.inverse_reduced(ne.S, blas_threads=prob.blas_threads)
        if points_needed == "all":
            pts = np.arange(prob.n_points, dtype=np.int64)
        else:
            pts = np.unique(prob.c_pt)
        Qp, T, obs = bs.track_cofactors(prob, ne, Qcc, pts)
        if points_needed == "all":
            Qpp = Qp
            # redundancy numbers of the image observations
            Jc, Jp = lin.Jc, lin.Jp
            cidx = ne.cidx
            Qii = Qcc[cidx[:, :, None], cidx[:, None, :]]
            h = np.einsum("mri,mij,mrj->mr", Jc, Qii, Jc)
            h -= 2 * np.einsum("mri,mia,mra->mr", Jc, T, Jp)
            h += np.einsum("mra,mab,mrb->mr", Jp, Qpp[prob.obs_pt], Jp)
            r_img = np.clip(1.0 - w.image * h, 0.0, 1.0)
        for k, p in enumerate(pts):
            Qsel[int(p)] = Qp[k]
        if len(prob.c_pt):
            qc = np.array([np.diag(Qsel[int(p)]) for p in prob.c_pt])
            r_ctrl = np.where(w.control > 0, np.clip(1.0 - w.control * qc, 0.0, 1.0), np.nan)
        if len(prob.g_img):
            hg = pose_hat(prob, Qcc, prob.g_img, lin.Jg, lin.Jgs)
            r_gnss = np.clip(1.0 - w.gnss * hg, 0.0, 1.0)
    mk = prob.obs_mark[:, None] if len(prob.obs_mark) == M else np.zeros((M, 1), bool)
    vi = w.image * res.image ** 2
    vtpv = {"image": float(np.sum(np.where(mk, 0.0, vi))), "marks": float(np.sum(np.where(mk, vi, 0.0))),
            "gnss": float(np.sum(w.gnss * res.gnss ** 2)),
            "ins": float(np.sum(w.ins * res.ins ** 2)), "control": float(np.sum(w.control * res.control ** 2))}
    # observations with a robust weight below 0.1 count as rejected
    used_img = (w.image > 0) & (robust_w.image >= 0.1)
    nobs = {"image": int(np.sum(used_img & ~mk)), "marks": int(np.sum(used_img & mk)),
            "gnss": int(np.sum((w.gnss > 0) & (robust_w.gnss >= 0.1))), "ins": int(np.sum(w.ins > 0)),
            "control": int(np.sum((w.control > 0) & (robust_w.control >= 0.1)))}
    r_tot = sum(nobs.values()) - u
    r: dict[str, float] = {}
    for g in GROUPS:
        r[g] = nobs[g] * r_tot / max(sum(nobs.values()), 1)  # proportional approximation
    if Qcc is not None:
        if points_needed == "all":
            keep = robust_w.image >= 0.1
            r["image"] = float(np.sum(r_img[keep & ~mk]))
            r["marks"] = float(np.sum(r_img[keep & mk]))
        if len(prob.c_pt):
            r["control"] = float(np.nansum(r_ctrl))
        if len(prob.g_img):
            r["gnss"] = float(np.sum(r_gnss[(w.gnss > 0) & (robust_w.gnss >= 0.1)]))
        if len(prob.i_img):
            pidx = 6 * prob.i_img[:, None] + np.arange(3)
            qi = Qcc[pidx, pidx] if lin.Ji is None else pose_hat(prob, Qcc, prob.i_img, lin.Ji, lin.Jis)
            r["ins"] = float(np.sum(np.clip(1.0 - w.ins * qi, 0.0, 1.0)))
        if points_needed != "all":
            r["image"] = r_tot - r["control"] - r["gnss"] - r["ins"] - r["marks"]
    return _Red(vtpv, r, nobs, Qcc, Qpp, Qsel, r_img, r_ctrl, r_gnss, res, w, ne, u)


def _result(prob: bs.Problem, st: bs.State, info: _Info, factors: Mapping[str, float], robust_w: bs.Weights,
            red: _Red, options: BundleOptions, iterations: int, converged: bool, limit: int,
            notes: Sequence[str], estimated: dict[str, float] | None = None, *,
            mcov: tuple[_Red, float] | None = None) -> BundleResult:
    n, P = prob.n_images, prob.n_points
    res, w = red.res, red.w
    r_tot = sum(red.n.values()) - red.n_unknowns
    vtpv = sum(red.vtpv.values())
    s0 = math.sqrt(vtpv / r_tot) if r_tot > 0 else float("nan")
    s0v = s0 ** 2 if math.isfinite(s0) else 1.0
    qsrc, s0q = (red, s0v) if mcov is None else mcov  # robust: eq. 2.28's factor on the a-priori cofactors
    present = {"image": True, "marks": bool(len(prob.obs_mark) and prob.obs_mark.any()),
               "gnss": len(prob.g_img) > 0 and not info.free_network,
               "ins": len(prob.i_img) > (1 if info.free_network else 0),
               "control": len(prob.c_pt) > 0}
    sigma0_groups = {g: (math.sqrt(red.vtpv[g] / red.r[g]) if red.r[g] > 0 else float("nan"))
                     for g in GROUPS if present[g]}
    # poses
    poses = []
    Rm = bs.rotations(st.angles)
    for i, p in enumerate(info.poses):
        poses.append(Pose(p.image, p.camera, st.centres[i], Rm[i]))
    names = [f"{p.image}.{e}" for p in info.poses for e in POSE_ELEMENTS]
    names += [f"{c}.{q}" for c in info.cam_ids for q in options.self_calibrate]
    sys_names, sys_val, sys_std = systematic_estimates(prob, st, red.Qcc, s0v)
    names += list(sys_names)
    pose_cov = np.full((n, 6, 6), np.nan)
    corr = np.zeros((0, 0))
    interior_std: dict[str, dict[str, float]] = {c: {} for c in info.cam_ids}
    if qsrc.Qcc is not None:
        C = s0q * qsrc.Qcc
        blk = np.arange(6 * n).reshape(n, 6)
        pose_cov = C[blk[:, :, None], blk[:, None, :]]
        sd = np.sqrt(np.clip(np.diag(C), 0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = C / np.outer(sd, sd)
        for q, cid in enumerate(info.cam_ids):
            for k, name in enumerate(options.self_calibrate):
                interior_std[cid][name] = float(sd[6 * n + prob.c * q + k])
    pose_std = np.sqrt(np.clip(np.diagonal(pose_cov, axis1=1, axis2=2), 0, None))
    pose_std[~np.isfinite(pose_std)] = np.nan
    cams = {cid: camera_from_interior(c, st.interior[q], interior_std[cid])
            for q, (cid, c) in enumerate(zip(info.cam_ids, info.cams, strict=True))}
    point_cov = None if qsrc.Qpp is None else s0q * qsrc.Qpp
    point_std = np.full((P, 3), np.nan)
    if point_cov is not None:
        point_std = np.sqrt(np.clip(np.diagonal(point_cov, axis1=1, axis2=2), 0, None))
    else:
        for j, qj in qsrc.Qpp_sel.items():
            point_std[j] = np.sqrt(np.clip(np.diag(s0q * qj), 0, None))
    # image observations: standardised residuals, flags
    sig = (prob.obs_sigma * _image_factor(prob, factors))[:, None]
    s0g = np.where(prob.obs_mark, sigma0_groups.get("marks", s0), sigma0_groups.get("image", s0))[:, None]
    # the larger of the a-priori and a-posteriori sigma, per group
    s0i = np.where(np.isfinite(s0g), np.maximum(s0g, 1.0), 1.0)
    rr = red.r_img if np.isfinite(red.r_img).all() else np.full_like(red.r_img, max(red.r["image"], 1e-9)
                                                                      / max(red.n["image"], 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        stdz = np.abs(res.image) / (s0i * sig * np.sqrt(np.maximum(rr, 1e-6)))
    low_w = robust_w.image < 0.1
    flagged = np.asarray(((stdz > options.blunder_threshold) | low_w).any(axis=1), dtype=bool)
    # rays not flagged per point: a point is determined by the images with two of them; a control point
    # all of whose rays were flagged is rejected (its ground coordinates then fix nothing but themselves)
    n_good = np.bincount(prob.obs_pt[~flagged], minlength=P)
    determined = np.asarray(np.isfinite(st.points).all(axis=1) & (n_good >= MIN_RAYS_DETERMINED), dtype=bool)
    # control
    tr = info.tracks
    n_rays = np.bincount(prob.obs_pt, minlength=P)
    ctrl_ok = n_good[prob.c_pt] > 0 if len(prob.c_pt) else np.zeros(0, bool)
    ctrl_rows = info.control_rows[ctrl_ok] if len(prob.c_pt) else info.control_rows
    ctrl_ids = tuple(info.control.ids[i] for i in ctrl_rows) if info.control is not None else ()
    rejected_control = tuple(info.control.ids[i] for i in info.control_rows[~ctrl_ok]) \
        if info.control is not None and len(prob.c_pt) else ()
    ctrl_res = np.where(np.isfinite(prob.c_sigma), res.control, np.nan)[ctrl_ok] if len(prob.c_pt) else \
        np.zeros((0, 3))
    flagged_control: list[str] = []
    if len(prob.c_pt):
        s0c = sigma0_groups.get("control", 1.0)
        s0c = max(s0c, 1.0) if math.isfinite(s0c) else 1.0
        rc = np.where(np.isfinite(red.r_ctrl), red.r_ctrl, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            zc = np.abs(res.control) * np.sqrt(w.control / np.maximum(rc, 1e-6)) / s0c
        bad = (np.nan_to_num(zc) > options.blunder_threshold).any(axis=1) | (robust_w.control < 0.1).any(axis=1)
        flagged_control = [info.control.ids[info.control_rows[i]] for i in np.flatnonzero(bad & ctrl_ok)
                           ] if info.control is not None else []
    # check points: not compared when every ray was flagged (the point is then determined by no measurement)
    check_ids: tuple[str, ...] = ()
    rejected_check: tuple[str, ...] = ()
    check_err = np.zeros((0, 3))
    check_std = np.zeros((0, 3))
    if info.control is not None and len(info.check_rows):
        chk_ok = n_good[info.check_pt] > 0
        rows, pts = info.check_rows[chk_ok], info.check_pt[chk_ok]
        check_ids = tuple(info.control.ids[i] for i in rows)
        rejected_check = tuple(info.control.ids[i] for i in info.check_rows[~chk_ok])
        check_err = st.points[pts] - info.control.xyz[rows]
        check_std = np.sqrt(point_std[pts] ** 2 + info.control.sigma_m[rows] ** 2)
    gn = len(prob.g_img) - (2 if info.free_network else 0)  # the minimum constraints are no GNSS
    datum_lines, groups, cond, warns = datum_analysis(prob, st, info.free_network, red.Qcc, red.ne, point_std,
                                                       s0v, info.control, info.control_rows, gn,
                                                       control_ok=ctrl_ok, determined=determined)
    by_id = {pid: k for k, pid in enumerate(tr.point_ids)}
    for cid in rejected_control:
        k = by_id[cid]
        warns.append(f"control point {cid} rejected: all {int(n_rays[k])} of its image observations were flagged "
                     "as blunders; it is not counted")
    for cid in rejected_check:
        k = by_id[cid]
        warns.append(f"check point {cid} rejected: all {int(n_rays[k])} of its image observations were flagged as "
                     "blunders; it is not compared")
    warns.extend(notes)
    if not converged:
        warns.append("the adjustment did not converge")
    return BundleResult(
        cameras=cams, poses=tuple(poses), point_ids=tr.point_ids, points=_ro(st.points), pose_std=_ro(pose_std),
        pose_covariance=_ro(pose_cov), correlation=_ro(corr), correlation_names=tuple(names),
        interior_std=interior_std, point_std=_ro(point_std),
        point_covariance=None if point_cov is None else _ro(point_cov), sigma0=s0, sigma0_groups=sigma0_groups,
        variance_factors={g: float(factors[g]) for g in GROUPS if present[g]},
        redundancy_groups={g: float(red.r[g]) for g in GROUPS if present[g]},
        residuals_px=_ro(res.image), weights=_ro(robust_w.image), standardized=_ro(stdz),
        redundancy_numbers=_ro(red.r_img), flagged=_ro(flagged), control_ids=ctrl_ids,
        control_residuals=_ro(ctrl_res), flagged_control=tuple(flagged_control), check_ids=check_ids,
        check_errors=_ro(check_err), check_std=_ro(check_std),
        gnss_residuals=_ro(res.gnss[:gn] if prob.pose_model is None else prob.pose_model.raw_gnss(res.gnss)[:gn]),
        iterations=iterations, converged=converged, datum=tuple(datum_lines), datum_groups=tuple(groups),
        condition_number=cond, warnings=tuple(warns), rejected_control=rejected_control,
        rejected_check=rejected_check, points_determined=_ro(determined), iteration_limit=limit,
        variance_estimated=None if estimated is None else {g: estimated[g] for g in GROUPS
                                                           if present[g] and g in estimated},
        systematic_names=sys_names, systematic=_ro(sys_val), systematic_std=_ro(sys_std))


def _ro(a: NDArray) -> NDArray:
    a = np.array(a, copy=True)
    a.flags.writeable = False
    return a
