"""How much of an orthophoto's output grid would hold data: checked before a tile is computed.

An orthophoto cell gets a value when the DEM has a height there (a constant height,
:meth:`rectify.raster.dem.Dem.constant_height`, has one everywhere) and the ground point at that
height projects into the image. :func:`ortho_coverage` estimates that share on a lattice of at most
64 x 64 cell centres of the output grid, with the heights of a decimated read of the DEM (its
longer side at most 512 cells), and gives the DEM's extent and the image footprint in the output
CRS, so that a refusal can say why nothing would be written: a DEM that does not cover the image,
an exterior orientation (or an RPC moved by far GCPs) that puts the image somewhere else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.crs import same_crs, transform_xy, unit_label
from rectify.geometry.sensors import SensorModel
from rectify.raster.dem import Dem
from rectify.raster.georef import Grid, boundary_pixels, crs_label, pixel_from_world

__all__ = ["Coverage", "ortho_coverage", "check_coverage", "LATTICE", "DEM_OVERVIEW"]

#: cells of the sampling lattice along each side of the output grid (at most)
LATTICE = 64
#: longer side of the decimated DEM read for the estimate, cells
DEM_OVERVIEW = 512

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class Coverage:
    """The estimated coverage of an output grid.

    Attributes
    ----------
    n : int
        Cells sampled.
    valid_share : float
        Share of the sampled cells with a DEM height whose ground point projects into the image.
    dem_share : float
        Share of the sampled cells with a DEM height.
    footprint_share : float
        Share of the sampled cells that see the image at the DEM's mean height.
    dem_bounds, footprint_bounds : (x0, y0, x1, y1) or None
        The DEM's extent and the image footprint (at the DEM's lowest to highest heights), output CRS.
    crs : str
        The output CRS.
    """

    n: int
    valid_share: float
    dem_share: float
    footprint_share: float
    dem_bounds: Bounds | None
    footprint_bounds: Bounds | None
    crs: str

    def line(self) -> str:
        """``valid cells: about 97.3 % of the output grid (4096 sampled)``."""
        return f"valid cells: about {100 * self.valid_share:.1f} % of the output grid ({self.n} sampled)"

    def refusal(self, minimum: float) -> str:
        """The one-line reason an orthophoto of this coverage is refused (below ``minimum``)."""
        u = unit_label(self.crs)
        where = f"in {crs_label(self.crs)}"
        dem = _bounds_text(self.dem_bounds, u)
        fp = _bounds_text(self.footprint_bounds, u)
        if self.dem_share == 0 and self.footprint_share > 0:
            why = "the DEM does not cover the image footprint"
        elif self.footprint_share == 0:
            why = "the image does not see the ground of its own footprint at the DEM's heights"
        elif self.dem_share < minimum:
            why = "the DEM covers too little of the image footprint"
        else:
            why = "the DEM's heights put the ground outside the image"
        return (f"the orthophoto would be {'empty' if self.valid_share == 0 else 'mostly nodata'}: "
                f"{100 * self.valid_share:.1f} % of the output grid ({self.n} cells sampled) gets a DEM height and "
                f"a pixel of the image (at least {100 * minimum:g} % needed); {why}: the DEM covers {dem} but the "
                f"image footprint is {fp} {where} (check the DEM, the exterior orientation or the GCPs)")


def _bounds_text(b: Bounds | None, unit: str) -> str:
    if b is None:
        return "nothing"
    return f"x {b[0]:.10g} .. {b[2]:.10g}, y {b[1]:.10g} .. {b[3]:.10g} {unit}"


def _bbox(xy: NDArray[np.float64]) -> Bounds | None:
    ok = np.isfinite(xy).all(axis=1)
    if not ok.any():
        return None
    p = xy[ok]
    return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())


def _to(src: str, dst: str, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points from ``src`` to ``dst``; rows that cannot be transformed become NaN."""
    if same_crs(src, dst):
        return xy
    out = np.full(xy.shape, np.nan)
    ok = np.isfinite(xy).all(axis=1)
    if ok.any():
        try:
            out[ok] = transform_xy(src, dst, xy[ok])
        except Exception:  # noqa: BLE001 - points outside a CRS's domain: no coverage there
            for i in np.flatnonzero(ok):
                try:
                    out[i] = transform_xy(src, dst, xy[i:i + 1])[0]
                except Exception:  # noqa: BLE001
                    pass
    return out


def ortho_coverage(model: SensorModel, dem: Dem, grid: Grid, *, lattice: int = LATTICE) -> Coverage:
    """Estimate the share of ``grid`` an orthophoto of ``model`` over ``dem`` fills (module docstring)."""
    crs = str(grid.crs)
    ny, nx = min(lattice, grid.height), min(lattice, grid.width)
    cols = (np.arange(nx) + 0.5) * grid.width / nx - 0.5
    rows = (np.arange(ny) + 0.5) * grid.height / ny - 0.5
    cc, rr = np.meshgrid(cols, rows)
    t = grid.transform
    px = np.column_stack([cc.ravel(), rr.ravel()]) + 0.5  # cell centres on rasterio's corner grid
    world = np.column_stack([t.c + t.a * px[:, 0] + t.b * px[:, 1], t.f + t.d * px[:, 0] + t.e * px[:, 1]])
    # heights from a decimated read of the DEM (read once per DEM file: Dem.overview); a constant height: 1 x 1
    if dem.constant is not None:
        data, valid, scale = np.full((1, 1, 1), dem.constant), np.ones((1, 1), bool), 1.0
    else:
        data, valid, scale = dem.overview(DEM_OVERVIEW)
    z_file = np.asarray(data, dtype=np.float64)[..., 0]
    ok_dem = valid & np.isfinite(z_file)
    if dem.nodata is not None:
        ok_dem &= z_file != dem.nodata
    q = _to(crs, dem.crs, world)
    fin = np.isfinite(q).all(axis=1)
    dpx = np.full(q.shape, np.nan)
    if fin.any():
        dpx[fin] = pixel_from_world(dem.transform, q[fin])
    oc = np.rint((dpx[:, 0] + 0.5) / scale - 0.5)
    orr = np.rint((dpx[:, 1] + 0.5) / scale - 0.5)
    h, w = z_file.shape
    if dem.constant is not None:  # everywhere
        oc, orr = np.where(fin, 0.0, np.nan), np.where(fin, 0.0, np.nan)
    inside_dem = fin & (oc >= 0) & (orr >= 0) & (oc < w) & (orr < h)
    z = np.full(len(world), np.nan)
    ii, jj = orr[inside_dem].astype(np.intp), oc[inside_dem].astype(np.intp)
    has = ok_dem[ii, jj]
    lo_off, hi_off = dem.offset_range()
    z_in = np.where(has, z_file[ii, jj] + 0.5 * (lo_off + hi_off), np.nan)
    z[inside_dem] = z_in
    has_z = np.isfinite(z)
    # the image at the DEM's heights, and at their mean (the footprint)
    g = _to(crs, model.crs, world)
    sees = np.zeros(len(world), bool)
    if has_z.any():
        pix = model.project(np.column_stack([g[has_z], z[has_z]]))
        sees[has_z] = _in_image(model, pix)
    zs = z_file[ok_dem]
    h_mean = float(np.mean(zs)) + 0.5 * (lo_off + hi_off) if zs.size else 0.0
    fin_g = np.isfinite(g).all(axis=1)
    in_fp = np.zeros(len(world), bool)
    if fin_g.any():
        in_fp[fin_g] = _in_image(model, model.project(np.column_stack([g[fin_g], np.full(int(fin_g.sum()),
                                                                                         h_mean)])))
    # the DEM's extent (a constant height: none, it is everywhere) and the footprint, output CRS
    dem_edge = _dem_edge(dem) if dem.constant is None else np.full((1, 2), np.nan)
    lo_h, hi_h = (float(zs.min()) + lo_off, float(zs.max()) + hi_off) if zs.size else (h_mean, h_mean)
    edge = boundary_pixels(model.width, model.height, 17)
    fp = [model.ground_at_height(edge, hh)[:, :2] for hh in (lo_h, hi_h)]
    n = len(world)
    return Coverage(n, float(np.mean(sees)), float(np.mean(has_z)), float(np.mean(in_fp)),
                    _bbox(_to(dem.crs, crs, dem_edge)), _bbox(_to(model.crs, crs, np.vstack(fp))), crs)


def _in_image(model: SensorModel, pix: NDArray[np.float64]) -> NDArray[np.bool_]:
    p = np.asarray(pix, dtype=np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        return np.asarray(np.isfinite(p).all(axis=1) & (p[:, 0] >= -0.5) & (p[:, 1] >= -0.5)
                          & (p[:, 0] <= model.width - 0.5) & (p[:, 1] <= model.height - 0.5), bool)


def _dem_edge(dem: Dem, n: int = 17) -> NDArray[np.float64]:
    """Points along the DEM's outer edge (its corners included), DEM CRS."""
    t: Any = dem.transform
    k = np.linspace(0.0, 1.0, n)
    W, H = float(dem.width), float(dem.height)
    px = np.vstack([np.column_stack([k * W, np.zeros(n)]), np.column_stack([k * W, np.full(n, H)]),
                    np.column_stack([np.zeros(n), k * H]), np.column_stack([np.full(n, W), k * H])])
    return np.column_stack([t.c + t.a * px[:, 0] + t.b * px[:, 1], t.f + t.d * px[:, 0] + t.e * px[:, 1]])


def check_coverage(model: SensorModel, dem: Dem, grid: Grid, minimum: float) -> Coverage:
    """:func:`ortho_coverage`, refused below ``minimum`` (a share of the output grid in [0, 1]).

    Raises
    ------
    InvalidInputError
        The orthophoto would be empty or mostly nodata: the valid share, the DEM's extent and the
        image footprint (:meth:`Coverage.refusal`).
    """
    if not (isinstance(minimum, (int, float)) and math.isfinite(minimum) and 0 <= minimum <= 1):
        raise InvalidInputError(f"the minimum valid share must be in [0, 1]; got {minimum!r}")
    cov = ortho_coverage(model, dem, grid)
    if cov.valid_share < minimum or (minimum > 0 and cov.valid_share == 0):
        raise InvalidInputError(cov.refusal(minimum))
    return cov
