"""Synthetic orthophotos of a known scene for the mosaic tests (issue 27): a ridge DSM, a texture known as a
function of ground coordinates, orthophotos with known projection centres (tags ORTHO_CENTER_X/Y/Z) and,
optionally, a visibility band.

Ground frame: EPSG:32632 metres, x east, y north. The ridge runs north-south at x = X0 + RIDGE_X, 20 m high
and 100 m wide at its foot (slopes of atan(20 / 50) = 21.8 degrees), on flat ground at 100 m.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

CRS = "EPSG:32632"
X0, Y0 = 500_000.0, 5_000_000.0  # west and north edges of the scene
RIDGE_X = 100.0
NODATA = -9999.0


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The scene's radiance at ground (x, y): smooth (periods 9-40 m), values about 40..160."""
    u, v = x - X0, y - Y0
    return (100 + 25 * np.sin(u / 6.1 + 0.3) * np.cos(v / 4.3) + 20 * np.sin((u + 2 * v) / 9.7)
            + 15 * np.cos(u / 3.1 - v / 5.3))


def ridge_height(x: np.ndarray) -> np.ndarray:
    return 100.0 + 20.0 * np.maximum(0.0, 1.0 - np.abs(x - (X0 + RIDGE_X)) / 50.0)


def write_dsm(path: Path, res: float = 2.0, noise: float = 0.0) -> Path:
    """The ridge DSM over x X0-20 .. X0+260, y Y0-140 .. Y0+20 (float32); ``noise``: m of uniform noise
    (seeded)."""
    w, h = int(280 / res), int(160 / res)
    xs = X0 - 20 + (np.arange(w) + 0.5) * res
    z = np.repeat(ridge_height(xs)[None], h, axis=0)
    z = z + noise * np.random.default_rng(7).uniform(-1, 1, z.shape)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=CRS,
                       transform=Affine(res, 0, X0 - 20, 0, -res, Y0 + 20)) as ds:
        ds.write(z.astype("float32"), 1)
    return path


def write_ortho(path: Path, x_left: float, x_right: float, *, centre: tuple[float, float, float] | None,
                y_top: float = Y0, y_bottom: float = Y0 - 120.0, res: float = 1.0, gain: float = 1.0,
                offset: float = 0.0, occluded: tuple[float, float, float, float] | None = None,
                true_ortho: bool = False, dx: float = 0.0, crs: str = CRS) -> Path:
    """An orthophoto of ``gain * texture + offset`` (float32, nodata -9999) over x_left .. x_right (+ dx).

    ``occluded`` (x0, x1, y0, y1): ground hidden in this image (visibility 1, nodata); ``true_ortho`` adds the
    visibility band (0 outside, 1 occluded, 2 visible) and its tag.
    """
    w, h = int(round((x_right - x_left) / res)), int(round((y_top - y_bottom) / res))
    left = x_left + dx
    xs = left + (np.arange(w) + 0.5) * res
    ys = y_top - (np.arange(h) + 0.5) * res
    X, Y = np.meshgrid(xs, ys)
    img = (gain * texture(X, Y) + offset).astype(np.float32)
    vis = np.full((h, w), 2, np.float32)
    if occluded is not None:
        a, b, c, d = occluded
        hid = (X >= a) & (X <= b) & (Y >= c) & (Y <= d)
        vis[hid] = 1
        img[hid] = NODATA
    tags = {"ORTHO_MODEL": "FrameModel", "ORTHO_NADIR_X": repr(centre[0] if centre else 0.5 * (x_left + x_right)),
            "ORTHO_NADIR_Y": repr(centre[1] if centre else 0.5 * (y_top + y_bottom))}
    if centre is not None:
        tags.update(ORTHO_CENTER_X=repr(centre[0]), ORTHO_CENTER_Y=repr(centre[1]), ORTHO_CENTER_Z=repr(centre[2]))
    count = 2 if true_ortho else 1
    if true_ortho:
        tags["ORTHO_VISIBILITY_BAND"] = "2"
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=count, dtype="float32", crs=crs,
                       nodata=NODATA, transform=Affine(res, 0, left, 0, -res, y_top)) as ds:
        ds.write(img, 1)
        if true_ortho:
            ds.write(vis, 2)
        ds.update_tags(**tags)
    return path


#: the two cameras of the ridge scene: A west of the ridge, B far east (1000 m up)
CENTRE_A = (X0 + RIDGE_X - 100.0, Y0 - 60.0, 1000.0)
CENTRE_B = (X0 + RIDGE_X + 250.0, Y0 - 60.0, 1000.0)


def ridge_pair(folder: Path, **kw) -> tuple[Path, Path, Path]:
    """Orthophotos A (x X0 .. X0+200) and B (X0+40 .. X0+240) and the ridge DSM; ``kw`` go to B."""
    a = write_ortho(folder / "a.tif", X0, X0 + 200, centre=CENTRE_A, true_ortho=kw.get("true_ortho", False))
    b = write_ortho(folder / "b.tif", X0 + 40, X0 + 240, centre=CENTRE_B, **kw)
    return a, b, write_dsm(folder / "dsm.tif")
