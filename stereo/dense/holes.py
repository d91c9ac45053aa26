"""The half-resolution hole pass of the dense matcher (``MatchOptions.hole_p2``, issue 30), box by box.

Split from :mod:`stereo.dense.matching`. The holes that the tests after SGBM leave are matched again at
half resolution with a stronger smoothness penalty. Most of a window is no hole, most holes are a few
pixels (occlusions next to depth edges, which nothing can match, and gaps that the DSM's gridding
bridges) and the holes at a window's left edge are mostly pixels whose match lies beyond the right
photo's edge: the half-resolution SGBM runs only on boxes around the holes of at least ``MIN_HOLE``
half-resolution pixels (about 2000 px) that can be matched, each over the range of the valid
disparities around it (plus ``RANGE_MARGIN``), instead of on the whole window over its whole range
(issue 30: with the whole-window pass the matcher took 1.5-1.8x OpenCV's SGBM time, now 1.4-1.5x;
docs/dense.md). SGBM costs about the same per pixel whatever the number of disparities, so a box
costs its area with the columns of its search. Disparity convention: ``d = col_left - col_right`` of
rectified photos, NaN where there is none. Pixels that have a disparity are never changed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from stereo.dense.checks import erode_valid
from stereo.dense.refine import zncc

if TYPE_CHECKING:
    from stereo.dense.matching import MatchOptions

__all__ = ["BOX_MARGIN", "MIN_HOLE", "RANGE_MARGIN", "fill_holes_half", "hole_boxes"]

#: holes (8-connected, half resolution, the pixels that can be matched) of fewer half-resolution
#: pixels are left as they are
MIN_HOLE = 512
#: half-resolution px of context around a hole's box
BOX_MARGIN = 4
#: full-resolution px added to both ends of a box's disparity range (that of the valid disparities
#: in the box and its margin)
RANGE_MARGIN = 8
#: full-resolution px below the first valid disparity of its row that a hole pixel's own may be, in
#: the test whether its right pixel can lie inside the right window
_REACH_MARGIN = 2
#: radius (half-resolution px) of the ZNCC window that accepts a hole pixel's disparity
_ZNCC_RADIUS = 3
#: the cost of one SGBM call of a box beyond its pixels, in pixels (boxes are merged when the merged
#: box costs less than the two): about 0.1 ms at 50-60 ns a pixel
_CALL_PX = 2000.0

#: ``match(L, R, lv, rv, dmin, dmax, opts, pad=...)``: SGBM and the tests of one window pair
#: (:func:`stereo.dense.matching._match_window`)
MatchWindow = Callable[..., NDArray[np.float32]]


def _grey(img: NDArray) -> NDArray[np.float32]:
    """Grey values (float32) of a window crop, as :func:`stereo.dense.matching._grey`."""
    if img.ndim == 2:
        return img.astype(np.float32)
    if img.dtype == np.uint8:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY), np.float32)
    return img.astype(np.float32).mean(axis=2)


def _or4(m: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Half-resolution mask: set where one of the four pixels is (an odd last row or column dropped)."""
    h, w = m.shape[0] // 2 * 2, m.shape[1] // 2 * 2
    out = m[0:h:2, 0:w:2] | m[1:h:2, 0:w:2]
    out |= m[0:h:2, 1:w:2]
    out |= m[1:h:2, 1:w:2]
    return out


def _halve(img: NDArray, valid: NDArray[np.bool_], r0: int, r1: int, c0: int, c1: int
           ) -> tuple[NDArray, NDArray[np.bool_]]:
    """The half-resolution crop of rows ``r0:r1`` and columns ``c0:c1`` (full resolution, even bounds;
    columns outside the image are zeros and invalid): 2 x 2 means, valid where all four are."""
    W = img.shape[1]
    a, b = max(c0, 0), min(c1, W)
    if a == c0 and b == c1:
        crop, cv = img[r0:r1, c0:c1], valid[r0:r1, c0:c1]
    else:
        crop = np.zeros((r1 - r0, c1 - c0) + img.shape[2:], img.dtype)
        cv = np.zeros((r1 - r0, c1 - c0), bool)
        if b > a:
            crop[:, a - c0:b - c0] = img[r0:r1, a:b]
            cv[:, a - c0:b - c0] = valid[r0:r1, a:b]
    h, w = (r1 - r0) // 2, (c1 - c0) // 2
    half = np.asarray(cv2.resize(np.ascontiguousarray(crop), (w, h), interpolation=cv2.INTER_AREA), img.dtype)
    if cv.all():
        return half, np.ones((h, w), bool)
    return half, np.asarray(cv[0::2, 0::2] & cv[1::2, 0::2] & cv[0::2, 1::2] & cv[1::2, 1::2])


def hole_boxes(cand: NDArray[np.bool_], d: NDArray[np.float32], lo: int, hi: int, right_col: int,
               min_hole: int | None = None) -> tuple[NDArray[np.int32], NDArray[np.int64]]:
    """The holes of the half-resolution pass: their labels and boxes.

    ``cand``: (H, W) full-resolution hole pixels that may take a disparity (H and W even); ``d``: the
    window's disparities (``lo..hi``, NaN where none); ``right_col``: the first column of the right
    window (moved by ``lo``) whose pixels can take a match. A half-resolution pixel is a hole pixel
    when one of its four pixels is a candidate, unless it lies left of its row's first valid
    disparity ``v`` and its right pixel lies left of ``right_col`` for every disparity above ``v -
    _REACH_MARGIN``: most holes at a window's left edge are pixels whose match lies beyond the right
    photo's edge. The 8-connected groups of at least ``min_hole`` (default ``MIN_HOLE``) hole pixels
    are the holes. Returns the (H / 2, W / 2) labels (holes and smaller groups) and per hole a row
    ``(label, y0, y1, x0, x1, dl, dh)``: its bounding box in half-resolution pixels and the
    full-resolution range of the valid disparities in the box and ``BOX_MARGIN`` around it,
    ``RANGE_MARGIN`` wider (``lo..hi`` when there are none).
    """
    c = _or4(cand)
    Hh, Wh = c.shape
    none = np.zeros((0, 7), np.int64)
    nl = min(Wh, (hi - lo + right_col) // 2 + 1)  # right of these columns every disparity can be matched
    if nl > 0 and c[:, :nl].any():
        rows = np.isfinite(d[0:2 * Hh:2])
        first = np.argmax(rows, axis=1)
        has = rows[np.arange(Hh), first]
        v = np.where(has, d[np.arange(0, 2 * Hh, 2), first], np.inf)
        col = 2 * np.arange(nl)[None, :]
        reach = col + 1 - (np.maximum(v[:, None] - _REACH_MARGIN, lo) - lo) >= right_col
        c[:, :nl] &= reach | (col >= first[:, None]) | ~has[:, None]
    if not c.any():
        return np.zeros((Hh, Wh), np.int32), none
    # Grana's algorithm: 2.5 times faster here than OpenCV's default with statistics
    n, lab_, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(c.view(np.uint8), 8, cv2.CV_32S, cv2.CCL_GRANA)
    lab = np.asarray(lab_, np.int32)
    big = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= (MIN_HOLE if min_hole is None else min_hole)) + 1
    if not len(big):
        return lab, none
    m = BOX_MARGIN
    out = []
    for i in big:
        x, y, w, h = (int(v) for v in stats[i, :4])
        vals = d[2 * max(0, y - m): 2 * min(Hh, y + h + m): 2, 2 * max(0, x - m): 2 * min(Wh, x + w + m): 2]
        vmin, vmax = float(np.fmin.reduce(vals, axis=None)), float(np.fmax.reduce(vals, axis=None))
        if math.isfinite(vmin):
            dl = max(lo, min(hi, int(math.floor(vmin - RANGE_MARGIN))))
            dh = max(dl, min(hi, int(math.ceil(vmax + RANGE_MARGIN))))
        else:
            dl, dh = lo, hi
        out.append((i, y, y + h, x, x + w, dl, dh))
    return lab, np.array(out, np.int64)


def _merge(boxes: NDArray[np.int64], lo: int, Wh: int, Hh: int, bh: int) -> list[tuple[list[int], list[int]]]:
    """Boxes merged while a merged box costs less SGBM time than the two (``_CALL_PX`` a call, the
    box's pixels with its margin and left context, 1/96 more per disparity). Returns per merged box
    its labels and ``[y0, y1, x0, x1, dl, dh]``."""
    b = boxes[:, 1:].astype(np.float64)
    labels: list[list[int] | None] = [[int(k)] for k in boxes[:, 0]]
    m = BOX_MARGIN
    lows = np.array([True, False, True, False, True, False])  # y0, y1, x0, x1, dl, dh: min or max

    def cost(v: NDArray[np.float64]) -> NDArray[np.float64]:
        y0, y1, x0, x1, dl, dh = (v[..., j] for j in range(6))
        qs = np.ceil((dh - lo) / 2.0) + 1 - np.floor((dl - lo) / 2.0)
        num = np.ceil((qs + 1) / 16.0) * 16
        h = np.minimum(Hh, y1 + m) - np.maximum(0, y0 - m)
        w = np.minimum(Wh, x1 + m + bh) - np.maximum(0, x0 - m) + np.maximum(num + 1, qs + bh + 1)
        return np.asarray(h * w * (1 + num / 96.0) + _CALL_PX)

    n = len(b)
    c = cost(b)
    gain = cost(np.where(lows, np.minimum(b[:, None], b[None, :]), np.maximum(b[:, None], b[None, :])))
    gain -= c[:, None] + c[None, :]
    np.fill_diagonal(gain, np.inf)
    alive = np.ones(n, bool)
    while n > 1:
        i, j = divmod(int(np.argmin(gain)), len(b))
        if gain[i, j] >= 0:
            break
        b[i] = np.where(lows, np.minimum(b[i], b[j]), np.maximum(b[i], b[j]))
        labels[i] += labels[j]  # type: ignore[operator]
        labels[j] = None
        alive[j] = False
        gain[j, :] = gain[:, j] = np.inf
        c[i] = cost(b[i])
        row = cost(np.where(lows, np.minimum(b[i], b), np.maximum(b[i], b))) - c[i] - c
        row[~alive] = np.inf
        row[i] = np.inf
        gain[i, :] = gain[:, i] = row
        n -= 1
    return [(lab, [int(v) for v in b[i]]) for i, lab in enumerate(labels) if lab is not None]


def _right_check(rv: NDArray[np.bool_], b: int) -> tuple[NDArray[np.bool_] | None, NDArray[np.bool_]]:
    """The right window's pixels away from nodata (:func:`stereo.dense.checks.erode_valid`): as
    columns ``(None, cols)`` when its nodata are whole columns (the usual case), else ``(pixels, any
    column)``."""
    cols = np.asarray(rv.all(axis=0))
    if np.array_equal(cols, rv.any(axis=0)):
        return None, np.asarray(erode_valid(np.ascontiguousarray(cols[None, :]), b)[0])
    rve = erode_valid(rv, b)
    return rve, np.asarray(rve.any(axis=0))


def fill_holes_half(d: NDArray[np.float32], L: NDArray, R: NDArray, lv: NDArray[np.bool_], rv: NDArray[np.bool_],
                    lo: int, hi: int, opts: MatchOptions, match: MatchWindow) -> NDArray[np.float32]:
    """Holes of ``d`` matched again at half resolution with a stronger smoothness penalty, box by box;
    ``d`` is filled in place and returned.

    ``R`` is the right window moved by ``lo`` (``R[:, x] = right[:, x - lo]``, as for ``match``);
    ``d``: (H, W) float32 disparities in ``lo..hi``, NaN where none. The holes of :func:`hole_boxes`
    are matched at half resolution in their boxes (``BOX_MARGIN`` px around them; nearby boxes
    merged) over the range of the valid disparities around them with ``P2 = opts.hole_p2`` and the
    same tests (at half resolution). A half-resolution pixel of a hole keeps its disparity when the
    ZNCC of the 7 x 7 windows of the left crop and the right crop warped by the box's disparities
    reaches ``opts.hole_zncc``; each of its four pixels that is a hole pixel then takes the doubled
    disparity when its left pixel is away from nodata and the window's left and right edges and its
    right pixel passes the full-resolution border rule. (The collision test runs at half resolution,
    on the box with the valid pixels around the hole: run again at full resolution it changed
    nothing that the benchmarks show, for 2 ms on Motorcycle.) Pixels that have a disparity are not
    changed.
    """
    if opts.hole_p2 <= 0:
        return d
    H, W = d.shape
    H2, W2 = H // 2 * 2, W // 2 * 2
    if min(H2, W2) < 32:
        return d
    b = opts.border_px
    cand = ~np.isfinite(d[:H2, :W2])
    if not cand.any():
        return d
    lve = erode_valid(lv, b)
    if lve is not lv:
        cand &= lve[:H2, :W2]
    if b:  # away from the window's left and right edges (the sub-pixel step is unsure there)
        cand[:, :b] = False
        cand[:, max(0, W - b):] = False
    rve, rcols = _right_check(rv, b)
    first = np.flatnonzero(rcols)
    if not len(first):
        return d
    labels, boxes = hole_boxes(cand, d, lo, hi, int(first[0]))
    if not len(boxes):
        return d
    Hh, Wh = H2 // 2, W2 // 2
    bh = max(1, b // 2)
    ho = replace(opts, p2=opts.hole_p2, speckle_window=max(1, opts.speckle_window // 4), border_px=bh)
    merged = _merge(boxes, lo, Wh, Hh, bh)
    owner = np.full(int(labels.max()) + 1, -1, np.int32)
    for i, (ks, _) in enumerate(merged):
        owner[ks] = i
    m = BOX_MARGIN
    for i, (_, (y0, y1, x0, x1, dl, dh)) in enumerate(merged):
        ql = max(0, (dl - lo) // 2)
        qh = int(math.ceil((dh - lo) / 2.0)) + 1
        num = int(math.ceil((qh - ql + 1) / 16.0)) * 16
        # the box with its margin; real columns on the left for the right pixels of its first columns
        # and for SGBM's first ``num`` columns (which it leaves unmatched), reflected ones only at the
        # window's left edge
        ya, yb = max(0, y0 - m), min(Hh, y1 + m)
        xa = max(0, max(0, x0 - m) - max(num + 1, qh - ql + bh + 1))
        xb = min(Wh, x1 + m + bh)
        Lc, lvc = _halve(L, lv, 2 * ya, 2 * yb, 2 * xa, 2 * xb)
        Rc, rvc = _halve(R, rv, 2 * ya, 2 * yb, 2 * (xa - ql), 2 * (xb - ql))
        q = match(Lc, Rc, lvc, rvc, 0, qh - ql, ho, pad=max(0, num + 1 - (x0 - xa)))
        # the ZNCC of the left crop and the right crop warped by the disparities found
        mx = np.arange(xb - xa, dtype=np.float32)[None, :] - np.nan_to_num(q, nan=0.0)
        my = np.empty_like(mx)
        my[:] = np.arange(yb - ya, dtype=np.float32)[:, None]
        rw = np.asarray(cv2.remap(_grey(Rc), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), np.float32)
        core = (slice(y0 - ya, y1 - ya), slice(x0 - xa, x1 - xa))
        ok = zncc(_grey(Lc), rw, _ZNCC_RADIUS)[core] >= opts.hole_zncc
        own = owner[labels[y0:y1, x0:x1]] == i
        qv = np.where(ok & own, 2.0 * (q[core] + ql) + lo, np.nan).astype(np.float32)
        up = np.asarray(cv2.resize(qv, (2 * (x1 - x0), 2 * (y1 - y0)), interpolation=cv2.INTER_NEAREST))
        Y0, X0 = 2 * y0, 2 * x0
        yy, xx = np.nonzero(cand[Y0:2 * y1, X0:2 * x1] & np.isfinite(up))
        if not len(yy):
            continue
        v = up[yy, xx]
        yy, xx = yy + Y0, xx + X0
        # the full-resolution border rule: the right pixel inside the window, away from nodata
        ci = np.rint(xx - (v - float(lo))).astype(np.intp)
        inside = (ci >= 0) & (ci < W)
        ci = np.clip(ci, 0, W - 1)
        good = inside & (rcols[ci] if rve is None else rve[yy, ci])
        d[yy[good], xx[good]] = v[good]
    return d
