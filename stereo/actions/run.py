"""``stereo run``: the whole pair chain (match, orient, model, absolute, optionally dense)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from rectify.errors import InvalidInputError
from rectify.features import MatcherConfig
from rectify.formats.detect import is_zoom_camera, read_one_camera
from rectify.geometry.camera import Camera
from rectify.geometry.points import ControlTable
from rectify.raster.distributed import check_scheduler
from rectify.raster.exif import exif_focal_length
from stereo.actions.common import PathArg, Progress, match_photos, parallax_sigma0_mm, sigma0_text
from stereo.actions.dense import DenseOptions, DenseResult, run_dense
from stereo.actions.workspace import PairWorkspace
from stereo.pair.model import ModelOptions, StereoModel, build_model
from stereo.relative import RelativeGeometry, RelativeOrientation
from stereo.relative.degenerate import check_base
from stereo.report.pair import write_pair_report


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

    Every output of the layout (:data:`stereo.actions.workspace.RUN_LAYOUT`) and the report folder are
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
        Also run the dense chain (``stereo run --dense``: :func:`stereo.actions.dense.run_dense`) on
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
        check_scheduler(dense.scheduler)  # a cluster: reachable, a Dask scheduler, with a worker
    # any camera file; a zoom camera at the photos' EXIF focal length (one camera for both photos)
    cam = camera if isinstance(camera, Camera) else read_one_camera(camera, image=left)
    if not isinstance(camera, Camera) and is_zoom_camera(camera):
        zl, zr = exif_focal_length(left), exif_focal_length(right)
        if zl != zr:
            raise InvalidInputError(f"stereo run uses one camera for both photos, but their EXIF focal lengths "
                                    f"differ ({zl} and {zr} mm): orient the pair with stereo orient (a camera per "
                                    "photo from the zoom camera), then stereo model")
    ctrl = ws.load_control(control) if isinstance(control, (str, Path)) else control
    # the camera against both photos and the control image points, before matching
    ws.check_camera_image(cam, left, "left")
    ws.check_camera_image(cam, right, "right")
    if ctrl is not None:
        for side, px in (("left", ctrl.left), ("right", ctrl.right)):
            ws.check_points_in_frame(cam, px, ctrl.ids, f"{side} control image points")
    t0 = time.perf_counter()
    mr = match_photos(left, right, progress, matcher)
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
    # each match by its own precision (unrefined matches weigh less); control image points weigh 1
    w = m.weights()
    weights = None if w is None else np.concatenate([w, np.ones(len(ids_all) - len(m))])
    ro = RelativeOrientation.from_points(left_mm, right_mm, focal_length_mm=(cam.focal_length_mm,
                                         cam.focal_length_mm), system=opts.ro_system, robust=opts.ro_robust,
                                         ids=ids_all, pixel_size_mm=cam.pixel_size_mm, weights=weights)
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
