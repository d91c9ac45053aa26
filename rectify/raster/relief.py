"""The relief displacement an orthophoto removed: per cell of a coarse lattice of the output grid.

:func:`relief_shift` measures, for the written cells of an orthophoto (:func:`rectify.raster.ortho.orthorectify`),
how far a planar rectification at the mean height would have put each cell (:class:`ReliefShift`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from affine import Affine
from numpy.typing import NDArray

from rectify.errors import CRSError
from rectify.geometry.crs import same_crs, transform_xy, unit_label, utm_crs
from rectify.geometry.sensors import SensorModel
from rectify.raster.georef import Grid

__all__ = ["ReliefShift", "relief_shift", "relief_stride"]


def _gt(transform: Any) -> tuple[float, ...]:
    """The six geotransform numbers (a, b, c, d, e, f) of a rasterio Affine."""
    return tuple(float(v) for v in tuple(transform)[:6])


def relief_stride(grid: Grid, max_size: int = 256) -> int:
    """Output pixels between the cells of the relief lattice (at most ``max_size`` cells a side); odd, so each
    lattice cell is centred on an output pixel."""
    s = max(1, math.ceil(max(grid.width, grid.height) / max_size))
    return s if s % 2 else s + 1


@dataclass(frozen=True, eq=False)
class ReliefShift:
    """The relief displacement the DEM removed, over the written (valid) cells of the relief lattice.

    For each sampled valid output cell, ground point X at its DEM height h: the horizontal distance
    between X and the point where a planar rectification at the mean height ``h_ref`` of the sampled
    cells would have put the same image pixel, ``|G(project(X, h), h_ref) - X|`` (exact, no
    linearisation), in metres. The lattice takes one output pixel every ``stride`` pixels in both
    directions (at most 256 a side), so the console, the report and the map hold the same numbers.

    Attributes
    ----------
    h_ref : float
        Mean height of the sampled cells (the plane), m.
    n_cells : int
        Sampled valid cells.
    n_unreached : int
        Cells whose line of sight does not reach the plane (left out of the figures).
    median, p95, max, mean : float
        Of the displacement, m (NaN without cells).
    map : (rows, cols) float32
        The displacement per lattice cell (NaN where the output has no data).
    transform : Affine
        Of ``map`` (cells of ``stride`` output pixels, in the output CRS).
    """

    h_ref: float
    n_cells: int
    n_unreached: int
    median: float
    p95: float
    max: float
    mean: float
    map: NDArray[np.float32]
    transform: Any
    stride: int

    def summary_line(self) -> str:
        if not self.n_cells:
            return "relief displacement removed: no valid output cell"
        left = (f"; {self.n_unreached} cells whose line of sight misses that plane left out"
                if self.n_unreached else "")
        return (f"relief displacement removed (DEM vs a plane at the mean height {self.h_ref:.2f} m, "
                f"{self.n_cells} valid cells sampled every {self.stride} px): median {self.median:.2f} m, "
                f"95th percentile {self.p95:.2f} m, max {self.max:.2f} m{left}")

    def to_dict(self) -> dict[str, Any]:
        """The figures (no map), for the report JSON."""
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None
        return {"definition": "horizontal distance between each valid output cell and where a planar "
                              "rectification at the mean height would have put it, m",
                "plane_height_m": num(self.h_ref), "cells": self.n_cells, "cells_missing_the_plane": self.n_unreached,
                "stride_px": self.stride, "median_m": num(self.median), "p95_m": num(self.p95),
                "max_m": num(self.max), "mean_m": num(self.mean)}


def _xy_or_nan(src: str, dst: str, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`transform_xy`, with NaN rows for the points PROJ cannot transform (a plane point far out)."""
    try:
        return transform_xy(src, dst, xy)
    except CRSError:
        out = np.full(xy.shape, np.nan)
        for i, q in enumerate(xy):
            if np.isfinite(q).all():
                try:
                    out[i] = transform_xy(src, dst, q[None])[0]
                except CRSError:
                    pass
        return out


def _finite_rows(a: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) True where every column of ``a`` (N, C) is finite (column by column: numpy's reduction over a short
    last axis is several times slower)."""
    ok = np.isfinite(a[:, 0])
    for j in range(1, a.shape[1]):
        ok &= np.isfinite(a[:, j])
    return ok


def relief_shift(model: SensorModel, grid: Grid, samples: NDArray[np.float64], stride: int) -> ReliefShift:
    """:class:`ReliefShift` of the lattice ``samples`` (M, 3) (row, col, h) of an output ``grid``."""
    t = _gt(grid.transform)
    ny, nx = -(-grid.height // stride), -(-grid.width // stride)
    shift_map = np.full((ny, nx), np.nan, np.float32)
    tr = Affine(t[0] * stride, 0.0, t[2], 0.0, t[4] * stride, t[5])
    a = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    a = a[_finite_rows(a)]
    gcrs = str(grid.crs)
    if not len(a):
        nan = float("nan")
        return ReliefShift(nan, 0, 0, nan, nan, nan, nan, shift_map, tr, stride)
    rows, cols, z = a[:, 0], a[:, 1], a[:, 2]
    h_ref = float(z.mean())
    world = np.column_stack([t[2] + t[0] * (cols + 0.5), t[5] + t[4] * (rows + 0.5)])
    same = same_crs(gcrs, model.crs)
    ground = world if same else _xy_or_nan(gcrs, model.crs, world)
    pix = model.project(np.column_stack([ground, z]))
    dist = np.full(len(a), np.nan)
    ok = _finite_rows(pix)
    if ok.any():
        g = model.ground_at_height(pix[ok], h_ref)
        ok2 = _finite_rows(g)
        idx = np.flatnonzero(ok)[ok2]
        if len(idx):
            plane = g[ok2, :2] if same else _xy_or_nan(model.crs, gcrs, g[ok2, :2])
            here = world[idx]
            if unit_label(gcrs) != "m":  # measure in metres: the UTM zone of the cells
                c = transform_xy(gcrs, "EPSG:4326", here[:1])[0]
                utm = utm_crs(float(c[0]), float(c[1]))
                plane, here = _xy_or_nan(gcrs, utm, plane), _xy_or_nan(gcrs, utm, here)
            dist[idx] = np.hypot(*(plane - here).T)
    fin = np.isfinite(dist)
    shift_map[(rows[fin] // stride).astype(np.intp), (cols[fin] // stride).astype(np.intp)] = dist[fin]
    d = dist[fin]
    if not len(d):
        nan = float("nan")
        return ReliefShift(h_ref, len(a), len(a), nan, nan, nan, nan, shift_map, tr, stride)
    return ReliefShift(h_ref, len(a), int((~fin).sum()), float(np.median(d)), float(np.percentile(d, 95)),
                       float(d.max()), float(d.mean()), shift_map, tr, stride)
