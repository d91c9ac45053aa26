"""rectify.formats: round trips for every image-side format, and the files of release 0.1.0."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from rectify import errors
from rectify.formats.camera import CAMERA_VERSION, read_camera, write_camera
from rectify.formats.common import check_format, stamp
from rectify.formats.gcps import read_gcps, write_gcps
from rectify.formats.report import REPORT_VERSION, read_report, read_residuals, write_residuals
from rectify.formats.tables import read_control, read_matches, write_control, write_matches
from rectify.formats.transform import TRANSFORM_VERSION, read_transform, write_transform
from rectify.geometry.camera import Camera
from rectify.geometry.crs import parse_crs
from rectify.geometry.points import ControlTable, GcpTable, Matches
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.transforms import METHODS, fit_gcps

OLD = Path(__file__).resolve().parents[1] / "data" / "release_0_1_0"
EPSG = "EPSG:32618"


def gcp_table(crs: str | None = EPSG, z: bool = False) -> GcpTable:
    rng = np.random.default_rng(3)
    pix = rng.uniform(0, 500, (12, 2))
    tgt = pix * [30.0, -30.0] + [300000.0, 4000000.0] + rng.normal(0, 2, (12, 2))
    return GcpTable(tuple(f"g{i}" for i in range(12)), pix, tgt, rng.uniform(0, 99, 12) if z else None,
                    np.arange(12) % 6 == 0, crs)


# ------------------------------------------------------------------ round trips
@pytest.mark.parametrize("crs, z", [(EPSG, False), (None, True)])
def test_gcps_round_trip(tmp_path, crs, z):
    g = gcp_table(crs, z)
    back = read_gcps(write_gcps(tmp_path / "g.csv", g))
    assert back.ids == g.ids and back.crs == g.crs
    assert_array_equal(back.pixel, g.pixel)
    assert_array_equal(back.target, g.target)
    assert_array_equal(back.check, g.check)
    if z:
        assert back.z is not None and g.z is not None
        assert_array_equal(back.z, g.z)
    else:
        assert back.z is None


def test_matches_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    m = Matches(tuple(str(i) for i in range(20)), rng.uniform(0, 900, (20, 2)), rng.uniform(0, 900, (20, 2)),
                rng.uniform(0, 1, 20))
    back = read_matches(write_matches(tmp_path / "m.csv", m))
    assert back.ids == m.ids
    assert_allclose(back.left, m.left, atol=5e-7)  # 6 decimals
    assert_allclose(back.right, m.right, atol=5e-7)
    assert back.score is not None and m.score is not None
    assert_allclose(back.score, m.score, rtol=1e-5)
    no_score = Matches(m.ids, m.left, m.right)
    assert read_matches(write_matches(tmp_path / "n.csv", no_score)).score is None


def test_matches_sigma_round_trip_and_weights(tmp_path):
    """Issue 30: the matcher's per-match sigma travels in the matches CSV (``sigma_px``) and gives the weights
    that `stereo orient` uses: an unrefined match (empty score) never weighs as much as a refined one."""
    ids = ("a", "b", "c", "d")
    pts = np.arange(8, dtype=float).reshape(4, 2)
    score = np.array([0.05, 0.1, np.nan, 0.08])
    sigma = np.array([0.05, 0.1, 0.5, np.nan])
    back = read_matches(write_matches(tmp_path / "m.csv", Matches(ids, pts, pts + 1, score, sigma)))
    assert back.sigma is not None
    assert_allclose(back.sigma[:3], sigma[:3], rtol=1e-3)
    assert np.isnan(back.sigma[3])
    w = back.weights()
    assert w is not None
    # refined matches weigh 1 whatever their own sigma (d has none); the unrefined c weighs (s0 / 0.5)^2,
    # s0 = 0.075 the median sigma of the refined matches that have one
    assert_allclose(w, [1.0, 1.0, (0.075 / 0.5) ** 2, 1.0], rtol=1e-3)
    # no score: nothing says which are refined, so each match by its own sigma (s0 = 0.1, the median);
    # one without a sigma as a raw keypoint
    alone = read_matches(write_matches(tmp_path / "s.csv", Matches(ids, pts, pts + 1, None, sigma)))
    assert_allclose(alone.weights(), [4.0, 1.0, 0.04, 0.04], rtol=1e-3)
    # an older file: scores only, unrefined ones empty -> refined 1, unrefined (0.1 / 0.5)^2
    old = read_matches(write_matches(tmp_path / "o.csv", Matches(ids, pts, pts + 1, score)))
    assert_allclose(old.weights(), [1, 1, 0.04, 1])
    assert read_matches(write_matches(tmp_path / "p.csv", Matches(ids, pts, pts + 1))).weights() is None
    (tmp_path / "bad.csv").write_text("id,col_left,row_left,col_right,row_right,sigma_px\n1,1,2,3,4,-0.5\n")
    with pytest.raises(errors.InvalidInputError, match=r"sigma_px -0.5"):
        read_matches(tmp_path / "bad.csv")


def test_control_round_trip(tmp_path):
    xyz = np.array([[1.5, 2.25, 3.0], [np.nan] * 3, [-4.0, 5.0, 6.125]])
    wkt = parse_crs("EPSG:32633").to_wkt()  # a WKT label (quotes, commas) reads back as written; it must be a CRS
    c = ControlTable(("a", "b", "c"), np.array([[1.0, 2], [3, 4], [5, 6]]), np.array([[7.0, 8], [9, 10], [11, 12]]),
                     xyz, wkt)
    back = read_control(write_control(tmp_path / "c.csv", c))
    assert back.ids == c.ids and back.crs == c.crs
    assert_array_equal(back.left, c.left)
    assert_array_equal(back.right, c.right)
    assert_array_equal(back.xyz, c.xyz)  # NaN rows stay NaN (tie points)
    assert back.is_control.tolist() == [True, False, True]


def test_camera_round_trip(tmp_path):
    cam = Camera(120.0, 0.144, 640, 1152, principal_point_mm=(0.01, -0.02), distortion={"k1": 1e-5, "p2": 2e-7})
    p = write_camera(tmp_path / "cam.json", cam)
    doc = json.loads(p.read_text())
    assert doc["format"] == "rectify-stereo/camera" and doc["version"] == CAMERA_VERSION
    assert read_camera(p).to_dict() == cam.to_dict()


@pytest.mark.parametrize("method", list(METHODS))
def test_transform_round_trip(tmp_path, method):
    g = gcp_table()
    r = fit_gcps(g, method)
    p = write_transform(tmp_path / "t.json", r.model, table=r.table, crs=g.crs, extra={"note": "x"})
    doc = json.loads(p.read_text())
    assert doc["format"] == "rectify-stereo/transform" and doc["version"] == TRANSFORM_VERSION
    f = read_transform(p)
    assert f.method == method and f.crs == g.crs and f.units == "m" and f.version == TRANSFORM_VERSION
    assert f.extra == {"note": "x"}
    assert f.rmse == r.table.summary()["rmse"]
    assert [row["id"] for row in f.residuals] == list(g.ids)
    pts = np.array([[10.0, 20.0], [250.0, 260.0], [480.0, 30.0]])
    assert_allclose(f.model(pts), r.model(pts), rtol=1e-12)
    with pytest.raises(errors.InvalidInputError, match="exists"):
        write_transform(p, r.model)


def test_residuals_round_trip(tmp_path):
    t = ResidualTable("GCP fit (affine)", ["a", "b", "c"], np.array([[1.0, 2], [3, 4], [5, 6]]),
                      np.array([[1.5, 2], [3, 4.25], [5, 6]]), "m", weights=[1.0, 0.5, 1.0],
                      outlier=[False, True, False], check=[False, False, True])
    back = read_residuals(write_residuals(tmp_path / "r.csv", t))
    assert back.step == t.step and back.units == t.units and back.ids == t.ids and back.components == t.components
    for name in ("observed", "adjusted", "weights", "outlier", "check"):
        assert_array_equal(getattr(back, name), getattr(t, name))


def test_report_json_round_trip(tmp_path):
    from rectify.report.builder import write_report

    t = ResidualTable("tiny fit", ["a", "b", "c"], np.zeros((3, 2)), np.ones((3, 2)), "px")
    out = write_report(tmp_path / "rep", title="round trip", tables=[t], summary={"n": 3})
    doc = read_report(out.parent)
    assert doc["version"] == REPORT_VERSION and doc["title"] == "round trip" and doc["summary"] == {"n": 3}
    assert doc["tables"][0]["summary"]["n_points"] == 3
    raw = json.loads((out.parent / "report.json").read_text())
    assert raw["format"] == "rectify-stereo/report"
    back = read_residuals(out.parent / doc["tables"][0]["files"]["csv"])
    assert_array_equal(back.adjusted, t.adjusted)


# ------------------------------------------------------------------ versions
def test_stamp_and_check_format():
    d = stamp("camera", 1, {"width": 4, "format": "ignored"})
    assert list(d)[:2] == ["format", "version"] and d["format"] == "rectify-stereo/camera"
    assert check_format(d, "camera", 1) == 1
    assert check_format({"width": 4}, "camera", 1) == 0  # unversioned 0.1.0 file


@pytest.mark.parametrize("doc, text", [
    ({"format": "rectify-stereo/camera", "version": 9}, r"version 9, newer than this release reads \(<= 1\)"),
    ({"format": "rectify-stereo/transform", "version": 1}, "format 'rectify-stereo/transform'; expected"),
    ({"format": "rectify-stereo/camera", "version": "1"}, "version '1'"),
    ([1, 2], "must hold a JSON object"),
])
def test_check_format_refuses(doc, text):
    with pytest.raises(errors.InvalidInputError, match=text):
        check_format(doc, "camera", 1, "cam.json")


def test_readers_name_the_file_and_the_value(tmp_path):
    p = tmp_path / "t.json"
    p.write_text(json.dumps({"format": "rectify-stereo/transform", "version": TRANSFORM_VERSION + 1,
                             "method": "affine", "matrix": np.eye(3).tolist()}))
    with pytest.raises(errors.InvalidInputError, match=rf"transform file .*t\.json.* version {TRANSFORM_VERSION + 1}"):
        read_transform(p)
    c = tmp_path / "cam.json"
    c.write_text(json.dumps({"format": "rectify-stereo/transform", "version": 1}))
    with pytest.raises(errors.InvalidInputError, match=r"camera file .*cam\.json.* 'rectify-stereo/transform'"):
        read_camera(c)


# ------------------------------------------------------------------ files of release 0.1.0
def test_reads_release_0_1_0_gcps():
    g = read_gcps(OLD / "gcps.csv")
    assert len(g) == 16 and g.crs == EPSG and int(g.check.sum()) == 4 and g.z is None
    assert g.ids[0] == "gcp1" and g.ids[-1] == "chk4"
    assert_allclose(g.pixel[0], [192.90223132710824, 163.97379240615112])
    assert_allclose(g.target[0], [149337.05161695098, 2786626.958648612])


@pytest.mark.parametrize("method", ["homography", "cotangent", "affine", "poly2", "poly3"])
def test_reads_release_0_1_0_transforms(method):
    f = read_transform(OLD / f"transform_{method}.json")
    assert f.method == method and f.version == 1 and f.crs == EPSG and f.units == "m"
    assert len(f.residuals) == 16
    g = read_gcps(OLD / "gcps.csv")
    adjusted = np.array([r["adjusted"] for r in f.residuals])
    assert_allclose(f.model(g.pixel), adjusted, rtol=1e-9, atol=1e-6)  # the model reproduces its own file


def test_reads_release_0_1_0_homography_figures():
    f = read_transform(OLD / "transform_homography.json")
    assert f.rmse == pytest.approx(71.04134940662999) and f.rmse_check == pytest.approx(111.32596753270258)
    assert f.summary["n_fit"] == 12 and f.summary["n_check"] == 4


def test_reads_release_0_1_0_camera():
    cam = read_camera(OLD / "camera.json")
    assert (cam.focal_length_mm, cam.pixel_size_mm, cam.width, cam.height) == (120.0, 0.192, 480, 480)


def test_reads_release_0_1_0_matches_and_control():
    m = read_matches(OLD / "matches.csv")
    assert len(m) == 60 and m.ids[0] == "1" and m.score is not None
    assert_allclose(m.left[0], [185.154099, 247.525360])
    assert_allclose(m.right[0], [9.806138, 254.304008])
    c = read_control(OLD / "control.csv")
    assert c.ids[0] == "c0" and c.crs is not None and c.crs.startswith('PROJCRS["Lo25"')
    assert_allclose(c.xyz[0], [-55511.1682, -3726193.6579, 625.6446])
    assert int(c.is_control.sum()) == len(c)


def test_reads_release_0_1_0_report():
    doc = read_report(OLD / "report.json")
    assert doc["version"] == 1 and doc["title"] == "rectify demo: Landsat tilted frame" and doc["crs"] == EPSG
    t = doc["tables"][0]
    assert t["step"] == "GCP fit (homography)" and t["summary"]["n_fit"] == 12
    r = read_residuals(OLD / "residuals_gcp_fit_homography.csv")
    assert r.step == "GCP fit (homography)" and r.units == "m" and r.n == 16
    assert int(r.check.sum()) == 4 and r.ids[0] == "gcp1"
    assert r.summary()["rmse"] == pytest.approx(t["summary"]["rmse"], rel=1e-12)


# ------------------------------------------------------------------ through a workspace
def test_workspace_load_save_round_trips(tmp_path):
    from rectify.actions.workspace import Workspace

    g = gcp_table()
    cam = Camera(120.0, 0.144, 640, 1152)
    r = fit_gcps(g, "affine")
    m = Matches(("1", "2"), np.array([[1.0, 2], [3, 4]]), np.array([[5.0, 6], [7, 8]]))
    c = ControlTable(("a",), np.array([[1.0, 2]]), np.array([[3.0, 4]]), np.array([[5.0, 6, 7]]), EPSG)
    ws = Workspace(tmp_path)
    with ws.transaction():
        ws.save_gcps(tmp_path / "g.csv", g)
        ws.save_matches(tmp_path / "m.csv", m)
        ws.save_control(tmp_path / "c.csv", c)
        ws.save_camera(tmp_path / "cam.json", cam)
        ws.save_transform(tmp_path / "t.json", r.model, table=r.table, crs=g.crs)
        assert not (tmp_path / "g.csv").exists()  # staged until the block ends
    assert_array_equal(ws.load_gcps(tmp_path / "g.csv").target, g.target)
    assert ws.load_matches(tmp_path / "m.csv").ids == m.ids
    assert_array_equal(ws.load_control(tmp_path / "c.csv").xyz, c.xyz)
    assert ws.load_camera(tmp_path / "cam.json").to_dict() == cam.to_dict()
    assert ws.load_transform(tmp_path / "t.json").crs == EPSG
    with pytest.raises(errors.InvalidInputError, match="also an input"):
        ws.check_output(tmp_path / "g.csv")
    with pytest.raises(errors.InvalidInputError, match="exists"):
        Workspace().save_gcps(tmp_path / "g.csv", g)
