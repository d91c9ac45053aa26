"""The shared NGI aerial pair (strip 05, frames 0182 and 0184): its aero-triangulated exterior orientations,
camera and DEM, and control points made from the DEM, for the tests and studies that run the real pair.

The orientations and the camera are those of the data's README (angles omega, phi, kappa in degrees, positions
in metres in ``LO25``); ``dem.tif`` is a 24 m grid good to about one ground pixel (5.6 m).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import rasterio
from numpy.typing import NDArray
from scipy import ndimage

from rectify.geometry.camera import Camera
from rectify.geometry.points import ControlTable
from rectify.geometry.rotation import matrix_from_angles
from stereo.formats.orientation import write_exterior
from stereo.pair.resection import ExteriorOrientation

LO25 = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m"
#: X, Y, Z (m, LO25) and omega, phi, kappa (degrees) of the aero-triangulation
EO = {"0182": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702),
      "0184": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883)}
GROUND_PIXEL_M = 5.6


def ngi_camera() -> Camera:
    """The DMC camera of the 640 x 1152 px frames (focal length 120 mm, pixel 0.144 mm)."""
    return Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)


def ngi_orientations(crs: str | None = None) -> dict[str, ExteriorOrientation]:
    """The aero-triangulated exterior orientations of frames '0182' and '0184' (``crs``: the one they record)."""
    return {k: ExteriorOrientation(position=np.array(v[:3]), rotation=matrix_from_angles(*np.radians(v[3:])),
                                   focal_length_mm=120.0, crs=crs) for k, v in EO.items()}


def write_ngi_exteriors(folder: Path) -> list[Path]:
    """``folder/eo_0182.json`` and ``eo_0184.json``: the aero-triangulated orientations in LO25 with the camera
    (exterior orientation JSON, as ``stereo dense`` reads); their paths, left first."""
    cam = ngi_camera().to_dict()
    return [write_exterior(folder / f"eo_{k}.json", eo, camera=cam) for k, eo in ngi_orientations(LO25).items()]


def dem_sampler(folder: Path) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """Bilinear heights (m) of ``folder/dem.tif`` at (N, 2) ground XY (LO25); NaN outside the grid."""
    with rasterio.open(folder / "dem.tif") as src:
        dem = src.read(1).astype(float)
        T = src.transform

    def dem_h(xy: NDArray[np.float64]) -> NDArray[np.float64]:
        col, row = ~T * (xy[:, 0], xy[:, 1])
        return ndimage.map_coordinates(dem, [np.asarray(row) - 0.5, np.asarray(col) - 0.5], order=1,
                                       mode="constant", cval=np.nan)

    return dem_h


def dem_control(folder: Path, n: int, left: str = "0182", right: str = "0184", seed: int = 0
                ) -> tuple[ControlTable, list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]]:
    """``n`` control points ``dem0..`` drawn (``seed``) about the pair's centre, on the DEM, projected into both
    frames with the aero-triangulation and kept when 30 px inside both. Returns the table (pixels of ``left`` and
    ``right``, ground in LO25) and the list of (ground (3,), left pixel (2,), right pixel (2,))."""
    cam, eos, dem_h = ngi_camera(), ngi_orientations(), dem_sampler(folder)
    rng = np.random.default_rng(seed)
    pts = []
    while len(pts) < n:
        c = (eos[left].position[:2] + eos[right].position[:2]) / 2 + rng.uniform(-2500, 2500, 2) * [0.6, 1.0]
        g = np.array([c[0], c[1], dem_h(c[None])[0]])
        pl = cam.pixel_from_photo(eos[left].project(g[None]))[0]
        pr = cam.pixel_from_photo(eos[right].project(g[None]))[0]
        if np.isfinite(g[2]) and all(30 < p[0] < 610 and 30 < p[1] < 1122 for p in (pl, pr)):
            pts.append((g, pl, pr))
    ctrl = ControlTable(tuple(f"dem{i}" for i in range(len(pts))), np.array([p[1] for p in pts]),
                        np.array([p[2] for p in pts]), np.array([p[0] for p in pts]), crs=LO25)
    return ctrl, pts
