"""``stereo block``: a block of images from tie points to an adjusted orientation, points and a report.

Steps (each in its own module):

1. the workspace checks every planned output and the report folder before any work;
2. the inputs, of any format :mod:`stereo.formats.detect` recognises: one camera file for every
   image (or the cameras of the pose file); known poses from a position/angle CSV, an OpenSfM
   ``reconstruction.json``, a COLMAP model (its tracks spare the matching), a Metashape XML or
   orthority's files, or GNSS positions from ODM's ``geo.txt``; the control from the block control
   CSV, ODM's ``gcp_list.txt`` or Metashape markers (:mod:`stereo.actions.block_users`);
3. block tie points: pairs from footprints (poses known) or all pairs / an overview match,
   tracks by union-find, evenly spread (:mod:`stereo.features.tracks`); the control points'
   image measurements join them as tracks of their own;
4. initial orientation: with known poses the tracks are intersected through them; without,
   a chain of independent models joined by 7-parameter similarities and brought to the ground
   by control and/or GNSS positions (:mod:`stereo.block.independent`, :mod:`stereo.block.models`);
5. the bundle adjustment with the observation groups and their precisions
   (:mod:`stereo.block.bundle.adjust`);
6. the outputs, all or none (the layout in :data:`BLOCK_LAYOUT`, ``camera_<id>.json`` per camera),
   the report, the STAC Item of the point cloud and the requested exports (COLMAP, OpenSfM,
   orthority).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.actions.workspace import StrPath, Workspace
from rectify.errors import InvalidInputError
from rectify.formats.camera import camera_document
from rectify.formats.detect import input_paths, read_camera_file
from rectify.geometry.camera import Camera
from rectify.geometry.crs import parse_crs, same_crs
from rectify.geometry.residuals import rms
from stereo.actions import block_frame as bf
from stereo.actions.block_checks import check_block_inputs, check_datum
from stereo.actions.block_models import MODEL_METHOD, ModelMethodOptions, check_block_method, run_models
from stereo.actions.block_report import block_report, check_accuracy, rms_labels
from stereo.actions.block_users import (
    FOLDER_ITEM,
    BlockExports,
    block_stac,
    block_tracks,
    check_exports,
    export_folders,
    geo_gnss,
    plan_exports,
    write_exports,
)
from stereo.actions.block_zoom import zoom_block
from stereo.actions.workspace import PairWorkspace
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.result import BundleResult
from stereo.block.bundle.systematic import summary_dict as systematic_summary
from stereo.block.frames import FRAME_KINDS
from stereo.block.independent import independent_models, to_ground, triangulate_tracks
from stereo.block.models import IndependentOptions
from stereo.block.types import BlockControl, GnssObservations, Pose, Tracks
from stereo.features.tracks import BlockMatchOptions, block_tie_points
from stereo.formats.block import BlockControlTable, block_orientation_text, observations_text, read_block_control
from stereo.formats.detect import read_control_file, resolve_control
from stereo.formats.odm import OdmGeo, detect_odm_gcps
from stereo.formats.opensfm import crs_label
from stereo.formats.points import LasWriter, dump_ply, points_csv_text
from stereo.formats.poses import pose_csv_text
from stereo.formats.trajectory import PoseExtras, block_gnss, image_times_names, read_poses_with_extras

__all__ = ["BLOCK_LAYOUT", "FRAME_KINDS", "BlockExports", "BlockOptions", "BlockResult", "run_block"]

Progress = Callable[[int, int], None]

#: the files of ``stereo block``'s output folder, by role
BLOCK_LAYOUT = {
    "orientation": "orientation.json",
    "poses": "poses.csv",
    "points": "points.ply",
    "points_csv": "points.csv",
    "points_las": "points.las",
    "observations": "observations.csv",
}
_REPORT = "report"
DEFAULT_CAMERA = "camera"


@dataclass(frozen=True)
class BlockOptions:
    """Options of ``stereo block`` (the bundle's numerical options are in ``bundle``).

    Attributes
    ----------
    gnss_sigma_m : (3,) float or None
        A-priori standard deviations (x, y, z), metres, of the GNSS projection centres. When set
        (or when the pose file has ``sx, sy, sz``), the positions of the pose file are
        observations of the adjustment; otherwise they are only initial values. An OpenSfM
        reconstruction's shots with ``gps_position`` are observed there (with this sigma, else
        their ``gps_dop``); without any, this makes its projection centres observations.
    ins_sigma_rad : (3,) float or None
        A-priori standard deviations of the angles of the pose file (omega, phi, kappa), radians;
        when set the angles are observations too.
    control_sigma_m : (3,) float
        Default a-priori standard deviations of control coordinates (x, y, z), ground units, where
        the control file gives none.
    control_sigma_px : float
        A-priori standard deviation of the control points' image measurements, pixels.
    tie_sigma_px : float
        A-priori standard deviation of the tie-point measurements, pixels.
    check_ids : tuple of str
        Control ids withheld from the adjustment and used as check points.
    lever_arm_m : (3,) float or None
        GNSS antenna offset in the camera frame, metres (for a navigation pose file).
    boresight_rad : (3,) float or None
        Boresight angles of the camera in the INS body frame (for a navigation pose file).
    ground_z : float or None
        Mean terrain height for the footprints (default: from control, else 0 below the lowest
        camera's flying height estimate).
    match : BlockMatchOptions
        Tie-point options.
    bundle : BundleOptions
        Adjustment options (image sigma, robust estimator, self-calibration, ...). The default is
        Tukey's robust weights with variance components per group: a-priori sigmas of tie points,
        GNSS and control are rarely known to better than a factor of two, and one wrong group sigma
        would make every predicted standard error wrong. Up to 100 iterations in all (the
        variance-component rounds included): a start from independent models can be metres off,
        and the robust stages come on top.
    report : bool
        Write the QA report into ``OUTDIR/report``.
    reuse_tracks : bool
        Take the tracks of a pose file that has some (a COLMAP model) as the tie points, sparing the
        matching, when they reach every image (``--rematch``: False).
    stac : bool
        Write the STAC Item of the point cloud, ``OUTDIR/item.stac.json``.
    exports : BlockExports
        Folders to write the adjusted block into in other tools' formats (COLMAP, OpenSfM, orthority).
    frame : {"topocentric", "geocentric", "map"} or None
        The adjustment frame (:mod:`stereo.block.frames`); None: topocentric with a CRS, else map.
    trajectory : path or None
        A GNSS/INS trajectory CSV (:mod:`stereo.formats.trajectory`): the pose file is then an image-times
        CSV (``image,time[,strip]``) and the poses are the trajectory's at the images' times.
    method : {"bundle", "independent-models"}
        The adjustment; ``models`` the options of independent models (:mod:`stereo.actions.block_models`).
    focal_settings : path or None
        With a zoom camera: a settings CSV ``image,setting`` (default each image's EXIF FocalLength;
        :mod:`stereo.actions.block_zoom`).
    """

    gnss_sigma_m: tuple[float, float, float] | None = None
    ins_sigma_rad: tuple[float, float, float] | None = None
    control_sigma_m: tuple[float, float, float] = (0.05, 0.05, 0.05)
    control_sigma_px: float = 1.0
    tie_sigma_px: float = 1.0
    check_ids: tuple[str, ...] = ()
    lever_arm_m: tuple[float, float, float] | None = None
    boresight_rad: tuple[float, float, float] | None = None
    ground_z: float | None = None
    match: BlockMatchOptions = field(default_factory=BlockMatchOptions)
    bundle: BundleOptions = field(default_factory=lambda: BundleOptions(robust="tukey", variance_components=True,
                                                                        max_iterations=100))
    report: bool = True
    reuse_tracks: bool = True
    stac: bool = True
    exports: BlockExports = field(default_factory=BlockExports)
    frame: str | None = None
    trajectory: str | None = None
    method: str = "bundle"
    models: ModelMethodOptions = field(default_factory=ModelMethodOptions)
    focal_settings: str | None = None

    def __post_init__(self) -> None:
        check_block_method(self.method, self.models, self.bundle)
        for name in ("gnss_sigma_m", "ins_sigma_rad", "control_sigma_m"):
            v = getattr(self, name)
            if v is None:
                continue
            t = tuple(float(x) for x in v)
            if len(t) != 3 or not all(math.isfinite(x) and x > 0 for x in t):
                raise InvalidInputError(f"`{name}` must be three finite numbers > 0; got {v!r}")
            object.__setattr__(self, name, t)
        for name in ("control_sigma_px", "tie_sigma_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InvalidInputError(f"`{name}` must be a finite number > 0; got {v!r}")
        object.__setattr__(self, "check_ids", tuple(str(s) for s in self.check_ids))


@dataclass(frozen=True, eq=False)
class BlockResult:
    """Result of :func:`run_block`: the adjustment, the inputs it used and the files written."""

    bundle: BundleResult
    tracks: Tracks
    n_tie_points: int
    n_control: int
    n_check: int
    initial: str
    out_dir: Path
    files: tuple[Path, ...]
    report: Path | None
    timings_s: dict[str, float] = field(default_factory=dict)
    tie_lines: tuple[str, ...] = ()
    n_points_written: int = 0
    input_lines: tuple[str, ...] = ()
    method_lines: tuple[str, ...] = ()  # in place of the bundle's lines (--method independent-models)

    def summary_lines(self) -> list[str]:
        out = list(self.input_lines)
        out.extend(self.tie_lines)
        out.append(f"initial orientation: {self.initial}")
        out.extend(self.method_lines or self.bundle.summary_lines())
        acc = check_accuracy(self.bundle)
        if acc is not None:
            out.extend(acc.lines())
        left = len(self.bundle.points) - self.n_points_written
        out.append(f"points written: {self.n_points_written}" + (f" ({left} left out: fewer than two rays not "
                                                                  "flagged as blunders)" if left else ""))
        out.extend(f"wrote {p}" for p in self.files)
        if self.report is not None:
            out.append(f"report: {self.report}")
        return out


# --------------------------------------------------------------------------- inputs
def _image_names(images: Sequence[StrPath]) -> tuple[str, ...]:
    names = tuple(Path(p).name for p in images)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InvalidInputError(f"two images have the same file name {dup[:3]}: image names must be unique")
    return names


def _match_pose_names(names: Sequence[str], poses: Sequence[Pose], source: StrPath) -> list[Pose]:
    """The pose of every image, in image order; a pose file names images by file name or by stem."""
    by_name = {p.image: p for p in poses}
    out = []
    missing = []
    for n in names:
        p = by_name.get(n) or by_name.get(Path(n).stem)
        if p is None:
            missing.append(n)
            continue
        out.append(Pose(n, p.camera, p.position, p.rotation))
    if missing:
        raise InvalidInputError(f"{str(source)!r} has no pose for image(s) {missing[:5]}"
                                f"{' ...' if len(missing) > 5 else ''} (it names {sorted(by_name)[:5]} ...)")
    given = set(names) | {Path(n).stem for n in names}
    extra = [p.image for p in poses if p.image not in given]
    if extra:
        raise InvalidInputError(f"{str(source)!r} has poses of {len(extra)} image(s) that are not given: {extra[:5]}"
                                f"{' ...' if len(extra) > 5 else ''} (the block's images: {list(names)[:5]}"
                                f"{' ...' if len(names) > 5 else ''}): give those images, or leave their rows out")
    return out


@dataclass(frozen=True, eq=False)
class _Inputs:
    cameras: dict[str, Camera]
    camera_of: tuple[str, ...]
    poses: list[Pose] | None
    pose_sigma: NDArray[np.float64] | None  # (n, 6) from the pose file
    angle_system: str  # "omega-phi-kappa" or "navigation" (the pose file's angles)
    crs: str | None
    control: BlockControlTable | None
    frame: str = ""  # what the coordinates of every output are
    reference: NDArray[np.float64] | None = None  # OpenSfM's topocentric origin (lon, lat, h)
    gps_position: NDArray[np.float64] | None = None  # (n, 3) an OpenSfM reconstruction's GPS, NaN where none
    gps_dop: NDArray[np.float64] | None = None  # (n,) their gps_dop, m
    pose_kind: str = ""  # the kind of the pose file (stereo.formats.detect.POSE_KINDS: "poses", "opensfm", ...)
    pose_name: str = ""
    control_note: str = ""  # where the control came from, when not from --control's block CSV
    geo: OdmGeo | None = None  # ODM geo.txt: positions (GNSS) without rotations
    tracks: Tracks | None = None  # a pose file's tracks (COLMAP) on the block's images
    block_names: tuple[str, ...] = ()  # the block's image names, in order
    extras: PoseExtras | None = None  # a pose CSV's time, strip and corr_* columns (stereo.formats.trajectory)
    zoom_line: str = ""  # a zoom camera evaluated per image (stereo.actions.block_zoom)


def _load_inputs(ws: Workspace, names: tuple[str, ...], camera: StrPath | Camera | Mapping[str, Camera] | None,
                 poses: StrPath | None, control: StrPath | None, opts: BlockOptions,
                 images: Sequence[StrPath] = ()) -> _Inputs:
    cameras: dict[str, Camera] = {}
    ws.add_inputs(*input_paths(opts.focal_settings))  # a zoom camera: one camera per focal setting
    zoom = zoom_block(camera, images, names, opts.focal_settings, self_calibrate=bool(opts.bundle.self_calibrate))
    if zoom is not None:
        cameras = dict(zoom.cameras)
    elif isinstance(camera, Camera):
        cameras = {DEFAULT_CAMERA: camera}
    elif isinstance(camera, Mapping):
        cameras = dict(camera)
    elif camera is not None:  # any camera file (camera JSON, orthority, OpenCV, COLMAP, Metashape)
        ws.add_inputs(*input_paths(camera))
        cameras = dict(read_camera_file(camera).cameras)
    ctrl = None
    deferred = None
    if control is not None:
        ws.add_inputs(*input_paths(control))
        ckind, cpath = resolve_control(control)
        if ckind.name == "control":
            ctrl = read_block_control(cpath)
        else:  # OpenDroneMap's gcp_list.txt, Metashape markers: read once the poses' frame is known
            deferred = control
    pose_list: list[Pose] | None = None
    sigma = gps = dop = reference = None
    extras = None
    crs = None
    frame = ""
    kind = ""
    angle_system = "omega-phi-kappa"
    geo = None
    file_tracks = None
    if opts.trajectory is not None and poses is None:
        raise InvalidInputError("--trajectory needs --poses: the image-times CSV (image,time[,strip]) of the images")
    if poses is not None:
        ws.add_inputs(*input_paths(poses))
        if opts.trajectory is not None:
            ws.add_inputs(opts.trajectory)
        # a pose CSV's time, strip and corr_* columns; with --trajectory the poses at the images' times
        pf, extras = read_poses_with_extras(poses, opts.trajectory,
                                            camera=DEFAULT_CAMERA if len(cameras) <= 1 or zoom else None,
                                            boresight_rad=opts.boresight_rad, lever_arm_m=opts.lever_arm_m,
                                            crs=ctrl.crs if ctrl is not None else None)
        kind = pf.kind.name
        if pf.reconstruction is not None:
            rec = pf.reconstruction
            if ctrl is not None and ctrl.crs is not None and rec.crs is not None and not same_crs(ctrl.crs, rec.crs):
                rec = rec.to_crs(ctrl.crs)  # the control's CRS is the frame of the outputs
            crs, frame, reference = rec.crs, rec.frame, rec.reference_lonlat_h
            if not cameras:
                cameras = dict(rec.cameras)
            pose_list = list(rec.poses)
            gps, dop = np.asarray(rec.gps_position), np.asarray(rec.gps_dop)
            if camera is not None and len(cameras) == 1:  # one camera given: every image uses it
                only = next(iter(cameras))
                pose_list = [Pose(p.image, only, p.position, p.rotation) for p in pose_list]
        elif pf.geo is not None:  # ODM geo.txt: positions only (GNSS observations), no rotations
            geo, crs, frame = pf.geo, pf.crs, pf.frame
        else:
            pose_list, sigma, crs, angle_system, frame = list(pf.poses), pf.sigma, pf.crs, pf.angle_system, pf.frame
            if not cameras:
                cameras = dict(pf.cameras)
            elif len(cameras) == 1:
                only = next(iter(cameras))
                pose_list = [Pose(p.image, only, p.position, p.rotation) for p in pose_list]
            if pf.tracks is not None:
                file_tracks = block_tracks(pf.tracks, names)
        if pose_list is not None:
            order = {p.image: k for k, p in enumerate(pose_list)}
            pose_list = _match_pose_names(names, pose_list, pf.path)
            idx = [order.get(n, order.get(Path(n).stem, 0)) for n in names]
            if sigma is not None:
                sigma = np.asarray(sigma)[idx]
            if gps is not None and dop is not None:
                gps, dop = gps[idx], dop[idx]
    control_note = ""
    gcp_path = None
    if deferred is None and control is None and kind == "opensfm" and crs is not None and poses is not None:
        gcp_path = _project_gcps(input_paths(poses)[0])  # the GCPs of the reconstruction's own project
        if gcp_path is not None:
            ws.add_inputs(gcp_path)
            deferred = gcp_path
    if deferred is not None:
        ctrl, control_note = read_control_file(deferred, crs=crs)
    if not cameras:
        raise InvalidInputError("no camera: give --camera (a camera JSON, orthority int_param, OpenCV calibration, "
                                "COLMAP or Metashape cameras), or --poses with a file that holds the cameras "
                                "(OpenSfM reconstruction.json, COLMAP model, Metashape XML)")
    if zoom is not None:
        camera_of, pose_list = zoom.camera_of, zoom.assign(pose_list)
    elif pose_list is not None:
        camera_of = tuple(p.camera for p in pose_list)
    elif len(cameras) == 1:
        camera_of = (next(iter(cameras)),) * len(names)
    else:
        raise InvalidInputError(f"{len(cameras)} cameras but no poses to say which image uses which")
    for n, c in zip(names, camera_of, strict=True):
        if c not in cameras:
            raise InvalidInputError(f"image {n!r} names camera {c!r}, which is not given (cameras: {sorted(cameras)})")
    if ctrl is not None:
        source = str(input_paths(control if control is not None else gcp_path)[0])
        unknown = sorted({m for m in ctrl.meas_image if m not in names and Path(m).stem not in
                          {Path(n).stem for n in names}})
        if unknown:
            raise InvalidInputError(f"{source!r} measures points in image(s) {unknown[:5]} that are not in the "
                                    f"block (images: {list(names)[:5]} ...)")
        missing_checks = sorted(set(opts.check_ids) - set(ctrl.ids))
        if missing_checks:
            raise InvalidInputError(f"check id(s) {missing_checks} are not in {source!r}")
        if crs is None:
            crs = ctrl.crs
            if crs is not None:
                frame = frame or f"{crs_label(crs)} (the CRS of the control file)"
            if kind in ("opensfm", "colmap", "metashape") and crs is not None:
                frame = (f"{crs_label(crs)} of the control file (the {pf.kind.label} is not georeferenced: its poses "
                         "are taken as given in that CRS)")
        elif ctrl.crs is not None and ctrl.crs != crs:
            if parse_crs(ctrl.crs) != parse_crs(crs):
                raise InvalidInputError(f"the control file's CRS {ctrl.crs!r} differs from the pose file's {crs!r}")
    elif opts.check_ids:
        raise InvalidInputError(f"check ids {list(opts.check_ids)} given without a control file")
    if not frame:
        frame = (f"{crs_label(crs)} (the CRS of the pose file)" if crs is not None
                 else "the frame of the given coordinates (no CRS given: not georeferenced)")
    return _Inputs(cameras, camera_of, pose_list, sigma, angle_system, crs, ctrl, frame, reference, gps, dop, kind,
                   input_paths(poses)[0].name if poses is not None else "", control_note, geo, file_tracks, names,
                   extras, zoom.line if zoom is not None else "")


#: where an OpenSfM dataset or an OpenDroneMap project keeps its GCPs, relative to its reconstruction.json
#: (ODM's copy in the CRS of its georeferencing first, then the user's, then OpenSfM's dataset folder)
PROJECT_GCPS = ("../odm_georeferencing/gcp_list.txt", "../gcp_list.txt", "gcp_list.txt")


def _project_gcps(reconstruction: Path) -> Path | None:
    """The ``gcp_list.txt`` of the reconstruction's own OpenSfM dataset (beside it) or ODM project (the
    reconstruction in ``opensfm/``), None when there is none."""
    for rel in PROJECT_GCPS:
        if rel.startswith("../") and reconstruction.parent.name != "opensfm":
            continue
        c = reconstruction.parent / rel
        if c.is_file() and detect_odm_gcps(c):
            return c.resolve()
    return None


def _with_control(tracks: Tracks, ctrl: BlockControlTable | None, names: tuple[str, ...],
                  sigma_px: float, measured: bool = False) -> Tracks:
    """Add the control points' image measurements to the tie tracks (as tracks of their own); ``measured``:
    the tracks may measure control ids the control file gives coordinates of only (``--observations``)."""
    if ctrl is None or not len(ctrl.meas_id):
        return tracks
    clash = sorted(set(ctrl.meas_id if measured else ctrl.ids) & set(tracks.point_ids))
    if clash:
        raise InvalidInputError(f"control id(s) {clash[:5]} clash with tie-point ids; rename them in the control file")
    stem = {Path(n).stem: k for k, n in enumerate(names)}
    idx = {n: k for k, n in enumerate(names)}
    cidx = ctrl.index()
    counts: dict[str, int] = {}
    for m in ctrl.meas_id:
        counts[m] = counts.get(m, 0) + 1
    keep = [k for k, m in enumerate(ctrl.meas_id) if counts[m] >= 2]
    used_ids = sorted({ctrl.meas_id[k] for k in keep}, key=lambda s: cidx[s])
    new_index = {s: len(tracks.point_ids) + j for j, s in enumerate(used_ids)}
    pt = np.concatenate([tracks.obs_point, [new_index[ctrl.meas_id[k]] for k in keep]]).astype(np.int64)
    im = np.concatenate([tracks.obs_image, [idx.get(ctrl.meas_image[k], stem.get(Path(ctrl.meas_image[k]).stem, -1))
                                            for k in keep]]).astype(np.int64)
    px = np.vstack([tracks.obs_pixel, ctrl.meas_pixel[keep].reshape(-1, 2)])
    sg = np.concatenate([tracks.obs_sigma_px, np.full(len(keep), float(sigma_px))])
    return Tracks(tracks.images, tracks.point_ids + tuple(used_ids), pt, im, px, sg)


def _block_control(ctrl: BlockControlTable | None, tracks: Tracks, opts: BlockOptions) -> BlockControl | None:
    if ctrl is None:
        return None
    present = set(tracks.point_ids)
    rows = [k for k, i in enumerate(ctrl.ids) if ctrl.kind[k] != "tie" and i in present]
    if not rows:
        return None
    sig = ctrl.sigma_m[rows]
    default = np.asarray(opts.control_sigma_m, dtype=np.float64)
    sig = np.where(np.isfinite(sig), sig, default)
    return BlockControl(ids=tuple(ctrl.ids[k] for k in rows), xyz=ctrl.xyz[rows],
                        kind=tuple(ctrl.kind[k] for k in rows), sigma_m=sig,
                        check=np.array([ctrl.ids[k] in opts.check_ids for k in rows], dtype=bool))


def _gnss(inp: _Inputs, opts: BlockOptions) -> tuple[GnssObservations | None, str]:
    """The GNSS (and INS) observations of the block and a sentence saying where they come from.

    An OpenSfM reconstruction's shots with ``gps_position`` are observed there, with ``--gnss-sigma``
    or else their ``gps_dop``; without any, ``--gnss-sigma`` makes the reconstruction's projection
    centres observations. A pose CSV's positions are observed with ``--gnss-sigma`` or its ``sx,sy,sz``.
    ODM's ``geo.txt`` positions (no rotations) are observed with its accuracies, else ``--gnss-sigma``.
    """
    if inp.geo is not None:
        return geo_gnss(inp.geo, inp.block_names, inp.pose_name, opts.gnss_sigma_m)
    if inp.poses is None:
        return None, "no poses given (--poses)"
    n = len(inp.poses)
    names = tuple(p.image for p in inp.poses)
    given = None if opts.gnss_sigma_m is None else np.tile(np.asarray(opts.gnss_sigma_m, dtype=np.float64), (n, 1))
    all_angles = np.array([p.angles for p in inp.poses]).reshape(n, 3)
    ins = None if opts.ins_sigma_rad is None else np.tile(np.asarray(opts.ins_sigma_rad, dtype=np.float64), (n, 1))
    ins_text = "" if ins is None else "; its angles as INS observations (--ins-sigma)"
    if inp.pose_kind == "opensfm":
        gps = np.full((n, 3), np.nan) if inp.gps_position is None else np.asarray(inp.gps_position)
        has = np.isfinite(gps).all(axis=1)
        if has.any():
            dop = np.full(n, np.nan) if inp.gps_dop is None else np.asarray(inp.gps_dop, dtype=np.float64)
            if given is not None:
                sig, how = given, "sigma from --gnss-sigma"
            else:
                sig = np.repeat(np.where(dop > 0, dop, np.nan)[:, None], 3, axis=1)
                ok_d = has & np.isfinite(sig).all(axis=1)
                how = (f"sigma = its gps_dop, median {float(np.median(dop[ok_d])):.3g} m" if ok_d.any() else "")
                has = ok_d
            if not has.any():
                return None, (f"{inp.pose_name} has gps_position but no gps_dop to weigh it: give --gnss-sigma S to "
                              "observe it")
            k = np.flatnonzero(has)
            return (GnssObservations(images=tuple(names[i] for i in k), position=gps[k], sigma_m=sig[k],
                                     angles=None if ins is None else all_angles[k],
                                     sigma_rad=None if ins is None else ins[k]),
                    f"the gps_position of {len(k)} of {n} shots of {inp.pose_name} ({how}){ins_text}")
        if given is None:
            return None, (f"{inp.pose_name} has no gps_position: its poses are initial values only (--gnss-sigma S "
                          "observes its projection centres)")
        return (GnssObservations(images=names, position=np.array([p.position for p in inp.poses]), sigma_m=given,
                                 angles=None if ins is None else all_angles, sigma_rad=ins),
                f"the projection centres of {inp.pose_name} (no gps_position in it; sigma from --gnss-sigma)"
                f"{ins_text}")
    sig_pos = given
    how = "sigma from --gnss-sigma"
    if sig_pos is None and inp.pose_sigma is not None and np.isfinite(inp.pose_sigma[:, :3]).all():
        sig_pos = np.asarray(inp.pose_sigma[:, :3], dtype=np.float64)
        how = "sigma from its sx,sy,sz"
    if sig_pos is None:
        return None, (f"the positions of {inp.pose_name} are initial values only (no sx,sy,sz in it; --gnss-sigma S "
                      "observes them)")
    angles = None
    sig_ang = ins
    if sig_ang is None and inp.pose_sigma is not None and np.isfinite(inp.pose_sigma[:, 3:]).all():
        # a navigation file's sigmas are of heading, pitch and roll; for a near-nadir camera they are
        # those of kappa, phi/omega and omega/phi: their mean is used for each of omega, phi, kappa
        sa = np.asarray(inp.pose_sigma[:, 3:], dtype=np.float64)
        sig_ang = sa if inp.angle_system == "omega-phi-kappa" else np.repeat(sa.mean(axis=1, keepdims=True), 3, 1)
    if sig_ang is not None:
        angles = all_angles
    return (GnssObservations(images=names, position=np.array([p.position for p in inp.poses]), sigma_m=sig_pos,
                             angles=angles, sigma_rad=sig_ang),
            f"the positions of {n} images of {inp.pose_name} ({how})" + ("; its angles as INS observations"
                                                                         if angles is not None else ""))


# --------------------------------------------------------------------------- the job
#: the bundle's pose standard errors (omega, phi, kappa, x, y, z) in the pose CSV's order (x, y, z, omega, phi, kappa)
POSE_CSV_STD_ORDER = [3, 4, 5, 0, 1, 2]
#: an image keeps at least this many rays after the intersection through initial poses (else all of them)
MIN_RAYS_PER_IMAGE = 12
#: a pose file's tracks are the tie points when every image has at least this many of their rays
MIN_FILE_TRACKS_PER_IMAGE = 6
#: above this many image observations the default full covariance (every point's) becomes "poses"
FULL_COVARIANCE_MAX_OBS = 200_000


def plan_block(out_dir: StrPath, *, overwrite: bool, inputs: Sequence[StrPath | None],
               report: bool) -> PairWorkspace:
    """The workspace of a block job: every output of :data:`BLOCK_LAYOUT` and the report folder checked."""
    root = Path(out_dir)
    ws = PairWorkspace(root, overwrite=overwrite, inputs=[p for p in inputs if p is not None],
                       report_dir=root / _REPORT if report else None)
    if root.exists() and not root.is_dir():
        raise InvalidInputError(f"output {str(root)!r} exists and is not a folder")
    parent = next((p for p in root.parents if p.exists()), Path("."))
    if not root.exists() and not parent.is_dir():
        raise InvalidInputError(f"output folder {str(parent)!r} is a file")
    ws.plan(*(root / n for n in BLOCK_LAYOUT.values()))
    ws.check_report_dir()
    if ws.report_dir is not None and (ws.report_dir / "report.html").exists() and not overwrite:
        raise InvalidInputError(f"report folder {str(ws.report_dir)!r} already holds a report; pass --overwrite")
    return ws


def camera_paths(out_dir: Path, cameras: Mapping[str, Camera]) -> list[Path]:
    """``OUTDIR/camera_<id>.json`` of each camera (the adjusted interior orientation, camera JSON)."""
    safe = {k: "".join(c if c.isalnum() or c in "-_." else "_" for c in k) for k in cameras}
    if len(set(safe.values())) != len(safe):
        raise InvalidInputError(f"camera ids {sorted(cameras)} do not give distinct file names")
    return [out_dir / f"camera_{safe[k]}.json" for k in cameras]


def _triangulated(cameras: Mapping[str, Camera], poses: Sequence[Pose], tracks: Tracks
                  ) -> tuple[Tracks, NDArray[np.float64]]:
    """Intersect the tracks through known poses; drop rays and tracks that do not intersect."""
    X, used = triangulate_tracks(cameras, poses, tracks)
    ok = np.asarray(np.isfinite(X).all(axis=1), dtype=bool)
    keep = used & ok[tracks.obs_point]
    sub = tracks.subset(keep)
    where = {pid: k for k, pid in enumerate(tracks.point_ids)}
    return sub, X[[where[p] for p in sub.point_ids]].reshape(-1, 3)


def _points_of(ids: Sequence[str], all_ids: Sequence[str], X: NDArray[np.float64]) -> NDArray[np.float64]:
    where = {pid: k for k, pid in enumerate(all_ids)}
    return X[[where[p] for p in ids]].reshape(-1, 3)


def run_block(images: Sequence[StrPath], *, out_dir: StrPath, camera: StrPath | Camera | Mapping[str, Camera] | None,
              poses: StrPath | None = None, control: StrPath | None = None, options: BlockOptions | None = None,
              overwrite: bool = False, progress: Progress | None = None,
              tracks: Tracks | None = None, observations: StrPath | None = None) -> BlockResult:
    """``stereo block``: tie points, initial orientation, bundle adjustment, outputs and report.

    Parameters
    ----------
    images : sequence of paths
        The block's images (at least 2); their file names are the image names.
    out_dir : path
        Output folder (layout :data:`BLOCK_LAYOUT` plus ``report/``).
    camera : path, Camera or mapping id -> Camera, optional
        One camera for every image, or the cameras by id (with poses that name them): any camera file
        (:func:`rectify.formats.detect.read_camera_file`). Optional when ``poses`` holds the cameras
        (OpenSfM ``reconstruction.json``, COLMAP model, Metashape XML).
    poses : path, optional
        Any pose file of :data:`stereo.formats.detect.POSE_KINDS` (position/angle CSV, OpenSfM, COLMAP,
        Metashape, orthority; ODM ``geo.txt`` gives positions only): initial values, and GNSS/INS
        observations with ``gnss_sigma_m``/``ins_sigma_rad`` or standard-deviation columns.
    control : path, optional
        Block control CSV, ODM ``gcp_list.txt`` or Metashape markers XML.
    tracks : Tracks, optional
        Tie points already measured (the matching is skipped); its images must be the file names.
    observations : path, optional
        An observations CSV (:mod:`stereo.formats.observations`): the tie points without the images
        (``images`` empty; the pose file names the images).

    Raises
    ------
    InvalidInputError, EstimationError, ConvergenceError, RasterIOError
        With a one-line reason; nothing is left at the output paths.
    """
    opts = options or BlockOptions()
    if observations is not None:
        images = (image_times_names(poses) if opts.trajectory is not None and poses is not None and not images
                  else bf.observation_images(images, poses, observations))
    if len(images) < 2:
        raise InvalidInputError(f"a block needs at least 2 images; got {len(images)}")
    names = _image_names(images)
    cam_input = camera if isinstance(camera, (str, Path)) else None
    ws = plan_block(out_dir, overwrite=overwrite, inputs=[*images, cam_input, poses, control, observations],
                    report=opts.report)
    inp = _load_inputs(ws, names, camera, poses, control, opts, images)
    obs_line: tuple[str, ...] = (inp.zoom_line,) if inp.zoom_line else ()  # a zoom camera's settings
    if observations is not None:
        tracks, line = bf.observation_tracks(observations, inp, names, opts.check_ids, opts.tie_sigma_px)
        obs_line += (line,)
    # a pose file's tracks (a COLMAP model's) are the tie points when they reach every image
    file_tracks = (inp.tracks if tracks is None and inp.tracks is not None and opts.reuse_tracks
                   and bool((inp.tracks.points_per_image() >= MIN_FILE_TRACKS_PER_IMAGE).all()) else None)
    gnss, gnss_text = _gnss(inp, opts)
    gnss = block_gnss(gnss, inp.extras, inp.poses, inp.pose_sigma, boresight_rad=opts.boresight_rad,
                      gnss_drift=opts.bundle.gnss_drift, boresight=opts.bundle.boresight_unknown)  # times, strips, cov.
    check_datum(inp.poses is not None, inp.control, gnss, gnss_text, names, free_network=opts.bundle.free_network,
                check_ids=opts.check_ids)
    check_block_inputs(ws, images, names, inp.cameras, inp.camera_of, inp.poses, inp.crs, inp.control,
                       control=control, poses_path=poses, matching=tracks is None and file_tracks is None)
    check_exports(opts.exports, inp.cameras, names, inp.crs)  # what the requested formats cannot hold, before work
    frame, nav = bf.frame_for(inp, opts.frame), inp.angle_system == "navigation"
    input_lines = (f"frame: {inp.frame}", f"GNSS: {gnss_text}" if gnss is not None else f"GNSS: none ({gnss_text})",
                   *((inp.control_note,) if inp.control_note else ()), *obs_line, *bf.frame_lines(frame, inp))
    ws.plan(*camera_paths(Path(out_dir), inp.cameras), Path(out_dir) / FOLDER_ITEM if opts.stac else None)
    plan_exports(ws, opts.exports.files(inp.crs))
    if tracks is not None and tuple(tracks.images) != names:
        raise InvalidInputError(f"the given tracks name images {list(tracks.images)[:4]}, not the block's "
                                f"{list(names)[:4]}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    tie_lines: tuple[str, ...] = ()
    if tracks is None:
        ground_z = opts.ground_z
        if ground_z is None and inp.control is not None and np.isfinite(inp.control.xyz[:, 2]).any():
            ground_z = float(np.nanmean(inp.control.xyz[:, 2]))
        cams_by_image = {n: inp.cameras[c] for n, c in zip(names, inp.camera_of, strict=True)}
        tp = block_tie_points([Path(p) for p in images], names=names, cameras=cams_by_image, poses=inp.poses,
                              ground_z=ground_z, options=opts.match, progress=progress)
        tie = tp.tracks
        tie_lines = tuple(tp.summary_lines())
    else:
        tie = tracks
    if file_tracks is not None:
        tie = file_tracks
        tie_lines = (f"tie points: {tie.n_points} tracks of {inp.pose_name} ({tie.n_obs} rays) on the block's images "
                     "(matching skipped; --rematch matches)",)
    n_tie = tie.n_points
    all_tracks = _with_control(tie, inp.control, names, opts.control_sigma_px, observations is not None)
    timings["tie_points_s"] = time.perf_counter() - t0
    # into the adjustment frame (stereo.actions.block_frame); the files are written in the inputs' CRS
    inp_map, gnss_map = inp, gnss
    inp, gnss = replace(inp, poses=bf.poses_to_frame(frame, inp.poses, navigation=nav)), bf.gnss_to_frame(frame, gnss,
                                                                                                    navigation=nav)
    t1 = time.perf_counter()
    if opts.method == MODEL_METHOD:  # independent models with control (seed 002, 3.1-3.2): no bundle
        bc = bf.control_to_frame(frame, _block_control(inp.control, all_tracks, opts))
        res, initial, mlines = run_models(inp.cameras, inp.camera_of, all_tracks, bc, gnss, opts.models,
                                          opts.tie_sigma_px, progress)
        timings["models_s"] = time.perf_counter() - t1
        res = bf.result_to_map(frame, res, gnss)
        files, report_path = _write(ws, res, all_tracks, inp_map, names, n_tie, initial, timings, gnss_map, opts,
                                    [*images, cam_input, poses, control, observations], frame.description())
        return BlockResult(res, all_tracks, n_tie, len(res.control_ids), len(res.check_ids), initial, Path(out_dir),
                           tuple(files), report_path, timings, tie_lines, int(res.determined.sum()), input_lines,
                           mlines)
    if inp.poses is not None:
        poses0: list[Pose] = list(inp.poses)
        all_tracks, points0 = _triangulated(inp.cameras, poses0, all_tracks)
        initial = "from the given poses (tracks intersected through them)"
    else:
        mb = independent_models(inp.cameras, inp.camera_of, all_tracks, options=IndependentOptions(),
                                progress=progress)
        ctrl0 = bf.control_to_frame(frame, _block_control(inp.control, all_tracks, opts))
        use = None if ctrl0 is None else ~ctrl0.check & np.array([k == "full" or k == "height" for k in ctrl0.kind])
        # GNSS positions without poses (ODM geo.txt) bring the models to the ground too
        gn = (list(gnss.images), np.asarray(gnss.position)) if gnss is not None and inp.poses is None else None
        if (ctrl0 is not None and use is not None and use.any()) or gn is not None:
            cc = (None if ctrl0 is None or use is None or not use.any()
                  else ([i for i, u in zip(ctrl0.ids, use, strict=True) if u], ctrl0.xyz[use]))
            gb = to_ground(mb, control=cc, gnss=gn)
            poses0, X0 = list(gb.poses), np.asarray(gb.points)
            initial = (f"independent models ({len(mb.joins)} models), to the ground by {len(gb.control_ids)} "
                       f"control points" + (f" and {len(gb.gnss_images)} GNSS positions" if gn is not None else "")
                       + " (7-parameter similarity)")
        else:
            poses0, X0 = list(mb.poses), np.asarray(mb.points)
            initial = f"independent models ({len(mb.joins)} models), in the model frame of the first pair"
        # the tracks are intersected again through the chained poses, with rejection; an image whose
        # chained pose was too rough to keep a few of its rays keeps all rays to triangulated points:
        # the bundle judges those again with its robust weights
        finite = np.asarray(np.isfinite(X0).all(axis=1), dtype=bool)
        X1, used = triangulate_tracks(inp.cameras, poses0, all_tracks)
        ok1 = np.asarray(np.isfinite(X1).all(axis=1), dtype=bool)
        keep = used & ok1[all_tracks.obs_point]
        per_image = np.bincount(all_tracks.obs_image[keep], minlength=len(names))
        for i in np.flatnonzero(per_image < MIN_RAYS_PER_IMAGE):
            back = (all_tracks.obs_image == i) & (ok1 | finite)[all_tracks.obs_point]
            keep |= back
        X0 = np.where(ok1[:, None], X1, X0)
        sub = all_tracks.subset(keep)
        points0 = _points_of(sub.point_ids, all_tracks.point_ids, X0)
        all_tracks = sub
    timings["initial_s"] = time.perf_counter() - t1
    bcontrol = _block_control(inp.control, all_tracks, opts)
    if bcontrol is not None:
        bcontrol = bf.control_to_frame(frame, bcontrol, _points_of(bcontrol.ids, all_tracks.point_ids, points0))
    bopts = opts.bundle
    if bopts.covariance == "full" and all_tracks.n_obs > FULL_COVARIANCE_MAX_OBS:
        bopts = replace(bopts, covariance="poses")
    t2 = time.perf_counter()
    res = adjust_bundle(inp.cameras, poses0, all_tracks, points0, control=bcontrol, gnss=gnss, options=bopts,
                        progress=progress)
    timings["bundle_s"] = time.perf_counter() - t2
    res = bf.result_to_map(frame, res, gnss)
    files, report_path = _write(ws, res, all_tracks, inp_map, names, n_tie, initial, timings, gnss_map, opts,
                                [*images, camera if isinstance(camera, (str, Path)) else None, poses, control,
                                 observations], frame.description())
    n_written = int(res.determined.sum())
    return BlockResult(res, all_tracks, n_tie, len(res.control_ids), len(res.check_ids), initial, Path(out_dir),
                       tuple(files), report_path, timings, tie_lines, n_written, input_lines)


def _residual_mm(res: BundleResult, tracks: Tracks, inp: _Inputs) -> NDArray[np.float64]:
    """RMS image residual of each point over its rays, mm in the photo (pixels x pixel size)."""
    pix = np.array([inp.cameras[c].pixel_size_mm for c in inp.camera_of])[tracks.obs_image]
    v = np.asarray(res.residuals_px, dtype=np.float64) * pix[:, None]
    ok = ~np.asarray(res.flagged, dtype=bool)
    ss = np.bincount(tracks.obs_point[ok], weights=np.sum(v[ok] ** 2, axis=1), minlength=tracks.n_points)
    n = np.bincount(tracks.obs_point[ok], minlength=tracks.n_points)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(ss / np.maximum(n, 1))


def _write(ws: Workspace, res: BundleResult, tracks: Tracks, inp: _Inputs, names: tuple[str, ...], n_tie: int,
           initial: str, timings: dict[str, float], gnss: GnssObservations | None, opts: BlockOptions,
           inputs: Sequence[StrPath | None], adjustment_frame: str = "") -> tuple[list[Path], Path | None]:
    root = Path(str(ws.root))
    X = np.asarray(res.points, dtype=np.float64)
    # the points determined by the images: at least two rays not flagged as blunders (a point whose rays were
    # flagged is not determined by the adjustment; it stays in observations.csv)
    ok = np.asarray(res.determined, dtype=bool)
    ids = [tracks.point_ids[i] for i in np.flatnonzero(ok)]
    pstd = np.asarray(res.point_std, dtype=np.float64)
    std = pstd[ok] if np.isfinite(pstd[ok]).all() and ok.any() else None
    resid_mm = _residual_mm(res, tracks, inp)
    units = "m"
    summary: dict[str, Any] = {"method": opts.method, "images": len(names), "tie_points": n_tie,
                               "points": int(ok.sum()), "points_left_out": int((~ok).sum()),
                               "observations": tracks.n_obs, "initial": initial,
                               "rms_image_px": res.rms_px, "sigma0": res.sigma0, "iterations": res.iterations,
                               "iteration_limit": res.iteration_limit, "converged": res.converged,
                               "condition_number": res.condition_number, "frame": inp.frame,
                               "adjustment_frame": adjustment_frame,
                               "control_points": len(res.control_ids), "control_rejected": list(res.rejected_control),
                               "check_points": len(res.check_ids), "check_rejected": list(res.rejected_check),
                               **timings}
    if len(res.gnss_residuals):
        lab = rms_labels(np.asarray(res.gnss_residuals, dtype=np.float64))
        summary["gnss_rms_per_component_m"], summary["gnss_rms_3d_m"] = lab["rms_per_component_m"], lab["rms_3d_m"]
    summary.update(systematic_summary(res.systematic_names, res.systematic, res.systematic_std))  # GNSS/INS unknowns
    ck_err = np.asarray(res.check_errors, dtype=np.float64).reshape(-1, 3)
    if len(ck_err):
        ck_std = np.asarray(res.check_std, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            summary["check_rmse_xyz_m"] = [rms(ck_err[:, k]) for k in range(3)]
            summary["check_normalised_rms"] = rms((ck_err / ck_std)[np.isfinite(ck_err / ck_std)])
        stated = check_accuracy(res)
        if stated is not None:
            summary["accuracy_statement"] = stated.to_dict()
    ws.prepare()
    written: list[Path] = []
    report_path = None
    wkt = None
    if inp.crs is not None:
        wkt = parse_crs(inp.crs).to_wkt()
    staged: dict[str, tuple[Path, Path]] = {}  # the point cloud files: final and staged paths (the STAC Item)
    with export_folders(opts.exports), ws.transaction():
        p = root / BLOCK_LAYOUT["orientation"]
        ws.write_text(p, block_orientation_text(res.cameras, res.poses, std_errors=res.pose_std, crs=inp.crs,
                                                sigma0={"all": res.sigma0, **res.sigma0_groups},
                                                datum=list(res.datum) + [f"WARNING: {w}" for w in res.warnings],
                                                summary=summary, frame=inp.frame, reference_lonlat_h=inp.reference))
        written.append(p)
        p = root / BLOCK_LAYOUT["poses"]
        # the bundle's pose_std is (omega, phi, kappa, x, y, z); the pose CSV's is (x, y, z, omega, phi, kappa)
        ws.write_text(p, pose_csv_text(res.poses, crs=inp.crs, angles="deg",
                                       std=np.asarray(res.pose_std)[:, POSE_CSV_STD_ORDER]))
        written.append(p)
        p = root / BLOCK_LAYOUT["points"]
        with ws.output(p) as tmp:
            dump_ply(tmp, X[ok], comment=f"stereo block points, crs {inp.crs or 'local'}")
            staged["points_ply"] = (p, tmp)
        written.append(p)
        p = root / BLOCK_LAYOUT["points_csv"]
        ws.write_text(p, points_csv_text(ids, X[ok], resid_mm[ok], std=std, crs=inp.crs))
        written.append(p)
        p = root / BLOCK_LAYOUT["points_las"]
        with ws.output(p) as tmp:
            staged["points_las"] = (p, tmp)
            # sigma_z: the bundle's height standard error of each point (NaN where not computed)
            las = LasWriter(tmp, X[ok].min(axis=0) if ok.any() else np.zeros(3), crs_wkt=wkt, fmt="las",
                            extra_dims=["sigma_z"])
            try:
                las.write(X[ok], extra={"sigma_z": pstd.reshape(-1, 3)[ok][:, 2]})
            finally:
                las.close()
        written.append(p)
        for (cid, cam), p in zip(res.cameras.items(), camera_paths(root, res.cameras), strict=True):
            ws.write_json(p, {**camera_document(cam), "name": cid})
            written.append(p)
        p = root / BLOCK_LAYOUT["observations"]
        w = np.min(np.asarray(res.weights, dtype=np.float64).reshape(-1, 2), axis=1)
        # the CSV's residuals are adjusted - observed; the bundle's observed - computed
        ws.write_text(p, observations_text(tracks, -np.asarray(res.residuals_px), w, np.asarray(res.flagged),
                                           redundancy=np.asarray(res.redundancy_numbers, dtype=np.float64)))
        written.append(p)
        if ws.report_dir is not None:  # staged: committed with the other outputs, or removed with them
            with ws.report_folder() as stage:
                page = block_report(stage, res, tracks, inp.crs, summary, units, gnss)
            report_path = ws.report_dir / Path(page).relative_to(stage)
        written += write_exports(ws, opts.exports, res.cameras, res.poses, inp.crs, tracks, ids, X[ok])
        if opts.stac:
            acc: dict[str, float] = {k: summary[k] for k in ("rms_image_px", "sigma0", "gnss_rms_3d_m") if k in summary}
            for axis, v in zip("xyz", summary.get("check_rmse_xyz_m") or (), strict=False):
                acc[f"check_rmse_{axis}_m"] = v
            written.append(block_stac(ws, root, staged, X[ok], inp.crs, acc, {"frame": inp.frame, "initial": initial,
                                                                            **_options_dict(opts)}, inputs))
    return written, report_path


def _options_dict(opts: BlockOptions) -> dict[str, Any]:
    """The options of a block run for its STAC Item (JSON-safe: nested dataclasses as dicts)."""
    d = dataclasses.asdict(opts)
    d["exports"] = {k: (None if v is None else str(v)) for k, v in d.get("exports", {}).items()}
    return d
