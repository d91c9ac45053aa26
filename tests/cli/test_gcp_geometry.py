"""Issue 12: GCP geometry judged (hull share, predicted error at the corners, extrapolation warning,
no redundancy) and residuals of a geographic CRS in degrees and metres."""

from __future__ import annotations

import re

import affine
import numpy as np
import pytest
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms import AffineTransform, fit_gcps
from rectify.geometry.transforms.quality import hull_area, judge_gcp_geometry, metres_per_degree
from rectify.raster.io import write_raster

A = np.array([[29.0, 6.0, 500100.0], [5.0, -31.0, 4399900.0], [0, 0, 1]])


def _table(pix, noise, seed=0, crs=None, a=A):
    rng = np.random.default_rng(seed)
    tgt = AffineTransform(a)(pix) + rng.normal(0, noise, (len(pix), 2))
    return GcpTable(tuple(f"g{i}" for i in range(len(pix))), pix, tgt, None, np.zeros(len(pix), bool), crs)


def test_hull_area():
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [5, 5], [2, 8]], float)
    assert hull_area(sq) == pytest.approx(100.0)
    assert hull_area(np.array([[0, 0], [1, 1], [2, 2]], float)) == 0.0


@pytest.mark.parametrize("n", [8, 60])   # exact Jacobian and the random-probe estimate
def test_predicted_corner_error_matches_monte_carlo(n):
    rng = np.random.default_rng(1)
    pix = rng.uniform(0, 300, (n, 2))            # GCPs in one corner of a 2000 x 1500 image
    g = judge_gcp_geometry(_table(pix, 2.0), "affine", 2000, 1500, units="m")
    corners = np.array([[-0.5, -0.5], [1999.5, -0.5], [1999.5, 1499.5], [-0.5, 1499.5]])
    truth = AffineTransform(A)(corners)
    err = []
    for k in range(400):
        m = fit_gcps(_table(pix, 2.0, seed=100 + k), "affine").model
        err.append(np.linalg.norm(m(corners) - truth, axis=1))
    mc = np.sqrt(np.mean(np.square(err), axis=0))
    predicted = g.corner_sigma / g.sigma0 * 2.0      # per unit of the true sigma
    tol = 0.2 if n <= 40 else 0.35
    assert np.all(np.abs(predicted / mc - 1) < tol), (predicted, mc)
    assert g.extrapolation and g.hull_share < 0.05


def _frame(tmp_path):
    img = np.full((150, 200), 100, np.uint8)
    img[::10] = 30
    src = tmp_path / "img.tif"
    write_raster(src, img, affine.Affine(1, 0, 0, 0, 1.0000001, 0), None)
    return src


def _csv(path, pix, tgt, crs):
    path.write_text(f"# crs={crs}\nid,col,row,x,y\n" + "".join(
        f"g{i},{c:.6f},{r:.6f},{x:.10f},{y:.10f}\n" for i, ((c, r), (x, y)) in enumerate(zip(pix, tgt, strict=True))))


def test_fit_and_warp_warn_on_extrapolation(tmp_path):
    src = _frame(tmp_path)
    rng = np.random.default_rng(2)
    pix = rng.uniform(0, 30, (6, 2))
    t = _table(pix, 3.0, crs="EPSG:32618")
    g = tmp_path / "g.csv"
    _csv(g, pix, t.target, "EPSG:32618")
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(tmp_path / "t.json"), "--method", "affine",
                                 "--image", str(src)])
    assert r.exit_code == 0, r.output
    assert re.search(r"convex hull covers \d+% of the 200 x 150 image", r.output)
    assert "predicted error (1 sigma" in r.output and "at the corners TL, TR, BR, BL" in r.output
    assert "warning: the GCPs cover only" in r.output and "extrapolation" in r.output
    r = CliRunner().invoke(cli, ["warp", str(src), str(tmp_path / "o.tif"), "--gcps", str(g), "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert "warning: the GCPs cover only" in r.output
    # well spread GCPs: no warning
    pix = np.array([[5, 5], [190, 8], [185, 140], [10, 145], [100, 70], [60, 120]], float)
    _csv(g, pix, _table(pix, 3.0).target, "EPSG:32618")
    r = CliRunner().invoke(cli, ["warp", str(src), str(tmp_path / "o2.tif"), "--gcps", str(g), "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert "convex hull covers" in r.output and "warning" not in r.output


def test_four_point_homography_says_no_redundancy(tmp_path):
    src = _frame(tmp_path)
    pix = np.array([[5, 5], [190, 8], [185, 140], [10, 145]], float)
    g = tmp_path / "g.csv"
    _csv(g, pix, _table(pix, 0.0).target, "EPSG:32618")
    for args in (["fit", str(g), "-o", str(tmp_path / "t.json")],
                 ["fit", str(g), "-o", str(tmp_path / "t2.json"), "--image", str(src)],
                 ["warp", str(src), str(tmp_path / "o.tif"), "--gcps", str(g)]):
        r = CliRunner().invoke(cli, args)
        assert r.exit_code == 0, r.output
        assert "no redundancy: 4 GCPs determine the 8 homography parameters exactly" in r.output


def test_geographic_residuals_in_degrees_and_metres(tmp_path):
    src = _frame(tmp_path)
    a = np.array([[1e-4, 1e-5, 30.0], [1e-5, -1e-4, 50.0], [0, 0, 1]])
    pix = np.array([[5, 5], [190, 8], [185, 140], [10, 145], [100, 70], [60, 120], [150, 30]], float)
    t = _table(pix, 2e-6, a=a, crs="EPSG:4326")
    g = tmp_path / "g.csv"
    _csv(g, pix, t.target, "EPSG:4326")
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(tmp_path / "t.json"), "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert "residuals in degrees and metres" in r.output
    row = next(ln for ln in r.output.splitlines() if ln.strip().startswith("g0 "))
    dlon, dlat, de, dn = map(float, row.split()[1:5])
    me, mn = metres_per_degree(float(np.mean(t.target[:, 1])))
    assert len(row.split()[1].split(".")[1]) == 8 and dlon != 0
    assert de == pytest.approx(dlon * me, abs=2e-3) and dn == pytest.approx(dlat * mn, abs=2e-3)
    assert re.search(r"RMSE [\d.e-]+ degree = [\d.]+ m", r.output)
    r = CliRunner().invoke(cli, ["warp", str(src), str(tmp_path / "o.tif"), "--gcps", str(g), "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert re.search(r"RMSE [\d.e-]+ degree = [\d.]+ m", r.output)
