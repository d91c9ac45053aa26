"""Least-squares image matching (LSM): refine tie points to a fraction of a pixel.

For each match the left point is kept fixed and a square window around it
(the *template*) is matched to the right image through an affine geometric
model and a linear radiometric model (gain and offset), in the spirit of
classical least-squares matching (Ackermann 1984; Gruen 1985)::

    L(x_l + u) = g * R(t + A u) + b + e        for every window offset u

where ``u`` runs over the (2r+1)^2 integer offsets of the window, ``A`` (2x2)
is the local affine shape, ``t`` (2,) the right position, and ``g``, ``b`` the
gain and offset. The eight unknowns are solved by Gauss-Newton iterations with
cubic-convolution resampling; the precision of ``t`` comes from the inverse normal
matrix scaled by the a-posteriori variance of unit weight.

All coordinates follow the project's pixel convention: the centre of pixel
``[r, c]`` is at ``(x=c, y=r)``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InvalidInputError, ShapeError
from .points import as_pair

__all__ = ["LsmConfig", "LsmResult", "bicubic", "bilinear", "refine_matches"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LsmConfig:
    """Options of :func:`refine_matches`.

    Attributes
    ----------
    radius_px : int
        Half size of the matching window; the window is (2r+1)^2 pixels.
    max_iter : int
        Gauss-Newton iterations at most.
    tol_px : float
        Convergence: the last position update is smaller than this (px).
    max_shift_px : float
        A match whose refined right position moves farther than this from
        its start is declared non-converged (it jumped to another feature).
    min_corr : float
        Minimum normalised cross-correlation between the template and the
        resampled right window after convergence.
    max_std_px : float
        Matches whose estimated position standard deviation exceeds this are
        declared non-converged (flat, ill-conditioned windows).
    """

    radius_px: int = 10
    max_iter: int = 20
    tol_px: float = 0.005
    max_shift_px: float = 2.0
    min_corr: float = 0.6
    max_std_px: float = 0.5

    def __post_init__(self) -> None:
        if int(self.radius_px) < 2:
            raise InvalidInputError(f"radius_px must be >= 2; got {self.radius_px}")
        if int(self.max_iter) < 1:
            raise InvalidInputError(f"max_iter must be >= 1; got {self.max_iter}")
        for name in ("tol_px", "max_shift_px", "max_std_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InvalidInputError(f"{name} must be a positive number; got {v!r}")
        if not (-1.0 <= self.min_corr <= 1.0):
            raise InvalidInputError(f"min_corr must be in [-1, 1]; got {self.min_corr!r}")


class LsmResult(NamedTuple):
    """Output of :func:`refine_matches`.

    Attributes
    ----------
    right : (N, 2) float64
        Refined right positions (pixel frame of the right image); equal to
        the input position where ``converged`` is False.
    converged : (N,) bool
        True where the adjustment converged and passed the quality checks.
    std_px : (N,) float64
        Standard deviation of the refined right position, sqrt(sx^2 + sy^2),
        px (NaN where not converged).
    corr : (N,) float64
        Normalised cross-correlation of the final windows.
    iterations : (N,) int
        Iterations used.
    affine : (N, 2, 2) float64
        Final local affine shape A (right offsets per left offset).
    """

    right: NDArray[np.float64]
    converged: NDArray[np.bool_]
    std_px: NDArray[np.float64]
    corr: NDArray[np.float64]
    iterations: NDArray[np.int64]
    affine: NDArray[np.float64]


def bilinear(img: NDArray, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sample a 2D image bilinearly at (x, y) (pixel centres at integers).

    Parameters
    ----------
    img : (H, W) array
        NaN marks invalid pixels; they propagate.
    x, y : arrays of the same shape
        Column and row coordinates, px.

    Returns
    -------
    values : float64 array, same shape as ``x``; NaN outside the image.
    """
    h, w = img.shape
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xc = np.clip(x, 0, w - 1)
    yc = np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(xc).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(yc).astype(np.int64), max(h - 2, 0))
    fx = xc - x0
    fy = yc - y0
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    v = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x1] * fx * (1 - fy)
         + img[y1, x0] * (1 - fx) * fy + img[y1, x1] * fx * fy)
    return np.where(inside, v, np.nan)


def _keys(t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Keys cubic-convolution weights (a = -0.5) of taps -1, 0, 1, 2 at fraction t."""
    t2 = t * t
    t3 = t2 * t
    w0 = -0.5 * t3 + t2 - 0.5 * t
    w1 = 1.5 * t3 - 2.5 * t2 + 1.0
    w2 = -1.5 * t3 + 2.0 * t2 + 0.5 * t
    w3 = 0.5 * t3 - 0.5 * t2
    return w0, w1, w2, w3


def bicubic(img: NDArray, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sample a 2D image by Keys cubic convolution at (x, y) (pixel centres at integers).

    Same contract as :func:`bilinear` (NaN outside the image and where a tap
    is NaN); borders are replicated for the outer taps.
    """
    a = np.asarray(img)
    return _bicubic_padded(np.pad(a, 2, mode="edge"), a.shape[0], a.shape[1], x, y)


#: an image padded by 2 px (edge mode) and its original height and width
_Padded = tuple[NDArray, int, int]


def _bicubic_padded(pad: NDArray, h: int, w: int, x, y) -> NDArray[np.float64]:
    """:func:`bicubic` on an image already padded by 2 px (edge mode); flat gathers, no clipping."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xc = np.clip(x, 0, w - 1)
    yc = np.clip(y, 0, h - 1)
    x0 = np.floor(xc)
    y0 = np.floor(yc)
    wx = _keys(xc - x0)
    wy = _keys(yc - y0)
    stride = w + 4
    base = (y0.astype(np.int64) + 1) * stride + x0.astype(np.int64) + 1
    flat = pad.ravel()
    out = np.zeros_like(x)
    for j in range(4):
        row = None
        for i in range(4):
            v = wx[i] * flat.take(base + (j * stride + i))
            row = v if row is None else row + v
        out = out + wy[j] * row
    return np.where(inside, out, np.nan)


def _as_grey(img: ArrayLike, name: str) -> NDArray[np.float32]:
    a = np.asarray(img)
    if a.ndim == 3:
        a = a.astype(np.float32).mean(axis=2)
    if a.ndim != 2:
        raise ShapeError(f"`{name}` must be (H, W) or (H, W, C); got {np.shape(img)}",
                         actual_shape=np.shape(img), expected_shape=(None, None))
    if min(a.shape) < 3:
        raise InvalidInputError(f"`{name}` is too small to match: shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float32)


def refine_matches(left_img: ArrayLike, right_img: ArrayLike, left_xy: ArrayLike, right_xy: ArrayLike,
                   *, affine: ArrayLike | None = None, config: LsmConfig | None = None,
                   chunk: int = 2048, progress: Callable[[int, int], None] | None = None) -> LsmResult:
    """Refine right positions of matches by least-squares image matching.

    Parameters
    ----------
    left_img, right_img : (H, W) or (H, W, C) arrays, any numeric dtype
        Images (bands are averaged). NaN marks invalid pixels: a window that
        touches one does not converge.
    left_xy, right_xy : (N, 2) array_like
        Matched positions (x = column, y = row, px, pixel centres at
        integers) in the left and right image. Left positions stay fixed.
    affine : (N, 2, 2) or (2, 2) array_like, optional
        Initial local affine shape (d right / d left); identity by default.
    config : LsmConfig, optional
    chunk : int
        Matches processed together (bounds memory: about
        ``chunk * (2r+1)^2 * 100`` bytes).
    progress : callable(done, total), optional

    Returns
    -------
    LsmResult

    Raises
    ------
    ShapeError, InvalidInputError
        On malformed images, points or affine shapes.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> img = rng.normal(size=(64, 64)).cumsum(0).cumsum(1)
    >>> shifted = np.roll(img, (0, 1), axis=(0, 1))   # right = left moved 1 px in x
    >>> r = refine_matches(img, shifted, [[30.0, 30.0]], [[31.3, 29.8]])
    >>> bool(r.converged[0]), np.round(r.right[0], 2).tolist()
    (True, [31.0, 30.0])
    """
    cfg = config or LsmConfig()
    L = _as_grey(left_img, "left_img")
    R = _as_grey(right_img, "right_img")
    pl, pr = as_pair(left_xy, right_xy, names=("left_xy", "right_xy"))
    n = len(pl)
    if affine is None:
        A0 = np.broadcast_to(np.eye(2), (n, 2, 2))
    else:
        A0 = np.asarray(affine, dtype=np.float64)
        if A0.shape == (2, 2):
            A0 = np.broadcast_to(A0, (n, 2, 2))
        if A0.shape != (n, 2, 2) or not np.isfinite(A0).all():
            raise ShapeError(f"`affine` must be finite (N, 2, 2) or (2, 2) with N={n}; got {np.shape(affine)}",
                             actual_shape=np.shape(affine), expected_shape=(n, 2, 2))
    Lp = (np.pad(L, 2, mode="edge"), L.shape[0], L.shape[1])
    Rp = (np.pad(R, 2, mode="edge"), R.shape[0], R.shape[1])
    out_r = pr.copy()
    conv = np.zeros(n, dtype=bool)
    std = np.full(n, np.nan)
    corr = np.full(n, np.nan)
    iters = np.zeros(n, dtype=np.int64)
    aff = np.array(A0, dtype=np.float64, copy=True)
    chunk = max(1, int(chunk))
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        res = _refine_chunk(Lp, Rp, pl[s:e], pr[s:e], np.array(A0[s:e]), cfg)
        out_r[s:e], conv[s:e], std[s:e], corr[s:e], iters[s:e], aff[s:e] = res
        if progress is not None:
            progress(e, n)
    logger.debug("LSM: %d of %d matches converged", int(conv.sum()), n)
    return LsmResult(out_r, conv, std, corr, iters, aff)


def _refine_chunk(L: _Padded, R: _Padded, pl, pr, A, cfg: LsmConfig):
    r = int(cfg.radius_px)
    g = np.arange(-r, r + 1, dtype=np.float64)
    uy, ux = np.meshgrid(g, g, indexing="ij")
    ux = ux.ravel()[None, :]
    uy = uy.ravel()[None, :]
    m = len(pl)
    npx = ux.shape[1]
    T = _bicubic_padded(*L, pl[:, :1] + ux, pl[:, 1:] + uy)                    # (m, P)
    t = pr.copy()
    A = A.copy()
    # initial radiometry from window statistics
    R0 = _sample(R, t, A, ux, uy)
    active = np.isfinite(T).all(axis=1) & np.isfinite(R0).all(axis=1)
    Tz = np.where(active[:, None], T, 0.0)
    Rz = np.where(active[:, None], R0, 0.0)
    sr = Rz.std(axis=1)
    gain = np.where(active & (sr > 0), Tz.std(axis=1) / np.where(sr > 0, sr, 1.0), 1.0)
    gain = np.where(gain > 0, gain, 1.0)
    off = Tz.mean(axis=1) - gain * Rz.mean(axis=1)
    done = np.zeros(m, dtype=bool)
    failed = ~active
    iters = np.zeros(m, dtype=np.int64)
    Ninv = np.full((m, 8, 8), np.nan)
    ssr = np.full(m, np.nan)
    for it in range(cfg.max_iter):
        idx = np.flatnonzero(~done & ~failed)
        if idx.size == 0:
            break
        ti, Ai = t[idx], A[idx]
        xs = ti[:, :1] + Ai[:, 0, :1] * ux + Ai[:, 0, 1:] * uy
        ys = ti[:, 1:] + Ai[:, 1, :1] * ux + Ai[:, 1, 1:] * uy
        Rv = _bicubic_padded(*R, xs, ys)
        # gradients of the resampled window (consistent with the resampling), back to image axes
        W = Rv.reshape(-1, 2 * r + 1, 2 * r + 1)
        du = np.asarray(np.gradient(W, axis=2)).reshape(Rv.shape)
        dv = np.asarray(np.gradient(W, axis=1)).reshape(Rv.shape)
        Ainv = np.linalg.inv(Ai)                                      # grad_x = A^-T grad_u
        Gx = Ainv[:, 0, :1] * du + Ainv[:, 1, :1] * dv
        Gy = Ainv[:, 0, 1:] * du + Ainv[:, 1, 1:] * dv
        gi = gain[idx][:, None]
        res = T[idx] - (gi * Rv + off[idx][:, None])
        J = np.stack([gi * Gx, gi * Gy, gi * Gx * ux, gi * Gx * uy, gi * Gy * ux, gi * Gy * uy,
                      Rv, np.ones_like(Rv)], axis=2)                     # (k, P, 8)
        bad = ~np.isfinite(res).all(axis=1)
        J = np.nan_to_num(J)
        res = np.nan_to_num(res)
        N = np.einsum("kpi,kpj->kij", J, J)
        c = np.einsum("kpi,kp->ki", J, res)
        det = np.linalg.det(N)
        bad |= ~np.isfinite(det) | (np.abs(det) < 1e-300)
        N[bad] = np.eye(8)
        try:
            Ni = np.linalg.inv(N)
        except np.linalg.LinAlgError:  # pragma: no cover - guarded by the det test
            Ni = np.array([np.linalg.pinv(x) for x in N])
        dp = np.einsum("kij,kj->ki", Ni, c)
        t[idx, 0] += dp[:, 0]
        t[idx, 1] += dp[:, 1]
        A[idx, 0, 0] += dp[:, 2]
        A[idx, 0, 1] += dp[:, 3]
        A[idx, 1, 0] += dp[:, 4]
        A[idx, 1, 1] += dp[:, 5]
        gain[idx] += dp[:, 6]
        off[idx] += dp[:, 7]
        iters[idx] = it + 1
        Ninv[idx] = Ni
        ssr[idx] = np.sum(res * res, axis=1)
        step = np.hypot(dp[:, 0], dp[:, 1])
        moved = np.hypot(*(t[idx] - pr[idx]).T)
        detA = np.abs(np.linalg.det(A[idx]))
        failed[idx] |= bad | ~np.isfinite(step) | (moved > cfg.max_shift_px) | (detA < 1e-3) | (gain[idx] <= 0)
        done[idx] |= (step < cfg.tol_px) & ~failed[idx]
    conv = done & ~failed
    # precision and correlation at the final estimate
    std = np.full(m, np.nan)
    corr = np.full(m, np.nan)
    if conv.any():
        idx = np.flatnonzero(conv)
        Rv = _sample(R, t[idx], A[idx], ux, uy)
        Ti = T[idx]
        res = Ti - (gain[idx][:, None] * Rv + off[idx][:, None])
        s2 = np.sum(res * res, axis=1) / max(npx - 8, 1)
        var = s2[:, None] * np.stack([Ninv[idx, 0, 0], Ninv[idx, 1, 1]], axis=1)
        std[idx] = np.sqrt(np.abs(var).sum(axis=1))
        a = Ti - Ti.mean(axis=1, keepdims=True)
        b = Rv - Rv.mean(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            corr[idx] = np.sum(a * b, axis=1) / np.sqrt(np.sum(a * a, axis=1) * np.sum(b * b, axis=1))
        ok = np.isfinite(std[idx]) & (std[idx] <= cfg.max_std_px) & (corr[idx] >= cfg.min_corr)
        conv[idx] = ok
    out = np.where(conv[:, None], t, pr)
    return out, conv, np.where(conv, std, np.nan), corr, iters, A


def _sample(R: _Padded, t, A, ux, uy):
    xs = t[:, :1] + A[:, 0, :1] * ux + A[:, 0, 1:] * uy
    ys = t[:, 1:] + A[:, 1, :1] * ux + A[:, 1, 1:] * uy
    return _bicubic_padded(*R, xs, ys)
