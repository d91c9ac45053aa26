"""stereo.actions.workspace and stereo.actions.run.run: outputs checked before work, all-or-nothing writes."""

from __future__ import annotations

import json

import numpy as np
import pytest

import stereo.actions.run as actions
from rectify.errors import EstimationError, InvalidInputError
from stereo.actions.scene import make_scene, write_scene_inputs
from stereo.actions.workspace import RUN_LAYOUT, PairWorkspace, model_outputs
from stereo.formats.orientation import read_relative


def test_model_outputs():
    assert [p.name for p in model_outputs("a/pts.ply")] == ["pts.ply", "pts.csv", "pts.orientation.json"]


def test_plan_run_checks_everything_before_work(tmp_path):
    out = tmp_path / "out"
    ws = PairWorkspace.for_run(out)
    assert [p.name for p in ws.plan_run()] == list(RUN_LAYOUT.values())
    assert not out.exists()  # planning creates nothing
    out.mkdir()
    (out / "points.csv").write_text("x")
    with pytest.raises(InvalidInputError, match="points.csv.*exists"):
        PairWorkspace.for_run(out).plan_run()
    PairWorkspace.for_run(out, overwrite=True).plan_run()
    (out / "report").mkdir()
    (out / "report" / "report.html").write_text("x")
    (out / "points.csv").unlink()
    with pytest.raises(InvalidInputError, match="already holds a report"):
        PairWorkspace.for_run(out).plan_run()
    with pytest.raises(InvalidInputError, match="also an input"):
        PairWorkspace.for_run(out, overwrite=True, inputs=(out / "matches.csv",)).plan_run()
    (tmp_path / "file").write_text("x")
    with pytest.raises(InvalidInputError, match="not a folder"):
        PairWorkspace.for_run(tmp_path / "file").plan_run()


def test_transaction_removes_a_folder_it_created(tmp_path):
    ws = PairWorkspace.for_run(tmp_path / "out")
    ws.plan_run()
    ws.prepare()
    with pytest.raises(RuntimeError), ws.transaction():
        ws.write_text(ws.layout_path("matches"), "id\n")
        (ws.root / "report").mkdir()
        raise RuntimeError("boom")
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    scene = make_scene(0, size_px=480)
    return write_scene_inputs(scene, d / "input"), scene


def test_run_failure_leaves_no_folder(tmp_path, pair, monkeypatch):
    inp, _scene = pair

    def fail(*args, **kwargs):
        raise EstimationError("simulated failure in the absolute orientation")

    monkeypatch.setattr(actions, "build_model", fail)
    out = tmp_path / "run"
    with pytest.raises(EstimationError, match="simulated"):
        actions.run(inp["left"], inp["right"], camera=inp["camera"], out_dir=out, control=inp["control"])
    assert not out.exists()
    # missing parent folders are created (as in release 0.1.0) and removed again after a failure
    nested = tmp_path / "a" / "b" / "run"
    with pytest.raises(EstimationError, match="simulated"):
        actions.run(inp["left"], inp["right"], camera=inp["camera"], out_dir=nested, control=inp["control"])
    assert not (tmp_path / "a").exists()


def test_run_writes_the_layout(tmp_path, pair):
    inp, _scene = pair
    out = tmp_path / "run"
    r = actions.run(inp["left"], inp["right"], camera=inp["camera"], out_dir=out, control=inp["control"],
                    report=False)
    assert sorted(p.name for p in out.iterdir()) == sorted(RUN_LAYOUT.values())
    g = read_relative(out / "relative.json")
    np.testing.assert_array_equal(g.base, r.ro.base)
    lines = r.summary_lines()
    assert lines[0].startswith(f"{r.model.summary['n_matches']} matches; relative orientation (left-image)")
    assert lines[-1] == (f"outputs in {out}: points.ply, points.csv, orientation.json, relative.json, matches.csv, "
                         "report/")
    o = json.loads((out / "orientation.json").read_text())
    assert o["format"] == "rectify-stereo/model-orientation" and o["summary"]["n_matches"] == len(
        (out / "matches.csv").read_text().splitlines()) - 1
    # a second run without --overwrite fails before matching and leaves the folder as it was
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(InvalidInputError, match="exists"):
        actions.run(inp["left"], inp["right"], camera=inp["camera"], out_dir=out, report=False)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
