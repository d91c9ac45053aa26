"""Analytical rectification of tilted aerial and space images.

Subpackages and modules
-----------------------
errors      one exception tree, reused by :mod:`stereo`
points      validation of point arrays at the public boundary
camera      interior orientation; pixel <-> photo millimetres
rotation    angle systems <-> rotation matrices
residuals   residual tables shared by every estimator and report
tables      CSV/JSON contracts (GCPs, matches, control points)
fileutil    atomic output files
"""

#: the project version (the only place it is written; pyproject.toml reads it from here)
__version__ = "0.2.0.dev0"
