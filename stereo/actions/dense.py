"""``run_dense``: an oriented frame pair -> normal case, disparity, point cloud, DSM and report.

Outputs in ``out_dir`` (all written together at the end, or none on an error):

================================  ==========================================================
``left_normal.tif``,              the photos resampled into the normal case (tiled GeoTIFF,
``right_normal.tif``              no georeference, internal mask)
``disparity.tif``                 float32 ``col_left - col_right`` on the left normal photo
                                  (nodata -9999)
``confidence.tif``                band 1 confidence in [0, 1] (nodata -9999), band 2: 1 filled
``points.las`` (or ``.laz``,      the dense point cloud (ground frame with control or exterior
``.copc.laz``, ``.ply``)          orientations, else the model frame), RGB from the left photo;
                                  LAS/LAZ/COPC: extra dimension ``sigma_z`` (the height standard
                                  error from the disparity's sub-pixel fit, frame units)
``dsm.tif``                       DSM: band 1 height (nodata -9999), band 2 points per cell,
                                  band 3: 1 where a hole was filled
``dense.json``                    the summary (parallax, density, DSM, comparison) and the
                                  rectification
``item.stac.json``                the STAC Item of the DSM and the point cloud (``--no-stac``:
                                  none; ``rectify.actions.products``)
``report/``                       disparity and DSM pictures, height-difference histogram
================================  ==========================================================
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.actions.products import FOLDER_ITEM, options_of, raster_grid, stac_text
from rectify.actions.workspace import Workspace
from rectify.atomic import read_json
from rectify.errors import InvalidInputError, StereoError
from rectify.features import MatcherConfig, match_images
from rectify.formats.detect import is_zoom_camera, read_one_camera
from rectify.formats.stac import StacAsset
from rectify.formats.tables import read_control, read_matches
from rectify.geometry.camera import Camera
from rectify.geometry.crs import same_crs
from rectify.geometry.robust import ROBUST_METHODS
from rectify.raster.distributed import Scheduler, check_scheduler, resolve_scheduler
from rectify.raster.georef import crs_label
from rectify.raster.io import (
    WindowReader,
    bound_gdal_cache,
    gdal_cache_limit,
    ignore_not_georeferenced,
    iter_windows,
    raster_info,
    read_overview,
)
from rectify.report.builder import json_safe
from stereo.dense.dsm import STATISTICS, DsmGrid, DsmResult, default_cell
from stereo.dense.epipolar import (
    EpipolarRectification,
    ParallaxReport,
    rectify_exterior,
    rectify_relative,
    resample_view,
    tie_parallax,
)
from stereo.dense.matching import NODATA, MatchOptions, MatchStats, match_rasters
from stereo.dense.precision import disparity_sigma
from stereo.dense.triangulate import triangulate_disparity
from stereo.formats.block import BLOCK_FORMAT, BlockOrientation, read_block_orientation
from stereo.formats.cloud import CLOUD_FORMATS, LasWriter
from stereo.formats.orientation import EXTERIOR_FORMAT, read_exterior, read_relative
from stereo.formats.points import point_writer
from stereo.pair.absolute import AbsoluteOrientation
from stereo.pair.intersection import intersect
from stereo.pair.model import ground_unit
from stereo.relative import RelativeOrientation
from stereo.report.dense import HeightComparison, compare_with_dem, save_histogram, save_picture

logger = logging.getLogger(__name__)

__all__ = ["DenseOptions", "DenseResult", "run_dense"]

StrPath = str | Path
Progress = Callable[[str, int, int], None]

#: GDAL block cache while run_dense reads and writes its rasters, MB
GDAL_CACHE_MB = 64
#: disparity window side of one intersection batch (its temporaries are about 1 kB per pixel)
TRIANGULATION_TILE = 256


@dataclass(frozen=True)
class DenseOptions:
    """Options of :func:`run_dense`.

    Attributes
    ----------
    matching : MatchOptions
        Default: :class:`MatchOptions` with holes of up to 200 px filled in the disparity product
        (flagged in band 2 of the confidence raster; filled disparities never become points) and
        the half-resolution hole pass (``hole_p2=128``, issue 30: more complete surfaces on steep
        or low-texture terrain).
    cloud_format : {"las", "laz", "copc", "ply", "none"}
        ``copc``: ``points.copc.laz`` (needs the ``copclib`` package).
    dsm_cell : float or None
        DSM cell side (ground units); default the median ground sampling distance.
    dsm_statistic : {"mean", "min", "max"}
    fill_holes : int
        DSM holes of at most this many cells are interpolated and flagged (0: none).
    min_confidence : float
        Points of lower confidence are left out of the cloud and the DSM (filled disparities have 0).
    interpolation : {"nearest", "linear", "cubic"}
        Resampling into the normal case.
    tile : int
        Tile of the resampling and of the triangulation.
    intersection : str
        Intersection method (``midpoint`` by default: the rectified rays meet exactly).
    reference_dem : path or None
        Compare the DSM with it (same or any CRS; resampled bilinearly onto the DSM grid).
    measure_parallax : bool
        Re-measure the tie points' vertical parallax by LSM in the resampled photos.
    relative_robust : str or None
        With a relative orientation, the dense chain re-estimates it from its own tie points (the
        LSM-refined matches only) with this estimator (:data:`rectify.geometry.robust.ROBUST_METHODS`;
        default Tukey, whose outliers get no weight) and rectifies with it, so that the reported
        parallax is that of the orientation used, on the points it used (its outliers left out and
        counted). None: the given orientation is used as it is. Exterior orientations are always
        used as given.
    despike_cells : float
        DSM cells differing from their 5 x 5 median by more than this many cell sides are removed (0: off).
    dsm_radius : float
        A point counts in the DSM cells within this many cells of it (Gaussian-weighted; 0: its own
        cell only).
    dsm_max_spread : float
        DSM cells whose points' height standard deviation exceeds this many cell sides are dropped
        (0: no test).
    scheduler : str, Scheduler or None
        Where the matching tiles run (``stereo dense --scheduler``): ``threads`` (one tile at a time
        in this process), ``processes[:N]`` (a local Dask cluster of N worker processes) or
        ``tcp://HOST:PORT`` (an existing Dask cluster); None: ``$RECTIFY_SCHEDULER``, else
        ``threads``. See :func:`stereo.dense.matching.match_rasters` and ``docs/scale.md``.
    stac : bool
        Write the STAC Item of the DSM and the point cloud, ``OUTDIR/item.stac.json``.
    """

    matching: MatchOptions = field(default_factory=lambda: MatchOptions(fill_max_px=200, hole_p2=128.0))
    cloud_format: str = "las"
    dsm_cell: float | None = None
    dsm_statistic: str = "mean"
    fill_holes: int = 0
    min_confidence: float = 0.0
    interpolation: str = "cubic"
    tile: int = 1024
    intersection: str = "midpoint"
    reference_dem: str | None = None
    measure_parallax: bool = True
    relative_robust: str | None = "tukey"
    despike_cells: float = 0.0
    dsm_radius: float = 1.0
    dsm_max_spread: float = 2.0
    scheduler: str | Scheduler | None = None
    stac: bool = True

    def __post_init__(self) -> None:
        if self.scheduler is not None and not isinstance(self.scheduler, Scheduler):
            if not isinstance(self.scheduler, str):
                raise InvalidInputError(f"`scheduler` must be a string or a Scheduler; got {self.scheduler!r}")
            if self.scheduler.strip():
                Scheduler.parse(self.scheduler)
        if not isinstance(self.matching, MatchOptions):
            raise InvalidInputError(f"`matching` must be a MatchOptions; got {type(self.matching).__name__}")
        if self.cloud_format not in ("las", "laz", "copc", "ply", "none"):
            raise InvalidInputError(f"unknown point cloud format {self.cloud_format!r}; expected las, laz, copc, ply "
                                    "or none")
        if self.dsm_cell is not None and not (isinstance(self.dsm_cell, (int, float)) and math.isfinite(self.dsm_cell)
                                              and self.dsm_cell > 0):
            raise InvalidInputError(f"`dsm_cell` must be a finite number > 0; got {self.dsm_cell!r}")
        if self.dsm_statistic not in STATISTICS:
            raise InvalidInputError(f"unknown DSM statistic {self.dsm_statistic!r}; expected one of "
                                    f"{list(STATISTICS)}")
        if isinstance(self.fill_holes, bool) or not isinstance(self.fill_holes, int) or self.fill_holes < 0:
            raise InvalidInputError(f"`fill_holes` must be an integer >= 0; got {self.fill_holes!r}")
        if not (isinstance(self.min_confidence, (int, float)) and 0 <= self.min_confidence <= 1):
            raise InvalidInputError(f"`min_confidence` must be in [0, 1]; got {self.min_confidence!r}")
        for name in ("despike_cells", "dsm_radius", "dsm_max_spread"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 100):
                raise InvalidInputError(f"`{name}` must be a number in [0, 100]; got {v!r}")
        if self.dsm_radius > 5:
            raise InvalidInputError(f"`dsm_radius` must be at most 5 cells; got {self.dsm_radius!r}")
        if self.relative_robust is not None:
            if self.relative_robust not in ROBUST_METHODS:
                raise InvalidInputError(f"unknown `relative_robust` {self.relative_robust!r}; expected None or one "
                                        f"of {list(ROBUST_METHODS)}")
        if not isinstance(self.tile, int) or self.tile < 64 or self.tile % 16:
            raise InvalidInputError(f"`tile` must be a multiple of 16, at least 64; got {self.tile!r}")


@dataclass(frozen=True, eq=False)
class DenseResult:
    """What :func:`run_dense` did and wrote."""

    out_dir: Path
    files: tuple[Path, ...]
    rectification: EpipolarRectification
    parallax: ParallaxReport
    matching: MatchStats
    n_points: int
    dsm: DsmResult
    dsm_cell: float
    frame: str
    crs: str | None
    comparison: HeightComparison | None
    control_rmse: float | None
    seconds: float
    crs_note: str | None = None
    control_unit: str = "ground units"
    n_control: int = 0
    gsd: float | None = None
    source: str = ""

    def summary_lines(self) -> list[str]:
        r = self.rectification
        lines = [self.source] if self.source else []
        lines += [
            f"normal case: left {r.left.width} x {r.left.height}, right {r.right.width} x {r.right.height} px, "
            f"principal distance {r.focal_px:.2f} px",
            self.parallax.summary_line(),
            f"disparity: {100 * self.matching.density:.1f}% of the left normal photo "
            f"({100 * self.matching.n_filled / max(1, self.matching.n_valid):.1f}% of them filled), range "
            f"{self.matching.disparity_min:.1f} .. {self.matching.disparity_max:.1f} px, {self.matching.n_tiles} tiles",
            f"points: {self.n_points} ({self.frame} frame)",
        ]
        if self.crs_note:
            lines.append(self.crs_note)
        unit = ground_unit(self.crs, "map") if self.frame == "ground" else "model units"
        cell = f"{self.dsm_cell:g} {unit}"
        if self.gsd is not None:
            cell += f" (the ground pixel {self.gsd:.4g} {unit}, rounded to 2 significant digits)"
        lines.append(f"DSM: {self.dsm.height.shape[1]} x {self.dsm.height.shape[0]} cells of {cell}, origin on whole "
                     f"multiples of the cell, coverage {100 * self.dsm.coverage:.1f}% of the grid, "
                     f"{int(self.dsm.filled.sum())} cells filled")
        if self.control_rmse is not None:
            lines.append(f"absolute orientation to the control (least squares, {self.n_control} full control points, "
                         f"map coordinates): RMSE {self.control_rmse:.3f} {self.control_unit} (3D: the root mean "
                         "square of the residual vectors' lengths)")
        if self.comparison is not None:
            lines.append(self.comparison.summary_line(cell=self.dsm_cell))
        lines.append(f"outputs in {self.out_dir}: " + ", ".join(
            p.relative_to(self.out_dir).as_posix() if p.is_relative_to(self.out_dir) else str(p) for p in self.files))
        lines.append(f"time {self.seconds:.1f} s")
        return lines


def _camera_from(doc: dict[str, Any], camera: StrPath | None, what: str, setting: float | None = None,
                 image: StrPath | None = None) -> Camera:
    if camera is not None:  # any camera file (camera JSON, orthority, OpenCV, COLMAP, Metashape); a zoom camera
        return read_one_camera(camera, focal_setting=setting, image=image)  # at the image's focal setting
    if isinstance(doc.get("camera"), dict):
        return Camera.from_dict(doc["camera"])
    raise InvalidInputError(f"{what} stores no camera; pass --camera")


def _tie_points(matches: StrPath | None, left: StrPath, right: StrPath
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], list[str], int]:
    """Tie points (left, right pixels), their ids and the number of unrefined matches left out.

    Only LSM-refined matches are used: a matches CSV's rows with an empty score (the matcher's
    ``keep_unrefined`` matches, at their raw SIFT positions) are left out; on the NGI pair their
    residual parallax is 0.15 px RMS against 0.096 px for the refined ones.
    """
    if matches is not None:
        m = read_matches(matches)
        tl, tr, ids = m.left, m.right, list(m.ids)
        refined = np.isfinite(m.score) if m.score is not None else np.ones(len(ids), bool)
    else:
        res = match_images(left, right, config=MatcherConfig(verify="fundamental", keep_unrefined=False))
        tl, tr, ids = res.matches.left, res.matches.right, list(res.matches.ids)
        refined = np.ones(len(ids), bool)
    if refined.sum() < 5:
        raise InvalidInputError(f"too few refined tie points for the normal case: {int(refined.sum())} of {len(ids)} "
                                "(at least 5 needed)")
    return tl[refined], tr[refined], [str(i) for i, k in zip(ids, refined, strict=True) if k], int((~refined).sum())


def _robust_keep(q: NDArray[np.float64]) -> NDArray[np.bool_]:
    med = np.median(q)
    s = 1.4826 * np.median(np.abs(q - med))
    return np.asarray(np.abs(q - med) <= max(5 * s, 0.5), bool)


@dataclass(frozen=True, eq=False)
class _Oriented:
    """The orientation the normal case is built from and the tie points it used."""

    rect: EpipolarRectification
    left: NDArray[np.float64]
    right: NDArray[np.float64]
    parallax_px: NDArray[np.float64] | None  # the orientation's own residual parallax of those points
    n_outliers: int
    info: dict[str, Any]


def _orient_ties(doc: dict[str, Any], geometry: Any, exterior: bool, cam_l: Camera, cam_r: Camera,
                 tl: NDArray[np.float64], tr: NDArray[np.float64], ids: list[str], robust: str | None, *,
                 ids_of_orientation: bool = True) -> _Oriented:
    """The normal case of the pair and the tie points of its orientation (outliers left out and counted).

    A relative orientation is re-estimated from the tie points with ``robust`` (see
    :attr:`DenseOptions.relative_robust`) in the given orientation's system, so the model frame is
    the same (left-image: the left photo frame, unit base). Otherwise the given orientation is
    used: the points it flagged as outliers (relative orientation JSON; only when ``ids`` are those
    of its points, ``ids_of_orientation``) and the points whose
    parallax under it is off by more than 5 NMAD (at least 0.5 px) are left out.
    """
    if exterior:
        eo_l, eo_r = geometry

        def build(a: NDArray[np.float64], b: NDArray[np.float64]) -> EpipolarRectification:
            return rectify_exterior(eo_l, eo_r, cam_l, cam_r, tie_left=a, tie_right=b)
    elif robust is not None:
        system = str(doc.get("system") or "left-image")
        if system.startswith("dobrynin-pimshina"):  # the turn of the frame is chosen again from the base
            system = "dobrynin-pimshina"
        ro = RelativeOrientation.from_pixels(tl, tr, cam_l, camera_right=cam_r, system=system, robust=robust,
                                             ids=ids)
        keep = np.asarray((ro.weights > 0) & ~ro.outlier, bool)
        if keep.sum() < 5:
            raise StereoError(f"the relative orientation of the dense chain kept {int(keep.sum())} tie points (at "
                              "least 5 needed)")
        rect = rectify_relative(ro, cam_l, cam_r, tie_left=tl[keep], tie_right=tr[keep])
        q = np.asarray(ro.parallax_px)[keep]
        info = {"source": f"relative orientation re-estimated from the refined tie points ({ro.system}, robust "
                          f"{ro.robust})", "system": ro.system, "robust": ro.robust, "n_used": int(keep.sum()),
                "n_outliers": int((~keep).sum()), "rms_parallax_px": float(np.sqrt(np.mean(q ** 2))),
                "rotation_right": ro.rotation_right.tolist(), "base": ro.base.tolist()}
        return _Oriented(rect, tl[keep], tr[keep], q, int((~keep).sum()), info)
    else:
        def build(a: NDArray[np.float64], b: NDArray[np.float64]) -> EpipolarRectification:
            return rectify_relative(geometry, cam_l, cam_r, tie_left=a, tie_right=b)
    keep = np.ones(len(tl), bool)
    if not exterior and ids_of_orientation:  # the outliers flagged by the given relative orientation
        out = {str(p.get("id")) for p in doc.get("points", []) if isinstance(p, dict) and p.get("outlier")}
        keep = np.array([i not in out for i in ids], bool)
    if keep.sum() < 5:
        raise InvalidInputError(f"too few tie points for the normal case: {int(keep.sum())} (at least 5 needed)")
    q0 = tie_parallax(build(tl[keep], tr[keep]), tl[keep], tr[keep])
    keep[np.flatnonzero(keep)] = _robust_keep(q0.geometric_px)
    rect = build(tl[keep], tr[keep])
    info = {"source": "exterior orientations as given" if exterior else "relative orientation as given",
            "n_used": int(keep.sum()), "n_outliers": int((~keep).sum())}
    return _Oriented(rect, tl[keep], tr[keep], None, int((~keep).sum()), info)


def _ground_transform(control_path: StrPath, rect: EpipolarRectification, cam_l: Camera, cam_r: Camera
                      ) -> tuple[Callable[[NDArray[np.float64]], NDArray[np.float64]], str | None, float, int]:
    """The model -> ground similarity from the control's full points (least squares, in the control's
    coordinates); returns it, the control's CRS, the 3D RMSE of its residuals and the number of points."""
    ctrl = read_control(control_path)
    full = ctrl.is_control
    if full.sum() < 3:
        raise InvalidInputError(f"control file {str(control_path)!r} has {int(full.sum())} full control points; at "
                                "least 3 needed")
    ml = cam_l.photo_from_pixel(ctrl.left[full])
    mr = cam_r.photo_from_pixel(ctrl.right[full])
    inter = intersect(ml, mr, rotation_left=rect.left.rotation, rotation_right=rect.right.rotation, base=rect.base,
                      focal_length_mm=(cam_l.focal_length_mm, cam_r.focal_length_mm), centre_left=rect.centre_left)
    ao = AbsoluteOrientation.from_points(inter.points, ctrl.xyz[full], ids=[ctrl.ids[i] for i in np.flatnonzero(full)],
                                         units="m")
    res = ao(inter.points) - ctrl.xyz[full]
    rmse = float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))
    return ao, ctrl.crs, rmse, int(full.sum())


def _points_at(rect: EpipolarRectification, pix: NDArray[np.float64], d: NDArray[np.float64], transform
               ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Points of rectified left pixels with disparities (midpoint intersection); and which pixels gave one."""
    ml = rect.photo_from_rectified("left", pix)
    mr = rect.photo_from_rectified("right", np.column_stack([pix[:, 0] - d, pix[:, 1]]))
    ok = np.isfinite(ml).all(1) & np.isfinite(mr).all(1) & (d + rect.disparity_offset > 1e-6)
    inter = intersect(ml[ok], mr[ok], rotation_left=rect.left.rotation, rotation_right=rect.right.rotation,
                      base=rect.base, focal_length_mm=(rect.left.camera.focal_length_mm,
                                                       rect.right.camera.focal_length_mm),
                      centre_left=rect.centre_left, method="midpoint")
    xyz = np.array(inter.points)
    if transform is not None:
        xyz = np.asarray(transform(xyz), dtype=np.float64).reshape(-1, 3)
    return xyz, ok


def _sample_points(rect: EpipolarRectification, disp_path: Path, transform, step: int = 8
                   ) -> tuple[NDArray[np.float64], float]:
    """Points of every ``step``-th disparity (for the DSM bounds) and the median ground sampling distance."""
    pts, gsd = [], []
    with WindowReader(disp_path) as rd, ignore_not_georeferenced():
        for c0, r0, w, h in iter_windows(rd.width, rd.height, 2048):
            d, _ = rd.read(c0, r0, w, h)
            sub = d[::step, ::step, 0].astype(np.float64)
            sub[sub == NODATA] = np.nan
            rr, cc = np.nonzero(np.isfinite(sub))
            if len(rr) == 0:
                continue
            pix = np.column_stack([cc * step + c0, rr * step + r0]).astype(np.float64)
            dd = sub[rr, cc]
            a, ok_a = _points_at(rect, pix, dd, transform)
            b, ok_b = _points_at(rect, pix + [1.0, 0.0], dd, transform)
            pts.append(a)
            both = ok_a & ok_b
            ga = a[both[ok_a]]
            gb = b[both[ok_b]]
            gsd.append(np.linalg.norm(ga[:, :2] - gb[:, :2], axis=1))
    if not pts or sum(len(p) for p in pts) == 0:
        raise StereoError("no 3D points: the disparities give no intersection in front of both cameras")
    g = np.concatenate(gsd) if gsd else np.array([])
    g = g[np.isfinite(g) & (g > 0)]
    return np.vstack(pts), float(np.median(g)) if g.size else float("nan")


def run_dense(
    orientation: StrPath,
    left: StrPath,
    right: StrPath,
    out_dir: StrPath,
    *,
    right_orientation: StrPath | None = None,
    camera: StrPath | None = None,
    matches: StrPath | None = None,
    control: StrPath | None = None,
    options: DenseOptions | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
    left_id: str | None = None,
    right_id: str | None = None,
    focal_settings: tuple[float | None, float | None] = (None, None),
) -> DenseResult:
    """The dense chain of an oriented frame pair.

    Parameters
    ----------
    orientation : path
        ``ro.json`` (relative orientation, ``stereo orient``), the left photo's exterior orientation
        JSON (then ``right_orientation`` is the right one's), or the ``orientation.json`` of
        ``stereo block`` (format ``rectify-stereo/block-orientation``: both photos' poses and cameras,
        picked by ``left_id``/``right_id``).
    left, right : path
        The original photos.
    out_dir : path
        Output folder (created; see the module docstring for its files).
    right_orientation : path, optional
        Right exterior orientation JSON (with an exterior ``orientation``).
    camera : path, optional
        Camera JSON; default the camera stored in the orientation file.
    matches : path, optional
        Tie points CSV (pixels), e.g. ``stereo orient --matches-out``; without it the photos are matched
        (SIFT, fundamental verification, LSM).
    control : path, optional
        Stereo control CSV: the model is oriented to the ground (7-parameter similarity) and the
        products are in the control's CRS.
    options : DenseOptions, optional
        Its ``scheduler`` says where the matching tiles run (local threads or Dask).
    overwrite : bool
    progress : callable(stage, done, total), optional
    left_id, right_id : str, optional
        With a block orientation: the image ids of the two photos in it (default: the block image
        whose name, or name without extension, is the photo's file name).
    focal_settings : (left, right)
        With a zoom camera (``--camera``, ``stereo calibrate --zoom``): the photos' focal settings
        (``--focal-setting``); None: the photo's EXIF FocalLength. Refused with another camera.

    The products of a ground frame (exterior orientations, a block, control) are in the CRS the
    orientation or control file names; when it names none and both photos name the same CRS, that
    one (said in the summary); when none is known the summary says so (and a warning is logged).

    Returns
    -------
    DenseResult

    Raises
    ------
    InvalidInputError, RasterIOError, CRSError, StereoError, EstimationError, SchedulerError
        One-line messages; nothing is left in ``out_dir`` on an error.
    """
    bound_gdal_cache()  # before any pixel IO
    t0 = time.perf_counter()
    opts = options or DenseOptions()
    if not isinstance(opts, DenseOptions):
        raise InvalidInputError(f"`options` must be a DenseOptions; got {type(opts).__name__}")
    scheduler = resolve_scheduler(opts.scheduler)  # a bad value (or $RECTIFY_SCHEDULER) fails before any work
    for name, p in (("orientation", orientation), ("left", left), ("right", right), ("right_orientation",
                    right_orientation), ("camera", camera), ("matches", matches), ("control", control),
                    ("reference DEM", opts.reference_dem)):
        if p is not None and not Path(p).is_file():
            raise InvalidInputError(f"{name} file not found: {str(p)!r}")
    zs = tuple(focal_settings)
    if any(z is not None for z in zs) and not (camera is not None and is_zoom_camera(camera)):
        given = ",".join(dict.fromkeys(f"{z:g}" for z in zs if z is not None))
        raise InvalidInputError(f"--focal-setting {given} goes with a zoom camera (--camera of stereo calibrate "
                                "--zoom)")
    scheduler = check_scheduler(scheduler)  # a cluster: reachable, a Dask scheduler, with a worker
    doc = read_json(orientation, "orientation file")
    if not isinstance(doc, dict):
        raise InvalidInputError(f"{str(orientation)!r} is not an orientation JSON object")
    block = doc.get("format") == BLOCK_FORMAT
    if not block and (left_id is not None or right_id is not None):
        raise InvalidInputError(f"--left-id/--right-id go with a block orientation (orientation.json of `stereo "
                                f"block`); {str(orientation)!r} is not one")
    if block and right_orientation is not None:
        raise InvalidInputError(f"{str(orientation)!r} is a block orientation: it holds both photos (picked by "
                                "--left-id/--right-id); --right-orientation goes with an exterior orientation")
    exterior = block or doc.get("format") == EXTERIOR_FORMAT or ("position" in doc and "rotation_left" not in doc)
    if exterior and not block and right_orientation is None:
        raise InvalidInputError(f"{str(orientation)!r} is an exterior orientation: pass the right photo's with "
                                "--right-orientation")
    if not exterior and right_orientation is not None:
        raise InvalidInputError("--right-orientation goes with an exterior orientation, not a relative one")
    source = ""
    crs_from = "the orientation file"
    if block:
        bo = read_block_orientation(orientation)
        eo_l, eo_r = _block_pose(bo, left_id, left, "left", orientation), _block_pose(bo, right_id, right, "right",
                                                                                     orientation)
        if eo_l.image == eo_r.image:
            raise InvalidInputError(f"the left and right photos are the same block image {eo_l.image!r}: pass "
                                    "--left-id/--right-id")
        cam_l = (read_one_camera(camera, eo_l.camera, named_by="the block", focal_setting=zs[0], image=left)
                 if camera is not None else bo.cameras[eo_l.camera])
        cam_r = (read_one_camera(camera, eo_r.camera, named_by="the block", focal_setting=zs[1], image=right)
                 if camera is not None else bo.cameras[eo_r.camera])
        crs = bo.crs
        source = (f"orientation: block images {eo_l.image!r} (left) and {eo_r.image!r} (right) of {str(orientation)!r}"
                  f" (cameras {eo_l.camera!r}, {eo_r.camera!r})")
    elif exterior:
        cam_l = _camera_from(doc, camera, repr(str(orientation)), zs[0], left)
        doc_r = read_json(right_orientation, "orientation file")  # type: ignore[arg-type]
        cam_r = _camera_from(doc_r if isinstance(doc_r, dict) else {}, camera, repr(str(right_orientation)), zs[1],
                             right)
        eo_l, eo_r = read_exterior(orientation), read_exterior(right_orientation)  # type: ignore[arg-type]
        if eo_l.crs and eo_r.crs and not same_crs(eo_l.crs, eo_r.crs):
            raise InvalidInputError(f"the exterior orientations {str(orientation)!r} and {str(right_orientation)!r} "
                                    "name different CRSs: both photos must be oriented in one ground frame")
        crs = eo_l.crs or eo_r.crs
        crs_from = "the orientation files"
    else:
        cam_l = _camera_from(doc, camera, repr(str(orientation)), zs[0], left)
        ro = read_relative(orientation)
        cam_r = (_camera_from(doc, camera, repr(str(orientation)), zs[1], right)
                 if camera is not None and is_zoom_camera(camera) else cam_l)
        crs = None
    photo_crs = []
    for path, cam in ((left, cam_l), (right, cam_r)):
        ds = raster_info(path)
        if (ds.width, ds.height) != (cam.width, cam.height):
            raise InvalidInputError(f"photo {str(path)!r} is {ds.width} x {ds.height} px but the camera is "
                                    f"{cam.width} x {cam.height} px")
        photo_crs.append(ds.crs)
    suffix = {"las": ".las", "laz": ".laz", "copc": ".copc.laz", "ply": ".ply"}.get(opts.cloud_format)
    names = ["left_normal.tif", "right_normal.tif", "disparity.tif", "confidence.tif", "dsm.tif", "dense.json"]
    if suffix:
        names.append("points" + suffix)
    if opts.stac:
        names.append(FOLDER_ITEM)
    out = Path(out_dir)
    ws = Workspace(out, overwrite=overwrite, report_dir=out / "report",
                   inputs=[p for p in (orientation, left, right, right_orientation, camera, matches, control,
                                       opts.reference_dem) if p])
    _plan_outputs(ws, names, opts)  # every output and report file against every input; nothing is created yet

    def prog(stage: str) -> Callable[[int, int], None] | None:
        if progress is None:
            return None
        return lambda d, t: progress(stage, d, t)

    tl, tr, tie_ids, n_unrefined = _tie_points(matches, left, right)
    oriented = _orient_ties(doc, (eo_l, eo_r) if exterior else ro, exterior, cam_l, cam_r, tl, tr, tie_ids,
                            opts.relative_robust, ids_of_orientation=matches is not None)
    rect, tl, tr = oriented.rect, oriented.left, oriented.right
    transform = None
    control_rmse = None
    n_control = 0
    frame = "ground" if exterior else "model"
    if control is not None:
        transform, crs, control_rmse, n_control = _ground_transform(control, rect, cam_l, cam_r)
        frame = "ground"
        crs_from = "the control file"
    crs, crs_note = _ground_crs(crs, crs_from, photo_crs, frame)
    files: list[Path] = []
    rep = out / "report"
    rep_files: list[Path] = []
    try:
        ws.prepare()  # the output folder, created only now (removed again on any error, SIGTERM included)
        # GDAL's block cache (default 5 % of the RAM) would hold the rasters read and written here:
        # bounded, so that memory stays that of the tiles whatever the photo size
        with gdal_cache_limit(GDAL_CACHE_MB), ws.transaction(), \
                contextlib.ExitStack() as stack:
            paths: dict[str, Path] = {}
            for n in names:
                paths[n] = stack.enter_context(ws.output(out / n))
                files.append(out / n)
            resample_view(rect, "left", left, paths["left_normal.tif"], interpolation=opts.interpolation,
                          tile=opts.tile, progress=prog("resample left"))
            resample_view(rect, "right", right, paths["right_normal.tif"], interpolation=opts.interpolation,
                          tile=opts.tile, progress=prog("resample right"))
            par = tie_parallax(rect, tl, tr, left_path=paths["left_normal.tif"] if opts.measure_parallax else None,
                               right_path=paths["right_normal.tif"] if opts.measure_parallax else None,
                               orientation_px=oriented.parallax_px, n_outliers=oriented.n_outliers,
                               n_unrefined=n_unrefined)
            ties = np.column_stack([rect.rectified_from_original("left", tl), par.disparity_px])
            stats = match_rasters(paths["left_normal.tif"], paths["right_normal.tif"], paths["disparity.tif"],
                                  paths["confidence.tif"], tie_points=ties, options=opts.matching,
                                  progress=prog("matching"), scheduler=scheduler)
            sample, gsd = _sample_points(rect, paths["disparity.tif"], transform)
            if opts.dsm_cell is None and not (math.isfinite(gsd) and gsd > 0):
                raise StereoError(f"cannot derive the DSM cell from the ground sampling distance ({gsd!r}); pass "
                                  "--dsm-cell")
            cell = float(opts.dsm_cell) if opts.dsm_cell is not None else default_cell(gsd)
            lo, hi = np.percentile(sample, 0.1, axis=0), np.percentile(sample, 99.9, axis=0)
            span = hi - lo
            bounds = (lo[0] - 0.02 * span[0] - cell, lo[1] - 0.02 * span[1] - cell, hi[0] + 0.02 * span[0] + cell,
                      hi[1] + 0.02 * span[1] + cell)
            heights = (f"{ground_unit(crs, 'map')}, the heights of {crs_from}" if frame == "ground"
                       else "model units: the relative orientation's frame, base length 1")
            grid = DsmGrid(bounds, cell, statistic=opts.dsm_statistic, crs=crs, radius=opts.dsm_radius,
                           max_spread=opts.dsm_max_spread, heights=heights)
            n_pts = _triangulate_all(rect, paths, grid, transform, opts, suffix, crs, frame, prog("points"))
            dsm = grid.result(max_hole_cells=opts.fill_holes, despike_cells=opts.despike_cells)
            dsm.write(paths["dsm.tif"], overwrite=True)
            comparison = None
            dz = None
            if opts.reference_dem is not None:
                comparison, dz = compare_with_dem(dsm, opts.reference_dem)
            summary = {
                "frame": frame, "crs": crs, "crs_note": crs_note, "dsm_cell": cell, "n_points": n_pts,
                "ground_sampling_distance": gsd, "source": source or None,
                "vertical_parallax_px": {"rms_mapped": par.rms_geometric_px, "rms_measured": par.rms_measured_px,
                                         "n": len(par.geometric_px), "n_measured": par.n_measured,
                                         "rms_orientation": par.rms_orientation_px,
                                         "n_outliers": par.n_outliers, "n_unrefined": par.n_unrefined},
                "orientation": oriented.info,
                "disparity": {"density": stats.density, "n_filled": stats.n_filled, "min": stats.disparity_min,
                              "max": stats.disparity_max, "tiles": stats.n_tiles},
                "dsm": {"width": int(dsm.height.shape[1]), "height": int(dsm.height.shape[0]),
                        "coverage": dsm.coverage, "filled_cells": int(dsm.filled.sum())},
                "control_rmse": control_rmse, "control_unit": ground_unit(crs, "map") if control else None,
                "n_control": n_control,
                "comparison": None if comparison is None else {k: v for k, v in comparison.__dict__.items()
                                                               if k != "histogram"},
                "rectification": rect.to_dict(),
            }
            with open(paths["dense.json"], "w", encoding="utf-8") as fh:
                json.dump(json_safe(summary), fh, indent=2)
            with ws.report_folder() as stage:  # staged: committed with the other outputs
                _picture_from_raster(paths["disparity.tif"], stage / "disparity.png", "disparity (px)")
                save_picture(stage / "dsm.png", dsm.height, title="DSM", cmap="terrain", label="height",
                             nodata=-9999.0)
                rep_files += [rep / "disparity.png", rep / "dsm.png"]
                if comparison is not None and dz is not None:
                    save_histogram(stage / "dz_histogram.png", comparison)
                    save_picture(stage / "dz.png", dz, title="DSM - reference DEM", cmap="RdBu_r", label="dz",
                                 symmetric=True)
                    rep_files += [rep / "dz_histogram.png", rep / "dz.png"]
            if opts.stac:  # the STAC Item of the DSM and the point cloud, committed with them
                acc: dict[str, float] = {k: v for k, v in (
                    ("vertical_parallax_rms_px", par.rms_geometric_px), ("disparity_density", stats.density),
                    ("control_rmse", control_rmse), ("dsm_coverage", dsm.coverage)) if v is not None}
                if comparison is not None:
                    acc.update({f"reference_dem_{k}": v for k, v in comparison.__dict__.items()
                                if isinstance(v, (int, float)) and not isinstance(v, bool)})
                assets = {"dsm": StacAsset(out / "dsm.tif", ("data",), "DSM", source=paths["dsm.tif"]),
                          "metadata": StacAsset(out / "dense.json", ("metadata",), "summary",
                                                source=paths["dense.json"])}
                if suffix:
                    assets["points"] = StacAsset(out / ("points" + suffix), ("data",), "point cloud",
                                                 source=paths["points" + suffix],
                                                 media_type="application/vnd.laszip+copc" if suffix == ".copc.laz"
                                                 else None)
                Path(paths[FOLDER_ITEM]).write_text(stac_text(
                    out / FOLDER_ITEM, item_id=out.name or "dense", assets=assets, command="stereo dense",
                    grid=raster_grid(paths["dsm.tif"]) if crs is not None else None, accuracy=acc,
                    options=options_of(opts, orientation=orientation, camera=camera, control=control),
                    inputs=[orientation, left, right, right_orientation, camera, matches, control]), encoding="utf-8")
    except BaseException:
        ws.discard_root()
        raise
    return DenseResult(out, tuple(files + rep_files), rect, par, stats, n_pts, dsm, cell, frame, crs, comparison,
                       control_rmse, time.perf_counter() - t0, crs_note, ground_unit(crs, "map"), n_control,
                       gsd if opts.dsm_cell is None else None, source)


#: the files of the report folder (``report/``) of ``stereo dense``; the last two with a reference DEM
REPORT_FILES = ("disparity.png", "dsm.png", "dz_histogram.png", "dz.png")


def _plan_outputs(ws: Workspace, names: list[str], opts: DenseOptions) -> None:
    """Check the output folder, its files and the report's before any work; create nothing.

    Raises when the folder is a file or lies below one, when an output exists without ``overwrite``,
    and when an output or report file is one of the inputs (resolved: symlinks, ``..``, hard links;
    even with ``overwrite``), e.g. a ``--reference-dem`` at ``OUT/dsm.tif``.
    """
    root = ws.root
    assert root is not None and ws.report_dir is not None
    if root.exists() and not root.is_dir():
        raise InvalidInputError(f"output {str(root)!r} exists and is not a folder")
    report = REPORT_FILES if opts.reference_dem is not None else REPORT_FILES[:2]
    ws.plan(*(root / n for n in names), *(ws.report_dir / n for n in report))
    ws.check_report_dir()


def _block_pose(bo: BlockOrientation, image_id: str | None, photo: StrPath, side: str, path: StrPath) -> Any:
    """The pose of one photo in a block orientation: ``image_id``, else the image named as the photo's file
    (with or without its extension)."""
    names = [q.image for q in bo.poses]
    listed = f"images: {names[:10]}{' ...' if len(names) > 10 else ''}"
    if image_id is not None:
        hits = [q for q in bo.poses if q.image == image_id]
        if not hits:
            raise InvalidInputError(f"--{side}-id {image_id!r} is not an image of the block orientation {str(path)!r} "
                                    f"({listed})")
        return hits[0]
    p = Path(photo)
    hits = [q for q in bo.poses if q.image == p.name] or [q for q in bo.poses if Path(q.image).stem == p.stem]
    if len(hits) != 1:
        what = "is not" if not hits else "is ambiguous"
        raise InvalidInputError(f"the {side} photo {p.name!r} {what} in the block orientation {str(path)!r} "
                                f"({listed}): pass --{side}-id")
    return hits[0]


def _ground_crs(crs: str | None, crs_from: str, photo_crs: list[str | None], frame: str
                ) -> tuple[str | None, str | None]:
    """The CRS of the products and the line that says where it came from (None: nothing to say).

    A ground frame without a CRS in its orientation or control file takes the photos' CRS when both
    name the same one; otherwise the products are written without a CRS, and the line (and a logged
    warning) says so. The model frame has no CRS.
    """
    if frame != "ground" or crs:
        return crs, None
    a, b = photo_crs
    if a and b and same_crs(a, b):
        note = (f"CRS: taken from the photos ({crs_label(a)}): there is none in {crs_from}; the ground coordinates "
                "are assumed to be in it")
        logger.info("%s", note)
        return a, note
    why = (f"the photos name different ones ({crs_label(a)}, {crs_label(b)})" if a and b else
           "none in the photos" if not (a or b) else f"only the {'left' if a else 'right'} photo names one")
    note = (f"warning: no CRS: none in {crs_from}, {why}; dsm.tif and the point cloud are written without a CRS "
            "(give it in the orientation file, key `crs`)")
    logger.warning("%s", note)
    return None, note


def _picture_from_raster(src: Path, dst: Path, title: str) -> None:
    data, valid, _ = read_overview(src, 1500)
    g = data[:, :, 0].astype(np.float64)
    g[(g == NODATA) | ~valid] = np.nan
    save_picture(dst, g, title=title, cmap="viridis", label="px")


def _disparity_sigma_window(rd: WindowReader, rl: WindowReader, rr: WindowReader, c0: int, r0: int, w: int,
                            h: int) -> NDArray[np.float32]:
    """Standard errors (px) of the disparities of a window (:func:`stereo.dense.precision.disparity_sigma`;
    NaN where none): read with a margin for the fit's window, the right photo over the columns the
    window's disparities reach."""
    m = 6  # margin of the sigma window (the fit's radius 3 and the gradient)
    a0, b0 = max(c0 - m, 0), max(r0 - m, 0)
    a1, b1 = min(c0 + w + m, rd.width), min(r0 + h + m, rd.height)
    dm, _ = rd.read(a0, b0, a1 - a0, b1 - b0)
    dmm = dm[:, :, 0].astype(np.float32)
    dmm[dmm == NODATA] = np.nan
    if not np.isfinite(dmm).any():
        return np.full((h, w), np.nan, np.float32)
    q0 = int(max(0, math.floor(a0 - float(np.nanmax(dmm))) - m))
    q1 = int(min(rr.width, math.ceil(a1 - float(np.nanmin(dmm))) + m))
    if q1 <= q0:
        return np.full((h, w), np.nan, np.float32)
    L, _ = rl.read(a0, b0, a1 - a0, b1 - b0)
    R, _ = rr.read(q0, b0, q1 - q0, b1 - b0)
    sd = disparity_sigma(L.astype(np.float32).mean(axis=2), R.astype(np.float32).mean(axis=2), dmm,
                         right_offset=float(a0 - q0))
    return sd[r0 - b0:r0 - b0 + h, c0 - a0:c0 - a0 + w]


def _height_sigma(rect: EpipolarRectification, model_xyz: NDArray[np.float64], xyz: NDArray[np.float64],
                  sigma_px: NDArray[np.float64], transform) -> NDArray[np.float64]:
    """Height standard errors (output frame units) of points from their disparity standard errors (px).

    A disparity error ``dp`` moves a point along the left ray: ``dv = v Z dp / (B f)`` (``v`` from the
    left centre to the point, ``Z`` its depth along the normal case's axis, ``B`` the base, ``f`` the
    normal principal distance in px; ``docs/surface.md``); the height error is the z change of the
    transformed point (the transform to the ground frame, when there is one, linearised).
    """
    v = model_xyz - rect.centre_left
    a = rect.normal_rotation[:, 2] / np.linalg.norm(rect.normal_rotation[:, 2])
    depth = np.abs(v @ a)
    dv = v * (depth * sigma_px / (float(np.linalg.norm(rect.base)) * rect.focal_px))[:, None]
    if transform is None:
        return np.abs(dv[:, 2])
    moved = np.asarray(transform(model_xyz + dv), dtype=np.float64).reshape(-1, 3)
    return np.abs(moved[:, 2] - xyz[:, 2])


def _triangulate_all(rect: EpipolarRectification, paths: dict[str, Path], grid: DsmGrid, transform,
                     opts: DenseOptions, suffix: str | None, crs: str | None, frame: str,
                     progress: Callable[[int, int], None] | None) -> int:
    """Triangulate every disparity window into the DSM grid and the point cloud (LAS/LAZ/COPC: with the
    ``sigma_z`` extra dimension from :func:`_disparity_sigma_window`; NaN where the fit gave none)."""
    writer = None
    n = 0
    fmt = opts.cloud_format
    with_sigma = fmt in CLOUD_FORMATS
    dims = ["sigma_z"] if with_sigma else []
    try:
        with WindowReader(paths["disparity.tif"]) as rd, WindowReader(paths["confidence.tif"]) as rc, \
                WindowReader(paths["left_normal.tif"]) as rl, WindowReader(paths["right_normal.tif"]) as rr_, \
                ignore_not_georeferenced():
            windows = list(iter_windows(rd.width, rd.height, min(opts.tile, TRIANGULATION_TILE)))
            for i, (c0, r0, w, h) in enumerate(windows):
                d, _ = rd.read(c0, r0, w, h)
                cf, _ = rc.read(c0, r0, w, h)
                disp = d[:, :, 0].astype(np.float64)
                disp[disp == NODATA] = np.nan
                # filled disparities (band 2 of the confidence) are for the disparity product only
                mask = np.isfinite(disp) & (cf[:, :, 1] == 0)
                if opts.min_confidence > 0:
                    mask &= cf[:, :, 0] >= opts.min_confidence
                pts = triangulate_disparity(rect, disp, col_off=c0, row_off=r0, mask=mask, method=opts.intersection)
                if len(pts):
                    xyz = pts.xyz if transform is None else \
                        np.asarray(transform(pts.xyz), dtype=np.float64).reshape(-1, 3)
                    grid.add(xyz)
                    if suffix is not None:
                        img, _ = rl.read(c0, r0, w, h)
                        rr = (pts.pixel[:, 1] - r0).astype(np.int64)
                        cc = (pts.pixel[:, 0] - c0).astype(np.int64)
                        col = img[rr, cc]
                        if col.shape[1] < 3:
                            col = np.repeat(col[:, :1], 3, axis=1)
                        col = col[:, :3]
                        if col.dtype != np.uint8:
                            col = np.clip(col.astype(np.float64) / max(1.0, float(np.percentile(col, 99))) * 255,
                                          0, 255)
                        extra = None
                        if with_sigma:
                            s_px = _disparity_sigma_window(rd, rl, rr_, c0, r0, w, h)[rr, cc].astype(np.float64)
                            extra = {"sigma_z": _height_sigma(rect, pts.xyz, xyz, s_px, transform)}
                        if writer is None:
                            writer = point_writer(paths["points" + suffix], fmt, offset=np.round(xyz[0], 0),
                                                  crs_wkt=crs, comment=f"{frame} frame", extra_dims=dims)
                        if isinstance(writer, LasWriter):
                            writer.write(xyz, col, extra)
                        else:
                            writer.write(xyz, col)
                    n += len(pts)
                if progress is not None:
                    progress(i + 1, len(windows))
        if suffix is not None:
            if writer is None:
                writer = point_writer(paths["points" + suffix], fmt, offset=(0, 0, 0), crs_wkt=crs,
                                      comment=f"{frame} frame", extra_dims=dims)
            writer.close()
    except BaseException:
        if writer is not None:  # the staging file of a COPC cloud, the body of a PLY: removed
            with contextlib.suppress(Exception):
                writer.abort() if isinstance(writer, LasWriter) else writer.close()
        raise
    return n
