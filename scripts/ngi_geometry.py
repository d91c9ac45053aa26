"""Known epipolar geometry of the NGI strip-05 pair (../shared/data/ngi_strip05/README).

The fundamental matrix implied by the two aero-triangulated exterior
orientations and the camera (f = 120 mm, pixel 0.144 mm, principal point at
the image centre, no distortion); used by the tests and by the benchmarks to
score tie points independently of any estimated model.
"""

from __future__ import annotations

import numpy as np

F_MM = 120.0
PIXEL_MM = 0.144
WIDTH, HEIGHT = 640, 1152
# X, Y, Z (m), omega, phi, kappa (deg); R = Rx(omega) Ry(phi) Rz(kappa), camera axes into world axes
EO = {
    "0182": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702),
    "0184": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883),
}


def _rot(omega: float, phi: float, kappa: float) -> np.ndarray:
    o, p, k = np.deg2rad([omega, phi, kappa])
    rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    return rx @ ry @ rz


def camera_matrix() -> np.ndarray:
    f_px = F_MM / PIXEL_MM
    return np.array([[f_px, 0, (WIDTH - 1) / 2], [0, f_px, (HEIGHT - 1) / 2], [0, 0, 1.0]])


def fundamental(left: str = "0182", right: str = "0184") -> np.ndarray:
    """F with x_right^T F x_left = 0 (pixel frame, pixel centres at integers)."""
    K = camera_matrix()
    flip = np.diag([1.0, -1.0, -1.0])  # camera axes (x right, y up, z back) -> (x right, y down, z forward)
    c1, c2 = np.array(EO[left][:3]), np.array(EO[right][:3])
    R1 = flip @ _rot(*EO[left][3:]).T       # world -> camera (OpenCV axes)
    R2 = flip @ _rot(*EO[right][3:]).T
    Rrel = R2 @ R1.T
    t = R2 @ (c1 - c2)                      # x2 = Rrel x1 + t, with camera 1 at the origin
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(K)
    F = Ki.T @ tx @ Rrel @ Ki
    return F / np.linalg.norm(F)


def project(xyz: np.ndarray, name: str) -> np.ndarray:
    """World points (N, 3) -> pixel (N, 2) by the README's formulas."""
    X = np.asarray(xyz, dtype=float)
    C = np.array(EO[name][:3])
    p = (X - C) @ _rot(*EO[name][3:])       # rows: R.T @ (P - C)
    x_mm = -F_MM * p[:, 0] / p[:, 2]
    y_mm = -F_MM * p[:, 1] / p[:, 2]
    return np.c_[(WIDTH - 1) / 2 + x_mm / PIXEL_MM, (HEIGHT - 1) / 2 - y_mm / PIXEL_MM]


def sampson(F: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Sampson distance (px) of each match (N,) to the epipolar geometry F."""
    xl = np.c_[left, np.ones(len(left))]
    xr = np.c_[right, np.ones(len(right))]
    Fx = xl @ F.T
    Ftx = xr @ F
    e = np.sum(xr * Fx, axis=1)
    return np.abs(e) / np.sqrt(Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2)


def left_overlap_mask(z: float = 400.0, step: int = 8) -> np.ndarray:
    """Left-image pixels (subsampled by ``step``) whose ground point at height ``z`` (m) falls in the right image.

    Returns a bool array of shape (ceil(HEIGHT/step), ceil(WIDTH/step)).
    """
    ys, xs = np.mgrid[0:HEIGHT:step, 0:WIDTH:step]
    pix = np.c_[xs.ravel(), ys.ravel()].astype(float)
    C = np.array(EO["0182"][:3])
    R = _rot(*EO["0182"][3:])
    x_mm = (pix[:, 0] - (WIDTH - 1) / 2) * PIXEL_MM
    y_mm = -(pix[:, 1] - (HEIGHT - 1) / 2) * PIXEL_MM
    d = np.c_[x_mm, y_mm, np.full(len(pix), -F_MM)] @ R.T      # ray directions, world
    lam = (z - C[2]) / d[:, 2]
    P = C + lam[:, None] * d
    q = project(P, "0184")
    ok = (q[:, 0] >= 0) & (q[:, 0] <= WIDTH - 1) & (q[:, 1] >= 0) & (q[:, 1] <= HEIGHT - 1)
    return ok.reshape(xs.shape)
