"""Line-of-sight visibility over a DEM block: the occlusion test of the true orthophoto.

Each ground point (an output cell at its DEM height) is visible when nothing of the DEM rises above
its line of sight towards the sensor. :func:`line_of_sight_reference` marches every line in half-pixel
steps, sampling the DEM bilinearly at each step, until the line is higher than the highest DEM point,
leaves the block, or passes under the terrain (occluded: the terrain is more than 1 mm above it).

:func:`line_of_sight` gives the same answer, cell for cell, faster, by skipping the steps that cannot
meet the terrain. Two bounds, on blocks of ``b`` x ``b`` cells and each 3 x 3 neighbourhood of blocks
(every point closer than ``b`` pixels to a line's position lies in a cell of that neighbourhood):

- height: the highest corner of each bilinear cell (a bilinear sample never exceeds it), maximised over
  the neighbourhood; a line above it cannot meet the terrain in the next ``2b`` half-pixel steps (the
  line only rises along its way);
- slope: the steepest rise of the bilinear surface along x and along y in each cell, maximised over the
  neighbourhood; a line of unit direction (ux, uy) that is ``g`` metres above the terrain at a sample and
  rises ``1 / |d|`` metres a pixel cannot get under it within ``b`` pixels while
  ``max(0, |ux| gx + |uy| gy - 1 / |d|) * b <= g + margin``. At the first sample (k = 0) the line is on the
  terrain (``g = 0`` exactly: the bilinear value at a lattice point is its height), so a line rising faster
  than the hills skips its first ``2b - 1`` steps at once; later, ``g`` comes from an exact sample.

Several block sizes are tried (the largest that holds sets the skip; the sets of lines they clear are
nested). The bounds are made only on the box of the block that the lines can reach before they are above
its highest point, and the lines are marched in batches of :data:`RAYS_PER_BATCH` (smaller temporaries:
on the NGI frames 12-17 % less CPU than all lines at once). The steps that are taken are the reference's
steps (the same positions and heights, the same arithmetic), so the result is identical, not merely close
(tests/rectify/test_ortho_speedpaths.py checks it).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.raster.dem import bilinear

__all__ = ["STEP_PX", "HIT_MARGIN_M", "levels_for_margin", "line_of_sight", "line_of_sight_reference"]

#: step along a line of sight, output pixels
STEP_PX = 0.5
#: the terrain must rise this far above a line of sight to hide its point, m
HIT_MARGIN_M = 1e-3
_MAX_STEPS = 100000
#: lines marched together (line_of_sight)
RAYS_PER_BATCH = 1 << 16


def _offsets(m: int | tuple[int, int]) -> tuple[int, int]:
    """(column, row) of the tile's first cell in the block: ``m`` for both, or ``m = (col, row)``."""
    if isinstance(m, tuple):
        return int(m[0]), int(m[1])
    return int(m), int(m)


def _candidates(d: NDArray, z: NDArray, inside: NDArray[np.bool_]):
    """The tile's cells to march (flat indices) and per cell: d as (h * w, 2), |d| and the height."""
    d2 = np.ascontiguousarray(d, dtype=np.float64).reshape(-1, 2)
    ddist = np.hypot(d2[:, 0], d2[:, 1])
    zr = np.ascontiguousarray(z).ravel()
    flat = np.flatnonzero(inside.ravel() & (ddist > 1e-12) & np.isfinite(zr))
    return flat, d2, ddist, zr


def _lines(flat: NDArray, w: int, m: int | tuple[int, int], d2: NDArray, ddist: NDArray, zr: NDArray):
    """The lines of cells ``flat``: z0, |d|, unit direction (ux, uy) and start (px0, py0) in block pixels."""
    mx, my = _offsets(m)
    rows, cols = np.divmod(flat, w)
    sel = d2.take(flat, axis=0)
    dd = ddist.take(flat)
    return zr.take(flat), dd, sel[:, 0] / dd, sel[:, 1] / dd, cols + mx + 0.0, rows + my + 0.0


def _rays(Z: NDArray, m: int | tuple[int, int], d: NDArray, z: NDArray, inside: NDArray[np.bool_]):
    """The lines to march: row, col, z0, |d|, unit direction (ux, uy) and start (px0, py0) in block pixels."""
    w = z.shape[1]
    flat, d2, ddist, zr = _candidates(d, z, inside)
    rows, cols = np.divmod(flat, w)
    return (rows, cols) + _lines(flat, w, m, d2, ddist, zr)


def line_of_sight_reference(Z: NDArray, m: int | tuple[int, int], d: NDArray, z: NDArray,
                            inside: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Visibility (h, w) bool of a tile's cells: True where nothing hides the ground point.

    Parameters
    ----------
    Z : (h + 2m, w + 2m) float
        Heights of the tile with a margin of ``m`` cells (NaN: no height), m.
    m : int or (int, int)
        The margin, cells: the tile's first cell is ``Z[m, m]``; or ``(mx, my)``: it is ``Z[my, mx]`` (a
        block with margins of their own on each side).
    d : (h, w, 2) float
        Horizontal displacement towards the sensor per metre of height, output pixels (col, row).
    z : (h, w) float
        Heights of the tile's cells, m.
    inside : (h, w) bool
        Cells whose ground point projects into the image (the others stay True).
    """
    h, w = z.shape
    vis = np.ones((h, w), bool)
    rows, cols, z0, dd, ux, uy, px0, py0 = _rays(Z, m, d, z, inside)
    if not len(rows):
        return vis
    zmax = float(np.nanmax(Z))
    occl = np.zeros(len(rows), bool)
    active = np.ones(len(rows), bool)
    Zf = np.where(np.isfinite(Z), Z, -np.inf)
    k = 1
    while active.any():
        a = np.flatnonzero(active)
        s = k * STEP_PX
        ray_h = z0[a] + s / dd[a]
        x = px0[a] + s * ux[a]
        y = py0[a] + s * uy[a]
        inb = (x >= 0) & (y >= 0) & (x <= Z.shape[1] - 1) & (y <= Z.shape[0] - 1)
        ter = np.full(len(a), -np.inf)
        if inb.any():
            with np.errstate(invalid="ignore"):   # -inf (a hole) times a zero weight: NaN, no hit, as intended
                ter[inb] = bilinear(Zf, None, x[inb], y[inb])
        hit = ter > ray_h + HIT_MARGIN_M
        occl[a[hit]] = True
        stop = hit | ~inb | (ray_h > zmax)
        active[a[stop]] = False
        k += 1
        if k > _MAX_STEPS:
            break
    vis[rows, cols] = ~occl
    return vis


def _reduce_max(M: NDArray[np.float64], f: int) -> NDArray[np.float64]:
    """Maximum over each ``f`` x ``f`` block of ``M`` (H, W, ...) (padded with -inf to whole blocks)."""
    H, W = M.shape[:2]
    nby, nbx = -(-H // f), -(-W // f)
    if nby * f != H or nbx * f != W:
        pad = np.full((nby * f, nbx * f) + M.shape[2:], -np.inf)
        pad[:H, :W] = M
        M = pad
    # rows, then columns: f - 1 elementwise maxima of strided slices each (the same maxima as one reduction)
    rows = M[0::f].copy()
    for i in range(1, f):
        np.maximum(rows, M[i::f], out=rows)
    out = rows[:, 0::f].copy()
    for j in range(1, f):
        np.maximum(out, rows[:, j::f], out=out)
    return out


def _block_maxima(Zf: NDArray[np.float64], sizes: list[int]) -> list[tuple[int, NDArray[np.float64]]]:
    """For each of the ascending ``sizes`` b (each a multiple of the one before): the maximum of ``Zf`` (H, W) or
    (H, W, C <= 4) over each b x b cell block, then over each 3 x 3 block neighbourhood (a replicated border
    repeats values already in the neighbourhood: the same maximum), channel by channel.

    A block of a larger size is a whole number of blocks of the smaller one (the -inf padding included), so
    its maximum is the maximum of theirs: each size is reduced from the previous one's block maxima.
    """
    out = []
    M, prev = Zf, 1
    for b in sizes:
        if b != prev:
            M = _reduce_max(M, b // prev)
            prev = b
        d = cv2.dilate(np.ascontiguousarray(M, dtype=np.float64), np.ones((3, 3), np.uint8),
                       borderType=cv2.BORDER_REPLICATE)
        out.append((b, np.asarray(d, dtype=np.float64).reshape(M.shape)))
    return out


def levels_for_margin(m: int) -> int:
    """Block sizes ``4**i`` worth trying for a block margin of ``m`` cells: up to the ``m / 1.5`` cells the
    lines travel at most (larger blocks seldom clear, smaller tops cost rounds), 2..5."""
    return int(min(5, max(2, 1 + math.floor(math.log(max(m, 1) / 1.5, 4)))))


def line_of_sight(Z: NDArray, m: int | tuple[int, int], d: NDArray, z: NDArray, inside: NDArray[np.bool_], *,
                  block: int = 1, levels: int | None = None, chunk: int = 1) -> NDArray[np.bool_]:
    """:func:`line_of_sight_reference`'s result, skipping the steps that cannot meet the terrain (module docstring).

    ``block`` (cells, >= 1) sets the smallest skip: ``2 * block`` steps; ``levels`` block sizes
    ``block * 4**i`` are tried (default :func:`levels_for_margin`), the largest whose bound the line clears
    sets the skip. The lines that may be under the terrain take their next ``chunk`` steps exactly at once
    (the first event decides, as in the reference's step by step march).
    """
    if levels is None:
        mx, my = _offsets(m)
        levels = levels_for_margin(max(mx, my, Z.shape[1] - z.shape[1] - mx, Z.shape[0] - z.shape[0] - my))
    h, w = z.shape
    vis = np.ones((h, w), bool)
    flat, d2, ddist, zr = _candidates(d, z, inside)
    if not len(flat):
        return vis
    n, B = len(flat), RAYS_PER_BATCH
    H, W = Z.shape
    fin = np.isfinite(Z)
    all_fin = bool(fin.all())
    zmax = float(Z.max() if all_fin else Z[fin].max())
    # the box of the block that every sample which can matter lies in: a line is done once it is above zmax,
    # after about (zmax - z0) |d| / STEP_PX steps (+ 2 for rounding, + the chunk sampled past a bound, + the
    # far corner of the bilinear cell); the bounds and the padded heights are made on this box only (block
    # coordinates stay the reference's: x, y and the tests of the block's edges are computed as there)
    lo_x = lo_y = np.inf
    hi_x = hi_y = -np.inf
    for lo in range(0, n, B):  # (the lines are made batch by batch: small arrays, their pages reused)
        z0, dd, ux, uy, px0, py0 = _lines(flat[lo:lo + B], w, m, d2, ddist, zr)
        reach = (np.floor((zmax - z0) * dd / STEP_PX) + 2 + chunk) * STEP_PX
        with np.errstate(invalid="ignore", over="ignore"):
            xe, ye = px0 + reach * ux, py0 + reach * uy
        lo_x, hi_x = min(lo_x, px0.min(), np.nanmin(xe)), max(hi_x, px0.max(), np.nanmax(xe))
        lo_y, hi_y = min(lo_y, py0.min(), np.nanmin(ye)), max(hi_y, py0.max(), np.nanmax(ye))
    ox, oy = max(int(math.floor(lo_x)) - 2, 0), max(int(math.floor(lo_y)) - 2, 0)
    wc, hc = min(int(math.ceil(hi_x)) + 3, W) - ox, min(int(math.ceil(hi_y)) + 3, H) - oy
    # bilinear() of the reference on an edge-padded copy: the clamped neighbour of the last row/column is the
    # padded copy of that row/column (inside the block: the next one), so the four samples are the reference's
    Wp = wc + 1
    Zq = np.empty((hc + 1, Wp))
    r1, c1 = min(oy + hc + 1, H), min(ox + wc + 1, W)
    if all_fin:
        Zq[:r1 - oy, :c1 - ox] = Z[oy:r1, ox:c1]
    else:
        np.copyto(Zq[:r1 - oy, :c1 - ox], -np.inf)
        np.copyto(Zq[:r1 - oy, :c1 - ox], Z[oy:r1, ox:c1], where=fin[oy:r1, ox:c1])
    if r1 - oy == hc:
        Zq[hc, :c1 - ox] = Zq[hc - 1, :c1 - ox]
    if c1 - ox == wc:
        Zq[:, wc] = Zq[:, wc - 1]
    Zp = Zq.ravel()
    sizes = [block * 4 ** i for i in range(max(1, levels)) if i == 0 or block * 4 ** i <= max(hc, wc)]
    # per bilinear cell (cell (r, c) spans grid rows r, r + 1 and columns c, c + 1): its highest corner and the
    # steepest rise of the surface along x and along y inside it (a line of unit direction (ux, uy) rises at
    # most |ux| gx + |uy| gy per pixel of path there); then their maxima over the block neighbourhoods
    top = np.maximum(np.maximum(Zq[:-1, :-1], Zq[:-1, 1:]), np.maximum(Zq[1:, :-1], Zq[1:, 1:]))
    with np.errstate(invalid="ignore"):
        ddx = np.abs(np.subtract(Zq[:, 1:], Zq[:, :-1]))
        ddy = np.abs(np.subtract(Zq[1:], Zq[:-1]))
        gx = np.maximum(ddx[:-1], ddx[1:])
        gy = np.maximum(ddy[:, :-1], ddy[:, 1:])
    if not all_fin:  # a NaN comes only from the -inf of a missing height: no bound there
        gx[np.isnan(gx)] = np.inf
        gy[np.isnan(gy)] = np.inf
    # (the slope bounds from the second size on: at the smallest they would skip a step or two)
    ssizes = sizes[1:] or sizes
    tables = [(b, T.ravel(), T.shape[1]) for b, T in _block_maxima(top, sizes)]
    slope_tables = [(b, GX.ravel(), GY.ravel(), GX.shape[1]) for (b, GX), (_, GY) in
                    zip(_block_maxima(gx, ssizes), _block_maxima(gy, ssizes), strict=True)]
    slack = HIT_MARGIN_M - 1e-6

    def march(z0: NDArray, dd: NDArray, ux: NDArray, uy: NDArray, px0: NDArray, py0: NDArray) -> NDArray[np.bool_]:
        """Occlusion of a batch of lines (their arrays are the batch's own: parked lines are written into px0)."""
        occl = np.zeros(len(z0), bool)
        idx = np.arange(len(z0))
        ax, ay, rise = np.abs(ux), np.abs(uy), 1.0 / dd
        # the first sample: at k = 0 the line is on the terrain (the bilinear value at a lattice point is its height
        # z0: gap 0), so where it rises faster than the terrain within b pixels the first 2b - 1 steps are skipped
        k = np.ones(len(z0), np.int64)
        todo = np.arange(len(z0))
        with np.errstate(invalid="ignore"):
            for b, GX, GY, nbx in slope_tables[::-1]:  # descending: the lines cleared at b are cleared below it
                xs0, ys0 = px0.take(todo).astype(np.intp) - ox, py0.take(todo).astype(np.intp) - oy
                cell = (ys0 // b) * nbx + xs0 // b if b > 1 else ys0 * nbx + xs0
                ok = (ax.take(todo) * GX.take(cell) + ay.take(todo) * GY.take(cell) - rise.take(todo)) * b <= slack
                k[todo[ok]] = 2 * b
                todo = todo[~ok]
                if not len(todo):
                    break
        # k never grows by more than this a round: the step limit is tested only once some line could reach it
        k_bound, step_max = int(k.max()), max(2 * sizes[-1], chunk + 2 * sizes[-1] - 1)
        while len(idx):
            s = k * STEP_PX
            ray_h = z0 + s / dd
            x = px0 + s * ux
            y = py0 + s * uy
            inb = (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
            done = ~inb | (ray_h > zmax)
            if k_bound > _MAX_STEPS:
                done |= k > _MAX_STEPS
            n_done = int(np.count_nonzero(done))
            if 4 * n_done >= len(idx):  # many: dropped
                keep = np.flatnonzero(~done)
                if not len(keep):
                    break
                kept: list[Any] = [a.take(keep) for a in (idx, k, z0, dd, ux, uy, px0, py0, ax, ay, rise, ray_h, x, y)]
                idx, k, z0, dd, ux, uy, px0, py0, ax, ay, rise, ray_h, x, y = kept
            elif n_done:  # few: parked outside the block (never inside again: no further sample, no hit)
                px0[done] = -np.inf
                x[done], y[done], ray_h[done] = ox, oy, np.inf  # any cell, above it: their steps go unused
            xi = x.astype(np.intp) - ox  # floor: x >= 0 inside; box cells
            yi = y.astype(np.intp) - oy
            step = np.ones(len(idx), np.int64)
            for b, T, nbx in tables:  # ascending sizes: a larger block's maximum is never lower
                clear = ray_h > T.take((yi // b) * nbx + xi // b if b > 1 else yi * nbx + xi)
                if not clear.any():
                    break
                step[clear] = 2 * b
            fine = np.flatnonzero(step == 1)
            if len(fine):
                # the next `chunk` steps of these lines at once; the first event (hit, out, above all) decides
                kk = k[fine][:, None] + np.arange(chunk)
                s2 = kk * STEP_PX
                rh = z0[fine][:, None] + s2 / dd[fine][:, None]
                x2 = px0[fine][:, None] + s2 * ux[fine][:, None]
                y2 = py0[fine][:, None] + s2 * uy[fine][:, None]
                in2 = (x2 >= 0) & (y2 >= 0) & (x2 <= W - 1) & (y2 <= H - 1)
                x0 = np.where(in2, x2, ox).astype(np.intp)
                y0 = np.where(in2, y2, oy).astype(np.intp)
                fx, fy = x2 - x0, y2 - y0
                p = (y0 - oy) * Wp + (x0 - ox)
                v00, v01, v10, v11 = Zp[p], Zp[p + 1], Zp[p + Wp], Zp[p + Wp + 1]
                with np.errstate(invalid="ignore"):
                    ter = (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy
                    hit = in2 & (ter > rh + HIT_MARGIN_M)
                    event = hit | ~in2 | (rh > zmax)
                    if k_bound + chunk - 1 > _MAX_STEPS:
                        event |= kk > _MAX_STEPS
                any_ev = event.any(axis=1)
                first = event.argmax(axis=1)
                hit_first = any_ev & hit[np.arange(len(fine)), first]
                occl[idx[fine[hit_first]]] = True
                px0[fine[any_ev]] = -np.inf  # done: parked outside the block (never inside again: no sample, no hit)
                step[fine] = chunk
                # from the chunk's last sample (no event, not under the terrain by the margin): skip 2b - 1 further
                # steps where the line rises faster than the terrain can within b pixels by more than its height
                # above the terrain there allows (ascending b: nested)
                with np.errstate(invalid="ignore"):
                    gap = rh[:, -1] - ter[:, -1]
                    go = ~any_ev & np.isfinite(gap) & (gap >= -slack)
                if go.any():
                    sel = np.flatnonzero(go)
                    xl, yl = x0[sel, -1] - ox, y0[sel, -1] - oy
                    fs = fine[sel]
                    af, bf, rf, room = ax[fs], ay[fs], rise[fs], gap[sel] + slack
                    extra = np.zeros(len(sel), np.int64)
                    with np.errstate(invalid="ignore"):
                        for b, GX, GY, nbx in slope_tables:
                            cell = (yl // b) * nbx + xl // b if b > 1 else yl * nbx + xl
                            ok = np.maximum(af * GX.take(cell) + bf * GY.take(cell) - rf, 0.0) * b <= room
                            if not ok.any():
                                break
                            extra[ok] = 2 * b - 1
                    step[fs] += extra
            k += step
            k_bound += step_max
        return occl

    # the lines in batches: the arrays of a batch and its temporaries stay small (fewer fresh pages to fault in,
    # more of them in cache), a few numpy calls more
    occl = np.zeros(n, bool)
    for lo in range(0, n, B):
        occl[lo:lo + B] = march(*_lines(flat[lo:lo + B], w, m, d2, ddist, zr))
    vis.ravel()[flat[occl]] = False
    return vis
