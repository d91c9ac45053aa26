"""Synthetic RPC blocks with known truth: pushbroom-like images fitted as RPCs, ground tie points, biases.

Three 2000 x 2000 px images of about 0.5 m pixels over a 1 km square near (lon 5.37, lat 43.3): looking
forward, at nadir and backward along the track (rows), so a height moves the row; a small cross-track
tilt moves the column. Each physical model is fitted as an RPC (:func:`rectify.geometry.rpc.fit_rpc`,
reproduced to well under 0.01 px). Measurements are the RPC projections plus a known image-space bias
per image and optional Gaussian noise.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from rectify.geometry.rpc import RPC, fit_rpc

LON0, LAT0 = 5.37, 43.3
M_LON = 111_320.0 * np.cos(np.radians(LAT0))
M_LAT = 111_132.0
GSD = 0.5
SIZE = (2000, 2000)
#: along-track (row) parallax per metre of height (px/m) and cross-track (col) per metre, per image
VIEWS = ((0.6, 0.05), (0.0, -0.02), (-0.55, 0.08))
BOX = ((LON0 - 0.008, LON0 + 0.008), (LAT0 - 0.006, LAT0 + 0.006), (0.0, 400.0))


def camera(view: tuple[float, float], rot: float = 0.0, gsd: float = GSD, size: int = SIZE[0]):
    """A pushbroom-like physical model ground (N, 3) -> (col, row) of a ``size`` x ``size`` image of ``gsd``
    metre pixels (``view`` in px/m at 0.5 m pixels)."""
    ky, kx = view[0] * GSD / gsd, view[1] * GSD / gsd
    c0 = (size - 1) / 2

    def project(g: np.ndarray) -> np.ndarray:
        e = (g[:, 0] - LON0) * M_LON
        n = (g[:, 1] - LAT0) * M_LAT
        h = g[:, 2] - 200.0
        c = c0 + (np.cos(rot) * e + np.sin(rot) * n) / gsd + kx * h + 2e-6 * e * e
        r = c0 + (np.sin(rot) * e - np.cos(rot) * n) / gsd - ky * h + 1e-6 * e * n
        return np.column_stack([c, r])
    return project


def triplet(gsd: float = GSD, size: int = SIZE[0]) -> list[RPC]:
    """The three RPCs (forward, nadir, backward)."""
    return [fit_rpc(camera(v, rot=0.01 * i, gsd=gsd, size=size), BOX, source=f"synthetic {i + 1}")
            for i, v in enumerate(VIEWS)]


def render(view_index: int, size: int, gsd: float, bias: np.ndarray, seed: int = 0) -> np.ndarray:
    """A uint8 image (size, size) of a textured ground on :func:`dem` seen by the physical model of
    ``triplet(gsd, size)[view_index]`` with the image-space ``bias`` (dc, dr) px: the pixel (c, r) shows the
    ground whose projection is (c, r) - bias. The model is inverted analytically (its linear part is a
    rotation over ``gsd``), the line of sight met with the DEM by fixed-point iteration on the height."""
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.normal(size=(1400, 1400)), 3.0)  # 1 m cells, ~3 m blobs
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    ky, kx = VIEWS[view_index][0] * GSD / gsd, VIEWS[view_index][1] * GSD / gsd
    rot = 0.01 * view_index
    c0 = (size - 1) / 2
    cc, rr = np.meshgrid(np.arange(size, dtype=float), np.arange(size, dtype=float))
    c = cc.ravel() - bias[0]
    r = rr.ravel() - bias[1]
    e = np.zeros_like(c)
    n = np.zeros_like(c)
    h = np.zeros_like(c)
    for _ in range(30):
        u = (c - c0 - kx * h - 2e-6 * e * e) * gsd  # cos e + sin n
        v = (r - c0 + ky * h - 1e-6 * e * n) * gsd  # sin e - cos n
        e = np.cos(rot) * u + np.sin(rot) * v
        n = np.sin(rot) * u - np.cos(rot) * v
        h = dem(np.column_stack([LON0 + e / M_LON, LAT0 + n / M_LAT])) - 200.0
    val = ndimage.map_coordinates(tex, [700.0 - n, e + 700.0], order=1, mode="reflect")
    return np.clip(20 + 215 * val, 0, 255).astype(np.uint8).reshape(size, size)


def dem(lonlat: np.ndarray) -> np.ndarray:
    """A smooth hilly surface, 60-340 m."""
    e = (lonlat[:, 0] - LON0) * M_LON
    n = (lonlat[:, 1] - LAT0) * M_LAT
    return 200.0 + 80.0 * np.sin(e / 150.0) * np.cos(n / 210.0) + 60.0 * np.sin((e + n) / 400.0)


def ground_points(n: int, seed: int = 0, margin: float = 0.15) -> np.ndarray:
    """n ground points (lon, lat, h) on the DEM inside the common coverage."""
    rng = np.random.default_rng(seed)
    e = rng.uniform(-(1 - margin), 1 - margin, n) * 380.0
    nn = rng.uniform(-(1 - margin), 1 - margin, n) * 380.0
    ll = np.column_stack([LON0 + e / M_LON, LAT0 + nn / M_LAT])
    return np.column_stack([ll, dem(ll)])


def measure(rpcs: list[RPC], ground: np.ndarray, biases: np.ndarray, noise: float = 0.0, seed: int = 1
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measurements of every point in every image: (image (M,), track (M,), pixels (M, 2)); ``biases`` (N, 2)
    (dc, dr) px added to the RPC projection."""
    rng = np.random.default_rng(seed)
    im, tr, px = [], [], []
    for j, rpc in enumerate(rpcs):
        p = rpc.project(ground) + biases[j] + rng.normal(0.0, noise, (len(ground), 2)) if noise else \
            rpc.project(ground) + biases[j]
        im.append(np.full(len(ground), j))
        tr.append(np.arange(len(ground)))
        px.append(p)
    return np.concatenate(im), np.concatenate(tr), np.vstack(px)
