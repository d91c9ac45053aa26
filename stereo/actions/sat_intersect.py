"""``stereo sat-intersect``: seed 001's space-image workflow as a command (docs/satellite.md).

Gauss-Krueger (any projected CRS) coordinates and normal heights of the projection centres -> B, L and
ellipsoidal height (height anomaly of the user's quasi-geoid / geoid model) -> geocentric X, Y, Z (seed
001 step 5) -> rays of the image points (attitude in the local level frame) -> least-squares intersection
in the geocentric frame (:mod:`stereo.pair.satellite`) -> B, L, h (seed 001, iterated) -> normal heights
and Gauss-Krueger x, y, with each point's standard deviations in the map grid axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.crs import (
    crs_to_string,
    geoid_height,
    grid_undulation,
    horizontal_crs,
    parse_crs,
    transform_xy,
    vertical_datum,
)
from rectify.geometry.geodesy import (
    blh_from_geocentric_formula,
    ellipsoid_of,
    enu_rotation,
    geocentric_from_blh_formula,
    geodetic_from_map,
    map_from_geodetic,
)
from rectify.geometry.mapframe import grid_from_enu
from stereo.actions.common import PathArg
from stereo.actions.workspace import PairWorkspace
from stereo.formats.satellite import read_image_points, read_stations, sat_points_text
from stereo.pair.satellite import ecef_directions, intersect_rays

__all__ = ["SatIntersectOptions", "SatIntersectResult", "sat_intersect"]

F64 = NDArray[np.float64]

#: suffixes taken as a grid file (anything else that is not an existing file is a vertical CRS)
GRID_SUFFIXES = (".tif", ".tiff", ".gtx")


@dataclass(frozen=True)
class SatIntersectOptions:
    """Options of ``stereo sat-intersect``.

    Attributes
    ----------
    crs : str or None
        Map CRS of the stations and of the output (a projected CRS, e.g. Gauss-Krueger ``EPSG:28404``;
        may be compound with a vertical CRS); default the stations file's ``# crs=`` line.
    geoid : str or None
        The quasi-geoid / geoid model of the heights: a PROJ grid file (GeoTIFF, GTX: heights of the
        model above the ellipsoid of the CRS on a lon/lat grid) or a vertical CRS (``EPSG:3855``), whose
        PROJ grid must be installed. Default: the vertical part of a compound ``crs``.
    ellipsoidal : bool
        The heights are ellipsoidal (no model); excludes ``geoid``.
    sigma_mm : float
        Standard deviation of an image coordinate, mm, for points without ``sigma_mm``.
    """

    crs: str | None = None
    geoid: str | None = None
    ellipsoidal: bool = False
    sigma_mm: float = 0.005

    def __post_init__(self) -> None:
        if not (isinstance(self.sigma_mm, (int, float)) and math.isfinite(self.sigma_mm) and self.sigma_mm > 0):
            raise InvalidInputError(f"--sigma-mm must be a finite number > 0; got {self.sigma_mm!r}")
        if self.ellipsoidal and self.geoid is not None:
            raise InvalidInputError(f"give --geoid {self.geoid} (normal heights) or --ellipsoidal, not both")


@dataclass(frozen=True, eq=False)
class SatIntersectResult:
    """Result of :func:`sat_intersect`: the points (map x, y, height), their standard deviations, the file."""

    ids: tuple[str, ...]
    xyz: F64
    std: F64
    n_rays: NDArray[np.int64]
    rms_mm: F64
    sigma0: float
    redundancy: int
    n_images: int
    crs: str
    heights: str
    output: Path

    def summary_lines(self) -> list[str]:
        s0 = f"{self.sigma0:.3f}" if math.isfinite(self.sigma0) else "n/a"
        med = np.median(self.std, axis=0)
        return [f"intersected {len(self.ids)} point(s) from {int(self.n_rays.sum())} rays of {self.n_images} "
                f"image(s) in the geocentric frame; map CRS {self.crs}",
                f"heights: {self.heights}",
                f"sigma0 {s0} (redundancy {self.redundancy}); median std x {med[0]:.3f} m, y {med[1]:.3f} m, "
                f"z {med[2]:.3f} m; largest image misclosure {float(self.rms_mm.max(initial=0.0)) * 1000:.2f} um",
                f"wrote {self.output}"]


def _undulation(model: str, lonlat: F64, geographic: str) -> F64:
    """N (m) of the model at (lon, lat) degrees on the CRS's datum: a grid file or a vertical CRS."""
    p = Path(model)
    if p.suffix.lower() in GRID_SUFFIXES or p.is_file():
        return grid_undulation(p, lonlat)  # a missing file is refused by name
    try:
        v = parse_crs(model)
    except CRSError as err:
        raise CRSError(f"--geoid {model!r} is neither a grid file (.tif, .gtx) nor a CRS: {err}") from err
    if not v.is_vertical:
        raise CRSError(f"--geoid {model!r} is not a vertical CRS ({v.name!r})")
    try:
        return geoid_height(v, transform_xy(geographic, "EPSG:4326", lonlat))
    except CRSError as err:  # the grid is named; this command's alternative is a grid file
        raise CRSError(str(err).replace("pass a constant undulation (--undulation N, metres)",
                                        "give the model as a grid file (--geoid FILE.tif)")) from err


def sat_intersect(*, stations: PathArg, points: PathArg, output: PathArg, overwrite: bool = False,
                  options: SatIntersectOptions | None = None) -> SatIntersectResult:
    """``stereo sat-intersect``: intersect the rays of satellite images in the geocentric frame.

    Raises
    ------
    InvalidInputError
        Bad files (named), points naming unknown images, a point with one ray, no CRS or a CRS that is not
        projected, no height model and no ``--ellipsoidal``, an output that exists.
    CRSError
        A geoid grid that is missing or not readable, a vertical CRS whose grid is not installed (named).
    EstimationError
        Parallel rays or a point behind a projection centre.
    """
    opts = options or SatIntersectOptions()
    ws = PairWorkspace(overwrite=overwrite, inputs=[stations, points])
    ws.plan(output)
    st = read_stations(stations)
    ip = read_image_points(points)
    crs_in = opts.crs or st.crs
    if crs_in is None:
        raise InvalidInputError(f"{str(stations)!r} has no '# crs=' line and no --crs was given: the map CRS "
                                "(Gauss-Krueger) is needed")
    full = parse_crs(crs_in)
    hcrs = horizontal_crs(full)
    hc = parse_crs(hcrs)
    if not hc.is_projected:
        raise InvalidInputError(f"CRS {hc.name!r} is not projected: the stations are map (Gauss-Krueger) x, y")
    model = opts.geoid
    if model is None and not opts.ellipsoidal:
        vd = vertical_datum(full)
        if vd is not None and vd.crs is not None:
            model = vd.crs
        elif vd is None or not vd.ellipsoidal:
            raise InvalidInputError("the heights need a model: --geoid GRID|VERTICAL_CRS (normal or orthometric "
                                    "heights) or --ellipsoidal (ellipsoidal heights)")
    geographic = crs_to_string(hc.geodetic_crs)
    # points -> their rays
    index = {name: k for k, name in enumerate(st.images)}
    unknown = [m for m in ip.images if m not in index]
    if unknown:
        raise InvalidInputError(f"{str(points)!r}: image {unknown[0]!r} is not in {str(stations)!r}")
    uid = tuple(dict.fromkeys(ip.ids))
    where = {u: k for k, u in enumerate(uid)}
    pidx = np.array([where[i] for i in ip.ids], dtype=np.int64)
    cnt = np.bincount(pidx, minlength=len(uid))
    if (cnt < 2).any():
        j = int(np.flatnonzero(cnt < 2)[0])
        raise InvalidInputError(f"{str(points)!r}: point {uid[j]!r} is measured in {int(cnt[j])} image; an "
                                "intersection needs two")
    # stations: map -> B, L, H -> h = H + N -> geocentric (seed 001 step 5)
    ll = geodetic_from_map(st.xyz, hcrs)
    n_st = np.zeros(len(ll)) if model is None else _undulation(model, ll[:, :2], geographic)
    ell = ellipsoid_of(hcrs)
    centres = geocentric_from_blh_formula(np.column_stack([np.radians(ll[:, 1]), np.radians(ll[:, 0]),
                                                           ll[:, 2] + n_st]), ell)
    s_img = np.array([index[m] for m in ip.images], dtype=np.int64)
    dirs = ecef_directions(ip.photo_mm, st.focal_mm[s_img], st.attitude_rad[s_img], ll[s_img, :2])
    sigma = np.where(np.isfinite(ip.sigma_mm), ip.sigma_mm, opts.sigma_mm)
    res = intersect_rays(centres[s_img], dirs, pidx, sigma, st.focal_mm[s_img], len(uid))
    # back: geocentric -> B, L, h (seed 001, iterated) -> H = h - N -> map
    blh = blh_from_geocentric_formula(res.points, ell)
    lonlat = np.column_stack([np.degrees(blh[:, 1]), np.degrees(blh[:, 0])])
    n_pt = np.zeros(len(lonlat)) if model is None else _undulation(model, lonlat, geographic)
    xyz = map_from_geodetic(np.column_stack([lonlat, blh[:, 2] - n_pt]), hcrs)
    std = np.empty((len(uid), 3))
    for j in range(len(uid)):
        R = grid_from_enu(hcrs, float(lonlat[j, 0]), float(lonlat[j, 1])) @ enu_rotation(float(lonlat[j, 0]),
                                                                                           float(lonlat[j, 1]))
        std[j] = np.sqrt(np.clip(np.diag(R @ res.covariance[j] @ R.T), 0.0, None))
    label = crs_to_string(hc)
    heights = ("ellipsoidal (no model)" if model is None else f"normal / orthometric, model {model} (h = H + N; "
               f"N {n_pt.min():.3f} .. {n_pt.max():.3f} m at the points)")
    text = sat_points_text(uid, xyz, std, res.n_rays, res.rms_mm, np.column_stack([lonlat, blh[:, 2]]), n_pt,
                           crs=label)
    with ws.transaction():
        ws.write_text(output, text)
    return SatIntersectResult(uid, xyz, std, res.n_rays, res.rms_mm, res.sigma0, res.redundancy, len(st.images),
                              label, heights, Path(output))
