"""``stereo sat-intersect``: seed 001's satellite workflow on a synthetic scene with known truth.

Two satellite frames (f = 1000 mm, 700 km above the ellipsoid, 80 km apart along track, attitude a few
degrees off nadir) look at ground points given in Gauss-Krueger zone 7 (Pulkovo 1942, EPSG:28407) with
normal heights; the quasi-geoid is a GeoTIFF grid written by the test (a linear field, which PROJ's
bilinear interpolation reproduces exactly). The truth goes to the geocentric frame through pyproj
(not the seed's formulas the command uses), the image coordinates are exact projections.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from rasterio.transform import from_origin

from rectify.errors import CRSError, EstimationError, InvalidInputError
from rectify.geometry.crs import grid_undulation
from rectify.geometry.geodesy import (
    ecef_from_geodetic,
    enu_from_body,
    enu_rotation,
    geodetic_from_map,
    map_from_geodetic,
)
from stereo.actions.sat_intersect import SatIntersectOptions, sat_intersect
from stereo.cli.main import cli
from stereo.pair.intersection import n_factor_seed001
from stereo.pair.satellite import ecef_directions, intersect_rays

CRS = "EPSG:28407"  # Pulkovo 1942 / Gauss-Kruger zone 7 (central meridian 39 E)
F_MM = 1000.0
# the quasi-geoid (height anomaly) of the test: zeta = 14 + 0.6 (lon - 39) - 0.4 (lat - 47) m
Z0, ZL, ZB = 14.0, 0.6, -0.4
STATIONS = {  # image: (lon, lat, normal height of the centre, heading, pitch, roll in degrees)
    "s1": (39.30, 46.84, 700_000.0, 10.0, 1.5, -0.8),
    "s2": (39.31, 47.56, 700_150.0, 10.0, -1.2, 0.5),
}


def zeta(lon, lat):
    return Z0 + ZL * (np.asarray(lon) - 39.0) + ZB * (np.asarray(lat) - 47.0)


def write_grid(path):
    res = 0.25
    lons = 37.0 + res * np.arange(17)
    lats = 49.0 - res * np.arange(17)
    z = zeta(lons[None, :], lats[:, None]).astype("float32")
    with rasterio.open(path, "w", driver="GTiff", width=17, height=17, count=1, dtype="float32", crs="EPSG:4326",
                       transform=from_origin(37.0 - res / 2, 49.0 + res / 2, res, res)) as ds:
        ds.write(z, 1)
    return path


def _rotation(lon, lat, h, p, r):
    """ECEF <- body at a station."""
    return enu_rotation(lon, lat).T @ enu_from_body(*np.radians([h, p, r]))


def make_scene(d, *, n=30, seed=0, noise_mm=0.0):
    """Write stations.csv, points.csv, geoid.tif into ``d``; return the true (x, y, H) of the points."""
    rng = np.random.default_rng(seed)
    geo = {}
    rows = ["# crs=" + CRS, "image,x,y,z,heading,pitch,roll,f_mm"]
    for name, (lon, lat, H, h, p, r) in STATIONS.items():
        xy = _map([[lon, lat]])[0]
        rows.append(f"{name},{xy[0]:.4f},{xy[1]:.4f},{H:.4f},{h},{p},{r},{F_MM}")
        c = ecef_from_geodetic([[lon, lat, H + float(zeta(lon, lat))]], crs=CRS)[0]
        geo[name] = (c, _rotation(lon, lat, h, p, r))
    (d / "stations.csv").write_text("\n".join(rows) + "\n")
    centre = _map([[39.3, 47.2]])[0]
    truth = np.column_stack([centre[0] + rng.uniform(-25e3, 25e3, n), centre[1] + rng.uniform(-20e3, 20e3, n),
                             rng.uniform(0.0, 400.0, n)])
    ll = geodetic_from_map(truth, CRS)
    X = ecef_from_geodetic(np.column_stack([ll[:, :2], truth[:, 2] + zeta(ll[:, 0], ll[:, 1])]), crs=CRS)
    lines = ["id,image,x_mm,y_mm,sigma_mm"]
    for k in range(n):
        for name, (c, R) in geo.items():
            b = R.T @ (X[k] - c)
            x, y = -F_MM * b[0] / b[2], -F_MM * b[1] / b[2]
            assert abs(x) < 150 and abs(y) < 150
            x, y = x + noise_mm * rng.normal(), y + noise_mm * rng.normal()
            lines.append(f"P{k},{name},{x:.7f},{y:.7f},{max(noise_mm, 0.005)}")
    (d / "points.csv").write_text("\n".join(lines) + "\n")
    write_grid(d / "geoid.tif")
    return truth


def _map(lonlat):
    ll = np.asarray(lonlat, dtype=float)
    return map_from_geodetic(np.column_stack([ll, np.zeros(len(ll))]), CRS)[:, :2]


def _read(path):
    rows = [r.split(",") for r in path.read_text().splitlines() if not r.startswith("#")]
    head = rows[0]
    return {c: np.array([float(r[i]) for r in rows[1:]]) for i, c in enumerate(head) if c != "id"}


def test_grid_undulation_reads_the_test_grid(tmp_path):
    g = write_grid(tmp_path / "g.tif")
    pts = np.array([[39.123, 47.321], [38.0, 46.5]])
    np.testing.assert_allclose(grid_undulation(g, pts), zeta(pts[:, 0], pts[:, 1]), atol=1e-4)
    with pytest.raises(CRSError, match="not found"):
        grid_undulation(tmp_path / "none.tif", pts)
    with pytest.raises(CRSError, match="no value at lon 60"):
        grid_undulation(g, [[60.0, 47.0]])


def test_exact_scene_closes_to_a_millimetre(tmp_path):
    truth = make_scene(tmp_path)
    r = sat_intersect(stations=tmp_path / "stations.csv", points=tmp_path / "points.csv",
                      output=tmp_path / "out.csv", options=SatIntersectOptions(geoid=str(tmp_path / "geoid.tif")))
    assert r.xyz.shape == truth.shape
    np.testing.assert_allclose(r.xyz, truth, atol=1e-3)
    out = _read(tmp_path / "out.csv")
    np.testing.assert_allclose(np.column_stack([out["x"], out["y"], out["z"]]), truth, atol=2e-3)
    np.testing.assert_allclose(out["undulation"], zeta(out["lon"], out["lat"]), atol=1e-3)
    assert (out["n_rays"] == 2).all() and out["rms_mm"].max() < 1e-6
    # predicted precision (5 um on the image at 1:700 000, base/height 0.11): metres, height worse than plan
    assert (r.std[:, :2] > 1.0).all() and (r.std[:, :2] < 10).all() and (r.std[:, 2] > r.std[:, 0]).all()
    assert any("normal / orthometric" in s for s in r.summary_lines())


def test_without_the_model_heights_are_off_by_the_height_anomaly(tmp_path):
    """The same scene taken as ellipsoidal heights (the 14 m height anomaly ignored at the stations and the
    points alike): most of it cancels (the whole configuration moves up and down together), but the
    stations' radial shift changes the geometry; the heights come out wrong by metres, not millimetres."""
    truth = make_scene(tmp_path)
    r = sat_intersect(stations=tmp_path / "stations.csv", points=tmp_path / "points.csv",
                      output=tmp_path / "out.csv", options=SatIntersectOptions(ellipsoidal=True))
    dz = r.xyz[:, 2] - truth[:, 2]
    assert 0.5 < np.abs(dz).mean() < 5.0


def test_noisy_scene_errors_agree_with_the_predicted_std(tmp_path):
    truth = make_scene(tmp_path, n=300, seed=4, noise_mm=0.005)
    r = sat_intersect(stations=tmp_path / "stations.csv", points=tmp_path / "points.csv",
                      output=tmp_path / "out.csv", options=SatIntersectOptions(geoid=str(tmp_path / "geoid.tif")))
    z = (r.xyz - truth) / r.std
    ratio = np.sqrt(np.mean(z ** 2, axis=0))
    assert ((ratio > 0.8) & (ratio < 1.2)).all(), ratio
    assert 0.8 < r.sigma0 < 1.2


def test_least_squares_intersection_equals_the_seed_factor_in_the_normal_case():
    """Horizontal frames along a base with a vertical component: the seed 001 factor N gives the same point."""
    f, B = 1000.0, np.array([20_000.0, 0.0, 150.0])
    X = np.array([[3_000.0, -2_000.0, -700_000.0], [-7_000.0, 5_000.0, -699_800.0]])
    S1, S2 = np.zeros(3), B
    x1 = f * (X - S1)[:, :2] / -(X - S1)[:, 2:]
    x2 = f * (X - S2)[:, :2] / -(X - S2)[:, 2:]
    N = n_factor_seed001(x1[:, 0], x2[:, 0], bx=B[0], bz=B[2], focal_length_mm=f)
    seed = np.column_stack([N * x1[:, 0], N * x1[:, 1], -N * f])
    d = np.vstack([np.column_stack([x1, -np.full(2, f)]), np.column_stack([x2, -np.full(2, f)])])
    r = intersect_rays(np.vstack([[S1, S1], [S2, S2]]), d, np.array([0, 1, 0, 1]), np.full(4, 0.005),
                       np.full(4, f), 2)
    np.testing.assert_allclose(r.points, seed, atol=1e-6)
    np.testing.assert_allclose(r.points, X, atol=1e-6)


def test_ray_functions_bad_input():
    with pytest.raises(EstimationError, match="1 ray"):
        intersect_rays(np.zeros((3, 3)), np.eye(3), np.array([0, 0, 1]), np.ones(3), np.ones(3), 2)
    with pytest.raises(EstimationError, match="parallel"):
        intersect_rays(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([[0.0, 0, -1], [0.0, 0, -1]]), np.array([0, 0]),
                       np.ones(2), np.ones(2), 1)
    with pytest.raises(InvalidInputError, match="same"):
        intersect_rays(np.zeros((2, 3)), np.eye(3), np.array([0, 0]), np.ones(2), np.ones(2), 1)
    with pytest.raises(InvalidInputError, match="focal"):
        ecef_directions([[0.0, 0.0]], [0.0], [[0.0, 0.0, 0.0]], [[39.0, 47.0]])


def _hashes(d):
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in d.rglob("*") if p.is_file()}


def test_cli_end_to_end_and_bad_input(tmp_path):
    truth = make_scene(tmp_path)
    base = ["sat-intersect", "--stations", str(tmp_path / "stations.csv"), "--points", str(tmp_path / "points.csv")]
    out = tmp_path / "o" / "pts.csv"
    out.parent.mkdir()
    r = CliRunner().invoke(cli, [*base, "-o", str(out), "--geoid", str(tmp_path / "geoid.tif")])
    assert r.exit_code == 0, r.output
    assert "intersected 30 point(s) from 60 rays of 2 image(s)" in r.output and f"wrote {out}" in r.output
    got = _read(out)
    np.testing.assert_allclose(got["x"], truth[:, 0], atol=2e-3)
    np.testing.assert_allclose(got["z"], truth[:, 2], atol=2e-3)
    bad_points = tmp_path / "bad_points.csv"
    bad_points.write_text("id,image,x_mm,y_mm\nA,s1,1,2\nA,s3,1,2\n")
    one_ray = tmp_path / "one_ray.csv"
    one_ray.write_text("id,image,x_mm,y_mm\nA,s1,1,2\nA,s2,1,2\nB,s1,3,4\n")
    dup = tmp_path / "dup.csv"
    dup.write_text("id,image,x_mm,y_mm\nA,s1,1,2\nA,s1,1,2\n")
    geo = str(tmp_path / "geoid.tif")
    new = tmp_path / "o" / "new.csv"
    before = _hashes(tmp_path)
    cases = [
        ([*base, "-o", str(new), "--geoid", str(tmp_path / "missing.tif")], "missing.tif' not found"),
        ([*base, "-o", str(new)], "--geoid GRID|VERTICAL_CRS"),
        ([*base, "-o", str(new), "--geoid", geo, "--ellipsoidal"], "not both"),
        ([*base, "-o", str(new), "--geoid", "EPSG:4326"], "not a vertical CRS"),
        ([*base, "-o", str(new), "--geoid", geo, "--crs", "EPSG:4284"], "not projected"),
        ([*base, "-o", str(new), "--geoid", geo, "--sigma-mm", "0"], "--sigma-mm"),
        ([*base, "-o", str(out), "--geoid", geo], "exists"),
        (["sat-intersect", "--stations", str(tmp_path / "stations.csv"), "--points", str(bad_points), "-o", str(new),
          "--geoid", geo], "image 's3' is not in"),
        (["sat-intersect", "--stations", str(tmp_path / "stations.csv"), "--points", str(one_ray), "-o", str(new),
          "--geoid", geo], "point 'B' is measured in 1 image"),
        (["sat-intersect", "--stations", str(tmp_path / "stations.csv"), "--points", str(dup), "-o", str(new),
          "--geoid", geo], "duplicate"),
        (["sat-intersect", "--stations", str(tmp_path / "points.csv"), "--points", str(dup), "-o", str(new),
          "--geoid", geo], "missing column"),
    ]
    for args, msg in cases:
        r = CliRunner().invoke(cli, args)
        assert r.exit_code != 0, args
        assert msg in r.output, (msg, r.output)
        assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
        assert not new.exists()
    after = _hashes(tmp_path)
    assert before == after  # inputs never modified, nothing else written


def test_vertical_crs_without_its_grid_is_refused_by_name(tmp_path):
    """A vertical CRS whose PROJ grid is not installed (EGM2008 here) is refused naming the grid."""
    make_scene(tmp_path, n=3)
    with pytest.raises(CRSError, match="grid"):
        sat_intersect(stations=tmp_path / "stations.csv", points=tmp_path / "points.csv",
                      output=tmp_path / "out.csv", options=SatIntersectOptions(geoid="EPSG:3855"))
    assert not (tmp_path / "out.csv").exists()
