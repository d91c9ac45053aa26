"""A small rendered block with known surface for ``stereo surface``: images, an orientation with the
true poses, and the truth to compare a DSM with (tests/stereo/test_surface_fusion.py,
tests/cli/test_surface.py, scripts/surface_sigma_study.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.types import Pose
from stereo.formats.block import block_orientation_text
from tests.support.block_render import BlockTerrain, make_terrain, render_block, strip_poses

#: 240 x 180 px frames, 0.25 m ground pixel at 100 m above the mean terrain
CAMERA = Camera(focal_length_mm=20.0, pixel_size_mm=0.05, width=240, height=180)
H_FLY = 100.0
Z0 = 50.0
GSD = H_FLY * CAMERA.pixel_size_mm / CAMERA.focal_length_mm


@dataclass(frozen=True, eq=False)
class SurfaceBlock:
    folder: Path          # orientation.json (and the images, unless written elsewhere)
    images: Path
    terrain: BlockTerrain
    names: tuple[str, ...]
    true_poses: tuple[Pose, ...] = ()   # the poses the images were rendered with (names as ``names``)


def make_surface_block(folder: str | Path, *, strips: int = 3, per_strip: int = 4, seed: int = 5,
                       relief_m: float = 6.0, forward_overlap: float = 0.6, side_overlap: float = 0.3,
                       images: str | Path | None = None, supersample: int = 2,
                       pose_sigma: tuple[float, float] = (0.0, 0.0)) -> SurfaceBlock:
    """Render a ``strips`` x ``per_strip`` block and write ``orientation.json`` with the true poses.

    ``pose_sigma`` = (angle rad, position m): the recorded poses are the true ones perturbed by
    Gaussian errors of these standard deviations, which ``std_errors`` states (the images are
    rendered with the true poses).
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    img_dir = Path(images) if images is not None else out
    poses = strip_poses(CAMERA, n_strips=strips, n_per_strip=per_strip, flying_height_m=H_FLY, ground_z=Z0,
                        forward_overlap=forward_overlap, side_overlap=side_overlap, angle_sigma_rad=0.01,
                        seed=seed)
    w, h = CAMERA.width * GSD, CAMERA.height * GSD
    base = (1 - forward_overlap) * w
    spacing = (1 - side_overlap) * h
    ext = (-w / 2 - 30, -(strips - 1) * spacing - h / 2 - 30, (per_strip - 1) * base + w / 2 + 30, h / 2 + 30)
    terrain = make_terrain(ext, cell_m=GSD / 2, base_height_m=Z0 - 2.0, relief_m=relief_m, seed=seed)
    paths = render_block(CAMERA, poses, terrain, img_dir, supersample=supersample)
    rng = np.random.default_rng(seed + 1000)
    sa, sp = (float(v) for v in pose_sigma)
    named = []
    for p, pth in zip(poses, paths, strict=True):
        da = rng.normal(0, sa, 3) if sa > 0 else np.zeros(3)
        dp = rng.normal(0, sp, 3) if sp > 0 else np.zeros(3)
        named.append(type(p)(pth.name, p.camera, p.position + dp, p.rotation @ matrix_from_angles(*da)))
    std = None if sa == 0 and sp == 0 else np.tile([sa, sa, sa, sp, sp, sp], (len(named), 1))
    (out / "orientation.json").write_text(block_orientation_text({"cam": CAMERA}, named, crs=None, std_errors=std),
                                          encoding="utf-8")
    truth = tuple(type(p)(q.image, p.camera, p.position, p.rotation) for p, q in zip(poses, named, strict=True))
    return SurfaceBlock(out, img_dir, terrain, tuple(p.image for p in named), truth)


def read_dsm(path: str | Path) -> tuple[NDArray[np.float64], Affine, list[str]]:
    """(bands (B, H, W) float64 with NaN at nodata, transform, band descriptions)."""
    with rasterio.open(path) as ds:
        a = ds.read().astype(np.float64)
        t = ds.transform
        desc = list(ds.descriptions)
    a[0][a[0] == -9999] = np.nan
    a[1][a[1] == -9999] = np.nan
    return a, t, desc


def truth_on(dsm_transform: Affine, shape: tuple[int, int], terrain: BlockTerrain) -> NDArray[np.float64]:
    """The terrain height at every cell centre of a grid."""
    H, W = shape
    cc, rr = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x = dsm_transform.c + dsm_transform.a * cc
    y = dsm_transform.f + dsm_transform.e * rr
    return terrain.height(np.column_stack([x.ravel(), y.ravel()])).reshape(H, W)


__all__ = ["CAMERA", "GSD", "SurfaceBlock", "make_surface_block", "read_dsm", "truth_on"]
