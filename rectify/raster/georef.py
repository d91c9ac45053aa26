"""Pixel <-> world on rasterio's grid, and output grids for warping.

This is the only module that does GDAL corner-grid arithmetic. The project
puts the centre of the top-left pixel at (0, 0) (x = column, y = row);
rasterio's ``Affine`` geotransform puts (0, 0) at the *corner* of that pixel.
:func:`world_from_pixel` and :func:`pixel_from_world` apply the half-pixel
shift; :func:`world_from_pixel_matrix` gives the same map as a (3, 3) matrix
for vectorised composition with projective models.

:func:`crs_label` names a grid's CRS in messages (``EPSG:n`` or the PROJ string).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from affine import Affine
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.crs import parse_crs
from rectify.geometry.points import as_points

__all__ = ["Grid", "world_from_pixel", "pixel_from_world", "world_from_pixel_matrix",
           "pixel_from_world_matrix", "boundary_pixels", "suggest_resolution", "output_grid", "check_horizon",
           "crs_label"]

logger = logging.getLogger(__name__)


def world_from_pixel_matrix(transform) -> NDArray[np.float64]:
    """(3, 3) matrix M with world = M @ (x, y, 1) for pixel centres at integers.

    Parameters
    ----------
    transform : affine.Affine
        rasterio geotransform (pixel-corner convention).
    """
    a, b, c, d, e, f = (float(v) for v in tuple(transform)[:6])
    # corner (x + 0.5, y + 0.5) -> world
    return np.array([[a, b, c + 0.5 * (a + b)],
                     [d, e, f + 0.5 * (d + e)],
                     [0.0, 0.0, 1.0]])


def pixel_from_world_matrix(transform) -> NDArray[np.float64]:
    """(3, 3) inverse of :func:`world_from_pixel_matrix`.

    Raises
    ------
    InvalidInputError
        If the geotransform is singular.
    """
    m = world_from_pixel_matrix(transform)
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    if not math.isfinite(det) or abs(det) < 1e-300:
        raise InvalidInputError(f"geotransform is singular: {tuple(transform)[:6]}")
    return np.asarray(np.linalg.inv(m), dtype=np.float64)


def world_from_pixel(transform, pixels: ArrayLike) -> NDArray[np.float64]:
    """World coordinates of pixel positions.

    Parameters
    ----------
    transform : affine.Affine
        rasterio geotransform (corner convention).
    pixels : (N, 2) float64
        (col, row), pixel centres at integers.

    Returns
    -------
    (N, 2) float64
        (x, y) in the raster's CRS units.

    Examples
    --------
    >>> from affine import Affine
    >>> world_from_pixel(Affine(10, 0, 1000, 0, -10, 5000), [[0, 0]]).tolist()
    [[1005.0, 4995.0]]
    """
    p = as_points(pixels, "pixels")
    m = world_from_pixel_matrix(transform)
    return p @ m[:2, :2].T + m[:2, 2]


def pixel_from_world(transform, world: ArrayLike) -> NDArray[np.float64]:
    """Pixel positions (centres at integers) of world coordinates (inverse of :func:`world_from_pixel`).

    Parameters
    ----------
    world : (N, 2) float64

    Returns
    -------
    (N, 2) float64 (col, row).
    """
    p = as_points(world, "world")
    m = pixel_from_world_matrix(transform)
    return p @ m[:2, :2].T + m[:2, 2]


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid: size, geotransform, CRS.

    Attributes
    ----------
    width, height : int
        Columns and rows.
    transform : affine.Affine
        rasterio geotransform (corner convention).
    crs : str or None
        ``"EPSG:nnnn"`` or WKT; None for a plain pixel frame.
    """

    width: int
    height: int
    transform: Affine
    crs: str | None = None

    def __post_init__(self) -> None:
        if int(self.width) < 1 or int(self.height) < 1:
            raise InvalidInputError(f"grid size must be positive; got {self.width} x {self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def resolution(self) -> tuple[float, float]:
        """(x, y) pixel size in CRS units (positive)."""
        t = tuple(self.transform)
        return abs(float(t[0])), abs(float(t[4]))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) of the outer pixel edges."""
        t = tuple(self.transform)
        left, top = float(t[2]), float(t[5])
        right = left + t[0] * self.width
        bottom = top + t[4] * self.height
        return min(left, right), min(bottom, top), max(left, right), max(bottom, top)


def boundary_pixels(width: int, height: int, n_per_edge: int = 21) -> NDArray[np.float64]:
    """Points along the outer edge of a ``width`` x ``height`` image (pixel frame).

    The edge is the outer boundary of the pixels (-0.5 .. width - 0.5), so the
    footprint covers whole pixels.

    Returns
    -------
    (4 * n_per_edge, 2) float64 (col, row).
    """
    t = np.linspace(0.0, 1.0, n_per_edge)
    x0, x1, y0, y1 = -0.5, width - 0.5, -0.5, height - 0.5
    top = np.column_stack([x0 + t * (x1 - x0), np.full_like(t, y0)])
    right = np.column_stack([np.full_like(t, x1), y0 + t * (y1 - y0)])
    bottom = np.column_stack([x1 - t * (x1 - x0), np.full_like(t, y1)])
    left = np.column_stack([np.full_like(t, x0), y1 - t * (y1 - y0)])
    return np.vstack([top, right, bottom, left])


def suggest_resolution(world_from_src: Callable[[NDArray], NDArray], width: int, height: int) -> float:
    """A square output pixel size, as GDAL's ``GDALSuggestedWarpOutput`` chooses it.

    The distance between the transformed top-left and bottom-right corners of
    the source, divided by the source diagonal in pixels: the output keeps
    about as many pixels along the diagonal as the source has.

    Parameters
    ----------
    world_from_src : callable (N, 2) -> (N, 2)
        Source pixels (centres at integers) -> output CRS coordinates.
    """
    corners = np.array([[-0.5, -0.5], [width - 0.5, height - 0.5]])
    w = np.asarray(world_from_src(corners), dtype=np.float64)
    dist = float(np.hypot(*(w[1] - w[0])))
    res = dist / math.hypot(width, height)
    if not math.isfinite(res) or res <= 0:
        # fall back to the other diagonal
        corners = np.array([[width - 0.5, -0.5], [-0.5, height - 0.5]])
        w = np.asarray(world_from_src(corners), dtype=np.float64)
        res = float(np.hypot(*(w[1] - w[0]))) / math.hypot(width, height)
    if not math.isfinite(res) or res <= 0:
        raise InvalidInputError(f"cannot estimate an output resolution (got {res!r}); pass a resolution")
    return res


def output_grid(world_from_src: Callable[[NDArray], NDArray], width: int, height: int, *,
                resolution: float | None = None, crs: str | None = None,
                max_pixels: float = 4e10, y_up: bool = True) -> Grid:
    """The north-up output grid covering the transformed footprint of a source image.

    Parameters
    ----------
    world_from_src : callable (N, 2) -> (N, 2)
        Source pixels -> output CRS coordinates (x east, y north).
    width, height : int
        Source size in pixels.
    resolution : float, optional
        Output pixel size in CRS units; default :func:`suggest_resolution`.
    crs : str, optional
        Stored in the grid.
    max_pixels : float
        Refuse grids larger than this (a sign of a degenerate transform).
    y_up : bool
        True for map CRSs (north-up, negative row step). False for target
        *pixel* frames (y down, no CRS): rows then increase with y.

    Returns
    -------
    Grid
        Bounds aligned to multiples of the resolution (like ``gdalwarp -tap``).

    Raises
    ------
    InvalidInputError
        Non-positive resolution, a footprint that does not transform to finite
        coordinates, or an absurdly large grid.
    """

    if resolution is not None and (not math.isfinite(resolution) or resolution <= 0):
        raise InvalidInputError(f"resolution must be a positive number; got {resolution!r}")
    matrix = getattr(world_from_src, "matrix", None)
    if matrix is not None:
        check_horizon(matrix, width, height)
    edge = boundary_pixels(width, height, 21 if max(width, height) < 100 else 65)
    w = np.asarray(world_from_src(edge), dtype=np.float64)
    if w.shape != edge.shape or not np.isfinite(w).all():
        raise InvalidInputError("the source footprint does not transform to finite coordinates "
                                "(is the horizon of the transform inside the image?)")
    res = float(resolution) if resolution is not None else suggest_resolution(world_from_src, width, height)
    # map grids align pixel edges to multiples of res; pixel frames align pixel centres
    half = 0.0 if y_up else 0.5 * res
    xmin, ymin = w.min(axis=0) + half
    xmax, ymax = w.max(axis=0) + half
    eps = 1e-9
    x0 = math.floor(xmin / res + eps) * res
    y0 = math.floor(ymin / res + eps) * res
    x1 = math.ceil(xmax / res - eps) * res
    y1 = math.ceil(ymax / res - eps) * res
    nx = max(1, int(round((x1 - x0) / res)))
    ny = max(1, int(round((y1 - y0) / res)))
    if float(nx) * float(ny) > max_pixels:
        raise InvalidInputError(f"output grid of {nx} x {ny} = {float(nx) * float(ny):.3g} pixels at resolution "
                                f"{res:.6g} is too large: above the limit of {max_pixels:.3g} pixels (--max-pixels); "
                                "check the transform, pass a coarser --resolution or raise --max-pixels")
    logger.debug("output grid %d x %d at %g, x0 %g, y %g..%g", nx, ny, res, x0, y0, y1)
    if not y_up:
        return Grid(nx, ny, Affine(res, 0.0, x0 - half, 0.0, res, y0 - half), crs)
    return Grid(nx, ny, Affine(res, 0.0, x0, 0.0, -res, y1), crs)


def check_horizon(matrix: ArrayLike, width: int, height: int) -> None:
    """Refuse a projective transform whose horizon crosses the source frame.

    The horizon is the line where the denominator ``h31 x + h32 y + h33`` of the (3, 3) matrix
    (source pixels -> world) is 0; the image on its far side maps to the other end of the plane, so
    no finite output grid covers the frame. The denominator is evaluated at the outer corners of the
    frame (pixel edges): it must keep one sign and stay away from 0.

    Raises
    ------
    InvalidInputError
        Naming the corners on each side and the denominators.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all():
        return
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    den = corners @ m[2, :2] + m[2, 2]
    scale = np.abs(corners @ np.abs(m[2, :2])) + abs(m[2, 2])
    tiny = np.abs(den) <= 1e-9 * np.maximum(scale, 1e-300)
    if (den > 0).all() or (den < 0).all():
        if not tiny.any():
            return
    raise InvalidInputError(
        f"the horizon of the transform crosses the source frame ({width} x {height} px): the projective "
        f"denominator at the corners (0,0), ({width},0), ({width},{height}), (0,{height}) is "
        f"{', '.join(f'{d:.3g}' for d in den)}, it changes sign inside the image; the part beyond the horizon "
        "has no place on the map (crop the sky away or check the GCPs)")


def crs_label(crs: str | None) -> str:
    """A short CRS name for messages: ``EPSG:n``, else the PROJ string."""
    if not crs:
        return "none"
    if crs.startswith("EPSG:"):
        return crs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return parse_crs(crs).to_proj4() or crs[:60]
        except Exception:  # noqa: BLE001 - a label only
            return crs[:60]
