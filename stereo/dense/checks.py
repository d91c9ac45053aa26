"""Per-row tests of SGBM's disparities and the strip layout of the dense post-processing.

Split from :mod:`stereo.dense.matching` (issue 30). Disparity convention: ``d = col_left - col_right``
of rectified photos, NaN where there is none. The tests run strip by strip: the temporaries of a
strip are small and reused, where whole-window temporaries each cost fresh pages.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["collisions", "erode_valid", "noise_fill", "row_tests", "strip_rows", "strips"]


#: pixels per strip of the post-processing (tests, median, sub-pixel step, confidence): the
#: temporaries of a strip are small and reused, where whole-window temporaries each cost fresh pages
#: (page faults were half the post-processing's time on Motorcycle, issue 30); the results are
#: those of whole windows
_STRIP_PX = 49152


def strip_rows(W: int) -> int:
    """Rows per strip of a window ``W`` px wide (about ``_STRIP_PX`` pixels, at least 16 rows)."""
    return max(16, _STRIP_PX // max(W, 1))


def strips(H: int, halo: int, W: int) -> list[tuple[int, int, int, int]]:
    """Strips ``(r0, r1, a0, a1)`` of a window W px wide: core rows r0:r1, read with ``halo`` rows
    either side (a0:a1)."""
    rows = strip_rows(W)
    out = []
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        if H - r1 < rows // 4:  # no thin last strip
            r1 = H
        out.append((r0, r1, max(0, r0 - halo), min(H, r1 + halo)))
        if r1 == H:
            break
    return out


def noise_fill(img: NDArray[np.uint8], valid: NDArray[np.bool_], seed: int) -> NDArray[np.uint8]:
    """``img`` with its invalid pixels replaced by random grey values (they then match nothing well)."""
    if valid.all():
        return img
    out = img.copy()
    bad = ~valid
    rng = np.random.default_rng(seed)
    shape = (int(bad.sum()),) + img.shape[2:]
    out[bad] = rng.integers(0, 256, shape, dtype=np.uint8)
    return out


def erode_valid(valid: NDArray[np.bool_], px: int) -> NDArray[np.bool_]:
    """``valid`` eroded by ``px`` (a (2 px + 1)^2 square); may return ``valid`` itself."""
    if px <= 0 or valid.all():
        return valid
    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    # the window's left and right edges count as nodata (matches and the sub-pixel step are unsure
    # there), its top and bottom edges do not (issue 30: they dropped a 4-row frame, and only in
    # windows that held nodata)
    v = cv2.copyMakeBorder(valid.astype(np.uint8), px, px, 0, 0, cv2.BORDER_REPLICATE)
    return np.asarray(cv2.erode(v, k, borderType=cv2.BORDER_CONSTANT, borderValue=0)[px:-px] > 0)


def collisions(d: NDArray[np.float32], tol: float) -> NDArray[np.bool_]:
    """Pixels hidden in the right photo by a nearer surface.

    Pixel x (disparity d) claims the right pixel ``x - d``. It is hidden when a pixel further right
    on the row maps left of that by more than ``tol`` (the nearer surface covers it), or when a pixel
    at least two columns further right maps within half a pixel of it: then that pixel's disparity
    exceeds d by more than 1.5 px and both claim one right pixel, which belongs to the nearer one.
    This is a z-buffer of the right pixels computed with two running minima per row (NaN-ignoring:
    pixels without a disparity hide nothing and are never marked).
    """
    W = d.shape[1]
    xr = np.arange(W, dtype=np.float32)[None, :] - d
    run = np.fmin.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
    hidden = np.zeros(d.shape, bool)
    if W > 1:
        np.less(run[:, 1:], xr[:, :-1] - np.float32(tol), out=hidden[:, :-1])
    if W > 2:
        hidden[:, :-2] |= run[:, 2:] < xr[:, :-2] + np.float32(0.5)
    return hidden


def row_tests(raw: NDArray, lve: NDArray[np.bool_], rve: NDArray[np.bool_], raw_r: NDArray | None,
           collision_tol: float | None, lr_max_diff: int, cols: tuple[int, int] | None = None
           ) -> NDArray[np.float32]:
    """Disparities (px, from the window's ``dmin``) of SGBM's raw rows after the per-row tests.

    Border rule (``lve``/``rve``: the eroded validity of the left and right windows; ``cols``: when
    given, the right pixels valid are exactly the columns ``cols[0]..cols[1]``), then the collision
    test (``collision_tol`` not None) or the check against the right-reference SGBM rows ``raw_r``
    (within ``lr_max_diff``).
    """
    h, W = raw.shape
    d = raw.astype(np.float32)
    d *= np.float32(1.0 / 16.0)
    d[raw < 0] = np.nan
    if not lve.all():
        d[~lve] = np.nan
    xr = np.arange(W, dtype=np.float32)[None, :] - d
    ci = None
    if cols is None and rve.all() and raw_r is None:
        cols = (0, W - 1)
    if cols is not None and raw_r is None:  # the right pixel's column alone decides (no lookup)
        rx = np.rint(xr)
        d[~((rx >= cols[0]) & (rx <= cols[1]))] = np.nan
    else:
        ci = np.rint(np.nan_to_num(xr, nan=-1.0)).astype(np.int64)
        inside = (ci >= 0) & (ci < W)
        np.clip(ci, 0, W - 1, out=ci)
        rows = np.arange(h)[:, None]
        d[~inside | ~rve[rows, ci]] = np.nan
    if collision_tol is not None:
        d[collisions(d, collision_tol)] = np.nan
    elif raw_r is not None and np.isfinite(d).any():
        assert ci is not None
        dr = raw_r.astype(np.float32)
        dr *= np.float32(1.0 / 16.0)
        dr[raw_r < 0] = np.nan
        back = dr[np.arange(h)[:, None], ci]
        d[~(np.abs(back - d) <= lr_max_diff)] = np.nan
    return d
