"""Heights: DEM sampling by windows and the vertical datum (ellipsoid vs geoid).

RPC models take heights above the WGS 84 ellipsoid; most DEMs give heights
above a geoid (EGM96, EGM2008). ``h = H + N`` with N the geoid undulation.
:class:`Dem` samples a DEM bilinearly at points given in any CRS (pixel
centres at integers, rasterio's half-pixel shift applied through
:mod:`rectify.raster.georef`), reading only the window around the points, and adds
the undulation: a constant (``undulation=``) or pyproj's geoid model
(``geoid="EPSG:5773"`` for EGM96, ``"EPSG:3855"`` for EGM2008), which needs the
PROJ grid installed; :func:`geoid_undulation` says so clearly when it is not.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from numpy.typing import ArrayLike, NDArray
from rasterio.errors import RasterioError
from rasterio.windows import Window

from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.geometry.crs import same_crs, transform_xy, transform_xyz
from rectify.raster.georef import pixel_from_world
from rectify.raster.io import raster_info, read_overview

__all__ = ["Dem", "geoid_undulation", "bilinear"]

logger = logging.getLogger(__name__)


def geoid_undulation(lonlat: ArrayLike, geoid: str = "EPSG:5773") -> NDArray[np.float64]:
    """Geoid undulation N (m) at WGS 84 (lon, lat) points, from pyproj's geoid grids.

    Raises
    ------
    CRSError
        When the geoid grid is not installed (PROJ returns the height
        unchanged); the message says to pass a constant undulation instead.
    """

    p = np.asarray(lonlat, dtype=np.float64).reshape(-1, 2)
    src = f"EPSG:4326+{geoid.split(':')[-1]}"
    xyz = np.column_stack([p, np.zeros(len(p))])
    try:
        out = transform_xyz(src, "EPSG:4979", xyz)
    except CRSError as err:
        raise CRSError(f"geoid {geoid!r} is not available to PROJ ({err}); install its grid or pass a constant "
                       f"undulation (e.g. --undulation 32.5)") from err
    n = out[:, 2]
    if len(n) and np.all(n == 0.0):
        raise CRSError(f"geoid grid for {geoid!r} is not installed (PROJ returned heights unchanged); install it "
                       f"(projsync) or pass a constant undulation instead")
    return n


def bilinear(data: NDArray, valid: NDArray[np.bool_] | None, x: NDArray, y: NDArray) -> NDArray[np.float64]:
    """Bilinear samples of a 2-D array at (x = col, y = row), pixel centres at integers.

    NaN where a neighbour is outside the array or invalid.
    """
    h, w = data.shape
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx, fy = x - x0, y - y0
    ok = np.isfinite(x) & np.isfinite(y) & (x0 >= 0) & (y0 >= 0) & (x0 <= w - 1) & (y0 <= h - 1)
    xi = np.where(ok, x0, 0).astype(np.intp)
    yi = np.where(ok, y0, 0).astype(np.intp)
    xi1 = np.minimum(xi + 1, w - 1)
    yi1 = np.minimum(yi + 1, h - 1)
    # exactly on the last row/column: weight 0 on the (clamped) neighbour
    d = data.astype(np.float64, copy=False)
    v00, v01, v10, v11 = d[yi, xi], d[yi, xi1], d[yi1, xi], d[yi1, xi1]
    if valid is not None:
        ok &= valid[yi, xi] & (valid[yi, xi1] | (fx == 0)) & (valid[yi1, xi] | (fy == 0)) \
            & (valid[yi1, xi1] | (fx == 0) | (fy == 0))
    out = (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy
    out[~ok] = np.nan
    return out


@dataclass(frozen=True, eq=False)
class Dem:
    """A DEM raster (any CRS, any resolution) sampled bilinearly, by windows.

    Attributes
    ----------
    path : str
    crs : str
        The DEM's CRS (required).
    transform : affine.Affine
    width, height : int
    undulation : float
        Constant added to every height (geoid undulation N, m): ``h = H + N``.
    geoid : str or None
        A geoid vertical CRS (``"EPSG:5773"``) whose undulation pyproj adds
        point by point (needs the grid; see :func:`geoid_undulation`).
    band : int
        1-based band.
    """

    path: str
    crs: str
    transform: object
    width: int
    height: int
    nodata: float | None
    undulation: float = 0.0
    geoid: str | None = None
    band: int = 1

    @classmethod
    def from_path(cls, path: str | Path, *, undulation: float = 0.0, geoid: str | None = None,
                  band: int = 1) -> Dem:
        """Open a DEM (only its header is read).

        Raises
        ------
        RasterIOError
            Missing or unreadable file.
        CRSError
            The DEM has no CRS.
        InvalidInputError
            Bad band or a non-finite undulation.
        """

        info = raster_info(path)
        if info.crs is None:
            raise CRSError(f"DEM {str(path)!r} has no CRS; a DEM must be georeferenced")
        if not (1 <= band <= info.count):
            raise InvalidInputError(f"DEM band {band} out of range 1..{info.count} in {str(path)!r}")
        if not math.isfinite(undulation):
            raise InvalidInputError(f"undulation must be finite; got {undulation!r}")
        if geoid is not None:
            geoid_undulation([[0.0, 0.0]], geoid)  # fail early, with the clear message
        return cls(str(path), info.crs, info.transform, info.width, info.height, info.nodata, float(undulation),
                   geoid, band)

    # one open dataset per thread
    def _ds(self):
        local = _LOCAL.__dict__.setdefault("dems", {})
        try:
            key = (self.path, os.stat(self.path).st_mtime_ns)
        except OSError as err:
            raise RasterIOError(f"cannot read DEM {self.path!r}: {err}") from err
        ds = local.get(key)
        if ds is None or ds.closed:
            try:
                ds = rasterio.open(self.path)
            except RasterioError as err:
                raise RasterIOError(f"cannot read DEM {self.path!r}: {err}") from err
            local[key] = ds
        return ds

    def heights_at_dem_pixels(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Orthometric (file) heights at DEM pixel positions (any shape), NaN outside/nodata.

        Reads only the window covering the points.
        """

        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        out = np.full(x.shape, np.nan)
        fin = np.isfinite(x) & np.isfinite(y)
        if not fin.any():
            return out
        c0 = max(int(math.floor(np.min(x[fin]))), 0)
        r0 = max(int(math.floor(np.min(y[fin]))), 0)
        c1 = min(int(math.floor(np.max(x[fin]))) + 2, self.width)
        r1 = min(int(math.floor(np.max(y[fin]))) + 2, self.height)
        if c1 <= c0 or r1 <= r0:
            return out
        try:
            ds = self._ds()
            win = Window(c0, r0, c1 - c0, r1 - r0)
            data = ds.read(self.band, window=win, masked=False).astype(np.float64)
            valid = ds.read_masks(self.band, window=win) > 0
        except RasterioError as err:
            raise RasterIOError(f"cannot read DEM {self.path!r}: {err}") from err
        valid &= np.isfinite(data)
        out[fin] = bilinear(data, None if valid.all() else valid, x[fin] - c0, y[fin] - r0)
        return out

    def sample(self, xy: ArrayLike, crs: str | None = None) -> NDArray[np.float64]:
        """Ellipsoidal heights (file height + undulation) at (N, 2) points in ``crs`` (default the DEM's)."""

        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if crs is not None and not same_crs(crs, self.crs):
            q = transform_xy(crs, self.crs, p)
        else:
            q = p
        px = pixel_from_world(self.transform, q)
        h = self.heights_at_dem_pixels(px[:, 0], px[:, 1]) + self.undulation
        if self.geoid is not None:
            ll = p if (crs is not None and same_crs(crs, "EPSG:4326")) else transform_xy(self.crs, "EPSG:4326", q)
            h = h + geoid_undulation(ll, self.geoid)
        return h

    def lonlat_function(self):
        """A callable (M, 2) WGS 84 lon/lat -> (M,) ellipsoidal heights (for RPC localisation)."""
        return lambda lonlat: self.sample(lonlat, "EPSG:4326")

    def range(self) -> tuple[float, float]:
        """(min, max) file heights + undulation, from a decimated read (overviews when present)."""

        data, valid, _ = read_overview(self.path, 512, bands=[self.band])
        d = np.asarray(data, dtype=np.float64)[..., 0]
        ok = valid & np.isfinite(d)
        if self.nodata is not None:
            ok &= d != self.nodata
        if not ok.any():
            raise InvalidInputError(f"DEM {self.path!r} has no valid heights")
        return float(d[ok].min()) + self.undulation, float(d[ok].max()) + self.undulation


_LOCAL = threading.local()
