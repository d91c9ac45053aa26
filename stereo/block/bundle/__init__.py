"""Bundle adjustment of a block of frame images.

Modules
-------
adjust
    :func:`adjust_bundle` and :class:`BundleOptions`: observation groups, robust weights,
    variance components, self-calibration, Levenberg-Marquardt iterations, redundancy numbers.
result
    :class:`BundleResult`: adjusted poses, points, cameras, precisions, residuals, datum statement.
model
    The collinearity model (as :func:`stereo.block.types.project_pixel`) and its analytic Jacobians.
solve
    Normal equations in Schur form: assembly, dense/sparse/banded solution of the reduced camera
    system, back-substitution, covariances.
datum
    The datum analysis: which observations fix the datum and how weak it is.
"""
