"""The files of a stereo job: :class:`PairWorkspace` adds the stereo artefacts to
:class:`rectify.actions.workspace.Workspace`.

``stereo run`` and ``stereo demo`` write a fixed layout into their output folder::

    OUTDIR/matches.csv          tie points (pixels)
    OUTDIR/relative.json        relative orientation
    OUTDIR/orientation.json     absolute orientation, frame, summary
    OUTDIR/points.ply           ground (or model) points
    OUTDIR/points.csv           id,x,y,z,residual_mm[,std_*]
    OUTDIR/model_points.ply     model frame points
    OUTDIR/report/              QA report (stereo.report.pair)

``stereo model`` writes ``<points>.ply`` with ``<points>.csv`` and ``<points>.orientation.json``
beside it (:func:`model_outputs`). The formats are in :mod:`stereo.formats.orientation` and
:mod:`stereo.formats.points`; every ``save_*`` method writes through
:meth:`~rectify.actions.workspace.Workspace.output`, so inside
:meth:`~rectify.actions.workspace.Workspace.transaction` the files of a job are written all or none.
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rectify.actions.workspace import StrPath, Workspace
from rectify.errors import CalibrationError, InvalidInputError
from rectify.geometry.camera import Camera
from rectify.raster.io import raster_info
from stereo.formats.orientation import dump_exterior, dump_orientation, dump_relative, orientation_dict, read_relative
from stereo.formats.points import dump_ply, dump_points_csv
from stereo.pair.resection import ExteriorOrientation
from stereo.relative import RelativeGeometry

if TYPE_CHECKING:  # type hints only (stereo.pair.model builds the model; this module stores it)
    from stereo.pair.model import StereoModel

__all__ = ["RUN_LAYOUT", "PairWorkspace", "model_outputs"]

#: the files of ``stereo run``'s output folder, by role
RUN_LAYOUT = {
    "matches": "matches.csv",
    "relative": "relative.json",
    "orientation": "orientation.json",
    "points": "points.ply",
    "points_csv": "points.csv",
    "model_points": "model_points.ply",
}
_REPORT = "report"


def model_outputs(points: StrPath) -> tuple[Path, Path, Path]:
    """``points.ply`` -> (``points.ply``, ``points.csv``, ``points.orientation.json``)."""
    p = Path(points)
    return p, p.with_suffix(".csv"), p.with_suffix(".orientation.json")


class PairWorkspace(Workspace):
    """The files of one stereo pair job (see the module docstring for the run layout).

    Parameters are those of :class:`rectify.actions.workspace.Workspace`. :meth:`for_run` makes the workspace
    of an output folder with the fixed layout and its ``report/`` folder.
    """

    @classmethod
    def for_run(cls, out_dir: StrPath, *, overwrite: bool = False, inputs: tuple[StrPath | None, ...] = (),
                report: bool = True) -> PairWorkspace:
        """Workspace of ``stereo run`` / ``stereo demo``: output folder ``out_dir``, report in ``out_dir/report``."""
        root = Path(out_dir)
        return cls(root, overwrite=overwrite, inputs=[p for p in inputs if p is not None],
                   report_dir=root / _REPORT if report else None)

    # ------------------------------------------------------------------ layout
    def layout_path(self, role: str) -> Path:
        """Path of a file of the run layout by role (``"matches"``, ``"relative"``, ... see :data:`RUN_LAYOUT`)."""
        return self.path(RUN_LAYOUT[role])

    def run_outputs(self) -> list[Path]:
        """Every file of the run layout (the report folder apart)."""
        return [self.path(n) for n in RUN_LAYOUT.values()]

    def plan_run(self) -> list[Path]:
        """Check the output folder, every output of the layout and the report folder before any work.

        Creates nothing. Raises when the folder is a file or its parent is missing, when an output
        exists without ``overwrite`` or equals an input, and when the report folder is not writable or
        already holds a report without ``overwrite``.
        """
        root = self.root
        if root is None:
            raise InvalidInputError("a pair run needs an output folder")
        if root.exists() and not root.is_dir():
            raise InvalidInputError(f"output {str(root)!r} exists and is not a folder")
        parent = next((p for p in root.parents if p.exists()), Path("."))
        if not root.exists() and not parent.is_dir():
            raise InvalidInputError(f"output folder {str(parent)!r} is a file")
        out = self.plan(*self.run_outputs())
        self.check_report_dir()
        if self.report_dir is not None and (self.report_dir / "report.html").exists() and not self.overwrite:
            raise InvalidInputError(f"report folder {str(self.report_dir)!r} already holds a report; pass --overwrite")
        return out

    def discard_root(self) -> None:
        """After a failure: remove the output folder if this workspace created it (with what was written in it)."""
        if self._created_root and self.root is not None:
            with contextlib.suppress(OSError):
                shutil.rmtree(self._created_top or self.root)

    # ------------------------------------------------------------------ consistency of the inputs
    def check_camera_image(self, camera: Camera, image: StrPath, which: str = "image") -> None:
        """Refuse a camera whose ``width`` x ``height`` differ from the size of ``image`` (read from its header).

        Raises
        ------
        CalibrationError
            Naming both sizes, the image and which photo it is (``"left"``, ``"right"``).
        """
        info = raster_info(str(image))
        if (info.width, info.height) != (camera.width, camera.height):
            raise CalibrationError(
                f"the camera is {camera.width} x {camera.height} px but the {which} image {str(image)!r} is "
                f"{info.width} x {info.height} px: wrong camera file for this photo (or a resized photo)")

    @staticmethod
    def check_points_in_frame(camera: Camera, pixel: Any, ids: Any, what: str, *, tolerance_px: float = 1.0) -> None:
        """Refuse measured pixels outside the camera's frame (by more than ``tolerance_px``).

        Raises
        ------
        InvalidInputError
            Naming the number of points outside, the first ids with their positions and the frame size.
        """
        px = np.asarray(pixel, dtype=np.float64).reshape(-1, 2)
        lo, t = -0.5 - tolerance_px, tolerance_px
        out = ((px[:, 0] < lo) | (px[:, 1] < lo) | (px[:, 0] > camera.width - 0.5 + t)
               | (px[:, 1] > camera.height - 0.5 + t)) & np.isfinite(px).all(axis=1)
        if out.any():
            idx = np.flatnonzero(out)
            names = [str(ids[i]) if ids is not None else f"#{i + 1}" for i in idx[:3]]
            where = ", ".join(f"{n} ({px[i, 0]:.1f}, {px[i, 1]:.1f})" for n, i in zip(names, idx[:3], strict=True))
            raise InvalidInputError(
                f"{len(idx)} {what} outside the camera's {camera.width} x {camera.height} px frame, e.g. {where}: "
                "wrong camera file, or points measured on another image size")

    # ------------------------------------------------------------------ stereo artefacts
    # (matches, control, camera and GCP files: the load_*/save_* methods of rectify.actions.workspace.Workspace)
    def save_relative(self, path: StrPath, ro: Any, *, extra: dict[str, Any] | None = None) -> Path:
        """Relative orientation JSON (``ro`` a :class:`~stereo.relative.RelativeOrientation` or its dict)."""
        with self.output(path) as tmp:
            dump_relative(tmp, ro, extra=extra)
        return Path(path)

    def load_relative(self, path: StrPath) -> RelativeGeometry:
        """Relative orientation JSON -> :class:`~stereo.relative.RelativeGeometry`."""
        return read_relative(path)

    def save_exterior(self, path: StrPath, eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None) -> Path:
        """Exterior orientation JSON, with the camera."""
        with self.output(path) as tmp:
            dump_exterior(tmp, eo, camera=camera)
        return Path(path)

    def save_model(self, model: StereoModel, *, points_path: StrPath, csv_path: StrPath | None = None,
                   orientation_path: StrPath | None = None, model_ply_path: StrPath | None = None,
                   extra: dict[str, Any] | None = None) -> None:
        """Points PLY (ground, or model frame without control), points CSV, orientation JSON, model-frame PLY."""
        res = np.sqrt(np.mean(model.intersection.residuals_mm ** 2, axis=1))
        with self.output(points_path) as tmp:
            dump_ply(tmp, model.points, comment="ground" if model.ground is not None else "model frame")
        if csv_path is not None:
            with self.output(csv_path) as tmp:
                dump_points_csv(tmp, model.ids, model.points, res, std=model.ground_std, crs=model.crs)
        if model_ply_path is not None:
            with self.output(model_ply_path) as tmp:
                dump_ply(tmp, model.intersection.points, comment="model frame")
        if orientation_path is not None:
            with self.output(orientation_path) as tmp:
                dump_orientation(tmp, orientation_dict(model, extra=extra))
