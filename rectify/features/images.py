"""Matching two raster files: whole when small, coarse-to-fine by tiles when large."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rectify.errors import EstimationError
from rectify.features.match import MatcherConfig, MatchResult, ProgressFn, _match_whole
from rectify.features.tiled import _match_tiled
from rectify.raster import io as rio
from rectify.raster.distributed import Scheduler, resolve_scheduler

__all__ = ["match_images"]


def match_images(left_path: str | Path, right_path: str | Path, *, config: MatcherConfig | None = None,
                 progress: ProgressFn | None = None, scheduler: Scheduler | str | None = None,
                 workdir: str | Path | None = None) -> MatchResult:
    """Match two raster files (any format rasterio reads; any band count and dtype).

    Images whose sides are all <= ``config.tiled_above_px`` are read whole;
    larger ones are matched coarse-to-fine by tiles with bounded memory (see
    the module docstring for the bound).

    Parameters
    ----------
    left_path, right_path : path
    config : MatcherConfig, optional
    progress : callable(done, total), optional
    scheduler : Scheduler or str, optional
        Where the tiles of a large pair are searched (:func:`rectify.raster.distributed.resolve_scheduler`):
        ``threads`` (the default: one tile after the other in this process), ``processes[:N]`` (a
        local Dask cluster) or ``tcp://HOST:PORT`` (an existing one); default ``$RECTIFY_SCHEDULER``,
        else ``threads``. Every choice gives the same matches. Small pairs (matched whole) always
        run in this process.
    workdir : path, optional
        Folder for the Dask tasks' block files (default the system's temporary folder; on a
        cluster, a folder every worker can write and this process can read).

    Returns
    -------
    MatchResult

    Raises
    ------
    RasterIOError
        Unreadable file.
    EstimationError
        Blank images, or images that do not overlap.
    InvalidInputError
        A bad scheduler (or ``$RECTIFY_SCHEDULER``).
    SchedulerError
        The Dask cluster cannot be started or reached, or lost a task.
    """
    cfg = config or MatcherConfig()
    sched = resolve_scheduler(scheduler)  # a bad value fails before any work
    il = rio.raster_info(left_path)
    ir = rio.raster_info(right_path)
    big = max(il.width, il.height, ir.width, ir.height) > cfg.tiled_above_px
    if big:  # a blank raster fails in a second, before the coarse pass reads it whole
        for path, info, side in ((left_path, il, "left"), (right_path, ir, "right")):
            if max(info.width, info.height) > cfg.tiled_above_px:
                _refuse_blank(path, side)
    if not big:
        L, lv = rio.read_window(left_path, 0, 0, il.width, il.height)
        R, rv = rio.read_window(right_path, 0, 0, ir.width, ir.height)
        return _match_whole(L, lv, R, rv, cfg, progress, (str(left_path), str(right_path)))
    return _match_tiled(left_path, right_path, il, ir, cfg, progress, scheduler=sched, workdir=workdir)


#: side of the nearest-neighbour overview read to refuse a blank large raster before matching
BLANK_CHECK_PX = 512


def _refuse_blank(path: str | Path, side: str) -> None:
    """Raise :class:`EstimationError` when a bounded overview of ``path`` holds one value (or no valid pixel).

    The overview is a nearest-neighbour decimation to at most :data:`BLANK_CHECK_PX` px (GDAL reads
    only the sampled rows), so a blank 400-megapixel raster is refused in about a second instead of
    after the area-averaged coarse pass has streamed every pixel.
    """
    data, valid, _ = rio.read_overview(path, BLANK_CHECK_PX)
    v = data[valid] if valid is not None and valid.shape == data.shape[:2] else data.reshape(-1, data.shape[-1])
    if v.size == 0:
        raise EstimationError(f"the {side} image {str(path)!r} has no valid pixel (all nodata or masked)")
    lo, hi = float(np.min(v)), float(np.max(v))
    if lo == hi:
        raise EstimationError(f"the {side} image {str(path)!r} is blank: every pixel of a {data.shape[1]} x "
                              f"{data.shape[0]} overview is {lo:g}; nothing to match")
