"""OpenDroneMap's ``gcp_list.txt`` (GCPs with their image measurements) and ``geo.txt`` (image positions) in.

Both files start with a line naming the CRS of their coordinates, as ODM reads it: ``EPSG:<code>``,
a PROJ string (``+proj=utm +zone=10 +datum=WGS84 ...``) or ``WGS84 UTM <zone><N|S>``; the other
lines are separated by spaces or tabs, and ``#`` lines are comments.

``gcp_list.txt``
    ``geo_x geo_y geo_z im_x im_y image_name [gcp_name] [extras...]`` - one line per image
    measurement of a GCP. :func:`read_odm_gcps` -> :class:`OdmGcps`, which gives a
    :class:`rectify.geometry.points.GcpTable` per image (:meth:`OdmGcps.gcp_table`) and the block
    control (:meth:`OdmGcps.control_table`).
``geo.txt``
    ``image_name geo_x geo_y [geo_z] [yaw pitch roll (degrees)] [horz_accuracy vert_accuracy
    (metres)] [extras...]``. :func:`read_odm_geo` -> :class:`OdmGeo`, and its GNSS observations
    (:meth:`OdmGeo.gnss`).

Conventions, converted once here:

pixels
    ``im_x im_y`` are OpenSfM's pixel coordinates (it adds 0.5 before normalising), which are
    ours: x = column right, y = row down, the centre of the top-left pixel at (0, 0). Unchanged.
CRS
    For ``EPSG:4326`` x is the longitude and y the latitude (ODM's traditional GIS order). A
    geographic file is projected, as ODM does, into the WGS 84 UTM zone of its first point (or the
    ``crs`` given) by PROJ; a projected file keeps its CRS unless ``crs`` is given.
heights
    ``geo_z`` passes unchanged into a CRS without a vertical datum (it is what the file says: ODM
    expects ellipsoidal heights for GPS-derived positions); it is converted by PROJ when both CRSs
    carry vertical datums. A ``NaN`` height (OpenSfM's "no altitude") makes a plan-only point; a
    ``geo.txt`` line without ``geo_z`` gives a NaN height.
GCP identity
    ``gcp_name`` when given; otherwise, as ODM and OpenSfM do, the lines with the same coordinates
    are one point (named ``gcp1``, ``gcp2``, ... in order of appearance).
angles and accuracies
    ``geo.txt``'s yaw, pitch, roll are kept (radians) but not turned into rotations: ODM uses them
    only for radiometric calibration and defines no axes for them. The accuracies are taken as
    standard deviations: sigma = (horz, horz, vert).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.formats.common import finite_number, read_table_text
from rectify.geometry.crs import crs_to_string, is_geographic, parse_crs, transform_xyz
from rectify.geometry.points import GcpTable
from stereo.block.types import GnssObservations
from stereo.formats.block import BlockControlTable

__all__ = ["OdmGcps", "OdmGeo", "odm_crs", "read_odm_gcps", "read_odm_geo", "detect_odm_gcps", "detect_odm_geo"]

StrPath = str | os.PathLike[str]


def odm_crs(header: str, path: StrPath) -> str:
    """The CRS of an ODM header line (``EPSG:n``, a PROJ string, ``WGS84 UTM <zone><N|S>``) as a CRS string.

    Raises
    ------
    CRSError
        A header ODM would not read, or a CRS PROJ does not know (the file and the line named).

    Examples
    --------
    >>> odm_crs("WGS84 UTM 16N", "gcp_list.txt")
    'EPSG:32616'
    >>> odm_crs("UTM 16N", "gcp_list.txt")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    rectify.errors.CRSError: 'gcp_list.txt' line 1: unknown CRS header 'UTM 16N'; expected EPSG:<code>, ...
    """
    h = header.strip().strip("'\"")
    m = re.fullmatch(r"WGS84\s+UTM\s+(\d{1,2})\s*([NSns])", h)
    if m and 1 <= int(m[1]) <= 60:
        return f"EPSG:{(32600 if m[2].upper() == 'N' else 32700) + int(m[1])}"
    if not (h.lower().startswith("epsg:") or "+proj" in h):
        raise CRSError(f"{str(path)!r} line 1: unknown CRS header {h!r}; expected EPSG:<code>, a +proj string or "
                       "'WGS84 UTM <zone><N|S>'")
    try:
        return crs_to_string(parse_crs(h.upper() if h.lower().startswith("epsg:") else h))
    except CRSError as err:
        raise CRSError(f"{str(path)!r} line 1: {err}") from None


def _data_lines(path: StrPath) -> tuple[str, list[tuple[int, list[str]]]]:
    """The CRS header and the data lines (number, cells) of an ODM file."""
    lines = read_table_text(path).splitlines()
    rows = [(no, ln.strip()) for no, ln in enumerate(lines, start=1) if ln.strip()]
    if not rows:
        raise InvalidInputError(f"{str(path)!r} is empty; its first line names the CRS")
    header = rows[0][1]
    data = [(no, s.split()) for no, s in rows[1:] if not s.startswith("#")]
    return header, data


def _number(cell: str, label: str, *, allow_nan: bool = False) -> float:
    if allow_nan and cell.strip().lower() == "nan":
        return math.nan
    return finite_number(cell, label)


def _utm_of(lon: float, lat: float) -> str:
    zone = int(math.floor((lon + 180.0) / 6.0) % 60) + 1
    return f"EPSG:{(32600 if lat >= 0 else 32700) + zone}"


def _to_ground(xyz: NDArray[np.float64], src: str, crs: str | None) -> tuple[NDArray[np.float64], str]:
    """Coordinates from the file's CRS into ``crs`` (default: the file's if projected, else its UTM zone)."""
    if crs is None:
        if not is_geographic(src):
            return xyz, src
        lonlat = transform_xyz(src, "EPSG:4326", np.nan_to_num(xyz[:1]))[0]
        crs = _utm_of(lonlat[0], lonlat[1])
    dst = crs_to_string(parse_crs(crs))
    if is_geographic(dst):
        raise CRSError(f"the ground CRS must be projected (a Cartesian frame); got {dst!r}")
    nan_z = np.isnan(xyz[:, 2])
    out = transform_xyz(src, dst, np.where(nan_z[:, None], np.column_stack([xyz[:, :2], np.zeros(len(xyz))]), xyz))
    out[nan_z, 2] = np.nan
    return out, dst


# --------------------------------------------------------------------------- gcp_list.txt
@dataclass(frozen=True, eq=False)
class OdmGcps:
    """GCPs of an ODM ``gcp_list.txt``, in a projected CRS.

    Attributes
    ----------
    ids : tuple of str
        One per GCP (K).
    xyz : (K, 3) float64
        Ground coordinates in ``crs``; z NaN for a point given without height.
    meas_id, meas_image : tuple of str
        GCP id and image name of each image measurement (L).
    meas_pixel : (L, 2) float64
        The measurements, pixels in our convention.
    crs : str
        The CRS of ``xyz``.
    file_crs : str
        The CRS the file named.
    """

    ids: tuple[str, ...]
    xyz: NDArray[np.float64]
    meas_id: tuple[str, ...]
    meas_image: tuple[str, ...]
    meas_pixel: NDArray[np.float64]
    crs: str
    file_crs: str

    @property
    def images(self) -> tuple[str, ...]:
        """The images measured, in order of first appearance."""
        return tuple(dict.fromkeys(self.meas_image))

    def gcp_table(self, image: str) -> GcpTable:
        """The GCPs measured in ``image`` as a :class:`GcpTable` (target x, y and z in :attr:`crs`).

        Raises
        ------
        InvalidInputError
            No GCP is measured in ``image`` (the measured images are named).
        """
        rows = [k for k, im in enumerate(self.meas_image) if im == image]
        if not rows:
            raise InvalidInputError(f"no GCP is measured in image {image!r}; measured: {list(self.images)[:10]}")
        index = {g: i for i, g in enumerate(self.ids)}
        pts = self.xyz[[index[self.meas_id[k]] for k in rows]]
        z = pts[:, 2].copy() if np.isfinite(pts[:, 2]).all() else None
        return GcpTable(tuple(self.meas_id[k] for k in rows), self.meas_pixel[rows].copy(), pts[:, :2].copy(), z,
                        np.zeros(len(rows), dtype=bool), self.crs)

    def control_table(self) -> BlockControlTable:
        """The GCPs as block control (``full`` points, or ``plan`` where the height is NaN; no a-priori sigma)."""
        kind = tuple("full" if math.isfinite(z) else "plan" for z in self.xyz[:, 2])
        return BlockControlTable(self.ids, self.xyz.copy(), kind, np.full((len(self.ids), 3), np.nan),
                                 self.meas_id, self.meas_image, self.meas_pixel.copy(), self.crs)


def read_odm_gcps(path: StrPath, *, crs: str | None = None) -> OdmGcps:
    """Read an ODM ``gcp_list.txt`` (see the module docstring).

    Parameters
    ----------
    path : path
    crs : str, optional
        The projected CRS to return coordinates in (default: the file's, or its UTM zone when the
        file is geographic).

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        A line with fewer than 6 values, a value that is not a number (file, line and column named),
        a ``gcp_name`` given two different coordinates, a GCP measured twice in one image, no rows.
    CRSError
        An unknown CRS header, a geographic ``crs``.
    """
    header, data = _data_lines(path)
    file_crs = odm_crs(header, path)
    names = ("geo_x", "geo_y", "geo_z", "im_x", "im_y")
    coords: dict[str, tuple[list[float], int]] = {}
    by_coords: dict[tuple[float, float, float], str] = {}
    m_id: list[str] = []
    m_img: list[str] = []
    m_px: list[list[float]] = []
    seen: set[tuple[str, str]] = set()
    for no, c in data:
        if len(c) < 6:
            raise InvalidInputError(f"{str(path)!r} line {no}: expected geo_x geo_y geo_z im_x im_y image_name "
                                    f"[gcp_name]; got {' '.join(c)!r}")
        v = [_number(x, f"{str(path)!r} line {no}: {k}", allow_nan=(k == "geo_z"))
             for x, k in zip(c[:5], names, strict=False)]
        key = (v[0], v[1], v[2])
        gid = c[6] if len(c) > 6 else by_coords.get(key) or f"gcp{len(coords) + 1}"
        by_coords.setdefault(key, gid)
        if gid in coords:
            old, line = coords[gid]
            if not np.allclose(old, v[:3], rtol=0, atol=1e-9, equal_nan=True):
                raise InvalidInputError(f"{str(path)!r} line {no}: GCP {gid!r} has coordinates {v[:3]} here and "
                                        f"{old} on line {line}")
        else:
            coords[gid] = (v[:3], no)
        if (gid, c[5]) in seen:
            raise InvalidInputError(f"{str(path)!r} line {no}: GCP {gid!r} is measured twice in image {c[5]!r}")
        seen.add((gid, c[5]))
        m_id.append(gid)
        m_img.append(c[5])
        m_px.append(v[3:5])
    if not m_id:
        raise InvalidInputError(f"{str(path)!r} has a CRS line but no GCP lines")
    ids = tuple(coords)
    xyz, ground = _to_ground(np.array([coords[g][0] for g in ids], dtype=np.float64), file_crs, crs)
    return OdmGcps(ids, xyz, tuple(m_id), tuple(m_img), np.array(m_px, dtype=np.float64), ground, file_crs)


# --------------------------------------------------------------------------- geo.txt
@dataclass(frozen=True, eq=False)
class OdmGeo:
    """Image positions of an ODM ``geo.txt``, in a projected CRS.

    Attributes
    ----------
    images : tuple of str
        Image names (n).
    position : (n, 3) float64
        Positions in ``crs``; z NaN where the line gives none.
    ypr_rad : (n, 3) float64
        Yaw, pitch, roll as given (radians; NaN where absent), not converted.
    sigma_m : (n, 3) float64
        (horz, horz, vert) accuracies, metres; NaN where absent.
    extras : tuple of str
        The rest of each line (labels), '' when none.
    crs : str
    file_crs : str
    """

    images: tuple[str, ...]
    position: NDArray[np.float64]
    ypr_rad: NDArray[np.float64]
    sigma_m: NDArray[np.float64]
    extras: tuple[str, ...]
    crs: str
    file_crs: str

    def gnss(self, *, default_sigma_m: float | None = None) -> GnssObservations:
        """The positions as GNSS observations (sigma from the file, else ``default_sigma_m``).

        Raises
        ------
        InvalidInputError
            A position without height, or without accuracy when no default is given (images named).
        """
        no_z = [im for im, z in zip(self.images, self.position[:, 2], strict=True) if not math.isfinite(z)]
        if no_z:
            raise InvalidInputError(f"geo.txt positions without height cannot be GNSS observations: {no_z[:5]}")
        sig = self.sigma_m.copy()
        missing = ~np.isfinite(sig).all(axis=1)
        if missing.any():
            if default_sigma_m is None:
                names = [im for im, m in zip(self.images, missing, strict=True) if m]
                raise InvalidInputError(f"geo.txt gives no accuracy for {names[:5]}; give a default sigma")
            sig[missing] = float(default_sigma_m)
        return GnssObservations(self.images, self.position.copy(), sig)


def read_odm_geo(path: StrPath, *, crs: str | None = None) -> OdmGeo:
    """Read an ODM ``geo.txt`` (see the module docstring).

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        A line with fewer than 3 values, a value that is not a number (file, line and column named),
        an accuracy <= 0, an image listed twice, no rows.
    CRSError
        An unknown CRS header, a geographic ``crs``.
    """
    header, data = _data_lines(path)
    file_crs = odm_crs(header, path)
    names: list[str] = []
    pos, ypr, sig, extras = [], [], [], []
    for no, c in data:
        where = f"{str(path)!r} line {no}"
        if len(c) < 3:
            raise InvalidInputError(f"{where}: expected image_name geo_x geo_y [geo_z] [yaw pitch roll] "
                                    f"[horz_accuracy vert_accuracy]; got {' '.join(c)!r}")
        if c[0] in names:
            raise InvalidInputError(f"{where}: image {c[0]!r} is listed twice")
        names.append(c[0])
        x, y = _number(c[1], f"{where}: geo_x"), _number(c[2], f"{where}: geo_y")
        z = _number(c[3], f"{where}: geo_z", allow_nan=True) if len(c) >= 4 else math.nan
        a = [math.radians(_number(v, f"{where}: {k}", allow_nan=True))
             for v, k in zip(c[4:7], ("yaw", "pitch", "roll"), strict=True)] if len(c) >= 7 else [math.nan] * 3
        if len(c) >= 9:
            h, v = _number(c[7], f"{where}: horz_accuracy"), _number(c[8], f"{where}: vert_accuracy")
            if h <= 0 or v <= 0:
                raise InvalidInputError(f"{where}: accuracies must be > 0; got {h!r}, {v!r}")
            s = [h, h, v]
        else:
            s = [math.nan] * 3
        rest = 9 if len(c) >= 9 else 7 if len(c) >= 7 else min(len(c), 4)
        pos.append([x, y, z])
        ypr.append(a)
        sig.append(s)
        extras.append(" ".join(c[rest:]))
    if not names:
        raise InvalidInputError(f"{str(path)!r} has a CRS line but no image lines")
    xyz, ground = _to_ground(np.array(pos, dtype=np.float64), file_crs, crs)
    return OdmGeo(tuple(names), xyz, np.array(ypr, dtype=np.float64), np.array(sig, dtype=np.float64),
                  tuple(extras), ground, file_crs)


# --------------------------------------------------------------------------- detection
def _first_lines(path: StrPath, n: int = 3) -> list[str]:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            lines = [ln.strip() for ln in fh.read(1 << 16).splitlines() if ln.strip()]
    except OSError:
        return []
    return lines[:n]


def _crs_header(line: str) -> bool:
    h = line.strip().strip("'\"")
    return bool(re.fullmatch(r"WGS84\s+UTM\s+\d{1,2}\s*[NSns]", h) or h.lower().startswith("epsg:") or "+proj" in h)


def detect_odm_gcps(path: StrPath) -> bool:
    """Whether ``path`` looks like an ODM ``gcp_list.txt``: a CRS line, then five numbers and an image name."""
    lines = _first_lines(path)
    if len(lines) < 2 or not _crs_header(lines[0]):
        return False
    c = lines[1].split()
    try:
        [float(v) for v in c[:5]]
    except ValueError:
        return False
    return len(c) >= 6


def detect_odm_geo(path: StrPath) -> bool:
    """Whether ``path`` looks like an ODM ``geo.txt``: a CRS line, then an image name and numbers."""
    lines = _first_lines(path)
    if len(lines) < 2 or not _crs_header(lines[0]):
        return False
    c = lines[1].split()
    if len(c) < 3 or _is_number(c[0]) or not all(_is_number(v) for v in c[1:3]):
        return False
    return not detect_odm_gcps(path)


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
