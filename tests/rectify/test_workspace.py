"""The files of one job: planned outputs, inputs refused as outputs, all-or-nothing writes."""

from __future__ import annotations

import os

import pytest

from rectify.actions.workspace import Workspace
from rectify.errors import InvalidInputError, RasterIOError


def test_transaction_writes_all_or_nothing(tmp_path):
    ws = Workspace(tmp_path / "a" / "b" / "out")
    ws.prepare("x.txt")
    with pytest.raises(RuntimeError, match="boom"), ws.transaction():
        ws.write_text(ws.path("x.txt"), "x")
        ws.write_json(ws.path("y.json"), {"y": 1})
        assert not ws.path("x.txt").exists()  # staged, not yet in place
        raise RuntimeError("boom")
    # nothing left: the files, their temporaries and the folders prepare() created
    assert not (tmp_path / "a").exists()
    assert os.listdir(tmp_path) == []

    ws = Workspace(tmp_path / "a" / "out")
    ws.prepare()
    with ws.transaction():
        ws.write_text(ws.path("x.txt"), "x")
        ws.write_json(ws.path("y.json"), {"y": 1})
    assert sorted(os.listdir(ws.root)) == ["x.txt", "y.json"]
    assert ws.path("y.json").read_text() == '{\n  "y": 1\n}\n'


def test_existing_folder_is_kept_after_a_failure(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    ws = Workspace(tmp_path / "out")
    ws.prepare()
    with pytest.raises(ValueError), ws.transaction():
        ws.write_text(ws.path("new.txt"), "n")
        raise ValueError("x")
    assert sorted(os.listdir(tmp_path / "out")) == ["keep.txt"]


@pytest.mark.parametrize("overwrite", [False, True])
def test_output_equal_to_an_input_is_refused(tmp_path, overwrite):
    src = tmp_path / "gcps.csv"
    src.write_text("id,col,row,x,y\n")
    ws = Workspace(overwrite=overwrite, inputs=[src])
    with pytest.raises(InvalidInputError, match="also an input"):
        ws.plan(tmp_path / "." / "gcps.csv")
    assert src.read_text() == "id,col,row,x,y\n"


def test_plan_checks_every_output_before_work(tmp_path):
    (tmp_path / "b.json").write_text("{}")
    ws = Workspace()
    with pytest.raises(InvalidInputError, match="b.json.*--overwrite"):
        ws.plan(tmp_path / "a.json", tmp_path / "b.json")
    with pytest.raises(InvalidInputError, match="named twice"):
        ws.plan(tmp_path / "c.json", tmp_path / "c.json")
    with pytest.raises(RasterIOError, match="does not exist"):
        ws.plan(tmp_path / "missing" / "c.json")
    assert Workspace(overwrite=True).plan(tmp_path / "b.json") == [tmp_path / "b.json"]


def test_existing_output_is_replaced_only_with_overwrite(tmp_path):
    p = tmp_path / "o.txt"
    p.write_text("old")
    with pytest.raises(InvalidInputError, match="exists"):
        Workspace().write_text(p, "new")
    assert p.read_text() == "old"
    Workspace(overwrite=True).write_text(p, "new")
    assert p.read_text() == "new"


def test_report_folder_must_be_writable(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(InvalidInputError, match="not a folder"):
        Workspace(report_dir=tmp_path / "file").check_report_dir()
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user who can write a read-only folder (root)")
        with pytest.raises(RasterIOError, match="not writable"):
            Workspace(report_dir=ro / "rep").check_report_dir()
    finally:
        ro.chmod(0o700)
