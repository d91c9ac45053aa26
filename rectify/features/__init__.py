"""Tie points: detection, matching, geometric verification, large images.

Pipeline (:func:`match_images`)::

    read (windows) -> grey uint8 (percentile stretch, detection only; nodata masked)
      -> detect (SIFT | ORB | AKAZE), bias-free subpixel positions, even spread (cap per grid cell)
      -> match (ratio test + mutual check; FLANN for float, Hamming brute force for binary)
      -> verify (OpenCV USAC MAGSAC++: homography | fundamental | none)
      -> refine (least-squares matching, :mod:`rectify.features.lsm`, started by :mod:`rectify.features.shape`)
      -> re-verify, screen the refined matches (:mod:`rectify.features.verify`) -> even selection

Small images (both sides <= ``MatcherConfig.tiled_above_px``) are matched whole.
Larger ones go coarse-to-fine: both images are read as area-averaged overviews
(streamed by strips), matched and verified with a homography; then the left
image is processed tile by tile (``tile_px`` plus ``overlap_px``), and for each
tile only the right window where the coarse homography predicts the partner
(plus ``search_margin_px``) is read and searched. Candidates are thinned by a
global grid cap, so the memory held does not grow with the image size.

Memory bound (defaults, any image size): one left tile (1120 x 1120 px) and
one right tile or window being detected, with their SIFT scale spaces (about
0.35 GB each), the right-tile feature cache (at most 256 MB of descriptors),
two overviews of at most 2048 px per side (float32, 16 MB per band), overview
strips of at most 16 Mpx of source, the right pixels under one tile's matches
for refinement, and at most ``max_candidates`` candidate matches (about 60
bytes each): about 1.3 GB. Measured peak RSS: 1.10 GB on an 8000^2 pair and
1.28 GB on a 33 000^2 pair (``scripts/bench_match.py``).

Modules
-------
detect   keypoint detection with the detector bias removed, even spread (:func:`detect`, :func:`grid_select`)
match    descriptor matching, whole-image matching (:func:`match_arrays`; a right image turned by quarter
         turns is turned back), the options (:class:`MatcherConfig`) and results
verify   geometric verification (:func:`verify_matches`), the screening of refined matches, residual tables
shape    start shapes of the refinement (homography Jacobian, neighbours' affine, keypoints' similarity)
lsm      least-squares matching (:func:`rectify.features.lsm.refine_matches`)
tiled    coarse-to-fine matching of large rasters by tiles, bounded memory
images   :func:`match_images`: two raster files, whole or tiled

The report figures of a match are :func:`rectify.report.figures.match_figures`.
"""

from rectify.features.detect import DETECTORS, SIFT_OFFSET_PX, Detector, Features, akaze_available, detect, grid_select
from rectify.features.images import match_images
from rectify.features.match import (
    VERIFY_METHODS,
    MatcherConfig,
    MatchResult,
    ProgressFn,
    Verification,
    Verify,
    match_arrays,
    match_descriptors,
    verify_matches,
)

__all__ = [
    "DETECTORS",
    "SIFT_OFFSET_PX",
    "VERIFY_METHODS",
    "Detector",
    "Features",
    "MatchResult",
    "MatcherConfig",
    "ProgressFn",
    "Verification",
    "Verify",
    "akaze_available",
    "detect",
    "grid_select",
    "match_arrays",
    "match_descriptors",
    "match_images",
    "verify_matches",
]
