"""``stereo run --dense``: the whole chain from two photos to a DSM on the synthetic scene."""

from __future__ import annotations

import json

import numpy as np
import rasterio
from click.testing import CliRunner

from stereo.actions.scene import make_scene, write_scene_inputs
from stereo.cli.main import cli


def test_run_dense_writes_the_pair_and_the_surface(tmp_path):
    scene = make_scene(0, size_px=320)
    inp = write_scene_inputs(scene, tmp_path / "input")
    out = tmp_path / "run"
    r = CliRunner().invoke(cli, ["run", str(inp["left"]), str(inp["right"]), "--camera", str(inp["camera"]),
                                 "--control", str(inp["control"]), "-o", str(out), "--dense"])
    assert r.exit_code == 0, r.output
    assert "dense/" in r.output and "dense: DSM:" in r.output
    # the orientation carries its camera, so the dense step needed no --camera
    assert "camera" in json.loads((out / "relative.json").read_text())
    with rasterio.open(out / "dense" / "dsm.tif") as ds:
        dsm = ds.read(1)
        valid = dsm != ds.nodata
    assert valid.mean() > 0.5
    # heights of the synthetic terrain (DEM values), in metres: the DSM lies within its range
    lo, hi = float(np.min(scene.dem)), float(np.max(scene.dem))
    h = dsm[valid]
    assert np.percentile(h, 2) > lo - 20 and np.percentile(h, 98) < hi + 20, (lo, hi, np.percentile(h, [2, 98]))

    # a second run without --overwrite is refused before any work, and leaves the first run's files
    before = sorted(p.name for p in out.iterdir())
    r2 = CliRunner().invoke(cli, ["run", str(inp["left"]), str(inp["right"]), "--camera", str(inp["camera"]),
                                  "-o", str(out), "--dense"])
    assert r2.exit_code == 1 and "--overwrite" in r2.output
    assert sorted(p.name for p in out.iterdir()) == before
