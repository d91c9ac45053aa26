"""Issue 12: -v/-q work before and after the subcommand (rectify and stereo)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.cli.main import cli
from stereo.cli.main import cli as stereo_cli


def _gcps(path):
    rng = np.random.default_rng(0)
    pix = rng.uniform(0, 500, (8, 2))
    tgt = pix * [2.0, -2.0] + [500000, 4400000] + rng.normal(0, 0.1, (8, 2))
    path.write_text("# crs=EPSG:32618\nid,col,row,x,y\n" + "".join(
        f"g{i},{c:.6f},{r:.6f},{x:.6f},{y:.6f}\n" for i, ((c, r), (x, y)) in enumerate(zip(pix, tgt, strict=True))))


@pytest.mark.parametrize("where", ["before", "after"])
def test_quiet_and_verbose_before_or_after_the_subcommand(tmp_path, where):
    g = tmp_path / "g.csv"
    _gcps(g)
    args = ["fit", str(g), "-o", str(tmp_path / "t.json")]
    r = CliRunner().invoke(cli, (["-q", *args] if where == "before" else [*args, "-q"]))
    assert r.exit_code == 0, r.output
    assert r.output == ""
    args = ["fit", str(g), "-o", str(tmp_path / "t2.json")]
    r = CliRunner().invoke(cli, (["-vv", *args] if where == "before" else [*args, "-vv"]))
    assert r.exit_code == 0, r.output
    assert "RMSE" in r.output
    assert logging.getLogger().getEffectiveLevel() == logging.DEBUG
    r = CliRunner().invoke(cli, [*args[:3], str(tmp_path / "t3.json"), "--verbose", "--quiet"])   # they add up
    assert r.exit_code == 0 and "RMSE" in r.output
    assert logging.getLogger().getEffectiveLevel() == logging.WARNING


def test_every_subcommand_takes_v_and_q():
    for group in (cli, stereo_cli):
        for name, cmd in group.commands.items():
            opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
            assert {"-v", "-q", "--verbose", "--quiet"} <= opts, name
    r = CliRunner().invoke(stereo_cli, ["orient", "--help"])
    assert r.exit_code == 0 and "--verbose" in r.output and "--quiet" in r.output
