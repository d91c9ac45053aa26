"""Directions in a map CRS: the rotation between the local east-north-up frame and a map's grid frame.

Frames (right-handed, metres):

- **ENU** at a point: x east, y true north, z up along the ellipsoid normal
  (:func:`rectify.geometry.geodesy.enu_rotation`).
- **grid** of a projected CRS at that point: x along the easting axis, y along the northing axis
  ("grid north"), z up.

The two differ by the meridian convergence: true north points ``a`` radians clockwise of grid
north (:func:`true_north_azimuth`), so the grid frame is the ENU frame turned about the vertical,
``grid_from_enu = Rz(-a)``. Rotations of cameras given in ENU or in geocentric coordinates (an INS's
roll, pitch and yaw; a Metashape chunk) are taken into a map CRS through it: this treats the map as
conformal and ignores its scale factor, the approximation every photogrammetric package makes
when it writes omega, phi, kappa in a projected CRS. ``a`` is found by PROJ (the points north and
south of the place, projected), so it holds for any projection.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.crs import parse_crs
from rectify.geometry.geodesy import map_from_geodetic
from rectify.geometry.rotation import rot_z

__all__ = ["true_north_azimuth", "grid_from_enu"]

#: half the latitude step (degrees) of the difference that finds true north (about 11 m)
_STEP_DEG = 1e-4


def true_north_azimuth(crs, lon_deg: float, lat_deg: float) -> float:
    """Azimuth of true north in the grid of a projected ``crs`` at (lon, lat): radians, clockwise from grid north.

    It is minus the meridian convergence as most texts define it (the angle from true north to grid
    north, positive when grid north lies east of true north).

    Parameters
    ----------
    crs : str or CRS
        A projected CRS (``EPSG:32634``, WKT, PROJ string).
    lon_deg, lat_deg : float
        The place, degrees on the datum of ``crs``.

    Raises
    ------
    CRSError
        ``crs`` is not projected, or PROJ cannot project the place.
    InvalidInputError
        The place is not finite or lies within 0.001 degrees of a pole.

    Examples
    --------
    >>> round(true_north_azimuth("EPSG:32634", 21.0, 30.0), 12)  # on the central meridian
    0.0
    >>> true_north_azimuth("EPSG:4326", 21.0, 30.0)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    rectify.errors.CRSError: true north in a grid needs a projected CRS; got 'WGS 84' ...
    """
    c = parse_crs(crs)
    if not c.is_projected:
        raise CRSError(f"true north in a grid needs a projected CRS; got {c.name!r} (geographic or geocentric)")
    lon, lat = float(lon_deg), float(lat_deg)
    if not (math.isfinite(lon) and math.isfinite(lat)) or abs(lat) > 90.0 - 1e-3:
        raise InvalidInputError(f"true north needs a finite place away from the poles; got lon {lon!r}, "
                                f"lat {lat!r}")
    p = map_from_geodetic([[lon, lat + _STEP_DEG, 0.0], [lon, lat - _STEP_DEG, 0.0]], c)
    v = p[0, :2] - p[1, :2]
    return float(math.atan2(v[0], v[1]))


def grid_from_enu(crs, lon_deg: float, lat_deg: float) -> NDArray[np.float64]:
    """Rotation (3, 3) taking ENU vectors at (lon, lat) into the grid frame of the projected ``crs``.

    ``Rz(-a)`` with ``a`` = :func:`true_north_azimuth`; the vertical is kept.

    Examples
    --------
    >>> R = grid_from_enu("EPSG:32634", 24.0, -33.0)  # 3 degrees west of the central meridian
    >>> bool(np.allclose(R @ R.T, np.eye(3)))
    True
    """
    return np.asarray(rot_z(-true_north_azimuth(crs, lon_deg, lat_deg)), dtype=np.float64)
