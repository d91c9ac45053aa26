"""Reports of the stereo steps (pair, block, calibration, dense), built with :mod:`rectify.report.builder`.
"""
