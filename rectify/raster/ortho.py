"""Orthorectification with a DEM: frame cameras and RPC images, true orthophotos.

For every output pixel (a north-up grid in any CRS) the ground height comes
from the DEM (any CRS and resolution, bilinear, resampled on the fly through
:class:`rectify.raster.dem.Dem`), the ground point (x, y, h) is projected into the
image by the sensor model, and the image is resampled there (OpenCV remap on
the source window the tile needs). The horizontal CRS changes (output ->
model, output -> DEM) are smooth and are evaluated exactly on a sparse grid
(every ``map_step_px`` pixels) and interpolated bilinearly; heights and the
sensor projection are evaluated exactly at every output pixel.

True orthophoto (``true_ortho=True``): each ground point is tested for
visibility by marching along its line of sight towards the sensor over the
DEM (half-pixel steps, up to the highest DEM point of the tile's
neighbourhood); a point hidden by higher ground (a wall, a building, a ridge)
gets nodata instead of the occluder's pixels (no ghost image), and an extra
last band records the visibility: 0 outside the image, 1 occluded, 2 visible.

Output: tiled, compressed GeoTIFF (COG with ``cog=True``), written tile by
tile from a thread pool (bounded memory: at most ``2 x threads + 1`` tiles in
flight) to a temporary file renamed at the end. Nodata outside the image:
the source nodata, else 0 for integer rasters and NaN for float ones (valid
pixels equal to 0 in integer outputs are raised to 1 so they stay valid).

Sensor models (:class:`FrameModel`, :class:`RPCModel`) share one small
interface: ``crs`` (the ground CRS of the model), ``width``/``height`` (image
size), ``project(ground (N, 3)) -> pixels (N, 2)`` (NaN where it cannot),
``ground_at_height(pixels, h) -> (N, 3)`` and ``nadir`` (the ground point under
the sensor, or the image centre for RPCs, in ``crs``).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError, RasterIOError, ShapeError
from rectify.geometry.camera import Camera
from rectify.raster.dem import Dem, bilinear
from rectify.raster.distributed import Scheduler, resolve_scheduler, run_windows
from rectify.raster.georef import Grid
from rectify.raster.io import bound_gdal_cache
from rectify.raster.warp import ProcessLocal, worker_count

__all__ = ["SensorModel", "FrameModel", "RPCModel", "OrthoOptions", "OrthoResult", "orthorectify",
           "read_exterior", "ortho_grid", "VISIBILITY_OUTSIDE", "VISIBILITY_OCCLUDED", "VISIBILITY_VISIBLE"]

logger = logging.getLogger(__name__)

VISIBILITY_OUTSIDE, VISIBILITY_OCCLUDED, VISIBILITY_VISIBLE = 0, 1, 2


class SensorModel(Protocol):
    @property
    def crs(self) -> str: ...

    @property
    def width(self) -> int: ...

    @property
    def height(self) -> int: ...

    def project(self, ground: NDArray[np.float64]) -> NDArray[np.float64]: ...

    def ground_at_height(self, pixels: NDArray[np.float64], h: NDArray[np.float64] | float
                         ) -> NDArray[np.float64]: ...

    @property
    def nadir(self) -> NDArray[np.float64]: ...


# =========================================================================== models
def read_exterior(path: str | Path) -> dict[str, Any]:
    """Read the fields the orthorectifier needs from an exterior orientation JSON (``stereo resect``).

    Returns ``{"position": (3,), "rotation": (3, 3), "crs": str | None}``. The
    rotation is ``rotation`` (photo vector -> ground) or is built from
    ``angles`` (radians, ``system`` default omega-phi-kappa).

    Raises
    ------
    RasterIOError, InvalidInputError
        Missing file, bad JSON, missing or bad keys (named).
    """
    from rectify.atomic import read_json
    from rectify.geometry.rotation import check_rotation, matrix_from_angles

    d = read_json(path, "exterior orientation file")
    if not isinstance(d, dict):
        raise InvalidInputError(f"exterior orientation {str(path)!r} must be a JSON object")
    if "position" not in d:
        raise InvalidInputError(f"exterior orientation {str(path)!r} lacks 'position'")
    pos = np.asarray(d["position"], dtype=np.float64).reshape(-1)
    if pos.shape != (3,) or not np.isfinite(pos).all():
        raise InvalidInputError(f"exterior orientation {str(path)!r}: 'position' must be 3 finite numbers; "
                                f"got {d['position']!r}")
    if "rotation" in d:
        R = check_rotation(d["rotation"], "rotation")
    elif isinstance(d.get("angles"), dict):
        a = d["angles"]
        try:
            R = matrix_from_angles(float(a["omega"]), float(a["phi"]), float(a["kappa"]),
                                   a.get("system", "omega-phi-kappa"))
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"exterior orientation {str(path)!r}: bad 'angles': {err}") from None
    else:
        raise InvalidInputError(f"exterior orientation {str(path)!r} lacks 'rotation' (or 'angles')")
    crs = d.get("crs")
    return {"position": pos, "rotation": np.asarray(R, dtype=np.float64), "crs": crs}


@dataclass(frozen=True, eq=False)
class FrameModel:
    """A frame camera: interior orientation + exterior orientation in a ground CRS.

    Attributes
    ----------
    camera : Camera
    position : (3,) projection centre (X, Y, Z) in ``crs`` units (heights in metres)
    rotation : (3, 3) photo vector (x, y, -f) -> ground frame
    crs : str
        The ground CRS (a projected CRS; heights as the DEM's after datum correction).
    """

    camera: Camera
    position: NDArray[np.float64]
    rotation: NDArray[np.float64]
    crs: str

    def __post_init__(self) -> None:
        from rectify.geometry.crs import crs_to_string
        from rectify.geometry.rotation import check_rotation

        pos = np.array(self.position, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.isfinite(pos).all():
            raise ShapeError(f"`position` must be 3 finite numbers; got {np.asarray(self.position).tolist()}")
        R = check_rotation(self.rotation, "rotation")
        if self.crs is None:
            raise CRSError("a frame model needs the CRS of its exterior orientation (--eo-crs or 'crs' in the JSON)")
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "crs", crs_to_string(self.crs))

    @classmethod
    def from_files(cls, camera_json: str | Path, exterior_json: str | Path, *, crs: str | None = None) -> FrameModel:
        """Camera JSON + exterior orientation JSON (``crs`` overrides the EO file's)."""
        cam = Camera.from_json(camera_json)
        eo = read_exterior(exterior_json)
        c = crs or eo["crs"]
        if c is None:
            raise CRSError(f"exterior orientation {str(exterior_json)!r} has no 'crs'; pass the CRS of its "
                           f"coordinates")
        return cls(cam, eo["position"], eo["rotation"], c)

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    @property
    def nadir(self) -> NDArray[np.float64]:
        return self.position[:2].copy()

    def project(self, ground: NDArray[np.float64]) -> NDArray[np.float64]:
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        p = (g - self.position) @ self.rotation  # R^T (P - C), row-wise
        f = self.camera.focal_length_mm
        out = np.full((len(g), 2), np.nan)
        ok = np.isfinite(p).all(axis=1) & (p[:, 2] < 0)  # in front of the camera
        if ok.any():
            mm = np.column_stack([-f * p[ok, 0] / p[ok, 2], -f * p[ok, 1] / p[ok, 2]])
            out[ok] = self.camera.pixel_from_photo(mm)
        return out

    def ground_at_height(self, pixels: NDArray[np.float64], h: NDArray[np.float64] | float) -> NDArray[np.float64]:
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        hh = np.broadcast_to(np.asarray(h, dtype=np.float64), (len(px),))
        rays = self.camera.rays_from_pixel(px) @ self.rotation.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (hh - self.position[2]) / rays[:, 2]
        out = self.position + t[:, None] * rays
        out[:, 2] = hh
        out[~(t > 0)] = np.nan
        return out


@dataclass(frozen=True, eq=False)
class RPCModel:
    """An RPC (or refined RPC) image: ground (lon, lat, ellipsoidal h) on WGS 84 -> pixels."""

    rpc: Any  # rectify.geometry.rpc.RPC or RPCRefinement
    width: int
    height: int
    crs: str = "EPSG:4326"

    def project(self, ground: NDArray[np.float64]) -> NDArray[np.float64]:
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        return self.rpc._project(g)

    def ground_at_height(self, pixels: NDArray[np.float64], h: NDArray[np.float64] | float) -> NDArray[np.float64]:
        return self.rpc.localize(pixels, h, on_failure="nan")

    @property
    def nadir(self) -> NDArray[np.float64]:
        """The image centre at the model's mean height (an RPC has no nadir point)."""
        c = np.array([[(self.width - 1) / 2.0, (self.height - 1) / 2.0]])
        return self.rpc.localize(c, self.rpc.validity_box[2][0] / 2 + self.rpc.validity_box[2][1] / 2)[0, :2]


# =========================================================================== options / result
@dataclass(frozen=True)
class OrthoOptions:
    """Options of :func:`orthorectify`.

    Attributes
    ----------
    resampling : ``nearest``, ``bilinear`` or ``cubic``
    tile_px : output tile and block size (multiple of 16)
    threads : worker threads (None: all cores)
    compress : GeoTIFF compression
    cog : write a Cloud Optimized GeoTIFF
    true_ortho : z-buffer (line-of-sight) visibility and the visibility band
    map_step_px : spacing of the exactly transformed points for CRS changes
    max_window_px : largest source window read for one tile (bigger tiles are split)
    scheduler : where the tiles run: ``threads``, ``processes[:N]`` or ``tcp://HOST:PORT``; None:
        ``$RECTIFY_SCHEDULER``, else ``threads`` (:mod:`rectify.raster.distributed`; same output bytes on every one)
    """

    resampling: str = "bilinear"
    tile_px: int = 512
    threads: int | None = None
    compress: str = "zstd"
    cog: bool = False
    true_ortho: bool = False
    map_step_px: int = 16
    max_window_px: int = 8192
    scheduler: Scheduler | str | None = None

    def __post_init__(self) -> None:
        if self.scheduler is not None:
            resolve_scheduler(self.scheduler)  # a bad value fails here, before any work
        if self.resampling not in ("nearest", "bilinear", "cubic"):
            raise InvalidInputError(f"unknown resampling {self.resampling!r}; expected nearest, bilinear or cubic")
        if self.tile_px < 16 or self.tile_px % 16 or self.tile_px > 4096:
            raise InvalidInputError(f"tile_px must be a multiple of 16 in 16..4096; got {self.tile_px}")
        if self.threads is not None and self.threads < 1:
            raise InvalidInputError(f"threads must be >= 1; got {self.threads}")
        if self.map_step_px < 1:
            raise InvalidInputError(f"map_step_px must be >= 1; got {self.map_step_px}")

    @property
    def n_threads(self) -> int:
        return worker_count(self.threads)


@dataclass(frozen=True)
class OrthoResult:
    """What :func:`orthorectify` wrote.

    Attributes
    ----------
    path, grid, seconds
    n_tiles, n_empty_tiles : int
    dem_path : str
    dem_range : (float, float)
        Lowest and highest ellipsoidal/model heights met on the output grid.
    max_relief_shift : float
        Largest horizontal displacement (output CRS units) a planar
        rectification at the mean height would have made: the height-induced
        shift the DEM removed.
    n_occluded : int
        Output pixels found hidden (true ortho).
    nodata : float
    model : str
    """

    path: Path
    grid: Grid
    seconds: float
    n_tiles: int
    n_empty_tiles: int
    dem_path: str
    dem_range: tuple[float, float]
    max_relief_shift: float
    n_occluded: int
    nodata: float
    model: str
    extra: dict[str, Any] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        from rectify.geometry.crs import unit_label

        g = self.grid
        u = unit_label(g.crs)
        out = [f"wrote {self.path}: {g.width} x {g.height} px, {g.resolution[0]:.6g} {u}/px, CRS {crs_label(g.crs)}, "
               f"{self.model}, {self.seconds:.2f} s",
               f"DEM {self.dem_path}: heights {self.dem_range[0]:.2f} .. {self.dem_range[1]:.2f} m on the output; "
               f"relief displacement removed up to {self.max_relief_shift:.2f} {u}"]
        if self.extra.get("true_ortho"):
            out.append(f"true ortho: {self.n_occluded} occluded pixels set to nodata (visibility band "
                       f"{self.extra.get('visibility_band')}: 0 outside, 1 occluded, 2 visible)")
        return out


def crs_label(crs: str | None) -> str:
    """A short CRS name for messages: ``EPSG:n``, else the PROJ string."""
    import warnings

    from rectify.geometry.crs import parse_crs

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


# =========================================================================== grids
def _utm_for(lon: float, lat: float) -> str:
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return f"EPSG:{32600 + zone if lat >= 0 else 32700 + zone}"


def ortho_grid(model: SensorModel, dem: Dem, *, dst_crs: str | None = None, resolution: float | None = None,
               max_pixels: float = 4e10) -> Grid:
    """The north-up output grid covering the image footprint between the DEM's lowest and highest heights.

    Default CRS: the model's for frame cameras, the UTM zone of the image
    centre for RPC images. Default resolution: the ground distance of the
    image diagonal over its length in pixels (GDAL's suggestion), at the mean
    height. Bounds are aligned to multiples of the resolution.
    """
    from affine import Affine

    from rectify.geometry.crs import crs_to_string, transform_xy
    from rectify.raster.georef import boundary_pixels

    hmin, hmax = dem.range()
    edge = boundary_pixels(model.width, model.height, 33)
    pts = []
    for h in (hmin, 0.5 * (hmin + hmax), hmax):
        g = model.ground_at_height(edge, h)
        pts.append(g[np.isfinite(g).all(axis=1), :2])
    world = np.vstack(pts)
    if len(world) < 3:
        raise InvalidInputError("the image footprint does not reach the ground at the DEM's heights "
                                f"({hmin:.1f} .. {hmax:.1f} m): check the orientation and the DEM")
    if dst_crs is None:
        if model.crs in ("EPSG:4326", "EPSG:4979"):
            c = world.mean(axis=0)
            dst_crs = _utm_for(float(c[0]), float(c[1]))
        else:
            dst_crs = model.crs
    dst = crs_to_string(dst_crs)
    w = transform_xy(model.crs, dst, world)
    if resolution is None:
        hm = 0.5 * (hmin + hmax)
        d = model.ground_at_height(np.array([[-0.5, -0.5], [model.width - 0.5, model.height - 0.5]]), hm)
        if not np.isfinite(d).all():
            raise InvalidInputError("cannot estimate an output resolution; pass one")
        dd = transform_xy(model.crs, dst, d[:, :2])
        resolution = float(np.hypot(*(dd[1] - dd[0]))) / math.hypot(model.width, model.height)
    res = float(resolution)
    if not math.isfinite(res) or res <= 0:
        raise InvalidInputError(f"resolution must be a positive number; got {resolution!r}")
    eps = 1e-9
    x0 = math.floor(w[:, 0].min() / res + eps) * res
    y0 = math.floor(w[:, 1].min() / res + eps) * res
    x1 = math.ceil(w[:, 0].max() / res - eps) * res
    y1 = math.ceil(w[:, 1].max() / res - eps) * res
    nx, ny = max(1, int(round((x1 - x0) / res))), max(1, int(round((y1 - y0) / res)))
    if float(nx) * float(ny) > max_pixels:
        raise InvalidInputError(f"output grid of {nx} x {ny} pixels at resolution {res!r} is too large; "
                                f"pass a coarser --resolution")
    return Grid(nx, ny, Affine(res, 0.0, x0, 0.0, -res, y1), dst)


# =========================================================================== tile engine
def _gt(transform: Any) -> tuple[float, ...]:
    """The six geotransform numbers (a, b, c, d, e, f) of a rasterio Affine."""
    return tuple(float(v) for v in tuple(transform)[:6])


def _interp_index(n: int, knots: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Left knot index and weight of 0..n-1 for linear interpolation between ``knots`` (ascending)."""
    x = np.arange(n, dtype=np.float64)
    k = len(knots)
    if k == 1:
        return np.zeros(n, np.intp), np.zeros(n)
    i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, k - 2)
    return i.astype(np.intp), (x - knots[i]) / (knots[i + 1] - knots[i])


def _densify(vals: NDArray[np.float64], kc: NDArray[np.float64], kr: NDArray[np.float64], w: int, h: int
             ) -> NDArray[np.float64]:
    """Bilinear interpolation of (nr, nc, ...) values at the knots to (h, w, ...)."""
    ir, tr = _interp_index(h, kr)
    ic, tc = _interp_index(w, kc)
    if len(kr) == 1:
        rows = np.repeat(vals[:1], h, axis=0)
    else:
        sh = (-1,) + (1,) * (vals.ndim - 1)
        rows = vals[ir] * (1 - tr).reshape(sh) + vals[ir + 1] * tr.reshape(sh)
    if len(kc) == 1:
        return np.repeat(rows[:, :1], w, axis=1)
    sh2 = (1, -1) + (1,) * (vals.ndim - 2)
    return rows[:, ic] * (1 - tc).reshape(sh2) + rows[:, ic + 1] * tc.reshape(sh2)


PROJECTION_TOLERANCE_PX = 1e-3
_NODES = np.array([0.0, 1 / 3, 2 / 3, 1.0])
#: power-basis coefficients from values at the 4 nodes: coef = _VANDER_INV @ values
_VANDER_INV = np.linalg.inv(np.vander(_NODES, 4, increasing=True))


def _lagrange4(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cubic Lagrange weights (N, 4) for nodes 0, 1/3, 2/3, 1 at t (N,)."""
    n = np.array([0.0, 1 / 3, 2 / 3, 1.0])
    out = np.ones((len(t), 4))
    for k in range(4):
        for j in range(4):
            if j != k:
                out[:, k] *= (t - n[j]) / (n[k] - n[j])
    return out


def _knots(n: int, step: int) -> NDArray[np.float64]:
    k = np.arange(0, n, step, dtype=np.float64)
    if k[-1] != n - 1:
        k = np.append(k, n - 1)
    return k


class _Engine(ProcessLocal):
    def __init__(self, src: str, model: SensorModel, dem: Dem, grid: Grid, opts: OrthoOptions, dtype: np.dtype,
                 count: int, nodata: float, margin_px: int, h_ref: float):
        import cv2

        self.src, self.model, self.dem, self.grid, self.opts = src, model, dem, grid, opts
        self.dtype, self.count, self.nodata = dtype, count, nodata
        self.margin = int(margin_px)
        self.h_ref = h_ref
        self.interp = {"nearest": cv2.INTER_NEAREST, "bilinear": cv2.INTER_LINEAR,
                       "cubic": cv2.INTER_CUBIC}[opts.resampling]
        self._local = threading.local()
        self._readers: list = []
        self._lock = threading.Lock()
        self.stats_lock = threading.Lock()
        self.hmin, self.hmax, self.max_shift, self.n_occluded = math.inf, -math.inf, 0.0, 0
        from rectify.geometry.crs import same_crs

        self.same_model = same_crs(grid.crs, model.crs)
        self.same_dem = same_crs(grid.crs, dem.crs)

    # ---------------------------------------------------------------- shipping to Dask workers
    _TRANSIENT = {"_local": threading.local, "_readers": list, "_lock": threading.Lock,
                  "stats_lock": threading.Lock}

    def portable(self) -> _Engine:
        """A copy for Dask workers: image and DEM by absolute path, no open readers, statistics reset."""
        import copy
        import dataclasses
        import os

        eng = copy.copy(self)
        eng.src = os.path.abspath(self.src)
        eng.dem = dataclasses.replace(self.dem, path=os.path.abspath(self.dem.path))
        eng.hmin, eng.hmax, eng.max_shift, eng.n_occluded = math.inf, -math.inf, 0.0, 0
        return eng

    def stats(self) -> tuple[float, float, float, int]:
        """Heights met, largest relief shift and occluded pixels of the tiles this engine computed."""
        return self.hmin, self.hmax, self.max_shift, self.n_occluded

    def merge_stats(self, stats: tuple[float, float, float, int]) -> None:
        """Add another copy's :meth:`stats` (a Dask task's) to this engine's."""
        lo, hi, shift, occluded = stats
        with self.stats_lock:
            self.hmin, self.hmax = min(self.hmin, lo), max(self.hmax, hi)
            self.max_shift = max(self.max_shift, shift)
            self.n_occluded += int(occluded)

    def reader(self):
        r = getattr(self._local, "reader", None)
        if r is None:
            from rectify.raster.io import WindowReader

            r = WindowReader(self.src)
            self._local.reader = r
            with self._lock:
                self._readers.append(r)
        return r

    def close(self) -> None:
        for r in self._readers:
            r.close()

    # ---------------------------------------------------------------- geometry of a block
    def _world(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray]:
        t = _gt(self.grid.transform)
        xs = t[2] + t[0] * (np.arange(c0, c0 + w) + 0.5)
        ys = t[5] + t[4] * (np.arange(r0, r0 + h) + 0.5)
        return np.broadcast_to(xs, (h, w)), np.broadcast_to(ys[:, None], (h, w))

    def _sparse(self, c0: int, r0: int, w: int, h: int, fn: Callable[[NDArray], NDArray], dim: int,
                step: int | None = None) -> NDArray:
        """fn evaluated on a sparse grid of the block's world points, interpolated to (h, w, dim)."""
        step = step or self.opts.map_step_px
        kc, kr = _knots(w, step), _knots(h, step)
        t = _gt(self.grid.transform)
        X = t[2] + t[0] * (c0 + kc + 0.5)
        Y = t[5] + t[4] * (r0 + kr + 0.5)
        XX, YY = np.meshgrid(X, Y)
        vals = np.asarray(fn(np.column_stack([XX.ravel(), YY.ravel()])), dtype=np.float64)
        vals = vals.reshape(len(kr), len(kc), dim)
        return _densify(vals, kc, kr, w, h)

    def _heights(self, c0: int, r0: int, w: int, h: int) -> NDArray[np.float64]:
        from rectify.geometry.crs import transform_xy
        from rectify.raster.georef import pixel_from_world_matrix

        M = pixel_from_world_matrix(self.dem.transform)
        if self.same_dem:
            X, Y = self._world(c0, r0, w, h)
            dx = M[0, 0] * X + M[0, 1] * Y + M[0, 2]
            dy = M[1, 0] * X + M[1, 1] * Y + M[1, 2]
        else:
            def to_dem_px(p):
                q = transform_xy(self.grid.crs, self.dem.crs, p)
                return q @ M[:2, :2].T + M[:2, 2]
            d = self._sparse(c0, r0, w, h, to_dem_px, 2)
            dx, dy = d[..., 0], d[..., 1]
        z = self.dem.heights_at_dem_pixels(dx, dy) + self.dem.undulation
        if self.dem.geoid is not None:
            from rectify.raster.dem import geoid_undulation

            z = z + self._sparse(c0, r0, w, h, lambda p: geoid_undulation(
                transform_xy(self.grid.crs, "EPSG:4326", p), self.dem.geoid or "")[:, None], 1)[..., 0]
        return z

    def _model_xy(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray]:
        from rectify.geometry.crs import transform_xy

        if self.same_model:
            return self._world(c0, r0, w, h)
        m = self._sparse(c0, r0, w, h, lambda p: transform_xy(self.grid.crs, self.model.crs, p), 2)
        return m[..., 0], m[..., 1]

    def _direction(self, c0: int, r0: int, w: int, h: int, hz: float, step: int | None = None
                   ) -> NDArray[np.float64]:
        """Horizontal displacement towards the sensor per metre of height, in output pixels (h, w, 2) (col, row)."""
        from rectify.geometry.crs import transform_xy

        t = _gt(self.grid.transform)
        dz = 10.0

        def fn(p):
            g0 = transform_xy(self.grid.crs, self.model.crs, p) if not self.same_model else p
            pix = self.model.project(np.column_stack([g0, np.full(len(g0), hz)]))
            out = np.zeros((len(p), 2))
            ok = np.isfinite(pix).all(axis=1)
            if ok.any():
                g1 = self.model.ground_at_height(pix[ok], hz + dz)
                ok2 = np.isfinite(g1).all(axis=1)
                w1 = np.full((ok.sum(), 2), np.nan)
                if ok2.any():
                    w1[ok2] = transform_xy(self.model.crs, self.grid.crs, g1[ok2, :2]) if not self.same_model \
                        else g1[ok2, :2]
                d = (w1 - p[ok]) / dz
                out[ok] = np.where(np.isfinite(d), d, 0.0)
            return np.column_stack([out[:, 0] / t[0], out[:, 1] / t[4]])
        return self._sparse(c0, r0, w, h, fn, 2, step)

    def _project(self, c0: int, r0: int, w: int, h: int, z: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Image (col, row) of every output pixel at its DEM height, (h, w) each; NaN where unknown.

        The projection is evaluated exactly on the sparse grid at 4 heights spanning the tile's heights
        and interpolated (bilinear in x, y; cubic Lagrange in h). The interpolation is checked against
        the exact projection at the sparse cells' centres and intermediate heights; when it is off by
        more than ``PROJECTION_TOLERANCE_PX`` the tile is projected exactly, pixel by pixel.
        """
        fin = np.isfinite(z)
        col = np.full((h, w), np.nan)
        row = np.full((h, w), np.nan)
        if not fin.any():
            return col, row
        zlo, zhi = float(z[fin].min()), float(z[fin].max())
        step = self.opts.map_step_px
        kc, kr = _knots(w, step), _knots(h, step)
        t = _gt(self.grid.transform)
        XX, YY = np.meshgrid(t[2] + t[0] * (c0 + kc + 0.5), t[5] + t[4] * (r0 + kr + 0.5))
        # cell centres, for the check
        xc = 0.5 * (kc[:-1] + kc[1:]) if len(kc) > 1 else kc
        yc = 0.5 * (kr[:-1] + kr[1:]) if len(kr) > 1 else kr
        XC, YC = np.meshgrid(t[2] + t[0] * (c0 + xc + 0.5), t[5] + t[4] * (r0 + yc + 0.5))
        pts = np.column_stack([np.concatenate([XX.ravel(), XC.ravel()]), np.concatenate([YY.ravel(), YC.ravel()])])
        if not self.same_model:
            from rectify.geometry.crs import transform_xy

            pts = transform_xy(self.grid.crs, self.model.crs, pts)
        n_knot = XX.size
        span = zhi - zlo
        K = 1 if span < 1e-9 else 4
        hk = np.linspace(zlo, zhi, K) if K > 1 else np.array([zlo])
        vals = np.empty((len(kr), len(kc), K, 2))
        for k, hv in enumerate(hk):
            vals[:, :, k] = self.model.project(np.column_stack([pts[:n_knot], np.full(n_knot, hv)])
                                               ).reshape(len(kr), len(kc), 2)
        exact = not np.isfinite(vals).all()
        if not exact and len(kc) > 1 and len(kr) > 1:
            # check at the cell centres and at heights between the nodes
            tq = np.array([1 / 6, 1 / 2, 5 / 6])[np.arange(XC.size) % 3] if K > 1 else np.zeros(XC.size)
            centre = 0.25 * (vals[:-1, :-1] + vals[1:, :-1] + vals[:-1, 1:] + vals[1:, 1:]).reshape(-1, K, 2)
            est = np.einsum("nk,nkc->nc", _lagrange4(tq), centre) if K > 1 else centre[:, 0]
            ex = self.model.project(np.column_stack([pts[n_knot:], zlo + tq * span]))
            err = np.abs(est - ex).max() if np.isfinite(ex).all() else np.inf
            exact = not (err <= PROJECTION_TOLERANCE_PX)
        if exact:
            mx, my = self._model_xy(c0, r0, w, h)
            g = np.column_stack([mx.ravel(), my.ravel(), z.ravel()])
            okz = fin.ravel()
            pix = np.full((len(g), 2), np.nan)
            pix[okz] = self.model.project(g[okz])
            return pix[:, 0].reshape(h, w), pix[:, 1].reshape(h, w)
        ir, tr = _interp_index(h, kr)
        ic, tc = _interp_index(w, kc)

        def plane(v: NDArray[np.float64]) -> NDArray[np.float64]:
            """One (nr, nc) plane bilinearly to (h, w)."""
            r = v[ir] * (1 - tr)[:, None] + v[np.minimum(ir + 1, len(kr) - 1)] * tr[:, None]
            return r[:, ic] * (1 - tc) + r[:, np.minimum(ic + 1, len(kc) - 1)] * tc

        res = np.empty((h, w, 2))
        if K == 1:
            for c in range(2):
                res[..., c] = plane(vals[:, :, 0, c])
        else:
            # cubic in t = (z - zlo) / span through the 4 nodes: coefficients per sparse point, Horner per pixel
            coef = np.einsum("jk,rskc->rsjc", _VANDER_INV, vals)
            tz = np.where(fin, (z - zlo) / span, 0.0)
            for c in range(2):
                acc = plane(coef[:, :, 3, c])
                for j in (2, 1, 0):
                    acc *= tz
                    acc += plane(coef[:, :, j, c])
                res[..., c] = acc
        res[~fin] = np.nan
        return res[..., 0], res[..., 1]

    # ---------------------------------------------------------------- one tile
    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, bool]:
        m = self.margin if self.opts.true_ortho else 0
        # the block with a margin (for the line-of-sight test), clipped to nothing: heights outside the grid exist
        bc0, br0, bw, bh = c0 - m, r0 - m, w + 2 * m, h + 2 * m
        Z = self._heights(bc0, br0, bw, bh)
        z = Z[m:m + h, m:m + w]
        col, row = self._project(c0, r0, w, h, z)
        W, H = self.model.width, self.model.height
        inside = np.isfinite(col) & np.isfinite(row) & (col >= -0.5) & (col <= W - 0.5) & (row >= -0.5) \
            & (row <= H - 0.5)
        vis = None
        d = None
        if inside.any():
            d = self._direction(c0, r0, w, h, float(np.nanmean(z[inside])),
                                None if self.opts.true_ortho else 8 * self.opts.map_step_px)
            self._stats(z[inside], d)
        if self.opts.true_ortho and d is not None:
            vis = self._visible(Z, m, d, w, h, z, inside)
        out_bands = self.count + (1 if self.opts.true_ortho else 0)
        out = np.full((h, w, out_bands), self.nodata, dtype=self.dtype)
        if self.opts.true_ortho:
            out[..., -1] = VISIBILITY_OUTSIDE
        if not inside.any():
            return out, True
        use = inside if vis is None else (inside & vis)
        if self.opts.true_ortho:
            out[..., -1] = np.where(inside, np.where(use, VISIBILITY_VISIBLE, VISIBILITY_OCCLUDED), VISIBILITY_OUTSIDE)
            with self.stats_lock:
                self.n_occluded += int((inside & ~use).sum())
        if use.any():
            data = self._resample(col, row, use, h, w)
            if data is not None:
                img, valid = data
                sel = use & valid
                band = out[..., :self.count]
                band[sel] = img[sel]
        return out, False

    def _stats(self, zin: NDArray, d: NDArray) -> None:
        if not len(zin):
            return
        lo, hi = float(np.nanmin(zin)), float(np.nanmax(zin))
        # relief displacement a planar rectification at h_ref would leave: |d| * |h - h_ref|
        mag = float(np.nanmax(np.hypot(d[..., 0], d[..., 1]))) * self.grid.resolution[0]
        sh = mag * max(abs(hi - self.h_ref), abs(lo - self.h_ref))
        with self.stats_lock:
            self.hmin, self.hmax = min(self.hmin, lo), max(self.hmax, hi)
            self.max_shift = max(self.max_shift, sh)

    def _visible(self, Z: NDArray, m: int, d: NDArray, w: int, h: int, z: NDArray,
                 inside: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Line-of-sight test over the DEM block ``Z`` (with margin ``m``): True where nothing hides the point.

        ``d`` (h, w, 2): output pixels per metre of height towards the sensor.
        """
        zmax = float(np.nanmax(Z))
        ddist = np.hypot(d[..., 0], d[..., 1])
        vis = np.ones((h, w), bool)
        cand = inside & (ddist > 1e-12) & np.isfinite(z)
        step = 0.5  # px
        rows, cols = np.nonzero(cand)
        if not len(rows):
            return vis
        dx, dy, dd = d[rows, cols, 0], d[rows, cols, 1], ddist[rows, cols]
        z0 = z[rows, cols]
        ux, uy = dx / dd, dy / dd
        px0, py0 = cols + m + 0.0, rows + m + 0.0
        occl = np.zeros(len(rows), bool)
        active = np.ones(len(rows), bool)
        Zf = np.where(np.isfinite(Z), Z, -np.inf)
        k = 1
        while active.any():
            a = np.flatnonzero(active)
            s = k * step
            ray_h = z0[a] + s / dd[a]
            x = px0[a] + s * ux[a]
            y = py0[a] + s * uy[a]
            inb = (x >= 0) & (y >= 0) & (x <= Z.shape[1] - 1) & (y <= Z.shape[0] - 1)
            ter = np.full(len(a), -np.inf)
            if inb.any():
                ter[inb] = bilinear(Zf, None, x[inb], y[inb])
            hit = ter > ray_h + 1e-3
            occl[a[hit]] = True
            stop = hit | ~inb | (ray_h > zmax)
            active[a[stop]] = False
            k += 1
            if k > 100000:
                break
        vis[rows, cols] = ~occl
        return vis

    def _resample(self, col: NDArray, row: NDArray, use: NDArray[np.bool_], h: int, w: int):
        import cv2

        W, H = self.model.width, self.model.height
        pad = 3
        c_lo = max(int(math.floor(np.min(col[use]))) - pad, 0)
        r_lo = max(int(math.floor(np.min(row[use]))) - pad, 0)
        c_hi = min(int(math.ceil(np.max(col[use]))) + pad + 1, W)
        r_hi = min(int(math.ceil(np.max(row[use]))) + pad + 1, H)
        if c_hi <= c_lo or r_hi <= r_lo:
            return None
        if c_hi - c_lo > self.opts.max_window_px or r_hi - r_lo > self.opts.max_window_px:
            if h <= 16 and w <= 16:
                raise InvalidInputError(f"the source window for one output tile exceeds {self.opts.max_window_px} px;"
                                        f" use a finer output resolution")
            # split the tile in four
            img = np.zeros((h, w, self.count), dtype=np.float64)
            valid = np.zeros((h, w), bool)
            hh, ww = max(h // 2, 1), max(w // 2, 1)
            for rs, re_ in ((0, hh), (hh, h)):
                for cs, ce in ((0, ww), (ww, w)):
                    if re_ <= rs or ce <= cs:
                        continue
                    u = use[rs:re_, cs:ce]
                    if not u.any():
                        continue
                    sub = self._resample(col[rs:re_, cs:ce], row[rs:re_, cs:ce], u, re_ - rs, ce - cs)
                    if sub is not None:
                        img[rs:re_, cs:ce] = sub[0]
                        valid[rs:re_, cs:ce] = sub[1]
            return img, valid
        data, vmask = self.reader().read(c_lo, r_lo, c_hi - c_lo, r_hi - r_lo)
        mx = np.where(use, col - c_lo, -10.0).astype(np.float32)
        my = np.where(use, row - r_lo, -10.0).astype(np.float32)
        src = data if data.dtype in (np.uint8, np.uint16, np.int16, np.float32) else data.astype(np.float32)
        chans = []
        for k0 in range(0, src.shape[2], 4):
            part = np.ascontiguousarray(src[..., k0:k0 + 4])
            if part.shape[2] == 2:
                r = cv2.remap(np.ascontiguousarray(part[..., :1]), mx, my, self.interp, borderMode=cv2.BORDER_REPLICATE)
                r2 = cv2.remap(np.ascontiguousarray(part[..., 1:]), mx, my, self.interp,
                               borderMode=cv2.BORDER_REPLICATE)
                r = np.dstack([r, r2])
            else:
                r = cv2.remap(part, mx, my, self.interp, borderMode=cv2.BORDER_REPLICATE)
            if r.ndim == 2:
                r = r[..., None]
            chans.append(r)
        img = np.concatenate(chans, axis=2)
        valid = np.ones((h, w), bool)
        if vmask is not None:
            v = cv2.remap(vmask.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
            valid = v > 0
        if self.dtype.kind in "ui":
            ii = np.iinfo(self.dtype)
            img = np.clip(np.rint(img), ii.min, ii.max)
            if self.nodata == 0:
                img = np.where(img == 0, 1, img)
        return img.astype(self.dtype), valid


def _run(engine: Any, writer, windows, threads: int, progress, *, scheduler: Scheduler | str | None = None,
         workdir: str | Path = ".", name: str = "ortho") -> int:
    """Compute the windows with ``engine.tile`` (-> (data, empty)) on the scheduler; write each (the ortho and
    mosaic engines). A raw ``writer`` (:class:`rectify.raster.io.TiledWriter`, Dask schedulers) gets the tiles
    compressed on the workers."""
    def write(res: tuple[Any, bool], c: int, r: int) -> bool:
        data, empty = res
        writer.write(data, c, r)
        return empty

    return run_windows(engine, write, windows, threads=threads, progress=progress, scheduler=scheduler,
                       workdir=workdir, name=name, raw_writer=writer if writer.raw else None)


def _margin_px(model: SensorModel, dem: Dem, grid: Grid, h_range: tuple[float, float]) -> int:
    """Output pixels a line of sight can travel over the DEM's height range (for the true-ortho margin)."""
    from rectify.geometry.crs import transform_xy

    t = _gt(grid.transform)
    cc, rr = np.meshgrid(np.linspace(0, grid.width - 1, 9), np.linspace(0, grid.height - 1, 9))
    X = t[2] + t[0] * (cc.ravel() + 0.5)
    Y = t[5] + t[4] * (rr.ravel() + 0.5)
    g0 = transform_xy(grid.crs, model.crs, np.column_stack([X, Y]))
    lo, hi = h_range
    pix = model.project(np.column_stack([g0, np.full(len(g0), lo)]))
    ok = np.isfinite(pix).all(axis=1)
    if not ok.any():
        return 8
    g1 = model.ground_at_height(pix[ok], hi)
    ok1 = np.isfinite(g1).all(axis=1)
    if not ok1.any():
        return 8
    w1 = transform_xy(model.crs, grid.crs, g1[ok1, :2])
    w0 = np.column_stack([X, Y])[ok][ok1]
    dist = float(np.hypot(*(w1 - w0).T).max()) / grid.resolution[0]
    return int(min(math.ceil(dist * 1.5) + 4, 2048))


def orthorectify(src: str | Path, dst: str | Path, model: SensorModel, dem: Dem, *, grid: Grid | None = None,
                 dst_crs: str | None = None, resolution: float | None = None, options: OrthoOptions | None = None,
                 overwrite: bool = False, progress: Callable[[int, int], None] | None = None) -> OrthoResult:
    """Orthorectify ``src`` through a sensor model and a DEM into the GeoTIFF ``dst``.

    Parameters
    ----------
    src : path
        The image (any band count and dtype rasterio reads). Never modified.
    dst : path
        Output GeoTIFF (tiled; COG with ``options.cog``), written atomically.
    model : FrameModel or RPCModel
    dem : Dem
        Heights in the model's vertical frame (ellipsoidal for RPCs: use
        ``Dem(undulation=...)`` or ``geoid=`` for geoid heights).
    grid : Grid, optional
        Output grid; default :func:`ortho_grid` (``dst_crs``, ``resolution``).
    options : OrthoOptions

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        Unreadable inputs, existing output without ``overwrite``, output equal
        to an input, an image that does not match its model's size.
    """
    from rectify.atomic import atomic_output, check_output
    from rectify.geometry.crs import crs_to_string
    from rectify.raster.io import MaskPolicy, TiledWriter, raster_info, translate_to_cog

    opts = options or OrthoOptions()
    sched = resolve_scheduler(opts.scheduler)
    t0 = time.perf_counter()
    src = str(src)
    for p in (src, dem.path):
        if Path(dst).resolve() == Path(p).resolve():
            raise InvalidInputError(f"output {str(dst)!r} is an input; inputs are never modified")
    check_output(dst, overwrite=overwrite)
    info = raster_info(src)
    if (info.width, info.height) != (model.width, model.height):
        raise InvalidInputError(f"image {src!r} is {info.width} x {info.height} px but its model expects "
                                f"{model.width} x {model.height}")
    if grid is None:
        grid = ortho_grid(model, dem, dst_crs=dst_crs, resolution=resolution)
    elif grid.crs is None:
        raise CRSError("the output grid needs a CRS")
    else:
        grid = Grid(grid.width, grid.height, grid.transform, crs_to_string(grid.crs))
    dtype = np.dtype(info.dtype)
    if info.nodata is not None:
        nodata = float(info.nodata)
    else:
        nodata = float("nan") if dtype.kind == "f" else 0.0
    hr = dem.range()
    h_ref = 0.5 * (hr[0] + hr[1])
    margin = _margin_px(model, dem, grid, hr) if opts.true_ortho else 0
    engine = _Engine(src, model, dem, grid, opts, dtype, info.count, nodata, margin, h_ref)
    tile = opts.tile_px
    windows = [(c, r, min(tile, grid.width - c), min(tile, grid.height - r))
               for r in range(0, grid.height, tile) for c in range(0, grid.width, tile)]
    count = info.count + (1 if opts.true_ortho else 0)
    import rasterio

    n_empty = 0
    try:
        with rasterio.Env(GDAL_CACHEMAX=64 * 1024 * 1024), atomic_output(dst, overwrite=overwrite) as tmp:
            body = tmp.with_name(tmp.name + ".body.tif") if opts.cog else tmp
            try:
                with TiledWriter(body, grid.width, grid.height, count, dtype.name, grid.transform, grid.crs,
                                 MaskPolicy("nodata", nodata), tile=tile,
                                 compress="none" if opts.cog else opts.compress, threads=opts.n_threads,
                                 raw=not sched.is_local_threads) as writer:
                    n_empty = _run(engine, writer, windows, opts.n_threads, progress, scheduler=sched,
                                   workdir=tmp.parent)
                nad = _nadir_in(model, str(grid.crs))
                tags = {"ORTHO_MODEL": type(model).__name__, "ORTHO_DEM": Path(dem.path).name,
                        "ORTHO_NADIR_X": repr(float(nad[0])), "ORTHO_NADIR_Y": repr(float(nad[1]))}
                if opts.true_ortho:
                    tags["ORTHO_VISIBILITY_BAND"] = str(count)
                with rasterio.open(body, "r+") as ds:
                    ds.update_tags(**tags)
                    if opts.true_ortho:
                        ds.set_band_description(count, "visibility: 0 outside, 1 occluded, 2 visible")
                if opts.cog:
                    translate_to_cog(body, tmp, compress=opts.compress, threads=opts.n_threads, tile=tile,
                                     resampling="nearest")
            finally:
                if opts.cog and body.exists():
                    body.unlink()
    except OSError as err:
        if isinstance(err, RasterIOError):
            raise
        raise RasterIOError(f"cannot write {str(dst)!r}: {err}") from err
    finally:
        engine.close()
    dt = time.perf_counter() - t0
    lo = engine.hmin if math.isfinite(engine.hmin) else float("nan")
    hi = engine.hmax if math.isfinite(engine.hmax) else float("nan")
    logger.info("ortho %s -> %s: %d x %d, %d tiles in %.2f s", src, dst, grid.width, grid.height, len(windows), dt)
    return OrthoResult(Path(dst), grid, dt, len(windows), n_empty, dem.path, (lo, hi), engine.max_shift,
                       engine.n_occluded, nodata, type(model).__name__,
                       {"true_ortho": opts.true_ortho, "visibility_band": count if opts.true_ortho else None,
                        "margin_px": margin})


def _nadir_in(model: SensorModel, crs: str) -> NDArray[np.float64]:
    from rectify.geometry.crs import transform_xy

    try:
        return transform_xy(model.crs, crs, np.asarray(model.nadir).reshape(1, 2))[0]
    except Exception:  # noqa: BLE001 - the nadir is metadata only
        return np.array([np.nan, np.nan])


# =========================================================================== one call for the CLI
@dataclass(frozen=True)
class OrthoRun:
    """What :func:`ortho_from_files` did: the ortho, and the GCP residuals when GCPs were given."""

    result: OrthoResult
    residuals: Any = None  # ResidualTable (px) or None
    model_kind: str = ""
    report_files: list[Path] | None = None

    def summary_lines(self) -> list[str]:
        out = []
        if self.residuals is not None:
            out.append(f"{self.residuals.step}: {self.residuals.summary_line()}")
            loo = self.residuals.extra.get("loo_rmse_px")
            raw = self.residuals.extra.get("rpc_only_rmse_px")
            if raw is not None:
                out.append(f"GCP error of the RPC alone: RMSE {raw:.4g} px" +
                           (f"; leave-one-out check RMSE after refinement {loo:.4g} px" if loo is not None else ""))
        out += self.result.summary_lines()
        if self.report_files:
            out.append(f"report: {', '.join(str(p) for p in self.report_files)}")
        return out


def _read_gcps(path: str | Path):
    try:
        from rectify.formats.common import read_gcps
    except ImportError:  # pragma: no cover - before the formats module existed
        from rectify.tables import read_gcps  # type: ignore[no-redef]
    return read_gcps(path)


def _gcp_ground(gcps, dem: Dem, crs: str) -> NDArray[np.float64]:
    """GCP ground points (N, 3) in ``crs``: x, y from the file (its CRS), z from the file or the DEM."""
    from rectify.geometry.crs import transform_xy

    src_crs = gcps.crs or crs
    xy = transform_xy(src_crs, crs, gcps.target) if gcps.crs else np.asarray(gcps.target, dtype=np.float64)
    if gcps.z is not None:
        z = np.asarray(gcps.z, dtype=np.float64) + dem.undulation
    else:
        z = dem.sample(xy, crs)
        if not np.isfinite(z).all():
            i = int(np.flatnonzero(~np.isfinite(z))[0])
            raise InvalidInputError(f"GCP {gcps.ids[i]!r} has no z and lies outside the DEM")
    return np.column_stack([xy, z])


def ortho_from_files(src: str | Path, dst: str | Path, dem_path: str | Path, *, rpc: str | Path | bool = False,
                     camera: str | Path | None = None, exterior: str | Path | None = None,
                     eo_crs: str | None = None, gcps: str | Path | None = None, refinement: str = "shift",
                     dst_crs: str | None = None, resolution: float | None = None, undulation: float = 0.0,
                     geoid: str | None = None, options: OrthoOptions | None = None, overwrite: bool = False,
                     progress: Callable[[int, int], None] | None = None,
                     report_dir: str | Path | None = None) -> OrthoRun:
    """Orthorectify ``src`` with its RPC (``rpc=True``: from the image; a path: an RPC file) or a frame camera.

    With ``gcps`` (any GCP file ``rectify`` reads; z optional, taken from the
    DEM when absent): an RPC is refined (``refinement``: shift, drift,
    affine) and the residual table carries leave-one-out errors; a frame
    camera is only checked (image residuals of the GCPs).

    Raises
    ------
    InvalidInputError
        Neither or both of ``rpc`` and ``camera``/``exterior``, bad files.
    """
    bound_gdal_cache()  # before any pixel IO
    from rectify.geometry.residuals import ResidualTable
    from rectify.raster.io import raster_info

    use_rpc = bool(rpc)
    if use_rpc == (camera is not None or exterior is not None):
        raise InvalidInputError("give either an RPC (--rpc) or a frame camera (--camera and --exterior)")
    if not use_rpc and (camera is None or exterior is None):
        raise InvalidInputError("a frame camera needs both --camera CAM.json and --exterior EO.json")
    for p in (src, dem_path, camera, exterior, gcps, rpc if isinstance(rpc, (str, Path)) else None):
        if p is not None and Path(dst).exists() and Path(p).exists() and Path(dst).resolve() == Path(p).resolve():
            raise InvalidInputError(f"output {str(dst)!r} is an input; inputs are never modified")
    from rectify.atomic import check_output

    check_output(dst, overwrite=overwrite)
    if report_dir is not None:  # fail before the work, not after
        rd = Path(report_dir)
        if rd.exists() and not rd.is_dir():
            raise InvalidInputError(f"report folder {str(rd)!r} is a file")
        if rd.is_dir():
            for name in ("ortho_report.json", "residuals.csv", "relief_shift.tif"):
                check_output(rd / name, overwrite=overwrite)
    dem = Dem.from_path(dem_path, undulation=undulation, geoid=geoid)
    info = raster_info(src)
    table = None
    model: SensorModel
    if use_rpc:
        from rectify.geometry.rpc import RPCRefinement, read_rpc, rpc_from_raster

        r = rpc_from_raster(src) if rpc is True else read_rpc(rpc)  # type: ignore[arg-type]
        model_rpc: Any = r
        if gcps is not None:
            g = _read_gcps(gcps)
            ground = _gcp_ground(g, dem, "EPSG:4326")
            ref = RPCRefinement.from_gcps(r, g.pixel, ground, model=refinement, ids=list(g.ids), check=g.check)
            model_rpc, table = ref, ref.residuals
        model = RPCModel(model_rpc, info.width, info.height)
    else:
        model = FrameModel.from_files(str(camera), str(exterior), crs=eo_crs)
        if gcps is not None:
            g = _read_gcps(gcps)
            ground = _gcp_ground(g, dem, model.crs)
            adj = model.project(ground)
            table = ResidualTable(step="GCP check (frame model)", ids=list(g.ids), observed=g.pixel, adjusted=adj,
                                  units="px", check=np.ones(len(g.ids), bool), position_px=g.pixel)
    result = orthorectify(src, dst, model, dem, dst_crs=dst_crs, resolution=resolution, options=options,
                          overwrite=overwrite, progress=progress)
    run = OrthoRun(result, table, type(model).__name__)
    if report_dir is not None:
        paths = write_ortho_report(report_dir, run, model, dem, overwrite=overwrite)
        run = OrthoRun(result, table, type(model).__name__, paths)
    return run


def relief_shift_map(model: SensorModel, dem: Dem, grid: Grid, *, max_size: int = 256
                     ) -> tuple[NDArray[np.float64], Any]:
    """The horizontal shift (output CRS units) the DEM removed, on a coarse copy of ``grid``.

    ``|d| * |h - h_mean|``: the displacement a planar rectification at the
    mean height would leave, with ``d`` the horizontal shift per metre of
    height. Returns the (rows, cols) array (NaN outside the DEM) and its
    rasterio geotransform.
    """
    from affine import Affine

    scale = max(1.0, max(grid.width, grid.height) / max_size)
    w, h = max(1, int(round(grid.width / scale))), max(1, int(round(grid.height / scale)))
    t = _gt(grid.transform)
    coarse = Grid(w, h, Affine(t[0] * grid.width / w, 0.0, t[2], 0.0, t[4] * grid.height / h, t[5]), grid.crs)
    eng = _Engine(dem.path, model, dem, coarse, OrthoOptions(), np.dtype("float32"), 1, float("nan"), 0, 0.0)
    z = eng._heights(0, 0, w, h)
    h_ref = float(np.nanmean(z)) if np.isfinite(z).any() else 0.0
    d = eng._direction(0, 0, w, h, h_ref, 4)
    shift = np.hypot(d[..., 0], d[..., 1]) * coarse.resolution[0] * np.abs(z - h_ref)
    return shift, coarse.transform


def write_ortho_report(report_dir: str | Path, run: OrthoRun, model: SensorModel, dem: Dem, *,
                       overwrite: bool = False) -> list[Path]:
    """``ortho_report.json`` (summary, DEM, GCP residuals), ``residuals.csv`` and ``relief_shift.tif``.

    Each file is written atomically into ``report_dir`` (created when missing).
    """
    import json

    from rectify.atomic import atomic_write_text
    from rectify.raster.io import write_raster

    d = Path(report_dir)
    if d.exists() and not d.is_dir():
        raise InvalidInputError(f"report folder {str(d)!r} is a file")
    d.mkdir(parents=True, exist_ok=True)
    r = run.result
    shift, tr = relief_shift_map(model, dem, r.grid)
    doc: dict[str, Any] = {
        "output": str(r.path), "model": r.model, "crs": r.grid.crs, "width": r.grid.width, "height": r.grid.height,
        "resolution": r.grid.resolution[0], "dem": {"path": r.dem_path, "undulation_m": dem.undulation,
                                                    "geoid": dem.geoid, "heights_on_output_m": list(r.dem_range)},
        "relief_shift_removed": {"max": float(np.nanmax(shift)) if np.isfinite(shift).any() else None,
                                 "mean": float(np.nanmean(shift)) if np.isfinite(shift).any() else None,
                                 "map": "relief_shift.tif"},
        "occluded_pixels": r.n_occluded, "seconds": r.seconds, "summary": run.summary_lines()}
    out = []
    if run.residuals is not None:
        doc["gcp_residuals"] = run.residuals.summary()
        out.append(atomic_write_text(d / "residuals.csv", run.residuals.to_csv(), overwrite=overwrite))
    out.append(write_raster(d / "relief_shift.tif", shift.astype(np.float32), tr, r.grid.crs, nodata=float("nan"),
                            valid=np.isfinite(shift), overwrite=overwrite))
    out.append(atomic_write_text(d / "ortho_report.json", json.dumps(doc, indent=2, default=str) + "\n",
                                 overwrite=overwrite))
    return out
