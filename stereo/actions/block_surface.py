"""``stereo block ... --surface``: ``stereo surface`` on the block's output folder, planned before the block runs.

:func:`plan_block_surface` checks, before any matching, that the block can feed a surface (a metric
method, the images in one folder) and whether the block's check points can check the DSM (a CSV control
file with ``id,x,y,z``; other control formats leave a note); :func:`run_block_surface` runs
:func:`stereo.actions.surface.run_surface` into ``OUTDIR/surface`` after the block.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from rectify.errors import InvalidInputError
from stereo.actions.surface import SurfaceOptions, SurfaceResult, run_surface
from stereo.actions.surface_outputs import CLOUD_FORMATS, cloud_output, read_check_points

__all__ = ["CLOUD_FORMATS", "SURFACE_FOLDER", "BlockSurfacePlan", "plan_block_surface", "refuse_zoom_settings",
           "run_block_surface"]

#: where ``stereo block --surface`` writes the surface, inside the block's output folder
SURFACE_FOLDER = "surface"


@dataclass(frozen=True)
class BlockSurfacePlan:
    """What ``--surface`` will run: the images' folder, the check-point file and ids (None, () when the
    block's check points cannot check the DSM), a note saying why not, and the point cloud's format
    (``laz``, ``las``, ``copc``: :attr:`stereo.actions.surface.SurfaceOptions.cloud_format`) and colours."""

    images_dir: str
    check: str | None = None
    check_ids: tuple[str, ...] = ()
    note: str = ""
    cloud_format: str = "laz"
    cloud_colors: bool = True


def refuse_zoom_settings(method: str, focal_settings: str | None) -> None:
    """``--focal-settings`` evaluates a zoom camera per image: refused with a method for images without a camera."""
    if focal_settings is not None:
        raise InvalidInputError(f"--focal-settings goes with a zoom camera; --method {method} is for images "
                                "without a known camera")


def plan_block_surface(images: Sequence[str | Path], *, projective: bool, method: str, control: str | None,
                       check_ids: Sequence[str], cloud_format: str = "laz", cloud_colors: bool = True
                       ) -> BlockSurfacePlan:
    """Check that a block can feed ``stereo surface`` (before any work); raises :class:`InvalidInputError`
    (a COPC ``cloud_format`` without ``copclib`` included)."""
    cloud_output(cloud_format)
    if projective:
        raise InvalidInputError(f"--surface needs a metric block (a camera); --method {method} has none")
    folders = {str(Path(p).resolve().parent) for p in images}
    if len(folders) != 1:
        raise InvalidInputError(f"--surface needs the images in one folder; they are in {len(folders)}: "
                                f"{sorted(folders)[:2]}")
    if check_ids and control is not None:  # the block's check points check the DSM too
        try:
            read_check_points(control, tuple(check_ids))
        except InvalidInputError as err:   # another control format (ODM, Metashape): the block still uses it
            return BlockSurfacePlan(folders.pop(), note=f"no DSM check at the check points: {err}",
                                    cloud_format=cloud_format, cloud_colors=cloud_colors)
        return BlockSurfacePlan(folders.pop(), control, tuple(check_ids), cloud_format=cloud_format,
                                cloud_colors=cloud_colors)
    return BlockSurfacePlan(folders.pop(), cloud_format=cloud_format, cloud_colors=cloud_colors)


def run_block_surface(out_dir: str | Path, plan: BlockSurfacePlan, *, overwrite: bool = False,
                      progress: Callable[[int, int], None] | None = None) -> SurfaceResult:
    """``stereo surface OUT_DIR -o OUT_DIR/surface`` with the plan's images, check points and cloud format."""
    opts = SurfaceOptions(images=plan.images_dir, check=plan.check, check_ids=plan.check_ids,
                          cloud_format=plan.cloud_format, cloud_colors=plan.cloud_colors)
    cb = None if progress is None else (lambda _stage, done, total: progress(done, total))
    return run_surface(out_dir, Path(out_dir) / SURFACE_FOLDER, options=opts, overwrite=overwrite, progress=cb)
