#!/usr/bin/env python
"""Benchmark: our bundle adjustment (``stereo.block.bundle.adjust.adjust_bundle``) vs pycolmap's bundle
adjuster (COLMAP on Ceres) on the same synthetic aerial block, in one run (issue 13).

Blocks (``--block``)
--------------------
small
    7 strips x 7 images = 49 images, ~7 800 points, ~31 000 observations (at most 4 rays/point).
large
    10 strips x 50 images = 500 images, ~100 000 points, ~500 000 observations (at most 5 rays).

Frame camera f = 100 mm, 10 um pixels, 2000 x 1500 px, no distortion; flying height ~1000 m over
a rolling terrain (+-60 m), 70 % forward and 40 % side overlap, strips flown in alternating
directions (kappa 0 / 180 deg), true attitudes within ~1 deg of vertical. Every observation has
Gaussian noise ``--noise`` px (default 0.7) on each coordinate; every observation has the same
weight in both solvers (our ``obs_sigma_px`` = 1, Ceres' trivial loss), so both minimise the
same sum of squares. Initial values (the same for both): true positions + N(0, 1 m), true
attitudes + N(0, 1 mrad) per axis, true points + N(0, 0.5 m) in X, Y and N(0, 1 m) in Z.

Datum, the same for both solvers
--------------------------------
Five full ground control points (the tie points nearest to the four corners of the block, inset
by 12 %, and to its centre; each seen in the most images available there) are held at their true
coordinates, which are also their initial values; every pose and every other point is free.
pycolmap: ``BundleAdjustmentConfig.add_constant_point`` (hard constraints; no gauge fix of its
own, ``fixed_gauge`` stays ``UNSPECIFIED``). Ours: ``BlockControl`` with sigma 0.1 mm per
coordinate, i.e. practically hard (the control group adds nothing measurable to the cost). This
holds 15 coordinates for a 7-parameter datum; the 8 extra are true values, so both minimise the
same image residuals under the same constraints. Neither has GNSS. Interior orientation is
fixed in both (SIMPLE_PINHOLE with ``refine_focal_length = refine_principal_point =
refine_extra_params = False``; ours without ``self_calibrate``).

Conventions (checked numerically before every run)
--------------------------------------------------
COLMAP's ``cam_from_world`` rotation maps world to camera axes x right, y down, z forward:
``R_cw = diag(1, -1, -1) @ pose.rotation.T``, ``t = -R_cw @ C``. COLMAP puts the centre of the
top-left pixel at (0.5, 0.5): its keypoints and principal point are ours + 0.5. The script
projects the true points with ``stereo.block.types.project_pixel`` and with pycolmap's
``Image.project_point`` and requires agreement to 1e-6 px.

Measurement
-----------
Each solver runs in its own subprocess (this script with ``--worker``), so its peak RSS
(``VmHWM`` of /proc/self/status, right after the solve; not ``ru_maxrss``, which Linux carries over
from the driver through fork and exec) is honest; the RSS before the solve (data loaded,
imports done) is printed as well. Time is wall time (and process CPU time, all threads, which is
less sensitive to other load on a shared machine) of the adjustment call only (pycolmap:
``create_default_ceres_bundle_adjuster`` + ``solve``; ours: ``adjust_bundle``), not the building of
either solver's input. Final reprojection RMS (px, per coordinate: sqrt(sum r^2 / 2M)) is
computed here, by one function, from each solver's final poses and points, not from either
solver's own report. ``--threads`` goes to Ceres' ``num_threads`` (its Jacobian evaluation and
Schur elimination) and, as OMP/OpenBLAS/MKL thread counts in both workers' environment, to our
solver: ``adjust_bundle`` (``BundleOptions.threads`` None: one thread; two were slower, the GIL
is held between its numpy operations) runs BLAS on one thread except in dense factorisations of
1500 unknowns or more, which get these. ``--blas-threads N`` gives our solver N BLAS threads
instead (OpenBLAS's threads spin-wait: on a machine loaded beyond its cores a 2-thread
Cholesky of a 294 x 294 matrix once took 0.4 s instead of 0.5 ms).
``--iterations`` is the iteration limit of both (Ceres ``max_num_iterations``, our
``max_iterations``). Ours runs with ``covariance="none"`` by default (Ceres computes no
covariance either); ``--ours-covariance poses|full`` times it with its precision output.
Ceres keeps COLMAP's defaults otherwise (Levenberg-Marquardt, solver type auto-selected by
COLMAP: dense Schur up to 50 images, sparse Schur up to 1000, SuiteSparse).

Targets (issue 13): our RMS equal to pycolmap's within 1 %; our time at most pycolmap's.

Usage::

    pip install -e ".[bench]"          # pycolmap, the peer
    python scripts/bench_bundle.py [--block small|large|both] [--seed 0] [--iterations 100]
                                   [--threads 2] [--blas-threads N] [--noise 0.7]
                                   [--only ours|colmap] [--ours-covariance none|poses|full]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles

D_FLIP = np.diag([1.0, -1.0, -1.0])  # our photo axes (x right, y up, z back) <-> camera x right, y down, z fwd

CAMERA = dict(focal_length_mm=100.0, pixel_size_mm=0.01, width=2000, height=1500)

#: name -> (strips, images per strip, points, max rays per point)
BLOCKS = {"small": (7, 7, 7_800, 4), "large": (10, 50, 100_000, 5)}
CONTROL_SIGMA_M = 1e-4  # ours: sigma of the (practically fixed) control coordinates

PIP_HINT = 'bench_bundle: pycolmap (the peer) is not installed; run  pip install -e ".[bench]"'


# --------------------------------------------------------------------------- the synthetic block

@dataclass
class Block:
    """Arrays only (so they go to the workers through one .npz)."""

    R_true: np.ndarray  # (N, 3, 3) photo -> ground
    C_true: np.ndarray  # (N, 3)
    X_true: np.ndarray  # (P, 3)
    R0: np.ndarray  # initial values, same shapes
    C0: np.ndarray
    X0: np.ndarray
    obs_point: np.ndarray  # (M,) int64, sorted by point then image
    obs_image: np.ndarray  # (M,) int64
    obs_pixel: np.ndarray  # (M, 2) ours: pixel centres at integers
    control: np.ndarray  # (K,) int64 point indices held at their true coordinates

    def save(self, path: Path) -> None:
        np.savez(path, **self.__dict__)

    @classmethod
    def load(cls, path: Path) -> Block:
        with np.load(path) as z:
            return cls(**{k: z[k] for k in z.files})


def terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 40.0 * np.sin(x / 310.0) * np.cos(y / 270.0) + 15.0 * np.sin((x + 2 * y) / 97.0) + 5.0 * np.cos(x / 23.0)


def rodrigues(w: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors -> (N, 3, 3) matrices."""
    th = np.linalg.norm(w, axis=1)[:, None, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(th > 1e-12, np.sin(th) / th, 1.0)
        b = np.where(th > 1e-12, (1 - np.cos(th)) / th**2, 0.5)
    return np.eye(3) + a * K + b * (K @ K)


def project(R: np.ndarray, C: np.ndarray, X: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised pinhole projection, one pose per row: R (M, 3, 3), C (M, 3), X (M, 3) -> pixels
    (M, 2) (ours: pixel centres at integers, y down) and the depth (M,) along the viewing axis
    (> 0 in front of the camera)."""
    d = X - C
    p = np.einsum("mij,mi->mj", R, d)  # R.T @ (X - C): photo frame, z back
    f = cam.focal_px
    cx, cy = cam.principal_point_px
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cx - f * p[:, 0] / p[:, 2]
        v = cy + f * p[:, 1] / p[:, 2]
    return np.column_stack([u, v]), -p[:, 2]


def make_block(name: str, seed: int, noise_px: float) -> Block:
    """A vectorised synthetic block: strips over a terrain, tracks of 2..max_rays images."""
    n_strips, n_per, n_points, max_rays = BLOCKS[name]
    cam = Camera(**CAMERA)
    rng = np.random.default_rng(seed)
    H = 1000.0
    gsd = CAMERA["pixel_size_mm"] / CAMERA["focal_length_mm"] * H  # ground pixel, m
    across, along = CAMERA["width"] * gsd, CAMERA["height"] * gsd  # footprint (x across, y along)
    base, spacing = 0.3 * along, 0.6 * across  # 70 % forward, 40 % side overlap
    s_idx, j_idx = np.divmod(np.arange(n_strips * n_per), n_per)
    n = len(s_idx)
    C = np.column_stack([s_idx * spacing, j_idx * base, np.full(n, H)]) + rng.normal(0, [3.0, 3.0, 5.0], (n, 3))
    kappa = np.where(s_idx % 2 == 0, 0.0, np.pi) + rng.normal(0, 0.01, n)
    R = matrix_from_angles(rng.normal(0, 0.015, n), rng.normal(0, 0.015, n), kappa)

    # candidate points over the block, kept if seen in >= 2 images; visibility only tested against
    # the images of the grid cells near the point (3 strips x 7 images), all at once
    m_cand = int(n_points * 1.6)
    lo = np.array([-0.3 * across, -0.3 * along])
    hi = np.array([(n_strips - 1) * spacing + 0.3 * across, (n_per - 1) * base + 0.3 * along])
    xy = rng.uniform(lo, hi, (m_cand, 2))
    X = np.column_stack([xy, terrain(xy[:, 0], xy[:, 1])])
    s0 = np.rint(xy[:, 0] / spacing).astype(np.int64)[:, None] + np.arange(-1, 2)[None, :]
    j0 = np.rint(xy[:, 1] / base).astype(np.int64)[:, None] + np.arange(-3, 4)[None, :]
    ss = np.repeat(s0, j0.shape[1], axis=1)
    jj = np.tile(j0, (1, s0.shape[1]))
    ok = (ss >= 0) & (ss < n_strips) & (jj >= 0) & (jj < n_per)
    pt = np.broadcast_to(np.arange(m_cand)[:, None], ss.shape)[ok]
    im = (ss * n_per + jj)[ok]
    px, depth = project(R[im], C[im], X[pt], cam)
    inside = ((depth > 0) & (px[:, 0] >= 0) & (px[:, 0] <= CAMERA["width"] - 1)
              & (px[:, 1] >= 0) & (px[:, 1] <= CAMERA["height"] - 1))
    pt, im = pt[inside], im[inside]
    # at most max_rays images per point, chosen at random
    order = np.lexsort((rng.random(len(pt)), pt))
    pt, im = pt[order], im[order]
    start = np.searchsorted(pt, pt, side="left")
    rank = np.arange(len(pt)) - start
    keep = rank < max_rays
    pt, im = pt[keep], im[keep]
    # the points with the most rays first (random order among equals): tracks of max_rays images
    # wherever the block's overlap allows, shorter ones only where it does not
    rays = np.bincount(pt, minlength=m_cand)
    good = np.flatnonzero(rays >= 2)
    if len(good) < n_points:
        raise SystemExit(f"bench_bundle: only {len(good)} candidate points seen twice; need {n_points}")
    chosen = np.sort(good[np.lexsort((rng.random(len(good)), -rays[good]))][:n_points])
    remap = np.full(m_cand, -1, dtype=np.int64)
    remap[chosen] = np.arange(n_points)
    sel = remap[pt] >= 0
    pt, im = remap[pt[sel]], im[sel]
    order = np.lexsort((im, pt))
    pt, im = pt[order], im[order]
    X = X[chosen]
    obs = project(R[im], C[im], X[pt], cam)[0] + rng.normal(0, noise_px, (len(pt), 2))

    R0 = R @ rodrigues(rng.normal(0, 1e-3, (n, 3)))
    C0 = C + rng.normal(0, 1.0, (n, 3))
    X0 = X + rng.normal(0, [0.5, 0.5, 1.0], X.shape)
    # control: the points nearest to the inset corners and the centre, among those with most rays
    rays = np.bincount(pt, minlength=n_points)
    c_lo, c_hi = X[:, :2].min(0), X[:, :2].max(0)
    a, b = c_lo + 0.12 * (c_hi - c_lo), c_hi - 0.12 * (c_hi - c_lo)
    cand = np.flatnonzero(rays == rays.max())
    control = []
    for t in ([a[0], a[1]], [b[0], a[1]], [a[0], b[1]], [b[0], b[1]], (a + b) / 2):
        d = np.linalg.norm(X[cand, :2] - np.asarray(t), axis=1)
        control.append(int(cand[np.argmin(d)]))
    control = np.array(control, dtype=np.int64)
    X0[control] = X[control]
    return Block(R, C, X, R0, C0, X0, pt, im, obs, control)


def reprojection_rms(block: Block, R: np.ndarray, C: np.ndarray, X: np.ndarray) -> float:
    """The one RMS of both solvers: px per coordinate, sqrt(sum r^2 / 2M), over all observations."""
    cam = Camera(**CAMERA)
    px, _ = project(R[block.obs_image], C[block.obs_image], X[block.obs_point], cam)
    r = px - block.obs_pixel
    return float(np.sqrt(np.mean(r**2)))


# --------------------------------------------------------------------------- COLMAP conversion

def colmap_camera(pycolmap, cam: Camera):
    cx, cy = cam.principal_point_px
    return pycolmap.Camera(model="SIMPLE_PINHOLE", width=cam.width, height=cam.height,
                           params=[cam.focal_px, cx + 0.5, cy + 0.5], camera_id=1)


def cam_from_world(pycolmap, R: np.ndarray, C: np.ndarray):
    R_cw = D_FLIP @ R.T
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R_cw), -R_cw @ C)


def pose_from_colmap(rigid) -> tuple[np.ndarray, np.ndarray]:
    M = np.asarray(rigid.matrix())
    R_cw, t = M[:, :3], M[:, 3]
    return R_cw.T @ D_FLIP, -R_cw.T @ t


def build_reconstruction(pycolmap, block: Block):
    """The block as a pycolmap Reconstruction (one camera with a trivial rig, one trivial frame per
    image, image ids = index + 1, point ids = index + 1 in the same order)."""
    cam = Camera(**CAMERA)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(colmap_camera(pycolmap, cam))
    n = len(block.R0)
    # keypoint index of each observation inside its image
    order = np.argsort(block.obs_image, kind="stable")
    counts = np.bincount(block.obs_image, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    kp_idx = np.empty(len(order), dtype=np.int64)
    kp_idx[order] = np.arange(len(order)) - starts[block.obs_image[order]]
    kps = block.obs_pixel[order] + 0.5
    for i in range(n):
        img = pycolmap.Image(name=f"img{i:04d}", keypoints=kps[starts[i]:starts[i] + counts[i]],
                             camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, cam_from_world(pycolmap, block.R0[i], block.C0[i]))
    bounds = np.concatenate([[0], np.cumsum(np.bincount(block.obs_point, minlength=len(block.X0)))])
    TE = pycolmap.TrackElement
    ims, kpl = (block.obs_image + 1).tolist(), kp_idx.tolist()
    for p in range(len(block.X0)):
        a, b = bounds[p], bounds[p + 1]
        track = pycolmap.Track([TE(ims[k], kpl[k]) for k in range(a, b)])
        rec.add_point3D(block.X0[p], track)
    return rec


def check_conventions(pycolmap, block: Block) -> float:
    """Project the true points of a few images with ``project_pixel``, with this script's vectorised
    projection and with COLMAP (``Rigid3d`` + ``Camera.img_from_cam``) -> max difference, px."""
    from stereo.block.types import Pose, project_pixel

    cam = Camera(**CAMERA)
    ccam = colmap_camera(pycolmap, cam)
    worst = 0.0
    for i in np.unique(np.r_[0, len(block.R_true) // 2, len(block.R_true) - 1]):
        sel = np.flatnonzero(block.obs_image == i)[:200]
        X = block.X_true[block.obs_point[sel]]
        ours = project_pixel(cam, Pose(f"img{i}", "cam", block.C_true[i], block.R_true[i]), X)
        mine = project(np.repeat(block.R_true[i][None], len(X), 0), np.repeat(block.C_true[i][None], len(X), 0),
                       X, cam)[0]
        theirs = np.asarray(ccam.img_from_cam(cam_from_world(pycolmap, block.R_true[i], block.C_true[i]) * X)) - 0.5
        worst = max(worst, float(np.abs(ours - theirs).max()), float(np.abs(ours - mine).max()))
    return worst


def check_reconstruction(block: Block, rec) -> float:
    """The built reconstruction against the block (first, middle, last image): keypoints = our
    observations + 0.5, each keypoint linked to its track's point, and ``Image.project_point`` of
    the true points = our projection through the initial pose + 0.5. Max difference, px."""
    cam = Camera(**CAMERA)
    worst = 0.0
    n = len(block.R0)
    for i in np.unique([0, n // 2, n - 1]):
        sel = np.flatnonzero(block.obs_image == i)
        img = rec.image(int(i) + 1)
        pts2d = img.points2D
        kp = np.array([pts2d[k].xy for k in range(len(pts2d))])
        ids = np.array([pts2d[k].point3D_id for k in range(len(pts2d))])
        if len(kp) != len(sel) or not np.array_equal(np.sort(ids - 1), np.sort(block.obs_point[sel])):
            return np.inf
        by_point = np.argsort(ids)
        worst = max(worst, float(np.abs(kp[by_point] - 0.5 - block.obs_pixel[sel][np.argsort(block.obs_point[sel])])
                                 .max()))
        X = block.X_true[block.obs_point[sel[:200]]]
        theirs = np.array([img.project_point(x) for x in X]) - 0.5
        ours = project(np.repeat(block.R0[i][None], len(X), 0), np.repeat(block.C0[i][None], len(X), 0), X, cam)[0]
        worst = max(worst, float(np.abs(theirs - ours).max()))
    return worst


# --------------------------------------------------------------------------- workers

def _peak_mb() -> float:
    """Peak RSS of this process so far, MB: ``VmHWM`` of /proc/self/status (the high-water mark of this
    address space; ``ru_maxrss`` is not used: Linux carries it across fork and exec, so a worker would
    report the benchmark driver's RSS whenever that is larger than its own peak)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:  # pragma: no cover - not Linux
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # pragma: no cover


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def run_colmap(block: Block, iterations: int, threads: int) -> dict:
    import pycolmap

    t0 = time.perf_counter()
    rec = build_reconstruction(pycolmap, block)
    t_build = time.perf_counter() - t0
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    opts.print_summary = False
    so = opts.ceres.solver_options
    so.max_num_iterations = iterations
    so.num_threads = threads
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(len(block.R0)):
        config.add_image(i + 1)
    for k in block.control:
        config.add_constant_point(int(k) + 1)
    check = check_reconstruction(block, rec)
    if check > 1e-6:
        raise SystemExit(f"bench_bundle: the COLMAP reconstruction disagrees with the block by {check:.3g} px")
    rss_before = _rss_mb()
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(opts, config, rec)
    summary = adjuster.solve()
    t_solve = time.perf_counter() - t0
    peak = _peak_mb()  # before anything else is built in this process
    cpu = time.process_time() - cpu0
    n = len(block.R0)
    R, C = np.empty((n, 3, 3)), np.empty((n, 3))
    for i in range(n):
        R[i], C[i] = pose_from_colmap(rec.image(i + 1).cam_from_world())
    X = np.asarray([rec.point3D(p + 1).xyz for p in range(len(block.X0))])
    cs = summary.ceres_summary
    iters = cs.num_successful_steps + cs.num_unsuccessful_steps
    detail = (f"{str(cs.termination_type).split('.')[-1]}, {str(cs.linear_solver_type_used).split('.')[-1]}, "
              f"{cs.num_threads_used} threads used, {cs.num_successful_steps} successful steps")
    return dict(R=R, C=C, X=X, time=t_solve, cpu=cpu, build=t_build, rss_before=rss_before, peak_rss=peak,
                iterations=iters, detail=f"{detail}; reconstruction check {check:.1e} px",
                label=f"pycolmap {pycolmap.__version__} (Ceres, {threads} threads)")


def run_ours(block: Block, iterations: int, threads: int, covariance: str = "none") -> dict:
    from stereo.block.bundle import adjust as bundle
    from stereo.block.types import BlockControl, Pose, Tracks

    cam = Camera(**CAMERA)
    n = len(block.R0)
    t0 = time.perf_counter()
    poses = [Pose(f"img{i:04d}", "cam", block.C0[i], block.R0[i]) for i in range(n)]
    ids = tuple(f"p{k}" for k in range(len(block.X0)))
    tracks = Tracks(tuple(p.image for p in poses), ids, block.obs_point, block.obs_image, block.obs_pixel,
                    np.ones(len(block.obs_point)))
    control = BlockControl(tuple(ids[k] for k in block.control), block.X_true[block.control],
                           ("full",) * len(block.control), np.full((len(block.control), 3), CONTROL_SIGMA_M))
    options = bundle.BundleOptions(max_iterations=iterations, covariance=covariance)
    t_build = time.perf_counter() - t0
    rss_before = _rss_mb()
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    res = bundle.adjust_bundle({"cam": cam}, poses, tracks, block.X0, control=control, options=options)
    t_solve = time.perf_counter() - t0
    peak = _peak_mb()  # before anything else is built in this process
    cpu = time.process_time() - cpu0
    R = np.array([p.rotation for p in res.poses])
    C = np.array([p.position for p in res.poses])
    from stereo.block.bundle import solve as bundle_solve

    prob = bundle._setup({"cam": cam}, poses, tracks, block.X0, control, None, options)[0]
    solver = ("banded Cholesky (images in reverse Cuthill-McKee order)" if bundle_solve.use_banded(prob) else
              "dense Cholesky" if prob.n_c <= options.dense_limit else "sparse LU")
    return dict(R=R, C=C, X=np.asarray(res.points), time=t_solve, cpu=cpu, build=t_build, rss_before=rss_before,
                peak_rss=peak, iterations=res.iterations,
                detail=f"{'converged' if res.converged else 'NOT converged'}, reduced system by {solver}, "
                       f"covariance {covariance}, own RMS {res.rms_px:.4f} px",
                label=f"ours (LM + Schur, 1 thread, BLAS {threads})")


def worker(a: argparse.Namespace) -> int:
    block = Block.load(Path(a.data))
    if a.worker == "colmap":
        out = run_colmap(block, a.iterations, a.threads)
    else:
        out = run_ours(block, a.iterations, a.threads, a.ours_covariance)
    np.savez(a.out, R=out.pop("R"), C=out.pop("C"), X=out.pop("X"))
    print("RESULT " + json.dumps(out))
    return 0


def spawn(which: str, data: Path, out: Path, a: argparse.Namespace) -> dict:
    env = dict(os.environ)
    blas = a.threads if which == "colmap" or a.blas_threads is None else a.blas_threads
    threads = blas if which == "ours" else a.threads
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        env[k] = str(blas)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", which, "--data", str(data),
           "--out", str(out), "--iterations", str(a.iterations), "--threads", str(threads),
           "--ours-covariance", a.ours_covariance]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return dict(error=f"{which} worker failed (exit {proc.returncode}): {tail}")
    res = json.loads(lines[-1][7:])
    with np.load(out) as z:
        res.update(R=z["R"], C=z["C"], X=z["X"])
    return res


# --------------------------------------------------------------------------- main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--block", choices=("small", "large", "both"), default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=100, help="iteration limit of both solvers")
    ap.add_argument("--threads", type=int, default=2, help="threads of both solvers")
    ap.add_argument("--noise", type=float, default=0.7, help="image noise, px per coordinate")
    ap.add_argument("--only", choices=("ours", "colmap"), help="run one solver only")
    ap.add_argument("--ours-covariance", choices=("none", "poses", "full"), default="none",
                    help="precision output of our solver (timed with it)")
    ap.add_argument("--blas-threads", type=int,
                    help="threads of our solver (BLAS environment and its own threads) if not --threads")
    ap.add_argument("--worker", choices=("ours", "colmap"), help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        return worker(a)
    if importlib.util.find_spec("pycolmap") is None:
        raise SystemExit(PIP_HINT)
    import pycolmap

    load = os.getloadavg()
    print(f"# bench_bundle: our bundle adjustment vs pycolmap {pycolmap.__version__} (Ceres); seed {a.seed}, "
          f"noise {a.noise} px, <= {a.iterations} iterations, {a.threads} threads each; "
          f"{os.cpu_count()} CPUs, load {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print("# datum: 5 control points held at their true coordinates in both; interior orientation fixed; "
          "RMS px per coordinate from each solver's final poses and points by one function; "
          "each solver in its own process\n")
    names = ("small", "large") if a.block == "both" else (a.block,)
    which = ("colmap", "ours") if a.only is None else (a.only,)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_bundle_") as tmp:
        for name in names:
            t0 = time.perf_counter()
            block = make_block(name, a.seed, a.noise)
            t_gen = time.perf_counter() - t0
            worst = check_conventions(pycolmap, block)
            if worst > 1e-6:
                raise SystemExit(f"bench_bundle: our projection and COLMAP's differ by {worst:.3g} px (> 1e-6)")
            rays = np.bincount(block.obs_point)
            print(f"{name}: {len(block.R0)} images, {len(block.X0)} points, {len(block.obs_point)} observations "
                  f"(rays/point {rays.mean():.2f}, max {rays.max()}); generated in {t_gen:.1f} s; "
                  f"projection ours vs COLMAP agrees to {worst:.1e} px; "
                  f"RMS truth {reprojection_rms(block, block.R_true, block.C_true, block.X_true):.4f} px, "
                  f"start {reprojection_rms(block, block.R0, block.C0, block.X0):.2f} px")
            data = Path(tmp) / f"{name}.npz"
            block.save(data)
            res = {}
            for w in which:
                res[w] = spawn(w, data, Path(tmp) / f"{name}_{w}.npz", a)
                if "error" in res[w]:
                    print(f"  {res[w]['error']}")
                    continue
                r = res[w]
                r["rms"] = reprojection_rms(block, r["R"], r["C"], r["X"])
                r["pt_err"] = float(np.sqrt(np.mean(np.sum((r["X"] - block.X_true) ** 2, axis=1))))
                load = os.getloadavg()[0]
                print(f"  {r['label']}: {r['time']:.2f} s wall, {r['cpu']:.2f} s CPU (input built in "
                      f"{r['build']:.1f} s), iterations {r['iterations']}, {r['detail']}; load after {load:.2f}")
            rows.append((name, res))
    print("\n| block | solver | RMS (px) | RMS / pycolmap | time (s) | time / pycolmap | CPU (s) | CPU / pycolmap | "
          "RSS before solve (MB) | peak RSS (MB) | peak / pycolmap | point error vs truth, RMS (m) | "
          "max diff vs pycolmap: centres, points (m) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, res in rows:
        ref = res.get("colmap", {})
        if "error" in ref:
            ref = {}
        for w in which:
            r = res[w]
            if "error" in r:
                print(f"| {name} | {w} | failed | | | | | | | | | | |")
                continue
            rat = {k: f"{r[k] / ref[k]:.3f}" if k in ref else "-" for k in ("rms", "time", "cpu", "peak_rss")}
            diff = (f"{np.abs(r['C'] - ref['C']).max():.1e}, {np.abs(r['X'] - ref['X']).max():.1e}"
                    if "C" in ref and w != "colmap" else "-")
            print(f"| {name} | {r['label']} | {r['rms']:.4f} | {rat['rms']} | {r['time']:.2f} | {rat['time']} | "
                  f"{r['cpu']:.2f} | {rat['cpu']} | "
                  f"{r['rss_before']:.0f} | {r['peak_rss']:.0f} | {rat['peak_rss']} | {r['pt_err']:.3f} | "
                  f"{diff} |")
    for name, res in rows:
        if "colmap" in res and "ours" in res and "error" not in res["colmap"] and "error" not in res["ours"]:
            o, c = res["ours"], res["colmap"]
            rms_ok = abs(o["rms"] / c["rms"] - 1) <= 0.01
            t_ok = o["time"] <= c["time"]
            print(f"{name}: RMS within 1 % of pycolmap: {'yes' if rms_ok else 'NO'}; "
                  f"time at most pycolmap's: {'yes' if t_ok else 'NO'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
