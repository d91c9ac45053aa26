"""The frame a block is adjusted in, and the conversions of coordinates and rotations into it and back.

A map projection is not a Cartesian frame: heights are measured along curved normals and the
projection's scale changes across the block (seed 004). ``stereo block`` therefore converts its
inputs (GNSS centres, control and check points, INS or pose angles) into an orthogonal frame,
adjusts there, and converts every result back into the CRS of the inputs.

Frames (:data:`FRAME_KINDS`; right-handed, metres):

``topocentric`` (default for any CRS with a datum)
    Local east, north, up about the block's centre O: the origin on the ellipsoid below the mean of
    the given positions (projection centres, control), z along the ellipsoid normal at O, x east,
    y north in the tangent plane (seed 004, eqs. 4-5, with its rows reordered east, north, up).
``geocentric``
    The ECEF frame of the CRS's datum, moved by the geocentric vector of O so that its numbers
    stay small (axes unchanged: X towards lon 0 on the equator, Z towards the north pole).
``map``
    The coordinates as given (E, N, h in a projected CRS, or a local frame without CRS): no
    conversion. Refused for a geographic CRS (degrees are not a frame).

Heights: ellipsoidal unless the CRS is compound with a vertical CRS (``EPSG:32633+3855``): then
they are heights above that vertical datum and the geoid undulation N from PROJ's grid is added
on the way in (h = H + N) and taken off on the way out (the grid must be installed; see
:func:`rectify.geometry.crs.geoid_height`).

Rotations (photo vector (x, y, -f) -> frame) are converted through the local frame at the
camera's own position:

* angles of a pose file in omega-phi-kappa are taken as given in the *local grid* at the camera:
  x along grid east, y along grid north, z along the ellipsoid normal at the camera (what
  photogrammetric packages write in a projected CRS; in a geographic CRS the local grid is local
  east, north, up);
* GNSS/INS navigation angles (heading from true north, pitch and roll from the local vertical,
  :mod:`stereo.block.navigation`) give the rotation in the local ENU frame at the camera.

``R_frame = frame_from_enu(c) @ R_enu`` with ``R_enu = grid_from_enu(c).T @ R_grid`` for grid
angles. ``frame_from_enu`` holds the meridian convergence (grid north vs true north,
:mod:`rectify.geometry.mapframe`) and the deflection of the camera's vertical from the frame's z
axis (about s / R: 0.13 degrees 14 km from O). In the map frame ``frame_from_enu`` is
``grid_from_enu`` alone: the vertical is taken as the same everywhere. Outputs go back the same
way: written angles are omega, phi, kappa in the local grid at each camera (see above).

Vectors (residuals, errors, standard errors, covariances) go out rotated into the local grid at
their point (grid east, grid north, up; metres): the projection's scale factor (within 0.1 % of 1
in a UTM zone) is not applied to them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.crs import crs_to_string, geoid_height, horizontal_crs, parse_crs, vertical_datum
from rectify.geometry.curvature import EARTH_RADIUS_M, height_drop
from rectify.geometry.geodesy import (
    ecef_from_geodetic,
    enu_rotation,
    geodetic_from_ecef,
    geodetic_from_map,
    map_from_geodetic,
)
from rectify.geometry.points import as_points

__all__ = ["FRAME_KINDS", "AdjustmentFrame", "default_frame_kind", "curvature_warning", "CURVATURE_WARN_M"]

F64 = NDArray[np.float64]

#: the frames ``stereo block --frame`` offers
FRAME_KINDS = ("topocentric", "geocentric", "map")
#: a map-frame block whose half-extent makes the level surface drop more than this (m) gets a warning
CURVATURE_WARN_M = 0.1
#: half the latitude step (degrees) of the difference that finds true north in a grid (about 11 m)
_STEP_DEG = 1e-4


def _is_cartesian_topocentric(crs) -> bool:
    """True for a CRS that is already a local topocentric frame (EPSG method 9837, OpenSfM's frame)."""
    op = getattr(parse_crs(crs), "coordinate_operation", None)
    return op is not None and str(op.method_code) == "9837"


def default_frame_kind(crs) -> str:
    """``"topocentric"`` for a CRS with a geodetic datum (projected, geographic, geocentric), else ``"map"``.

    A CRS that is itself a topocentric frame (EPSG method 9837, OpenSfM's) is Cartesian already: ``"map"``.
    """
    if crs is None:
        return "map"
    c = parse_crs(crs)
    return "topocentric" if c.geodetic_crs is not None and not _is_cartesian_topocentric(c) else "map"


def curvature_warning(xyh: ArrayLike, crs) -> str | None:
    """The warning of a map-frame adjustment over a block wide enough for Earth curvature to matter, or None.

    The drop of the level surface below the tangent plane at the largest plan distance from the
    block's centre (seed 004, eq. 1 with h = 0: R (1 - cos(s / R)), R = 6371 km) when it exceeds
    :data:`CURVATURE_WARN_M`; only for a projected CRS (a local frame has no known curvature).
    """
    if crs is None or not parse_crs(horizontal_crs(crs)).is_projected:
        return None
    p = as_points(xyh, "xyh", 3)
    if len(p) < 2:
        return None
    xy = p[:, :2]
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    s = float(np.max(np.hypot(*(xy - centre).T)))
    extent = float(np.max(xy.max(axis=0) - xy.min(axis=0)))
    drop = float(height_drop(s, EARTH_RADIUS_M))
    if drop <= CURVATURE_WARN_M:
        return None
    return (f"adjusting in the map CRS over {extent / 1000:.1f} km: Earth curvature alone bends heights by up to "
            f"{drop:.1f} m at {s / 1000:.1f} km from the block's centre (seed 004 eq. 1, R = 6371 km); use "
            "--frame topocentric")


def _lonlat_rotation(lon: F64, lat: F64) -> F64:
    """(N, 3, 3) rotations ECEF -> ENU at each (lon, lat) (degrees), rows east, north, up."""
    lam, phi = np.radians(lon), np.radians(lat)
    sl, cl, sp, cp = np.sin(lam), np.cos(lam), np.sin(phi), np.cos(phi)
    z = np.zeros_like(lam)
    return np.stack([np.stack([-sl, cl, z], -1), np.stack([-sp * cl, -sp * sl, cp], -1),
                     np.stack([cp * cl, cp * sl, sp], -1)], axis=-2)


def _rot_z(a: F64) -> F64:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], axis=-2)


@dataclass(frozen=True, eq=False)
class AdjustmentFrame:
    """An adjustment frame and the CRS of the inputs and outputs (immutable).

    Build it with :meth:`from_points` (or :meth:`local` for a block without CRS).

    Attributes
    ----------
    kind : {"topocentric", "geocentric", "map"}
    crs : str or None
        The CRS of the inputs and outputs (a projected, geographic, geocentric or compound CRS); None
        for a local block.
    origin_lonlat_h : (3,) float64 or None
        The block's centre O: lon, lat (degrees) on the ellipsoid (h = 0); None for ``map``.
    """

    kind: str
    crs: str | None
    origin_lonlat_h: F64 | None = None
    _hcrs: str | None = field(default=None, init=False, repr=False)
    _geoid: str | None = field(default=None, init=False, repr=False)
    _o_ecef: F64 | None = field(default=None, init=False, repr=False)
    _E0: F64 | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in FRAME_KINDS:
            raise InvalidInputError(f"unknown adjustment frame {self.kind!r}; expected one of {list(FRAME_KINDS)}")
        crs = None if self.crs is None else crs_to_string(parse_crs(self.crs))
        object.__setattr__(self, "crs", crs)
        if crs is None:
            if self.kind != "map":
                raise InvalidInputError(f"--frame {self.kind} needs a CRS (a '# crs=' line in the pose or control "
                                        "file): a block without CRS is adjusted in its own local frame (--frame map)")
            return
        c = parse_crs(crs)
        if c.geodetic_crs is None:
            if self.kind != "map":
                raise InvalidInputError(f"--frame {self.kind} needs a CRS with a geodetic datum; {c.name!r} has none "
                                        "(a local engineering frame: use --frame map)")
            return
        if self.kind != "map" and _is_cartesian_topocentric(c):
            raise InvalidInputError(f"--frame {self.kind}: {c.name!r} is a topocentric frame already (Cartesian, "
                                    "its z is not a height): use --frame map")
        hcrs = horizontal_crs(crs)
        h = parse_crs(hcrs)
        if self.kind == "map" and h.is_geographic:
            raise InvalidInputError(f"--frame map cannot adjust in the geographic CRS {h.name!r} (degrees are not a "
                                    "Cartesian frame): use --frame topocentric")
        vd = vertical_datum(crs)
        object.__setattr__(self, "_hcrs", hcrs)
        object.__setattr__(self, "_geoid", vd.crs if vd is not None and not vd.ellipsoidal else None)
        if self.kind == "map":
            object.__setattr__(self, "origin_lonlat_h", None)
            return
        if self.origin_lonlat_h is None:
            raise InvalidInputError(f"the {self.kind} frame needs an origin (lon, lat, h)")
        o = np.array(self.origin_lonlat_h, dtype=np.float64).reshape(-1)
        if o.shape != (3,) or not np.isfinite(o).all() or abs(o[1]) > 89.0:
            raise InvalidInputError(f"frame origin must be finite (lon, lat, h) away from the poles; got {o.tolist()}")
        o.flags.writeable = False
        E0 = enu_rotation(float(o[0]), float(o[1]))
        E0.flags.writeable = False
        oe = ecef_from_geodetic(o[None, :], crs=hcrs)[0]
        oe.flags.writeable = False
        object.__setattr__(self, "origin_lonlat_h", o)
        object.__setattr__(self, "_E0", E0)
        object.__setattr__(self, "_o_ecef", oe)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(cls, kind: str, crs, xyh: ArrayLike) -> AdjustmentFrame:
        """The frame about the centre of the map points ``xyh`` (N, 3) (projection centres, control).

        The origin is the mean of the points' longitudes and latitudes, on the ellipsoid (h = 0).

        Raises
        ------
        InvalidInputError
            Unknown kind; a frame that conflicts with the CRS (topocentric or geocentric without a
            CRS or datum, map in a geographic CRS); no finite point for the origin.
        CRSError
            PROJ cannot convert the points (or the geoid grid of a vertical CRS is missing).
        """
        if kind not in FRAME_KINDS:
            raise InvalidInputError(f"unknown adjustment frame {kind!r}; expected one of {list(FRAME_KINDS)}")
        if kind == "map" or crs is None or parse_crs(crs).geodetic_crs is None or _is_cartesian_topocentric(crs):
            return cls(kind, crs)
        p = as_points(xyh, "xyh", 3)
        p = p[np.isfinite(p).all(axis=1)]
        if not len(p):
            raise InvalidInputError(f"the {kind} frame needs at least one finite position for its origin")
        geographic = parse_crs(horizontal_crs(crs)).is_geographic
        probe = cls("topocentric" if geographic else "map", crs, np.zeros(3) if geographic else None)
        llh = probe._geodetic(p)
        lon = llh[:, 0]
        lon0 = float(np.degrees(np.arctan2(np.mean(np.sin(np.radians(lon))), np.mean(np.cos(np.radians(lon))))))
        return cls(kind, crs, np.array([lon0, float(np.mean(llh[:, 1])), 0.0]))

    @classmethod
    def local(cls) -> AdjustmentFrame:
        """The map frame of a block without CRS."""
        return cls("map", None)

    # ------------------------------------------------------------------ description
    @property
    def is_identity(self) -> bool:
        """True when coordinates are adjusted as given (the map frame)."""
        return self.kind == "map"

    def description(self) -> str:
        """One line: the frame, its origin and the heights."""
        heights = (f"heights above {self._geoid} converted to ellipsoidal heights" if self._geoid is not None
                   else "ellipsoidal heights")
        if self.kind == "map":
            if self.crs is None:
                return "map (the local frame of the given coordinates)"
            return f"map ({self.crs} as given: no Earth curvature, no scale change)"
        o = self.origin_lonlat_h
        assert o is not None  # noqa: S101 -- set in __post_init__ for these kinds
        what = ("topocentric east-north-up" if self.kind == "topocentric"
                else "geocentric (ECEF axes, moved to the origin)")
        return f"{what} about lon {o[0]:.6f}, lat {o[1]:.6f} deg on the ellipsoid ({heights}; results in {self.crs})"

    # ------------------------------------------------------------------ points
    def _geodetic(self, xyh: F64) -> F64:
        """(N, 3) map points -> (lon, lat, h ellipsoidal)."""
        assert self._hcrs is not None  # noqa: S101
        h = parse_crs(self._hcrs)
        if h.is_geocentric:
            return geodetic_from_ecef(xyh, crs=self._hcrs)
        llh = geodetic_from_map(xyh, self._hcrs)
        if self._geoid is not None and len(llh):
            llh[:, 2] = llh[:, 2] + self._undulation(llh[:, :2])
        return llh

    def _undulation(self, lonlat: F64) -> F64:
        """The geoid undulation N (m) of the CRS's vertical datum; refused by name when PROJ lacks its grid."""
        try:
            return geoid_height(self._geoid, lonlat)
        except CRSError as err:
            text = str(err).split(" or pass a constant undulation")[0]
            raise CRSError(f"{text}, or give ellipsoidal heights (a CRS without a vertical datum)") from err

    def _lonlat(self, xyh: F64) -> F64:
        """(N, 3) map points -> (N, 2) lon, lat (degrees); no height conversion (no geoid needed)."""
        assert self._hcrs is not None  # noqa: S101
        if parse_crs(self._hcrs).is_geocentric:
            return geodetic_from_ecef(xyh, crs=self._hcrs)[:, :2]
        return geodetic_from_map(xyh, self._hcrs)[:, :2]

    def _map(self, llh: F64) -> F64:
        """(lon, lat, h ellipsoidal) -> map points."""
        assert self._hcrs is not None  # noqa: S101
        if parse_crs(self._hcrs).is_geocentric:
            return ecef_from_geodetic(llh, crs=self._hcrs)
        out = map_from_geodetic(llh, self._hcrs)
        if self._geoid is not None and len(out):
            out[:, 2] = out[:, 2] - self._undulation(llh[:, :2])
        return out

    def frame_from_map(self, xyh: ArrayLike) -> F64:
        """Map points (N, 3) (x, y, height in the CRS) -> frame coordinates (N, 3), m."""
        p = as_points(xyh, "xyh", 3)
        if self.kind == "map" or not len(p):
            return p.copy()
        ecef = ecef_from_geodetic(self._geodetic(p), crs=self._hcrs)
        assert self._o_ecef is not None and self._E0 is not None  # noqa: S101
        d = ecef - self._o_ecef
        return np.asarray(d @ self._E0.T if self.kind == "topocentric" else d, dtype=np.float64)

    def map_from_frame(self, xyz: ArrayLike) -> F64:
        """Frame coordinates (N, 3), m -> map points (N, 3) in the CRS (the inverse of :meth:`frame_from_map`)."""
        p = as_points(xyz, "xyz", 3)
        if self.kind == "map" or not len(p):
            return p.copy()
        return self._map(geodetic_from_ecef(self._ecef(p), crs=self._hcrs))

    def _ecef(self, xyz: F64) -> F64:
        assert self._o_ecef is not None and self._E0 is not None  # noqa: S101
        d = xyz @ self._E0 if self.kind == "topocentric" else xyz
        return np.asarray(d + self._o_ecef, dtype=np.float64)

    def _lonlat_of_frame(self, xyz: F64) -> F64:
        if self.kind == "map":
            return self._lonlat(xyz) if self._hcrs is not None else np.zeros((len(xyz), 2))
        return geodetic_from_ecef(self._ecef(xyz), crs=self._hcrs)[:, :2]

    # ------------------------------------------------------------------ rotations
    def _grid_from_enu(self, lonlat: F64) -> F64:
        """(N, 3, 3) ENU -> local grid at each point (Rz(-a), a = azimuth of true north in the grid)."""
        n = len(lonlat)
        if self._hcrs is None or not parse_crs(self._hcrs).is_projected:
            return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        up = np.column_stack([lonlat[:, 0], lonlat[:, 1] + _STEP_DEG, np.zeros(n)])
        dn = np.column_stack([lonlat[:, 0], lonlat[:, 1] - _STEP_DEG, np.zeros(n)])
        v = map_from_geodetic(up, self._hcrs)[:, :2] - map_from_geodetic(dn, self._hcrs)[:, :2]
        return _rot_z(-np.arctan2(v[:, 0], v[:, 1]))

    def _frame_from_enu(self, lonlat: F64) -> F64:
        """(N, 3, 3) ENU at each point -> frame."""
        n = len(lonlat)
        if self._hcrs is None:
            return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        E = _lonlat_rotation(lonlat[:, 0], lonlat[:, 1])  # ECEF -> ENU at the point
        Et = np.swapaxes(E, -1, -2)
        if self.kind == "topocentric":
            assert self._E0 is not None  # noqa: S101
            return np.asarray(self._E0 @ Et, dtype=np.float64)
        if self.kind == "geocentric" or parse_crs(self._hcrs).is_geocentric:
            return np.asarray(Et, dtype=np.float64)
        return self._grid_from_enu(lonlat)

    def _frame_from_grid(self, lonlat: F64) -> F64:
        """(N, 3, 3) local grid at each point -> frame."""
        if self._hcrs is not None and parse_crs(self._hcrs).is_geocentric:
            M = self._E0 if self.kind == "topocentric" and self._E0 is not None else np.eye(3)
            return np.broadcast_to(M, (len(lonlat), 3, 3)).copy()
        F = self._frame_from_enu(lonlat)
        return np.asarray(F @ np.swapaxes(self._grid_from_enu(lonlat), -1, -2), dtype=np.float64)

    def rotations_in(self, R: ArrayLike, xyh: ArrayLike, *, navigation: bool = False) -> F64:
        """Camera rotations (N, 3, 3) at map positions ``xyh`` (N, 3) -> rotations photo -> frame.

        Parameters
        ----------
        R : (N, 3, 3)
            Photo vector (x, y, -f) -> the local grid at the camera (``navigation=False``: angles in
            omega-phi-kappa of a pose file) or -> local ENU at the camera (``navigation=True``:
            heading from true north, tilts from the local vertical).
        """
        m, p = self._rot_args(R, xyh)
        if self._hcrs is None:
            return m.copy()
        ll = self._lonlat(p)
        T = self._frame_from_enu(ll) if navigation else self._frame_from_grid(ll)
        return np.asarray(T @ m, dtype=np.float64)

    def rotations_out(self, R: ArrayLike, xyz: ArrayLike) -> F64:
        """Rotations photo -> frame (N, 3, 3) of cameras at frame positions ``xyz`` -> photo -> local grid."""
        m, p = self._rot_args(R, xyz)
        if self._hcrs is None:
            return m.copy()
        T = self._frame_from_grid(self._lonlat_of_frame(p))
        return np.asarray(np.swapaxes(T, -1, -2) @ m, dtype=np.float64)

    def grid_from_frame(self, xyz: ArrayLike) -> F64:
        """(N, 3, 3) rotations taking frame vectors at frame points ``xyz`` into the local grid there."""
        p = as_points(xyz, "xyz", 3)
        if self._hcrs is None or not len(p):
            return np.broadcast_to(np.eye(3), (len(p), 3, 3)).copy()
        return np.asarray(np.swapaxes(self._frame_from_grid(self._lonlat_of_frame(p)), -1, -2), dtype=np.float64)

    def frame_from_grid_at(self, xyh: ArrayLike) -> F64:
        """(N, 3, 3) rotations taking local-grid vectors at map points ``xyh`` into the frame."""
        p = as_points(xyh, "xyh", 3)
        if self._hcrs is None:
            return np.broadcast_to(np.eye(3), (len(p), 3, 3)).copy()
        return self._frame_from_grid(self._lonlat(p))

    def vectors_out(self, v: ArrayLike, xyz: ArrayLike) -> F64:
        """Frame vectors (N, 3) at frame points ``xyz`` (N, 3) -> local grid vectors (rotation only), m."""
        vv = as_points(v, "v", 3)
        G = self.grid_from_frame(xyz)
        return np.asarray(np.einsum("nij,nj->ni", G, vv), dtype=np.float64)

    def covariances_out(self, C: ArrayLike, xyz: ArrayLike) -> F64:
        """Frame covariances (N, 3, 3) at frame points -> local grid covariances (N, 3, 3), m^2."""
        c = np.asarray(C, dtype=np.float64).reshape(-1, 3, 3)
        G = self.grid_from_frame(xyz)
        return np.asarray(G @ c @ np.swapaxes(G, -1, -2), dtype=np.float64)

    @staticmethod
    def _rot_args(R: ArrayLike, xyz: ArrayLike) -> tuple[F64, F64]:
        m = np.asarray(R, dtype=np.float64)
        if m.ndim == 2:
            m = m[None]
        p = as_points(xyz, "positions", 3)
        if m.shape != (len(p), 3, 3):
            raise InvalidInputError(f"rotations must have shape ({len(p)}, 3, 3), one per position; got {m.shape}")
        return m, p
