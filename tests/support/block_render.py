"""Synthetic blocks with known truth: a textured terrain and the images of a block of frame cameras.

Everything is generated deterministically from a seed (nothing is stored). :func:`make_terrain`
builds a smooth DEM (Gaussian hills on a tilted plane) with a texture draped over it: band-passed
noise at three scales plus hard-edged discs and bars, so that SIFT finds plenty of well-localised
points. :func:`strip_poses` lays out a regular block of strips; :func:`render_image` ray-casts one
photo (per pixel the ray is intersected with the DEM by damped fixed-point iteration on the height,
then the texture is sampled bilinearly), vectorised over all pixels, as :mod:`stereo.actions.scene`
does for its pair; :func:`render_block` writes one small PNG or GeoTIFF per pose.

Frames: the ground frame is a local metric frame (x east, y north, z up, metres); poses are
:class:`stereo.block.types.Pose` (rotation: photo vector (x, y, -f) -> ground); pixels follow the
project's convention (x = column, y = row, pixel centres at integers).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from affine import Affine
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from rectify.atomic import atomic_output
from rectify.errors import InvalidInputError, RasterIOError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from rectify.raster import io as rio
from stereo.block.types import Pose

logger = logging.getLogger(__name__)

__all__ = ["BlockTerrain", "make_terrain", "render_block", "render_image", "strip_poses"]

#: grey value of pixels whose ray leaves the DEM
OUTSIDE_VALUE = 0


@dataclass(frozen=True, eq=False)
class BlockTerrain:
    """A DEM with a texture, ground frame (metres).

    Attributes
    ----------
    dem : (H, W) float64
        Heights, m, on a grid whose cell (r, c) centre is at ``origin + (c * cell_m, -r * cell_m)``
        (row 0 is the north edge).
    texture : (H, W) float32
        Grey values in [0, 1] on the same grid.
    origin : (2,) float64
        Ground (x, y) of the centre of cell (0, 0), m.
    cell_m : float
        Grid spacing, m.
    """

    dem: NDArray[np.float64]
    texture: NDArray[np.float32]
    origin: NDArray[np.float64]
    cell_m: float

    def __post_init__(self) -> None:
        dem = np.array(self.dem, dtype=np.float64, copy=True)
        tex = np.array(self.texture, dtype=np.float32, copy=True)
        if dem.ndim != 2 or tex.shape != dem.shape or min(dem.shape) < 2:
            raise InvalidInputError(f"terrain: dem and texture must be (H, W) grids of one shape with H, W >= 2; "
                                    f"got {dem.shape} and {tex.shape}")
        org = np.array(self.origin, dtype=np.float64, copy=True).reshape(-1)
        if org.shape != (2,) or not np.isfinite(org).all():
            raise InvalidInputError(f"terrain: origin must be 2 finite numbers; got {org.tolist()}")
        if not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise InvalidInputError(f"terrain: cell_m must be > 0; got {self.cell_m!r}")
        for a in (dem, tex, org):
            a.flags.writeable = False
        object.__setattr__(self, "dem", dem)
        object.__setattr__(self, "texture", tex)
        object.__setattr__(self, "origin", org)
        object.__setattr__(self, "cell_m", float(self.cell_m))

    @property
    def mean_height(self) -> float:
        """Mean DEM height, m (the ``ground_z`` of footprint pair selection)."""
        return float(self.dem.mean())

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the cell centres, ground frame, m."""
        h, w = self.dem.shape
        x0, y0 = self.origin
        return (float(x0), float(y0 - (h - 1) * self.cell_m), float(x0 + (w - 1) * self.cell_m), float(y0))

    def _sample(self, grid: NDArray, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        c = (xy[:, 0] - self.origin[0]) / self.cell_m
        r = (self.origin[1] - xy[:, 1]) / self.cell_m
        out = ndimage.map_coordinates(grid, [r, c], order=1, mode="nearest")
        inside = (r >= 0) & (c >= 0) & (r <= grid.shape[0] - 1) & (c <= grid.shape[1] - 1)
        return np.where(inside, out, np.nan)

    def height(self, xy: ArrayLike) -> NDArray[np.float64]:
        """Bilinear DEM height (N,), m, at ground points ``xy`` (N, 2); NaN outside the grid."""
        return self._sample(self.dem, np.asarray(xy, dtype=np.float64).reshape(-1, 2))

    def ground_from_pixel(self, camera: Camera, pose: Pose, pixel: ArrayLike, *, iterations: int = 60
                          ) -> NDArray[np.float64]:
        """Ray-cast pixels (N, 2) of the image with ``pose`` onto the DEM -> ground points (N, 3), m.

        Rays that leave the grid come out as NaN rows.
        """
        px = np.asarray(pixel, dtype=np.float64).reshape(-1, 2)
        d = camera.rays_from_pixel(px) @ pose.rotation.T
        return self._cast(pose.position, d, iterations)

    def _cast(self, C: NDArray[np.float64], d: NDArray[np.float64], iterations: int) -> NDArray[np.float64]:
        z = np.full(len(d), self.mean_height)
        with np.errstate(divide="ignore", invalid="ignore"):
            for _ in range(iterations):
                t = (z - C[2]) / d[:, 2]
                zn = self.height(C[:2] + t[:, None] * d[:, :2])
                zn = np.where(np.isfinite(zn), zn, z)
                step = zn - z
                z = z + 0.5 * step  # damped: stable for slopes up to ~45 degrees at ordinary view angles
                if np.max(np.abs(step), initial=0.0) < 1e-5:
                    break
            t = (z - C[2]) / d[:, 2]
        xy = C[:2] + t[:, None] * d[:, :2]
        g = np.column_stack([xy, z])
        bad = ~np.isfinite(self.height(xy)) | ~(t > 0)
        g[bad] = np.nan
        return g


def make_terrain(extent_m: tuple[float, float, float, float], *, cell_m: float = 0.25, base_height_m: float = 0.0,
                 relief_m: float = 10.0, n_hills: int = 12, seed: int = 0) -> BlockTerrain:
    """Build a deterministic textured terrain covering ``extent_m``.

    Parameters
    ----------
    extent_m : (xmin, ymin, xmax, ymax)
        Ground area to cover, m.
    cell_m : float
        Grid spacing, m; about the ground pixel size of the images keeps the texture sharp.
    base_height_m : float
        Height of the plane the hills sit on, m.
    relief_m : float
        Height scale of the hills, m.
    n_hills : int
        Number of Gaussian hills (and hollows).
    seed : int
        Everything random comes from ``np.random.default_rng(seed)``.

    Returns
    -------
    BlockTerrain
    """
    xmin, ymin, xmax, ymax = (float(v) for v in extent_m)
    if not (xmax > xmin and ymax > ymin):
        raise InvalidInputError(f"extent_m must be (xmin, ymin, xmax, ymax) with max > min; got {extent_m!r}")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise InvalidInputError(f"cell_m must be > 0; got {cell_m!r}")
    w = int(math.ceil((xmax - xmin) / cell_m)) + 1
    h = int(math.ceil((ymax - ymin) / cell_m)) + 1
    if w * h > 40_000_000:
        raise InvalidInputError(f"terrain grid of {w} x {h} cells is too large; raise cell_m (got {cell_m})")
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) * cell_m
    span = max(xmax - xmin, ymax - ymin)
    z = base_height_m + 0.02 * relief_m * (xx / span) - 0.01 * relief_m * (yy / span)
    for _ in range(n_hills):
        cx, cy = rng.uniform(0, w * cell_m), rng.uniform(0, h * cell_m)
        s = rng.uniform(0.06, 0.2) * span
        z = z + rng.uniform(-0.5, 1.0) * relief_m * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    tex = np.zeros((h, w))
    for sigma, weight in ((1.0, 0.5), (2.5, 1.0), (7.0, 0.7)):
        t = ndimage.gaussian_filter(rng.standard_normal((h, w)), sigma)
        tex += weight * t / t.std()
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    # hard-edged discs and bars: corners and blobs that SIFT localises well
    marks = np.zeros((h, w), dtype=np.float32)
    n_marks = int(w * h / 400)
    rad = rng.uniform(1.5, 5.0, n_marks)
    val = rng.uniform(-0.45, 0.45, n_marks)
    cxs, cys = rng.uniform(0, w, n_marks), rng.uniform(0, h, n_marks)
    for k in range(n_marks):
        centre = (int(cxs[k]), int(cys[k]))
        if k % 2:
            cv2.circle(marks, centre, int(round(rad[k])), float(val[k]), -1)
        else:
            half = (int(round(rad[k] * 1.6)), int(round(rad[k] * 0.7)))
            ang = float(rng.uniform(0, 180))
            box = cv2.boxPoints((centre, (2 * half[0], 2 * half[1]), ang)).astype(np.int32)
            cv2.fillConvexPoly(marks, box, float(val[k]))
    tex = np.clip(0.7 * tex + 0.15 + ndimage.gaussian_filter(marks, 0.6), 0.0, 1.0)
    origin = np.array([xmin, ymax])
    return BlockTerrain(dem=z, texture=tex.astype(np.float32), origin=origin, cell_m=float(cell_m))


def strip_poses(camera: Camera, *, n_strips: int, n_per_strip: int, flying_height_m: float, ground_z: float = 0.0,
                forward_overlap: float = 0.6, side_overlap: float = 0.3, alternate: bool = True,
                camera_id: str = "cam", angle_sigma_rad: float = 0.01, position_sigma_m: float = 0.0,
                seed: int = 0, prefix: str = "img") -> list[Pose]:
    """Poses of a regular block: strips along ground x, near-vertical images.

    The image x axis (columns) points along the strip. Strip ``s`` (0-based) is at ground
    y = -s * spacing, so the first strip is the northernmost; with ``alternate`` every second strip
    is flown back (kappa = pi, images turned by 180 degrees), as a real block is.

    Parameters
    ----------
    camera : Camera
    n_strips, n_per_strip : int
    flying_height_m : float
        Height of the projection centres above ``ground_z``, m.
    ground_z : float
        Mean terrain height, m.
    forward_overlap, side_overlap : float
        Overlap fractions along and across the strips, on the plane z = ``ground_z``.
    alternate : bool
    camera_id : str
    angle_sigma_rad, position_sigma_m : float
        Gaussian perturbation of the angles (rad) and positions (m).
    seed : int
    prefix : str
        Image names are ``f"{prefix}_{strip}_{k}"`` (both 1-based).

    Returns
    -------
    list of Pose
        Strip by strip, in flight order within each strip, with the footprint of the first image
        centred at ground (0, 0).
    """
    if n_strips < 1 or n_per_strip < 1:
        raise InvalidInputError(f"n_strips and n_per_strip must be >= 1; got {n_strips} and {n_per_strip}")
    if not (0 <= forward_overlap < 1 and 0 <= side_overlap < 1):
        raise InvalidInputError(f"overlaps must be in [0, 1); got {forward_overlap} and {side_overlap}")
    if not flying_height_m > 0:
        raise InvalidInputError(f"flying_height_m must be > 0; got {flying_height_m!r}")
    rng = np.random.default_rng(seed)
    gsd = flying_height_m * camera.pixel_size_mm / camera.focal_length_mm
    base = (1 - forward_overlap) * camera.width * gsd
    spacing = (1 - side_overlap) * camera.height * gsd
    out = []
    for s in range(n_strips):
        back = alternate and s % 2 == 1
        for k in range(n_per_strip):
            kk = n_per_strip - 1 - k if back else k
            a = rng.normal(0.0, angle_sigma_rad, 3)
            pos = np.array([kk * base, -s * spacing, ground_z + flying_height_m]) + rng.normal(0, position_sigma_m, 3)
            R = matrix_from_angles(a[0], a[1], a[2] + (math.pi if back else 0.0))
            out.append(Pose(f"{prefix}_{s + 1}_{k + 1}", camera_id, pos, R))
    return out


def render_image(terrain: BlockTerrain, camera: Camera, pose: Pose, *, supersample: int = 1) -> NDArray[np.uint8]:
    """Ray-cast one photo of the terrain -> (H, W) uint8 image (``camera.height``, ``camera.width``).

    Parameters
    ----------
    supersample : int
        Rays per pixel side; the samples sit symmetrically about the pixel centre and are averaged
        (anti-aliasing without moving the pixel centre).

    Pixels whose ray leaves the DEM are :data:`OUTSIDE_VALUE`.
    """
    s = int(supersample)
    if s < 1:
        raise InvalidInputError(f"supersample must be >= 1; got {supersample!r}")
    off = (np.arange(s) + 0.5) / s - 0.5
    rows = (np.arange(camera.height)[:, None] + off[None, :]).ravel()
    cols = (np.arange(camera.width)[:, None] + off[None, :]).ravel()
    cc, rr = np.meshgrid(cols, rows)
    px = np.column_stack([cc.ravel(), rr.ravel()])
    g = terrain.ground_from_pixel(camera, pose, px)
    ok = np.isfinite(g[:, 0])
    v = np.full(len(px), np.nan)
    v[ok] = terrain._sample(terrain.texture, g[ok, :2])
    img = (20 + 215 * v).reshape(camera.height, s, camera.width, s)
    inside = np.isfinite(img).all(axis=(1, 3))
    mean = np.nan_to_num(img).mean(axis=(1, 3))
    return np.where(inside, np.clip(np.round(mean), 1, 255), OUTSIDE_VALUE).astype(np.uint8)


def render_block(camera: Camera, poses: Sequence[Pose], terrain: BlockTerrain, out_dir: str | Path, *,
                 suffix: str = ".png", supersample: int = 1, overwrite: bool = False,
                 progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Render every pose's image of ``terrain`` into ``out_dir`` as ``<image name><suffix>``.

    Parameters
    ----------
    camera : Camera
        One camera for all images.
    poses : sequence of Pose
    terrain : BlockTerrain
    out_dir : path
        Created when missing.
    suffix : {".png", ".tif"}
        PNG through OpenCV (as :mod:`stereo.actions.scene` writes its pair) or an ungeoreferenced
        GeoTIFF through :mod:`rectify.raster.io`.
    supersample : int
        See :func:`render_image`.
    overwrite : bool
        Replace existing files.
    progress : callable(done, total), optional

    Returns
    -------
    list of Path
        One file per pose, in order.
    """
    if suffix not in (".png", ".tif"):
        raise InvalidInputError(f"suffix must be '.png' or '.tif'; got {suffix!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, pose in enumerate(poses):
        img = render_image(terrain, camera, pose, supersample=supersample)
        p = out / f"{pose.image}{suffix}"
        if suffix == ".png":
            with atomic_output(p, overwrite=overwrite, suffix=".png") as tmp:
                if not cv2.imwrite(str(tmp), img):
                    raise RasterIOError(f"cannot write {str(p)!r}")
        else:
            rio.write_raster(p, img, Affine.identity(), None, overwrite=overwrite)
        paths.append(p)
        if progress is not None:
            progress(k + 1, len(poses))
    logger.debug("rendered %d images into %s", len(paths), out)
    return paths
