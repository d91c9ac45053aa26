"""Seamlines of the least-transformed image (seed 003, section 4.2.1), on a coarse grid of zones.

Seed 003 (4.2.1) builds a combined orthophoto by taking each part of the surface from the image on which it
"came out best": the one seen at the smallest angle to the surface normal, i.e. the one that underwent the
least transformation in the orthorectification. Per zone (a square of ``zone`` x ``zone`` output pixels)
and per orthophoto i with projection centre C_i, at the zone's ground point P = (x, y, Z(x, y)) on the DSM:

* the ray u_i = (C_i - P) / |C_i - P| (unit, towards the camera);
* the nadir angle ``nu_i = acos(u_i . e_z)`` (the angle between the ray and the vertical: it grows with the
  distance from the image's ground nadir);
* the normal angle ``alpha_i = acos(u_i . n)`` with n the DSM's upward unit normal
  ``(-dZ/dx, -dZ/dy, 1) / norm`` (central differences on the zone grid);
* the criterion ``c_i = (1 - w) nu_i + w alpha_i`` (radians; ``w`` the normal weight, 0.5 by default). Over
  flat ground n = e_z and both angles agree; on a slope the image looking at the slope face wins.

An image is a candidate in a zone when at least half of the zone's samples are valid in it (inside its
footprint and, for a true orthophoto, not occluded: visibility band 2); when no image reaches half, those
with the largest share are. The zone takes the candidate with the smallest criterion, smoothed over the
zones by a Gaussian of sigma ``radius`` zones (DSM noise flips single zones otherwise); a majority filter
((2 ``radius`` + 1)^2 zones, ``iterations`` passes, restricted to candidates) then removes isolated zones,
so seams are few and follow the choice. Each image's region is turned into a signed distance (zones, positive inside),
which the mosaic engine interpolates bilinearly at every output pixel: the seam is where two signed
distances are equal, a smooth line through the zone grid, and the feathering weights follow from the
distances (:mod:`rectify.raster.mosaic`).

Arrays here are (rows, cols) of the zone grid; ground coordinates in the mosaic's CRS units, heights in
metres; angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError

__all__ = ["SeamPlan", "surface_normals", "view_angles", "criterion", "choose", "majority", "mask_distance",
           "signed_distance", "plan_seams"]

#: signed distance (zones) of an image chosen nowhere: far outside everywhere
FAR = 1.0e6


def surface_normals(Z: NDArray[np.float64], spacing: float) -> NDArray[np.float64]:
    """Upward unit normals (rows, cols, 3) of heights Z (rows, cols) on a square grid of ``spacing`` units.

    Rows go south (y down), so dZ/dy = -dZ/drow / spacing. Cells whose neighbours lack a height get the
    vertical (0, 0, 1).
    """
    z = np.asarray(Z, dtype=np.float64)
    if z.ndim != 2:
        raise InvalidInputError(f"heights must be a 2-D grid; got shape {z.shape}")
    if z.shape[0] < 2 or z.shape[1] < 2:
        gx = np.zeros_like(z)
        gy = np.zeros_like(z)
    else:
        grads = np.gradient(z, spacing)
        gx, gy = np.asarray(grads[1]), -np.asarray(grads[0])
    n = np.stack([-gx, -gy, np.ones_like(z)], axis=-1)
    bad = ~np.isfinite(n).all(axis=-1)
    n[bad] = (0.0, 0.0, 1.0)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def view_angles(centre: NDArray[np.float64], X: NDArray, Y: NDArray, Z: NDArray,
                normals: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Nadir angle and normal angle (radians, each (rows, cols)) of the rays from ground (X, Y, Z) to ``centre``.

    ``centre`` (3,): projection centre (x, y, z); ``normals`` (rows, cols, 3) upward unit normals.
    """
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    u = np.stack([c[0] - X, c[1] - Y, c[2] - Z], axis=-1)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    nadir = np.arccos(np.clip(u[..., 2], -1.0, 1.0))
    normal = np.arccos(np.clip(np.einsum("...k,...k->...", u, normals), -1.0, 1.0))
    return nadir, normal


def criterion(centres: NDArray[np.float64], X: NDArray, Y: NDArray, Z: NDArray, normals: NDArray[np.float64],
              weight: float) -> NDArray[np.float64]:
    """The least-transformation criterion (n, rows, cols), radians: ``(1 - weight) nadir + weight normal``."""
    out = []
    for c in np.asarray(centres, dtype=np.float64).reshape(-1, 3):
        nu, al = view_angles(c, X, Y, Z, normals)
        out.append((1.0 - weight) * nu + weight * al)
    return np.stack(out)


def candidates(share: NDArray[np.float64], min_share: float = 0.5) -> NDArray[np.bool_]:
    """Images that may fill each zone (n, rows, cols): valid share >= ``min_share``, else the largest share."""
    s = np.asarray(share, dtype=np.float64)
    best = s.max(axis=0)
    return (s > 0) & ((s >= min_share) | (s >= best[None] - 1e-12))


def choose(cost: NDArray[np.float64], cand: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Per zone the candidate with the smallest cost (rows, cols); -1 where no image is valid."""
    c = np.where(cand, cost, np.inf)
    lab = np.argmin(c, axis=0).astype(np.int64)
    lab[~cand.any(axis=0)] = -1
    return lab


def majority(labels: NDArray[np.int64], cand: NDArray[np.bool_], radius: int, iterations: int = 2
             ) -> NDArray[np.int64]:
    """Majority filter of the zone labels over (2 radius + 1)^2 zones, restricted to each zone's candidates.

    A zone changes to the label most frequent in its neighbourhood when that label is a candidate there and
    strictly more frequent than the zone's own; ties keep the zone's label. Zones without a candidate stay -1.
    """
    lab = np.asarray(labels, dtype=np.int64).copy()
    n = cand.shape[0]
    if radius <= 0 or n < 2:
        return lab
    k = 2 * radius + 1
    for _ in range(iterations):
        counts = np.stack([cv2.boxFilter((lab == i).astype(np.float32), -1, (k, k), normalize=False,
                                         borderType=cv2.BORDER_CONSTANT) for i in range(n)])
        counts = np.where(cand, counts, -1.0)
        best = np.argmax(counts, axis=0)
        own = np.take_along_axis(counts, np.clip(lab, 0, None)[None], axis=0)[0]
        top = np.take_along_axis(counts, best[None], axis=0)[0]
        new = np.where((lab >= 0) & (top > own), best, lab)
        if np.array_equal(new, lab):
            break
        lab = new
    return lab


def mask_distance(inside: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Signed distance (rows, cols) of each zone centre to the edge of the region ``inside``, in zones:
    positive inside, negative outside, 0 half-way between an inside and an outside zone centre;
    -:data:`FAR` everywhere for an empty region, +:data:`FAR` for a full one."""
    if not inside.any():
        return np.full(inside.shape, -FAR, np.float32)
    if inside.all():
        return np.full(inside.shape, FAR, np.float32)
    # distanceTransform: distance from each non-zero pixel to the nearest zero pixel
    d_in = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_out = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(inside, d_in - 0.5, -(d_out - 0.5)).astype(np.float32)


def signed_distance(labels: NDArray[np.int64], n: int) -> NDArray[np.float32]:
    """Signed distance (n, rows, cols) of each zone centre to the edge of image i's region, in zones
    (:func:`mask_distance` of ``labels == i``): 0 on the seam; an image chosen nowhere gets -:data:`FAR`."""
    return np.stack([mask_distance(labels == i) for i in range(n)])


@dataclass(frozen=True, eq=False)
class SeamPlan:
    """The zone grid of a mosaic's seams.

    Attributes
    ----------
    zone : int
        Zone size, output pixels; zone (r, c) covers output rows r*zone .. (r+1)*zone - 1.
    labels : (rows, cols) int64
        Chosen image per zone after smoothing (-1: none valid).
    raw : (rows, cols) int64
        The choice before smoothing.
    cost : (n, rows, cols) float64
        The criterion, radians.
    sdist : (n, rows, cols) float32
        Signed distance to each image's region, zones (:func:`signed_distance`).
    """

    zone: int
    labels: NDArray[np.int64]
    raw: NDArray[np.int64]
    cost: NDArray[np.float64]
    sdist: NDArray[np.float32]

    @property
    def changed(self) -> int:
        """Zones the majority filter changed."""
        return int((self.labels != self.raw).sum())

    def regions(self) -> int:
        """Connected regions (4-connected) of one chosen image: 1 per image means one zone per image."""
        return sum(int(cv2.connectedComponents((self.labels == i).astype(np.uint8), connectivity=4)[0]) - 1
                   for i in range(self.cost.shape[0]))

    def seam_edges(self) -> int:
        """Zone edges between two different chosen images (a measure of the seams' length, in zones)."""
        lab = self.labels
        h = (lab[:, 1:] != lab[:, :-1]) & (lab[:, 1:] >= 0) & (lab[:, :-1] >= 0)
        v = (lab[1:, :] != lab[:-1, :]) & (lab[1:, :] >= 0) & (lab[:-1, :] >= 0)
        return int(h.sum() + v.sum())


def plan_seams(centres: NDArray[np.float64], X: NDArray, Y: NDArray, Z: NDArray, share: NDArray[np.float64], *,
               zone: int, spacing: float, weight: float = 0.5, radius: int = 1, iterations: int = 2) -> SeamPlan:
    """The seam plan of zones at ground (X, Y) with DSM heights Z (rows, cols; NaN: none).

    ``centres`` (n, 3) projection centres; ``share`` (n, rows, cols) valid share of each image per zone;
    ``spacing`` the zone size in ground units (for the normals). Zones without a height take the median
    height of the others (the normal is then vertical).
    """
    if not 0.0 <= weight <= 1.0:
        raise InvalidInputError(f"the normal weight must lie in 0..1; got {weight!r}")
    z = np.asarray(Z, dtype=np.float64)
    if not np.isfinite(z).any():
        raise InvalidInputError("the DSM has no height under the mosaic")
    normals = surface_normals(z, spacing)
    zf = np.where(np.isfinite(z), z, float(np.nanmedian(z)))
    cost = criterion(centres, X, Y, zf, normals, weight)
    cand = candidates(share)
    raw = choose(cost, cand)
    smooth = cost
    if radius > 0:  # the criterion smoothed over the zones first (a Gaussian of sigma ``radius`` zones)
        smooth = np.stack([cv2.GaussianBlur(c, (0, 0), sigmaX=float(radius), borderType=cv2.BORDER_REFLECT)
                           for c in cost])
    lab = majority(choose(smooth, cand), cand, radius, iterations)
    return SeamPlan(zone, lab, raw, cost, signed_distance(lab, cost.shape[0]))
