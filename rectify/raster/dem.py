"""Heights: DEM sampling by windows and the vertical datum (ellipsoid vs geoid).

RPC models take heights above the WGS 84 ellipsoid; most DEMs give heights
above a geoid (EGM96, EGM2008). ``h = H + N`` with N the geoid undulation.
:class:`Dem` samples a DEM bilinearly at points given in any CRS (pixel
centres at integers, rasterio's half-pixel shift applied through
:mod:`rectify.raster.georef`), reading only the window around the points, and adds
the undulation once, from one source, stated in :attr:`Dem.datum`:

- a constant (``undulation=``, ``--undulation``);
- a geoid model (``geoid="EPSG:5773"`` for EGM96, ``"EPSG:3855"`` for EGM2008, ``--geoid``), through
  :func:`rectify.geometry.crs.geoid_height`, which needs the PROJ grid installed and says so clearly
  when it is not (PROJ downloads nothing);
- else the vertical CRS the DEM's own CRS declares (a compound CRS such as ``EPSG:4326+3855``),
  converted the same way (refused with a one-line message naming the datum and ``--undulation``
  when its grid is missing); a DEM declaring ellipsoidal heights (``EPSG:4979``) and a DEM declaring
  nothing are used as they are.

:func:`ground_on_dem` finds where image pixels' lines of sight meet the DEM (any sensor model).

A constant height instead of a DEM file (``rectify ortho --dem-height H``): :meth:`Dem.constant_height`
makes a :class:`Dem` that is ``H`` everywhere, in the model's heights (ellipsoidal for an RPC, the
exterior orientation's for a frame camera; no datum conversion), with no file behind it
(:attr:`Dem.constant` is set; ``path`` is a label).

Speed: the decimated read of a DEM (:meth:`Dem.overview`, used for its height range and the coverage
estimate) is made once per file version and kept (a small cache keyed by path, modification time,
size and band); :meth:`Dem.heights_on_lattice` samples a north-up DEM on the rows and columns of a
north-up output grid separably (one interpolation along x per DEM row, then one along y), with the
same arithmetic, in the same order, as :func:`bilinear`, so the heights are bit-identical.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from numpy.typing import ArrayLike, NDArray
from rasterio.errors import RasterioError
from rasterio.windows import Window

from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.geometry.crs import (
    VerticalDatum,
    geoid_height,
    horizontal_crs,
    same_crs,
    transform_xy,
    vertical_datum,
)
from rectify.raster.georef import pixel_from_world
from rectify.raster.io import raster_info, read_overview

__all__ = ["Dem", "geoid_undulation", "bilinear", "ground_on_dem"]

logger = logging.getLogger(__name__)


def _vertical_code(geoid: str) -> str:
    """``"5773"`` -> ``"EPSG:5773"``; any other CRS text as given."""
    g = str(geoid).strip()
    return f"EPSG:{g}" if g.isdigit() else g


def geoid_undulation(lonlat: ArrayLike, geoid: str = "EPSG:5773") -> NDArray[np.float64]:
    """Geoid undulation N (m) at WGS 84 (lon, lat) points, from pyproj's geoid grids (h = H + N).

    Raises
    ------
    CRSError
        When the geoid grid is not installed; the message names it and says to pass a constant
        undulation instead (:func:`rectify.geometry.crs.geoid_height`).
    """
    return geoid_height(_vertical_code(geoid), lonlat)


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
        The DEM's horizontal CRS (required; a compound CRS's vertical part is in ``declared``).
    transform : affine.Affine
    width, height : int
    undulation : float
        Constant added to every height (geoid undulation N, m): ``h = H + N``.
    geoid : str or None
        A vertical CRS (``"EPSG:5773"``, or the one the DEM declares) whose undulation pyproj adds
        point by point (needs the grid; see :func:`rectify.geometry.crs.geoid_height`).
    band : int
        1-based band.
    declared : VerticalDatum or None
        The heights the DEM's CRS declares (None: a 2D CRS).
    datum : str
        One line saying which heights the file holds and how they were converted.
    constant : float or None
        A constant height (m, the model's heights) instead of a file (:meth:`constant_height`); then
        ``path`` is a label, not a file.
    count : int or None
        Bands of the file (:meth:`from_path`; None: not known).
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
    declared: VerticalDatum | None = None
    datum: str = "DEM heights used as they are"
    constant: float | None = None
    count: int | None = None

    @classmethod
    def constant_height(cls, height: float, crs: str) -> Dem:
        """A DEM that is ``height`` (m) everywhere, in the model's heights; ``crs`` its horizontal CRS.

        Raises
        ------
        InvalidInputError
            A height that is not a finite number.
        """
        if isinstance(height, bool) or not isinstance(height, (int, float, np.floating, np.integer)) \
                or not math.isfinite(float(height)):
            raise InvalidInputError(f"--dem-height must be a finite number of metres; got {height!r}")
        h = float(height)
        return cls(f"constant height {h:g} m", horizontal_crs(crs), Affine.identity(), 1, 1, None,
                   datum=f"constant height {h:g} m (--dem-height), in the model's heights", constant=h)

    @property
    def is_constant(self) -> bool:
        """True for a constant height (no file)."""
        return self.constant is not None

    @classmethod
    def from_path(cls, path: str | Path, *, undulation: float | None = None, geoid: str | None = None,
                  band: int = 1, convert_declared: bool = True) -> Dem:
        """Open a DEM (only its header is read) and settle its vertical datum (module docstring).

        Parameters
        ----------
        undulation : float, optional
            A constant geoid undulation N (m) added to the file's heights.
        geoid : str, optional
            The geoid (vertical CRS) of the file's heights; pyproj adds its undulation.
        convert_declared : bool
            Convert heights above a vertical CRS the DEM declares to ellipsoidal heights (what an
            RPC needs); False keeps them (a frame camera whose exterior orientation has the DEM's heights).

        Raises
        ------
        RasterIOError
            Missing or unreadable file.
        CRSError
            The DEM has no CRS; the geoid grid (given or declared) is not installed (the message names
            the datum and ``--undulation``).
        InvalidInputError
            Bad band, a non-finite undulation, both ``undulation`` and ``geoid``, or either of them for a
            DEM that declares ellipsoidal heights.
        """

        info = raster_info(path)
        name = str(path)
        if info.crs is None:
            raise CRSError(f"DEM {name!r} has no CRS; a DEM must be georeferenced")
        if not (1 <= band <= info.count):
            raise InvalidInputError(f"DEM band {band} out of range 1..{info.count} in {name!r}")
        if undulation is not None and not math.isfinite(undulation):
            raise InvalidInputError(f"undulation must be finite; got {undulation!r}")
        if undulation is not None and geoid is not None:
            raise InvalidInputError(f"give a constant undulation ({undulation!r} m) or a geoid ({geoid!r}), not both")
        declared = vertical_datum(info.crs)
        if declared is not None and declared.ellipsoidal and (undulation is not None or geoid is not None):
            given = f"--undulation {undulation!r}" if undulation is not None else f"--geoid {geoid}"
            raise InvalidInputError(f"DEM {name!r} declares ellipsoidal heights in its CRS; {given} would convert "
                                    f"them a second time (leave it out)")
        note = "" if declared is None or declared.ellipsoidal else f"; its CRS declares {declared.label}"
        n_const, vcrs = 0.0, None
        if geoid is not None:
            vcrs = _vertical_code(geoid)
            label = (vertical_datum(vcrs) or VerticalDatum(False, vcrs)).label
            datum = f"DEM heights above {label} (--geoid) + the geoid undulation from PROJ{note}"
        elif undulation is not None:
            n_const = float(undulation)
            datum = f"DEM heights + {n_const:g} m undulation (--undulation){note}"
        elif declared is not None and declared.ellipsoidal:
            datum = "DEM heights ellipsoidal (declared by its CRS), used as they are"
        elif declared is not None and convert_declared:
            vcrs = declared.crs
            datum = f"DEM heights above {declared.label} (declared by its CRS) + the geoid undulation from PROJ"
        elif declared is not None:
            datum = f"DEM heights above {declared.label} (declared by its CRS), used as they are"
        else:
            datum = "DEM heights used as they are (its CRS declares no vertical datum)"
        dem = cls(name, horizontal_crs(info.crs), info.transform, info.width, info.height, info.nodata, n_const,
                  vcrs, band, declared, datum, count=info.count)
        if vcrs is not None:  # fail early, with the clear message
            try:
                dem.offset(dem._lonlat_lattice(1))
            except CRSError as err:
                raise CRSError(f"DEM {name!r}: {err}") from err
        return dem

    def _lonlat_lattice(self, n: int) -> NDArray[np.float64]:
        """WGS 84 lon/lat of an n x n lattice of DEM pixel centres (the corners and centre for n = 3)."""
        t: Any = self.transform
        k = np.linspace(0.0, 1.0, n) if n > 1 else np.array([0.5])
        cc, rr = np.meshgrid(k * (self.width - 1), k * (self.height - 1))
        px = np.column_stack([cc.ravel(), rr.ravel()]) + 0.5
        xy = np.column_stack([t.c + t.a * px[:, 0] + t.b * px[:, 1], t.f + t.d * px[:, 0] + t.e * px[:, 1]])
        return xy if same_crs(self.crs, "EPSG:4326") else transform_xy(self.crs, "EPSG:4326", xy)

    def offset(self, lonlat: ArrayLike) -> NDArray[np.float64]:
        """What is added to the file's heights at WGS 84 (lon, lat) points (M, 2): undulation + geoid N, m."""
        p = np.asarray(lonlat, dtype=np.float64).reshape(-1, 2)
        n = np.full(len(p), self.undulation)
        if self.geoid is not None and len(p):
            n += geoid_height(self.geoid, p)
        return n

    def offset_range(self) -> tuple[float, float]:
        """(min, max) of :meth:`offset` over the DEM (a 5 x 5 lattice when a geoid varies it)."""
        if self.geoid is None:
            return self.undulation, self.undulation
        n = self.offset(self._lonlat_lattice(5))
        return float(n.min()), float(n.max())

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
        """File heights (before any datum conversion) at DEM pixel positions (any shape), NaN outside/nodata.

        Reads only the window covering the points. A constant height: that height at every finite point.
        """

        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.constant is not None:
            return np.where(np.isfinite(x) & np.isfinite(y), self.constant, np.nan)
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
        data, valid = self._read_window(c0, r0, c1, r1)
        valid &= np.isfinite(data)
        out[fin] = bilinear(data, None if valid.all() else valid, x[fin] - c0, y[fin] - r0)
        return out

    def _read_window(self, c0: int, r0: int, c1: int, r1: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """File heights (float64) and the validity mask of DEM columns c0..c1-1, rows r0..r1-1.

        A one-band DEM of at most 512 px a side is its own :meth:`overview` (read once per file version,
        for :meth:`range`): the window is cut from it (the same values and mask: the dataset mask of one
        band is its mask), with no dataset opened on this thread.
        """
        if self.count == 1 and max(self.width, self.height) <= 512:
            data, valid, scale = self.overview(512)
            if scale == 1.0 and data.shape[:2] == (self.height, self.width):
                return data[r0:r1, c0:c1, 0].astype(np.float64), valid[r0:r1, c0:c1].copy()
        try:
            ds = self._ds()
            win = Window(c0, r0, c1 - c0, r1 - r0)
            data = ds.read(self.band, window=win, masked=False).astype(np.float64)
            valid = ds.read_masks(self.band, window=win) > 0
        except RasterioError as err:
            raise RasterIOError(f"cannot read DEM {self.path!r}: {err}") from err
        return data, valid

    def heights_on_lattice(self, x: NDArray, y: NDArray) -> NDArray[np.float64] | None:
        """File heights on the lattice of DEM pixel columns ``x`` (w,) and rows ``y`` (h,): (h, w).

        The separable form of :meth:`heights_at_dem_pixels` for a north-up output grid over a north-up
        DEM (module docstring): bit-identical values. None when the DEM window holds invalid cells
        (the caller then samples point by point) or nothing is inside.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.constant is not None:
            return np.where(np.isfinite(y)[:, None] & np.isfinite(x)[None, :], self.constant, np.nan)
        if not (np.isfinite(x).all() and np.isfinite(y).all()) or not len(x) or not len(y):
            return None
        c0 = max(int(math.floor(x.min())), 0)
        r0 = max(int(math.floor(y.min())), 0)
        c1 = min(int(math.floor(x.max())) + 2, self.width)
        r1 = min(int(math.floor(y.max())) + 2, self.height)
        if c1 <= c0 or r1 <= r0:
            return None
        data, valid = self._read_window(c0, r0, c1, r1)
        if not (valid.all() and np.isfinite(data).all()):
            return None
        h, w = data.shape
        xs, ys = x - c0, y - r0
        x0, y0 = np.floor(xs), np.floor(ys)
        fx, fy = xs - x0, ys - y0
        okx = (x0 >= 0) & (x0 <= w - 1)
        oky = (y0 >= 0) & (y0 <= h - 1)
        xi = np.where(okx, x0, 0).astype(np.intp)
        yi = np.where(oky, y0, 0).astype(np.intp)
        xi1 = np.minimum(xi + 1, w - 1)
        yi1 = np.minimum(yi + 1, h - 1)
        # the rows bilinear() combines, interpolated along x once per DEM row: (v0 (1 - fx) + v1 fx)
        ax = data[:, xi] * (1 - fx) + data[:, xi1] * fx
        out = ax[yi] * (1 - fy)[:, None] + ax[yi1] * fy[:, None]
        out[~(oky[:, None] & okx[None, :])] = np.nan
        return out

    def overview(self, max_size: int = 512) -> tuple[NDArray, NDArray[np.bool_], float]:
        """:func:`rectify.raster.io.read_overview` of the DEM's band, read once per file version (cached).

        The arrays are shared: read-only.
        """
        if self.constant is not None:
            raise InvalidInputError("a constant height has no overview")
        try:
            st = os.stat(self.path)
        except OSError as err:
            raise RasterIOError(f"cannot read DEM {self.path!r}: {err}") from err
        return _overview(os.path.abspath(self.path), st.st_mtime_ns, st.st_size, self.band, int(max_size))

    def sample(self, xy: ArrayLike, crs: str | None = None) -> NDArray[np.float64]:
        """Converted heights (file height + :meth:`offset`) at (N, 2) points in ``crs`` (default the DEM's)."""

        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.constant is not None:
            return np.where(np.isfinite(p).all(axis=1), self.constant, np.nan)
        if crs is not None and not same_crs(crs, self.crs):
            q = transform_xy(crs, self.crs, p)
        else:
            q = p
        px = pixel_from_world(self.transform, q)
        h = self.heights_at_dem_pixels(px[:, 0], px[:, 1]) + self.undulation
        if self.geoid is not None:
            ll = p if (crs is not None and same_crs(crs, "EPSG:4326")) else transform_xy(self.crs, "EPSG:4326", q)
            h = h + geoid_height(self.geoid, ll)
        return h

    def lonlat_function(self):
        """A callable (M, 2) WGS 84 lon/lat -> (M,) converted heights (for RPC localisation)."""
        return lambda lonlat: self.sample(lonlat, "EPSG:4326")

    def range(self) -> tuple[float, float]:
        """(min, max) converted heights, from a decimated read (overviews when present)."""

        if self.constant is not None:
            return self.constant, self.constant
        data, valid, _ = self.overview(512)
        d = np.asarray(data, dtype=np.float64)[..., 0]
        ok = valid & np.isfinite(d)
        if self.nodata is not None:
            ok &= d != self.nodata
        if not ok.any():
            raise InvalidInputError(f"DEM {self.path!r} has no valid heights")
        lo, hi = self.offset_range()
        return float(d[ok].min()) + lo, float(d[ok].max()) + hi


def ground_on_dem(model: Any, dem: Dem, pixels: ArrayLike, *, h_range: tuple[float, float] | None = None,
                  n_scan: int = 256, tol_m: float = 1e-4) -> NDArray[np.float64]:
    """Where image pixels' lines of sight first meet the DEM: (N, 3) ground points in ``model.crs``.

    ``model`` is any sensor model (``ground_at_height``). The line of sight is scanned from the top
    of ``h_range`` (default the DEM's converted heights, 1 m wider) down in ``n_scan`` steps, so the
    visible surface is found; the first bracket is bisected on exact ``ground_at_height`` points
    until the height is within ``tol_m``. NaN rows: the line misses the DEM.
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    lo, hi = h_range if h_range is not None else dem.range()
    lo, hi = float(lo) - 1.0, float(hi) + 1.0
    n = len(px)
    out = np.full((n, 3), np.nan)
    if n == 0:
        return out

    def gap(h: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        g = model.ground_at_height(px, h)
        f = np.full(n, np.nan)
        ok = np.isfinite(g).all(axis=1)
        if ok.any():
            f[ok] = h[ok] - dem.sample(g[ok, :2], model.crs)
        return f, g

    a = np.full(n, np.nan)  # bracket: above the surface at a, below at b
    b = np.full(n, np.nan)
    prev_h = np.full(n, np.nan)
    prev_f = np.full(n, np.nan)
    for h0 in np.linspace(hi, lo, n_scan + 1):
        todo = np.isnan(b)
        if not todo.any():
            break
        h = np.full(n, h0)
        f, _ = gap(h)
        hit = todo & (f <= 0) & (prev_f > 0)
        a[hit], b[hit] = prev_h[hit], h0
        upd = todo & np.isfinite(f)
        prev_h[upd], prev_f[upd] = h0, f[upd]
    found = np.isfinite(b)
    if not found.any():
        return out
    for _ in range(64):
        mid = np.where(found, 0.5 * (a + b), lo)
        f, _ = gap(mid)
        above = f > 0
        a = np.where(found & above, mid, a)
        b = np.where(found & ~above, mid, b)
        if np.nanmax(np.where(found, a - b, 0.0)) < tol_m:
            break
    h = np.where(found, 0.5 * (a + b), lo)
    _, g = gap(h)
    out[found] = g[found]
    return out


@functools.lru_cache(maxsize=8)
def _overview(path: str, mtime_ns: int, size: int, band: int, max_size: int
              ) -> tuple[NDArray, NDArray[np.bool_], float]:
    """The decimated read of one version of a DEM file (``mtime_ns`` and ``size`` name the version)."""
    data, valid, scale = read_overview(path, max_size, bands=[band])
    data.setflags(write=False)
    valid.setflags(write=False)
    return data, valid, scale


_LOCAL = threading.local()
