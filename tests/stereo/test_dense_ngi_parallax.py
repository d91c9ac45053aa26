"""Issue 14 must-show on the real NGI pair (shared data; skips without ../shared/data):
residual vertical parallax after normal-case resampling at most 0.1 px RMS on the tie points.

``stereo run --dense`` as a user runs it: the run's matches and relative orientation, then the
dense chain, which re-estimates the relative orientation (Tukey) from the LSM-refined matches,
rectifies with it and reports the parallax of the points it used (its outliers and the unrefined
matches left out and counted).
"""

from __future__ import annotations

import json

import numpy as np

from rectify.formats.tables import read_matches
from stereo.actions.dense import DenseOptions
from stereo.actions.run import run

CAMERA = {"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152}


def test_ngi_vertical_parallax_after_resampling(ngi_pair, tmp_path):
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(CAMERA))
    res = run(ngi_pair / "3324c_2015_1004_05_0182_RGB.tif", ngi_pair / "3324c_2015_1004_05_0184_RGB.tif",
              camera=cam, out_dir=tmp_path / "out", report=False, dense=DenseOptions(cloud_format="none"))
    assert res.dense is not None
    par = res.dense.parallax

    # the must-show: <= 0.1 px RMS, mapped through the rectification and re-measured in the resampled photos
    assert par.rms_geometric_px <= 0.1, par.summary_line()
    assert par.rms_measured_px <= 0.1, par.summary_line()

    # the points it is measured on: every refined match is either used or an outlier of the orientation
    m = read_matches(tmp_path / "out" / "matches.csv")
    assert m.score is not None
    refined = int(np.isfinite(m.score).sum())
    assert par.n_unrefined == len(m) - refined
    assert par.n + par.n_outliers == refined
    assert par.n >= 450  # 515 of 543 refined matches in the recorded run
    assert par.n_outliers <= 0.1 * refined
    assert par.n_measured >= 0.9 * par.n  # 497 re-measured in the recorded run

    # the orientation used is the one whose parallax is reported, and the maps are exact: the mapped
    # parallax of every point equals the orientation's own residual parallax (up to its sign convention)
    assert par.orientation_px is not None
    np.testing.assert_allclose(np.abs(par.geometric_px), np.abs(par.orientation_px), atol=0.005)

    summary = json.loads((tmp_path / "out" / "dense" / "dense.json").read_text())
    vp = summary["vertical_parallax_px"]
    assert vp["n"] == par.n and vp["n_outliers"] == par.n_outliers and vp["n_unrefined"] == par.n_unrefined
    assert vp["rms_mapped"] <= 0.1 and vp["rms_measured"] <= 0.1
    assert summary["orientation"]["robust"] == "tukey"
    assert summary["orientation"]["n_used"] == par.n
