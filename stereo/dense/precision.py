"""Height precision of dense points: disparity and orientation errors propagated to sigma_Z.

Everything here is first-order error propagation (``docs/surface.md`` has the derivations); the
functions take plain arrays, so that any pair geometry (frame pairs in the normal case, satellite
pairs in their epipolar frame) can use them.

Disparity precision
    :func:`disparity_sigma` is the standard error of the least-squares sub-pixel fit of a
    disparity along the row (the 1-D Lucas-Kanade step of :func:`stereo.dense.matching.refine_subpixel`):
    in a Gaussian window of ``radius`` pixels (weights ``w``, sigma ``radius / 2``) the residuals
    ``e = L(x) - R(x - d)`` (mean removed) and the x gradient ``g`` of the left photo give

    ``sigma_d^2 = var_w(e) / (n_eff * var_w(g)) + floor^2``,  ``n_eff = 1 / sum(w^2) = 4 pi (radius / 2)^2``

    (``var_w``: the weighted variance in the window). ``floor`` (default 0.05 px) stands for the
    errors the fit does not see (resampling of the photos into the normal case).
Normal case
    The depth along the normal frame's viewing axis is ``Z = B f / p`` (``B`` base length, ``f`` the
    principal distance in pixels, ``p`` the x-parallax in pixels), hence
    ``sigma_Z = Z^2 / (B f) * sigma_p``; a point moves along the left ray when ``p`` changes, so its
    height (ground z) changes by ``|z - z_C| / Z`` times that (:func:`height_sigma_disparity`).
Orientation, from the bundle's points
    :class:`PointSigmaField`: the height standard errors of the block's own points (tie points),
    which the bundle propagated from its full covariance (the correlations of the poses included),
    taken near each dense point (the median of the ``k`` nearest in plan). They include the tie
    points' own measurement error too, but at the bundle's image precision that is small: on a
    synthetic block through ``stereo block`` the full pose covariance propagated to each pair's
    DSM cells gave 0.0820 m RMS against 0.0825 m from this field (``docs/surface.md``). The
    share is common to all pairs at a place (mostly the datum's error: one draw per block).
Orientation, from the pose standard errors alone
    :func:`height_sigma_orientation`: the pose standard errors of the two photos (omega, phi,
    kappa in rad; x, y, z in ground units) as independent errors: a tilt error ``da`` of either
    photo changes the parallax by ``f da``, so the depth by ``Z^2 / B da``; an error ``db`` of
    a projection centre along the base changes the depth by ``Z db / B``; the projection centres'
    height errors move the point by half their mean. Tilt: the root mean square of omega and phi;
    along the base: of x and y. Without the poses' correlations this is an upper bound: in a block
    the relative orientation of neighbours is far better known than each pose (the datum part of
    the errors is common to both photos and moves the surface as a whole).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.points import as_points

__all__ = ["DISPARITY_SIGMA_FLOOR_PX", "PointSigmaField", "disparity_sigma", "height_sigma_disparity",
           "height_sigma_orientation", "normal_case_sigma_z"]

#: the smallest disparity standard error (px): resampling errors the sub-pixel fit cannot see
DISPARITY_SIGMA_FLOOR_PX = 0.05


def normal_case_sigma_z(depth: ArrayLike, base: float, focal_px: float, sigma_px: ArrayLike) -> NDArray[np.float64]:
    """``sigma_Z = Z^2 / (B f) * sigma_p``: the depth standard error of the normal case.

    Parameters
    ----------
    depth : array_like
        Depths ``Z`` along the viewing axis (ground units).
    base : float
        Base length ``B`` (ground units).
    focal_px : float
        Principal distance ``f`` of the normal-case photos, pixels.
    sigma_px : array_like
        Parallax (disparity) standard errors, pixels; broadcast against ``depth``.
    """
    if not (math.isfinite(base) and base > 0 and math.isfinite(focal_px) and focal_px > 0):
        raise InvalidInputError(f"base and focal length must be finite and > 0; got {base!r}, {focal_px!r}")
    z = np.asarray(depth, dtype=np.float64)
    return np.asarray(z * z / (base * focal_px) * np.asarray(sigma_px, dtype=np.float64), dtype=np.float64)


def height_sigma_disparity(xyz: ArrayLike, centre_left: ArrayLike, view_axis: ArrayLike, base: float, focal_px: float,
                           sigma_px: ArrayLike) -> NDArray[np.float64]:
    """Height (z) standard error of normal-case points from their disparity standard errors.

    Parameters
    ----------
    xyz : (N, 3) array_like
        The points (ground frame).
    centre_left : (3,) array_like
        Left projection centre (the point moves along the left ray when the disparity changes).
    view_axis : (3,) array_like
        The normal frame's viewing axis (any sign; normalised here).
    base, focal_px : float
        Base length (ground units) and the normal case's principal distance (pixels).
    sigma_px : (N,) array_like
        Disparity standard errors, pixels.

    Returns
    -------
    (N,) float64
        ``|z - z_C| / Z * Z^2 / (B f) * sigma_p`` with ``Z`` the depth along ``view_axis``.
    """
    p = np.asarray(xyz, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError(f"`xyz` must be (N, 3); got {p.shape}", actual_shape=p.shape, expected_shape=(None, 3))
    a = np.asarray(view_axis, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(a))
    if not n > 0:
        raise InvalidInputError(f"`view_axis` must be a non-zero vector; got {a.tolist()}")
    v = p - np.asarray(centre_left, dtype=np.float64).reshape(3)
    depth = np.abs(v @ (a / n))
    return np.abs(v[:, 2]) / np.maximum(depth, 1e-12) * normal_case_sigma_z(depth, base, focal_px, sigma_px)


def _tilt_base_height(std: ArrayLike | None) -> tuple[float, float, float]:
    if std is None:
        return 0.0, 0.0, 0.0
    s = np.asarray(std, dtype=np.float64).reshape(-1)
    if s.shape != (6,):
        raise ShapeError(f"pose standard errors must be 6 values (omega, phi, kappa, x, y, z); got {s.shape}",
                         actual_shape=s.shape, expected_shape=(6,))
    s = np.where(np.isfinite(s), s, 0.0)
    if (s < 0).any():
        raise InvalidInputError(f"pose standard errors must be >= 0; got {s.tolist()}")
    return (float(np.sqrt((s[0] ** 2 + s[1] ** 2) / 2)), float(np.sqrt((s[3] ** 2 + s[4] ** 2) / 2)), float(s[5]))


def height_sigma_orientation(depth: ArrayLike, base: float, std_left: ArrayLike | None,
                             std_right: ArrayLike | None) -> NDArray[np.float64]:
    """Height standard error of points from the two photos' pose standard errors (module docstring).

    ``sigma^2 = (Z^2 / B)^2 (a_l^2 + a_r^2) + (Z / B)^2 (b_l^2 + b_r^2) + (h_l^2 + h_r^2) / 4``

    Parameters
    ----------
    depth : array_like
        Depths ``Z`` (ground units).
    base : float
        Base length, ground units.
    std_left, std_right : (6,) array_like or None
        omega, phi, kappa (rad), x, y, z (ground units) standard errors; NaN or None: not known (0).
    """
    if not (math.isfinite(base) and base > 0):
        raise InvalidInputError(f"base must be finite and > 0; got {base!r}")
    al, bl, hl = _tilt_base_height(std_left)
    ar, br, hr = _tilt_base_height(std_right)
    z = np.asarray(depth, dtype=np.float64)
    var = (z * z / base) ** 2 * (al ** 2 + ar ** 2) + (z / base) ** 2 * (bl ** 2 + br ** 2) + (hl ** 2 + hr ** 2) / 4
    return np.asarray(np.sqrt(var), dtype=np.float64)


def disparity_sigma(left: ArrayLike, right: ArrayLike, disparity: ArrayLike, *, radius: int = 3,
                    floor_px: float = DISPARITY_SIGMA_FLOOR_PX, right_offset: float = 0.0) -> NDArray[np.float32]:
    """Standard error of each disparity from its least-squares sub-pixel fit (module docstring).

    Parameters
    ----------
    left : (H, W) array_like
        Left normal-case photo (grey), the window of the disparities.
    right : (H, W2) array_like
        Right normal-case photo rows of the same window: left column ``x`` of the window matches
        right column ``x + right_offset - d`` (columns outside it are clamped).
    disparity : (H, W) array_like
        ``col_left - col_right``; NaN where none.
    radius : int
        Half side of the fit window (Gaussian sigma ``radius / 2``), pixels.
    floor_px : float
        Added in quadrature.
    right_offset : float
        Column of ``right`` that left window column 0 faces at disparity 0 (e.g. the left window's
        column offset when ``right`` holds whole rows).

    Returns
    -------
    (H, W) float32
        Pixels; NaN where the disparity is NaN or the left photo has no x gradient in the window.
    """
    L = np.asarray(left, dtype=np.float32)
    R = np.asarray(right, dtype=np.float32)
    d = np.asarray(disparity, dtype=np.float32)
    if L.ndim != 2 or d.shape != L.shape or R.ndim != 2 or R.shape[0] != L.shape[0]:
        raise ShapeError(f"`left` and `disparity` must be (H, W) and `right` (H, W2); got {L.shape}, {d.shape}, "
                         f"{R.shape}", actual_shape=(L.shape, d.shape, R.shape))
    if isinstance(radius, bool) or not isinstance(radius, int) or radius < 1:
        raise InvalidInputError(f"`radius` must be an integer >= 1; got {radius!r}")
    if not (math.isfinite(floor_px) and floor_px >= 0):
        raise InvalidInputError(f"`floor_px` must be a finite number >= 0; got {floor_px!r}")
    H, W = L.shape
    v = np.isfinite(d)
    xs = np.arange(W, dtype=np.float32)[None, :] + np.float32(right_offset) - np.where(v, d, 0)
    ys = np.repeat(np.arange(H, dtype=np.float32)[:, None], W, axis=1)
    rw = cv2.remap(R, xs.astype(np.float32), ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    g = np.asarray(cv2.Sobel(L, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), dtype=np.float32)
    e = np.where(v, L - rw, 0).astype(np.float32)
    k = (2 * radius + 1, 2 * radius + 1)
    s = radius / 2.0

    def win(a: NDArray[np.float32]) -> NDArray[np.float32]:
        return np.asarray(cv2.GaussianBlur(a, k, s), dtype=np.float32)

    wv = win(v.astype(np.float32))
    inv = 1.0 / np.maximum(wv, 1e-6)
    me = win(e) * inv
    var_e = np.maximum(win(e * e) * inv - me * me, 0)
    mg = win(g)
    var_g = np.maximum(win(g * g) - mg * mg, 0)
    n_eff = 4 * math.pi * s * s
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.sqrt(var_e / (n_eff * var_g) + floor_px ** 2)
    out[~v | ~(var_g > 1e-6)] = np.nan
    return out.astype(np.float32)


class PointSigmaField:
    """Height standard errors known at scattered points (a bundle's tie points), looked up near others.

    Build with :meth:`from_points`; calling it with plan positions (N, 2) gives, per position, the
    median of the ``k`` nearest points' sigmas (ground units).
    """

    def __init__(self, xy: NDArray[np.float64], sigma: NDArray[np.float64], k: int):
        self._tree = cKDTree(xy)
        self._sigma = sigma
        self.k = min(k, len(sigma))
        self.median = float(np.median(sigma))

    @classmethod
    def from_points(cls, xy: ArrayLike, sigma_z: ArrayLike, *, k: int = 8) -> PointSigmaField:
        """Parameters: ``xy`` (N, 2) plan positions, ``sigma_z`` (N,) their height standard errors
        (ground units; rows with a non-finite or negative value are left out), ``k`` neighbours.

        Raises
        ------
        InvalidInputError
            No usable point, or ``k`` < 1.
        """
        p = as_points(xy, "xy", 2)
        s = np.asarray(sigma_z, dtype=np.float64).reshape(-1)
        if s.shape != (len(p),):
            raise ShapeError(f"`sigma_z` must have one value per point ({len(p)}); got {s.shape}",
                             actual_shape=s.shape, expected_shape=(len(p),))
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise InvalidInputError(f"`k` must be an integer >= 1; got {k!r}")
        ok = np.isfinite(p).all(axis=1) & np.isfinite(s) & (s >= 0)
        if not ok.any():
            raise InvalidInputError("no point with a finite height standard error")
        return cls(p[ok].copy(), s[ok].copy(), k)

    def __call__(self, xy: ArrayLike) -> NDArray[np.float64]:
        q = as_points(xy, "xy", 2)
        if len(q) == 0:
            return np.zeros(0)
        _d, idx = self._tree.query(q, k=self.k)
        idx = np.asarray(idx).reshape(len(q), -1)
        return np.asarray(np.median(self._sigma[idx], axis=1), dtype=np.float64)
