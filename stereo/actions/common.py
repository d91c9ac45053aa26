"""What the ``stereo`` pair actions share: the matcher presets, the printed sigma0, tie points of a pair.

Each command has one action module (``stereo/actions/<command>.py``, named as its ``stereo/cli`` module):
it takes the input paths and an options dataclass, checks every planned output before any work (a
:class:`~stereo.actions.workspace.PairWorkspace`), computes, writes its outputs in one transaction (all
or none), and returns a frozen result whose ``summary_lines()`` are exactly the lines the command prints.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.features import MatcherConfig, match_images
from rectify.geometry.camera import Camera
from rectify.geometry.points import ControlTable, Matches
from rectify.raster.io import ignore_not_georeferenced
from stereo.relative import RelativeOrientation

Progress = Callable[[int, int], None]
PathArg = str | Path


def given(*paths: PathArg | None) -> list[PathArg]:
    return [p for p in paths if p is not None]


#: The matcher of a stereo pair: fundamental-matrix verification (a homography drops most matches of a
#: pair with relief); the other options are :class:`rectify.features.MatcherConfig`'s defaults.
PAIR_MATCHER = MatcherConfig(verify="fundamental")
#: The matcher of ``stereo orient LEFT RIGHT``: a relative orientation needs no more than a few thousand
#: well-spread tie points (its precision saturates long before), so at most 12000 keypoints per image and
#: 4000 matches (issue 12: about a third of the time on a 2000 x 2000 pair; figures in docs/features.md).
#: ``stereo run`` keeps :data:`PAIR_MATCHER`: its matches are its model points.
ORIENT_MATCHER = replace(PAIR_MATCHER, max_keypoints=12000, max_matches=4000)


def matcher_config(*, detector: str | None = None, verify: str | None = None, refine: bool | None = None,
                   max_matches: int | None = None, max_keypoints: int | None = None,
                   base: MatcherConfig = PAIR_MATCHER) -> MatcherConfig:
    """``base`` (:data:`PAIR_MATCHER` or :data:`ORIENT_MATCHER`) with the commands' options (None: the base's)."""
    given: dict[str, Any] = {"detector": detector, "verify": verify, "refine": refine, "max_matches": max_matches,
                             "max_keypoints": max_keypoints}
    return replace(base, **{k: v for k, v in given.items() if v is not None})


def parallax_sigma0_mm(ro: RelativeOrientation) -> float | None:
    """The sigma0 of a relative orientation that the console and the report both print, mm.

    sigma0 = sqrt(sum w q^2 / (n_used - 5)) over the residual vertical parallaxes q of the points
    used (outliers excluded; w the final robust weights, 1 without a robust estimator): the sigma0
    of the report's residual table (:meth:`RelativeOrientation.residual_table`). ``None`` without
    redundancy (5 points). ``ro.sigma0_mm`` (one photo coordinate) is a different figure, kept in
    the JSON for the weighting of the model.
    """
    s = ro.residual_table(units="mm").sigma0
    return float(s) if s is not None and math.isfinite(s) else None


def sigma0_text(ro: RelativeOrientation, pixel_size_mm: float | None) -> str:
    """``"7.96 um = 0.055 px (parallax, 444 - 5 redundancy)"``, the one printed sigma0 (:func:`parallax_sigma0_mm`)."""
    s = parallax_sigma0_mm(ro)
    if s is None:
        return "n/a (no redundancy)"
    px = f" = {s / pixel_size_mm:.3f} px" if pixel_size_mm else ""
    return f"{s * 1000:.2f} um{px} (vertical parallax, {ro.n_used} - 5 redundancy, outliers excluded)"


def match_photos(left: PathArg, right: PathArg, progress: Progress | None = None,
               matcher: MatcherConfig | None = None) -> Any:
    """Tie points of a photo pair: :data:`PAIR_MATCHER` unless ``matcher`` is given."""
    with ignore_not_georeferenced():  # plain photos have no geotransform, as expected
        return match_images(left, right, config=matcher or PAIR_MATCHER, progress=progress)


def pair_tie_points(images: tuple[PathArg, PathArg] | None, matches: PathArg | None,
                    load: Callable[[PathArg], Matches], matcher: MatcherConfig | None = None
                    ) -> tuple[Matches, int | None, float | None]:
    """The tie points of a pair: matched from ``images`` (default :data:`ORIENT_MATCHER`) or read from the
    ``matches`` CSV by ``load``; with the count and verification RMSE of a matching (None for a CSV).
    Raises :class:`InvalidInputError` when there is none."""
    n_matched = rmse = None
    if images is not None:
        res = match_photos(images[0], images[1], matcher=matcher or ORIENT_MATCHER)
        m = res.matches
        n_matched, rmse = len(m), res.rmse_px
    else:
        if matches is None:
            raise InvalidInputError("give either a matches CSV or the two images LEFT RIGHT")
        m = load(matches)
    if len(m) == 0:
        raise InvalidInputError("no tie points")
    return m, n_matched, rmse


def control_mm(control: ControlTable | None, camera: Camera) -> tuple[NDArray, NDArray] | None:
    if control is None:
        return None
    return camera.photo_from_pixel(control.left), camera.photo_from_pixel(control.right)
