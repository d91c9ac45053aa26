"""Synthetic calibration scenes with known truth (for tests, the benchmark and the docs).

Everything is seeded: pass a ``np.random.default_rng(seed)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.rotation import rodrigues, rotvec_from_matrix
from stereo.calibration.model import Intrinsics
from stereo.calibration.views import TargetView
from stereo.features.targets import Chessboard

__all__ = ["SyntheticScene", "look_at", "board_scene", "field_scene", "rig_scene", "zoom_camera", "DEFAULT_CAMERA",
           "board_homography", "render_chessboard"]

F64 = NDArray[np.float64]

#: A 640 x 480 camera with noticeable distortion (near the published calibration's numbers).
DEFAULT_CAMERA = Intrinsics(fx=800.0, fy=796.0, cx=330.0, cy=228.0, width=640, height=480, k1=-0.15, k2=0.12,
                            k3=0.0, p1=0.0012, p2=-0.0008)


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """Views with known truth: ``views`` (noisy pixels), ``exact`` (noise-free pixels), ``poses`` (S, 6)."""

    camera: Intrinsics
    views: tuple[TargetView, ...]
    exact: tuple[F64, ...]
    poses: F64
    noise_px: float


def look_at(centre: F64, target: F64, roll: float = 0.0) -> tuple[F64, F64]:
    """OpenCV pose ``(R_cv, t)`` of a camera at ``centre`` looking at ``target`` (z forward, y down)."""
    z = np.asarray(target, dtype=np.float64) - centre
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R = np.array([x, y, z])
    return R, -R @ centre


def _project_views(cam: Intrinsics, X: F64, poses: list[tuple[F64, F64]], ids: tuple[str, ...], names: list[str],
                   noise_px: float, rng: np.random.Generator) -> SyntheticScene:
    views, exact, pv = [], [], []
    for (R, t), name in zip(poses, names, strict=True):
        xc = X @ R.T + t
        px = cam.project(xc)
        exact.append(px)
        views.append(TargetView(name, X, px + rng.normal(0.0, noise_px, px.shape), ids))
        pv.append(np.concatenate([rotvec_from_matrix(R), t]))
    return SyntheticScene(cam, tuple(views), tuple(exact), np.array(pv), noise_px)


def _inside(cam: Intrinsics, px: F64, margin: float) -> bool:
    return bool(np.all((px[:, 0] > margin) & (px[:, 0] < cam.width - 1 - margin)
                       & (px[:, 1] > margin) & (px[:, 1] < cam.height - 1 - margin)))


def board_scene(rng: np.random.Generator, *, n_views: int = 12, board: Chessboard | None = None,
                camera: Intrinsics = DEFAULT_CAMERA, noise_px: float = 0.2, tilt_deg: tuple[float, float] = (15, 45),
                fill: float = 0.6) -> SyntheticScene:
    """Views of a plane chessboard (z = 0) from random tilted directions, all corners inside the frame.

    ``tilt_deg = (0, 0)`` gives views parallel to the image plane.
    """
    b = board or Chessboard(9, 6, 25.0)
    X = b.object_xyz
    centre = X.mean(axis=0)
    extent = float(np.ptp(X[:, 0]))
    dist0 = camera.fx * extent / (fill * camera.width)
    poses: list[tuple[F64, F64]] = []
    for _ in range(100 * n_views):
        if len(poses) == n_views:
            break
        tilt = math.radians(rng.uniform(*tilt_deg))
        az = rng.uniform(0, 2 * math.pi)
        d = dist0 * rng.uniform(0.9, 1.3)
        C = centre + d * np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), -math.cos(tilt)])
        aim = centre + rng.normal(0, 0.08 * extent, 3) * np.array([1, 1, 0])
        if tilt == 0.0:
            R, t = np.eye(3), -C
            R = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1.0]])
            t = -R @ C
        else:
            R, t = look_at(C, aim, rng.uniform(-0.3, 0.3))
        if _inside(camera, camera.project(X @ R.T + t), 5):
            poses.append((R, t))
    if len(poses) < n_views:
        raise InvalidInputError("could not place the board inside the frame; lower `fill`")
    return _project_views(camera, X, poses, b.ids, [f"view{i:02d}" for i in range(n_views)], noise_px, rng)


def field_scene(rng: np.random.Generator, *, n_views: int = 3, n_points: int = 60,
                camera: Intrinsics = DEFAULT_CAMERA, noise_px: float = 0.3, depth: float = 0.6) -> SyntheticScene:
    """Views of a 3D test field: points in a 2 x 1.5 x ``depth`` box (object units m), cameras 3-4 m away."""
    X = rng.uniform([-1.0, -0.75, 0.0], [1.0, 0.75, depth], (n_points, 3))
    ids = tuple(f"p{i}" for i in range(n_points))
    poses: list[tuple[F64, F64]] = []
    for _ in range(200 * n_views):
        if len(poses) == n_views:
            break
        ang = math.radians(rng.uniform(-35, 35)) if n_views > 1 else 0.15
        el = math.radians(rng.uniform(-20, 20))
        d = rng.uniform(3.2, 3.8)
        C = np.array([d * math.sin(ang) * math.cos(el), d * math.sin(el), -d * math.cos(ang) * math.cos(el)])
        R, t = look_at(C, np.array([0, 0, depth / 2]) + rng.normal(0, 0.05, 3), rng.uniform(-0.2, 0.2))
        if _inside(camera, camera.project(X @ R.T + t), 3):
            poses.append((R, t))
    if len(poses) < n_views:
        raise InvalidInputError("could not place the field inside the frame")
    return _project_views(camera, X, poses, ids, [f"img{i}" for i in range(n_views)], noise_px, rng)


def rig_scene(rng: np.random.Generator, *, n_views: int = 6, left: Intrinsics = DEFAULT_CAMERA,
              right: Intrinsics | None = None, rel_rotvec: tuple[float, float, float] = (0.01, 0.2, 0.005),
              rel_t: tuple[float, float, float] = (-120.0, 1.5, 4.0), noise_px: float = 0.2,
              board: Chessboard | None = None) -> tuple[SyntheticScene, SyntheticScene]:
    """Synchronous board views of a two-camera rig: ``Xc_right = R_rel Xc_left + t_rel`` (OpenCV frames)."""
    b = board or Chessboard(9, 6, 25.0)
    cam_r = right or left
    Rr = rodrigues(np.array(rel_rotvec))[0]
    tr = np.asarray(rel_t, dtype=np.float64)
    cand = board_scene(rng, n_views=4 * n_views, board=b, camera=left, noise_px=0.0, fill=0.45)
    X = b.object_xyz
    pl: list[tuple[F64, F64]] = []
    pr: list[tuple[F64, F64]] = []
    for pose in cand.poses:
        R = rodrigues(pose[:3])[0]
        R2, t2 = Rr @ R, Rr @ pose[3:] + tr
        if _inside(cam_r, cam_r.project(X @ R2.T + t2), 5):
            pl.append((R, pose[3:]))
            pr.append((R2, t2))
        if len(pl) == n_views:
            break
    if len(pl) < n_views:
        raise InvalidInputError("could not place the board inside both frames")
    names = [f"pair{i:02d}" for i in range(n_views)]
    return (_project_views(left, X, pl, b.ids, names, noise_px, rng),
            _project_views(cam_r, X, pr, b.ids, names, noise_px, rng))


def zoom_camera(setting: float, width: int = 640, height: int = 480) -> Intrinsics:
    """A synthetic zoom lens: interior orientation as quadratic functions of the setting (10..30, "mm")."""
    z = float(setting)
    f = 40.0 * z + 0.3 * (z - 20.0) ** 2
    return Intrinsics(fx=f, fy=f * 0.998, cx=322.0 + 0.25 * (z - 20.0), cy=236.0 - 0.15 * (z - 20.0),
                      width=width, height=height, k1=-0.25 + 0.008 * z, k2=0.10 - 0.002 * z, k3=0.0,
                      p1=0.0005, p2=-0.0004)


# ------------------------------------------------------------------ rendered chessboard images
def board_homography(rng: np.random.Generator, board: Chessboard, size: tuple[int, int], *, fill: float = 0.6,
                     tilt_deg: tuple[float, float] = (10, 50), focal_px: float = 700.0) -> F64:
    """A random perspective view of ``board`` (its white margin inside the frame): the (3, 3) homography
    pixel ~ H @ (X, Y, 1) from board coordinates (object units, corner (i, j) at (i, j) * square) to pixels."""
    w, h = size
    sq = board.square
    ext = (board.cols + 1) * sq
    centre = np.array([(board.cols - 1) / 2 * sq, (board.rows - 1) / 2 * sq, 0.0])
    K = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1.0]])
    margin = np.array([[-2, -2, 1], [board.cols + 1, -2, 1], [board.cols + 1, board.rows + 1, 1],
                       [-2, board.rows + 1, 1]], dtype=np.float64) * np.array([sq, sq, 1.0])
    for _ in range(1000):
        t = math.radians(rng.uniform(*tilt_deg))
        az = rng.uniform(0, 2 * math.pi)
        R = rodrigues(np.array([math.cos(az) * t, math.sin(az) * t, rng.uniform(-0.4, 0.4)]))[0]
        d = focal_px * ext / (fill * w) * rng.uniform(0.9, 1.2)
        tv = np.array([rng.uniform(-0.1, 0.1) * ext, rng.uniform(-0.1, 0.1) * ext, d]) - R @ centre
        H = K @ np.column_stack([R[:, 0], R[:, 1], tv])
        Q = margin @ H.T
        q = Q[:, :2] / Q[:, 2:]
        if np.all(Q[:, 2] > 0) and q[:, 0].min() > 2 and q[:, 0].max() < w - 3 and q[:, 1].min() > 2 \
                and q[:, 1].max() < h - 3:
            return H / H[2, 2]
    raise InvalidInputError("could not place the board inside the frame; lower `fill`")


def render_chessboard(rng: np.random.Generator, board: Chessboard, H: F64, size: tuple[int, int], *,
                      blur_px: float = 1.0, noise: float = 2.0, dark: float = 40.0, light: float = 210.0,
                      background: float = 128.0, supersample: int = 4) -> tuple[NDArray[np.uint8], F64]:
    """Render ``board`` (one-square white margin, grey background) through the homography ``H`` of
    :func:`board_homography`: area-sampled (``supersample``^2 samples per pixel), Gaussian blur of
    ``blur_px``, Gaussian noise of ``noise`` grey levels, rounded to uint8.

    Returns the (H, W) image and the true inner corners (cols * rows, 2), px, OpenCV's order
    (pixel centres at integers)."""
    w, h = size
    o = (np.arange(supersample) + 0.5) / supersample - 0.5
    u = np.arange(w)[None, :, None, None] + o[None, None, None, :]
    v = np.arange(h)[:, None, None, None] + o[None, None, :, None]
    u, v = np.broadcast_arrays(u, v)
    Hi = np.linalg.inv(H)
    z = Hi[2, 0] * u + Hi[2, 1] * v + Hi[2, 2]
    X = (Hi[0, 0] * u + Hi[0, 1] * v + Hi[0, 2]) / z / board.square
    Y = (Hi[1, 0] * u + Hi[1, 1] * v + Hi[1, 2]) / z / board.square
    squares = (X >= -1) & (X < board.cols) & (Y >= -1) & (Y < board.rows)
    black = (np.floor(X).astype(np.int64) + np.floor(Y).astype(np.int64)) % 2 == 0
    val = np.where(squares & black, dark, light)
    val = np.where((X >= -2) & (X < board.cols + 1) & (Y >= -2) & (Y < board.rows + 1), val, background)
    img = val.mean(axis=(2, 3))
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if noise > 0:
        img = img + rng.normal(0.0, noise, img.shape)
    P = np.column_stack([board.object_xyz[:, :2], np.ones(board.cols * board.rows)]) @ H.T
    return np.clip(np.round(img), 0, 255).astype(np.uint8), P[:, :2] / P[:, 2:]
