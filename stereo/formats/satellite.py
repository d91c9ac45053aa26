"""Files of ``stereo sat-intersect`` (docs/formats.md, "Satellite intersection files").

- stations CSV: ``image,x,y,z,heading,pitch,roll,f_mm`` -- each image's projection centre in the map CRS
  (x easting, y northing: a Gauss-Krueger x is our y), its height ``z`` (normal height above the
  quasi-geoid of ``--geoid``, or ellipsoidal with ``--ellipsoidal``), the attitude in the local level
  frame at the centre (``# angles=deg`` default, or ``rad``) and the focal length, mm; ``# crs=``.
- image points CSV: ``id,image,x_mm,y_mm`` with optional ``sigma_mm``: photo coordinates, mm from the
  principal point, x right, y up.
- intersected points CSV (written): ``id,x,y,z,sx,sy,sz,n_rays,rms_mm,lon,lat,h,undulation`` with a
  ``# crs=`` line.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath, TableReader, need_columns, no_duplicates
from rectify.geometry.crs import crs_to_string, parse_crs

__all__ = ["ImagePoints", "StationTable", "read_image_points", "read_stations", "sat_points_text"]

F64 = NDArray[np.float64]

STATION_COLUMNS: tuple[str, ...] = ("image", "x", "y", "z", "heading", "pitch", "roll", "f_mm")
POINT_COLUMNS: tuple[str, ...] = ("id", "image", "x_mm", "y_mm")
OUTPUT_COLUMNS: tuple[str, ...] = ("id", "x", "y", "z", "sx", "sy", "sz", "n_rays", "rms_mm", "lon", "lat", "h",
                                   "undulation")


@dataclass(frozen=True, eq=False)
class StationTable:
    """Projection centres and attitudes of the images.

    Attributes
    ----------
    images : tuple of str
    xyz : (K, 3) float64
        Map x (easting), y (northing), height, m.
    attitude_rad : (K, 3) float64
        Heading, pitch, roll, radians.
    focal_mm : (K,) float64
    crs : str or None
        The ``# crs=`` line.
    """

    images: tuple[str, ...]
    xyz: F64
    attitude_rad: F64
    focal_mm: F64
    crs: str | None


@dataclass(frozen=True, eq=False)
class ImagePoints:
    """Image measurements: ``ids`` and ``images`` (M,), ``photo_mm`` (M, 2), ``sigma_mm`` (M,) (NaN: default)."""

    ids: tuple[str, ...]
    images: tuple[str, ...]
    photo_mm: F64
    sigma_mm: F64


def read_stations(path: StrPath) -> StationTable:
    """Read a stations CSV.

    Raises
    ------
    InvalidInputError
        Missing columns, bad numbers (file, line, column named), duplicate or empty image names, an unknown
        angle unit, a focal length <= 0, |pitch| or |roll| of 90 degrees or more.
    CRSError
        A ``# crs=`` line naming no CRS.
    """
    with TableReader(path) as t:
        need_columns(list(t.fields), STATION_COLUMNS, path)
        c = t.read("stations", numbers=STATION_COLUMNS[1:], texts=("image",))
    label = repr(str(path))
    images = tuple(c.texts["image"])
    if any(not s for s in images):
        i = images.index("")
        raise InvalidInputError(f"{label} line {int(c.lines[i])}: empty image name")
    no_duplicates(images, path, "image")
    unit = "deg"
    for line, key, value in c.settings:
        if key == "angles":
            if value.lower() not in ("deg", "rad"):
                raise InvalidInputError(f"{label} line {line}: unknown angle unit {value!r}; expected deg or rad")
            unit = value.lower()
    ang = np.column_stack([c.numbers[k] for k in ("heading", "pitch", "roll")])
    if unit == "deg":
        ang = np.radians(ang)
    bad = (np.abs(ang[:, 1:]) >= math.pi / 2).any(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidInputError(f"{label} line {int(c.lines[i])}: pitch or roll of image {images[i]!r} is 90 degrees "
                                "or more")
    f = c.numbers["f_mm"]
    if (f <= 0).any():
        i = int(np.flatnonzero(f <= 0)[0])
        raise InvalidInputError(f"{label} line {int(c.lines[i])}: focal length f_mm {f[i]!r} of image {images[i]!r} "
                                "must be > 0")
    crs = None if c.crs is None else crs_to_string(parse_crs(c.crs))
    return StationTable(images, np.column_stack([c.numbers[k] for k in ("x", "y", "z")]), ang, f, crs)


def read_image_points(path: StrPath) -> ImagePoints:
    """Read an image points CSV.

    Raises
    ------
    InvalidInputError
        Missing columns, bad numbers, empty ids or image names, a point measured twice in one image,
        a sigma <= 0.
    """
    with TableReader(path) as t:
        need_columns(list(t.fields), POINT_COLUMNS, path)
        has_sigma = "sigma_mm" in t.fields
        c = t.read("image points", numbers=("x_mm", "y_mm") + (("sigma_mm",) if has_sigma else ()),
                   texts=("id", "image"), empty=("sigma_mm",))
    label = repr(str(path))
    ids, images = tuple(c.texts["id"]), tuple(c.texts["image"])
    for name, col in (("id", ids), ("image", images)):
        if "" in col:
            raise InvalidInputError(f"{label} line {int(c.lines[col.index('')])}: empty {name}")
    no_duplicates([f"{i} in {m}" for i, m in zip(ids, images, strict=True)], path, "measurement")
    sigma = c.numbers["sigma_mm"] if has_sigma else np.full(len(ids), np.nan)
    if (sigma <= 0).any():
        i = int(np.flatnonzero(sigma <= 0)[0])
        raise InvalidInputError(f"{label} line {int(c.lines[i])}: sigma_mm {sigma[i]!r} must be > 0")
    return ImagePoints(ids, images, np.column_stack([c.numbers["x_mm"], c.numbers["y_mm"]]), sigma)


def sat_points_text(ids: Sequence[str], xyz: F64, std: F64, n_rays: NDArray[np.int64], rms_mm: F64, lonlat_h: F64,
                    undulation: F64, *, crs: str) -> str:
    """The intersected points CSV: map x, y, height z (normal or ellipsoidal, as the stations' heights) and
    their standard deviations sx, sy (map grid axes) and sz, m; rays; image misclosure RMS, mm; geodetic
    lon, lat (degrees), ellipsoidal height h and the undulation used, m."""
    buf = io.StringIO()
    buf.write(f"# crs={crs}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(OUTPUT_COLUMNS)
    for k, pid in enumerate(ids):
        w.writerow([pid, *(f"{v:.4f}" for v in xyz[k]), *(f"{v:.4f}" for v in std[k]), str(int(n_rays[k])),
                    f"{rms_mm[k]:.6f}", f"{lonlat_h[k, 0]:.9f}", f"{lonlat_h[k, 1]:.9f}", f"{lonlat_h[k, 2]:.4f}",
                    f"{undulation[k]:.4f}"])
    return buf.getvalue()
