"""stereo.formats.orientation: round trips of every stereo artefact, versions, and the files of release 0.1.0."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from rectify.errors import InvalidInputError, RasterIOError
from stereo.formats.orientation import (
    EXTERIOR_FORMAT,
    FORMAT_VERSION,
    ORIENTATION_FORMAT,
    RELATIVE_FORMAT,
    orientation_dict,
    read_exterior,
    read_orientation,
    read_relative,
    relative_dict,
    write_exterior,
    write_orientation,
    write_relative,
)
from stereo.formats.points import read_ply, read_ply_xyz, read_points_csv, write_ply, write_points_csv
from stereo.pair.resection import ExteriorOrientation, resect
from stereo.relative import RelativeGeometry, RelativeOrientation
from tests.support.stereo_support import simulate_pair

OLD = Path(__file__).resolve().parents[1] / "data" / "release_0_1_0"
CAM = {"focal_length_mm": 120.0, "pixel_size_mm": 0.192, "width": 480, "height": 480}


# ------------------------------------------------------------------ round trips
def test_relative_round_trip(tmp_path):
    sp = simulate_pair("vertical", n=40, noise_px=0.3, rng=2)
    ro = RelativeOrientation.from_points(sp.left_mm, sp.right_mm, focal_length_mm=120.0, pixel_size_mm=0.144,
                                         ids=[f"p{i}" for i in range(40)])
    p = write_relative(tmp_path / "ro.json", ro, extra={"camera": CAM})
    d = json.loads(p.read_text())
    assert d["format"] == RELATIVE_FORMAT and d["version"] == FORMAT_VERSION and list(d)[:2] == ["format", "version"]
    g = read_relative(p)
    want = RelativeGeometry.from_relative(ro)
    for name in ("rotation_left", "rotation_right", "base"):
        assert_array_equal(getattr(g, name), getattr(want, name))
    assert g.focal_length_mm == want.focal_length_mm == (120.0, 120.0)
    assert g.sigma0_mm == ro.sigma0_mm and g.pixel_size_mm == 0.144 and g.system == "left-image"
    assert g.raw == json.loads(json.dumps(relative_dict(ro, extra={"camera": CAM})))
    assert g.raw["camera"] == CAM and [q["id"] for q in g.raw["points"]] == list(ro.ids)
    with pytest.raises(InvalidInputError, match="exists"):
        write_relative(p, ro)


def _eo():
    rng = np.random.default_rng(5)
    truth = ExteriorOrientation(position=[1000.0, 2000.0, 3000.0], rotation=np.eye(3), focal_length_mm=120.0)
    G = np.column_stack([rng.uniform(0, 2000, 12), rng.uniform(1000, 3000, 12), rng.uniform(0, 300, 12)])
    x = truth.project(G) + rng.normal(0, 0.005, (12, 2))
    chk = np.zeros(12, bool)
    chk[:2] = True
    return resect(x, G, focal_length_mm=120.0, ids=[f"g{i}" for i in range(12)], check=chk, crs="EPSG:32735")


def test_exterior_round_trip(tmp_path):
    eo = _eo()
    p = write_exterior(tmp_path / "eo.json", eo, camera=CAM)
    d = json.loads(p.read_text())
    assert d["format"] == EXTERIOR_FORMAT and d["version"] == FORMAT_VERSION and d["camera"] == CAM
    back = read_exterior(p)
    assert_array_equal(back.position, eo.position)
    assert_array_equal(back.rotation, eo.rotation)
    assert back.focal_length_mm == eo.focal_length_mm and back.crs == "EPSG:32735"
    assert_array_equal(back.principal_point_mm, eo.principal_point_mm)
    assert back.sigma0 == eo.sigma0 and back.iterations == eo.iterations and back.converged
    assert back.param_names == eo.param_names
    assert_allclose(back.covariance, eo.covariance, rtol=1e-12, atol=0)
    assert back.extra["camera"] == CAM


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(0, 1e5, (50, 3))
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    write_ply(tmp_path / "c.ply", xyz, colors=rgb, comment="ground")
    pc = read_ply(tmp_path / "c.ply")
    assert_array_equal(pc.xyz, xyz)
    assert_array_equal(pc.colors, rgb)
    assert pc.comments == ("ground",)
    write_ply(tmp_path / "p.ply", xyz[:0])
    assert read_ply_xyz(tmp_path / "p.ply").shape == (0, 3)
    write_ply(tmp_path / "p.ply", xyz, overwrite=True)
    pc = read_ply(tmp_path / "p.ply")
    assert_array_equal(pc.xyz, xyz)
    assert pc.colors is None and pc.comments == ()


def test_points_csv_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    ids = [f"t{i}" for i in range(20)]
    xyz = np.round(rng.normal(0, 1e4, (20, 3)), 4)
    res = np.round(rng.uniform(0, 0.01, 20), 5)
    std = np.round(rng.uniform(0, 2, (20, 3)), 4)
    write_points_csv(tmp_path / "p.csv", ids, xyz, res, std=std, crs="EPSG:32618")
    t = read_points_csv(tmp_path / "p.csv")
    assert t.ids == tuple(ids) and t.crs == "EPSG:32618"
    assert_allclose(t.xyz, xyz, rtol=0, atol=1e-9)
    assert_allclose(t.residual_mm, res, rtol=0, atol=1e-12)
    assert_allclose(t.std, std, rtol=0, atol=1e-12)
    write_points_csv(tmp_path / "q.csv", ids, xyz, res, crs="PROJCRS[" + "x" * 300 + "]")
    t = read_points_csv(tmp_path / "q.csv")
    assert t.std is None and t.crs is None  # a long WKT stays in the orientation JSON


def test_orientation_round_trip(tmp_path):
    model = SimpleNamespace(frame={"name": "topocentric", "origin_lon_lat_h": [24.4, -33.7, 574.2]},
                            crs="EPSG:32735", summary={"n_points": 3, "rmse_check_m": float("nan")},
                            absolute=None)
    d = orientation_dict(model, extra={"note": "x"})
    assert d["format"] == ORIENTATION_FORMAT and d["version"] == FORMAT_VERSION
    assert d["summary"]["rmse_check_m"] is None  # NaN -> null, never NaN in JSON
    write_orientation(tmp_path / "o.json", d)
    assert read_orientation(tmp_path / "o.json") == d


# ------------------------------------------------------------------ versions
@pytest.mark.parametrize("reader, name", [(read_relative, RELATIVE_FORMAT), (read_exterior, EXTERIOR_FORMAT),
                                          (read_orientation, ORIENTATION_FORMAT)])
def test_wrong_format_or_future_version(tmp_path, reader, name):
    p = tmp_path / "x.json"
    p.write_text(json.dumps({"format": "rectify-stereo/something-else", "version": 1}))
    with pytest.raises(InvalidInputError, match=r"x\.json.*format 'rectify-stereo/something-else'"):
        reader(p)
    p.write_text(json.dumps({"format": name, "version": FORMAT_VERSION + 1}))
    with pytest.raises(InvalidInputError, match=rf"x\.json.*version {FORMAT_VERSION + 1}"):
        reader(p)
    p.write_text("[1, 2]")
    with pytest.raises(InvalidInputError, match="expected a JSON object"):
        reader(p)
    with pytest.raises(RasterIOError, match="not found"):
        reader(tmp_path / "missing.json")


def test_bad_ply_and_csv(tmp_path):
    p = tmp_path / "a.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(InvalidInputError, match="unsupported PLY"):
        read_ply(p)
    p.write_bytes(b"not a ply")
    with pytest.raises(InvalidInputError, match="not a PLY"):
        read_ply(p)
    c = tmp_path / "a.csv"
    c.write_text("id,x,y\n1,2,3\n")
    with pytest.raises(InvalidInputError, match="not a points CSV"):
        read_points_csv(c)
    c.write_text("id,x,y,z,residual_mm\n1,2,3,abc,0\n")
    with pytest.raises(InvalidInputError, match="line 2"):
        read_points_csv(c)


# ------------------------------------------------------------------ release 0.1.0 files
def test_reads_release_0_1_0_relative():
    g = read_relative(OLD / "ro.json")
    assert g.system == "left-image" and g.focal_length_mm == (120.0, 120.0)
    assert_array_equal(g.rotation_left, np.eye(3))
    assert_allclose(np.linalg.norm(g.base), 1.0, atol=1e-12)
    assert_allclose(g.raw["elements"]["tau"], 0.005346616394630743, rtol=0, atol=0)
    assert_allclose(g.sigma0_mm, 0.0021629897520302555, rtol=0, atol=0)
    assert g.raw["n_points"] == 60 == len(g.raw["points"])
    assert g.raw["camera"] == CAM and "format" not in g.raw


def test_reads_release_0_1_0_exterior():
    eo = read_exterior(OLD / "eo.json")
    assert_allclose(eo.position, [-56075.621823853835, -3726768.074909741, 3508.6169127044027], rtol=0, atol=0)
    assert eo.focal_length_mm == 120.0 and eo.crs.startswith('PROJCRS["Lo25"')
    assert_allclose(eo.std_errors["x"], 5.2378005774122895, rtol=1e-12)
    assert_allclose(eo.std_errors["kappa"], 0.00027949424023391005, rtol=1e-12)
    assert eo.sigma0 == 0.029106856412573122 and eo.extra["camera"] == CAM


def test_reads_release_0_1_0_points():
    pc = read_ply(OLD / "points.ply")
    assert pc.xyz.shape == (90, 3) and pc.comments == ("ground",) and pc.colors is None
    t = read_points_csv(OLD / "points.csv")
    assert len(t.ids) == 90 and t.ids[:2] == ("1", "2") and t.ids[-1] == "k19"
    assert t.crs is None and t.std is not None  # the Lo25 WKT is too long for the comment line
    assert_allclose(t.xyz[0], [-56317.4350, -3726820.5503, 517.0070], rtol=0, atol=0)
    assert_allclose(t.xyz, pc.xyz, rtol=0, atol=5e-5)  # CSV to 0.1 mm
    o = read_orientation(OLD / "points.orientation.json")
    assert o["frame"]["name"] == "topocentric" and len(o["frame"]["origin_lon_lat_h"]) == 3
    assert o["summary"]["n_points"] == 90 and o["summary"]["n_control"] == 30
    assert o["crs"].startswith('PROJCRS["Lo25"') and o["absolute"]["scale"] > 0


def test_exterior_orientation_without_sigma0_round_trips(tmp_path):
    """An orientation that was not adjusted has sigma0 NaN: written as null, read back as NaN."""
    import dataclasses
    import json as _json

    from stereo.formats.orientation import read_exterior, write_exterior

    eo = read_exterior(OLD / "eo.json")
    eo = dataclasses.replace(eo, sigma0=float("nan"))
    p = write_exterior(tmp_path / "eo.json", eo)
    assert _json.loads(p.read_text())["sigma0_mm"] is None
    back = read_exterior(p)
    assert np.isnan(back.sigma0)
    np.testing.assert_allclose(back.position, eo.position, rtol=0, atol=1e-9)
