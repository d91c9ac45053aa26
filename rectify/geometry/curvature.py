"""Earth curvature in a block: seed 004's sphere formulas (1)-(3), the exact sphere and the exact ellipsoid.

A point A at height ``h`` (m, along the normal) whose foot lies at the distance ``s`` (m, along the
level surface) from the block's centre O. The topocentric frame has its origin at O on the level
surface, its z axis along the normal at O and its plan axes in the tangent plane (seed 004, eq. 5).
With ``theta = s / R`` on a sphere of radius ``R``, the exact topocentric coordinates of A are

    plan = (R + h) sin(theta),    height = (R + h) cos(theta) - R        (:func:`sphere_exact`).

Seed 004 gives two ways of recomputing map-like coordinates (plan distance along the level
surface, height along the normal) into the topocentric frame:

* "unrolling" (разворачивание, eq. 1): the plan coordinate is ``s`` unchanged and
  ``H_T = [h - ((R + h) / cos(theta) - R - h)] cos(theta)`` (:func:`unrolling_height`);
* "projection" (проектирование, eqs. 2-3): ``H_T = [h - (R / cos(theta) - R)] cos(theta)``
  (:func:`projection_height`; exact on the sphere) and the plan distance corrected by
  ``Delta_s = [h - (R / cos(theta) - R)] sin(theta)`` (:func:`projection_plan_correction`).

Eq. 2 is printed ``Delta_s = [h - (R / cos(theta) - R) sin(theta)]``: the bracket closes after
``sin(theta)`` instead of before it, which makes Delta_s about ``h`` (kilometres for a mountain
block) and dimensionally a height, not a plan correction. The corrected form is the plan component
of the segment of the plumb line from the tangent plane to A, whose vertical component is eq. 3:
both follow from the same right triangle (the plumb line meets the tangent plane at the distance
``R tan(theta)`` from O, at ``R / cos(theta)`` from the centre). The printed form is kept as
:func:`printed_eq2` for the record. Eq. 2 then places A at ``R tan(theta) + Delta_s``; the seed
lays out ``s`` instead of ``R tan(theta)``, an approximation of ``R (tan(theta) - theta)``, about
``s^3 / (3 R^2)`` (0.07 m at 20 km).

The seed's claim (unrolling section) that the laid-out arc differs from its orthogonal projection
by at most 0.03 m for a block up to 40 km across is ``s - R sin(s / R)`` (about ``s^3 / (6 R^2)``)
at ``s`` = 20 km: 0.033 m on the level surface (:func:`arc_minus_chord`); see docs/curvature.md for
where it fails (heights above the level surface, the full 40 km arc).

The exact ellipsoidal model (:func:`ellipsoid_exact`) places A at the geodesic distance ``s`` and
azimuth ``alpha`` from O (PROJ's azimuthal equidistant projection about O) and converts it to ENU at
O through geocentric coordinates (seed 004, eqs. 4-5).

Units: metres and radians; the origin's longitude and latitude in degrees (the CRS boundary).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.geodesy import (
    WGS84,
    Ellipsoid,
    ecef_from_geodetic,
    ellipsoid_of,
    enu_from_ecef,
    geodetic_from_map,
)

__all__ = [
    "EARTH_RADIUS_M", "CURVATURE_MODELS", "gaussian_radius", "arc_minus_chord", "height_drop", "sphere_exact",
    "unrolling_height", "projection_height", "projection_plan_correction", "printed_eq2", "model_coordinates",
    "model_errors", "ellipsoid_exact",
]

F64 = NDArray[np.float64]

#: mean Earth radius (m), the seed's "mean radius of curvature of the geoid" when none is given
EARTH_RADIUS_M = 6_371_000.0
#: the models of :func:`model_coordinates`: map coordinates taken as Cartesian ("none"), seed 004's
#: unrolling (eq. 1) and projection (eqs. 2-3, eq. 2 corrected)
CURVATURE_MODELS = ("none", "unrolling", "projection")


def _arrays(s: ArrayLike, h: ArrayLike, R: float) -> tuple[F64, F64, float]:
    sa, ha = np.broadcast_arrays(np.asarray(s, dtype=np.float64), np.asarray(h, dtype=np.float64))
    r = float(R)
    if not (math.isfinite(r) and r > 0):
        raise InvalidInputError(f"the radius R must be a finite number > 0 (m); got {R!r}")
    if not (np.isfinite(sa).all() and np.isfinite(ha).all()):
        raise InvalidInputError("distances s and heights h must be finite")
    if np.any(np.abs(sa) >= 0.5 * math.pi * r):
        raise InvalidInputError(f"distances must be below a quarter meridian (pi R / 2 = {0.5 * math.pi * r:.0f} m)")
    return np.array(sa, dtype=np.float64), np.array(ha, dtype=np.float64), r


def gaussian_radius(lat_deg: float, ellipsoid: Ellipsoid | None = None) -> float:
    """The Gaussian mean radius of curvature sqrt(M N) (m) of the ellipsoid at latitude ``lat_deg``.

    M is the meridian radius a (1 - e2) / W^3, N the prime-vertical radius a / W, W = sqrt(1 - e2 sin^2 B).

    >>> round(gaussian_radius(0.0) / 1000, 1), round(gaussian_radius(45.0) / 1000, 1)
    (6356.8, 6378.1)
    """
    a, e2 = ellipsoid if ellipsoid is not None else ellipsoid_of(WGS84)
    w2 = 1.0 - e2 * math.sin(math.radians(lat_deg)) ** 2
    return float(a * math.sqrt(1.0 - e2) / w2)


def arc_minus_chord(s: ArrayLike, R: float = EARTH_RADIUS_M) -> F64:
    """``s - R sin(s / R)``: the arc laid out unchanged minus its orthogonal projection on the tangent plane, m.

    Seed 004's "0.03 m at 40 km" is this at s = 20 km:

    >>> round(float(arc_minus_chord(20_000.0)), 4)
    0.0328
    """
    sa, _, r = _arrays(s, 0.0, R)
    return np.asarray(sa - r * np.sin(sa / r), dtype=np.float64)


def height_drop(s: ArrayLike, R: float = EARTH_RADIUS_M) -> F64:
    """``R (1 - cos(s / R))`` (about s^2 / 2R): how far the level surface lies below the tangent plane at s, m.

    >>> round(float(height_drop(14_000.0)), 1)
    15.4
    """
    sa, _, r = _arrays(s, 0.0, R)
    return np.asarray(r * (1.0 - np.cos(sa / r)), dtype=np.float64)


def sphere_exact(s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> tuple[F64, F64]:
    """Exact topocentric plan distance and height of a point at arc ``s`` and height ``h`` on a sphere.

    Returns
    -------
    plan, height : float64 arrays (broadcast shape of s, h), m
        ``(R + h) sin(s / R)`` and ``(R + h) cos(s / R) - R``.
    """
    sa, ha, r = _arrays(s, h, R)
    t = sa / r
    return (r + ha) * np.sin(t), (r + ha) * np.cos(t) - r


def unrolling_height(s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> F64:
    """Seed 004, eq. 1 (unrolling): ``H_T = [h - ((R + h) / cos(s/R) - R - h)] cos(s/R)``, m."""
    sa, ha, r = _arrays(s, h, R)
    c = np.cos(sa / r)
    return np.asarray((ha - ((r + ha) / c - r - ha)) * c, dtype=np.float64)


def projection_height(s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> F64:
    """Seed 004, eq. 3 (projection): ``H_T = [h - (R / cos(s/R) - R)] cos(s/R)``, m (exact on the sphere)."""
    sa, ha, r = _arrays(s, h, R)
    c = np.cos(sa / r)
    return np.asarray((ha - (r / c - r)) * c, dtype=np.float64)


def projection_plan_correction(s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> F64:
    """Seed 004, eq. 2 corrected: ``Delta_s = [h - (R / cos(s/R) - R)] sin(s/R)``, m.

    The plan component of the plumb line from the tangent plane (met at ``R tan(s/R)`` from O) up
    to the point; the printed bracket is :func:`printed_eq2`.

    >>> round(float(projection_plan_correction(20_000.0, 2000.0)), 3)
    6.18
    """
    sa, ha, r = _arrays(s, h, R)
    t = sa / r
    return np.asarray((ha - (r / np.cos(t) - r)) * np.sin(t), dtype=np.float64)


def printed_eq2(s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> F64:
    """Seed 004, eq. 2 as printed: ``[h - (R / cos(s/R) - R) sin(s/R)]`` -- wrong (about ``h``), kept for the record.

    >>> round(float(printed_eq2(20_000.0, 2000.0)), 1)
    1999.9
    """
    sa, ha, r = _arrays(s, h, R)
    t = sa / r
    return np.asarray(ha - (r / np.cos(t) - r) * np.sin(t), dtype=np.float64)


def model_coordinates(model: str, s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> tuple[F64, F64]:
    """Topocentric plan distance and height (m) a model assigns to the point (arc ``s``, height ``h``).

    ``"none"``: ``(s, h)`` (map coordinates taken as Cartesian); ``"unrolling"``: ``(s, eq. 1)``;
    ``"projection"``: ``(s + Delta_s, eq. 3)`` with the corrected eq. 2 (the seed's layout of
    ``s`` in place of ``R tan(s/R)``).
    """
    if model not in CURVATURE_MODELS:
        raise InvalidInputError(f"unknown curvature model {model!r}; expected one of {list(CURVATURE_MODELS)}")
    sa, ha, r = _arrays(s, h, R)
    if model == "none":
        return sa, ha
    if model == "unrolling":
        return sa, unrolling_height(sa, ha, r)
    return sa + projection_plan_correction(sa, ha, r), projection_height(sa, ha, r)


def model_errors(model: str, s: ArrayLike, h: ArrayLike, R: float = EARTH_RADIUS_M) -> tuple[F64, F64]:
    """Plan and height errors (model minus exact sphere, m) of a model at arc ``s`` and height ``h``.

    >>> [round(float(v), 3) for v in model_errors("none", 20_000.0, 0.0)]
    [0.033, 31.392]
    """
    plan, height = model_coordinates(model, s, h, R)
    p0, h0 = sphere_exact(s, h, R)
    return plan - p0, height - h0


def ellipsoid_exact(origin_lon_deg: float, origin_lat_deg: float, azimuth_rad: ArrayLike, s: ArrayLike,
                    h: ArrayLike, *, crs=WGS84) -> F64:
    """ENU coordinates (m) at the origin (on the ellipsoid) of points at geodesic distance ``s`` and height ``h``.

    Parameters
    ----------
    origin_lon_deg, origin_lat_deg : float
        The block's centre, degrees, on the datum of ``crs``.
    azimuth_rad, s, h : array_like, broadcast to one shape S
        Azimuth from north towards east (rad), geodesic distance on the ellipsoid (m), ellipsoidal height (m).

    Returns
    -------
    S + (3,) float64
        East, north, up. The exact "height drop" of a point at h = 0 is ``-up``; its plan error
        when the map distance ``s`` is taken as Cartesian is ``s - hypot(east, north)``.
    """
    az, sa, ha = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (azimuth_rad, s, h)))
    if not (np.isfinite(az).all() and np.isfinite(sa).all() and np.isfinite(ha).all()):
        raise InvalidInputError("azimuths, distances and heights must be finite")
    lon0, lat0 = float(origin_lon_deg), float(origin_lat_deg)
    if not (math.isfinite(lon0) and math.isfinite(lat0) and abs(lat0) < 89.0):
        raise InvalidInputError(f"the origin must be finite and away from the poles; got lon {lon0!r}, lat {lat0!r}")
    ell = ellipsoid_of(crs)
    b = ell.a * math.sqrt(1.0 - ell.e2)
    aeqd = f"+proj=aeqd +lat_0={lat0!r} +lon_0={lon0!r} +a={ell.a!r} +b={b!r} +units=m +no_defs +type=crs"
    xyh = np.column_stack([(sa * np.sin(az)).ravel(), (sa * np.cos(az)).ravel(), ha.ravel()])
    llh = geodetic_from_map(xyh, aeqd)
    enu = enu_from_ecef(ecef_from_geodetic(llh, crs=crs), (lon0, lat0, 0.0), crs=crs)
    return enu.reshape(*sa.shape, 3)
