"""``stereo resect``: space resection of one photo from ground control."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from stereo.actions.common import PathArg
from stereo.actions.workspace import PairWorkspace
from stereo.formats.orientation import exterior_dict
from stereo.pair.resection import ExteriorOrientation
from stereo.pair.resection import resect as resect_points
from stereo.report.pair import write_resect_report


@dataclass(frozen=True)
class ResectOptions:
    """Options of ``stereo resect``.

    Attributes
    ----------
    initial : str
        Direct solution for the initial values (:data:`stereo.pair.resection.INITIAL_METHODS`).
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
        The GCP file has no z column; an output exists; and as :func:`stereo.pair.resection.resect`.
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
