"""``stereo disparity``: the dense disparity of an already rectified pair (the dense chain's matcher).

The pair is in the normal case already (rows are epipolar lines: equal heights), e.g. the
``left_normal.tif``/``right_normal.tif`` of ``stereo dense`` or a stereo benchmark's pair. The
matcher is the dense chain's (:func:`stereo.dense.matching.match_rasters`: tiled SGBM with its
occlusion test, border rule, median and sub-pixel step), without hole filling: the output is
``col_left - col_right`` of every left pixel, float32, nodata -9999 where there is none, on the
left image's grid (and georeference, when it has one).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from rectify.actions.workspace import Workspace
from rectify.errors import InvalidInputError
from rectify.raster.io import bound_gdal_cache, gdal_cache_limit, ignore_not_georeferenced, raster_info
from stereo.actions.common import PathArg
from stereo.dense.matching import NODATA, MatchOptions, MatchStats, match_rasters

__all__ = ["DisparityOptions", "DisparityResult", "disparity"]

#: GDAL block cache while the pair is matched, MB
GDAL_CACHE_MB = 64


@dataclass(frozen=True)
class DisparityOptions:
    """Options of :func:`disparity`.

    Attributes
    ----------
    min_disparity : int or None
        Smallest disparity searched, px (``col_left - col_right``).
    num_disparities : int or None
        How many disparities are searched from ``min_disparity`` on: a positive multiple of 16
        (OpenCV's ``numDisparities``); the search covers ``min .. min + num - 1``, every tile the
        same range. Both None: each tile takes its range from a coarse pass of the pair (searching
        0 .. a third of the width), as in the dense chain. Give both or neither.
    matching : MatchOptions
        The matcher's options (default the dense chain's, without hole filling).
    """

    min_disparity: int | None = None
    num_disparities: int | None = None
    matching: MatchOptions = dataclasses.field(default_factory=MatchOptions)

    def __post_init__(self) -> None:
        if (self.min_disparity is None) != (self.num_disparities is None):
            raise InvalidInputError("--min-disparity and --num-disparities go together: give both (the search "
                                    "range min .. min + num - 1) or neither (a range per tile from a coarse pass)")
        for name in ("min_disparity", "num_disparities"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
                raise InvalidInputError(f"--{name.replace('_', '-')} must be an integer; got {v!r}")
        n = self.num_disparities
        if n is not None and (n <= 0 or n % 16):
            raise InvalidInputError(f"--num-disparities must be a positive multiple of 16 (as OpenCV's "
                                    f"numDisparities); got {n}")
        if not isinstance(self.matching, MatchOptions):
            raise InvalidInputError(f"`matching` must be a MatchOptions; got {type(self.matching).__name__}")

    @property
    def disparity_range(self) -> tuple[int, int] | None:
        """(lowest, highest) disparity searched, or None (per tile from the coarse pass)."""
        if self.min_disparity is None or self.num_disparities is None:
            return None
        return self.min_disparity, self.min_disparity + self.num_disparities - 1


@dataclass(frozen=True, eq=False)
class DisparityResult:
    """What :func:`disparity` wrote: the disparity GeoTIFF and the matcher's figures."""

    output: Path
    stats: MatchStats
    searched: tuple[int, int] | None
    seconds: float

    def summary_lines(self) -> list[str]:
        s = self.stats
        rng = ("per tile from a coarse pass" if self.searched is None
               else f"{self.searched[0]} .. {self.searched[1]} px")
        return [f"disparity: {100 * s.density:.1f}% of the left image's {s.width} x {s.height} px, range "
                f"{s.disparity_min:.2f} .. {s.disparity_max:.2f} px (searched: {rng}), {s.n_tiles} tiles",
                f"wrote {self.output} (float32 col_left - col_right, px; nodata {NODATA:g})",
                f"time {self.seconds:.1f} s"]


def disparity(left: PathArg, right: PathArg, output: PathArg, *, options: DisparityOptions | None = None,
              overwrite: bool = False) -> DisparityResult:
    """``stereo disparity``: the disparity of the left image of a rectified pair into ``output``.

    Raises
    ------
    InvalidInputError
        A missing photo, photos of different heights, a search range wider than the left image,
        bad options, an output that exists (without ``overwrite``) or is an input.
    RasterIOError
        An unreadable photo, or the output cannot be written.
    StereoError
        No disparity found anywhere.

    Nothing is left at ``output`` on an error.
    """
    t0 = time.perf_counter()
    opts = options or DisparityOptions()
    if not isinstance(opts, DisparityOptions):
        raise InvalidInputError(f"`options` must be a DisparityOptions; got {type(opts).__name__}")
    for name, p in (("left", left), ("right", right)):
        if not Path(p).is_file():
            raise InvalidInputError(f"{name} image not found: {str(p)!r}")
    with ignore_not_georeferenced():
        il, ir = raster_info(left), raster_info(right)
    if il.height != ir.height:
        raise InvalidInputError(f"the images are not a rectified pair: LEFT is {il.width} x {il.height} px, RIGHT "
                                f"{ir.width} x {ir.height} px (rows must be epipolar lines: equal heights)")
    rng = opts.disparity_range
    if rng is not None and opts.num_disparities is not None and opts.num_disparities >= il.width:
        raise InvalidInputError(f"--num-disparities {opts.num_disparities} is not below the left image's width "
                                f"{il.width} px")
    ws = Workspace(overwrite=overwrite, inputs=[left, right])
    (out,) = ws.plan(output)
    m = dataclasses.replace(opts.matching, fill_max_px=0)
    if rng is not None:  # the given range in every tile: no coarse pass, no margin
        m = dataclasses.replace(m, coarse_max_px=0, margin_px=0.0,
                                max_disparities=max(m.max_disparities, rng[1] - rng[0] + 1))
    bound_gdal_cache()
    with gdal_cache_limit(GDAL_CACHE_MB), ws.transaction(), ws.output(out) as tmp:
        stats = match_rasters(left, right, tmp, None, disparity_range=rng, options=m,
                              transform=il.transform if il.crs else None, crs=il.crs)
    return DisparityResult(out, stats, rng, time.perf_counter() - t0)
