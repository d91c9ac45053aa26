"""The checks of ``stereo block``'s inputs made before any matching: do the files fit together, does a datum exist.

:func:`check_block_inputs` refuses images of another size than their camera, coordinates that cannot
be in their CRS, control measured outside an image's frame or lying far outside every image it is
measured in; :func:`check_datum` refuses a block whose datum nothing fixes, and a free network that
would compare check points with a frame they are not in. Each raises with one line naming the values.
The pose file's own check (a pose for every image, no pose of an image not given) is made where the
poses are matched to the images (:mod:`stereo.actions.block`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from rectify.actions.workspace import StrPath, check_table_crs
from rectify.errors import EstimationError, InvalidInputError, RasterIOError
from rectify.geometry.camera import Camera
from stereo.actions.workspace import PairWorkspace
from stereo.block.types import GnssObservations, Pose, project_pixel
from stereo.formats.block import BlockControlTable

__all__ = ["CONTROL_FRAME_MARGIN", "check_block_inputs", "check_datum", "usable_control"]

#: a measured control point must project (through the given poses) within this share of the frame size
#: outside the frame of an image it is measured in (the poses are initial values: a generous margin)
CONTROL_FRAME_MARGIN = 0.5


def check_block_inputs(ws: PairWorkspace, images: Sequence[StrPath], names: tuple[str, ...],
                       cameras: Mapping[str, Camera], camera_of: Sequence[str], poses: Sequence[Pose] | None,
                       crs: str | None, ctrl: BlockControlTable | None, *, control: StrPath | None = None,
                       poses_path: StrPath | None = None, matching: bool = True) -> None:
    """Refuse block inputs that do not fit together, before any matching.

    - every image has the size of its camera (read from the image's header; when the tie points
      are given, ``matching`` False, an image that cannot be read is not checked: it is not used);
    - the projection centres of the poses (``poses_path``) and the control's coordinates are possible
      in their CRS (a geographic CRS label on projected numbers, a UTM zone far from the points:
      :func:`rectify.actions.workspace.check_table_crs`);
    - every control measurement lies in the frame of its image's camera (1 px tolerance, as
      :meth:`PairWorkspace.check_points_in_frame`);
    - with poses, every measured control point projects near (within :data:`CONTROL_FRAME_MARGIN` of
      the frame size) at least one image it is measured in.

    Raises
    ------
    CalibrationError
        An image of another size than its camera.
    CRSError
        Coordinates that cannot be in their CRS (the file, the point, the CRS named).
    InvalidInputError
        Control measured outside an image's frame, or lying outside every image it is measured in.
    RasterIOError
        An image that cannot be read (when it is to be matched).
    """
    for path, cid in zip(images, camera_of, strict=True):
        try:
            ws.check_camera_image(cameras[cid], path, which="block" if len(cameras) == 1 else f"camera {cid!r}'s")
        except RasterIOError:
            if matching:
                raise
    if poses is not None and crs is not None and poses_path is not None:
        check_table_crs(poses_path, crs, np.array([q.position[:2] for q in poses]).reshape(-1, 2),
                        [q.image for q in poses])
    if ctrl is None or not len(ctrl.ids):
        return
    source = str(control) if control is not None else "the control"
    if ctrl.crs is not None:
        check_table_crs(source, ctrl.crs, ctrl.xyz[:, :2], ctrl.ids)
    where = {Path(n).stem: k for k, n in enumerate(names)} | {n: k for k, n in enumerate(names)}
    img = np.array([where.get(m, where.get(Path(m).stem, -1)) for m in ctrl.meas_image], dtype=np.int64)
    outside = np.zeros(len(img), dtype=bool)
    for k in np.unique(img[img >= 0]):
        sel = np.flatnonzero(img == k)
        cam = cameras[camera_of[k]]
        px = ctrl.meas_pixel[sel]
        with np.errstate(invalid="ignore"):
            off = (px[:, 0] < -1.5) | (px[:, 1] < -1.5) | (px[:, 0] > cam.width + 0.5) | (px[:, 1] > cam.height + 0.5)
        outside[sel] = np.isfinite(px).all(axis=1) & off
    if outside.any():
        bad = np.flatnonzero(outside)
        e = ", ".join(f"{ctrl.meas_id[i]} in {names[img[i]]} ({ctrl.meas_pixel[i, 0]:.1f}, {ctrl.meas_pixel[i, 1]:.1f})"
                      for i in bad[:3])
        sizes = sorted({f"{cameras[camera_of[img[i]]].width} x {cameras[camera_of[img[i]]].height} px" for i in bad})
        raise InvalidInputError(f"{bad.size} control measurements of {source!r} outside the camera's "
                                f"{', '.join(sizes)} frame, e.g. {e}: wrong camera file, or points measured on "
                                "another image size")
    if poses is not None:
        _check_control_near_images(ctrl, source, img, cameras, camera_of, poses)


def _check_control_near_images(ctrl: BlockControlTable, source: str, img: np.ndarray, cameras: Mapping[str, Camera],
                               camera_of: Sequence[str], poses: Sequence[Pose]) -> None:
    """Every measured control point (plan-only ones at the control's mean height) projects through the given
    poses near at least one image it is measured in (:data:`CONTROL_FRAME_MARGIN`)."""
    xyz = np.array(ctrl.xyz, dtype=np.float64)
    zs = xyz[np.isfinite(xyz[:, 2]), 2]
    xyz[~np.isfinite(xyz[:, 2]), 2] = float(np.mean(zs)) if zs.size else np.nan
    row = {pid: i for i, pid in enumerate(ctrl.ids)}
    near = np.zeros(len(ctrl.ids), dtype=bool)
    measured = np.zeros(len(ctrl.ids), dtype=bool)
    for m_id, k in zip(ctrl.meas_id, img.tolist(), strict=True):
        i = row[m_id]
        if k < 0 or not np.isfinite(xyz[i]).all():
            continue
        measured[i] = True
        cam = cameras[camera_of[k]]
        px = project_pixel(cam, poses[k], xyz[i][None])[0]
        mx, my = CONTROL_FRAME_MARGIN * cam.width, CONTROL_FRAME_MARGIN * cam.height
        near[i] |= bool(np.isfinite(px).all() and -mx <= px[0] <= cam.width + mx and -my <= px[1] <= cam.height + my)
    far = np.flatnonzero(measured & ~near)
    if far.size:
        e = ", ".join(f"{ctrl.ids[i]} ({xyz[i, 0]:.10g}, {xyz[i, 1]:.10g}, {xyz[i, 2]:.6g})" for i in far[:3])
        raise InvalidInputError(
            f"{far.size} control point(s) of {source!r} lie outside every image they are measured in (projected "
            f"through the given poses, with a margin of {CONTROL_FRAME_MARGIN:g} frame): {e}"
            f"{' ...' if far.size > 3 else ''}; wrong coordinates, CRS or image names in the control file, or poses "
            "in another frame")


def usable_control(ctrl: BlockControlTable | None, names: tuple[str, ...], check_ids: Sequence[str]
                   ) -> tuple[int, int]:
    """Control points that fix the datum: (plan, height) counts of the points measured in two images of the
    block or more, check points excluded (a full point counts in both)."""
    plan = height = 0
    if ctrl is not None:
        block = set(names) | {Path(n).stem for n in names}
        counts: dict[str, int] = {}
        for pid, im in zip(ctrl.meas_id, ctrl.meas_image, strict=True):
            if im in block:
                counts[pid] = counts.get(pid, 0) + 1
        for pid, kind in zip(ctrl.ids, ctrl.kind, strict=True):
            if counts.get(pid, 0) >= 2 and pid not in check_ids:
                plan += kind in ("full", "plan")
                height += kind in ("full", "height")
    return plan, height


def check_datum(has_poses: bool, ctrl: BlockControlTable | None, gnss: GnssObservations | None, gnss_text: str,
                names: tuple[str, ...], *, free_network: bool, check_ids: Sequence[str]) -> None:
    """Refuse a block whose datum nothing fixes, before any matching (the bundle's own rule: GNSS at >= 3 images,
    or >= 2 plan and >= 3 height control points, each measured in >= 2 images of the block).

    A free network takes the frame of the initial values; without poses that is the model frame of the
    first pair, which only control brings to the ground: when every control point is a check point (or
    none with a height is measured in two images), the check points and the control's CRS would be
    compared with, and written on, a frame they are not in (a datum from nothing): refused.

    Raises
    ------
    EstimationError
        "datum defect" or "datum from nothing", with the counts and what would fix it.
    """
    if free_network:
        if not has_poses and ctrl is not None and usable_control(ctrl, names, check_ids)[1] == 0:
            n_check = sum(1 for i in ctrl.ids if i in check_ids)
            raise EstimationError(
                f"datum from nothing: --free-network without poses works in the model frame of the first pair, and "
                f"no control point brings it to the ground ({len(ctrl.ids)} in the control file, {n_check} of them "
                f"check points, none else with a height measured in two images or more): the check points and the "
                f"control's CRS would be taken for a frame they are not in. Keep control points out of --check, or "
                f"give poses (--poses)")
        return
    if gnss is not None and len(gnss.images) >= 3:
        return
    plan, height = usable_control(ctrl, names, check_ids)
    if plan >= 2 and height >= 3:
        return
    g = gnss_text if gnss is None else f"GNSS at only {len(gnss.images)} images ({gnss_text})"
    c = ("no control (--control)" if ctrl is None else
         f"the control gives {plan} plan and {height} height points measured in two images or more (check points "
         "excluded)")
    raise EstimationError(f"datum defect: nothing fixes the position, rotation and scale of the block: {g}; {c}. "
                          "Give --gnss-sigma S with poses, control points (--control: >= 2 plan and >= 3 height "
                          "points), or --free-network (the frame of the initial poses)")
