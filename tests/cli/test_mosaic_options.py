"""``rectify mosaic`` end to end with the issue 27 options (--dsm, --seams, --blend, --balance, --provenance) and
its bad input: one-line errors, non-zero exit, nothing written."""

from __future__ import annotations

import json

import numpy as np
import rasterio
from click.testing import CliRunner

from rectify.cli.main import cli
from tests.support.mosaic_scene import CENTRE_A, X0, ridge_pair, texture, write_ortho


def _run(args):
    return CliRunner().invoke(cli, ["mosaic", *map(str, args)])


def _outputs(folder, inputs):
    return sorted(p.name for p in folder.iterdir() if p.name not in inputs)


def test_mosaic_least_transformed_with_provenance_and_balance(tmp_path):
    a, b, dsm = ridge_pair(tmp_path, true_ortho=True, gain=1.1, offset=-5.0)
    out = tmp_path / "m.tif"
    r = _run([a, b, "-o", out, "--dsm", dsm, "--balance", "reference", "--provenance", "--feather", "8"])
    assert r.exit_code == 0, r.output
    assert "seams of the least-transformed image" in r.output
    assert "radiometric balance (reference, a.tif kept)" in r.output
    assert "wrote " + str(tmp_path / "m.source.tif") in r.output
    assert _outputs(tmp_path, {"a.tif", "b.tif", "dsm.tif"}) == ["m.source.tif", "m.stac.json", "m.tif"]
    with rasterio.open(out) as ds:
        m, t = ds.read(1), ds.transform
        assert ds.count == 1  # the visibility band is not carried over
        assert ds.tags()["MOSAIC_SEAMS"] == "normal"
    X, Y = np.meshgrid(t.c + t.a * (np.arange(m.shape[1]) + 0.5), t.f + t.e * (np.arange(m.shape[0]) + 0.5))
    assert np.abs(m - texture(X, Y)).max() < 0.01  # B balanced onto A
    with rasterio.open(tmp_path / "m.source.tif") as ds:
        s = ds.read(1)
        assert ds.tags()["MOSAIC_SOURCE_1"] == "a.tif" and ds.tags()["MOSAIC_SOURCE_2"] == "b.tif"
    assert set(np.unique(s)) == {1, 2}
    item = json.loads((tmp_path / "m.stac.json").read_text())
    assert "provenance" in item["assets"]


def test_mosaic_average_blend(tmp_path):
    a, b, _ = ridge_pair(tmp_path, offset=10.0)
    out = tmp_path / "m.tif"
    r = _run([a, b, "-o", out, "--blend", "average", "--no-stac"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out) as ds:
        m, t = ds.read(1), ds.transform
    X, Y = np.meshgrid(t.c + t.a * (np.arange(m.shape[1]) + 0.5), t.f + t.e * (np.arange(m.shape[0]) + 0.5))
    d = m - texture(X, Y)
    assert np.allclose(d[:, 50:190], 5.0, atol=1e-3)  # the overlap: the mean of T and T + 10
    assert np.allclose(d[:, :30], 0.0, atol=1e-3) and np.allclose(d[:, 210:], 10.0, atol=1e-3)


def test_bad_input_one_line_nothing_written(tmp_path):
    a, b, dsm = ridge_pair(tmp_path)
    plain = write_ortho(tmp_path / "plain.tif", X0 + 20, X0 + 120, centre=None)
    far = write_ortho(tmp_path / "far.tif", X0 + 5000, X0 + 5060, centre=CENTRE_A)
    other = write_ortho(tmp_path / "utm33.tif", X0, X0 + 60, centre=CENTRE_A, crs="EPSG:32633")
    before = sorted(p.name for p in tmp_path.iterdir())
    cases = [
        ([a, plain, "--dsm", dsm], "has no projection centre", "--seams nadir"),
        ([a, b, "--seams", "normal"], "needs a DSM", "--dsm FILE"),
        ([a, far, "--balance", "mean"], "overlaps no other orthophoto", "a.tif"),
        ([a, other], "must share one CRS", "utm33.tif"),
        ([a, b, "--dsm", tmp_path / "missing.tif"], "missing.tif", ""),
    ]
    for args, what, more in cases:
        r = _run([*args, "-o", tmp_path / "m.tif"])
        assert r.exit_code != 0, args
        line = r.output.strip()
        assert "\n" not in line and "Traceback" not in line, line
        assert what in line and more in line, line
        assert sorted(p.name for p in tmp_path.iterdir()) == before, args
