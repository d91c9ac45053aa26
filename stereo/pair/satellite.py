"""Seed 001's processing of space images: rays of satellite frames in the geocentric frame and their intersection.

Seed 001 (steps 1, 4, 5) does the photogrammetry of space images in the geocentric rectangular frame:
the projection centres (given in Gauss-Krueger coordinates with normal heights) go to geodetic B, L, H
(the normal height plus the height anomaly of a quasi-geoid model gives the ellipsoidal height) and to
geocentric X, Y, Z (seed 001 step 5 formulas, :func:`rectify.geometry.geodesy.geocentric_from_blh_formula`);
the image points give rays; the rays are intersected in the geocentric frame; the points go back to
B, L, H (iterated, :func:`rectify.geometry.geodesy.blh_from_geocentric_formula`) and to Gauss-Krueger
with normal heights.

Frames and units:

- photo coordinates: mm from the principal point, x right, y up; the image vector is ``(x, y, -f)``;
- platform (body) frame: x right, y forward, z up; a frame camera looking down along -z;
- attitude: heading (from north towards east), pitch and roll of the platform in the local level
  frame at the projection centre (seed 004, :func:`rectify.geometry.geodesy.enu_from_body`); at zero
  angles the photo x axis points east and y north;
- geocentric (ECEF) X, Y, Z in metres on the datum of the map CRS.

The intersection is least squares over two or more rays (the seed's two-ray factor
``N = (Bx + x2 Bz / f) / (x1 - x2)`` is its special case for horizontal frames along the base, see
:func:`stereo.pair.intersection.n_factor_seed001`): a ray k from ``O_k`` along the unit vector
``d_k`` gives two observations, the components of ``X - O_k`` perpendicular to ``d_k``, with the
standard deviation ``sigma_k * range_k / f_k`` (``sigma_k`` the image coordinate's, mm). The normal
matrix is ``sum w_k (I - d_k d_k^T)``; its inverse is the a-priori covariance of the point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.geodesy import enu_from_body, enu_rotation
from rectify.geometry.points import as_points

__all__ = ["RayIntersection", "ecef_directions", "intersect_rays"]

F64 = NDArray[np.float64]

#: rays meeting at less than this angle (radians) leave a point undetermined
MIN_INTERSECTION_ANGLE_RAD = 1e-4


def ecef_directions(photo_mm: ArrayLike, focal_mm: ArrayLike, attitude_rad: ArrayLike, lonlat_deg: ArrayLike) -> F64:
    """Unit ray directions (K, 3) in ECEF of image points.

    Parameters
    ----------
    photo_mm : (K, 2) float64
        Photo coordinates, mm from the principal point, x right, y up.
    focal_mm : (K,) float64
        Focal length of each point's image, mm.
    attitude_rad : (K, 3) float64
        Heading, pitch, roll of each point's image (radians) in the local level frame at its
        projection centre.
    lonlat_deg : (K, 2) float64
        Geodetic longitude and latitude of each point's projection centre, degrees.
    """
    p = as_points(photo_mm, "photo_mm", 2)
    k = len(p)
    f = np.asarray(focal_mm, dtype=np.float64).reshape(-1)
    a = np.asarray(attitude_rad, dtype=np.float64).reshape(k, 3)
    ll = np.asarray(lonlat_deg, dtype=np.float64).reshape(k, 2)
    if f.shape != (k,) or not (np.isfinite(f).all() and (f > 0).all()):
        raise InvalidInputError(f"focal lengths must be {k} finite numbers > 0")
    out = np.empty((k, 3))
    cache: dict[tuple[float, ...], F64] = {}
    for i in range(k):
        key = (*a[i], *ll[i])
        R = cache.get(key)
        if R is None:  # ECEF <- ENU at the centre <- body
            R = cache[key] = enu_rotation(float(ll[i, 0]), float(ll[i, 1])).T @ enu_from_body(*a[i])
        out[i] = R @ np.array([p[i, 0], p[i, 1], -f[i]])
    return np.asarray(out / np.linalg.norm(out, axis=1)[:, None], dtype=np.float64)


@dataclass(frozen=True, eq=False)
class RayIntersection:
    """Points intersected from rays (:func:`intersect_rays`).

    Attributes
    ----------
    points : (P, 3) float64
        Intersected points, the frame of the rays (ECEF, m).
    covariance : (P, 3, 3) float64
        A-priori covariance of each point (m^2), from the image sigmas.
    n_rays : (P,) int64
    rms_mm : (P,) float64
        RMS of the ray misclosures on the image, mm (perpendicular distance times f / range).
    sigma0 : float
        A-posteriori standard deviation of unit weight over all points (NaN without redundancy:
        two rays give one redundant observation per point).
    redundancy : int
        2 K - 3 P.
    """

    points: F64
    covariance: F64
    n_rays: NDArray[np.int64]
    rms_mm: F64
    sigma0: float
    redundancy: int


def intersect_rays(origins: ArrayLike, directions: ArrayLike, point_index: ArrayLike, sigma_mm: ArrayLike,
                   focal_mm: ArrayLike, n_points: int, *, iterations: int = 3) -> RayIntersection:
    """Least-squares intersection of rays grouped by point.

    Parameters
    ----------
    origins : (K, 3) float64
        Projection centre of each ray, m.
    directions : (K, 3) float64
        Unit direction of each ray.
    point_index : (K,) int
        The point (0 .. n_points - 1) each ray belongs to.
    sigma_mm, focal_mm : (K,) float64
        Standard deviation of the image coordinates and the focal length of each ray's image, mm.
    n_points : int
    iterations : int
        Re-weightings by the ranges of the previous solution (the first solution weights by the
        sigmas alone).

    Raises
    ------
    EstimationError
        A point with fewer than two rays, or rays (nearly) parallel, named by index.
    """
    org = as_points(origins, "origins", 3)
    D = as_points(directions, "directions", 3)
    k = len(org)
    idx = np.asarray(point_index).reshape(-1)
    s = np.asarray(sigma_mm, dtype=np.float64).reshape(-1)
    f = np.asarray(focal_mm, dtype=np.float64).reshape(-1)
    if D.shape != (k, 3) or idx.shape != (k,) or s.shape != (k,) or f.shape != (k,):
        raise InvalidInputError(f"origins, directions, point_index, sigma_mm and focal_mm must describe the same "
                                f"{k} rays")
    if not (np.issubdtype(idx.dtype, np.integer) and (idx >= 0).all() and (idx < n_points).all()):
        raise InvalidInputError(f"point_index must hold integers in [0, {n_points})")
    if not ((s > 0).all() and np.isfinite(s).all()):
        raise InvalidInputError("sigma_mm must be finite and > 0")
    D = D / np.linalg.norm(D, axis=1)[:, None]
    cnt = np.bincount(idx, minlength=n_points)
    if (cnt < 2).any():
        j = int(np.flatnonzero(cnt < 2)[0])
        raise EstimationError(f"point index {j} has {int(cnt[j])} ray(s); an intersection needs two")
    proj = np.eye(3)[None] - D[:, :, None] * D[:, None, :]         # (K, 3, 3) I - d d^T
    ang = s / f                                                     # angular sigma, rad
    rng = np.ones(k)
    X = np.zeros((n_points, 3))
    for _ in range(max(1, iterations)):
        w = 1.0 / (ang * rng) ** 2
        N = np.zeros((n_points, 3, 3))
        b = np.zeros((n_points, 3))
        np.add.at(N, idx, w[:, None, None] * proj)
        np.add.at(b, idx, w[:, None] * np.einsum("kij,kj->ki", proj, org))
        # conditioning: the smallest eigenvalue relative to the largest (sin^2 of the ray angle)
        ev = np.linalg.eigvalsh(N)
        bad = ~(ev[:, 0] > (MIN_INTERSECTION_ANGLE_RAD ** 2) * ev[:, 2])
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise EstimationError(f"point index {j}: its rays are (nearly) parallel; no intersection")
        X = np.asarray(np.linalg.solve(N, b[:, :, None])[:, :, 0], dtype=np.float64)
        rng = np.einsum("ki,ki->k", X[idx] - org, D)
        if (rng <= 0).any():
            j = int(idx[np.flatnonzero(rng <= 0)[0]])
            raise EstimationError(f"point index {j} lies behind one of its projection centres")
    w = 1.0 / (ang * rng) ** 2
    N = np.zeros((n_points, 3, 3))
    np.add.at(N, idx, w[:, None, None] * proj)
    cov = np.asarray(np.linalg.inv(N), dtype=np.float64)
    perp = np.einsum("kij,kj->ki", proj, X[idx] - org)                 # misclosure vectors, m
    img = np.linalg.norm(perp, axis=1) * f / rng                     # on the image, mm
    rms = np.sqrt(np.bincount(idx, weights=img ** 2, minlength=n_points) / cnt)
    red = 2 * k - 3 * n_points
    vtpv = float(np.sum(w * np.sum(perp ** 2, axis=1)))
    s0 = float(np.sqrt(vtpv / red)) if red > 0 else float("nan")
    return RayIntersection(points=X, covariance=cov, n_rays=cnt.astype(np.int64), rms_mm=rms, sigma0=s0,
                           redundancy=red)
