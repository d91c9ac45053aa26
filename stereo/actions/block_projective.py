"""``stereo block --method affine|projective``: a block of images without a known camera.

Steps: the workspace checks every planned output first; the control CSV is read and the minimum
control for the metric upgrade (:data:`stereo.pair.projective.MIN_CONTROL_PROJECTIVE` full control
points measured in two images or more, check points excluded) is checked before any matching; the
image sizes come from the images; the tie points are matched (no camera, no poses: all pairs or an
overview); then :func:`stereo.block.projective_bundle.uncalibrated_block` (models, joint affine or
projective orientation, projective bundle, metric upgrade by control, bundle with self-calibration
of fx, fy, skew and the principal point) and the outputs of ``stereo block``: ``orientation.json``,
``poses.csv``, ``points.ply``, ``points.csv``, ``points.las``, ``observations.csv`` and the
recovered camera ``camera_camera.json`` (fx, fy, skew, principal point with standard errors), all or
none. There is no HTML report for these methods.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from rectify.actions.workspace import StrPath
from rectify.errors import InvalidInputError
from rectify.formats.camera import camera_document
from rectify.raster import io as rio
from stereo.actions.workspace import PairWorkspace
from stereo.block.bundle.adjust import BundleOptions
from stereo.block.projective import BLOCK_METHODS, MIN_IMAGES
from stereo.block.projective_bundle import CAMERA_ID, DEFAULT_CALIBRATE, UncalibratedBlock, uncalibrated_block
from stereo.block.types import BlockControl, Tracks
from stereo.features.tracks import BlockMatchOptions, block_tie_points
from stereo.formats.block import BlockControlTable, block_orientation_text, observations_text, read_block_control
from stereo.formats.observations import read_observations
from stereo.formats.points import LasWriter, dump_ply, points_csv_text
from stereo.formats.poses import pose_csv_text
from stereo.pair.projective import MIN_CONTROL_PROJECTIVE

__all__ = ["PROJECTIVE_LAYOUT", "ProjectiveBlockOptions", "ProjectiveBlockResult", "run_block_projective"]

Progress = Callable[[int, int], None]

#: the files of the output folder (plus ``camera_camera.json``)
PROJECTIVE_LAYOUT = ("orientation.json", "poses.csv", "points.ply", "points.csv", "points.las", "observations.csv",
                     f"camera_{CAMERA_ID}.json")
#: the bundle's pose standard errors (omega, phi, kappa, x, y, z) in the pose CSV's order
_POSE_CSV_STD_ORDER = [3, 4, 5, 0, 1, 2]


@dataclass(frozen=True)
class ProjectiveBlockOptions:
    """Options of ``stereo block --method affine|projective``.

    Attributes
    ----------
    method : str
        ``affine`` (joint affine orientation of similar models with virtual control, seed 003,
        3.4.1/3.4.3) or ``projective`` (joint projective orientation of projective models, 3.4.2).
    check_ids : tuple of str
        Control ids used only as check points.
    control_sigma_m : (3,) float
        A-priori standard deviations of control coordinates where the CSV gives none.
    control_sigma_px : float
        A-priori standard deviation of the control points' image measurements, px.
    calibrate : tuple of str
        Interior elements the metric bundle estimates (default f, x0, y0, aspect, shear: fx, fy,
        skew, principal point).
    virtual : bool
        Virtual control by vector products in the affine method.
    focal_guess_px : float or None
        The affine method's nominal focal length (default max(width, height)).
    match : BlockMatchOptions
    bundle : BundleOptions
        Options of the metric bundle (its ``self_calibrate`` is replaced by ``calibrate``).
    """

    method: str = "projective"
    check_ids: tuple[str, ...] = ()
    control_sigma_m: tuple[float, float, float] = (0.05, 0.05, 0.05)
    control_sigma_px: float = 1.0
    calibrate: tuple[str, ...] = DEFAULT_CALIBRATE
    virtual: bool = True
    focal_guess_px: float | None = None
    match: BlockMatchOptions = field(default_factory=BlockMatchOptions)
    bundle: BundleOptions = field(default_factory=lambda: BundleOptions(max_iterations=100))

    def __post_init__(self) -> None:
        if self.method not in BLOCK_METHODS:
            raise InvalidInputError(f"unknown block method {self.method!r}; expected one of {list(BLOCK_METHODS)}")
        if self.focal_guess_px is not None and not (math.isfinite(self.focal_guess_px) and self.focal_guess_px > 0):
            raise InvalidInputError(f"`focal_guess_px` must be a finite number > 0; got {self.focal_guess_px!r}")
        object.__setattr__(self, "check_ids", tuple(str(s) for s in self.check_ids))


@dataclass(frozen=True, eq=False)
class ProjectiveBlockResult:
    """Result of :func:`run_block_projective`."""

    block: UncalibratedBlock
    out_dir: Path
    files: tuple[Path, ...]
    tie_lines: tuple[str, ...] = ()

    def summary_lines(self) -> list[str]:
        out = list(self.tie_lines)
        out.extend(self.block.summary_lines())
        out.extend(self.block.bundle.summary_lines())
        out.extend(f"wrote {p}" for p in self.files)
        return out


def _control_tracks(tracks: Tracks, ctrl: BlockControlTable, names: tuple[str, ...], sigma_px: float) -> Tracks:
    """The tie tracks plus the control points' image measurements (a track per point measured twice or more)."""
    clash = sorted(set(ctrl.ids) & set(tracks.point_ids))
    if clash:
        raise InvalidInputError(f"control id(s) {clash[:5]} clash with tie-point ids; rename them in the control file")
    idx = {n: k for k, n in enumerate(names)}
    idx.update({Path(n).stem: k for k, n in enumerate(names)})
    counts: dict[str, int] = {}
    for m in ctrl.meas_id:
        counts[m] = counts.get(m, 0) + 1
    keep = [k for k, m in enumerate(ctrl.meas_id) if counts[m] >= 2 and ctrl.meas_image[k] in idx]
    used = sorted({ctrl.meas_id[k] for k in keep})
    new = {s: tracks.n_points + j for j, s in enumerate(used)}
    pt = np.concatenate([tracks.obs_point, [new[ctrl.meas_id[k]] for k in keep]]).astype(np.int64)
    im = np.concatenate([tracks.obs_image, [idx[ctrl.meas_image[k]] for k in keep]]).astype(np.int64)
    px = np.vstack([tracks.obs_pixel, ctrl.meas_pixel[keep].reshape(-1, 2)])
    sg = np.concatenate([tracks.obs_sigma_px, np.full(len(keep), float(sigma_px))])
    o = np.lexsort((im, pt))
    return Tracks(tracks.images, tracks.point_ids + tuple(used), pt[o], im[o], px[o], sg[o])


def _block_control(ctrl: BlockControlTable, tracks: Tracks, opts: ProjectiveBlockOptions) -> BlockControl | None:
    present = set(tracks.point_ids)
    rows = [k for k, i in enumerate(ctrl.ids) if ctrl.kind[k] != "tie" and i in present]
    if not rows:
        return None
    sig = np.where(np.isfinite(ctrl.sigma_m[rows]), ctrl.sigma_m[rows], np.asarray(opts.control_sigma_m))
    return BlockControl(ids=tuple(ctrl.ids[k] for k in rows), xyz=ctrl.xyz[rows],
                        kind=tuple(ctrl.kind[k] for k in rows), sigma_m=sig,
                        check=np.array([ctrl.ids[k] in opts.check_ids for k in rows], dtype=bool))


def _check_control(ctrl: BlockControlTable, names: tuple[str, ...], opts: ProjectiveBlockOptions, source: str) -> None:
    missing = sorted(set(opts.check_ids) - set(ctrl.ids))
    if missing:
        raise InvalidInputError(f"check id(s) {missing} are not in {source!r}")
    known = set(names) | {Path(n).stem for n in names}
    unknown = sorted({m for m in ctrl.meas_image if m not in known})
    if unknown:
        raise InvalidInputError(f"{source!r} measures points in image(s) {unknown[:5]} that are not in the block")
    counts: dict[str, int] = {}
    for m in ctrl.meas_id:
        counts[m] = counts.get(m, 0) + 1
    usable = [i for k, i in enumerate(ctrl.ids) if ctrl.kind[k] == "full" and i not in opts.check_ids
              and counts.get(i, 0) >= 2]
    if len(usable) < MIN_CONTROL_PROJECTIVE:
        raise InvalidInputError(f"too few control points for the metric upgrade of a projective block: {len(usable)} "
                                f"full control points measured in two images or more in {source!r} (check points "
                                f"excluded); at least {MIN_CONTROL_PROJECTIVE} not on one plane are needed")


def run_block_projective(images: Sequence[StrPath], *, out_dir: StrPath, control: StrPath | None,
                         options: ProjectiveBlockOptions | None = None, overwrite: bool = False,
                         progress: Progress | None = None, tracks: Tracks | None = None,
                         observations: StrPath | None = None, camera: StrPath | None = None,
                         poses: StrPath | None = None) -> ProjectiveBlockResult:
    """Orient a block of images without a known camera (seed 003, 3.4.1-3.4.4 and 1.2) into ``out_dir``.

    Parameters
    ----------
    images : sequence of paths
        The images (at least 2, one size); their file names are the image names; only their size is
        read when ``tracks`` is given.
    out_dir : path
        Output folder (:data:`PROJECTIVE_LAYOUT`).
    control : path
        Block control CSV (``id,image,col,row,x,y,z``): at least 5 full control points.
    tracks : Tracks, optional
        Tie points already measured (the matching is skipped); its images must be the file names.
    observations : path, optional
        An observations CSV (:mod:`stereo.formats.observations`): the tie points measured elsewhere
        (the matching is skipped; the images give their sizes).
    camera, poses : None
        Refused: these methods are for images without a known camera or orientation.

    Raises
    ------
    InvalidInputError, EstimationError, RasterIOError
        With a one-line reason; nothing is left at the output paths.
    """
    opts = options or ProjectiveBlockOptions()
    for given, what in ((camera, "--camera"), (poses, "--poses")):
        if given is not None:
            raise InvalidInputError(f"--method {opts.method} is for images without a known camera and orientation: "
                                    f"{what} {str(given)!r} is not used (use --method bundle)")
    if len(images) < MIN_IMAGES:
        raise InvalidInputError(f"a block needs at least {MIN_IMAGES} images; got {len(images)}")
    names = tuple(Path(p).name for p in images)
    if len(set(names)) != len(names):
        raise InvalidInputError(f"two images have the same file name: image names must be unique ({list(names)[:5]})")
    if control is None:
        raise InvalidInputError(f"--method {opts.method} needs --control: the metric upgrade of a projective block "
                                f"needs at least {MIN_CONTROL_PROJECTIVE} full control points")
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise InvalidInputError(f"output {str(root)!r} exists and is not a folder")
    ws = PairWorkspace(root, overwrite=overwrite, inputs=[p for p in (*images, control, observations) if p],
                       report_dir=None)
    ws.plan(*(root / n for n in PROJECTIVE_LAYOUT))
    ctrl = read_block_control(control)
    _check_control(ctrl, names, opts, str(control))
    sizes = []
    for p in images:
        info = rio.raster_info(Path(p))
        sizes.append((int(info.width), int(info.height)))
    if len(set(sizes)) != 1:
        raise InvalidInputError(f"the images of an uncalibrated block share one camera and must have one size; got "
                                f"{sorted(set(sizes))}")
    tie_lines: tuple[str, ...] = ()
    if observations is not None and tracks is None:
        ob = read_observations(observations, names, dict(zip(names, sizes, strict=True)))
        tracks = ob.tracks
        tie_lines = (f"tie points: {tracks.n_points} tracks of {str(observations)!r} ({tracks.n_obs} rays; matching "
                     "skipped)",)
    if tracks is None:
        tp = block_tie_points([Path(p) for p in images], names=names, options=opts.match, progress=progress)
        tie, tie_lines = tp.tracks, tuple(tp.summary_lines())
    else:
        if tuple(tracks.images) != names:
            raise InvalidInputError(f"the given tracks name images {list(tracks.images)[:4]}, not the block's "
                                    f"{list(names)[:4]}")
        tie = tracks
    all_tracks = _control_tracks(tie, ctrl, names, opts.control_sigma_px)
    bc = _block_control(ctrl, all_tracks, opts)
    ub = uncalibrated_block(all_tracks, sizes, bc, method=opts.method, virtual=opts.virtual,
                            focal_guess_px=opts.focal_guess_px, calibrate=opts.calibrate, options=opts.bundle,
                            progress=progress)
    files = _write(ws, ub, ctrl.crs, opts)
    return ProjectiveBlockResult(ub, root, tuple(files), tie_lines)


def _write(ws: PairWorkspace, ub: UncalibratedBlock, crs: str | None, opts: ProjectiveBlockOptions) -> list[Path]:
    root = Path(str(ws.root))
    res, tracks = ub.bundle, ub.tracks
    X = np.asarray(res.points, dtype=np.float64)
    ok = np.asarray(res.determined, dtype=bool)
    ids = [tracks.point_ids[i] for i in np.flatnonzero(ok)]
    pstd = np.asarray(res.point_std, dtype=np.float64)
    std = pstd[ok] if ok.any() and np.isfinite(pstd[ok]).all() else None
    v = np.asarray(res.residuals_px, dtype=np.float64) * ub.start.camera.pixel_size_mm
    good = ~np.asarray(res.flagged, dtype=bool)
    ss = np.bincount(tracks.obs_point[good], weights=np.sum(v[good] ** 2, axis=1), minlength=tracks.n_points)
    cnt = np.bincount(tracks.obs_point[good], minlength=tracks.n_points)
    resid_mm = np.sqrt(ss / np.maximum(cnt, 1))
    mb, pb, st = ub.models, ub.projective, ub.start
    summary: dict[str, Any] = {
        "method": ub.method, "images": len(tracks.images), "points": int(ok.sum()), "observations": tracks.n_obs,
        "models": len(mb.models), "joint_orientation_rms_model_units": mb.rms_model, "virtual_points": mb.n_virtual,
        "projective_bundle_sigma0": pb.sigma0_px, "projective_bundle_rms_px": pb.rms_px,
        "upgrade_control_points": list(st.control_ids),
        "per_image_interior_px": {n: dict(zip(("fx", "fy", "skew", "cx", "cy"), map(float, row), strict=True))
                                  for n, row in zip(tracks.images, st.per_image, strict=True)},
        "camera_px": {k: {"value": val, "std": sd} for k, (val, sd) in ub.interior.items()},
        "rms_image_px": res.rms_px, "sigma0": res.sigma0, "iterations": res.iterations, "converged": res.converged,
        "control_points": len(res.control_ids), "check_points": len(res.check_ids)}
    ck = np.asarray(res.check_errors, dtype=np.float64).reshape(-1, 3)
    if len(ck):
        summary["check_rmse_xyz_m"] = [float(np.sqrt(np.mean(ck[:, k] ** 2))) for k in range(3)]
    cam = res.cameras[CAMERA_ID]
    written: list[Path] = []
    ws.prepare()
    with ws.transaction():
        p = root / "orientation.json"
        ws.write_text(p, block_orientation_text(res.cameras, res.poses, std_errors=res.pose_std, crs=crs,
                                                sigma0={"all": res.sigma0, **res.sigma0_groups},
                                                datum=list(res.datum) + [f"WARNING: {w}" for w in res.warnings],
                                                summary=summary, frame="the frame of the control"))
        written.append(p)
        p = root / "poses.csv"
        ws.write_text(p, pose_csv_text(res.poses, crs=crs, angles="deg",
                                       std=np.asarray(res.pose_std)[:, _POSE_CSV_STD_ORDER]))
        written.append(p)
        p = root / "points.ply"
        with ws.output(p) as tmp:
            dump_ply(tmp, X[ok], comment=f"stereo block --method {ub.method} points")
        written.append(p)
        p = root / "points.csv"
        ws.write_text(p, points_csv_text(ids, X[ok], resid_mm[ok], std=std, crs=crs))
        written.append(p)
        p = root / "points.las"
        with ws.output(p) as tmp:
            las = LasWriter(tmp, X[ok].min(axis=0) if ok.any() else np.zeros(3))
            try:
                las.write(X[ok])
            finally:
                las.close()
        written.append(p)
        p = root / "observations.csv"
        w = np.min(np.asarray(res.weights, dtype=np.float64).reshape(-1, 2), axis=1)
        ws.write_text(p, observations_text(tracks, -np.asarray(res.residuals_px), w, np.asarray(res.flagged)))
        written.append(p)
        p = root / f"camera_{CAMERA_ID}.json"
        se = {**cam.std_errors, **{k: sd for k, (_val, sd) in ub.interior.items() if math.isfinite(sd)}}
        ws.write_json(p, {**camera_document(replace(cam, std_errors=se)), "name": CAMERA_ID})
        written.append(p)
    return written
