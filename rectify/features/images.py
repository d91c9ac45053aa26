"""Matching two raster files: whole when small, coarse-to-fine by tiles when large."""

from __future__ import annotations

from pathlib import Path

from .. import io as rio
from .match import MatcherConfig, MatchResult, ProgressFn, _match_whole
from .tiled import _match_tiled

__all__ = ["match_images"]


def match_images(left_path: str | Path, right_path: str | Path, *, config: MatcherConfig | None = None,
                 progress: ProgressFn | None = None) -> MatchResult:
    """Match two raster files (any format rasterio reads; any band count and dtype).

    Images whose sides are all <= ``config.tiled_above_px`` are read whole;
    larger ones are matched coarse-to-fine by tiles with bounded memory (see
    the module docstring for the bound).

    Parameters
    ----------
    left_path, right_path : path
    config : MatcherConfig, optional
    progress : callable(done, total), optional

    Returns
    -------
    MatchResult

    Raises
    ------
    RasterIOError
        Unreadable file.
    EstimationError
        Blank images, or images that do not overlap.
    """
    cfg = config or MatcherConfig()
    il = rio.raster_info(left_path)
    ir = rio.raster_info(right_path)
    big = max(il.width, il.height, ir.width, ir.height) > cfg.tiled_above_px
    if not big:
        L, lv = rio.read_window(left_path, 0, 0, il.width, il.height)
        R, rv = rio.read_window(right_path, 0, 0, ir.width, ir.height)
        return _match_whole(L, lv, R, rv, cfg, progress, (str(left_path), str(right_path)))
    return _match_tiled(left_path, right_path, il, ir, cfg, progress)
