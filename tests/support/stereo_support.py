"""Stereo test and benchmark support: synthetic tie points of a pair with known relative geometry.

Moved out of the library (``stereo.relative``) in issue 11: only tests and ``scripts/bench_ro.py`` use it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.rotation import matrix_from_angles
from stereo.actions.scene import SyntheticScene, make_scene, render
from stereo.formats.orientation import write_exterior
from stereo.relative import SYSTEMS

__all__ = ["SimulatedPair", "simulate_pair"]


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v)


@dataclass(frozen=True, eq=False)
class SimulatedPair:
    """Tie points of a synthetic pair with known relative geometry (for tests and benchmarks).

    Attributes
    ----------
    left_mm, right_mm : (N, 2) float64
        Photo coordinates, mm, with noise and outliers applied.
    R_rel : (3, 3)
        True right photo -> left photo rotation.
    base_left : (3,)
        True unit base in the left photo frame.
    outlier : (N,) bool
        Points whose right coordinates were replaced by gross errors.
    focal_length_mm, pixel_size_mm : float
    """

    left_mm: NDArray[np.float64]
    right_mm: NDArray[np.float64]
    R_rel: NDArray[np.float64]
    base_left: NDArray[np.float64]
    outlier: NDArray[np.bool_]
    focal_length_mm: float
    pixel_size_mm: float

    def truth(self, system: str) -> NDArray[np.float64]:
        """True elements (5,) in the named system."""
        return SYSTEMS[system].elements_from_relative(self.R_rel, self.base_left)


def simulate_pair(kind: str = "vertical", *, n: int = 200, noise_px: float = 0.0, outlier_fraction: float = 0.0,
                  focal_length_mm: float = 120.0, pixel_size_mm: float = 0.144,
                  frame_mm: tuple[float, float] = (92.16, 165.888),
                  rng: np.random.Generator | int | None = None) -> SimulatedPair:
    """Simulate tie points of a stereo pair.

    Parameters
    ----------
    kind : {"vertical", "kappa180", "convergent"}
        ``vertical``: near-vertical aerial pair, 60 % overlap, small tilts,
        terrain relief 15 % of the flying height. ``kappa180``: as vertical but
        the right image turned by 180 degrees (relative kappa = pi).
        ``convergent``: optical axes converging by 30 degrees (phi = +-15 deg),
        base 0.5 of the distance.
    n : int
        Points kept (visible in both frames).
    noise_px : float
        Gaussian noise per coordinate, pixels.
    outlier_fraction : float
        Fraction of points whose right coordinates are displaced by 10-60 px
        in a random direction.
    """
    gen = np.random.default_rng(rng)
    f = focal_length_mm
    deg = math.pi / 180
    if kind in ("vertical", "kappa180"):
        H, B = 5000.0, 0.4 * frame_mm[0] / f * 5000.0
        R1 = matrix_from_angles(0.4 * deg, -0.3 * deg, 0.6 * deg)
        k2 = math.pi if kind == "kappa180" else -0.2 * deg
        R2 = matrix_from_angles(-0.5 * deg, 0.35 * deg, k2 + 0.3 * deg)
        C1, C2 = np.array([0.0, 0.0, H]), np.array([B, 0.02 * B, H + 0.01 * H])
        half = 0.5 * np.array(frame_mm) / f * H
        X = np.column_stack([gen.uniform(-half[0] + B, half[0], 6 * n), gen.uniform(-half[1], half[1], 6 * n),
                             gen.uniform(0, 0.15 * H, 6 * n)])
    elif kind == "convergent":
        D = 100.0
        B = 0.5 * D
        R1 = matrix_from_angles(0.5 * deg, -15 * deg, 0.4 * deg)
        R2 = matrix_from_angles(-0.8 * deg, 15 * deg, -0.6 * deg)
        C1, C2 = np.array([0.0, 0.0, D]), np.array([B, 0.5, D + 1.0])
        X = np.column_stack([gen.uniform(-0.2 * D, B + 0.2 * D, 6 * n), gen.uniform(-0.3 * D, 0.3 * D, 6 * n),
                             gen.uniform(-0.15 * D, 0.15 * D, 6 * n)])
    else:
        raise InvalidInputError(f"unknown kind {kind!r}; expected 'vertical', 'kappa180' or 'convergent'")

    def project(R, C):
        p = (X - C) @ R
        return np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]]), p[:, 2] < 0

    x1, ok1 = project(R1, C1)
    x2, ok2 = project(R2, C2)
    inside = ok1 & ok2
    for x in (x1, x2):
        inside &= (np.abs(x[:, 0]) < frame_mm[0] / 2) & (np.abs(x[:, 1]) < frame_mm[1] / 2)
    idx = np.flatnonzero(inside)[:n]
    if len(idx) < n:
        raise EstimationError(f"simulation produced only {len(idx)} visible points of {n}")
    x1, x2 = x1[idx].copy(), x2[idx].copy()
    s = noise_px * pixel_size_mm
    if s > 0:
        x1 += gen.normal(0, s, x1.shape)
        x2 += gen.normal(0, s, x2.shape)
    outl = np.zeros(n, dtype=bool)
    k = int(round(outlier_fraction * n))
    if k:
        j = gen.choice(n, k, replace=False)
        ang = gen.uniform(0, 2 * math.pi, k)
        mag = gen.uniform(10, 60, k) * pixel_size_mm
        x2[j] += np.column_stack([np.cos(ang), np.sin(ang)]) * mag[:, None]
        outl[j] = True
    return SimulatedPair(x1, x2, R1.T @ R2, _unit(R1.T @ (C2 - C1)), outl, f, pixel_size_mm)


def occlusion_from_truth(gt: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Occluded (or unknown) pixels of a left true disparity: those hidden by a larger disparity in the right."""
    H, W = gt.shape
    yy, xx = np.mgrid[0:H, 0:W]
    known = np.isfinite(gt)
    d = np.where(known, gt, -1)
    xt = np.rint(xx - d).astype(int)
    ok = known & (xt >= 0) & (xt < W)
    zb = np.full((H, W), -1.0)
    np.maximum.at(zb, (yy[ok], xt[ok]), d[ok])
    occ = np.ones((H, W), bool)
    occ[ok] = zb[yy[ok], xt[ok]] > d[ok] + 1.0
    return occ | ~known


def read_rgb(path: Path) -> NDArray[np.uint8]:
    """An RGB image file (a Middlebury PNG) as (H, W, 3) uint8, in RGB order."""
    img = cv2.imread(str(path))
    assert img is not None, path
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))


def read_grey(path: Path) -> NDArray[np.uint8]:
    """A one-band image file (a Middlebury occlusion mask) as (H, W) uint8."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return np.asarray(img)


def write_known_pair(folder: Path, *, n_ties: int = 60, margin_px: float = 20.0,
                     with_crs: bool = False) -> SyntheticScene:
    """The 320 px synthetic pair of ``make_scene(3)`` with exact orientations, for ``stereo dense``: ``l.png`` and
    ``r.png``, their exterior orientations ``l.json`` and ``r.json`` (sigma0 0: not adjusted; the scene's CRS
    when ``with_crs``) with the camera, and ``m.csv``: ``n_ties`` exact tie points (``margin_px`` inside both
    photos). Returns the scene (its surface is the truth)."""
    sc = make_scene(3, size_px=320)
    cv2.imwrite(str(folder / "l.png"), render(sc, "left"))
    cv2.imwrite(str(folder / "r.png"), render(sc, "right"))
    cam = sc.camera.to_dict()
    extra = {"crs": sc.crs} if with_crs else {}
    write_exterior(folder / "l.json", dataclasses.replace(sc.left, sigma0=0.0, **extra), camera=cam)
    write_exterior(folder / "r.json", dataclasses.replace(sc.right, sigma0=0.0, **extra), camera=cam)
    g = sc.random_ground_points(n_ties, np.random.default_rng(0), margin_px=margin_px)
    pl, pr = sc.pixel_from_ground(sc.left, g), sc.pixel_from_ground(sc.right, g)
    (folder / "m.csv").write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"{i},{a[0]},{a[1]},{b[0]},{b[1]}\n" for i, (a, b) in enumerate(zip(pl, pr, strict=True))))
    return sc
