"""OpenDroneMap's ``gcp_list.txt`` in (GCPs with their image measurements), and the ODM files' shared parts.

Both of ODM's point files start with a line naming the CRS of their coordinates, as ODM reads it:
``EPSG:<code>``, a PROJ string (``+proj=utm +zone=10 +datum=WGS84 ...``) or ``WGS84 UTM <zone><N|S>``
(:func:`odm_crs`); the other lines are separated by spaces or tabs, and ``#`` lines are comments.

``gcp_list.txt``
    ``geo_x geo_y geo_z im_x im_y image_name [gcp_name] [extras...]`` - one line per image
    measurement of a GCP. :func:`read_odm_gcp_list` -> :class:`OdmGcpList`, which gives a
    :class:`rectify.geometry.points.GcpTable` per image (:meth:`OdmGcpList.gcp_table`, what
    ``rectify fit``, ``warp`` and ``ortho`` take); ``stereo.formats.odm`` adds the block control and
    reads ``geo.txt`` (image positions).

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
    carry vertical datums. A ``NaN`` height (OpenSfM's "no altitude") makes a plan-only point.
GCP identity
    ``gcp_name`` when given; otherwise, as ODM and OpenSfM do, the lines with the same coordinates
    are one point (named ``gcp1``, ``gcp2``, ... in order of appearance).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.formats.common import StrPath, finite_number, read_table_text
from rectify.geometry.crs import crs_to_string, is_geographic, parse_crs, transform_xyz, utm_crs
from rectify.geometry.points import GcpTable

__all__ = ["OdmGcpList", "odm_crs", "odm_lines", "odm_number", "odm_ground", "read_odm_gcp_list",
           "detect_odm_gcps", "detect_odm_geo"]


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


def odm_lines(path: StrPath) -> tuple[str, list[tuple[int, list[str]]]]:
    """The CRS header and the data lines (number, cells) of an ODM file."""
    lines = read_table_text(path).splitlines()
    rows = [(no, ln.strip()) for no, ln in enumerate(lines, start=1) if ln.strip()]
    if not rows:
        raise InvalidInputError(f"{str(path)!r} is empty; its first line names the CRS")
    header = rows[0][1]
    data = [(no, s.split()) for no, s in rows[1:] if not s.startswith("#")]
    return header, data


def odm_number(cell: str, label: str, *, allow_nan: bool = False) -> float:
    """A finite number of an ODM line (``nan`` allowed where OpenSfM allows it); ``label`` names file, line, column."""
    if allow_nan and cell.strip().lower() == "nan":
        return math.nan
    return finite_number(cell, label)


def odm_ground(xyz: NDArray[np.float64], src: str, crs: str | None) -> tuple[NDArray[np.float64], str]:
    """Coordinates from the file's CRS into ``crs`` (default: the file's if projected, else its UTM zone)."""
    if crs is None:
        if not is_geographic(src):
            return xyz, src
        lonlat = transform_xyz(src, "EPSG:4326", np.nan_to_num(xyz[:1]))[0]
        crs = utm_crs(lonlat[0], lonlat[1])
    dst = crs_to_string(parse_crs(crs))
    if is_geographic(dst):
        raise CRSError(f"the ground CRS must be projected (a Cartesian frame); got {dst!r}")
    nan_z = np.isnan(xyz[:, 2])
    out = transform_xyz(src, dst, np.where(nan_z[:, None], np.column_stack([xyz[:, :2], np.zeros(len(xyz))]), xyz))
    out[nan_z, 2] = np.nan
    return out, dst


# --------------------------------------------------------------------------- gcp_list.txt
@dataclass(frozen=True, eq=False)
class OdmGcpList:
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


def read_odm_gcp_list(path: StrPath, *, crs: str | None = None) -> OdmGcpList:
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
    header, data = odm_lines(path)
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
        v = [odm_number(x, f"{str(path)!r} line {no}: {k}", allow_nan=(k == "geo_z"))
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
    xyz, ground = odm_ground(np.array([coords[g][0] for g in ids], dtype=np.float64), file_crs, crs)
    return OdmGcpList(ids, xyz, tuple(m_id), tuple(m_img), np.array(m_px, dtype=np.float64), ground, file_crs)


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
    """Whether ``path`` looks like an ODM ``gcp_list.txt``: a first line that is not a CSV header (the CRS; the
    reader names one it does not know), then lines of at least six values that start with two numbers."""
    lines = _first_lines(path)
    if len(lines) < 2 or "," in lines[0]:  # a CRS line of any form: its reader names one it does not know
        return False
    c = lines[1].split()
    return len(c) >= 6 and _is_number(c[0]) and _is_number(c[1])


def detect_odm_geo(path: StrPath) -> bool:
    """Whether ``path`` looks like an ODM ``geo.txt``: a first line that is not a CSV header, then lines of an
    image name and at least two more values (a CRS line, or a number after the name; the reader names a
    malformed value)."""
    lines = _first_lines(path)
    if len(lines) < 2 or "," in lines[0] or "," in lines[1]:
        return False
    c = lines[1].split()
    return len(c) >= 3 and not _is_number(c[0]) and (_crs_header(lines[0]) or _is_number(c[1]))


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
