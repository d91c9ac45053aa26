"""A synthetic pair of an uncalibrated camera (fx != fy, skew, principal point offset) over a 3D scene,
for the projective pair tests (issue 26)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles

__all__ = ["UNCALIBRATED", "PairScene", "pair_scene"]

#: f = 24 mm, 5 um pixels, fy = 1.04 fx, skew 0.015 fx, principal point off centre
UNCALIBRATED = Camera(focal_length_mm=24.0, pixel_size_mm=0.005, width=6000, height=4000,
                      principal_point_mm=(0.3, -0.2), aspect=1.04, shear=0.015)


@dataclass(frozen=True)
class PairScene:
    """Object points ``X`` (N, 3), metres, and their pixels ``left``/``right`` (N, 2) with noise; ``camera``;
    the true rotations (photo -> object) and centres."""

    X: NDArray[np.float64]
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    camera: Camera
    R: tuple[NDArray[np.float64], NDArray[np.float64]]
    C: tuple[NDArray[np.float64], NDArray[np.float64]]

    @property
    def R_rel(self) -> NDArray[np.float64]:
        """Right photo frame -> left photo frame."""
        return self.R[0].T @ self.R[1]


def pair_scene(seed: int = 0, *, n: int = 80, noise_px: float = 0.5, camera: Camera = UNCALIBRATED,
               relief: float = 8.0, convergence_deg: float = 17.0, tilt_deg: float = 2.0) -> PairScene:
    """A near-vertical pair from 100 m over a 60 x 40 m block with +-``relief`` m of height; base 30 m;
    the optical axes converge by about ``convergence_deg``; omega is ``tilt_deg`` (left) and
    ``tilt_deg - 3`` degrees (right)."""
    g = np.random.default_rng(seed)
    X = np.column_stack([g.uniform(-30, 30, n), g.uniform(-20, 20, n), g.uniform(-relief, relief, n)])
    deg = math.pi / 180
    h = convergence_deg / 2
    R1 = matrix_from_angles(tilt_deg * deg, -(h - 0.5) * deg, 1 * deg)
    R2 = matrix_from_angles((tilt_deg - 3) * deg, (h + 0.5) * deg, -2 * deg)
    C1, C2 = np.array([-15.0, 0.0, 100.0]), np.array([15.0, 1.0, 101.0])

    def observe(R, C):
        p = (X - C) @ R
        photo = np.column_stack([-camera.focal_length_mm * p[:, 0] / p[:, 2],
                                 -camera.focal_length_mm * p[:, 1] / p[:, 2]])
        return camera.pixel_from_photo(photo) + g.normal(0, noise_px, (n, 2))

    return PairScene(X, observe(R1, C1), observe(R2, C2), camera, (R1, R2), (C1, C2))
