"""Post-processing of a disparity map: median, sub-pixel refinement, ZNCC, confidence, background fill.

Split from :mod:`stereo.dense.matching` (issue 30). Disparity convention: ``d = col_left - col_right``
of rectified photos, NaN where there is none; images are (H, W) float32 grey values.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

__all__ = ["confidence", "fill_background", "median_valid", "refine_subpixel", "zncc"]


def fill_background(disp: NDArray[np.float32], max_px: int) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Fill holes of at most ``max_px`` pixels by the smaller of the nearest valid disparities on the row.

    Returns the filled map and the mask of filled pixels.
    """
    v = np.isfinite(disp)
    if max_px <= 0 or v.all() or not v.any():
        return disp, np.zeros(disp.shape, bool)
    H, W = disp.shape
    lab, n = ndimage.label(~v)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    small = sizes <= max_px
    small[0] = False
    target = small[lab]
    cols = np.arange(W)[None, :]
    left = np.maximum.accumulate(np.where(v, cols, -1), axis=1)
    right = np.minimum.accumulate(np.where(v, cols, W)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(H)[:, None]
    lv = np.where(left >= 0, disp[rows, np.clip(left, 0, W - 1)], np.inf)
    rv = np.where(right < W, disp[rows, np.clip(right, 0, W - 1)], np.inf)
    f = np.minimum(lv, rv)
    target &= np.isfinite(f)
    out = disp.copy()
    out[target] = f[target]
    return out, target


def median_valid(disp: NDArray[np.float32]) -> NDArray[np.float32]:
    """3 x 3 median of the valid disparities; where nodata neighbours could change it, the value is kept.

    The median with nodata as -inf and as +inf bounds the median of the valid values only; where the
    two agree it is exact, elsewhere (next to holes) the pixel keeps its own disparity.
    """
    v = np.isfinite(disp)
    if v.all():
        return np.asarray(cv2.medianBlur(disp.astype(np.float32), 3), dtype=np.float32)
    a = cv2.medianBlur(np.where(v, disp, np.float32(-1e9)), 3)
    b = cv2.medianBlur(np.where(v, disp, np.float32(1e9)), 3)
    m = np.where(a == b, a, disp)
    return np.where(v, m, np.nan).astype(np.float32)


def confidence(grey: NDArray[np.float32], disp: NDArray[np.float32], filled: NDArray[np.bool_]
                ) -> NDArray[np.float32]:
    """Texture (5 x 5 grey variance) times smoothness (3 x 3 disparity variance), in [0, 1].

    ``(1 - exp(-var_grey / 16)) * exp(-var_disparity) * (share of valid 3 x 3 neighbours)``; 0 where
    there is no disparity or it was filled.
    """
    g = grey.astype(np.float32, copy=False)
    mu = cv2.blur(g, (5, 5))
    var_g = cv2.blur(g * g, (5, 5)) - mu * mu
    tex = 1.0 - cv2.exp(np.maximum(var_g, 0) * np.float32(-1.0 / 16.0))
    v = np.isfinite(disp)
    d = np.where(v, disp, np.float32(0))
    n = cv2.blur(v.astype(np.float32), (3, 3))
    inv = 1.0 / np.maximum(n, np.float32(1e-6))
    m1 = cv2.blur(d, (3, 3)) * inv
    var_d = cv2.blur(d * d, (3, 3)) * inv - m1 * m1
    c = tex * cv2.exp(-np.maximum(var_d, 0)) * n
    c[~v | filled] = 0.0
    return c.astype(np.float32, copy=False)


def refine_subpixel(left: NDArray[np.float32], right: NDArray[np.float32], disp: NDArray[np.float32], *,
                    radius: int = 3, iterations: int = 1, max_step: float = 1.0) -> NDArray[np.float32]:
    """Least-squares refinement of disparities along the rows (1-D Lucas-Kanade, Gaussian window).

    Each iteration warps the right photo by the current disparity (cubic) and solves, per pixel, for
    the update that best aligns the two windows (radius ``radius``, Gaussian weights) with the mean
    grey difference removed (an offset between the photos does not bias it); the gradient is the
    left photo's x gradient. This removes most of the pixel-locking bias
    of SGBM's parabola. Updates of more than ``max_step`` px in total are undone.
    """
    v = np.isfinite(disp)
    if not v.any() or iterations <= 0:
        return disp
    left = left.astype(np.float32)
    right = right.astype(np.float32)
    H, W = disp.shape
    xs = np.arange(W, dtype=np.float32)[None, :].repeat(H, 0)
    ys = np.arange(H, dtype=np.float32)[:, None].repeat(W, 1)
    d0 = np.where(v, disp, 0).astype(np.float32)
    d = d0.copy()
    g = np.asarray(cv2.Sobel(left, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), dtype=np.float32)
    k = (2 * radius + 1, 2 * radius + 1)

    def win(a: NDArray[np.float32]) -> NDArray[np.float32]:
        return np.asarray(cv2.GaussianBlur(a, k, radius / 2.0), dtype=np.float32)

    mg = win(g)
    den = win(g * g) - mg * mg
    for _ in range(iterations):
        mx = xs - d
        rw = cv2.remap(right, mx, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        e = left - rw
        # L(x) = R(x - d)  =>  dL/dd = -g ; update dd = -cov(g, e) / var(g) over the window
        num = win(g * e) - mg * win(e)
        step = np.where(den > 1e-4, -num / np.maximum(den, 1e-4), 0).astype(np.float32)
        d = d + np.clip(step, -0.5, 0.5)
    moved = np.abs(d - d0) > max_step
    d[moved] = d0[moved]
    return np.where(v, d, np.nan).astype(np.float32)


def zncc(a: NDArray[np.float32], b: NDArray[np.float32], radius: int) -> NDArray[np.float32]:
    """Zero-mean normalised cross-correlation of the (2 radius + 1)^2 windows of two aligned images."""
    k = (2 * radius + 1, 2 * radius + 1)
    ma, mb = cv2.blur(a, k), cv2.blur(b, k)
    cov = cv2.blur(a * b, k) - ma * mb
    va = np.maximum(cv2.blur(a * a, k) - ma * ma, 0)
    vb = np.maximum(cv2.blur(b * b, k) - mb * mb, 0)
    return np.asarray(cov / np.sqrt(np.maximum(va * vb, 1e-6)), dtype=np.float32)
