"""Formulas of the image side: pure functions and immutable estimators on arrays (no files, rasters or printing).

Points and point tables, the camera (pixel <-> photo millimetres), rotations, least squares and robust
estimation, residual tables, CRS and geodesy (the one door to pyproj), analytic rectification, RPC and
sensor models, and the planar transforms (``transforms/``). See ``docs/architecture.md``.
"""
