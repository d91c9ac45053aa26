"""Projective bundles (seed 003, 3.4.4) and the upgrade of a projective block to a metric one (1.2).

:func:`adjust_projective` adjusts the 3 x 4 camera matrices of all images and the block points
together on the image observations (the projective bundle: no interior orientation, no rotation
matrices -- every image has its own 11-parameter projective camera):

    residual (px) = s_i (dehom(P_i (X, 1)) - u_obs)

with ``u`` the image's normalised coordinates (:func:`stereo.block.projective.pixel_normaliser`,
scale ``s_i`` back to pixels). The datum (gauge) is the first camera, held; each other camera is
held to unit norm by a constraint; the remaining four gauge freedoms (the projective maps
``I + C0 w^T`` that fix the first camera, C0 its centre) are fixed by four inner constraints on the
point corrections. Redundancy ``2M - (11 n + 3 P - 15)``.

:func:`upgrade_to_metric` takes the projective block to the object frame with control points: a
3D projective transformation (15 parameters, at least
:data:`stereo.pair.projective.MIN_CONTROL_PROJECTIVE` full control points not on one plane) turns
every camera into an object-frame DLT, whose RQ decomposition
(:meth:`stereo.calibration.dlt.DLT.decompose`) gives each image's own projective interior
orientation ``K_i`` (fx, fy, skew, principal point) and exterior orientation. The reduction of the
projective bundles to a common focal length (seed 003, 1.2) then gives the block one camera: the
median of the ``K_i`` (each image's coordinates are reduced by ``f / f_i``), and the spread of the
``K_i`` is reported. :func:`metric_bundle` finishes with the usual bundle adjustment with control
(:func:`stereo.block.bundle.adjust.adjust_bundle`), self-calibrating the camera (default: f, x0, y0,
aspect, shear: fx, fy, skew and the principal point), and :func:`pixel_interior` states fx, fy, skew,
cx, cy with standard errors propagated from the bundle's covariance.

:func:`uncalibrated_block` runs the whole chain: models, joint orientation
(:mod:`stereo.block.projective`), projective bundle, upgrade, metric bundle.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.sparse
from numpy.typing import NDArray

from rectify.errors import CalibrationError, EstimationError, InvalidInputError
from rectify.geometry.camera import NOMINAL_PIXEL_SIZE_MM, Camera
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.result import BundleResult
from stereo.block.projective import (
    BLOCK_METHODS,
    MIN_IMAGE_POINTS,
    MIN_IMAGES,
    OUTLIER_FACTOR,
    ModelBlock,
    form_models,
    join_models,
    pixel_normaliser,
    resect_cameras,
)
from stereo.block.types import BlockControl, Pose, Tracks
from stereo.calibration.dlt import DLT
from stereo.pair.projective import (
    MIN_CONTROL_AFFINE,
    MIN_CONTROL_PROJECTIVE,
    Affine3D,
    Projective3D,
    triangulate_projective,
)

__all__ = ["DEFAULT_CALIBRATE", "MetricStart", "ProjectiveBundle", "UncalibratedBlock", "adjust_projective",
           "metric_bundle", "pixel_interior", "uncalibrated_block", "upgrade_to_metric"]

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: interior elements the metric bundle self-calibrates by default: fx (f), fy (aspect), skew (shear), principal point
DEFAULT_CALIBRATE: tuple[str, ...] = ("f", "x0", "y0", "aspect", "shear")
#: the camera id of an uncalibrated block
CAMERA_ID = "camera"
#: the upgrade is refused when the images' principal distances (fx) differ by more than this ratio: one camera
#: took them, so a larger spread means the control did not determine the transformation
MAX_FOCAL_SPREAD = 1.5
#: the projective bundle solves its steps densely up to this many unknowns, iteratively (LSMR) beyond (0: always
#: LSMR; the dense trust-region steps were slower already at 1000 unknowns)
DENSE_LIMIT = 0
#: weight of the four inner constraints that fix the projective bundle's gauge (residual units: sigmas)
GAUGE_WEIGHT = 1e3
#: the a-priori spread of the images' interior orientation in the refinement of the upgrade, relative to fx
K_SIGMA_RELATIVE = 0.01


@dataclass(frozen=True, eq=False)
class ProjectiveBundle:
    """Result of :func:`adjust_projective`.

    Attributes
    ----------
    cameras : (n, 3, 4) float64
        Block point (X, Y, Z, 1) -> homogeneous pixel (col, row, 1) of every image (unit norm).
    points : (P, 3) float64
        Block coordinates of the tracks (the projective block frame).
    residuals_px : (M, 2) float64
        Observed minus computed, pixels.
    sigma0_px, rms_px : float
        sigma0 of unit weight (a-priori sigmas of ``Tracks.obs_sigma_px``) and RMS residual, px.
    redundancy, iterations : int
    converged : bool
    rejected : (M,) bool
        Observations given zero weight (beyond :data:`stereo.block.projective.OUTLIER_FACTOR` robust
        standard deviations after the robust adjustment).
    """

    cameras: F64
    points: F64
    residuals_px: F64
    sigma0_px: float
    rms_px: float
    redundancy: int
    iterations: int
    converged: bool
    rejected: NDArray[np.bool_]


def adjust_projective(tracks: Tracks, sizes: Sequence[tuple[int, int]], cameras: F64, points: F64, *,
                      max_iterations: int = 100) -> ProjectiveBundle:
    """The projective bundle adjustment (seed 003, 3.4.4).

    Parameters
    ----------
    tracks : Tracks
        Image observations, px, with their a-priori sigmas.
    sizes : sequence of (width, height)
        Image sizes, px.
    cameras : (n, 3, 4) float64
        Initial cameras, block point -> normalised image coordinates (as :class:`ModelBlock`).
    points : (P, 3) float64
        Initial block points (finite for every track).

    Raises
    ------
    EstimationError
        Too few observations (the redundancy would be <= 0) or a diverged adjustment.
    """
    n, P = len(tracks.images), tracks.n_points
    Ns = np.stack([pixel_normaliser(int(w), int(h)) for w, h in sizes])
    scale = 1.0 / Ns[:, 0, 0]  # normalised -> px
    oi, op = tracks.obs_image, tracks.obs_point
    u = tracks.obs_pixel * Ns[oi, 0, 0][:, None] + Ns[oi, :2, 2]
    wobs = scale[oi] / tracks.obs_sigma_px  # residual in units of sigma
    M = len(oi)
    red = 2 * M - (11 * n + 3 * P - 15)
    if red <= 0:
        raise EstimationError(f"the projective bundle has no redundancy: {2 * M} image coordinates for "
                              f"{11 * n + 3 * P - 15} unknowns ({n} cameras of 11, {P} points of 3, less 15)")
    X0 = np.asarray(points, dtype=np.float64)
    if not np.isfinite(X0).all():
        raise EstimationError("the projective bundle needs a start for every point")
    C0 = np.asarray(cameras, dtype=np.float64) / np.linalg.norm(np.asarray(cameras).reshape(n, -1), axis=1)[:, None,
                                                                                                            None]
    held = C0[0]
    nc = 12 * (n - 1)
    free_img = oi > 0
    x0 = np.concatenate([C0[1:].reshape(-1), X0.reshape(-1)])
    rows_o = np.arange(M)

    def unpack(x: F64) -> tuple[F64, F64]:
        Ps = np.concatenate([held[None], x[:nc].reshape(n - 1, 3, 4)])
        return Ps, x[nc:].reshape(P, 3)

    def fun(x: F64) -> F64:
        Ps, X = unpack(x)
        Xh = np.column_stack([X[op], np.ones(M)])
        q = np.einsum("mij,mj->mi", Ps[oi], Xh)
        r = (q[:, :2] / q[:, 2:3] - u) * wobs[:, None]
        norm = np.sum(Ps[1:].reshape(n - 1, -1) ** 2, axis=1) - 1.0
        gauge = GAUGE_WEIGHT * np.einsum("pkc,pc->k", V, X - X0)
        return np.concatenate([r.reshape(-1), norm, gauge])

    # the gauge left with the first camera held: H = I + C0 w^T (C0 its centre) moves each point along its ray
    # from C0, d X_j / d w_k = Xh_jk (c - X_j c4); four inner constraints sum_j V_jk . (X_j - X0_j) = 0 fix it
    C0 = np.linalg.svd(held)[2][-1]
    Xh0 = np.column_stack([X0, np.ones(P)])
    V = Xh0[:, :, None] * (C0[None, None, :3] - X0[:, None, :] * C0[3])  # (P, 4, 3)
    V = V / (np.linalg.norm(V.reshape(P, -1), axis=1).max() or 1.0)
    dense = len(x0) <= DENSE_LIMIT

    def jac(x: F64) -> scipy.sparse.csr_matrix | F64:
        Ps, X = unpack(x)
        Xh = np.column_stack([X[op], np.ones(M)])
        Pm = Ps[oi]
        q = np.einsum("mij,mj->mi", Pm, Xh)
        w = 1.0 / q[:, 2]
        # d r / d q: (M, 2, 3)
        D = np.zeros((M, 2, 3))
        D[:, 0, 0] = w
        D[:, 1, 1] = w
        D[:, 0, 2] = -q[:, 0] * w * w
        D[:, 1, 2] = -q[:, 1] * w * w
        D *= wobs[:, None, None]
        # cameras: d r_a / d P[b, c] = D[a, b] Xh[c]
        Jc = np.einsum("mab,mc->mabc", D, Xh).reshape(M, 2, 12)
        Jp = np.einsum("mab,mbc->mac", D, Pm[:, :, :3])
        rr, cc, vv = [], [], []
        ci = 12 * (oi[free_img] - 1)
        for a in range(2):
            rr.append(np.repeat(2 * rows_o[free_img] + a, 12))
            cc.append((ci[:, None] + np.arange(12)).reshape(-1))
            vv.append(Jc[free_img, a].reshape(-1))
            rr.append(np.repeat(2 * rows_o + a, 3))
            cc.append((nc + 3 * op[:, None] + np.arange(3)).reshape(-1))
            vv.append(Jp[:, a].reshape(-1))
        rr.append(np.repeat(2 * M + np.arange(n - 1), 12))
        cc.append(np.arange(nc))
        vv.append(2.0 * Ps[1:].reshape(-1))
        rr.append(np.repeat(2 * M + n - 1 + np.arange(4), 3 * P))
        cc.append(np.tile(nc + np.arange(3 * P), 4))
        vv.append(GAUGE_WEIGHT * V.transpose(1, 0, 2).reshape(-1))
        J = scipy.sparse.csr_matrix((np.concatenate(vv), (np.concatenate(rr), np.concatenate(cc))),
                                    shape=(2 * M + n - 1 + 4, len(x0)))
        return J.toarray() if dense else J

    # robust first (soft L1 beyond 3 sigma), then the observations beyond OUTLIER_FACTOR robust sigmas are
    # given zero weight and the adjustment repeated by plain least squares
    solver = "exact" if dense else "lsmr"
    sol = scipy.optimize.least_squares(fun, x0, jac=jac, method="trf", tr_solver=solver, x_scale="jac",
                                       loss="soft_l1", f_scale=3.0, max_nfev=max_iterations, xtol=1e-10, ftol=1e-10)
    if not np.isfinite(sol.x).all():
        raise EstimationError("the projective bundle diverged")
    e = np.linalg.norm(sol.fun[:2 * M].reshape(M, 2), axis=1)
    out = e > max(OUTLIER_FACTOR * 1.4826 * float(np.median(e)), 3.0)
    base_w = wobs.copy()
    wobs[out] = 0.0
    sol = scipy.optimize.least_squares(fun, sol.x, jac=jac, method="trf", tr_solver=solver, x_scale="jac",
                                       max_nfev=max_iterations, xtol=1e-10, ftol=1e-10)
    if not np.isfinite(sol.x).all():
        raise EstimationError("the projective bundle diverged")
    red -= 2 * int(out.sum())
    Ps, X = unpack(sol.x)
    Xh = np.column_stack([X[op], np.ones(M)])
    q = np.einsum("mij,mj->mi", Ps[oi], Xh)
    r = (q[:, :2] / q[:, 2:3] - u) * base_w[:, None]
    v_px = r * tracks.obs_sigma_px[:, None]  # (u - u_obs) s_i: pixels
    r = r[~out]
    cams_px = np.einsum("nij,njk->nik", np.linalg.inv(Ns), Ps)
    cams_px /= np.linalg.norm(cams_px.reshape(n, -1), axis=1)[:, None, None]
    if red <= 0:
        raise EstimationError(f"the projective bundle has no redundancy after rejecting {int(out.sum())} "
                              "observations")
    s0 = float(math.sqrt(float(np.sum(r ** 2)) / red))
    rms = float(np.sqrt(np.mean(np.sum(v_px[~out] ** 2, axis=1)) / 2.0))
    logger.debug("projective bundle: sigma0 %.3g, rms %.3g px, %d evaluations (%s)", s0, rms, sol.nfev, sol.message)
    # observed - computed
    return ProjectiveBundle(cams_px, X, -v_px, s0, rms, red, int(sol.nfev), bool(sol.status > 0), out)


# ------------------------------------------------------------------ metric upgrade
@dataclass(frozen=True, eq=False)
class MetricStart:
    """The projective block in the object frame (seed 003, 3.3.2 and 1.2).

    Attributes
    ----------
    transform : Projective3D or Affine3D
        Block frame -> object frame, fitted to the control points.
    per_image : (n, 5) float64
        Each image's own projective interior orientation fx, fy, skew, cx, cy (px) from the RQ
        decomposition of its object-frame camera.
    camera : Camera
        The common camera: the reduction of the bundles to a common focal length (median of
        ``per_image``), a pixel camera with aspect fy/fx and shear skew/fx.
    poses : list of Pose
        Exterior orientation of every image (from its own decomposition).
    points : (P, 3) float64
        Object coordinates of the tracks (NaN where the transformation sends a point to infinity).
    control_ids : tuple of str
        The control points the transformation used.
    """

    transform: Projective3D | Affine3D
    per_image: F64
    camera: Camera
    poses: list[Pose]
    points: F64
    control_ids: tuple[str, ...]


def _control_rows(tracks: Tracks, control: BlockControl | None) -> list[int]:
    """Rows of the full control points (check points excluded) that are tracks of two rays or more."""
    if control is None:
        return []
    rays = tracks.rays_per_point()
    pid = {p: k for k, p in enumerate(tracks.point_ids)}
    return [k for k, (i, kind, chk) in enumerate(zip(control.ids, control.kind, control.check, strict=True))
            if kind == "full" and not chk and i in pid and rays[pid[i]] >= 2]


def _enough_control(tracks: Tracks, control: BlockControl | None, method: str) -> None:
    """Refuse, before any work, fewer control points than the upgrade's transformation needs."""
    need, n_par, kind_t = ((MIN_CONTROL_PROJECTIVE, 15, "projective") if method == "projective"
                           else (MIN_CONTROL_AFFINE, 12, "affine"))
    k = len(_control_rows(tracks, control))
    if k < need:
        raise EstimationError(f"too few control points for the metric upgrade of the {method} block: {k} full "
                              f"control points measured in two images or more; at least {need} not on one plane "
                              f"are needed ({n_par} parameters of the 3D {kind_t} transformation)")


def upgrade_to_metric(pb: ProjectiveBundle, tracks: Tracks, sizes: Sequence[tuple[int, int]],
                      control: BlockControl | None, *, method: str = "projective") -> MetricStart:
    """Orient the block to control and reduce its bundles to one camera.

    ``method`` ``projective``: a 3D projective transformation (15 parameters, at least 5 control points
    not on one plane); ``affine``: a 3D affine one (12 parameters, at least 4), for a block built from
    similar models whose frame is affine to the object.

    Raises
    ------
    EstimationError
        Too few full control points (check points excluded) among the tracks (the minimum is named),
        control on one plane, a camera that does not decompose, or images whose principal distances
        differ by more than :data:`MAX_FOCAL_SPREAD` (the control does not determine the upgrade).
    """
    pid = {p: k for k, p in enumerate(tracks.point_ids)}
    _enough_control(tracks, control, method)
    rows = _control_rows(tracks, control)
    assert control is not None
    ids = tuple(control.ids[k] for k in rows)
    src = pb.points[[pid[i] for i in ids]]
    try:
        tr: Projective3D | Affine3D = (Projective3D.from_points(src, control.xyz[rows]) if method == "projective"
                                       else Affine3D.from_points(src, control.xyz[rows]))
    except EstimationError as err:
        raise EstimationError(f"metric upgrade: {err}") from err
    H = np.asarray(tr.H) if isinstance(tr, Projective3D) else np.asarray(tr.matrix)
    if method == "projective":
        H = _refine_upgrade(H, pb.cameras, src, control.xyz[rows], control.sigma_m[rows])
    Hi = np.linalg.inv(H)
    Y = np.column_stack([pb.points, np.ones(len(pb.points))]) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        Xg = Y[:, :3] / Y[:, 3:4]
    n = len(tracks.images)
    per = np.full((n, 5), np.nan)
    poses = []
    for i in range(n):
        Pg = pb.cameras[i] @ Hi
        obs = tracks.obs_image == i
        Xh = np.column_stack([Xg[tracks.obs_point[obs]], np.ones(int(obs.sum()))])
        ok = np.isfinite(Xh).all(axis=1)
        if np.median(Xh[ok] @ Pg[2]) < 0:  # points in front: positive third coordinate
            Pg = -Pg
        Pg = Pg / np.linalg.norm(Pg[2, :3])
        try:
            dec = DLT(matrix=Pg).decompose()
        except CalibrationError as err:
            raise EstimationError(f"metric upgrade: the camera of image {tracks.images[i]!r} does not decompose: "
                                  f"{err}") from err
        if not (dec.fx > 0 and dec.fy > 0):
            raise EstimationError(f"metric upgrade: image {tracks.images[i]!r} gets a principal distance <= 0 "
                                  f"(fx {dec.fx:.4g}, fy {dec.fy:.4g} px): the control does not fix the block")
        per[i] = (dec.fx, dec.fy, dec.skew, dec.cx, dec.cy)
        poses.append(Pose(tracks.images[i], CAMERA_ID, dec.centre, dec.rotation))
    spread = float(np.max(per[:, 0]) / np.min(per[:, 0]))
    if spread > MAX_FOCAL_SPREAD:
        raise EstimationError(f"the control does not determine the metric upgrade of the {method} block: the "
                              f"images' principal distances fx range {np.min(per[:, 0]):.4g}..{np.max(per[:, 0]):.4g} "
                              f"px (ratio {spread:.3g} > {MAX_FOCAL_SPREAD}); the {len(ids)} control points are too "
                              "close to one plane for it: give control with more depth"
                              + (" or use --method affine" if method == "projective" else ""))
    fx, fy, sk, cx, cy = np.median(per, axis=0)
    w, h = sizes[0]
    ps = NOMINAL_PIXEL_SIZE_MM
    cam = Camera(focal_length_mm=float(fx) * ps, pixel_size_mm=ps, width=int(w), height=int(h),
                 principal_point_mm=((cx - (w - 1) / 2.0) * ps, -(cy - (h - 1) / 2.0) * ps), pixel_camera=True,
                 aspect=float(fy / fx), shear=float(sk / fx))
    return MetricStart(tr, per, cam, poses, Xg, ids)


def _interiors(cams_px: F64, Gi: F64) -> F64:
    """(n, 5) fx, fy, skew, cx, cy of the cameras ``P_i Gi`` (RQ of their left 3 x 3 blocks, positive diagonal)."""
    out = np.empty((len(cams_px), 5))
    for i, P in enumerate(cams_px):
        K = scipy.linalg.rq((P @ Gi)[:, :3])[0]
        K = K @ np.diag(np.sign(np.diag(K)))
        K = K / K[2, 2]
        out[i] = (K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])
    return out


def _refine_upgrade(H0: F64, cams_px: F64, src: F64, xyz: F64, sigma: F64) -> F64:
    """The 3D projective transformation of the upgrade refined by the self-calibration condition of one camera.

    Least squares over the 15 elements of H (h44 = 1, in a frame centred and scaled on the control):
    the control residuals ``H(x_block) - X`` weighted by their sigmas, and for every image the departure
    of its interior orientation ``K_i`` (RQ of ``P_i H^-1``) from the block's mean, weighted by
    :data:`K_SIGMA_RELATIVE` times the mean fx. Minimal control (5 points, no redundancy) nearly on one
    plane leaves H weakly determined; the images, all taken with one camera, fix what the control does not.
    """
    c = xyz.mean(axis=0)
    sc = float(np.sqrt(np.mean(np.sum((xyz - c) ** 2, axis=1)))) or 1.0
    S = np.diag([1.0 / sc, 1.0 / sc, 1.0 / sc, 1.0])
    S[:3, 3] = -c / sc
    G0 = S @ H0
    G0 = G0 / G0[3, 3]
    xn = (xyz - c) / sc
    sn = np.where(np.isfinite(sigma) & (sigma > 0), sigma, 0.01 * sc) / sc
    sh = np.column_stack([src, np.ones(len(src))])

    def fun(p: F64) -> F64:
        G = np.append(p, 1.0).reshape(4, 4)
        Y = sh @ G.T
        rc = (Y[:, :3] / Y[:, 3:4] - xn) / sn
        k = _interiors(cams_px, np.linalg.inv(G))
        rk = (k - k.mean(axis=0)) / (K_SIGMA_RELATIVE * abs(float(k[:, 0].mean())))
        return np.concatenate([rc.reshape(-1), rk.reshape(-1)])

    try:
        sol = scipy.optimize.least_squares(fun, G0.reshape(-1)[:15], method="trf", x_scale="jac", max_nfev=200)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise EstimationError(f"metric upgrade: the refinement of the projective transformation failed: {err}") from err
    if not np.isfinite(sol.x).all():
        return H0
    return np.asarray(np.linalg.inv(S) @ np.append(sol.x, 1.0).reshape(4, 4), dtype=np.float64)


def pixel_interior(res: BundleResult, camera_id: str = CAMERA_ID) -> dict[str, tuple[float, float]]:
    """fx, fy, skew, cx, cy (px) of a bundle's camera, each with its standard error (NaN when not estimated),
    propagated from the covariance of f, aspect, shear (fy = aspect fx, skew = shear fx)."""
    cam = res.cameras[camera_id]
    ps = cam.pixel_size_mm
    fx, a, s = cam.focal_px, cam.aspect, cam.shear
    names = list(res.correlation_names)
    std = res.interior_std.get(camera_id, {})

    def sd(q: str) -> float:
        return float(std.get(q, float("nan")))

    def cov(p: str, q: str) -> float:
        a_, b_ = f"{camera_id}.{p}", f"{camera_id}.{q}"
        if a_ not in names or b_ not in names:
            return 0.0
        return float(res.correlation[names.index(a_), names.index(b_)]) * sd(p) * sd(q)

    def prop(g: dict[str, float]) -> float:
        keys = [k for k in g if k in std]
        if not keys and any(g.values()):
            return float("nan")
        return float(math.sqrt(max(sum(g[p] * g[q] * cov(p, q) for p in keys for q in keys), 0.0)))

    fmm = cam.focal_length_mm
    out = {"fx_px": (fx, prop({"f": 1.0 / ps})),
           "fy_px": (cam.fy_px, prop({"f": a / ps, "aspect": fmm / ps})),
           "skew_px": (cam.skew_px, prop({"f": s / ps, "shear": fmm / ps})),
           "cx_px": (float(cam.principal_point_px[0]), sd("x0") / ps),
           "cy_px": (float(cam.principal_point_px[1]), sd("y0") / ps)}
    return out


def metric_bundle(start: MetricStart, tracks: Tracks, control: BlockControl | None, *,
                  calibrate: Sequence[str] = DEFAULT_CALIBRATE, options: BundleOptions | None = None,
                  progress: Callable[[int, int], None] | None = None) -> tuple[BundleResult, Tracks]:
    """The usual bundle adjustment with control from the upgraded start, self-calibrating ``calibrate``.

    Tracks whose upgraded point is not finite or lies behind one of its cameras are left out (they
    are returned without them). Returns the bundle result and the tracks it used.
    """
    X = start.points
    ok_pt = np.asarray(np.isfinite(X).all(axis=1), dtype=bool)
    cam = start.camera
    depth = np.full(tracks.n_obs, -1.0)
    for i, p in enumerate(start.poses):
        obs = np.flatnonzero((tracks.obs_image == i) & ok_pt[tracks.obs_point])
        d = (X[tracks.obs_point[obs]] - p.position) @ p.rotation
        depth[obs] = -d[:, 2]
    keep = depth > 0
    counts = np.bincount(tracks.obs_point[keep], minlength=tracks.n_points)
    keep &= counts[tracks.obs_point] >= 2
    sub = tracks.subset(keep)
    where = {q: k for k, q in enumerate(tracks.point_ids)}
    X0 = X[[where[q] for q in sub.point_ids]].reshape(-1, 3)
    base = options or BundleOptions(max_iterations=100)
    opts = BundleOptions(**{**{f: getattr(base, f) for f in base.__dataclass_fields__},
                            "self_calibrate": tuple(calibrate)})
    if control is not None:
        present = set(sub.point_ids)
        k = [j for j, i in enumerate(control.ids) if i in present]
        control = None if not k else BlockControl(tuple(control.ids[j] for j in k), control.xyz[k],
                                                  tuple(control.kind[j] for j in k), control.sigma_m[k],
                                                  control.check[k])
    res = adjust_bundle({CAMERA_ID: cam}, start.poses, sub, X0, control=control, options=opts, progress=progress)
    return res, sub


# ------------------------------------------------------------------ the chain
def _intersect_all(tracks: Tracks, sizes: Sequence[tuple[int, int]], cams: F64, *, outlier_px: float = 5.0
                   ) -> tuple[F64, NDArray[np.bool_]]:
    """Every track intersected through the resected cameras (normalised image coordinates), and the rays kept:
    within ``outlier_px`` (and 5 robust standard deviations) of the intersected point, the control points' rays
    always (they are judged by the bundles)."""
    n = len(tracks.images)
    P = tracks.n_points
    Ns = np.stack([pixel_normaliser(int(w), int(h)) for w, h in sizes])
    oi, op = tracks.obs_image, tracks.obs_point
    u = tracks.obs_pixel * Ns[oi, 0, 0][:, None] + Ns[oi, :2, 2]
    pts = [np.full((P, 2), np.nan) for _ in range(n)]
    for i in range(n):
        o = oi == i
        pts[i][op[o]] = u[o]
    H = triangulate_projective(list(cams), pts)
    ok = np.asarray(np.abs(H[:, 3]) > 1e-9, dtype=bool) & np.isfinite(H).all(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = np.where(ok[:, None], H[:, :3] / np.where(ok, H[:, 3], 1.0)[:, None], np.nan)
        q = np.einsum("mij,mj->mi", cams[oi], np.column_stack([X[op], np.ones(len(op))]))
        e = np.linalg.norm(q[:, :2] / q[:, 2:3] - u, axis=1) / Ns[oi, 0, 0]
    fin = np.isfinite(e)
    lim = max(outlier_px, OUTLIER_FACTOR * 1.4826 * float(np.median(e[fin]))) if fin.any() else outlier_px
    return X, np.asarray(fin & (e <= lim), dtype=bool)


@dataclass(frozen=True, eq=False)
class UncalibratedBlock:
    """Result of :func:`uncalibrated_block`: every stage's figures and the metric bundle."""

    method: str
    models: ModelBlock
    projective: ProjectiveBundle
    start: MetricStart
    bundle: BundleResult
    tracks: Tracks
    interior: dict[str, tuple[float, float]] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        mb, pb, st = self.models, self.projective, self.start
        fx = st.per_image[:, 0]
        out = [f"models: {len(mb.models)} ({self.method}), joint {self.method} orientation rms "
               f"{mb.rms_model:.3g} model units" + (f", {mb.n_virtual} virtual points" if mb.n_virtual else ""),
               f"projective bundle: sigma0 {pb.sigma0_px:.3f}, rms {pb.rms_px:.3f} px, redundancy {pb.redundancy}",
               f"metric upgrade: 3D {'projective' if self.method == 'projective' else 'affine'} transformation on "
               f"{len(st.control_ids)} control points "
               f"(sigma0 {st.transform.sigma0 if st.transform.sigma0 is not None else float('nan'):.3g}); "
               f"focal lengths of the images fx {np.min(fx):.1f}..{np.max(fx):.1f} px, reduced to "
               f"{st.camera.focal_px:.1f} px"]
        parts = [f"{k[:-3]} {v:.2f} +- {s:.2f}" for k, (v, s) in self.interior.items()]
        out.append("camera (px): " + ", ".join(parts))
        return out


def uncalibrated_block(tracks: Tracks, sizes: Sequence[tuple[int, int]], control: BlockControl | None, *,
                       method: str = "projective", virtual: bool = True, focal_guess_px: float | None = None,
                       calibrate: Sequence[str] = DEFAULT_CALIBRATE, options: BundleOptions | None = None,
                       progress: Callable[[int, int], None] | None = None) -> UncalibratedBlock:
    """Images without a known camera to a metric block: models, joint affine/projective orientation,
    projective bundle, metric upgrade by control, metric bundle with self-calibration.

    Parameters
    ----------
    tracks : Tracks
        Tie points and control-point measurements (control points are tracks with their ids).
    sizes : sequence of (width, height)
        Image sizes (one camera: all equal).
    control : BlockControl or None
        Control and check points (object frame); at least
        :data:`stereo.pair.projective.MIN_CONTROL_PROJECTIVE` full control points.
    method : str
        ``affine`` or ``projective`` (:data:`stereo.block.projective.BLOCK_METHODS`).

    Raises
    ------
    InvalidInputError
        Fewer than 2 images, images of different sizes, an image with too few tracks.
    EstimationError
        A degenerate configuration or too little control; the message names it.
    """
    if method not in BLOCK_METHODS:
        raise InvalidInputError(f"unknown block method {method!r}; expected one of {list(BLOCK_METHODS)}")
    n = len(tracks.images)
    if n < MIN_IMAGES:
        raise InvalidInputError(f"a block needs at least {MIN_IMAGES} images; got {n}")
    if len(sizes) != n:
        raise InvalidInputError(f"{len(sizes)} image sizes for {n} images")
    if len({(int(w), int(h)) for w, h in sizes}) != 1:
        raise InvalidInputError(f"the images of an uncalibrated block share one camera and must have one size; got "
                                f"{sorted({(int(w), int(h)) for w, h in sizes})}")
    ppi = tracks.points_per_image()
    few = np.flatnonzero(ppi < MIN_IMAGE_POINTS)
    if len(few):
        raise InvalidInputError(f"image(s) with fewer than {MIN_IMAGE_POINTS} tracks (a projective camera has 11 "
                                f"parameters): {[(tracks.images[i], int(ppi[i])) for i in few[:5]]}")
    _enough_control(tracks, control, method)
    models = form_models(tracks, sizes, method=method, focal_guess_px=focal_guess_px)
    mb = join_models(models, tracks.n_points, n, method=method, virtual=virtual)
    cams, inl = resect_cameras(tracks, sizes, mb.points, initial=mb.cameras)
    X1, inl_new = _intersect_all(tracks, sizes, cams)
    have = np.asarray(np.isfinite(mb.points).all(axis=1), dtype=bool)
    X1[have] = mb.points[have]  # the joined models' points; the others intersected through the resected cameras
    inl = np.where(have[tracks.obs_point], inl, inl_new)
    if control is not None:  # the control points' rays are kept (the bundles judge them)
        cidx = np.isin(np.asarray(tracks.point_ids, dtype=object)[tracks.obs_point], list(control.ids))
        inl |= cidx & np.asarray(np.isfinite(X1).all(axis=1), dtype=bool)[tracks.obs_point]
    counts = np.bincount(tracks.obs_point[inl], minlength=tracks.n_points)
    sub = tracks.subset(inl & (counts >= 2)[tracks.obs_point])
    where = {q: k for k, q in enumerate(tracks.point_ids)}
    X0 = X1[[where[q] for q in sub.point_ids]]
    pb = adjust_projective(sub, sizes, cams, X0)
    start = upgrade_to_metric(pb, sub, sizes, control, method=method)
    res, used = metric_bundle(start, sub, control, calibrate=calibrate, options=options, progress=progress)
    return UncalibratedBlock(method, mb, pb, start, res, used, pixel_interior(res))
