"""The truth side of sigma_Z checks on a rendered block (tests/stereo/test_surface_fusion.py,
scripts/surface_sigma_study.py).

:func:`reliability` is the reliability table of a DSM's standard errors (per sigma quantile bin the
RMS of the errors, of the sigmas and of their ratio). :func:`realised_orientation_error` splits the
orientation's share off a fused DSM's error: per cell, the error its provenance pair's orientation
alone makes, i.e. the true surface point projected with the true poses (what a perfect matcher
finds) and the two rays intersected with the orientation's poses (midpoint of their closest
approach). That share is common to every pair at a place, and over a block it is one draw of the
orientation's (mostly datum) error, so one block cannot check its sigma (``docs/surface.md``); the
rest, ``error - realised``, checks the per-cell (disparity) share. :func:`orientation_sigma_from_covariance`
propagates a bundle's full pose covariance (the correlations between the poses included) to the same
cells: the orientation's share of sigma_Z as the bundle's model has it, to compare with the points'
field that ``stereo surface`` takes.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from affine import Affine
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.types import Pose
from stereo.formats.block import read_block_orientation
from tests.support.block_surface import SurfaceBlock

__all__ = ["orientation_sigma_from_covariance", "realised_orientation_error", "reliability"]


def reliability(err: NDArray[np.float64], sigma: NDArray[np.float64], bins: int = 10
                ) -> list[tuple[float, float, float, float, float, int]]:
    """Per sigma quantile bin: (sigma lo, sigma hi, RMS error, RMS sigma, RMS(error / sigma), cells)."""
    q = np.quantile(sigma, np.linspace(0, 1, bins + 1))
    rows = []
    for i in range(bins):
        m = (sigma >= q[i]) & ((sigma < q[i + 1]) if i < bins - 1 else (sigma <= q[i + 1]))
        z = err[m] / sigma[m]
        rows.append((float(q[i]), float(q[i + 1]), float(np.sqrt(np.mean(err[m] ** 2))),
                     float(np.sqrt(np.mean(sigma[m] ** 2))), float(np.sqrt(np.mean(z ** 2))), int(m.sum())))
    return rows


def _rays(camera: Camera, pose: Pose, pixel: NDArray[np.float64]) -> NDArray[np.float64]:
    ph = camera.photo_from_pixel(pixel)
    d = np.column_stack([ph, np.full(len(ph), -camera.focal_length_mm)]) @ pose.rotation.T
    return np.asarray(d / np.linalg.norm(d, axis=1, keepdims=True))


def _intersect(a: NDArray[np.float64], da: NDArray[np.float64], b: NDArray[np.float64], db: NDArray[np.float64]
               ) -> NDArray[np.float64]:
    """(N, 3) midpoints of the closest approach of the rays ``a + s da`` and ``b + t db``."""
    w0 = a - b
    aa, bb, cc = (da * da).sum(1), (da * db).sum(1), (db * db).sum(1)
    d, e = (da * w0).sum(1), (db * w0).sum(1)
    den = aa * cc - bb * bb
    s, t = (bb * e - cc * d) / den, (aa * e - bb * d) / den
    return np.asarray(0.5 * (a + s[:, None] * da + b + t[:, None] * db))


def realised_orientation_error(blk: SurfaceBlock, camera: Camera, orientation: str | Path,
                               pairs: Sequence[tuple[str, str]], transform: Affine, provenance: NDArray[np.float64],
                               cells: NDArray[np.bool_]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The orientation's error of each selected DSM cell, through the cell's provenance pair.

    Parameters
    ----------
    blk : SurfaceBlock
        The rendered block (its terrain and true poses).
    camera : Camera
        The block's camera.
    orientation : path
        The block orientation JSON whose poses made the DSM (e.g. ``stereo block``'s).
    pairs : sequence of (left, right) image names
        The DSM's pairs, in the order of its provenance band.
    transform : Affine
        The DSM grid's transform.
    provenance : (H, W) array
        The DSM's provenance band.
    cells : (H, W) bool
        The cells wanted (with a provenance).

    Returns
    -------
    dz : (N,) float64
        Height error (ground units) that the pair's orientation alone makes at each wanted cell, in
        row-major order of ``cells``.
    xy : (N, 2) float64
        The cells' centres.
    """
    est = {p.image: p for p in read_block_orientation(orientation).poses}
    true = {p.image: p for p in blk.true_poses}
    X = _cells_xyz(blk, transform, cells)
    xy = X[:, :2]
    dz = np.full(len(X), np.nan)
    pv = np.asarray(provenance)[cells].astype(int)
    for _k, left, right, m, pa, pb in _pair_pixels(pairs, pv, true, camera, X):
        ea, eb = est[left], est[right]
        dz[m] = _intersect(ea.position, _rays(camera, ea, pa), eb.position, _rays(camera, eb, pb))[:, 2] - X[m, 2]
    return dz, xy


def _pair_pixels(pairs: Sequence[tuple[str, str]], provenance: NDArray[np.int_], true: dict[str, Pose],
                 camera: Camera, X: NDArray[np.float64]
                 ) -> Iterator[tuple[int, str, str, NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]]:
    """Per pair k with cells (provenance == k): k, its images, the cells' mask and their true pixels (N, 2) in the
    left and the right image (the true poses)."""
    for k, (left, right) in enumerate(pairs):
        m = provenance == k
        if m.any():
            yield k, left, right, m, true[left].pixel_from_ground(camera, X[m]), true[right].pixel_from_ground(camera,
                                                                                                            X[m])


def _cells_xyz(blk: SurfaceBlock, transform: Affine, cells: NDArray[np.bool_]) -> NDArray[np.float64]:
    rows, cols = np.nonzero(cells)
    xy = np.column_stack([transform.c + transform.a * (cols + 0.5), transform.f + transform.e * (rows + 0.5)])
    return np.column_stack([xy, blk.terrain.height(xy)])


def _height(camera: Camera, a: Pose, b: Pose, pa: NDArray[np.float64], pb: NDArray[np.float64]) -> NDArray[np.float64]:
    return _intersect(a.position, _rays(camera, a, pa), b.position, _rays(camera, b, pb))[:, 2]


def orientation_sigma_from_covariance(blk: SurfaceBlock, camera: Camera, poses: Sequence[Pose],
                                      covariance: NDArray[np.float64], pairs: Sequence[tuple[str, str]],
                                      transform: Affine, provenance: NDArray[np.float64], cells: NDArray[np.bool_]
                                      ) -> NDArray[np.float64]:
    """The height standard error the poses' covariance gives each selected cell through its provenance pair.

    Parameters
    ----------
    blk, camera, pairs, transform, provenance, cells :
        As :func:`realised_orientation_error`.
    poses : sequence of Pose
        The adjusted poses, in the order of ``covariance``.
    covariance : (6 n, 6 n) array
        Their joint covariance, per pose omega, phi, kappa (rad; ``R = matrix_from_angles(omega, phi,
        kappa)``), x, y, z (ground units).

    Returns
    -------
    (N,) float64
        ``sqrt(J C J^T)`` per cell, ``J`` the derivative of the height intersected from the pair's two
        rays (the true surface point's pixels) with respect to the pair's 12 pose elements (central
        differences).
    """
    C = np.asarray(covariance, dtype=np.float64)
    index = {p.image: k for k, p in enumerate(poses)}
    est = {p.image: p for p in poses}
    true = {p.image: p for p in blk.true_poses}
    X = _cells_xyz(blk, transform, cells)
    pv = np.asarray(provenance)[cells].astype(int)
    out = np.full(len(X), np.nan)

    def moved(p: Pose, k: int, h: float) -> Pose:
        d = np.zeros(6)
        d[k] = h
        return Pose(p.image, p.camera, p.position + d[3:], matrix_from_angles(*(np.asarray(p.angles) + d[:3])))

    for _n, left, right, m, pa, pb in _pair_pixels(pairs, pv, true, camera, X):

        J = np.zeros((int(m.sum()), 12))
        for k in range(6):
            h = 1e-6 if k < 3 else 1e-3
            ea, eb = est[left], est[right]
            J[:, k] = (_height(camera, moved(ea, k, h), eb, pa, pb)
                       - _height(camera, moved(ea, k, -h), eb, pa, pb)) / (2 * h)
            J[:, 6 + k] = (_height(camera, ea, moved(eb, k, h), pa, pb)
                           - _height(camera, ea, moved(eb, k, -h), pa, pb)) / (2 * h)
        ii = np.r_[6 * index[left] + np.arange(6), 6 * index[right] + np.arange(6)]
        out[m] = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", J, C[np.ix_(ii, ii)], J), 0.0))
    return out
