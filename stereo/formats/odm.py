"""OpenDroneMap's ``gcp_list.txt`` (as block control) and ``geo.txt`` (image positions) in.

The ``gcp_list.txt`` reader is :mod:`rectify.formats.odm` (``rectify`` reads it too, one image at a
time); here it becomes the block's control (:meth:`OdmGcps.control_table`). Both files start with a
line naming the CRS of their coordinates (:func:`rectify.formats.odm.odm_crs`).

``gcp_list.txt``
    ``geo_x geo_y geo_z im_x im_y image_name [gcp_name] [extras...]`` - one line per image
    measurement of a GCP. :func:`read_odm_gcps` -> :class:`OdmGcps`, which gives a
    :class:`rectify.geometry.points.GcpTable` per image (:meth:`OdmGcps.gcp_table`) and the block
    control (:meth:`OdmGcps.control_table`).
``geo.txt``
    ``image_name geo_x geo_y [geo_z] [yaw pitch roll (degrees)] [horz_accuracy vert_accuracy
    (metres)] [extras...]``. :func:`read_odm_geo` -> :class:`OdmGeo`, and its GNSS observations
    (:meth:`OdmGeo.gnss`).

Conventions (pixels, CRS, heights and GCP identity as in :mod:`rectify.formats.odm`):

heights
    A ``geo.txt`` line without ``geo_z`` gives a NaN height.
angles and accuracies
    ``geo.txt``'s yaw, pitch, roll are kept (radians) but not turned into rotations: ODM uses them
    only for radiometric calibration and defines no axes for them. The accuracies are taken as
    standard deviations: sigma = (horz, horz, vert).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath
from rectify.formats.odm import (
    OdmGcpList,
    detect_odm_gcps,
    detect_odm_geo,
    odm_crs,
    odm_ground,
    odm_lines,
    odm_number,
    read_odm_gcp_list,
)
from stereo.block.types import GnssObservations
from stereo.formats.block import BlockControlTable

__all__ = ["OdmGcps", "OdmGeo", "odm_crs", "read_odm_gcps", "read_odm_geo", "detect_odm_gcps", "detect_odm_geo"]


# --------------------------------------------------------------------------- gcp_list.txt
class OdmGcps(OdmGcpList):
    """GCPs of an ODM ``gcp_list.txt`` in a projected CRS (:class:`rectify.formats.odm.OdmGcpList`), as block
    control too."""

    def control_table(self) -> BlockControlTable:
        """The GCPs as block control (``full`` points, or ``plan`` where the height is NaN; no a-priori sigma)."""
        kind = tuple("full" if math.isfinite(z) else "plan" for z in self.xyz[:, 2])
        return BlockControlTable(self.ids, self.xyz.copy(), kind, np.full((len(self.ids), 3), np.nan),
                                 self.meas_id, self.meas_image, self.meas_pixel.copy(), self.crs)


def read_odm_gcps(path: StrPath, *, crs: str | None = None) -> OdmGcps:
    """Read an ODM ``gcp_list.txt`` (:func:`rectify.formats.odm.read_odm_gcp_list`) as :class:`OdmGcps`.

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        As :func:`rectify.formats.odm.read_odm_gcp_list`.
    """
    g = read_odm_gcp_list(path, crs=crs)
    return OdmGcps(g.ids, g.xyz, g.meas_id, g.meas_image, g.meas_pixel, g.crs, g.file_crs)


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

    def gnss(self, *, default_sigma_m: float | tuple[float, float, float] | None = None) -> GnssObservations:
        """The positions as GNSS observations (sigma from the file, else ``default_sigma_m``: one value, or x, y, z).

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
            sig[missing] = np.broadcast_to(np.asarray(default_sigma_m, dtype=np.float64), (3,))
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
    header, data = odm_lines(path)
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
        x, y = odm_number(c[1], f"{where}: geo_x"), odm_number(c[2], f"{where}: geo_y")
        z = odm_number(c[3], f"{where}: geo_z", allow_nan=True) if len(c) >= 4 else math.nan
        a = [math.radians(odm_number(v, f"{where}: {k}", allow_nan=True))
             for v, k in zip(c[4:7], ("yaw", "pitch", "roll"), strict=True)] if len(c) >= 7 else [math.nan] * 3
        if len(c) >= 9:
            h, v = odm_number(c[7], f"{where}: horz_accuracy"), odm_number(c[8], f"{where}: vert_accuracy")
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
    xyz, ground = odm_ground(np.array(pos, dtype=np.float64), file_crs, crs)
    return OdmGeo(tuple(names), xyz, np.array(ypr, dtype=np.float64), np.array(sig, dtype=np.float64),
                  tuple(extras), ground, file_crs)
