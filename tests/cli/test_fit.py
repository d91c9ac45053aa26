"""End-to-end tests of ``rectify fit``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.formats.transform import read_transform
from rectify.geometry.transforms import Homography

H_TRUE = np.array([[1.1, 0.05, 10.0], [-0.02, 0.95, 20.0], [1e-4, -5e-5, 1.0]])


def _write_gcps(path, n=10, checks=(8, 9), noise=0.2, crs=None):
    rng = np.random.default_rng(11)
    pix = rng.uniform(0, 1000, (n, 2))
    tgt = Homography(H_TRUE)(pix) + rng.normal(0, noise, (n, 2))
    lines = ([f"# crs={crs}"] if crs else []) + ["id,col,row,x,y,check"]
    for i in range(n):
        lines.append(f"G{i},{pix[i, 0]:.10f},{pix[i, 1]:.10f},{tgt[i, 0]:.10f},{tgt[i, 1]:.10f},{int(i in checks)}")
    path.write_text("\n".join(lines) + "\n")
    return pix, tgt


@pytest.mark.parametrize("method", ["homography", "cotangent", "affine", "poly2", "poly3"])
def test_fit_writes_transform_and_prints_table(tmp_path, method):
    g = tmp_path / "gcps.csv"
    pix, tgt = _write_gcps(g, n=14, checks=(12, 13))
    out = tmp_path / "t.json"
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(out), "--method", method])
    assert r.exit_code == 0, r.output
    assert "dx" in r.output and "dy" in r.output and "|v|" in r.output
    assert "RMSE" in r.output and "check" in r.output
    assert "G12" in r.output and "G0" in r.output
    d = json.loads(out.read_text())
    assert d["method"] == method and len(d["residuals"]) == 14
    model = read_transform(out).model
    assert np.abs(model(pix[:12]) - tgt[:12]).max() < (2.0 if method != "affine" else 200.0)
    # printed RMSE equals the JSON's
    assert f"RMSE {d['rmse']:.4g} px" in r.output


def test_fit_refuses_overwrite_and_bad_input(tmp_path):
    g = tmp_path / "gcps.csv"
    _write_gcps(g)
    out = tmp_path / "t.json"
    runner = CliRunner()
    assert runner.invoke(cli, ["fit", str(g), "-o", str(out)]).exit_code == 0
    r = runner.invoke(cli, ["fit", str(g), "-o", str(out)])
    assert r.exit_code == 1 and "exists" in r.output
    assert runner.invoke(cli, ["fit", str(g), "-o", str(out), "--overwrite"]).exit_code == 0
    r = runner.invoke(cli, ["fit", str(g), "-o", str(tmp_path / "u.json"), "--method", "spline"])
    assert r.exit_code == 2 and "spline" in r.output
    r = runner.invoke(cli, ["fit", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "v.json")])
    assert r.exit_code == 1 and "not found" in r.output
    bad = tmp_path / "three.csv"
    bad.write_text("id,col,row,x,y\na,0,0,0,0\nb,10,0,10,0\nc,0,10,0,10\n")
    r = runner.invoke(cli, ["fit", str(bad), "-o", str(tmp_path / "w.json")])
    assert r.exit_code == 1 and "too few fit points for homography: 3" in r.output
    assert not (tmp_path / "w.json").exists()


def test_fit_report(tmp_path):
    g = tmp_path / "gcps.csv"
    _write_gcps(g, crs="EPSG:32633")
    rep = tmp_path / "rep"
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(tmp_path / "t.json"), "--report", str(rep)])
    assert r.exit_code == 0, r.output
    assert (rep / "report.html").is_file() and (rep / "report.json").is_file()
    assert list(rep.glob("*.csv"))
    assert "RMSE" in r.output and " m," in r.output  # EPSG:32633 is in metres


def test_fit_states_check_point_accuracy_in_the_standard_forms(tmp_path):
    """Issue 27: a GCP fit with check points prints per-axis RMSE, RMSE_r, CE90 and the ASPRS (2023) sentence,
    computed here by hand from the check points' residuals in the transform JSON; the report's JSON holds them."""
    g = tmp_path / "gcps.csv"
    _write_gcps(g, n=20, checks=tuple(range(14, 20)), noise=0.3, crs="EPSG:32633")
    out = tmp_path / "t.json"
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(out), "--report", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    rows = [row for row in json.loads(out.read_text())["residuals"] if row["check"]]
    assert len(rows) == 6
    v = np.array([[row["dx"], row["dy"]] for row in rows])
    rx, ry = np.sqrt(np.mean(v ** 2, axis=0))
    assert "accuracy statement from 6 check points (m;" in r.output
    assert f"RMSE_r {np.hypot(rx, ry):.3f} m" in r.output
    assert f"x: mean {v[:, 0].mean():+.3f}, std {v[:, 0].std(ddof=1):.3f}, RMSE {rx:.3f}" in r.output
    assert f"RMSE_H = {np.hypot(rx, ry) * 100:.1f} (cm)" in r.output and "produced to meet" in r.output
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    acc = rep["summary"]["accuracy_statement"]
    assert acc["n"] == 6 and acc["rmse_r"] == pytest.approx(np.hypot(rx, ry), rel=1e-9)
