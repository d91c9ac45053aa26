"""CRS handling: the one door to pyproj.

Every coordinate transformation in the project goes through
:func:`get_transformer`, which returns a cached
``Transformer.from_crs(src, dst, always_xy=True)``, and every call uses
``errcheck=True`` (:func:`transform_xy`, :func:`transform_xyz`), so a failed
transformation raises instead of returning ``inf``. CRSs are stored as
``"EPSG:nnnn"`` when they have a code, WKT2 otherwise (:func:`crs_to_string`).
Axis order is always (x, y) = (easting, northing) or (lon, lat).

Heights: :func:`vertical_datum` says what a CRS declares about its heights (nothing, ellipsoidal
heights, or heights above a vertical datum such as EGM2008), :func:`horizontal_crs` strips the
vertical part, and :func:`geoid_height` gives the geoid undulation N (h = H + N) of a vertical CRS
from PROJ's grids, refusing when the grid is not installed (no download at run time: PROJ's network
access stays off).
"""

from __future__ import annotations

import functools
import logging
import os
import warnings
from dataclasses import dataclass

import numpy as np
import pyproj
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer
from pyproj.crs import CompoundCRS
from pyproj.exceptions import CRSError as ProjCRSError
from pyproj.exceptions import ProjError
from pyproj.transformer import TransformerGroup

from rectify.errors import CRSError
from rectify.geometry.points import as_points

__all__ = ["unit_label", "parse_crs", "crs_to_string", "get_transformer", "transform_xy", "transform_xyz",
           "transform_arrays", "geographic3d_wkt", "geocentric_wkt", "same_crs", "is_geographic", "check_area_of_use",
           "VerticalDatum", "vertical_datum", "horizontal_crs", "geoid_height", "grid_undulation", "utm_crs"]

logger = logging.getLogger(__name__)


@functools.lru_cache(maxsize=128)
def _parse(text: str):

    try:
        return pyproj.CRS.from_user_input(text)
    except ProjCRSError as err:
        raise CRSError(f"unknown CRS {text!r}: {err}") from err


def parse_crs(crs) -> pyproj.CRS:
    """Parse ``"EPSG:nnnn"``, WKT, a ``pyproj.CRS`` or a ``rasterio.crs.CRS``.

    Raises
    ------
    CRSError
        If the CRS is missing, empty or unknown to PROJ; the message names it.

    Examples
    --------
    >>> parse_crs("EPSG:32618").to_epsg()
    32618
    >>> parse_crs("EPSG:99999999")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    rectify.errors.CRSError: unknown CRS 'EPSG:99999999': ...
    """

    if crs is None:
        raise CRSError("CRS is missing (None)")
    if isinstance(crs, pyproj.CRS):
        return crs
    if hasattr(crs, "to_wkt") and not isinstance(crs, str):  # rasterio CRS
        crs = crs.to_wkt()
    if not isinstance(crs, str) or not crs.strip():
        raise CRSError(f"CRS must be a non-empty string like 'EPSG:32618' or WKT; got {crs!r}")
    return _parse(crs.strip())


def crs_to_string(crs) -> str:
    """``"EPSG:nnnn"`` when the CRS matches a code exactly, WKT2 otherwise."""
    if isinstance(crs, str):  # the EPSG lookup searches PROJ's database (~0.1 s for a custom CRS): once per text
        return _crs_to_string_text(crs)
    return _crs_to_string_text(parse_crs(crs).to_wkt())


@functools.lru_cache(maxsize=128)
def _crs_to_string_text(text: str) -> str:
    c = parse_crs(text)
    epsg = c.to_epsg(min_confidence=100)
    return f"EPSG:{epsg}" if epsg else c.to_wkt()


def utm_crs(lon: float, lat: float) -> str:
    """``"EPSG:326zz"`` (north) or ``"EPSG:327zz"`` (south): the WGS 84 UTM zone of a point (degrees)."""
    zone = int(np.floor((float(lon) + 180.0) / 6.0)) % 60 + 1
    return f"EPSG:{(32600 if float(lat) >= 0 else 32700) + zone}"


def same_crs(a, b) -> bool:
    """True when two CRSs describe the same system."""
    return parse_crs(a).equals(parse_crs(b), ignore_axis_order=True)


def is_geographic(crs) -> bool:
    """True for longitude/latitude CRSs (degrees)."""
    return bool(parse_crs(crs).is_geographic)


@functools.lru_cache(maxsize=64)
def _transformer(src_key: str, dst_key: str):

    try:
        return Transformer.from_crs(_parse(src_key), _parse(dst_key), always_xy=True)
    except ProjError as err:
        raise CRSError(f"no transformation from {src_key!r} to {dst_key!r}: {err}") from err


def get_transformer(src, dst) -> pyproj.Transformer:
    """Cached ``Transformer.from_crs(src, dst, always_xy=True)``.

    Parameters
    ----------
    src, dst : str or CRS
        ``"EPSG:nnnn"``, WKT or a CRS object.

    Raises
    ------
    CRSError
        If a CRS is unknown or no transformation exists.
    """
    return _transformer(parse_crs(src).to_wkt(), parse_crs(dst).to_wkt())


def transform_xy(src, dst, xy: ArrayLike) -> NDArray[np.float64]:
    """Transform (N, 2) points (x, y) from ``src`` to ``dst`` (always_xy, errcheck).

    Parameters
    ----------
    xy : (N, 2) float64
        Easting/northing or lon/lat (degrees), in that order.

    Returns
    -------
    (N, 2) float64, a new array.

    Raises
    ------
    CRSError
        If a point cannot be transformed (the message names the first one).
    """


    p = as_points(xy, "xy", 2)
    if len(p) == 0:
        return p
    t = get_transformer(src, dst)
    try:
        x, y = t.transform(p[:, 0], p[:, 1], errcheck=True)
    except ProjError as err:
        raise CRSError(f"cannot transform points from {crs_to_string(src)!r} to {crs_to_string(dst)!r} "
                       f"(first point {p[0].tolist()}): {err}") from err
    out = np.column_stack([np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)])
    if not np.isfinite(out).all():
        i = int(np.flatnonzero(~np.isfinite(out).all(axis=1))[0])
        raise CRSError(f"point {p[i].tolist()} cannot be transformed from {crs_to_string(src)!r} "
                       f"to {crs_to_string(dst)!r}")
    return out


def transform_xyz(src, dst, xyz: ArrayLike) -> NDArray[np.float64]:
    """Transform (N, 3) points (x, y, z) from ``src`` to ``dst`` (always_xy, errcheck).

    Returns
    -------
    (N, 3) float64, a new array.
    """


    p = as_points(xyz, "xyz", 3)
    if len(p) == 0:
        return p
    t = get_transformer(src, dst)
    try:
        x, y, z = t.transform(p[:, 0], p[:, 1], p[:, 2], errcheck=True)
    except ProjError as err:
        raise CRSError(f"cannot transform points from {crs_to_string(src)!r} to {crs_to_string(dst)!r} "
                       f"(first point {p[0].tolist()}): {err}") from err
    out = np.column_stack([np.asarray(v, dtype=np.float64) for v in (x, y, z)])
    if not np.isfinite(out).all():
        i = int(np.flatnonzero(~np.isfinite(out).all(axis=1))[0])
        raise CRSError(f"point {p[i].tolist()} cannot be transformed from {crs_to_string(src)!r} "
                       f"to {crs_to_string(dst)!r}")
    return out


def transform_arrays(src, dst, x: ArrayLike, y: ArrayLike, *, failure: str
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``x``, ``y`` (same shape) from ``src`` to ``dst`` through :func:`get_transformer` (errcheck).

    No finiteness test (see :func:`transform_xy` for that).

    Raises
    ------
    CRSError
        ``"<failure>: <PROJ's message>"`` when PROJ fails on a point; as :func:`get_transformer`.
    """
    t = get_transformer(src, dst)
    try:
        u, v = t.transform(x, y, errcheck=True)
    except ProjError as err:
        raise CRSError(f"{failure}: {err}") from err
    return np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)


_CARTESIAN = {"subtype": "Cartesian", "axis": [
    {"name": "Geocentric X", "abbreviation": "X", "direction": "geocentricX", "unit": "metre"},
    {"name": "Geocentric Y", "abbreviation": "Y", "direction": "geocentricY", "unit": "metre"},
    {"name": "Geocentric Z", "abbreviation": "Z", "direction": "geocentricZ", "unit": "metre"}]}


def _geodetic(wkt: str) -> pyproj.CRS:
    """The geodetic CRS of the CRS ``wkt``; :class:`CRSError` when it has no geodetic datum."""
    c = parse_crs(wkt)
    g = c.geodetic_crs
    if g is None:
        raise CRSError(f"CRS {c.name!r} has no geodetic datum")
    return g


@functools.lru_cache(maxsize=32)
def geographic3d_wkt(wkt: str) -> str:
    """WKT of the 3D geographic CRS (lon, lat, h) on the datum of the CRS ``wkt`` (cached)."""
    return _geodetic(wkt).to_3d().to_wkt()


@functools.lru_cache(maxsize=32)
def geocentric_wkt(wkt: str) -> str:
    """WKT of the geocentric (ECEF, X Y Z metres) CRS on the datum of the CRS ``wkt`` (cached)."""
    g = _geodetic(wkt)
    if g.is_geocentric:
        return g.to_wkt()
    d = g.to_json_dict()
    d.pop("id", None)
    d["type"] = "GeodeticCRS"
    d["name"] = f"{d.get('name', 'unnamed')} (geocentric)"
    d["coordinate_system"] = _CARTESIAN
    return pyproj.CRS.from_json_dict(d).to_wkt()


def unit_label(crs, *, default: str = "map units") -> str:
    """Short name of a CRS's first-axis unit, for labels: ``"m"`` for metres,
    the CRS's own unit name otherwise (``"degree"``, ``"us survey foot"``), and
    ``default`` when ``crs`` is None or unreadable (the unit is only a label)."""
    if not crs:
        return default
    try:
        axes = parse_crs(crs).axis_info
    except CRSError:
        return default
    name = (axes[0].unit_name or "").lower() if axes else ""
    if name in ("metre", "meter", "m"):
        return "m"
    return name or default


def check_area_of_use(crs, xy: ArrayLike, ids=None, *, margin_deg: float = 10.0) -> None:
    """Refuse coordinates that cannot be in ``crs``.

    A geographic CRS takes longitudes within +-360 and latitudes within +-90 degrees (projected
    metres labelled EPSG:4326 are caught here). A projected CRS takes points that transform to
    longitude/latitude within ``margin_deg`` of its area of use (pyproj's ``CRS.area_of_use``).
    Rows with NaN are skipped.

    Raises
    ------
    CRSError
        Naming the first offending point (its id when ``ids`` is given), its coordinates, the CRS
        and its area of use.
    """
    c = parse_crs(crs)
    p = as_points(xy, "xy", 2)
    names = [str(i) for i in ids] if ids is not None else [f"#{k + 1}" for k in range(len(p))]
    keep: NDArray[np.bool_] = np.asarray(np.isfinite(p).all(axis=1), dtype=bool)
    names = [names[i] for i in np.flatnonzero(keep)]
    p = p[keep]
    if len(p) == 0:
        return
    label = crs_to_string(c) if c.to_epsg(min_confidence=100) else (c.name or "the CRS")
    if c.is_geographic:
        bad = (np.abs(p[:, 0]) > 360.0) | (np.abs(p[:, 1]) > 90.0)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CRSError(f"point {names[i]} ({p[i, 0]:.10g}, {p[i, 1]:.10g}) is not a longitude/latitude in "
                           f"{label} (degrees, |lat| <= 90): are these projected coordinates (metres) labelled "
                           "with a geographic CRS?")
        lon, lat = (p[:, 0] + 180.0) % 360.0 - 180.0, p[:, 1]
    else:
        try:
            t = get_transformer(c, "EPSG:4326")
            lon, lat = (np.asarray(v, dtype=np.float64) for v in t.transform(p[:, 0], p[:, 1]))
        except (CRSError, ProjError):
            return
        bad = ~(np.isfinite(lon) & np.isfinite(lat))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CRSError(f"point {names[i]} ({p[i, 0]:.10g}, {p[i, 1]:.10g}) lies outside the domain of {label} "
                           "(it has no longitude/latitude): wrong CRS for these coordinates?")
    aou = c.area_of_use
    if aou is None:
        return
    m = float(margin_deg)
    out = (lat < aou.south - m) | (lat > aou.north + m)
    if aou.west <= aou.east and aou.east - aou.west < 360.0 - 2 * m:
        out |= (lon < aou.west - m) | (lon > aou.east + m)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise CRSError(f"point {names[i]} ({p[i, 0]:.10g}, {p[i, 1]:.10g}) lies far outside the area of use of "
                       f"{label} (lon {aou.west:g}..{aou.east:g}, lat {aou.south:g}..{aou.north:g}; the point is at "
                       f"lon {lon[i]:.4g}, lat {lat[i]:.4g}): wrong CRS for these coordinates?")


# --------------------------------------------------------------------------- heights
@dataclass(frozen=True)
class VerticalDatum:
    """What a CRS declares about its heights.

    Attributes
    ----------
    ellipsoidal : bool
        True for ellipsoidal heights (a 3D geographic or projected CRS).
    name : str
        The vertical CRS's name (``"EGM2008 height"``), or ``"ellipsoidal height"``.
    crs : str or None
        The vertical CRS (``"EPSG:3855"`` or WKT) for heights above a geoid; None when ellipsoidal.
    """

    ellipsoidal: bool
    name: str
    crs: str | None = None

    @property
    def label(self) -> str:
        """``"EGM2008 height (EPSG:3855)"``: the name, and the code when it has one."""
        if self.crs is not None and self.crs.startswith("EPSG:"):
            return f"{self.name} ({self.crs})"
        return self.name


def vertical_datum(crs) -> VerticalDatum | None:
    """The heights a CRS declares: a vertical CRS (compound ``EPSG:4326+3855``, or vertical alone),
    ellipsoidal heights (3D geographic or projected CRS, e.g. ``EPSG:4979``), or None (2D CRS)."""
    c = parse_crs(crs)
    if c.is_compound:
        for sub in c.sub_crs_list[1:]:
            if sub.is_vertical:
                return VerticalDatum(False, sub.name or "unnamed vertical CRS", crs_to_string(sub))
        return None
    if c.is_vertical:
        return VerticalDatum(False, c.name or "unnamed vertical CRS", crs_to_string(c))
    axes = c.axis_info
    if len(axes) == 3 and not c.is_geocentric and "ellipsoidal" in (axes[2].name or "").lower():
        return VerticalDatum(True, "ellipsoidal height")
    return None


def horizontal_crs(crs) -> str:
    """The horizontal part of a CRS (the first member of a compound CRS, the 2D form of a 3D one)."""
    c = parse_crs(crs)
    if c.is_compound:
        return crs_to_string(c.sub_crs_list[0])
    if len(c.axis_info) == 3 and not c.is_geocentric:
        return crs_to_string(c.to_2d())
    return crs_to_string(c)


@functools.lru_cache(maxsize=16)
def _geoid_transformer(vertical: str) -> Transformer:
    """The transformation (lon, lat, H above ``vertical``) -> (lon, lat, h on WGS 84), refused without its grid."""
    v = parse_crs(vertical)
    name = v.name or vertical
    src = CompoundCRS(f"WGS 84 + {name}", [parse_crs("EPSG:4326"), v])
    with warnings.catch_warnings():  # pyproj warns about a missing grid; the error below says it in one line
        warnings.simplefilter("ignore")
        try:
            group = TransformerGroup(src, parse_crs("EPSG:4979"), always_xy=True)
        except ProjError as err:
            raise CRSError(f"no transformation from {name!r} heights to WGS 84 ellipsoidal heights: {err}") from err
    if not group.best_available:
        grids = list(dict.fromkeys(g.short_name for op in group.unavailable_operations for g in op.grids
                                   if not g.available))
        raise CRSError(f"heights above {name!r} need the PROJ grid {' or '.join(grids) or '(unnamed)'}, which is "
                       f"not installed (PROJ downloads nothing here): install it (projsync --file NAME) or pass a "
                       f"constant undulation (--undulation N, metres)")
    usable = [t for t in group.transformers if "ballpark" not in (t.description or "").lower()]
    if not usable:
        raise CRSError(f"PROJ knows no transformation from {name!r} heights to WGS 84 ellipsoidal heights (only a "
                       f"ballpark one that leaves heights unchanged): pass a constant undulation (--undulation N, "
                       f"metres)")
    return usable[0]


def geoid_height(vertical, lonlat: ArrayLike) -> NDArray[np.float64]:
    """Geoid undulation N (m) of the vertical CRS ``vertical`` at WGS 84 (lon, lat) points: h = H + N.

    Parameters
    ----------
    vertical : str or CRS
        A vertical CRS (``"EPSG:3855"``, WKT, a bound vertical CRS naming its grid).
    lonlat : (N, 2) float64

    Raises
    ------
    CRSError
        The grid the transformation needs is not installed (named), or PROJ knows no transformation;
        the message says to pass a constant undulation instead.
    """
    v = parse_crs(vertical)
    if not v.is_vertical:
        raise CRSError(f"{crs_to_string(v)!r} is not a vertical CRS")
    p = as_points(lonlat, "lonlat", 2)
    if len(p) == 0:
        return np.zeros(0)
    t = _geoid_transformer(v.to_wkt())
    try:
        _, _, h = t.transform(p[:, 0], p[:, 1], np.zeros(len(p)), errcheck=True)
    except ProjError as err:
        raise CRSError(f"cannot convert {v.name!r} heights to ellipsoidal heights at {p[0].tolist()}: {err}") from err
    n = np.asarray(h, dtype=np.float64)
    if not np.isfinite(n).all():
        i = int(np.flatnonzero(~np.isfinite(n))[0])
        raise CRSError(f"{v.name!r}: no geoid undulation at lon/lat {p[i].tolist()} (outside the grid?)")
    return n


@functools.lru_cache(maxsize=8)
def _grid_transformer(path: str, mtime_ns: int) -> Transformer:
    """(lon, lat, 0) degrees -> (lon, lat, N): PROJ's vgridshift on the grid file ``path`` (absolute; cached
    per modification time)."""
    if '"' in path:
        raise CRSError(f"geoid grid path {path!r} contains a double quote, which PROJ cannot take")
    pipe = ("+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            f'+step +proj=vgridshift +grids="{path}" +multiplier=1 +step +proj=unitconvert +xy_in=rad +xy_out=deg')
    try:
        return Transformer.from_pipeline(pipe)
    except ProjError as err:
        raise CRSError(f"geoid grid {path!r} is not a grid PROJ can read (GeoTIFF or GTX of heights on "
                       f"longitude/latitude): {err}") from err


def grid_undulation(path, lonlat: ArrayLike) -> NDArray[np.float64]:
    """Geoid undulation or height anomaly N (m) from a user's grid file at (lon, lat) points: h = H + N.

    The grid (a PROJ vertical grid: GeoTIFF or GTX, heights of the geoid or quasi-geoid above the
    ellipsoid on a longitude/latitude grid) is read by PROJ's ``vgridshift`` with bilinear
    interpolation; nothing is downloaded.

    Parameters
    ----------
    path : str or Path
        The grid file (must exist).
    lonlat : (N, 2) float64
        Degrees, on the grid's geodetic datum.

    Raises
    ------
    CRSError
        The file is missing or not a grid PROJ reads; a point outside the grid (named).
    """
    p = os.path.abspath(os.fspath(path))
    if not os.path.isfile(p):
        raise CRSError(f"geoid grid {str(path)!r} not found")
    pts = as_points(lonlat, "lonlat", 2)
    if len(pts) == 0:
        return np.zeros(0)
    t = _grid_transformer(p, os.stat(p).st_mtime_ns)
    try:
        _, _, n = t.transform(pts[:, 0], pts[:, 1], np.zeros(len(pts)), errcheck=True)
        out = np.asarray(n, dtype=np.float64).reshape(-1)
    except ProjError:
        out = np.empty(len(pts))
        for i, (lon, lat) in enumerate(pts):  # the first point without a value is named
            try:
                out[i] = t.transform(lon, lat, 0.0, errcheck=True)[2]
            except ProjError as err:
                raise CRSError(f"geoid grid {str(path)!r} has no value at lon {lon:.6f}, lat {lat:.6f} deg "
                               f"(outside the grid?): {err}") from err
    if not np.isfinite(out).all():
        i = int(np.flatnonzero(~np.isfinite(out))[0])
        raise CRSError(f"geoid grid {str(path)!r} has no value at lon {pts[i, 0]:.6f}, lat {pts[i, 1]:.6f} deg")
    return out
