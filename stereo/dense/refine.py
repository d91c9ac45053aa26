"""Post-processing of a disparity map: depth-edge classification, median, sub-pixel refinement, ZNCC,
confidence, background fill.

Split from :mod:`stereo.dense.matching` (issue 30). Disparity convention: ``d = col_left - col_right``
of rectified photos, NaN where there is none; images are (H, W) float32 grey values.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from rectify.errors import InvalidInputError, ShapeError

__all__ = ["confidence", "edge_classify", "fill_background", "median_valid", "refine_subpixel", "zncc"]


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
    def f32(a: object) -> NDArray[np.float32]:
        return np.asarray(a, np.float32)

    g = grey.astype(np.float32, copy=False)
    mu = f32(cv2.blur(g, (5, 5)))
    var_g = f32(cv2.blur(g * g, (5, 5)))
    var_g -= mu * mu
    np.maximum(var_g, 0, out=var_g)
    var_g *= np.float32(-1.0 / 16.0)
    tex = f32(cv2.exp(var_g))
    np.subtract(np.float32(1.0), tex, out=tex)
    v = np.isfinite(disp)
    d = np.where(v, disp, np.float32(0))
    n = f32(cv2.blur(v.astype(np.float32), (3, 3)))
    inv = f32(1.0 / np.maximum(n, np.float32(1e-6)))
    m1 = f32(cv2.blur(d, (3, 3)))
    m1 *= inv
    var_d = f32(cv2.blur(d * d, (3, 3)))
    var_d *= inv
    var_d -= m1 * m1
    np.maximum(var_d, 0, out=var_d)
    np.negative(var_d, out=var_d)
    tex *= f32(cv2.exp(var_d))
    tex *= n
    tex[~v | filled] = 0.0
    return tex


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
    left = np.asarray(left, np.float32)
    right = np.asarray(right, np.float32)
    H, W = disp.shape
    xs = np.arange(W, dtype=np.float32)[None, :]
    ys = np.arange(H, dtype=np.float32)[:, None].repeat(W, 1)
    d0 = np.where(v, disp, np.float32(0)).astype(np.float32, copy=False)
    d = d0.copy()
    g = np.asarray(cv2.Sobel(left, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), dtype=np.float32)
    k = (2 * radius + 1, 2 * radius + 1)

    def win(a: NDArray[np.float32]) -> NDArray[np.float32]:
        return np.asarray(cv2.GaussianBlur(a, k, radius / 2.0), dtype=np.float32)

    mg = win(g)
    den = win(g * g)
    den -= mg * mg
    ok = den > 1e-4
    np.maximum(den, 1e-4, out=den)
    for _ in range(iterations):
        e = np.asarray(cv2.remap(right, xs - d, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE), np.float32)
        np.subtract(left, e, out=e)
        # L(x) = R(x - d)  =>  dL/dd = -g ; update dd = -cov(g, e) / var(g) over the window
        num = win(g * e)
        num -= mg * win(e)
        np.negative(num, out=num)
        num /= den
        num[~ok] = 0
        d += np.clip(num, -0.5, 0.5, out=num)
    if 0.5 * iterations > max_step:  # else no update can exceed it
        moved = np.abs(d - d0) > max_step
        d[moved] = d0[moved]
    d[~v] = np.nan
    return d


def zncc(a: NDArray[np.float32], b: NDArray[np.float32], radius: int) -> NDArray[np.float32]:
    """Zero-mean normalised cross-correlation of the (2 radius + 1)^2 windows of two aligned images."""
    k = (2 * radius + 1, 2 * radius + 1)
    ma, mb = cv2.blur(a, k), cv2.blur(b, k)
    cov = cv2.blur(a * b, k) - ma * mb
    va = np.maximum(cv2.blur(a * a, k) - ma * ma, 0)
    vb = np.maximum(cv2.blur(b * b, k) - mb * mb, 0)
    return np.asarray(cov / np.sqrt(np.maximum(va * vb, 1e-6)), dtype=np.float32)



def edge_classify(disp: NDArray[np.float32], grey: NDArray, *, radius: int = 4, noise: float = 5.0,
                  jump: float = 2.0, strip: int = 64) -> NDArray[np.float32]:
    """Disparity edges moved onto the photo's edges: each pixel next to a depth edge joins the
    surface whose grey values it resembles (a two-class Gaussian classification).

    A pixel p next to a disparity jump (the largest minus the smallest valid disparity of its
    ``(2 radius + 1)^2`` window W(p) exceeds ``jump`` px) has a near and a far surface in its
    window: the valid pixels q of W(p) whose disparity exceeds the middle of their own window's
    range, and the others. Each surface's grey values in W(p) are modelled as a Gaussian (mean,
    variance plus ``noise**2``, prior = its share of the valid pixels); p is classified by its grey
    value (the larger posterior). When that is not the surface of its own disparity, p takes the
    other surface's mean disparity in W(p) (the sub-pixel step refines it). This undoes the
    fattening of near surfaces over far ones that SGM's aggregation leaves next to depth edges (and
    its opposite) where the photo shows the edge. All sums are box filters: cost O(1) per pixel.

    ``disp``: (H, W) float32, NaN where none; ``grey``: (H, W) grey values (uint8 or float, 0..255).
    Returns a new array; pixels away from depth edges and all NaN are unchanged.
    """
    disp, grey = np.asarray(disp), np.asarray(grey)
    if disp.ndim != 2 or grey.shape != disp.shape:
        raise ShapeError(f"`disp` and `grey` must be (H, W) arrays of one shape; got {disp.shape} and {grey.shape}",
                         actual_shape=(disp.shape, grey.shape))
    for name, ival, low in (("radius", radius, 0), ("strip", strip, 1)):
        if isinstance(ival, bool) or not isinstance(ival, (int, np.integer)) or ival < low:
            raise InvalidInputError(f"`{name}` must be an integer >= {low}; got {ival!r}")
    for name, fval in (("noise", noise), ("jump", jump)):
        if not (isinstance(fval, (int, float)) and np.isfinite(fval) and fval > 0):
            raise InvalidInputError(f"`{name}` must be a finite number > 0; got {fval!r}")
    r = int(radius)
    H, W = disp.shape
    out = np.array(disp, np.float32, copy=True)
    if r < 1 or not np.isfinite(out).any():
        return out
    ksize = (2 * r + 1, 2 * r + 1)
    k = np.ones(ksize, np.uint8)
    var0 = np.float32(noise * noise)
    g8 = grey if grey.dtype == np.uint8 else np.rint(np.clip(grey, 0, 255)).astype(np.uint8)
    # strip buffers, allocated once and reused (fresh large temporaries cost page faults); the
    # window sums are box filters of small integer types where they can be
    n_max = min(H, strip + 6 * r)
    v, nv, near = (np.empty((n_max, W), bool) for _ in range(3))
    t, lo, hi, dv, dn = (np.empty((n_max, W), np.float32) for _ in range(5))
    gv, gn = (np.empty((n_max, W), np.uint8) for _ in range(2))
    g2v, g2n = (np.empty((n_max, W), np.uint16) for _ in range(2))
    sums = np.empty((8, n_max, W), np.float32)

    def box(a: NDArray, i: int, n: int) -> NDArray[np.float32]:
        return np.asarray(cv2.boxFilter(a, cv2.CV_32F, ksize, dst=sums[i, :n], normalize=False,
                                        borderType=cv2.BORDER_CONSTANT))

    for r0 in range(0, H, strip):
        r1 = min(H, r0 + strip)
        a0, a1 = max(0, r0 - 3 * r), min(H, r1 + 3 * r)  # the labels of a window's pixels need 2 r more
        n = a1 - a0
        ds = disp[a0:a1]
        vs, nvs, ts, los, his = v[:n], nv[:n], t[:n], lo[:n], hi[:n]
        np.isfinite(ds, out=vs)
        np.logical_not(vs, out=nvs)
        np.copyto(ts, ds)
        np.copyto(ts, np.float32(np.inf), where=nvs)
        c0, c1 = r0 - a0, r1 - a0
        # the range over the (2 r + 1)^2 window, then over the (4 r + 1)^2 one (the same filter twice)
        lo_c = cv2.erode(ts, k, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        cv2.erode(lo_c, k, dst=los, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        np.copyto(ts, np.float32(-np.inf), where=nvs)
        hi_c = cv2.dilate(ts, k, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
        cv2.dilate(hi_c, k, dst=his, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
        lo_c, hi_c = lo_c[c0:c1], hi_c[c0:c1]
        with np.errstate(invalid="ignore"):
            cand = (hi_c - lo_c > jump) & vs[c0:c1]
            idx = np.flatnonzero(cand)
            if not len(idx):
                continue
            # near: above the middle of the range of a window twice as large (it holds every window
            # that holds the pixel, so the pixels of one window are split at one level near an edge)
            np.add(his, los, out=his)
            his *= np.float32(0.5)
            ns = near[:n]
            np.greater(ds, his, out=ns)  # NaN compares False
        # window sums over the valid pixels and over the near ones: count, grey, grey squared,
        # disparity; on the core rows and r rows either side (the box filter's reach)
        b0, b1 = max(0, c0 - r), min(n, c1 + r)
        m = b1 - b0
        vb, nb, ndb, db = vs[b0:b1], nvs[b0:b1], ns[b0:b1], ds[b0:b1]
        gvs, gns, g2vs, g2ns, dvs, dns = gv[:m], gn[:m], g2v[:m], g2n[:m], dv[:m], dn[:m]
        np.multiply(g8[a0 + b0:a0 + b1], vb, out=gvs)
        np.multiply(gvs, gvs, out=g2vs, dtype=np.uint16)
        np.multiply(gvs, ndb, out=gns)
        np.multiply(g2vs, ndb, out=g2ns)
        np.copyto(dvs, db)
        np.copyto(dvs, np.float32(0), where=nb)
        np.multiply(dvs, ndb, out=dns)
        flat = idx + (c0 - b0) * W
        sa = [box(a, i, m).ravel().take(flat) for i, a in enumerate((vb.view(np.uint8), gvs, g2vs, dvs))]
        sn = [box(a, 4 + i, m).ravel().take(flat) for i, a in enumerate((ndb.view(np.uint8), gns, g2ns, dns))]
        sf = [a - b for a, b in zip(sa, sn, strict=True)]
        gp = g8[r0:r1].ravel().take(idx).astype(np.float32)
        cost = []
        for cnt_, s1, s2, _ in (sn, sf):
            cnt = np.maximum(cnt_, np.float32(0.5))
            mu = s1 / cnt
            var = np.maximum(s2 / cnt - mu * mu, 0) + var0
            # negative log posterior, up to a constant: (g - mu)^2 / var + log var - 2 log(prior),
            # the prior being the surface's count over the window's (the same for both: left out)
            cost.append((gp - mu) ** 2 / var + np.log(var / (cnt * cnt)))
        own_near = ns[c0:c1].ravel().take(idx)
        to_far = own_near & (cost[1] < cost[0]) & (sf[0] > 0.5)
        to_near = ~own_near & (cost[0] < cost[1]) & (sn[0] > 0.5)
        o = out[r0:r1].ravel()  # a view: out is C-contiguous
        o[idx[to_far]] = sf[3][to_far] / sf[0][to_far]
        o[idx[to_near]] = sn[3][to_near] / sn[0][to_near]
    return out
