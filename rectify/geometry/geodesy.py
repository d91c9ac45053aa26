"""Map, geodetic, geocentric and local topocentric (ENU) coordinates.

Frames (all right-handed, metres unless stated):

- **map**: a projected CRS (UTM, Gauss-Krueger, ...), columns (E, N, h).
- **geodetic**: columns (lon, lat, h) -- longitude and latitude in
  *degrees* (the CRS boundary), ellipsoidal height ``h`` in metres. Always
  lon first (``always_xy``).
- **geocentric** (ECEF): X towards (lat 0, lon 0), Z towards the north pole,
  Y completing a right-handed frame, on the datum of the given CRS.
- **topocentric ENU** at an origin (lon0, lat0, h0): x east, y north, z up
  along the ellipsoid normal at the origin (seed 004, eq. 5, with its rows
  reordered east, north, up so the frame is right-handed; the seed's own
  order north, east, up is :func:`neu_from_enu`).

pyproj does every datum and projection computation (through
:mod:`rectify.geometry.crs`). Heights are ellipsoidal: the seeds' normal heights would
need a geoid model, which this project does not ship; pass heights that are
already ellipsoidal, or accept the geoid undulation (tens of metres) as a
known offset.

Seed 001 (step 5) gives closed formulas between geocentric X, Y, Z and
geodetic B, L, H; they are implemented in :func:`geocentric_from_blh_formula`
and :func:`blh_from_geocentric_formula` and tested against pyproj. Two
misprints of the seed are corrected: ``tg(L - L0) = Y / X`` (not X / Y) and
``H = X sec B sec(L - L0) - N = Y sec B cosec(L - L0) - N``. ``tg B`` depends
on N and H, so it is iterated (it converges to 1e-12 rad in a few steps).

Seed 004 gives the rotation of the navigation platform from heading, pitch
and roll (eqs. 6-10): :func:`navigation_matrix`; its eq. 7 is corrected to
``gamma = arccos(-tg(pitch) tg(roll))`` (the printed ``ctg`` makes
``gamma`` undefined at zero angles, where it must be 90 degrees).
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.crs import geocentric_wkt, geographic3d_wkt, parse_crs, transform_arrays, transform_xyz
from rectify.geometry.points import as_points

__all__ = [
    "Ellipsoid", "ellipsoid_of", "geographic3d_crs", "geocentric_crs",
    "ecef_from_geodetic", "geodetic_from_ecef",
    "enu_rotation", "enu_from_ecef", "ecef_from_enu",
    "geodetic_from_map", "map_from_geodetic", "ecef_from_map", "map_from_ecef",
    "enu_from_map", "map_from_enu", "neu_from_enu",
    "geocentric_from_blh_formula", "blh_from_geocentric_formula",
    "navigation_matrix", "enu_from_body",
]

logger = logging.getLogger(__name__)

WGS84 = "EPSG:4979"


class Ellipsoid(NamedTuple):
    """Reference ellipsoid: semi-major axis ``a`` (m) and first eccentricity squared ``e2``."""

    a: float
    e2: float


def ellipsoid_of(crs) -> Ellipsoid:
    """The ellipsoid of a CRS's datum.

    >>> round(ellipsoid_of("EPSG:32618").a)
    6378137
    """
    c = parse_crs(crs)
    ell = c.ellipsoid
    if ell is None:
        raise CRSError(f"CRS {c.name!r} has no ellipsoid")
    a = float(ell.semi_major_metre)
    b = float(ell.semi_minor_metre)
    return Ellipsoid(a, 1.0 - (b * b) / (a * a))


def geographic3d_crs(crs=WGS84) -> str:
    """WKT of the 3D geographic CRS (lon, lat, h) on the datum of ``crs``."""
    return geographic3d_wkt(parse_crs(crs).to_wkt())


def geocentric_crs(crs=WGS84) -> str:
    """WKT of the geocentric (ECEF) CRS on the datum of ``crs``."""
    return geocentric_wkt(parse_crs(crs).to_wkt())


# --------------------------------------------------------------- geodetic <-> ECEF
def ecef_from_geodetic(lonlat_h: ArrayLike, *, crs=WGS84) -> NDArray[np.float64]:
    """Geocentric X, Y, Z from geodetic lon, lat (degrees), h (m), through pyproj.

    Parameters
    ----------
    lonlat_h : (N, 3) float64
        Longitude, latitude (degrees), ellipsoidal height (m).
    crs : CRS, default WGS 84
        Any CRS whose datum is meant (a projected CRS selects its datum).

    Returns
    -------
    (N, 3) float64
        ECEF X, Y, Z in metres on that datum.
    """
    p = as_points(lonlat_h, "lonlat_h", 3)
    return transform_xyz(geographic3d_crs(crs), geocentric_crs(crs), p)


def geodetic_from_ecef(xyz: ArrayLike, *, crs=WGS84) -> NDArray[np.float64]:
    """Geodetic lon, lat (degrees), h (m) from ECEF X, Y, Z (m), through pyproj.

    Returns
    -------
    (N, 3) float64
    """
    p = as_points(xyz, "xyz", 3)
    return transform_xyz(geocentric_crs(crs), geographic3d_crs(crs), p)


# --------------------------------------------------------------- topocentric ENU
def enu_rotation(lon_deg: float, lat_deg: float) -> NDArray[np.float64]:
    """Rotation (3, 3) taking ECEF difference vectors into the ENU frame at (lon, lat).

    Rows are the east, north and up unit vectors in ECEF (seed 004, eq. 5, with
    its first two rows swapped).
    """
    lam, phi = math.radians(lon_deg), math.radians(lat_deg)
    sl, cl, sp, cp = math.sin(lam), math.cos(lam), math.sin(phi), math.cos(phi)
    return np.array([[-sl, cl, 0.0],
                     [-sp * cl, -sp * sl, cp],
                     [cp * cl, cp * sl, sp]])


def _origin(origin_lonlat_h: ArrayLike) -> NDArray[np.float64]:
    o = np.array(origin_lonlat_h, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.isfinite(o).all():
        raise InvalidInputError(f"`origin_lonlat_h` must be (lon_deg, lat_deg, h_m); got {origin_lonlat_h!r}")
    if not -90.0 <= o[1] <= 90.0:
        raise InvalidInputError(f"origin latitude must be within [-90, 90] degrees; got {o[1]!r}")
    return o


def enu_from_ecef(xyz: ArrayLike, origin_lonlat_h: ArrayLike, *, crs=WGS84) -> NDArray[np.float64]:
    """Local topocentric ENU coordinates of ECEF points.

    Parameters
    ----------
    xyz : (N, 3) float64
        ECEF X, Y, Z (m) on the datum of ``crs``.
    origin_lonlat_h : (3,) float
        Origin: lon, lat (degrees), ellipsoidal height (m).

    Returns
    -------
    (N, 3) float64
        East, north, up (m) from the origin.

    Examples
    --------
    >>> enu_from_ecef([[6378137.0, 0, 0]], (0.0, 0.0, 0.0)).round(6).tolist()
    [[0.0, 0.0, 0.0]]
    """
    p = as_points(xyz, "xyz", 3)
    o = _origin(origin_lonlat_h)
    o_xyz = ecef_from_geodetic(o[None, :], crs=crs)[0]
    return (p - o_xyz) @ enu_rotation(o[0], o[1]).T


def ecef_from_enu(enu: ArrayLike, origin_lonlat_h: ArrayLike, *, crs=WGS84) -> NDArray[np.float64]:
    """ECEF X, Y, Z of local ENU points (inverse of :func:`enu_from_ecef`).

    Parameters
    ----------
    enu : (N, 3) float64
        East, north, up (m) from the origin.
    origin_lonlat_h : (3,) float
        lon, lat (degrees), h (m).

    Returns
    -------
    (N, 3) float64
    """
    p = as_points(enu, "enu", 3)
    o = _origin(origin_lonlat_h)
    o_xyz = ecef_from_geodetic(o[None, :], crs=crs)[0]
    return p @ enu_rotation(o[0], o[1]) + o_xyz


def neu_from_enu(enu: ArrayLike) -> NDArray[np.float64]:
    """Seed 004's topocentric order (north, east, up) from ENU (a left-handed frame)."""
    p = as_points(enu, "enu", 3)
    return p[:, [1, 0, 2]].copy()


# --------------------------------------------------------------- map <-> others
def geodetic_from_map(xyh: ArrayLike, crs) -> NDArray[np.float64]:
    """(E, N, h) in the projected (or geographic) ``crs`` -> (lon, lat, h) on its datum.

    Heights pass through unchanged (ellipsoidal).
    """
    p = as_points(xyh, "xyh", 3)
    src = parse_crs(crs)
    if src.is_geocentric:
        raise CRSError(f"{src.name!r} is geocentric, not a map CRS; use geodetic_from_ecef")
    out = p.copy()
    if len(p):
        out[:, 0], out[:, 1] = transform_arrays(src, src.geodetic_crs, p[:, 0], p[:, 1],
                                                failure=f"cannot unproject points from {src.name!r}")
    return out


def map_from_geodetic(lonlat_h: ArrayLike, crs) -> NDArray[np.float64]:
    """(lon, lat, h) on the datum of ``crs`` -> (E, N, h) in ``crs``."""
    p = as_points(lonlat_h, "lonlat_h", 3)
    dst = parse_crs(crs)
    out = p.copy()
    if len(p):
        out[:, 0], out[:, 1] = transform_arrays(dst.geodetic_crs, dst, p[:, 0], p[:, 1],
                                                failure=f"cannot project points into {dst.name!r}")
    return out


def ecef_from_map(xyh: ArrayLike, crs) -> NDArray[np.float64]:
    """(E, N, h) in ``crs`` -> ECEF (m) on its datum."""
    return ecef_from_geodetic(geodetic_from_map(xyh, crs), crs=crs)


def map_from_ecef(xyz: ArrayLike, crs) -> NDArray[np.float64]:
    """ECEF (m) on the datum of ``crs`` -> (E, N, h) in ``crs``."""
    return map_from_geodetic(geodetic_from_ecef(xyz, crs=crs), crs)


def enu_from_map(xyh: ArrayLike, crs, origin_lonlat_h: ArrayLike) -> NDArray[np.float64]:
    """(E, N, h) in ``crs`` -> local ENU (m) at ``origin_lonlat_h`` (datum of ``crs``)."""
    return enu_from_ecef(ecef_from_map(xyh, crs), origin_lonlat_h, crs=crs)


def map_from_enu(enu: ArrayLike, crs, origin_lonlat_h: ArrayLike) -> NDArray[np.float64]:
    """Local ENU (m) at ``origin_lonlat_h`` -> (E, N, h) in ``crs``."""
    return map_from_ecef(ecef_from_enu(enu, origin_lonlat_h, crs=crs), crs)


# --------------------------------------------------------------- seed 001 formulas
def geocentric_from_blh_formula(blh_rad: ArrayLike, ellipsoid: Ellipsoid, *, lon0_rad: float = 0.0
                                ) -> NDArray[np.float64]:
    """Seed 001, step 5: X, Y, Z from B, L, H by the closed formulas.

    X = (N + H) cos B cos(L - L0); Y = (N + H) cos B sin(L - L0);
    Z = [N (1 - e^2) + H] sin B; N = a / sqrt(1 - e^2 sin^2 B).

    Parameters
    ----------
    blh_rad : (N, 3) float64
        Latitude B, longitude L (radians), height H (m) -- note the B, L order of the seed.
    ellipsoid : Ellipsoid
    lon0_rad : float
        L0, the longitude of the X axis (0 for ECEF).

    Returns
    -------
    (N, 3) float64, metres.
    """
    p = as_points(blh_rad, "blh_rad", 3)
    a, e2 = ellipsoid
    B, L, H = p[:, 0], p[:, 1] - lon0_rad, p[:, 2]
    N = a / np.sqrt(1.0 - e2 * np.sin(B) ** 2)
    return np.column_stack([(N + H) * np.cos(B) * np.cos(L), (N + H) * np.cos(B) * np.sin(L),
                            (N * (1.0 - e2) + H) * np.sin(B)])


def blh_from_geocentric_formula(xyz: ArrayLike, ellipsoid: Ellipsoid, *, lon0_rad: float = 0.0,
                                tol_rad: float = 1e-13, max_iter: int = 20) -> NDArray[np.float64]:
    """Seed 001, step 5: B, L, H from X, Y, Z by the closed formulas, iterated.

    tg B = Z / ([1 - e^2 N / (N + H)] sqrt(X^2 + Y^2)); tg(L - L0) = Y / X;
    H = sqrt(X^2 + Y^2) sec B - N (equal to the seed's X sec B sec(L - L0) - N)
    or, near the poles, H = Z cosec B - N (1 - e^2). Starting from H = 0, B and
    H are refined until B changes by less than ``tol_rad``.

    Returns
    -------
    (N, 3) float64
        B, L (radians), H (m).

    Raises
    ------
    InvalidInputError
        For points at the centre of the Earth.
    """
    p = as_points(xyz, "xyz", 3)
    a, e2 = ellipsoid
    X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
    r = np.hypot(X, Y)
    if ((r == 0) & (Z == 0)).any():
        raise InvalidInputError("a point is at the centre of the Earth; B is undefined")
    L = np.arctan2(Y, X) + lon0_rad
    B = np.arctan2(Z, r * (1.0 - e2))
    H = np.zeros_like(B)
    for _ in range(max_iter):
        N = a / np.sqrt(1.0 - e2 * np.sin(B) ** 2)
        polar = np.abs(B) > math.radians(45.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            H = np.where(polar, Z / np.sin(B) - N * (1.0 - e2), r / np.cos(B) - N)
        B_new = np.arctan2(Z, r * (1.0 - e2 * N / (N + H)))
        done = np.max(np.abs(B_new - B)) if len(B) else 0.0
        B = B_new
        if done < tol_rad:
            break
    N = a / np.sqrt(1.0 - e2 * np.sin(B) ** 2)
    polar = np.abs(B) > math.radians(45.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        H = np.where(polar, Z / np.sin(B) - N * (1.0 - e2), r / np.cos(B) - N)
    L = (L + np.pi) % (2 * np.pi) - np.pi
    return np.column_stack([B, L, H])


# --------------------------------------------------------------- seed 004 navigation
def navigation_matrix(heading: float, pitch: float, roll: float) -> NDArray[np.float64]:
    """Seed 004, eqs. 6-10: the platform rotation A from heading, pitch and roll.

    Parameters
    ----------
    heading : float
        Course angle (radians) of the platform's X' axis, from north towards east.
    pitch : float
        Elevation (radians) of the X' axis above the horizontal plane, measured in
        the vertical plane through X' (a great circle through the normal).
    roll : float
        Elevation (radians) of the Y' axis above the horizontal plane, likewise.
        |pitch|, |roll| < 90 degrees.

    Returns
    -------
    (3, 3) float64
        A = [e_X' e_Y' e_Z']: its columns are the platform axes (X' forward,
        Y' right, Z' = X' x Y') expressed in the seed's local frame (X north,
        Y east, Z up along the normal). At zero angles A is the identity.

    Notes
    -----
    e_X' = (cos d cos h, cos d sin h, sin d); gamma = arccos(-tan d tan r) is the
    horizontal angle from X' to Y' (the seed prints ``ctg``; the spherical cosine
    rule with side ab = 90 degrees gives ``tg``); e_Y' = (cos r cos(h + gamma),
    cos r sin(h + gamma), sin r); e_Z' = e_X' x e_Y'.

    Raises
    ------
    InvalidInputError
        If pitch and roll together make the axes impossible (|tan d tan r| > 1).
    """
    vals = np.array([heading, pitch, roll], dtype=np.float64)
    if not np.isfinite(vals).all():
        raise InvalidInputError(f"navigation angles must be finite; got {vals.tolist()}")
    h, d, r = (float(v) for v in vals)
    c = -math.tan(d) * math.tan(r)
    if abs(d) >= math.pi / 2 or abs(r) >= math.pi / 2 or abs(c) > 1.0:
        raise InvalidInputError(f"pitch {d!r} and roll {r!r} rad admit no orthogonal platform axes")
    g = math.acos(c)
    ex = np.array([math.cos(d) * math.cos(h), math.cos(d) * math.sin(h), math.sin(d)])
    ey = np.array([math.cos(r) * math.cos(h + g), math.cos(r) * math.sin(h + g), math.sin(r)])
    ez = np.cross(ex, ey)
    return np.column_stack([ex, ey, ez])


def enu_from_body(heading: float, pitch: float, roll: float) -> NDArray[np.float64]:
    """Rotation taking platform vectors (x right, y forward, z up) into ENU.

    The same rotation as :func:`navigation_matrix`, written in right-handed
    frames (both the seed's local frame and the platform frame have their
    first two axes swapped).

    Returns
    -------
    (3, 3) float64, a proper rotation (det +1).
    """
    P = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return P @ navigation_matrix(heading, pitch, roll) @ P
