"""CRS handling: the one door to pyproj.

Every coordinate transformation in the project goes through
:func:`get_transformer`, which returns a cached
``Transformer.from_crs(src, dst, always_xy=True)``, and every call uses
``errcheck=True`` (:func:`transform_xy`, :func:`transform_xyz`), so a failed
transformation raises instead of returning ``inf``. CRSs are stored as
``"EPSG:nnnn"`` when they have a code, WKT2 otherwise (:func:`crs_to_string`).
Axis order is always (x, y) = (easting, northing) or (lon, lat).
"""

from __future__ import annotations

import functools
import logging

import numpy as np
import pyproj
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer
from pyproj.exceptions import CRSError as ProjCRSError
from pyproj.exceptions import ProjError

from rectify.errors import CRSError
from rectify.geometry.points import as_points

__all__ = ["unit_label", "parse_crs", "crs_to_string", "get_transformer", "transform_xy", "transform_xyz",
           "transform_arrays", "geographic3d_wkt", "geocentric_wkt", "same_crs", "is_geographic", "check_area_of_use"]

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
    c = parse_crs(crs)
    epsg = c.to_epsg(min_confidence=100)
    return f"EPSG:{epsg}" if epsg else c.to_wkt()


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
