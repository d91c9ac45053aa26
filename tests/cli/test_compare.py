"""``rectify compare`` and the study library (rectify.actions.compare) on tiny sizes."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.errors import InvalidInputError
from rectify.geometry.transforms.study import StudyConfig, run_study

ARGS = ["--configs", "30", "--trials", "8", "--speed-points", "2000", "--seed", "3"]


def test_compare_cli_writes_study(tmp_path):
    out = tmp_path / "study"
    r = CliRunner().invoke(cli, ["compare", "--out", str(out), *ARGS])
    assert r.exit_code == 0, r.output
    assert (out / "study.md").is_file() and (out / "study.json").is_file()
    for part in ("agreement", "noise", "propagation", "conditioning", "speed"):
        assert (out / f"fig_{part}.png").stat().st_size > 1000
    md = (out / "study.md").read_text()
    for head in ("## 1. Agreement", "## 2. Accuracy under noise", "## 3. First-order", "## 4. Conditioning",
                 "## 5. Speed"):
        assert head in md
    d = json.loads((out / "study.json").read_text())
    assert d["agreement"]["n_configs"] == 30
    assert d["agreement"]["max_rel"] < 1e-8  # the two methods agree on exact data
    assert d["agreement"]["printed_median_rel"] > 1e-2  # eq. (2) as printed does not
    assert "agreement: 30 configurations" in r.output and "ratio" in r.output
    r2 = CliRunner().invoke(cli, ["compare", "--out", str(out), *ARGS])
    assert r2.exit_code == 1 and "exists" in r2.output


def test_study_results_are_consistent():
    res = run_study(StudyConfig(n_configs=20, n_trials=40, n_speed_points=1000, speed_repeats=1,
                                noise_px=(0.5,), seed=5))
    assert len(res.noise) == 2 and len(res.propagation) == 6
    for row in res.noise:
        # the cotangent method and the 4-point homography are the same map
        assert row["rmse_cotangent"] == pytest.approx(row["rmse_homography4"], rel=1e-6)
        assert row["max_diff_cot_h4"] < 1e-6
        # least squares on more points is better than 4 points
        assert row["rmse_homography_lsq"] < row["rmse_cotangent"]
    for row in res.propagation:
        assert 0.6 < row["ratio"] < 1.6  # first-order prediction matches the Monte Carlo
    gains = [r["gain_cotangent"] for r in res.conditioning if "error" not in r]
    assert gains == sorted(gains)  # noise gain grows as the configuration degenerates
    sp = res.speed  # throughput ratio cotangent / homography from the two measured rates (timing: loose range)
    assert sp["ratio"] == pytest.approx(sp["cotangent_pts_per_s"] / sp["homography_pts_per_s"], rel=1e-9)
    for m in ("cotangent", "homography"):
        assert sp[f"{m}_pts_per_s"] == pytest.approx(1000 / sp[f"{m}_s"], rel=1e-9), sp
    assert 1e-3 < sp["ratio"] < 1e3, sp


def test_study_config_validation():
    with pytest.raises(InvalidInputError, match="n_trials"):
        StudyConfig(n_trials=0)
    with pytest.raises(InvalidInputError, match="n_lsq"):
        StudyConfig(n_lsq=7)
    with pytest.raises(InvalidInputError, match="noise_px"):
        StudyConfig(noise_px=(-1.0,))
    with pytest.raises(InvalidInputError, match="StudyConfig"):
        run_study({"n_trials": 3})  # type: ignore[arg-type]


def test_comparison_summary_for_demo():
    from rectify.geometry.transforms.study import comparison_summary

    d = comparison_summary(n_configs=10, n_trials=5, n_speed_points=1000)
    assert d["agreement_max_rel"] < 1e-8 and d["printed_eq2_median_rel"] > 1e-2
    assert d["rmse_1px_resurs_f_cotangent"] == pytest.approx(d["rmse_1px_resurs_f_homography4"], rel=1e-6)
    assert {"rmse_1px_aerial_homography_lsq", "propagation_ratio_min", "speed_ratio"} <= set(d)


def test_summary_lines_are_labelled_with_units():
    from rectify.actions.demo import _compare_lines
    from rectify.geometry.transforms.study import comparison_summary, summary_lines

    d = comparison_summary(n_configs=10, n_trials=5, n_speed_points=1000)
    lines = summary_lines(d)
    assert lines[0].startswith("cotangent vs homography on exact data: max difference ")
    assert lines[0].endswith("of the image size (10 configurations)")
    cams = [s for s in lines if s.startswith("check-point RMSE at 1 px noise, ")]
    assert len(cams) == 2 and any("Resurs-F: cotangent " in s for s in cams)
    assert all(" px, homography (4 pts) " in s and " px, homography LSQ (all pts) " in s for s in cams)
    assert lines[-1] == f"throughput cotangent/homography: {d['speed_ratio']:.2f}"
    assert not any("{" in s for s in lines)
    # partial / empty summaries give fewer lines, never an error
    assert summary_lines({"speed_ratio": 0.8}) == ["throughput cotangent/homography: 0.80"]
    assert summary_lines({}) == [] and _compare_lines(None) == ()
    assert _compare_lines(d) == tuple(lines)
