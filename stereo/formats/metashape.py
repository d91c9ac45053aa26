"""Agisoft Metashape's XML exports as block inputs: poses of the aligned images and markers as control.

The reader is :func:`rectify.formats.metashape.read_metashape_chunk` (cameras, exterior orientations
and markers, with the conventions converted once there: calibration, pose frames, georeferencing and
the 0.5 px of marker measurements); :func:`read_metashape` returns it as a :class:`MetashapeDocument`,
which adds the block's types: :attr:`MetashapeDocument.poses` (:class:`stereo.block.types.Pose`) and
:meth:`MetashapeDocument.control_table` (markers with reference coordinates are ``full`` control,
the others ``tie`` points).
"""

from __future__ import annotations

import numpy as np

from rectify.formats.common import StrPath
from rectify.formats.metashape import MetashapeChunk, detect_metashape, read_metashape_chunk
from stereo.block.types import Pose
from stereo.formats.block import BlockControlTable

__all__ = ["MetashapeDocument", "read_metashape", "detect_metashape"]


class MetashapeDocument(MetashapeChunk):
    """One chunk of a Metashape XML export (:class:`rectify.formats.metashape.MetashapeChunk`) with block poses
    and control."""

    @property
    def poses(self) -> tuple[Pose, ...]:
        """The aligned images (camera ``label`` as image name, sensor id as camera id), in :attr:`crs`."""
        return tuple(Pose(n, s, p, R) for n, s, p, R in zip(self.images, self.image_sensor, self.positions,
                                                            self.rotations, strict=True))

    def control_table(self) -> BlockControlTable:
        """The markers as block control: ``full`` with reference coordinates, ``tie`` without."""
        kind = tuple("full" if np.isfinite(r).all() else "tie" for r in self.marker_xyz)
        return BlockControlTable(self.marker_ids, self.marker_xyz.copy(), kind,
                                 np.full((len(self.marker_ids), 3), np.nan), self.meas_id, self.meas_image,
                                 self.meas_pixel.copy(), self.crs)


def read_metashape(path: StrPath, *, crs: str | None = None, chunk: int = 0) -> MetashapeDocument:
    """Read a Metashape cameras or markers XML (:func:`rectify.formats.metashape.read_metashape_chunk`).

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        As :func:`rectify.formats.metashape.read_metashape_chunk`.
    """
    c = read_metashape_chunk(path, crs=crs, chunk=chunk)
    return MetashapeDocument(**{f: getattr(c, f) for f in c.__dataclass_fields__})
