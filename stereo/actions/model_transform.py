"""``stereo model --transform affine|projective``: a pair's model oriented to control by a 3D affine (12
parameters) or projective (15 parameters) transformation (seed 003, 3.3.1-3.3.2).

The relative orientation JSON of ``stereo orient`` (any system, a camera known) gives a similar
model; the projective pair JSON of ``stereo orient --system projective`` without a camera gives a
projective model (only ``--transform projective``). Writes the same three files as the similarity
path: the points PLY, ``<output>.csv`` and ``<output>.orientation.json``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rectify.atomic import read_json
from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from stereo.actions.common import PathArg, given
from stereo.actions.workspace import PairWorkspace, model_outputs
from stereo.formats.orientation import dump_orientation
from stereo.formats.points import dump_ply, dump_points_csv
from stereo.formats.projective import is_projective_pair, read_projective_pair
from stereo.pair.projective_model import TransformedModel, build_transformed_model, metric_cameras

__all__ = ["TransformModelResult", "model_transformed"]


@dataclass(frozen=True, eq=False)
class TransformModelResult:
    """Result of :func:`model_transformed`: the oriented model and the files written."""

    model: TransformedModel
    outputs: tuple[Path, Path, Path]

    def summary_lines(self) -> list[str]:
        ply, csv_path, orient_path = self.outputs
        return [*self.model.summary_lines(), f"wrote {ply}, {csv_path}, {orient_path}"]


def model_transformed(ro_json: PathArg, *, matches: PathArg, output: PathArg, transform: str,
                      camera: PathArg | None = None, control: PathArg | None = None,
                      check_ids: Sequence[str] = (), report_dir: PathArg | None = None,
                      overwrite: bool = False) -> TransformModelResult:
    """Intersect the matches of a pair and orient the model to control by ``transform``.

    Raises
    ------
    InvalidInputError
        No control; ``--report`` (not available for these transformations); ``--camera`` with a
        projective pair; the affine transformation of a projective model; ids of another pair;
        outputs that exist.
    EstimationError
        Too few control points (4 non-coplanar for affine, 5 for projective), coplanar control.
    """
    if transform not in ("affine", "projective"):
        raise InvalidInputError(f"unknown transformation {transform!r}; expected 'affine' or 'projective'")
    if control is None:
        raise InvalidInputError(f"--transform {transform} needs --control (the {transform} orientation to control "
                                "is the only way to object coordinates)")
    if report_dir is not None:
        raise InvalidInputError(f"--report is not available with --transform {transform}")
    outputs = model_outputs(output)
    ws = PairWorkspace(overwrite=overwrite, inputs=given(ro_json, matches, camera, control))
    ws.plan(*outputs)
    doc = read_json(ro_json, what="orientation JSON")
    m = ws.load_matches(matches)
    ctrl = ws.load_control(control)
    if is_projective_pair(doc):
        if camera is not None:
            raise InvalidInputError(f"{str(ro_json)!r} is a projective pair (no camera): --camera does not apply")
        pair = read_projective_pair(ro_json)
        ro_ids = set(pair.ids)
        cams = pair.cameras
        left, right = m.left, m.right
        cl, cr = ctrl.left, ctrl.right
        px = (1.0, 1.0)
        kind = "projective"
        pix = None
    else:
        geom = ws.load_relative(ro_json)
        if camera is not None:
            cam = ws.load_camera(camera)
        elif isinstance(geom.raw.get("camera"), dict):
            cam = Camera.from_dict(geom.raw["camera"])
        else:
            raise InvalidInputError(f"{str(ro_json)!r} holds no camera (it was not written by `stereo orient`): "
                                    "pass --camera CAM.json")
        for side, pts in (("left", m.left), ("right", m.right)):
            ws.check_points_in_frame(cam, pts, m.ids, f"{side} tie points")
        ro_ids = {str(p.get("id")) for p in geom.raw.get("points", []) if isinstance(p, dict)}
        cams = metric_cameras(geom.rotation_left, geom.rotation_right, geom.base)
        f1, f2 = geom.focal_length_mm

        def norm(pxy: np.ndarray, f: float) -> np.ndarray:
            return -cam.photo_from_pixel(pxy) / f  # (-x / f, -y / f): see metric_cameras

        left, right = norm(m.left, f1), norm(m.right, f2)
        cl, cr = norm(ctrl.left, f1), norm(ctrl.right, f2)
        pix = cam.pixel_size_mm
        px = (f1 / pix, f2 / pix)
        kind = "similar"
    if ro_ids and not ro_ids & set(m.ids):
        raise InvalidInputError(
            f"ids in {str(matches)!r} do not match the points of {str(ro_json)!r} (e.g. {sorted(m.ids)[:3]} vs "
            f"{sorted(ro_ids)[:3]}): the files belong to different pairs")
    tm = build_transformed_model(cams, left, right, transform=transform, model_kind=kind, ids=m.ids,
                                 control=ctrl, control_image=(cl, cr), check_ids=check_ids, px_per_unit=px)
    # per-point residual column of the CSV: the reprojection rms in mm on the photo (NaN for a projective
    # model, whose image has no millimetres)
    res_mm = tm.image_residual_px * pix if pix is not None else np.full(len(tm.ids), np.nan)
    with ws.transaction():
        with ws.output(outputs[0]) as tmp:
            dump_ply(tmp, np.where(np.isfinite(tm.points), tm.points, 0.0),
                     comment=f"object frame ({transform} orientation of a {kind} model)")
        with ws.output(outputs[1]) as tmp:
            dump_points_csv(tmp, tm.ids, tm.points, res_mm, std=tm.std, crs=tm.crs)
        with ws.output(outputs[2]) as tmp:
            dump_orientation(tmp, tm.to_dict())
    return TransformModelResult(tm, outputs)
