"""``stereo block --observations`` on a 140-image block built on a curved Earth (issue 25's "Must show").

The block (tests/support/block_curved.py): 10 strips x 14 images, about 25 x 29 km, 25 km east of
the central meridian of UTM 33N, ground points on the ellipsoid plus terrain, images projected
through the true geocentric geometry, 0.5 px, GNSS 5 cm, INS 0.005 deg in the navigation frame,
28 control and 24 check points. It is adjusted from its observations CSV alone (no images).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.geometry.geodesy import geodetic_from_map
from stereo.cli.main import cli
from stereo.formats.observations import read_observations
from tests.support.block_curved import CRS, CurvedBlock, make_curved_block, write_curved_block


@pytest.fixture(scope="module")
def curved(tmp_path_factory) -> tuple[CurvedBlock, dict[str, Path]]:
    blk = make_curved_block(0)
    return blk, write_curved_block(tmp_path_factory.mktemp("curved") / "in", blk)


@pytest.fixture(scope="module")
def default_run(curved, tmp_path_factory) -> tuple[str, Path]:
    """The block adjusted from its observations CSV in the default frame: (console output, OUTDIR)."""
    blk, files = curved
    out = tmp_path_factory.mktemp("default") / "out"
    r = CliRunner().invoke(cli, _args(files, blk, out))
    assert r.exit_code == 0, r.output
    return r.output, out


def _args(files: dict[str, Path], blk: CurvedBlock, out: Path, *extra: str) -> list[str]:
    return ["block", "--observations", str(files["observations"]), "--camera", str(files["camera"]), "--poses",
            str(files["poses"]), "--control", str(files["control"]), "--check", ",".join(blk.check_ids), "-o",
            str(out), "--no-report", "--no-stac", *extra]


def _check_errors(blk: CurvedBlock, out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check-point errors (adjusted - true) and std from OUT/points.csv, with the true points (map)."""
    text = [ln for ln in (out / "points.csv").read_text().splitlines() if not ln.startswith("#")]
    rows = {r["id"]: r for r in csv.DictReader(text)}
    where = {p: k for k, p in enumerate(blk.point_ids)}
    truth = blk.points[[where[c] for c in blk.check_ids]]
    got = np.array([[float(rows[c][k]) for k in "xyz"] for c in blk.check_ids])
    std = np.array([[float(rows[c][f"std_{k}"]) for k in "xyz"] for c in blk.check_ids])
    return got - truth, std, truth


def test_the_block_has_the_issue_size(curved) -> None:
    blk, _ = curved
    assert len(blk.images) >= 140
    assert (blk.extent_m >= 25_000).all()
    assert len(blk.control_ids) >= 25 and len(blk.check_ids) >= 20


def test_curved_block_from_its_observations_in_the_default_frame(curved, default_run) -> None:
    """Must show: check-point RMS(error / std) within 0.67-1.5 per axis, none beyond 4 std; plan within 1.5 std
    25 km from the central meridian (INS in the navigation frame, with the meridian convergence)."""
    blk, _ = curved
    output, out = default_run
    assert "adjustment frame: topocentric" in output
    assert "observations: " in output and "no matching" in output
    # the orientation records the frame it was adjusted in
    summ = json.loads((out / "orientation.json").read_text())["summary"]
    assert summ["adjustment_frame"].startswith("topocentric")
    err, std, _ = _check_errors(blk, out)
    ratio = np.sqrt(np.mean((err / std) ** 2, axis=0))
    assert ((ratio > 0.67) & (ratio < 1.5)).all(), ratio
    assert np.abs(err / std).max() < 4.0
    assert (ratio[:2] < 1.5).all()
    assert abs(err[:, 2].mean()) < 0.15  # no height bias: the frame is Cartesian and true to scale
    # the observations CSV the run wrote (with residuals, weights, flags) reads back as its input
    back = read_observations(out / "observations.csv", blk.images, {n: (10_000, 10_000) for n in blk.images})
    n_rows = len((out / "observations.csv").read_text().splitlines()) - 1
    assert back.n_rows == n_rows and back.tracks.n_obs + back.n_single == n_rows
    assert back.n_flagged == int(output.split("image residuals: RMS ")[1].split("(")[1].split(" flagged")[0])


def test_curved_block_in_the_map_frame_shows_the_predicted_error(curved, tmp_path) -> None:
    """``--frame map`` warns with the curvature figure and its heights carry the scale error of the projection
    that docs/curvature.md predicts for a GNSS-supported block: dz = (1 - k) (h_camera - h_point), k the UTM
    point scale (about 1.0 m here); tolerance 0.25 m on the mean over the check points (their std is ~0.2 m)."""
    blk, files = curved
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(files, blk, out, "--frame", "map"))
    assert r.exit_code == 0, r.output
    assert "warning: adjusting in the map CRS over" in r.output and "use --frame topocentric" in r.output
    err, std, truth = _check_errors(blk, out)
    llh = geodetic_from_map(truth, CRS)
    lam = np.radians(llh[:, 0] - 15.0)
    # UTM point scale factor (ellipsoidal series, enough to 1e-7 here)
    k = 0.9996 * (1 + (lam * np.cos(np.radians(llh[:, 1]))) ** 2 / 2)
    pred = (1 - k) * (blk.centres[:, 2].mean() - truth[:, 2])
    assert 0.8 < pred.mean() < 1.3
    assert abs(err[:, 2].mean() - pred.mean()) < 0.25
    assert np.sqrt(np.mean((err[:, 2] / std[:, 2]) ** 2)) > 3.0  # the map frame's heights fail their std
    assert np.sqrt(np.mean(((err[:, 2] - pred) / std[:, 2]) ** 2)) < 1.5  # ... and the prediction explains it


# --------------------------------------------------------------------------- bad input
def _rewrite(src: Path, dst: Path, edit) -> Path:
    lines = src.read_text().splitlines()
    dst.write_text("\n".join(edit(lines)) + "\n")
    return dst


def _fails(files: dict[str, Path], blk: CurvedBlock, tmp_path: Path, *extra: str, **replace: Path) -> str:
    f = {**files, **replace}
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, _args(f, blk, out, *extra))
    assert r.exit_code != 0
    assert "Traceback" not in r.output
    assert not out.exists()
    msg = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(msg) == 1, r.output
    return msg[0]


def test_unknown_image_is_refused(curved, tmp_path) -> None:
    blk, files = curved
    bad = _rewrite(files["observations"], tmp_path / "o.csv",
                   lambda ls: ls[:5] + [ls[5].replace(blk.images[blk.obs_image[4]], "nowhere.tif")] + ls[6:])
    m = _fails(files, blk, tmp_path, observations=bad)
    assert "'nowhere.tif' is not in the pose file" in m and "line 6" in m


def test_duplicate_rows_are_refused(curved, tmp_path) -> None:
    blk, files = curved
    bad = _rewrite(files["observations"], tmp_path / "o.csv", lambda ls: ls + [ls[3]])
    m = _fails(files, blk, tmp_path, observations=bad)
    assert "measured twice in image" in m and "lines 4 and " in m


def test_measurement_outside_the_image_is_refused(curved, tmp_path) -> None:
    blk, files = curved

    def edit(ls):
        f = ls[2].split(",")
        f[2] = "10012.5"
        return ls[:2] + [",".join(f)] + ls[3:]

    m = _fails(files, blk, tmp_path, observations=_rewrite(files["observations"], tmp_path / "o.csv", edit))
    assert "lies outside image" in m and "10000 x 10000" in m and "line 3" in m


def test_non_numeric_value_is_refused(curved, tmp_path) -> None:
    blk, files = curved

    def edit(ls):
        f = ls[7].split(",")
        f[3] = "12.5x"
        return ls[:7] + [",".join(f)] + ls[8:]

    m = _fails(files, blk, tmp_path, observations=_rewrite(files["observations"], tmp_path / "o.csv", edit))
    assert "line 8" in m and "row" in m


def test_check_point_measured_nowhere_is_refused(curved, tmp_path) -> None:
    blk, files = curved
    gone = blk.check_ids[0]
    bad = _rewrite(files["observations"], tmp_path / "o.csv",
                   lambda ls: [ln for ln in ls if f",{gone}," not in ln])
    m = _fails(files, blk, tmp_path, observations=bad)
    assert gone in m and "fewer than two images" in m


def test_frame_that_conflicts_with_the_crs_is_refused(curved, tmp_path) -> None:
    blk, files = curved
    poses = _rewrite(files["poses"], tmp_path / "p.csv", lambda ls: [ln for ln in ls if not ln.startswith("# crs")])
    ctrl = _rewrite(files["control"], tmp_path / "c.csv", lambda ls: [ln for ln in ls if not ln.startswith("# crs")])
    m = _fails(files, blk, tmp_path, "--frame", "topocentric", poses=poses, control=ctrl)
    assert "--frame topocentric needs a CRS" in m


def test_images_and_observations_together_are_refused(curved, tmp_path) -> None:
    blk, files = curved
    img = tmp_path / blk.images[0]
    img.write_bytes(b"x")
    r = CliRunner().invoke(cli, [*_args(files, blk, tmp_path / "out")[:1], str(img),
                                 *_args(files, blk, tmp_path / "out")[1:]])
    assert r.exit_code != 0 and "give either IMAGES or --observations" in r.output
    assert not (tmp_path / "out").exists()


def test_points_seen_once_are_dropped_and_counted(curved, tmp_path) -> None:
    blk, files = curved
    obs = _rewrite(files["observations"], tmp_path / "o.csv",
                   lambda ls: ls + [f"{blk.images[0]},lonely,100.0,200.0,0.5"])
    t = read_observations(obs, blk.images, {n: (10_000, 10_000) for n in blk.images})
    assert t.n_single == 1 and "lonely" not in t.tracks.point_ids
    assert "1 rows of points seen in one image only dropped" in t.summary_line()
    assert math.isclose(float(t.tracks.obs_sigma_px[0]), 0.5)


def test_unknown_check_point_is_refused(curved, tmp_path) -> None:
    """Every id of the CSV that the control file does not name is a tie point; a check id must be a control id."""
    blk, files = curved
    args = _args(files, blk, tmp_path / "out")
    args[args.index("--check") + 1] = "chk00,nowhere"
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0 and "nowhere" in r.output and "Traceback" not in r.output
    assert len([ln for ln in r.output.splitlines() if ln.strip()]) == 1
    assert not (tmp_path / "out").exists()


def test_rerun_from_the_written_observations_with_measured_control(curved, default_run, tmp_path) -> None:
    """An earlier run's observations.csv is an input; the control file's own measurements replace the CSV's."""
    blk, files = curved
    first = default_run[1]
    rows = [ln.split(",") for ln in (first / "observations.csv").read_text().splitlines()[1:]]
    meas = [f"{r[1]},{r[0]},{r[2]},{r[3]},,,,,," for r in rows if r[1] in ("gcp00", "gcp01")]
    ctrl = tmp_path / "control.csv"
    ctrl.write_text(files["control"].read_text() + "\n".join(meas) + "\n")
    second = tmp_path / "second"
    r = CliRunner().invoke(cli, _args({**files, "observations": first / "observations.csv", "control": ctrl}, blk,
                                      second))
    assert r.exit_code == 0, r.output
    assert f"{len(meas)} measurements of 2 control point(s) taken from the control file instead" in r.output
    assert "rows flagged by the earlier run kept" in r.output
    e1, _, _ = _check_errors(blk, first)
    e2, _, _ = _check_errors(blk, second)
    assert np.abs(e1 - e2).max() < 0.01


def test_topocentric_and_geocentric_frames_give_the_same_block(tmp_path) -> None:
    """Both frames are Cartesian and true to scale: without INS observations (whose sigmas are per angle of
    the frame) the two adjustments are one problem in rotated axes; their map results agree to 1 mm."""
    blk = make_curved_block(3, strips=3, images_per_strip=5, n_grid=30, n_control=8, n_check=4)
    files = write_curved_block(tmp_path / "in", blk, ins_sigma_deg=None)
    out = {}
    for fr in ("topocentric", "geocentric"):
        out[fr] = tmp_path / fr
        r = CliRunner().invoke(cli, [*_args(files, blk, out[fr]), "--frame", fr, "--robust", "none",
                                     "--no-variance-components"])
        assert r.exit_code == 0, r.output
        assert f"adjustment frame: {fr}" in r.output
    e_t, s_t, _ = _check_errors(blk, out["topocentric"])
    e_g, s_g, _ = _check_errors(blk, out["geocentric"])
    assert np.abs(e_t - e_g).max() < 1e-3
    assert np.abs(s_t - s_g).max() < 1e-3
    assert np.abs(e_t).max() < 1.0  # a sane adjustment, not two equal failures
