"""``stereo model``: model points of an oriented pair and their absolute orientation."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from rectify.atomic import read_json
from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from stereo.actions.common import PathArg, control_mm, given
from stereo.actions.model_transform import TransformModelResult, model_transformed
from stereo.actions.workspace import PairWorkspace, model_outputs
from stereo.formats.projective import is_projective_pair
from stereo.pair.model import ModelOptions, StereoModel, build_model
from stereo.pair.projective_model import TRANSFORMS
from stereo.relative import RelativeGeometry
from stereo.report.pair import write_pair_report


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
          options: ModelOptions | None = None, transform: str = "similarity") -> ModelResult | TransformModelResult:
    """``stereo model``: matches + relative orientation -> model points, oriented to control when given.

    Writes ``output`` (PLY) with ``<output>.csv`` and ``<output>.orientation.json`` beside it.
    ``transform`` ``"affine"`` or ``"projective"`` (seed 003, 3.3): the model oriented by the 12- or
    15-parameter transformation instead of the similarity
    (:func:`stereo.actions.model_transform.model_transformed`); a projective pair JSON (``stereo orient
    --system projective`` without a camera) needs ``"projective"``.

    Raises
    ------
    InvalidInputError
        No camera, ids of other pairs, check ids without control, outputs that exist; and as
        :func:`stereo.pair.model.build_model`.
    """
    opts = options or ModelOptions()
    if transform not in TRANSFORMS:
        raise InvalidInputError(f"unknown transformation {transform!r}; expected one of {list(TRANSFORMS)}")
    projective_pair = is_projective_pair(read_json(ro_json, what="orientation JSON"))
    if transform != "similarity" or projective_pair:
        if transform == "similarity":
            raise InvalidInputError(f"{str(ro_json)!r} is a projective pair (no camera): its model is projective, "
                                    "not similar; use --transform projective with --control")
        if replace(opts, check_ids=()) != ModelOptions():
            raise InvalidInputError(f"--frame, --method, --robust, --deformation and --control-sigma-px apply to the "
                                    f"similarity only, not to --transform {transform}")
        return model_transformed(ro_json, matches=matches, output=output, transform=transform, camera=camera,
                                 control=control, check_ids=opts.check_ids, report_dir=report_dir,
                                 overwrite=overwrite)
    outputs = model_outputs(output)
    ws = PairWorkspace(overwrite=overwrite, inputs=given(ro_json, matches, camera, control),
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
                         control=ctrl, control_mm=control_mm(ctrl, cam), options=opts,
                         pixel_size_mm=cam.pixel_size_mm)
    report = None
    with ws.transaction():
        ws.save_model(result, points_path=outputs[0], csv_path=outputs[1], orientation_path=outputs[2])
        if report_dir is not None:
            report = write_pair_report(result, report_dir, title="stereo model", camera=cam, overwrite=overwrite)
    return ModelResult(result, outputs, report)
