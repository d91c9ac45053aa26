"""Tests of stereo.report.pair (relative/absolute orientation figures, write_stereo_report).

Named test_stereo_report.py, not test_report.py: tests/ has no __init__.py, so two
test modules with the same basename would clash under pytest's default import mode.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.residuals import ResidualTable
from stereo.report.pair import absolute_orientation_figures, relative_orientation_figures, write_stereo_report

NAMES = ["tau", "nu", "alpha2", "omega2", "kappa2"]


def corr() -> np.ndarray:
    c = np.eye(5)
    c[2, 4] = c[4, 2] = 0.93
    c[0, 3] = c[3, 0] = -0.4
    return c


def ro_table(n: int = 30) -> ResidualTable:
    rng = np.random.default_rng(5)
    pos = rng.uniform(0, [640, 1152], (n, 2))
    q = rng.normal(0, 0.005, n)
    out = np.zeros(n, bool)
    out[0] = True
    return ResidualTable("relative orientation (vertical parallax)", [f"t{i}" for i in range(n)], q,
                         np.zeros(n), "mm", components=("q",), position_px=pos, outlier=out, n_params=5)


def ao_table(n: int = 8) -> tuple[ResidualTable, np.ndarray]:
    rng = np.random.default_rng(9)
    ground = rng.uniform([-30000, -25000], [-29000, -24000], (n, 2))
    obs = np.column_stack([ground, rng.uniform(100, 200, n)])
    adj = obs + rng.normal(0, [0.3, 0.3, 0.6], (n, 3))
    chk = np.zeros(n, bool)
    chk[-2:] = True
    return ResidualTable("absolute orientation", [f"G{i}" for i in range(n)], obs, adj, "m",
                         components=("dX", "dY", "dZ"), check=chk, n_params=7), ground


def test_relative_orientation_figures():
    figs = relative_orientation_figures(NAMES, corr(), table=ro_table(), image_shape=(1152, 640))
    assert list(figs) == ["RO correlation of elements", "RO vertical parallax over the left image"]
    heat = figs["RO correlation of elements"]
    img = heat.axes[0].images[0].get_array()
    np.testing.assert_allclose(img, corr())
    texts = [t.get_text() for t in heat.axes[0].texts]
    assert "+0.93" in texts and "-0.40" in texts
    assert [t.get_text() for t in heat.axes[0].get_xticklabels()] == NAMES
    # without a table only the heat map
    assert list(relative_orientation_figures(NAMES, corr())) == ["RO correlation of elements"]


def test_absolute_orientation_figures():
    t, g = ao_table()
    figs = absolute_orientation_figures(t, g)
    assert all(isinstance(f, Figure) for f in figs.values())
    bars = figs["AO height residuals"].axes[0].patches
    np.testing.assert_allclose([b.get_height() for b in bars], t.residual[:, 2])
    plan = figs["AO plan residuals"].axes[0]
    assert not plan.yaxis_inverted()  # map axes: north up
    assert plan.get_xlabel() == "X (m)"


def test_absolute_orientation_bad_input():
    t, g = ao_table()
    with pytest.raises(ShapeError, match=r"\(8, 2\)"):
        absolute_orientation_figures(t, g[:3])
    with pytest.raises(InvalidInputError, match="3 components"):
        absolute_orientation_figures(ro_table(), np.zeros((30, 2)))
    with pytest.raises(ShapeError):
        relative_orientation_figures(NAMES, np.eye(4))
    with pytest.raises(InvalidInputError, match="absolute_ground_xy"):
        write_stereo_report("unused", title="t", absolute=t)


def test_write_stereo_report(tmp_path: Path):
    ro = ro_table()
    ao, g = ao_table()
    p = write_stereo_report(tmp_path / "r", title="stereo test", relative=ro, correlation=(NAMES, corr()),
                            absolute=ao, absolute_ground_xy=g, crs="EPSG:32734", left_image_shape=(1152, 640),
                            principal_point_px=(319.5, 575.5), summary={"base_mm": 92.0})
    assert p == tmp_path / "r" / "report.html"
    doc = json.loads((tmp_path / "r" / "report.json").read_text())
    assert [t["step"] for t in doc["tables"]] == [ro.step, ao.step]
    assert doc["tables"][1]["summary"]["n_check"] == 2
    assert set(doc["figures"]) == {"RO correlation of elements", "AO plan residuals", "AO height residuals"}
    gj = json.loads((tmp_path / "r" / "absolute_orientation.geojson").read_text())
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32734"
    f0 = gj["features"][0]
    ex = f0["properties"]["exaggeration"]
    (x0, y0), (x1, y1) = f0["geometry"]["coordinates"]
    np.testing.assert_allclose([(x1 - x0) / ex, (y1 - y0) / ex], ao.residual[0, :2], rtol=1e-9)
    html = p.read_text()
    assert "Relative orientation: correlation of the elements" not in html  # titles are in the PNGs
    assert html.count("data:image/png;base64,") == 3 + 3 + 1  # RO: vectors, dist, radial; AO: dist; 3 extra
