"""One function per step of the ``stereo`` commands: orient, model, resect, run, demo.

Each action takes the input paths and an options dataclass, checks every planned output before any
work (a :class:`~stereo.workspace.PairWorkspace`), computes, writes its outputs in one
transaction (all or none), and returns a frozen result whose ``summary_lines()`` are exactly the
lines the command prints. The ``stereo`` CLI modules only parse options, call one action and print
those lines.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rasterio.errors import NotGeoreferencedWarning

from rectify.camera import Camera
from rectify.distributed import resolve_scheduler
from rectify.errors import InvalidInputError
from rectify.features import MatcherConfig, match_images
from rectify.formats import ControlTable
from rectify.report import json_safe
from rectify.residuals import rms

from .dense.pipeline import DenseOptions, DenseResult, run_dense
from .formats import exterior_dict
from .model import ModelOptions, StereoModel, build_model
from .relative import RelativeGeometry, RelativeOrientation
from .relative.degenerate import check_base
from .report import write_orient_report, write_pair_report, write_resect_report
from .resection import ExteriorOrientation
from .resection import resect as resect_points
from .synthetic import make_scene, write_scene_inputs
from .workspace import PairWorkspace, model_outputs

__all__ = [
    "DemoResult",
    "ModelResult",
    "OrientOptions",
    "OrientResult",
    "ResectOptions",
    "ResectResult",
    "RunResult",
    "demo",
    "model",
    "orient",
    "resect",
    "run",
]

Progress = Callable[[int, int], None]
PathArg = str | Path


def _given(*paths: PathArg | None) -> list[PathArg]:
    return [p for p in paths if p is not None]


# ---------------------------------------------------------------------- orient
@dataclass(frozen=True)
class OrientOptions:
    """Options of ``stereo orient``.

    Attributes
    ----------
    system : str
        System of elements (:data:`stereo.relative.SYSTEMS`).
    robust : str
        :data:`rectify.robust.ROBUST_METHODS`; ``"none"`` is plain least squares.
    initial : str
        :data:`stereo.relative.INITIAL_METHODS`.
    """

    system: str = "left-image"
    robust: str = "none"
    initial: str = "auto"


@dataclass(frozen=True, eq=False)
class OrientResult:
    """Result of :func:`orient`: the relative orientation and the files written."""

    ro: RelativeOrientation
    camera: Camera
    output: Path
    options: OrientOptions
    n_matched: int | None = None
    match_rmse_px: float | None = None
    report: Path | None = None

    def summary_lines(self) -> list[str]:
        ro, cam, o = self.ro, self.camera, self.options
        out = []
        if self.n_matched is not None:
            out.append(f"matched {self.n_matched} tie points (verification RMSE {self.match_rmse_px:.3g} px)")
        s = ro.summary()
        out.append(f"relative orientation ({o.system}), {s['n_used']} of {s['n_points']} points used, "
                   f"{s['n_outliers']} outliers, {s['iterations']} iterations"
                   + (f" + {s['irls_iterations']} reweightings ({o.robust})" if o.robust != "none" else "")
                   + f", start: {s['initial']}")
        out.append(f"residual vertical parallax: RMSE {s['rms_parallax_px']:.3f} px "
                   f"({s['rms_parallax_mm'] * 1000:.2f} um); sigma0 {sigma0_text(ro, cam.pixel_size_mm)}; "
                   f"condition number {ro.condition_number:.3g}")
        std = ro.std_errors
        for i, name in enumerate(ro.names):
            se = "" if std is None else f" +- {math.degrees(std[i]):.5f}"
            out.append(f"  {name:>7} = {math.degrees(ro.elements[i]):11.5f}{se} deg")
        wf = ro.western()
        out.append(f"  relative omega, phi, kappa = {math.degrees(wf.omega):.5f}, {math.degrees(wf.phi):.5f}, "
                   f"{math.degrees(wf.kappa):.5f} deg; base (1, {wf.by:.5f}, {wf.bz:.5f})")
        out.append(f"wrote {self.output}")
        if self.report is not None:
            out.append(f"report: {self.report}")
        return out


#: The matcher of a stereo pair: fundamental-matrix verification (a homography drops most matches of a
#: pair with relief); the other options are :class:`rectify.features.MatcherConfig`'s defaults.
PAIR_MATCHER = MatcherConfig(verify="fundamental")
#: The matcher of ``stereo orient LEFT RIGHT``: a relative orientation needs no more than a few thousand
#: well-spread tie points (its precision saturates long before), so at most 12000 keypoints per image and
#: 4000 matches (issue 12: about a third of the time on a 2000 x 2000 pair; figures in docs/features.md).
#: ``stereo run`` keeps :data:`PAIR_MATCHER`: its matches are its model points.
ORIENT_MATCHER = replace(PAIR_MATCHER, max_keypoints=12000, max_matches=4000)


def matcher_config(*, detector: str | None = None, verify: str | None = None, refine: bool | None = None,
                   max_matches: int | None = None, max_keypoints: int | None = None,
                   base: MatcherConfig = PAIR_MATCHER) -> MatcherConfig:
    """``base`` (:data:`PAIR_MATCHER` or :data:`ORIENT_MATCHER`) with the commands' options (None: the base's)."""
    given: dict[str, Any] = {"detector": detector, "verify": verify, "refine": refine, "max_matches": max_matches,
                             "max_keypoints": max_keypoints}
    return replace(base, **{k: v for k, v in given.items() if v is not None})


def parallax_sigma0_mm(ro: RelativeOrientation) -> float | None:
    """The sigma0 of a relative orientation that the console and the report both print, mm.

    sigma0 = sqrt(sum w q^2 / (n_used - 5)) over the residual vertical parallaxes q of the points
    used (outliers excluded; w the final robust weights, 1 without a robust estimator): the sigma0
    of the report's residual table (:meth:`RelativeOrientation.residual_table`). ``None`` without
    redundancy (5 points). ``ro.sigma0_mm`` (one photo coordinate) is a different figure, kept in
    the JSON for the weighting of the model.
    """
    s = ro.residual_table(units="mm").sigma0
    return float(s) if s is not None and math.isfinite(s) else None


def sigma0_text(ro: RelativeOrientation, pixel_size_mm: float | None) -> str:
    """``"7.96 um = 0.055 px (parallax, 444 - 5 redundancy)"``, the one printed sigma0 (:func:`parallax_sigma0_mm`)."""
    s = parallax_sigma0_mm(ro)
    if s is None:
        return "n/a (no redundancy)"
    px = f" = {s / pixel_size_mm:.3f} px" if pixel_size_mm else ""
    return f"{s * 1000:.2f} um{px} (vertical parallax, {ro.n_used} - 5 redundancy, outliers excluded)"


def _match(left: PathArg, right: PathArg, progress: Progress | None = None,
           matcher: MatcherConfig | None = None) -> Any:
    """Tie points of a photo pair: :data:`PAIR_MATCHER` unless ``matcher`` is given."""
    with warnings.catch_warnings():  # plain photos have no geotransform, as expected
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return match_images(left, right, config=matcher or PAIR_MATCHER, progress=progress)


def orient(*, camera: PathArg, output: PathArg, matches: PathArg | None = None,
           images: tuple[PathArg, PathArg] | None = None, camera_right: PathArg | None = None,
           matches_out: PathArg | None = None, report_dir: PathArg | None = None, overwrite: bool = False,
           options: OrientOptions | None = None, matcher: MatcherConfig | None = None) -> OrientResult:
    """``stereo orient``: relative orientation from a matches CSV or from matching two images.

    Parameters
    ----------
    camera, camera_right : path
        Camera JSON of both images (or the left one) and of the right image when it differs.
    output : path
        Relative orientation JSON to write (the cameras are stored in it).
    matches : path, optional
        Matches CSV (pixels). Exactly one of ``matches`` and ``images``.
    images : (left, right), optional
        Photos to match first; ``matches_out`` also writes the matches.
    report_dir : path, optional
        QA report folder.
    matcher : MatcherConfig, optional
        Matcher options with ``images`` (default :data:`ORIENT_MATCHER`, fundamental-matrix verification).

    Raises
    ------
    InvalidInputError
        Neither or both of ``matches`` and ``images``; no tie points; an output exists without
        ``overwrite`` or equals an input; and as :meth:`RelativeOrientation.from_pixels`.
    """
    opts = options or OrientOptions()
    if (matches is None) == (images is None):
        raise InvalidInputError("give either a matches CSV or the two images LEFT RIGHT")
    ws = PairWorkspace(overwrite=overwrite, inputs=_given(camera, camera_right, matches, *(images or ())),
                       report_dir=report_dir)
    ws.plan(output, matches_out)
    ws.check_report_dir()
    cam = ws.load_camera(camera)
    cam_r = ws.load_camera(camera_right) if camera_right else None
    n_matched = rmse = None
    if images is not None:  # check the cameras against the photos before matching
        ws.check_camera_image(cam, images[0], "left")
        ws.check_camera_image(cam_r or cam, images[1], "right")
        res = _match(images[0], images[1], matcher=matcher or ORIENT_MATCHER)
        m = res.matches
        n_matched, rmse = len(m), res.rmse_px
    else:
        assert matches is not None
        m = ws.load_matches(matches)
    if len(m) == 0:
        raise InvalidInputError("no tie points")
    ws.check_points_in_frame(cam, m.left, m.ids, "left tie points")
    ws.check_points_in_frame(cam_r or cam, m.right, m.ids, "right tie points")
    cam2 = cam_r or cam
    check_base(cam.photo_from_pixel(m.left), cam2.photo_from_pixel(m.right),
               (cam.focal_length_mm, cam2.focal_length_mm), cam.pixel_size_mm)
    ro = RelativeOrientation.from_pixels(m.left, m.right, cam, camera_right=cam_r, system=opts.system,
                                         robust=opts.robust, initial=opts.initial, ids=m.ids)
    # the cameras travel with the orientation, so `stereo model` needs no --camera
    cams = {"camera": cam.to_dict(), **({"camera_right": cam_r.to_dict()} if cam_r else {})}
    report = None
    with ws.transaction():
        if matches_out is not None:
            ws.save_matches(matches_out, m)
        ws.save_relative(output, ro, extra=cams)
        if report_dir is not None:
            report = write_orient_report(ro, cam, report_dir, title=f"stereo orient: relative orientation "
                                         f"({opts.system})", overwrite=overwrite)
    return OrientResult(ro, cam, Path(output), opts, n_matched, rmse, report)


# ---------------------------------------------------------------------- model
@dataclass(frozen=True, eq=False)
class ModelResult:
    """Result of :func:`model`: the model and the files written."""

    model: StereoModel
    outputs: tuple[Path, Path, Path]
    report: Path | None = None

    def summary_lines(self) -> list[str]:
        m = self.model
        s = m.summary
        out = [f"{len(m.ids)} points intersected ({s['intersection_method']}); RMS vertical parallax "
               f"{s['rms_vertical_parallax_mm'] * 1000:.2f} um "
               f"({s.get('rms_vertical_parallax_px', float('nan')):.3f} px)"]
        out += m.summary_lines()
        ply, csv_path, orient_path = self.outputs
        out.append(f"wrote {ply}, {csv_path}, {orient_path}")
        if self.report is not None:
            out.append(f"report: {self.report}")
        return out


def _camera_for(ws: PairWorkspace, geometry: RelativeGeometry, camera: PathArg | None, ro_json: PathArg) -> Camera:
    if camera is not None:
        return ws.load_camera(camera)
    if isinstance(geometry.raw.get("camera"), dict):  # written by `stereo orient`
        return Camera.from_dict(geometry.raw["camera"])
    raise InvalidInputError(f"{str(ro_json)!r} holds no camera (it was not written by `stereo orient`): pass "
                            "--camera CAM.json, pixels cannot be converted to photo mm without it")


def model(ro_json: PathArg, *, matches: PathArg, output: PathArg, camera: PathArg | None = None,
          control: PathArg | None = None, report_dir: PathArg | None = None, overwrite: bool = False,
          options: ModelOptions | None = None) -> ModelResult:
    """``stereo model``: matches + relative orientation -> model points, oriented to control when given.

    Writes ``output`` (PLY) with ``<output>.csv`` and ``<output>.orientation.json`` beside it.

    Raises
    ------
    InvalidInputError
        No camera, ids of other pairs, check ids without control, outputs that exist; and as
        :func:`stereo.model.build_model`.
    """
    opts = options or ModelOptions()
    outputs = model_outputs(output)
    ws = PairWorkspace(overwrite=overwrite, inputs=_given(ro_json, matches, camera, control),
                       report_dir=report_dir)
    ws.plan(*outputs)
    ws.check_report_dir()
    geom = ws.load_relative(ro_json)
    cam = _camera_for(ws, geom, camera, ro_json)
    m = ws.load_matches(matches)
    ro_ids = {str(p.get("id")) for p in geom.raw.get("points", []) if isinstance(p, dict)}
    if ro_ids and not ro_ids & set(m.ids):
        raise InvalidInputError(
            f"ids in {str(matches)!r} do not match the points of {str(ro_json)!r} (e.g. {sorted(m.ids)[:3]} vs "
            f"{sorted(ro_ids)[:3]}): the files belong to different pairs")
    ctrl = ws.load_control(control) if control else None
    if opts.check_ids and ctrl is None:
        raise InvalidInputError("--check needs --control")
    for side, px in (("left", m.left), ("right", m.right)):
        ws.check_points_in_frame(cam, px, m.ids, f"{side} tie points")
    if ctrl is not None:
        for side, px in (("left", ctrl.left), ("right", ctrl.right)):
            ws.check_points_in_frame(cam, px, ctrl.ids, f"{side} control image points")
    result = build_model(cam.photo_from_pixel(m.left), cam.photo_from_pixel(m.right), geom, ids=m.ids,
                         control=ctrl, control_mm=_control_mm(ctrl, cam), options=opts,
                         pixel_size_mm=cam.pixel_size_mm)
    report = None
    with ws.transaction():
        ws.save_model(result, points_path=outputs[0], csv_path=outputs[1], orientation_path=outputs[2])
        if report_dir is not None:
            report = write_pair_report(result, report_dir, title="stereo model", camera=cam, overwrite=overwrite)
    return ModelResult(result, outputs, report)


def _control_mm(control: ControlTable | None, camera: Camera) -> tuple[NDArray, NDArray] | None:
    if control is None:
        return None
    return camera.photo_from_pixel(control.left), camera.photo_from_pixel(control.right)


# ---------------------------------------------------------------------- resect
@dataclass(frozen=True)
class ResectOptions:
    """Options of ``stereo resect``.

    Attributes
    ----------
    initial : str
        Direct solution for the initial values (:data:`stereo.resection.INITIAL_METHODS`).
    free_interior : bool
        Also estimate f, x0, y0 (at least 5 points; weak over flat ground).
    """

    initial: str = "pnp"
    free_interior: bool = False


@dataclass(frozen=True, eq=False)
class ResectResult:
    """Result of :func:`resect`: the exterior orientation and the files written."""

    eo: ExteriorOrientation
    camera: Camera
    output: Path
    options: ResectOptions
    report: Path | None = None

    def summary_lines(self) -> list[str]:
        eo, cam = self.eo, self.camera
        om, ph, ka = (math.degrees(a) for a in eo.angles)
        se = eo.std_errors
        out = [f"omega {om:.4f} deg +- {math.degrees(se['omega']):.4f}, phi {ph:.4f} +- "
               f"{math.degrees(se['phi']):.4f}, kappa {ka:.4f} +- {math.degrees(se['kappa']):.4f}",
               f"X {eo.position[0]:.3f} +- {se['x']:.3f}, Y {eo.position[1]:.3f} +- {se['y']:.3f}, "
               f"Z {eo.position[2]:.3f} +- {se['z']:.3f}"]
        if self.options.free_interior:
            out.append(f"f {eo.focal_length_mm:.4f} mm +- {se['f']:.4f}, x0 {eo.principal_point_mm[0]:.4f} mm, "
                       f"y0 {eo.principal_point_mm[1]:.4f} mm")
        t = eo.residuals
        assert t is not None
        out.append(f"{t.step}: {t.summary_line()} ({t.summary()['rmse'] / cam.pixel_size_mm:.3f} px)")
        out.append(f"wrote {self.output}")
        if self.report is not None:
            out.append(f"report: {self.report}")
        return out


def resect(*, camera: PathArg, gcps: PathArg, output: PathArg, report_dir: PathArg | None = None,
           overwrite: bool = False, options: ResectOptions | None = None) -> ResectResult:
    """``stereo resect``: exterior orientation of one photo from GCPs with heights.

    Raises
    ------
    InvalidInputError
        The GCP file has no z column; an output exists; and as :func:`stereo.resection.resect`.
    """
    opts = options or ResectOptions()
    ws = PairWorkspace(overwrite=overwrite, inputs=[camera, gcps], report_dir=report_dir)
    ws.plan(output)
    ws.check_report_dir()
    cam = ws.load_camera(camera)
    g = ws.load_gcps(gcps)
    if g.z is None:
        raise InvalidInputError(f"{str(gcps)!r} has no z column: space resection needs ground heights")
    ground = np.column_stack([g.target, g.z])
    eo = resect_points(cam.photo_from_pixel(g.pixel), ground, focal_length_mm=cam.focal_length_mm,
                       principal_point_mm=(0.0, 0.0), ids=g.ids, check=g.check, free_interior=opts.free_interior,
                       initial=opts.initial, crs=g.crs)
    report = None
    with ws.transaction():
        ws.save_exterior(output, eo, camera=cam.to_dict())
        if report_dir is not None:
            summary = {k: v for k, v in exterior_dict(eo, camera=cam.to_dict()).items()
                       if k not in ("format", "version")}
            report = write_resect_report(eo, report_dir, summary=summary, overwrite=overwrite)
    return ResectResult(eo, cam, Path(output), opts, report)


# ---------------------------------------------------------------------- run
@dataclass(frozen=True, eq=False)
class RunResult:
    """Result of :func:`run`: the model (its summary holds the matching and RO figures) and the folder."""

    model: StereoModel
    ro: RelativeOrientation
    out_dir: Path
    report: Path | None = None
    dense: DenseResult | None = None

    def summary_lines(self) -> list[str]:
        s = self.model.summary
        n_ctrl_file = s.get("n_control_file_points", 0)
        out = [f"{s['n_matches']} matches; relative orientation ({s['ro_system']}) on "
               f"{s['n_matches'] + n_ctrl_file} points ({s['n_matches']} matches + {n_ctrl_file} control-file "
               f"points): {s['ro_n_used']} used, sigma0 {sigma0_text(self.ro, self.ro.pixel_size_mm)}"]
        out += self.model.summary_lines(tie_note="kept by the relative orientation")
        out.append(f"outputs in {self.out_dir}: points.ply, points.csv, orientation.json, relative.json, "
                   "matches.csv, report/" + (", dense/" if self.dense is not None else ""))
        if self.dense is not None:
            out += [f"dense: {line}" for line in self.dense.summary_lines()]
        return out


def run(left: PathArg, right: PathArg, *, camera: PathArg | Camera, out_dir: PathArg,
        control: PathArg | ControlTable | None = None, overwrite: bool = False, options: ModelOptions | None = None,
        report: bool = True, title: str = "stereo run", extra_summary: dict[str, Any] | None = None,
        progress: Progress | None = None, matcher: MatcherConfig | None = None,
        dense: DenseOptions | None = None) -> RunResult:
    """``stereo run``: match, orient, intersect, orient absolutely; write everything into ``out_dir``.

    Every output of the layout (:data:`stereo.workspace.RUN_LAYOUT`) and the report folder are
    checked before matching. The files are written in one transaction: on any error none of them
    is left, and an output folder created by the run is removed again.

    Parameters
    ----------
    left, right : path
        The photos.
    camera : path or Camera
        Camera JSON (one camera for both photos).
    control : path or ControlTable, optional
        Stereo control CSV; its image points are tie points of the relative orientation too.
    options : ModelOptions, optional
        ``ro_system``/``ro_robust`` for the relative orientation, the rest for the model.
    matcher : MatcherConfig, optional
        Matcher options (default :data:`PAIR_MATCHER`, fundamental-matrix verification).
    dense : DenseOptions, optional
        Also run the dense chain (``stereo run --dense``: :func:`stereo.dense.pipeline.run_dense`) on
        the orientation just written, into ``out_dir/dense``. It runs after the pair's files are
        committed; if it fails, the pair's files stay and ``dense/`` is left out.
    """
    opts = options or ModelOptions()
    inputs = [left, right] + [p for p in (camera, control) if isinstance(p, (str, Path))]
    ws = PairWorkspace.for_run(out_dir, overwrite=overwrite, inputs=tuple(inputs), report=report)
    ws.plan_run()
    dense_dir = Path(out_dir) / "dense"
    if dense is not None and dense_dir.exists() and not overwrite:
        raise InvalidInputError(f"output {str(dense_dir)!r} exists; pass --overwrite to replace it")
    if dense is not None:  # the dense step's scheduler (or $RECTIFY_SCHEDULER) is checked before any work
        resolve_scheduler(dense.scheduler)
    cam = camera if isinstance(camera, Camera) else ws.load_camera(camera)
    ctrl = ws.load_control(control) if isinstance(control, (str, Path)) else control
    # the camera against both photos and the control image points, before matching
    ws.check_camera_image(cam, left, "left")
    ws.check_camera_image(cam, right, "right")
    if ctrl is not None:
        for side, px in (("left", ctrl.left), ("right", ctrl.right)):
            ws.check_points_in_frame(cam, px, ctrl.ids, f"{side} control image points")
    t0 = time.perf_counter()
    mr = _match(left, right, progress, matcher)
    m = mr.matches
    t_match = time.perf_counter() - t0
    # pixels -> photo mm once, for the relative orientation and the model
    left_px, right_px, ids_all = m.left, m.right, list(m.ids)
    if ctrl is not None:  # control image points are tie points too
        left_px = np.vstack([left_px, ctrl.left])
        right_px = np.vstack([right_px, ctrl.right])
        ids_all += list(ctrl.ids)
    left_mm, right_mm = cam.photo_from_pixel(left_px), cam.photo_from_pixel(right_px)
    check_base(left_mm, right_mm, cam.focal_length_mm, cam.pixel_size_mm)  # "no base" before the adjustment
    ro = RelativeOrientation.from_points(left_mm, right_mm, focal_length_mm=(cam.focal_length_mm,
                                         cam.focal_length_mm), system=opts.ro_system, robust=opts.ro_robust,
                                         ids=ids_all, pixel_size_mm=cam.pixel_size_mm)
    ro = replace(ro, left_px=np.asarray(left_px, dtype=np.float64))
    n = len(m)
    keep = ~np.asarray(ro.outlier)[:n]
    kept_ids = tuple(np.asarray(m.ids)[keep])
    cmm = None if ctrl is None else (left_mm[n:], right_mm[n:])
    result = build_model(left_mm[:n][keep], right_mm[:n][keep], RelativeGeometry.from_relative(ro), ids=kept_ids,
                         control=ctrl, control_mm=cmm, options=opts, pixel_size_mm=cam.pixel_size_mm)
    summary = dict(result.summary)
    summary.update({"n_matches": n, "match_rmse_px": mr.rmse_px, "t_match_s": t_match,
                    "ro_sigma0_mm": ro.sigma0_mm, "ro_sigma0_parallax_mm": parallax_sigma0_mm(ro),
                    "ro_n_used": ro.n_used, "ro_system": ro.system})
    if extra_summary:
        summary.update(extra_summary)
    result = replace(result, summary=summary, tables=[ro.residual_table()] + result.tables)
    report_path = None
    ws.prepare()
    with ws.transaction():
        ws.save_matches(ws.layout_path("matches"), m)
        # the camera travels with the orientation (as in `stereo orient`): `stereo model`/`dense` need no --camera
        ws.save_relative(ws.layout_path("relative"), ro, extra={"camera": cam.to_dict()})
        ws.save_model(result, points_path=ws.layout_path("points"), csv_path=ws.layout_path("points_csv"),
                      orientation_path=ws.layout_path("orientation"), model_ply_path=ws.layout_path("model_points"))
        if ws.report_dir is not None:
            report_path = write_pair_report(result, ws.report_dir, title=title, ro=ro, left_image=left, camera=cam,
                                            overwrite=overwrite, right_image=right)
    dres = None
    if dense is not None:
        dres = run_dense(ws.layout_path("relative"), left, right, dense_dir, matches=ws.layout_path("matches"),
                         control=control if isinstance(control, (str, Path)) else None, options=dense,
                         overwrite=overwrite)
    return RunResult(result, ro, Path(out_dir), report_path, dres)


# ---------------------------------------------------------------------- demo
@dataclass(frozen=True, eq=False)
class DemoResult:
    """Result of :func:`demo`: the run and the comparison with the synthetic truth."""

    run: RunResult
    truth: dict[str, Any] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        t, m = self.truth, self.run.model
        x, y, z = t["check_rmse_xyz_m"]
        return self.run.summary_lines() + [
            "accuracy against the truth:",
            f"  {t['n_check']} check points: RMSE X {x:.3f} m, Y {y:.3f} m, Z {z:.3f} m; RMS of error / "
            f"predicted std {t['check_normalised_rms']:.3f} (target 0.67-1.5); per axis "
            + ", ".join(f"{v:.2f}" for v in t["check_normalised_rms_xyz"]),
            f"  control/check image noise: simulated {t['pixel_noise_px']:.3f} px, estimated "
            f"{m.summary.get('control_sigma_px', float('nan')):.3f} px",
            f"  all {t['n_points']} points vs DEM height: RMSE {t['dem_rmse_m']:.3f} m "
            f"({t['dem_rmse_m'] / t['ground_pixel_m']:.2f} ground pixels of {t['ground_pixel_m']:.2f} m)",
            f"report: {self.run.out_dir / 'report' / 'report.html'}",
        ]


def demo(out_dir: PathArg, *, seed: int = 0, size_px: int = 480, overwrite: bool = False,
         pixel_noise_px: float = 0.2, progress: Progress | None = None) -> DemoResult:
    """``stereo demo``: synthetic pair (:mod:`stereo.synthetic`) -> :func:`run` -> accuracy against the truth.

    Writes the inputs into ``out_dir/input``, the run layout into ``out_dir`` and the comparison
    with the truth (check point RMSE per axis, RMS of normalised check errors, RMSE of all points'
    heights against the DEM) into ``out_dir/truth_comparison.json``.
    """
    out = Path(out_dir)
    PairWorkspace.for_run(out, overwrite=overwrite).plan_run()  # fail before rendering
    scene = make_scene(seed, size_px=size_px)
    inp = write_scene_inputs(scene, out / "input", seed=seed, pixel_noise_px=pixel_noise_px, overwrite=overwrite,
                             progress=progress)
    control = PairWorkspace().load_control(inp["control"])
    ground_px = scene.cell_m
    r = run(inp["left"], inp["right"], camera=scene.camera, out_dir=out, control=control, overwrite=overwrite,
            # robust="none": the demo's control is clean and its figures are the README's
            options=ModelOptions(check_ids=inp["check_ids"], robust="none"),
            title="stereo demo: synthetic pair with known truth",
            extra_summary={"scene_seed": seed, "ground_pixel_m": ground_px}, progress=progress)
    m = r.model
    assert m.ground is not None
    chk = m.is_check
    truth = np.array([inp["truth"][i] for i, c in zip(m.ids, chk, strict=True) if c])
    e = m.ground[chk] - truth
    dz = m.ground[:, 2] - scene.height(m.ground[:, :2])
    ok = np.isfinite(dz)
    nrm = e / m.ground_std[chk] if m.ground_std is not None else np.full_like(e, np.nan)
    res = {"n_check": int(chk.sum()), "check_rmse_xyz_m": [rms(e[:, k]) for k in range(3)],
           "check_normalised_rms": rms(nrm), "check_normalised_rms_xyz": [rms(nrm[:, k]) for k in range(3)],
           "pixel_noise_px": pixel_noise_px,
           "dem_rmse_m": rms(dz[ok]), "n_points": int(ok.sum()), "ground_pixel_m": ground_px}
    PairWorkspace(overwrite=overwrite).write_json(out / "truth_comparison.json", json_safe(res))
    return DemoResult(r, res)
