"""``rectify mosaic``: one GeoTIFF/COG from several orthophotos (nearest-nadir or least-transformed seams,
averaging, radiometric balancing, feathering, a provenance raster).

The file step of :func:`rectify.raster.mosaic.mosaic`: the orthophotos are the job's inputs, the
output is written through the workspace (checked against every input before any work, renamed into place
at the end, nothing left on an error or SIGTERM), with its overwrite policy.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rectify.actions.common import Progress
from rectify.actions.products import options_of, raster_grid, raster_roles, stac_path, write_stac
from rectify.actions.workspace import Workspace
from rectify.errors import InvalidInputError
from rectify.formats.stac import StacAsset
from rectify.raster.engine import COMPRESSIONS, JPEG_QUALITY
from rectify.raster.mosaic import MAX_PIXELS, MosaicOptions, MosaicResult
from rectify.raster.mosaic import mosaic as mosaic_orthos

__all__ = ["COMPRESSIONS", "JPEG_QUALITY", "MosaicOptions", "MosaicRunOptions", "MosaicRun", "mosaic"]


@dataclass(frozen=True)
class MosaicRunOptions:
    """Options of :func:`mosaic`: the output pixel size (default: the finest input's), the engine's
    options (feathering, tiles, threads, compression, COG, scheduler) and the largest output grid
    (pixels; orthophotos far apart would otherwise make a grid of mostly nothing)."""

    resolution: float | None = None
    engine: MosaicOptions = field(default_factory=MosaicOptions)
    max_pixels: float = MAX_PIXELS
    stac: bool = True  # write the STAC Item <output stem>.stac.json beside the mosaic, in the same transaction
    provenance: bool = False  # write <output stem>.source.tif: the 1-based input number per pixel

    def __post_init__(self) -> None:
        v = self.max_pixels
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 1):
            raise InvalidInputError(f"max_pixels must be a number >= 1; got {v!r}")


@dataclass(frozen=True)
class MosaicRun:
    """Result of :func:`mosaic`: what the mosaic engine wrote."""

    result: MosaicResult
    stac: Path | None = None

    def summary_lines(self) -> list[str]:
        """The output grid, CRS, inputs and time, then each input's share of the mosaic; the STAC Item."""
        return self.result.summary_lines() + ([f"wrote {self.stac} (STAC Item)"] if self.stac is not None else [])


def mosaic(ws: Workspace, orthos: Sequence[str | Path], dst: str | Path,
           options: MosaicRunOptions = MosaicRunOptions(), progress: Progress = None) -> MosaicRun:
    """Mosaic the orthophotos ``orthos`` (one CRS, one band count and type) into the GeoTIFF ``dst``.

    Raises
    ------
    InvalidInputError, CRSError
        As :func:`rectify.raster.mosaic.mosaic`.
    """
    dsm = options.engine.dsm
    ws.add_inputs(*orthos, *([dsm] if dsm is not None else []))
    item = stac_path(dst) if options.stac else None
    src = provenance_path(dst) if options.provenance else None
    ws.plan(dst, item, src)  # the outputs against every input (resolved, hard links and symlinks), before any work
    # the grid is checked (size, inputs far apart) before any tile; the mosaic is renamed into place at the end
    with ws.transaction(), ws.output(dst, suffix=Path(dst).suffix or ".tif") as tmp, \
            contextlib.ExitStack() as stack:
        tmp_src = stack.enter_context(ws.output(src, suffix=".tif")) if src is not None else None
        res = mosaic_orthos(list(orthos), tmp, resolution=options.resolution, options=options.engine,
                            overwrite=True, progress=progress, max_pixels=options.max_pixels, provenance=tmp_src)
        if item is not None:
            assets = {"mosaic": StacAsset(dst, raster_roles(tmp), "orthophoto mosaic", source=tmp)}
            if src is not None and tmp_src is not None:
                assets["provenance"] = StacAsset(src, ("metadata",), "source orthophoto per pixel (1-based, 0 none)",
                                                 source=tmp_src)
            write_stac(ws, item, item_id=Path(dst).stem, grid=raster_grid(tmp), command="rectify mosaic",
                       assets=assets, options=options_of(options, orthos=[str(p) for p in orthos]),
                       inputs=list(orthos))
    return MosaicRun(dataclasses.replace(res, path=Path(dst), provenance=src), item)


def provenance_path(dst: str | Path) -> Path:
    """The provenance raster beside the mosaic ``dst``: ``<stem>.source.tif``."""
    p = Path(dst)
    return p.with_name(p.stem + ".source.tif")
