"""Dense stereo: normal-case (epipolar) resampling, dense matching, intersection, DSM and point cloud.

Modules
-------
epipolar     the rectifying rotations/homographies of a frame pair, streamed resampling, maps back
matching     semi-global matching (OpenCV StereoSGBM) with LR check, sub-pixel, speckle removal,
             confidence and an edge-aware fill; tiled for bounded memory
checks       its per-row tests after SGBM (collision test, border rule) and the strip layout
holes        its half-resolution hole pass (``MatchOptions.hole_p2``), on boxes around the large holes
refine       its post-processing: depth-edge classification, median, sub-pixel step, confidence
triangulate  disparity -> 3D by intersection through the original cameras (:mod:`stereo.pair.intersection`)
products     LAS/LAZ and PLY point clouds, DSM GeoTIFF, disparity and confidence rasters
report       pictures, coverage and the height-difference statistics against a reference DEM
pipeline     :func:`run_dense`: the whole chain behind ``stereo dense``
"""

from __future__ import annotations
