"""Line-of-sight visibility over a DEM block: the occlusion test of the true orthophoto.

Each ground point (an output cell at its DEM height) is visible when nothing of the DEM rises above
its line of sight towards the sensor. :func:`line_of_sight_reference` marches every line in half-pixel
steps, sampling the DEM bilinearly at each step, until the line is higher than the highest DEM point,
leaves the block, or passes under the terrain (occluded: the terrain is more than 1 mm above it).

:func:`line_of_sight` gives the same answer, cell for cell, faster: the block's heights are reduced to
the highest corner of each bilinear cell, then the maximum over blocks of ``block`` x ``block`` cells and
over each 3 x 3 neighbourhood of blocks; every point closer than ``block`` pixels to a line's position
lies in a cell of that neighbourhood, and a bilinear sample never exceeds the highest corner of its
cell, so when the line is already above that maximum the
next ``2 * block`` half-pixel steps cannot meet the terrain and are skipped at once (the line only rises
along its way). Several block sizes are tried, the largest cleared one sets the skip. Likewise from a
sample where the line is not under the terrain: when the line rises faster (per pixel of its path)
than the bilinear surface can within ``block`` pixels (the largest |dZ/dx| + |dZ/dy| of the cells
there), the next ``2 * block - 1`` steps cannot meet it either. The steps that are taken are the
reference's steps (the same positions and heights, the same arithmetic), so the result
is identical, not merely close (tests/rectify/test_ortho_speedpaths.py checks it).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.raster.dem import bilinear

__all__ = ["STEP_PX", "HIT_MARGIN_M", "line_of_sight", "line_of_sight_reference"]

#: step along a line of sight, output pixels
STEP_PX = 0.5
#: the terrain must rise this far above a line of sight to hide its point, m
HIT_MARGIN_M = 1e-3
_MAX_STEPS = 100000


def _rays(Z: NDArray, m: int, d: NDArray, z: NDArray, inside: NDArray[np.bool_]):
    ddist = np.hypot(d[..., 0], d[..., 1])
    cand = inside & (ddist > 1e-12) & np.isfinite(z)
    rows, cols = np.nonzero(cand)
    dx, dy, dd = d[rows, cols, 0], d[rows, cols, 1], ddist[rows, cols]
    return rows, cols, z[rows, cols], dd, dx / dd, dy / dd, cols + m + 0.0, rows + m + 0.0


def line_of_sight_reference(Z: NDArray, m: int, d: NDArray, z: NDArray,
                            inside: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Visibility (h, w) bool of a tile's cells: True where nothing hides the ground point.

    Parameters
    ----------
    Z : (h + 2m, w + 2m) float
        Heights of the tile with a margin of ``m`` cells (NaN: no height), m.
    m : int
        The margin, cells.
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
    """Maximum over each ``f`` x ``f`` block of ``M`` (padded with -inf to whole blocks)."""
    H, W = M.shape
    nby, nbx = -(-H // f), -(-W // f)
    if nby * f != H or nbx * f != W:
        pad = np.full((nby * f, nbx * f), -np.inf)
        pad[:H, :W] = M
        M = pad
    # rows first, then columns: two contiguous reductions (the same maxima as one over both axes)
    return M.reshape(nby, f, nbx * f).max(axis=1).reshape(nby, nbx, f).max(axis=2)


def _block_maxima(Zf: NDArray[np.float64], sizes: list[int]) -> list[tuple[int, NDArray[np.float64]]]:
    """For each of the ascending ``sizes`` b (each a multiple of the one before): the maximum of ``Zf`` over each
    b x b cell block, then over each 3 x 3 block neighbourhood (a replicated border repeats values already in
    the neighbourhood: the same maximum).

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
        out.append((b, np.asarray(d, dtype=np.float64)))
    return out


def line_of_sight(Z: NDArray, m: int, d: NDArray, z: NDArray, inside: NDArray[np.bool_], *,
                  block: int = 1, levels: int = 3, chunk: int = 1) -> NDArray[np.bool_]:
    """:func:`line_of_sight_reference`'s result, skipping the steps that cannot meet the terrain (module docstring).

    ``block`` (cells, >= 1) sets the smallest skip: ``2 * block`` steps when the line is above the highest
    DEM cell within ``block`` pixels; ``levels`` block sizes ``block * 4**i`` are tried, the largest
    whose maximum the line clears sets the skip. The lines that cannot skip take their next ``chunk``
    steps at once (the first event decides, as in the reference's step by step march).
    """
    h, w = z.shape
    vis = np.ones((h, w), bool)
    rows, cols, z0, dd, ux, uy, px0, py0 = _rays(Z, m, d, z, inside)
    if not len(rows):
        return vis
    zmax = float(np.nanmax(Z))
    H, W = Z.shape
    all_fin = bool(np.isfinite(Z).all())
    Zf = Z if all_fin else np.where(np.isfinite(Z), Z, -np.inf)  # Zp below is a copy
    # bilinear() of the reference on an edge-padded copy: the clamped neighbour of the last row/column is the
    # padded copy of that row/column, so the four samples (and the sums) are the reference's
    Zp = np.pad(Zf, ((0, 1), (0, 1)), mode="edge").ravel()
    Wp = W + 1
    sizes = [block * 4 ** i for i in range(max(1, levels)) if i == 0 or block * 4 ** i <= max(H, W)]
    # the highest corner of each bilinear cell (cell (r, c) spans grid rows r, r + 1 and columns c, c + 1)
    Zq = Zp.reshape(H + 1, Wp)
    top = np.maximum(np.maximum(Zq[:-1, :-1], Zq[:-1, 1:]), np.maximum(Zq[1:, :-1], Zq[1:, 1:]))
    maxima = _block_maxima(top, sizes)
    # the steepest rise of the bilinear surface per pixel of path in each cell (|d/dx| + |d/dy| bounds), then
    # its maximum over the same block neighbourhoods: a line rising faster than that from a point where it
    # is not under the terrain cannot get under it within the neighbourhood
    with np.errstate(invalid="ignore"):
        ddx = np.abs(np.diff(Zq, axis=1))
        ddy = np.abs(np.diff(Zq, axis=0))
        g = np.maximum(ddx[:-1], ddx[1:]) + np.maximum(ddy[:, :-1], ddy[:, 1:])
    if not all_fin:  # a NaN comes only from the -inf of a missing height
        g = np.where(np.isnan(g), np.inf, g)
    slopes = _block_maxima(g, sizes)
    occl = np.zeros(len(rows), bool)
    idx = np.arange(len(rows))
    k = np.ones(len(rows), np.int64)
    # k never grows by more than this a round: the step limit is tested only once some line could reach it
    k_bound, step_max = 1, max(2 * sizes[-1], chunk + 2 * sizes[-1] - 1)
    while len(idx):
        s = k * STEP_PX
        ray_h = z0 + s / dd
        x = px0 + s * ux
        y = py0 + s * uy
        inb = (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
        done = ~inb | (ray_h > zmax)
        xi = np.where(inb, x, 0.0).astype(np.intp)  # floor: x >= 0 inside
        yi = np.where(inb, y, 0.0).astype(np.intp)
        step = np.ones(len(idx), np.int64)
        for b, M3 in maxima:  # ascending sizes: a larger block's maximum is never lower
            cell = yi * M3.shape[1] + xi if b == 1 else (yi // b) * M3.shape[1] + xi // b
            clear = ray_h > M3.take(cell)  # out of the block too: such a line is done, its step unused
            if not clear.any():
                break
            step[clear] = 2 * b
        fine = np.flatnonzero(inb & (step == 1))
        if len(fine):
            # the next `chunk` steps of these lines at once; the first event (hit, out, above all) decides
            kk = k[fine][:, None] + np.arange(chunk)
            s2 = kk * STEP_PX
            rh = z0[fine][:, None] + s2 / dd[fine][:, None]
            x2 = px0[fine][:, None] + s2 * ux[fine][:, None]
            y2 = py0[fine][:, None] + s2 * uy[fine][:, None]
            in2 = (x2 >= 0) & (y2 >= 0) & (x2 <= W - 1) & (y2 <= H - 1)
            x0 = np.where(in2, x2, 0.0).astype(np.intp)
            y0 = np.where(in2, y2, 0.0).astype(np.intp)
            fx, fy = x2 - x0, y2 - y0
            p = y0 * Wp + x0
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
            done[fine[any_ev]] = True
            step[fine] = chunk
            # from the chunk's last sample (no event): skip 2b - 1 further steps where the line rises faster
            # than the terrain can within b pixels and is not under it there (margin kept: no tie decides)
            go = ~any_ev & (ter[:, -1] <= rh[:, -1] + HIT_MARGIN_M - 1e-6)
            if go.any():
                xl, yl = x0[:, -1], y0[:, -1]
                rise = 1.0 / dd[fine]
                extra = np.zeros(len(fine), np.int64)
                for b, G3 in slopes:
                    ok = go & (rise >= G3.take((yl // b) * G3.shape[1] + xl // b))
                    if not ok.any():
                        break
                    extra[ok] = 2 * b - 1
                step[fine] += extra
        k += step
        k_bound += step_max
        if k_bound > _MAX_STEPS:
            done |= k > _MAX_STEPS
        if done.any():
            n_done = int(done.sum())
            if 4 * n_done >= len(idx):
                keep = ~done
                idx, k, z0, dd, ux, uy, px0, py0 = (a[keep] for a in (idx, k, z0, dd, ux, uy, px0, py0))
            else:  # few: park them outside the block (never inside again: no further sample, no hit)
                px0[done] = -np.inf
    vis[rows, cols] = ~occl
    return vis
