"""``rectify mosaic``: one GeoTIFF/COG from several orthophotos (nearest-nadir seams, feathering).

The file step of :func:`rectify.raster.mosaic.mosaic`: the orthophotos are the job's inputs, the
output is written atomically with the workspace's overwrite policy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.raster.mosaic import MosaicOptions, MosaicResult
from rectify.raster.mosaic import mosaic as mosaic_orthos

__all__ = ["MosaicOptions", "MosaicRunOptions", "MosaicRun", "mosaic"]


@dataclass(frozen=True)
class MosaicRunOptions:
    """Options of :func:`mosaic`: the output pixel size (default: the finest input's) and the engine's
    options (feathering, tiles, threads, compression, COG, scheduler)."""

    resolution: float | None = None
    engine: MosaicOptions = field(default_factory=MosaicOptions)


@dataclass(frozen=True)
class MosaicRun:
    """Result of :func:`mosaic`: what the mosaic engine wrote."""

    result: MosaicResult

    def summary_lines(self) -> list[str]:
        """The output grid, CRS, inputs and time, then each input's share of the mosaic."""
        return self.result.summary_lines()


def mosaic(ws: Workspace, orthos: Sequence[str | Path], dst: str | Path,
           options: MosaicRunOptions = MosaicRunOptions(), progress: Progress = None) -> MosaicRun:
    """Mosaic the orthophotos ``orthos`` (one CRS, one band count and type) into the GeoTIFF ``dst``.

    Raises
    ------
    InvalidInputError, CRSError
        As :func:`rectify.raster.mosaic.mosaic`.
    """
    ws.add_inputs(*orthos)
    res = mosaic_orthos(list(orthos), dst, resolution=options.resolution, options=options.engine,
                        overwrite=ws.overwrite, progress=progress)
    return MosaicRun(res)
