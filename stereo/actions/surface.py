"""``run_surface``: a block's orientation -> stereo pairs -> dense matching per pair -> one fused DSM.

Steps (``docs/surface.md``):

1. the block orientation (``orientation.json`` of ``stereo block``, any block orientation JSON, or
   another tool's poses and cameras, :mod:`stereo.actions.surface_inputs`) and its images, found by
   the names it records in ``images`` (default: the orientation's folder);
   every image is checked before any work;
2. pairs (:func:`select_pairs`): every two images whose footprints on the mean terrain height
   overlap enough, with a base-to-height ratio and an intersection angle in the documented ranges;
   per area (a coarse grid over the block) the ``pairs_per_area`` best pairs (score: overlap times
   the base-to-height ratio, capped at :data:`BH_TARGET`) are kept;
3. per pair: the normal case from the two exterior orientations
   (:func:`stereo.dense.epipolar.rectify_exterior`), resampling, SGBM matching
   (:func:`stereo.dense.matching.match_rasters`) in a scratch folder, triangulation
   (:func:`stereo.dense.triangulate.triangulate_disparity`) and per point the height standard
   error (:mod:`stereo.dense.precision`); gridded with its sigma on the common grid
   (:class:`stereo.dense.fusion.SigmaGrid`);
4. the fusion (:func:`stereo.dense.fusion.fuse_heights`) by row blocks into ``dsm.tif``.

Outputs in ``out_dir`` (all written together at the end, or none on an error):

=================  ==========================================================================
``dsm.tif``        band 1 height, 2 sigma_Z, 3 count of agreeing pairs, 4 provenance (pair
                   index, -1 none); float32, nodata -9999, cells on whole multiples of the cell
``pairs.json``     the pairs (images, overlap, B/H, angle, points, coverage, median sigma_Z), the
                   thresholds, the grid, the summary, the orthomosaic, the cloud, the check points
``ortho.tif``      (``ortho``, default) the true orthomosaic over the fused DSM: seams of the
                   least-transformed image, COG with overviews (:mod:`stereo.actions.surface_outputs`)
``ortho.source.tif`` its provenance: the 1-based number of the image per pixel (order of ``images``)
``points.laz``     (``cloud``, default; ``.las`` without a LAZ backend; ``points.las`` or
                   ``points.copc.laz`` by ``cloud_format``) one point per DSM cell with
                   the extra dimensions ``sigma_z``, ``pair``, ``count`` and RGB (``cloud_colors``)
``ortho_*.tif``    (``keep_orthophotos``) the true orthophoto of every image
=================  ==========================================================================
"""

from __future__ import annotations

import contextlib
import json
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.actions.workspace import Workspace
from rectify.errors import InvalidInputError, StereoError
from rectify.geometry.accuracy import LE90_FACTOR
from rectify.geometry.camera import Camera
from rectify.raster.distributed import Scheduler, resolve_scheduler
from rectify.raster.engine import COMPRESSIONS
from rectify.raster.io import (
    MaskPolicy,
    TiledWriter,
    WindowReader,
    gdal_cache_limit,
    ignore_not_georeferenced,
    iter_windows,
    raster_info,
)
from rectify.raster.mosaic import BALANCES, MosaicResult
from rectify.report.builder import json_safe
from stereo.actions.surface_inputs import SurfaceOrientation, dem_ground_z, load_orientation, read_block_points
from stereo.actions.surface_outputs import (
    CLOUD_DIMS,
    CLOUD_FORMATS,
    CheckPoints,
    CloudWritten,
    PairView,
    check_points_accuracy,
    cloud_output,
    read_check_points,
    save_grid,
    write_cloud,
    write_orthomosaic,
    write_orthophotos,
)
from stereo.block.tracks_pairs import footprints
from stereo.block.types import Pose
from stereo.dense.dsm import DSM_NODATA, DsmResult, default_cell
from stereo.dense.epipolar import EpipolarRectification, rectify_exterior, resample_view
from stereo.dense.fusion import (
    FUSED_BANDS,
    FusedHeights,
    SigmaGrid,
    fuse_heights,
    fused_band_descriptions,
    nodata_of,
    variance_factor,
)
from stereo.dense.matching import NODATA, MatchOptions, match_rasters
from stereo.dense.precision import (
    DISPARITY_SIGMA_FLOOR_PX,
    PointSigmaField,
    disparity_sigma,
    height_sigma_disparity,
    height_sigma_orientation,
)
from stereo.dense.triangulate import triangulate_disparity
from stereo.formats.block import BlockOrientation, block_orientation_text
from stereo.formats.points import PointsTable
from stereo.pair.model import ground_unit
from stereo.report.dense import HeightComparison, compare_with_dem

__all__ = ["BH_TARGET", "CLOUD_FORMATS", "SURFACE_FORMAT", "StereoPair", "SurfaceOptions", "SurfaceResult",
           "run_surface", "select_pairs"]

StrPath = str | Path
Progress = Callable[[str, int, int], None]

SURFACE_FORMAT = "rectify-stereo/surface-pairs"
#: the base-to-height ratio above which a pair scores no better (wider bases match less well)
BH_TARGET = 0.6
#: sources of the orientation's share of sigma_Z (:attr:`SurfaceOptions.orientation_sigma`)
ORIENTATION_SIGMA = ("auto", "points", "poses", "none")
ORIENTATION_NOTE = {"points": "the block points' height standard errors", "poses": "the pose standard errors "
                    "taken as independent (an upper bound)", "none": "none (no standard errors in the block)"}
#: the sub-pixel window radius of the surface's matching: on the synthetic blocks of docs/surface.md
#: radius 3 gave RMSE 0.35 GSD and RMS(error / sigma_Z) 1.04, the matcher's default 6: 0.38 and 1.27
SURFACE_REFINE_RADIUS = 3
#: rows of the fused grid per fusion block
FUSION_ROWS = 256
#: side of a triangulation window, pixels
WINDOW = 256
#: image suffixes tried when an image name is found without its extension
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".TIF", ".PNG", ".JPG")


@dataclass(frozen=True)
class SurfaceOptions:
    """Options of :func:`run_surface`.

    Attributes
    ----------
    images : path or None
        Folder of the images (default: the orientation's folder).
    camera : path or None
        The camera file of another tool's pose file that holds no cameras (any kind ``--camera`` reads;
        :mod:`stereo.actions.surface_inputs`).
    cell : float or None
        DSM cell (ground units); default the median ground sampling distance to 2 significant
        digits. At least a tenth of it.
    ground_z : float or None
        Mean terrain height for the footprints and the disparity search; default the median height
        of the block's ``points.csv``.
    relief : float or None
        Expected height range about ``ground_z`` (ground units) for the disparity search; default
        the block points' 1-99 % range plus a tenth of the flying height.
    min_overlap : float
        Smallest footprint overlap of a pair, as a share of the smaller footprint.
    min_base_height, max_base_height : float
        Range of the base-to-height ratio B / H.
    min_angle_deg, max_angle_deg : float
        Range of the intersection angle at the centre of the overlap, degrees.
    pairs_per_area : int
        Pairs kept per area (cell of an 8 x 8 grid over the block), best score first.
    k_sigma : float
        Fusion rejection threshold (:func:`stereo.dense.fusion.fuse_heights`).
    sigma_floor_px : float
        Disparity standard error floor (:func:`stereo.dense.precision.disparity_sigma`).
    min_confidence : float
        Points of lower matching confidence are left out.
    reference_dem : path or None
        Compare the DSM with it (resampled bilinearly onto the DSM grid; RMSE, NMAD, coverage).
    orientation_sigma : {"auto", "points", "poses", "none"}
        The orientation's share of sigma_Z (``docs/surface.md``): ``points``: the height standard
        errors of the block's ``points.csv`` (the bundle's propagation of its full covariance) near
        each point; ``poses``: the pose standard errors of ``orientation.json`` taken as independent
        (an upper bound); ``none``; ``auto``: ``points`` when the points file has standard errors,
        else ``poses`` when the orientation has some, else none.
    scheduler : str, Scheduler or None
        Where each pair's matching tiles run (:func:`stereo.dense.matching.match_rasters`; ``threads``,
        ``processes[:N]``, ``tcp://HOST:PORT``; None: ``$RECTIFY_SCHEDULER``, else threads). The
        scratch folder lies in the output folder, which Dask workers must see under the same path.
    matching : MatchOptions
        The matcher's options; default :class:`MatchOptions` with the sub-pixel window radius
        :data:`SURFACE_REFINE_RADIUS` (3), for which the disparity sigma is validated
        (``docs/surface.md``).
    ortho : bool
        Write the true orthomosaic ``ortho.tif`` over the fused DSM (needs a block CRS; without one it is
        left out with a note).
    keep_orthophotos : bool
        Keep every image's true orthophoto as ``ortho_<image stem>.tif`` (else they are removed).
    ortho_compress : str
        The orthomosaic's compression (:data:`rectify.raster.engine.COMPRESSIONS`; ``jpeg``: JPEG-in-TIFF
        with a mask); the orthophotos are lossless.
    balance : {"none", "mean", "reference"}
        Radiometric balancing of the mosaic (``rectify mosaic --balance``; default as there).
    feather_px : float
        Feathering width of the mosaic's seams, output pixels (``rectify mosaic --feather``).
    cloud : bool
        Write the point cloud (one point per DSM cell with ``sigma_z``, ``pair``, ``count``).
    cloud_format : {"laz", "las", "copc"}
        ``points.laz`` (``points.las`` when no LAZ backend is installed), ``points.las``, or the Cloud
        Optimized Point Cloud ``points.copc.laz`` (needs ``copclib``).
    cloud_colors : bool
        The cloud's RGB: from the orthomosaic, else the left image of each point's pair (else RGB 0).
    check : path or None
        Check points (CSV with ``id, x, y, z``; the block control CSV does): the DSM's vertical accuracy
        statement at them.
    check_ids : tuple of str
        Only these ids of ``check`` (``stereo block --check``'s); default all.
    """

    images: str | None = None
    camera: str | None = None
    cell: float | None = None
    ground_z: float | None = None
    relief: float | None = None
    min_overlap: float = 0.25
    min_base_height: float = 0.1
    max_base_height: float = 1.2
    min_angle_deg: float = 5.0
    max_angle_deg: float = 60.0
    pairs_per_area: int = 3
    k_sigma: float = 3.0
    sigma_floor_px: float = DISPARITY_SIGMA_FLOOR_PX
    min_confidence: float = 0.0
    reference_dem: str | None = None
    orientation_sigma: str = "auto"
    scheduler: str | Scheduler | None = None
    matching: MatchOptions = field(default_factory=lambda: MatchOptions(refine_radius=SURFACE_REFINE_RADIUS))
    ortho: bool = True
    keep_orthophotos: bool = False
    ortho_compress: str = "zstd"
    balance: str = "none"
    feather_px: float = 16.0
    cloud: bool = True
    cloud_format: str = "laz"
    cloud_colors: bool = True
    check: str | None = None
    check_ids: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        def num(name: str, lo: float, hi: float = math.inf) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise InvalidInputError(f"`{name}` must be a number in [{lo:g}, {hi:g}]; got {v!r}")

        for name in ("cell", "relief"):
            if getattr(self, name) is not None:
                num(name, 1e-12)
        if self.ground_z is not None:
            num("ground_z", -1e7, 1e7)
        num("min_overlap", 0.01, 1.0)
        num("min_base_height", 0.0, 10.0)
        num("max_base_height", 0.0, 10.0)
        num("min_angle_deg", 0.0, 180.0)
        num("max_angle_deg", 0.0, 180.0)
        num("k_sigma", 0.5, 100.0)
        num("sigma_floor_px", 0.0, 10.0)
        num("min_confidence", 0.0, 1.0)
        if self.min_base_height >= self.max_base_height:
            raise InvalidInputError(f"`min_base_height` must be below `max_base_height`; got {self.min_base_height} "
                                    f"and {self.max_base_height}")
        if self.min_angle_deg >= self.max_angle_deg:
            raise InvalidInputError(f"`min_angle_deg` must be below `max_angle_deg`; got {self.min_angle_deg} and "
                                    f"{self.max_angle_deg}")
        if isinstance(self.pairs_per_area, bool) or not isinstance(self.pairs_per_area, int) \
                or not 1 <= self.pairs_per_area <= 50:
            raise InvalidInputError(f"`pairs_per_area` must be an integer in 1..50; got {self.pairs_per_area!r}")
        if not isinstance(self.matching, MatchOptions):
            raise InvalidInputError(f"`matching` must be a MatchOptions; got {type(self.matching).__name__}")
        if isinstance(self.scheduler, str) and self.scheduler.strip():
            Scheduler.parse(self.scheduler)
        elif self.scheduler is not None and not isinstance(self.scheduler, (str, Scheduler)):
            raise InvalidInputError(f"`scheduler` must be a string or a Scheduler; got {self.scheduler!r}")
        num("feather_px", 0.0, 4096.0)
        if str(self.ortho_compress).lower() not in COMPRESSIONS:
            raise InvalidInputError(f"`ortho_compress` must be one of {list(COMPRESSIONS)}; got "
                                    f"{self.ortho_compress!r}")
        if self.balance not in BALANCES:
            raise InvalidInputError(f"`balance` must be one of {list(BALANCES)}; got {self.balance!r}")
        if self.cloud_format not in CLOUD_FORMATS:
            raise InvalidInputError(f"`cloud_format` must be one of {list(CLOUD_FORMATS)}; got {self.cloud_format!r}")
        if self.orientation_sigma not in ORIENTATION_SIGMA:
            raise InvalidInputError(f"`orientation_sigma` must be one of {list(ORIENTATION_SIGMA)}; got "
                                    f"{self.orientation_sigma!r}")


@dataclass(frozen=True)
class StereoPair:
    """A candidate pair of a block: images ``i`` < ``j`` and its figures."""

    i: int
    j: int
    left: str
    right: str
    overlap: float
    base_height: float
    angle_deg: float
    score: float
    passes: bool

    def figures(self) -> str:
        return (f"{self.left} + {self.right}: overlap {100 * self.overlap:.0f}%, B/H {self.base_height:.3f}, "
                f"intersection angle {self.angle_deg:.1f} deg")


@dataclass(frozen=True, eq=False)
class SurfaceResult:
    """What :func:`run_surface` did and wrote."""

    out_dir: Path
    files: tuple[Path, ...]
    pairs: tuple[StereoPair, ...]
    pair_stats: tuple[dict[str, Any], ...]
    cell: float
    gsd: float
    shape: tuple[int, int]
    coverage: float
    median_sigma: float
    n_rejected: int
    crs: str | None
    seconds: float
    n_candidates: int = 0
    variance_factor: float = 1.0
    overlap_coverage: float = math.nan
    orientation_sigma: str = "none"
    comparison: HeightComparison | None = None
    le90: tuple[float, float] = (math.nan, math.nan)   # against the reference DEM: from the RMSE, observed
    mosaic: MosaicResult | None = None
    ortho_note: str = ""
    cloud_points: int = 0
    check: CheckPoints | None = None
    cloud_file: str = ""
    cloud_colors: str = ""
    frame_note: str = ""   # the orientation converted into a map CRS (stereo.actions.surface_inputs.to_map_frame)

    def summary_lines(self) -> list[str]:
        unit = ground_unit(self.crs, "map")
        lines = [f"pairs: {len(self.pairs)} of {self.n_candidates} candidates"]
        for k, (p, s) in enumerate(zip(self.pairs, self.pair_stats, strict=True)):
            if s.get("skipped"):
                lines.append(f"  pair {k}: {p.figures()}; skipped: {s['skipped']}")
                continue
            lines.append(f"  pair {k}: {p.figures()}; {s['points']} points, median sigma_Z "
                         f"{s['median_sigma_z']:.3g} {unit}")
        lines += [f"DSM: {self.shape[1]} x {self.shape[0]} cells of {self.cell:g} {unit} (ground pixel {self.gsd:.4g} "
                  f"{unit}), coverage {100 * self.coverage:.1f}%, median sigma_Z {self.median_sigma:.3g} {unit}, "
                  f"{self.n_rejected} pair heights rejected as inconsistent; the pairs' sigmas scaled by the "
                  f"variance factor {self.variance_factor:.3f} of their agreement; orientation share of sigma_Z: "
                  f"{ORIENTATION_NOTE[self.orientation_sigma]}",
                  f"coverage of the chosen pairs' overlap (footprints on the mean height): "
                  f"{100 * self.overlap_coverage:.1f}%"]
        if self.comparison is not None:
            lines.append(self.comparison.summary_line(unit, cell=self.cell) +
                         f"; LE90 {self.le90[0]:.3g} {unit} (1.6449 RMSE; observed 90th percentile of |dz| "
                         f"{self.le90[1]:.3g})")
        if self.check is not None:
            lines += self.check.summary_lines()
        if self.mosaic is not None:
            m = self.mosaic
            regions = m.plan.regions() if m.plan is not None else 0
            lines.append(f"orthomosaic: {m.grid.width} x {m.grid.height} px of {m.grid.resolution[0]:.4g} {unit}, "
                         f"{len(m.inputs)} true orthophotos, seams of the least-transformed image ({regions} "
                         f"regions), balance {m.balance.mode if m.balance else 'none'}")
        if self.frame_note:
            lines.append(self.frame_note)
        if self.ortho_note:
            lines.append(self.ortho_note)
        if self.cloud_points:
            lines.append(f"point cloud: {self.cloud_points} points (one per DSM cell) with sigma_z, pair, count"
                         + (f" in {self.cloud_file}" if self.cloud_file else "")
                         + (f"; {self.cloud_colors}" if self.cloud_colors else ""))
        lines += [f"outputs in {self.out_dir}: " + ", ".join(p.name for p in self.files),
                  f"time {self.seconds:.1f} s"]
        return lines


# --------------------------------------------------------------------------- inputs
def find_images(bo: BlockOrientation, folder: Path) -> list[Path]:
    """The file of each image of the block: ``folder / name``, else a file of the name's stem with an
    image suffix. Raises naming the first image not found."""
    if not folder.is_dir():
        raise InvalidInputError(f"image folder not found: {str(folder)!r}")
    out = []
    for pose in bo.poses:
        p = folder / pose.image
        if not p.is_file():
            hits = [folder / (Path(pose.image).stem + s) for s in IMAGE_SUFFIXES]
            hits = [h for h in hits if h.is_file()]
            if not hits:
                raise InvalidInputError(f"image {pose.image!r} of the block orientation is not in {str(folder)!r} "
                                        "(pass --images DIR)")
            p = hits[0]
        out.append(p)
    return out


def _camera(bo: BlockOrientation, pose: Pose) -> Camera:
    cam = bo.cameras.get(pose.camera) or bo.cameras.get(pose.image)
    if cam is None:
        if len(bo.cameras) == 1:
            return next(iter(bo.cameras.values()))
        raise InvalidInputError(f"image {pose.image!r} names camera {pose.camera!r}, which the orientation does not "
                                f"hold ({sorted(bo.cameras)})")
    return cam


def _ground_z(so: SurfaceOrientation, opts: SurfaceOptions) -> tuple[float, float | None, PointsTable | None]:
    """Mean terrain height, the block points' height range (None: no points file) and the points: from
    ``--ground-z``, else the block's ``points.csv``, else the reference DEM under the images' nadir points."""
    z = None
    t = read_block_points(so)
    if t is not None:
        zz = np.asarray(t.xyz, dtype=np.float64)[:, 2]
        zz = zz[np.isfinite(zz)]
        if zz.size:
            z = zz
    if opts.ground_z is not None:
        g = float(opts.ground_z)
    elif z is not None:
        g = float(np.median(z))
    else:
        gd = None if opts.reference_dem is None else dem_ground_z(
            opts.reference_dem, np.array([p.position[:2] for p in so.orientation.poses]), so.orientation.crs)
        if gd is None:
            where = f"no points.csv beside the orientation in {str(so.folder)!r}" if so.ours else \
                f"the {so.source} {str(so.path)!r} has no points"
            raise InvalidInputError(f"{where} to take the terrain height from: pass --ground-z (or a --reference-dem "
                                    "under the images)")
        g = gd
    rng = None if z is None else float(np.percentile(z, 99) - np.percentile(z, 1))
    return g, rng, t


def _orientation_term(bo: BlockOrientation, points: PointsTable | None, mode: str
                      ) -> tuple[str, PointSigmaField | None]:
    """The source of the orientation's share of sigma_Z and, for ``points``, the field of the points' sigmas."""
    has_std = points is not None and points.std is not None and bool(np.isfinite(points.std[:, 2]).any())
    if mode == "points" and not has_std:
        raise InvalidInputError("orientation sigma from the points: the block has no points.csv with standard "
                                "errors (std_z) beside its orientation")
    if mode == "auto":
        mode = "points" if has_std else "poses" if np.isfinite(bo.std_errors).any() else "none"
    if mode == "points":
        assert points is not None and points.std is not None
        return mode, PointSigmaField.from_points(points.xyz[:, :2], points.std[:, 2])
    return mode, None


# --------------------------------------------------------------------------- pairs
def _pair_figures(polys: list[NDArray[np.float64]], poses: list[Pose], i: int, j: int, ground_z: float
                  ) -> tuple[float, float, float, NDArray[np.float64] | None]:
    """Overlap (share of the smaller footprint), B/H, intersection angle (deg) and the overlap polygon."""
    o = np.mean(polys[i], axis=0)
    a = np.ascontiguousarray(cv2.convexHull(np.asarray(polys[i] - o, np.float32)))
    b = np.ascontiguousarray(cv2.convexHull(np.asarray(polys[j] - o, np.float32)))
    area, inter = cv2.intersectConvexConvex(a, b)
    small = min(cv2.contourArea(a), cv2.contourArea(b))
    ov = float(area / small) if small > 0 else 0.0
    ci, cj = poses[i].position, poses[j].position
    h = 0.5 * (abs(ci[2] - ground_z) + abs(cj[2] - ground_z))
    bh = float(np.linalg.norm(cj - ci) / h) if h > 0 else math.inf
    if inter is None or area <= 0:
        centre = 0.5 * (ci[:2] + cj[:2])
        poly = None
    else:
        poly = inter.reshape(-1, 2).astype(np.float64) + o
        centre = poly.mean(axis=0)
    x = np.array([centre[0], centre[1], ground_z])
    ri, rj = ci - x, cj - x
    cosang = float(ri @ rj / (np.linalg.norm(ri) * np.linalg.norm(rj)))
    return ov, bh, math.degrees(math.acos(max(-1.0, min(1.0, cosang)))), poly


def select_pairs(bo: BlockOrientation, ground_z: float, opts: SurfaceOptions
                 ) -> tuple[list[StereoPair], list[StereoPair], list[NDArray[np.float64]]]:
    """The pairs to match, all candidates (best score first) and the footprints (module docstring, step 2).

    Raises
    ------
    StereoError
        No pair passes the thresholds (the best candidate's figures are named).
    """
    poses = list(bo.poses)
    if len(poses) < 2:
        raise InvalidInputError(f"a surface needs at least 2 images; the orientation has {len(poses)}")
    cams = {p.image: _camera(bo, p) for p in poses}
    polys = footprints(poses, cams, ground_z)
    cands: list[StereoPair] = []
    shapes: dict[tuple[int, int], NDArray[np.float64]] = {}
    for i in range(len(poses)):
        for j in range(i + 1, len(poses)):
            ov, bh, ang, poly = _pair_figures(polys, poses, i, j, ground_z)
            ok = (ov >= opts.min_overlap and opts.min_base_height <= bh <= opts.max_base_height
                  and opts.min_angle_deg <= ang <= opts.max_angle_deg)
            score = ov * min(bh, BH_TARGET) / BH_TARGET
            cands.append(StereoPair(i, j, poses[i].image, poses[j].image, ov, bh, ang, score, ok))
            if poly is not None:
                shapes[(i, j)] = poly
    cands.sort(key=lambda p: (not p.passes, -p.score))
    good = [p for p in cands if p.passes]
    if not good:
        best = max(cands, key=lambda p: p.overlap)
        raise StereoError(
            f"no stereo pair passes the thresholds (overlap >= {100 * opts.min_overlap:g}%, B/H "
            f"{opts.min_base_height:g}..{opts.max_base_height:g}, angle {opts.min_angle_deg:g}..{opts.max_angle_deg:g}"
            f" deg); the best pair: {best.figures()}")
    # per area: an 8 x 8 grid over the footprints; the best pairs_per_area pairs that cover each area centre
    allp = np.vstack(polys)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 17)[1::2], np.linspace(lo[1], hi[1], 17)[1::2])
    centres = np.column_stack([gx.ravel(), gy.ravel()]).astype(np.float32)
    chosen: set[tuple[int, int]] = set()
    inside = {}
    for p in good:
        poly = shapes.get((p.i, p.j))
        if poly is None:
            continue
        cnt = np.asarray(poly, np.float32).reshape(-1, 1, 2)
        inside[(p.i, p.j)] = np.array([cv2.pointPolygonTest(cnt, (float(x), float(y)), False) >= 0
                                       for x, y in centres])
    for a in range(len(centres)):
        k = 0
        for p in good:  # best score first
            m = inside.get((p.i, p.j))
            if m is not None and m[a]:
                chosen.add((p.i, p.j))
                k += 1
                if k >= opts.pairs_per_area:
                    break
    sel = [p for p in good if (p.i, p.j) in chosen] or good[:1]
    return sel, cands, polys


# --------------------------------------------------------------------------- one pair
def _disparity_range(rect: EpipolarRectification, depth_lo: float, depth_hi: float) -> tuple[float, float]:
    b = float(np.linalg.norm(rect.base))
    p_hi, p_lo = b * rect.focal_px / depth_lo, b * rect.focal_px / depth_hi
    off = rect.disparity_offset
    return p_lo - off, p_hi - off


def _pair_points(rect: EpipolarRectification, paths: dict[str, Path], grid: SigmaGrid, std_l: NDArray[np.float64],
                 std_r: NDArray[np.float64], opts: SurfaceOptions, orient: tuple[str, PointSigmaField | None]
                 ) -> dict[str, Any]:
    """Triangulate one pair's disparities window by window, with each point's sigma_Z, into ``grid``."""
    base = float(np.linalg.norm(rect.base))
    axis = rect.normal_rotation[:, 2]
    n = 0
    sig_d: list[float] = []
    sig_z: list[float] = []
    radius = opts.matching.refine_radius  # the window of the matcher's sub-pixel fit
    m = radius + 3  # margin of the sigma window (the fit's radius and the gradient)
    with WindowReader(paths["disparity"]) as rd, WindowReader(paths["confidence"]) as rc, \
            WindowReader(paths["left"]) as rl, WindowReader(paths["right"]) as rr, ignore_not_georeferenced():
        for c0, r0, w, h in iter_windows(rd.width, rd.height, WINDOW):
            d, _ = rd.read(c0, r0, w, h)
            disp = d[:, :, 0].astype(np.float64)
            disp[disp == NODATA] = np.nan
            if not np.isfinite(disp).any():
                continue
            cf, _ = rc.read(c0, r0, w, h)
            mask = np.isfinite(disp) & (cf[:, :, 1] == 0)
            if opts.min_confidence > 0:
                mask &= cf[:, :, 0] >= opts.min_confidence
            # the sigma of each disparity, on the window with a margin (right: full rows)
            a0, b0 = max(c0 - m, 0), max(r0 - m, 0)
            a1, b1 = min(c0 + w + m, rd.width), min(r0 + h + m, rd.height)
            dm, _ = rd.read(a0, b0, a1 - a0, b1 - b0)
            dmm = dm[:, :, 0].astype(np.float32)
            dmm[dmm == NODATA] = np.nan
            L, _ = rl.read(a0, b0, a1 - a0, b1 - b0)
            R, _ = rr.read(0, b0, rr.width, b1 - b0)
            sd = disparity_sigma(L.astype(np.float32).mean(axis=2), R.astype(np.float32).mean(axis=2), dmm,
                                 radius=radius, floor_px=opts.sigma_floor_px, right_offset=float(a0))
            sd = sd[r0 - b0:r0 - b0 + h, c0 - a0:c0 - a0 + w]
            mask &= np.isfinite(sd)
            pts = triangulate_disparity(rect, disp, col_off=c0, row_off=r0, mask=mask)
            if not len(pts):
                continue
            rows = np.rint(pts.pixel[:, 1] - r0).astype(np.int64)
            cols = np.rint(pts.pixel[:, 0] - c0).astype(np.int64)
            s_px = sd[rows, cols].astype(np.float64)
            depth = np.abs((pts.xyz - rect.centre_left) @ (axis / np.linalg.norm(axis)))
            s_disp = height_sigma_disparity(pts.xyz, rect.centre_left, axis, base, rect.focal_px, s_px)
            if orient[0] == "poses":
                s_or = height_sigma_orientation(depth, base, std_l, std_r)
            else:
                s_or = np.zeros(len(depth))
            s = np.sqrt(s_disp ** 2 + s_or ** 2)
            grid.add(pts.xyz, s)
            n += len(pts)
            step = max(1, len(s) // 2000)
            sig_d += s_px[::step].tolist()
            sig_z += s[::step].tolist()
    return {"points": n, "median_sigma_disparity_px": float(np.median(sig_d)) if sig_d else math.nan,
            "median_sigma_z": float(np.median(sig_z)) if sig_z else math.nan}


def _overlap_mask(polys: list[NDArray[np.float64]], transform: Any, shape: tuple[int, int]) -> NDArray[np.bool_]:
    """Cells of the grid inside any of the polygons (ground x, y)."""
    m = np.zeros(shape, np.uint8)
    inv = ~transform
    for poly in polys:
        cr = np.array([inv * (float(x), float(y)) for x, y in poly]) - 0.5   # cell centres at integers
        cv2.fillPoly(m, [np.round(cr * 16).astype(np.int32)], 1, shift=4)
    return m > 0


def _fuse_rows(hs: list[Any], ss: list[Any], r0: int, r1: int, factor: float, k: float,
               common: PointSigmaField | None = None, transform: Any = None) -> FusedHeights:
    """Fuse rows ``r0:r1`` of the pairs' height and sigma grids (sigmas scaled by ``factor``); ``common``:
    the orientation's share of sigma_Z at the cell centres (the block points' field)."""
    c = None
    if common is not None:
        w = hs[0].shape[1]
        cc, rr = np.meshgrid(np.arange(w) + 0.5, np.arange(r0, r1) + 0.5)
        x = transform.c + transform.a * cc
        y = transform.f + transform.e * rr
        c = common(np.column_stack([x.ravel(), y.ravel()])).reshape(r1 - r0, w)
    return fuse_heights(np.stack([np.asarray(a[r0:r1], np.float64) for a in hs]),
                        np.stack([factor * np.asarray(a[r0:r1], np.float64) for a in ss]), k=k, common=c)


# --------------------------------------------------------------------------- the action
def run_surface(orientation: StrPath, out_dir: StrPath, *, options: SurfaceOptions | None = None,
                overwrite: bool = False, progress: Progress | None = None) -> SurfaceResult:
    """A block's orientation -> one fused DSM with sigma_Z, count and provenance bands (module docstring).

    Parameters
    ----------
    orientation : path
        The output folder of ``stereo block`` (its ``orientation.json``), a block orientation JSON, or another
        tool's pose file (with ``options.camera`` when it holds no cameras; ``KIND:PATH`` names a kind).
    out_dir : path
        Output folder (``dsm.tif``, ``pairs.json``).
    options : SurfaceOptions, optional
    overwrite : bool
    progress : callable(stage, done, total), optional

    Raises
    ------
    InvalidInputError
        A missing orientation or image (named), bad options, a cell smaller than a tenth of the ground
        pixel, outputs that exist (without ``overwrite``) or are inputs.
    StereoError
        No pair passes the thresholds (the best pair's figures named), or no pair gives points.
    """
    t0 = time.perf_counter()
    opts = options or SurfaceOptions()
    if not isinstance(opts, SurfaceOptions):
        raise InvalidInputError(f"`options` must be a SurfaceOptions; got {type(opts).__name__}")
    so = load_orientation(orientation, camera=opts.camera)
    ofile, bo, folder = so.path, so.orientation, so.folder
    images = find_images(bo, Path(opts.images) if opts.images is not None else folder)
    for pose, img in zip(bo.poses, images, strict=True):
        cam = _camera(bo, pose)
        with ignore_not_georeferenced():
            info = raster_info(img)
        if (info.width, info.height) != (cam.width, cam.height):
            raise InvalidInputError(f"image {str(img)!r} is {info.width} x {info.height} px; its camera says "
                                    f"{cam.width} x {cam.height}")
    ground_z, zrange, block_points = _ground_z(so, opts)
    orient_mode, orient_field = _orientation_term(bo, block_points, opts.orientation_sigma)
    scheduler = resolve_scheduler(opts.scheduler)  # a bad value fails before any work
    pairs, cands, _polys = select_pairs(bo, ground_z, opts)
    poses = list(bo.poses)
    gsds = [abs(p.position[2] - ground_z) * _camera(bo, p).pixel_size_mm / _camera(bo, p).focal_length_mm
            for p in poses]
    gsd = float(np.median(gsds))
    cell = float(opts.cell) if opts.cell is not None else default_cell(gsd)
    if cell < gsd / 10:
        raise InvalidInputError(f"DSM cell {cell:g} is smaller than a tenth of the ground pixel ({gsd:.4g}): choose "
                                f"at least {gsd / 10:.3g}")
    flying = float(np.median([abs(p.position[2] - ground_z) for p in poses]))
    relief = opts.relief if opts.relief is not None else (zrange or 0.0) + 0.1 * flying
    out = Path(out_dir)
    if opts.reference_dem is not None and not Path(opts.reference_dem).is_file():
        raise InvalidInputError(f"reference DEM not found: {str(opts.reference_dem)!r}")
    if opts.check is not None:
        read_check_points(opts.check, tuple(opts.check_ids))   # a bad file fails before any work
    ws = Workspace(out, overwrite=overwrite,
                   inputs=[*so.inputs, *images, *[q for q in (opts.reference_dem, opts.check) if q is not None]])
    if out.exists() and not out.is_dir():
        raise InvalidInputError(f"output {str(out)!r} exists and is not a folder")
    names = {"dsm": out / "dsm.tif", "pairs": out / "pairs.json"}
    ortho_note = ""
    do_ortho = opts.ortho and bo.crs is not None
    if opts.ortho and not do_ortho:
        ortho_note = "no orthomosaic: the block orientation has no CRS (a mosaic needs one)"
    if do_ortho:
        names["ortho"], names["ortho_source"] = out / "ortho.tif", out / "ortho.source.tif"
    kept = {}
    if do_ortho and opts.keep_orthophotos:
        kept = {k: out / f"ortho_{Path(pose.image).stem}.tif" for k, pose in enumerate(bo.poses)}
    if opts.cloud:
        cloud_fmt, cloud_name = cloud_output(opts.cloud_format)   # COPC without copclib: refused here
        names["cloud"] = out / cloud_name
    ws.plan(*names.values(), *kept.values())
    # the common grid: the union of the chosen pairs' overlaps on the mean height, with a margin
    boxes = []
    for p in pairs:
        _ov, _bh, _a, poly = _pair_figures(_polys, poses, p.i, p.j, ground_z)
        if poly is not None:
            boxes.append(poly)
    allp = np.vstack(boxes)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    pad = 0.1 * (hi - lo) + 2 * cell
    bounds = (lo[0] - pad[0], lo[1] - pad[1], hi[0] + pad[0], hi[1] + pad[1])
    std = {p.image: bo.std_errors[k] for k, p in enumerate(poses)}
    files: list[Path] = []
    stats: list[dict[str, Any]] = []
    try:
        ws.prepare()
        with gdal_cache_limit(64), ws.transaction(), ignore_not_georeferenced(), contextlib.ExitStack() as stack:
            scratch = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=".surface-", dir=out)))
            pair_files: list[tuple[Path, Path] | None] = []
            for k, p in enumerate(pairs):
                if progress is not None:
                    progress("pairs", k, len(pairs))
                pl, pr = poses[p.i], poses[p.j]
                cl, cr = _camera(bo, pl), _camera(bo, pr)
                dz_hi = abs(0.5 * (pl.position[2] + pr.position[2]) - ground_z)
                paths = {n: scratch / f"pair{k}_{n}.tif" for n in ("left", "right", "disparity", "confidence")}
                try:  # a pair without a normal case or without matches is skipped, with its reason
                    rect = rectify_exterior(pl, pr, cl, cr)
                    rng = _disparity_range(rect, max(dz_hi - relief, 1e-3 * dz_hi), dz_hi + relief)
                    resample_view(rect, "left", images[p.i], paths["left"])
                    resample_view(rect, "right", images[p.j], paths["right"])
                    match_rasters(paths["left"], paths["right"], paths["disparity"], paths["confidence"],
                                  disparity_range=(math.floor(rng[0]), math.ceil(rng[1])), options=opts.matching,
                                  scheduler=scheduler)
                except StereoError as err:
                    stats.append({"points": 0, "median_sigma_disparity_px": math.nan, "median_sigma_z": math.nan,
                                  "coverage": 0.0, "skipped": str(err)})
                    pair_files.append(None)
                    continue
                grid = SigmaGrid(bounds, cell, crs=bo.crs)
                st = _pair_points(rect, paths, grid, std[pl.image], std[pr.image], opts, (orient_mode, orient_field))
                h, s = grid.result()
                st["coverage"] = float(np.isfinite(h).mean())
                hp, sp = scratch / f"pair{k}_h.npy", scratch / f"pair{k}_s.npy"
                save_grid(hp, h.astype(np.float32))
                save_grid(sp, s.astype(np.float32))
                del h, s, grid
                for n in ("left", "right", "disparity", "confidence"):
                    paths[n].unlink()
                stats.append(st)
                pair_files.append((hp, sp))
            used = [q for q in pair_files if q is not None]
            if not used:
                raise StereoError(f"no pair gave points ({len(pairs)} pairs tried; the first: "
                                  f"{stats[0].get('skipped')})")
            index = [k for k, q in enumerate(pair_files) if q is not None]
            hs = [np.load(q[0], mmap_mode="r") for q in used]
            ss = [np.load(q[1], mmap_mode="r") for q in used]
            H, W = hs[0].shape
            transform = SigmaGrid(bounds, cell).transform
            heights = (f"{ground_unit(bo.crs, 'map')}, the heights of the block orientation")
            # first pass: the a-posteriori variance factor of the pairs' sigmas from the cells of several pairs
            chi2_sum, dof_sum = 0.0, 0
            for r0 in range(0, H, FUSION_ROWS):
                f = _fuse_rows(hs, ss, r0, min(r0 + FUSION_ROWS, H), 1.0, opts.k_sigma)
                chi2_sum += float(f.chi2.sum())
                dof_sum += int(f.dof.sum())
            factor = variance_factor(chi2_sum, dof_sum)
            n_valid = n_rej = 0
            sig_sample: list[NDArray[np.float64]] = []
            full_h = np.full((H, W), DSM_NODATA, np.float32)   # for the overlap coverage and the reference DEM
            full_n = np.zeros((H, W), np.uint16)
            with ws.output(names["dsm"], suffix=".tif") as tmp, TiledWriter(
                    tmp, W, H, len(FUSED_BANDS), "float32", transform, bo.crs, MaskPolicy("nodata", DSM_NODATA),
                    tile=256, descriptions=fused_band_descriptions(heights, opts.k_sigma)) as wr:
                for r0 in range(0, H, FUSION_ROWS):
                    f = _fuse_rows(hs, ss, r0, min(r0 + FUSION_ROWS, H), factor, opts.k_sigma, orient_field, transform)
                    prov = np.where(f.provenance >= 0, np.asarray(index)[np.maximum(f.provenance, 0)], -1)
                    wr.write(np.dstack([nodata_of(f.height), nodata_of(f.sigma), f.count.astype(np.float32),
                                        prov.astype(np.float32)]), 0, r0)
                    ok = np.isfinite(f.height)
                    n_valid += int(ok.sum())
                    n_rej += int(f.rejected.sum())
                    sig_sample.append(f.sigma[ok][::7])
                    full_h[r0:r0 + len(ok)] = nodata_of(f.height)
                    full_n[r0:r0 + len(ok)] = np.minimum(f.count, 65535)
            files.append(names["dsm"])
            dsm_tmp = tmp
            del hs, ss
            for grid_files in used:   # fused: their disk space goes to the cloud and the orthophotos
                for gf in grid_files:
                    with contextlib.suppress(OSError):   # else removed with the scratch folder
                        gf.unlink()
            coverage = n_valid / float(H * W)
            sg = np.concatenate(sig_sample) if sig_sample else np.zeros(0)
            med_sigma = float(np.median(sg)) if sg.size else math.nan
            in_overlap = _overlap_mask(boxes, transform, (H, W))
            ov_cov = float((full_n[in_overlap] > 0).mean()) if in_overlap.any() else math.nan
            comparison = None
            le90 = (math.nan, math.nan)
            if opts.reference_dem is not None:
                comparison, dz = compare_with_dem(
                    DsmResult(full_h, full_n, np.zeros((H, W), bool), transform, bo.crs), opts.reference_dem)
                adz = np.abs(dz[np.isfinite(dz)])
                le90 = (LE90_FACTOR * comparison.rmse, float(np.percentile(adz, 90)) if adz.size else math.nan)
                del dz, adz
            del full_h, full_n
            unit = ground_unit(bo.crs, "map")
            check = None
            if opts.check is not None:
                check = check_points_accuracy(dsm_tmp, opts.check, unit, tuple(opts.check_ids))
            mos, ortho_tmp, cloud = None, None, CloudWritten(0)
            if do_ortho:
                ortho_px = default_cell(gsd)   # the images' ground pixel, whatever the DSM cell
                odir = scratch / "orthophotos"
                odir.mkdir()
                src = ofile if so.ours else scratch / "orientation.json"   # a peer's poses, as the DSM used them
                if not so.ours:
                    src.write_text(block_orientation_text(bo.cameras, poses, crs=bo.crs), encoding="utf-8")
                orthos = write_orthophotos(src, [q.image for q in poses], images, dsm_tmp, odir, ortho_px,
                                           progress=progress)
                with ws.output(names["ortho"], suffix=".tif") as tmp, \
                        ws.output(names["ortho_source"], suffix=".tif") as tmp_src:
                    ortho_tmp = tmp
                    if progress is not None:
                        progress("mosaic", 0, 1)
                    mos = write_orthomosaic(orthos, dsm_tmp, tmp, tmp_src, balance=opts.balance,
                                            feather_px=opts.feather_px, compress=opts.ortho_compress.lower())
                files += [names["ortho"], names["ortho_source"]]
                for k, q in enumerate(orthos):
                    if k in kept:
                        with ws.output(kept[k], suffix=".tif") as tmp:
                            q.replace(tmp)
                        files.append(kept[k])
                    else:
                        q.unlink()
            if opts.cloud:   # after the mosaic: its colours (docs/surface.md)
                if progress is not None:
                    progress("cloud", 0, 1)
                on = opts.cloud_colors
                views = [PairView(images[p.i], _camera(bo, poses[p.i]), poses[p.i]) for p in pairs] if on else None
                with ws.output(names["cloud"], suffix=".part") as tmp:
                    cloud = write_cloud(dsm_tmp, tmp, cloud_fmt, bo.crs, mosaic=ortho_tmp if on else None, views=views)
                files.append(names["cloud"])
            doc = {
                "format": SURFACE_FORMAT, "version": 1, "orientation": str(ofile), "crs": bo.crs,
                "dsm": "dsm.tif", "bands": list(FUSED_BANDS),
                "grid": {"cell": cell, "width": W, "height": H, "transform": list(transform)[:6],
                         "ground_sampling_distance": gsd},
                "thresholds": {"min_overlap": opts.min_overlap, "base_height": [opts.min_base_height,
                                                                                opts.max_base_height],
                               "angle_deg": [opts.min_angle_deg, opts.max_angle_deg],
                               "pairs_per_area": opts.pairs_per_area, "k_sigma": opts.k_sigma,
                               "sigma_floor_px": opts.sigma_floor_px},
                "ground_z": ground_z, "relief": relief, "orientation_sigma": orient_mode,
                "pairs": [{"index": k, "left": p.left, "right": p.right, "left_file": str(images[p.i]),
                           "right_file": str(images[p.j]), "overlap": p.overlap, "base_height": p.base_height,
                           "angle_deg": p.angle_deg, "score": p.score, **stats[k]} for k, p in enumerate(pairs)],
                "summary": {"coverage": coverage, "overlap_coverage": ov_cov, "median_sigma_z": med_sigma,
                            "rejected_heights": n_rej,
                            "variance_factor": factor, "variance_factor_dof": dof_sum,
                            "candidates": len(cands), "candidates_passing": sum(p.passes for p in cands)},
                "comparison": None if comparison is None else {
                    "reference_dem": str(opts.reference_dem), "le90": le90[0], "le90_observed": le90[1],
                    **{k: v for k, v in comparison.__dict__.items() if k != "histogram"}},
                "check_points": None if check is None else check.to_dict(),
                "ortho": None if mos is None else {
                    "file": "ortho.tif", "provenance": "ortho.source.tif", "seams": mos.seams,
                    "balance": opts.balance, "feather_px": opts.feather_px, "compress": opts.ortho_compress,
                    "resolution": ortho_px, "images": [q.image for q in poses],
                    "share": list(mos.share), "kept_orthophotos": [kept[k].name for k in sorted(kept)]},
                "ortho_note": ortho_note or None, "frame": bo.frame,
                "cloud": None if not opts.cloud else {"file": names["cloud"].name, "format": cloud_fmt,
                                                      "points": cloud.points, "extra_dims": list(CLOUD_DIMS),
                                                      "colors": cloud.to_dict()},
            }
            with ws.output(names["pairs"]) as tmp:
                tmp.write_text(json.dumps(json_safe(doc), indent=2) + "\n", encoding="utf-8")
            files.append(names["pairs"])
    except BaseException:
        ws.discard_root()
        raise
    return SurfaceResult(out, tuple(files), tuple(pairs), tuple(stats), cell, gsd, (H, W), coverage, med_sigma,
                         n_rej, bo.crs, time.perf_counter() - t0, len(cands), factor, ov_cov, orient_mode,
                         comparison, le90, mos, ortho_note, cloud.points, check,
                         names["cloud"].name if opts.cloud else "", cloud.note() if opts.cloud else "",
                         f"orientation in {bo.frame}" if so.converted_from else "")
