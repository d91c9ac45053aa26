"""Analytical rectification of tilted aerial and space images.

Subpackages and modules
-----------------------
errors      one exception tree, reused by :mod:`stereo`
points      validation of point arrays at the public boundary
camera      interior orientation; pixel <-> photo millimetres
rotation    angle systems <-> rotation matrices
residuals   residual tables shared by every estimator and report
formats     every image-side file: GCP/matches/control CSV, camera, transform and report JSON
workspace   the files of one job (planned outputs checked at once, atomic all-or-nothing writes)
actions     one function per step (match, fit, warp, compare, demo), used by the commands
fileutil    atomic output files
"""

#: the project version (the only place it is written; pyproject.toml reads it from here)
__version__ = "0.2.0.dev0"
