"""Synthetic stereo scenes with known truth: a DEM, a texture, two frame cameras.

Everything is generated deterministically from a seed (nothing is stored):
:func:`make_scene` builds a smooth DEM (sum of Gaussian hills on a tilted
plane) with a random texture draped over it, and two near-vertical frame
cameras with known exterior orientation; :func:`render` ray-casts each photo
(per pixel: the ray is intersected with the DEM by fixed-point iteration on
the height, then the texture is sampled bilinearly). The ground frame is a
local metric frame (x east, y north, z up, metres) offset into the NGI
"Lo25" transverse Mercator zone, so that the map <-> topocentric path can be
exercised.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from rectify.atomic import atomic_output, atomic_write_text
from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.pair.resection import ExteriorOrientation

logger = logging.getLogger(__name__)

__all__ = ["LO25_CRS", "SyntheticScene", "make_scene", "render", "write_scene_inputs"]

#: the NGI data's CRS (transverse Mercator, central meridian 25 E, WGS84)
LO25_CRS = ('PROJCRS["Lo25",BASEGEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",'
            '6378137,298.257223563]],PRIMEM["Greenwich",0]],CONVERSION["TM 25E",METHOD["Transverse Mercator",'
            'ID["EPSG",9807]],PARAMETER["Latitude of natural origin",0],PARAMETER["Longitude of natural origin",'
            '25],PARAMETER["Scale factor at natural origin",1],PARAMETER["False easting",0],'
            'PARAMETER["False northing",0]],CS[Cartesian,2],AXIS["easting",east],AXIS["northing",north],'
            'LENGTHUNIT["metre",1]]')


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A DEM with texture and two cameras; all in one ground frame (metres).

    Attributes
    ----------
    dem : (H, W) float64
        Heights (m) on a grid whose cell (r, c) centre is at
        ``origin + (c * cell_m, -r * cell_m)`` (row 0 is the north edge).
    texture : (H, W) float32
        Grey values in [0, 1] on the same grid.
    origin : (2,) float64
        Ground (x, y) of the centre of DEM cell (0, 0).
    cell_m : float
    camera : Camera
    left, right : ExteriorOrientation
    crs : str
    """

    dem: NDArray[np.float64]
    texture: NDArray[np.float32]
    origin: NDArray[np.float64]
    cell_m: float
    camera: Camera
    left: ExteriorOrientation
    right: ExteriorOrientation
    crs: str

    def height(self, xy: NDArray) -> NDArray[np.float64]:
        """Bilinear DEM height (N,) at ground points (N, 2); NaN outside."""
        return self._sample(self.dem, xy)

    def _sample(self, grid: NDArray, xy: NDArray, order: int = 1) -> NDArray[np.float64]:
        c = (xy[:, 0] - self.origin[0]) / self.cell_m
        r = (self.origin[1] - xy[:, 1]) / self.cell_m
        out = ndimage.map_coordinates(grid, [r, c], order=order, mode="constant", cval=np.nan)
        inside = (r >= 0) & (c >= 0) & (r <= grid.shape[0] - 1) & (c <= grid.shape[1] - 1)
        return np.where(inside, out, np.nan)

    def ground_from_pixel(self, eo: ExteriorOrientation, pixel: NDArray, *, iterations: int = 30
                          ) -> NDArray[np.float64]:
        """Ray-cast pixels (N, 2) of the photo with ``eo`` onto the DEM -> ground (N, 3)."""
        mm = self.camera.photo_from_pixel(pixel)
        d = np.column_stack([mm, np.full(len(mm), -self.camera.focal_length_mm)]) @ eo.rotation.T
        C = eo.position
        z = np.full(len(mm), float(np.nanmean(self.dem)))
        for _ in range(iterations):
            t = (z - C[2]) / d[:, 2]
            xy = C[:2] + t[:, None] * d[:, :2]
            zn = self.height(xy)
            zn = np.where(np.isfinite(zn), zn, z)
            if np.max(np.abs(zn - z), initial=0.0) < 1e-4:
                z = zn
                break
            z = 0.5 * z + 0.5 * zn  # damped: stable for slopes up to ~45 degrees at these view angles
        t = (z - C[2]) / d[:, 2]
        xy = C[:2] + t[:, None] * d[:, :2]
        return np.column_stack([xy, z])

    def pixel_from_ground(self, eo: ExteriorOrientation, ground: NDArray) -> NDArray[np.float64]:
        """Project ground points (N, 3) into the photo with ``eo`` -> pixels (N, 2)."""
        return self.camera.pixel_from_photo(eo.project(ground))

    def random_ground_points(self, n: int, rng: np.random.Generator, *, margin_px: float = 20.0
                             ) -> NDArray[np.float64]:
        """n ground points (x, y, DEM z) visible in both photos (at least ``margin_px`` inside)."""
        out: list[NDArray[np.float64]] = []
        H, W = self.dem.shape
        while sum(len(o) for o in out) < n:
            xy = self.origin + np.column_stack([rng.uniform(0, W - 1, 4 * n), -rng.uniform(0, H - 1, 4 * n)]
                                               ) * self.cell_m
            g = np.column_stack([xy, self.height(xy)])
            ok = np.isfinite(g[:, 2])
            for eo in (self.left, self.right):
                px = self.pixel_from_ground(eo, g)
                ok &= (px[:, 0] >= margin_px) & (px[:, 1] >= margin_px)
                ok &= (px[:, 0] <= self.camera.width - 1 - margin_px)
                ok &= (px[:, 1] <= self.camera.height - 1 - margin_px)
            out.append(g[ok])
        return np.vstack(out)[:n]


def make_scene(seed: int = 0, *, size_px: int = 480, relief_m: float = 250.0) -> SyntheticScene:
    """Build a deterministic scene: DEM, texture and two cameras.

    Parameters
    ----------
    seed : int
        Everything random (hills, texture, small orientation angles) comes
        from ``np.random.default_rng(seed)``.
    size_px : int
        Side of each square photo, pixels.
    relief_m : float
        Height range of the hills, m.
    """
    if size_px < 64:
        raise InvalidInputError(f"`size_px` must be >= 64; got {size_px}")
    rng = np.random.default_rng(seed)
    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144 * 640 / size_px, width=size_px, height=size_px)
    flying_h = 3000.0  # above the mean terrain
    footprint = flying_h * (cam.width * cam.pixel_size_mm) / cam.focal_length_mm  # ground side, m
    base = 0.4 * footprint  # 60 % overlap
    cell = footprint / size_px * 1.0  # DEM cell ~ ground pixel
    n = int(np.ceil((footprint + base) * 1.3 / cell))
    yy, xx = np.mgrid[0:n, 0:n] * cell
    z = 400.0 + 0.02 * xx - 0.01 * yy
    for _ in range(9):
        cx, cy = rng.uniform(0, n * cell, 2)
        s = rng.uniform(0.08, 0.25) * n * cell
        z = z + rng.uniform(-0.5, 1.0) * relief_m * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    # texture: band-passed noise at several scales (gives SIFT plenty of corners)
    tex = np.zeros((n, n))
    for sigma, w in ((1.0, 0.5), (3.0, 1.0), (8.0, 0.7)):
        t = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma)
        tex += w * t / t.std()
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    origin = np.array([-55000.0 - 0.65 * n * cell, -3727400.0 + 0.65 * n * cell])
    centre_xy = origin + np.array([n * cell / 2, -n * cell / 2])
    zc = float(z.mean()) + flying_h
    a = rng.uniform(-0.02, 0.02, 6)
    left = ExteriorOrientation(position=np.array([centre_xy[0] - base / 2, centre_xy[1], zc]),
                               rotation=matrix_from_angles(a[0], a[1], a[2]), focal_length_mm=120.0)
    right = ExteriorOrientation(position=np.array([centre_xy[0] + base / 2, centre_xy[1] + 20.0, zc + 15.0]),
                                rotation=matrix_from_angles(a[3], a[4], a[5]), focal_length_mm=120.0)
    return SyntheticScene(dem=z, texture=tex.astype(np.float32), origin=origin, cell_m=cell, camera=cam,
                          left=left, right=right, crs=LO25_CRS)


def render(scene: SyntheticScene, which: str = "left", *, progress: Callable[[int, int], None] | None = None
           ) -> NDArray[np.uint8]:
    """Ray-cast one photo of the scene -> (H, W) uint8 image.

    Pixels whose ray leaves the DEM are 0.
    """
    if which not in ("left", "right"):
        raise InvalidInputError(f"`which` must be 'left' or 'right'; got {which!r}")
    eo = scene.left if which == "left" else scene.right
    cam = scene.camera
    rows, cols = np.mgrid[0:cam.height, 0:cam.width]
    px = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float64)
    img = np.zeros(len(px))
    step = 1 << 16
    for s in range(0, len(px), step):
        g = scene.ground_from_pixel(eo, px[s:s + step])
        v = scene._sample(scene.texture.astype(np.float64), g[:, :2], order=1)
        img[s:s + step] = np.where(np.isfinite(v), 20 + 215 * v, 0)
        if progress is not None:
            progress(min(s + step, len(px)), len(px))
    return np.clip(np.round(img), 0, 255).astype(np.uint8).reshape(cam.height, cam.width)


def write_scene_inputs(scene: SyntheticScene, out_dir: str | Path, *, n_control: int = 10, n_check: int = 20,
                       seed: int = 0, pixel_noise_px: float = 0.2, overwrite: bool = False,
                       progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Render both photos (PNG) and write camera.json and control.csv into ``out_dir``.

    Control and check points are DEM points projected into both photos, with
    Gaussian "measurement" noise of ``pixel_noise_px``; check ids start with ``k``.

    Returns
    -------
    dict with paths (``left``, ``right``, ``camera``, ``control``), ``check_ids``
    and the true ground coordinates ``truth`` (id -> (3,)).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for which in ("left", "right"):
        img = render(scene, which, progress=progress)
        p = out / f"{which}.png"
        with atomic_output(p, overwrite=overwrite, suffix=".png") as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise InvalidInputError(f"cannot write {p}")
        paths[which] = p
    paths["camera"] = atomic_write_text(out / "camera.json", json.dumps(scene.camera.to_dict(), indent=2),
                                        overwrite=overwrite)
    rng = np.random.default_rng(seed + 1000)
    g = scene.random_ground_points(n_control + n_check, rng, margin_px=25.0)
    pl = scene.pixel_from_ground(scene.left, g) + rng.normal(0, pixel_noise_px, (len(g), 2))
    pr = scene.pixel_from_ground(scene.right, g) + rng.normal(0, pixel_noise_px, (len(g), 2))
    ids = [f"c{i}" for i in range(n_control)] + [f"k{i}" for i in range(n_check)]
    lines = ["# synthetic control: DEM points projected into both photos", f"# crs={scene.crs}",
             "id,col_left,row_left,col_right,row_right,x,y,z"]
    for i, pid in enumerate(ids):
        lines.append(f"{pid},{pl[i, 0]:.4f},{pl[i, 1]:.4f},{pr[i, 0]:.4f},{pr[i, 1]:.4f},"
                     f"{g[i, 0]:.4f},{g[i, 1]:.4f},{g[i, 2]:.4f}")
    paths["control"] = atomic_write_text(out / "control.csv", "\n".join(lines) + "\n", overwrite=overwrite)
    return {**paths, "check_ids": tuple(ids[n_control:]), "truth": dict(zip(ids, g, strict=True))}
