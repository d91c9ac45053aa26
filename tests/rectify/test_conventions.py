"""Conventions checked against independent references, so that a convention error cannot cancel out.

* pixel <-> world: rasterio's ``transform.xy`` / the inverse ``Affine``, with rotated geotransforms;
* the warp engine: values at output pixel centres of a rotated output grid at another resolution
  than the source's, against a linear ramp evaluated where rasterio puts those centres;
* eq. (1) of seed 001 in every rotation order, against a projection written out here with
  non-zero phi and kappa;
* the camera's pixel <-> photo conversion against the formulas of the data description;
* weights: an integer weight 2 equals the point listed twice, for every weighted 2D estimator.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio
import rasterio.transform
from affine import Affine
from numpy.testing import assert_allclose

from rectify.formats.gcps import read_gcps, write_gcps
from rectify.geometry.analytic import TiltedFrame
from rectify.geometry.camera import Camera
from rectify.geometry.points import GcpTable
from rectify.geometry.transforms import AffineTransform, Homography, PolynomialTransform, fit_gcps
from rectify.raster.georef import Grid, pixel_from_world, world_from_pixel, world_from_pixel_matrix
from rectify.raster.io import write_raster
from rectify.raster.warp import WarpOptions, warp_raster

ROTATED = [
    Affine(2.0 * math.cos(0.3), -2.0 * math.sin(0.3), 5e5, -2.0 * math.sin(0.3), -2.0 * math.cos(0.3), 4e6),
    Affine(10.0, 3.0, 1000.0, 4.0, -12.0, 5000.0),  # sheared, non-square
    Affine(-1.5, 0.7, 250.0, 0.9, 2.5, -300.0),  # mirrored, y up
]


# ------------------------------------------------------------------ pixel <-> world
@pytest.mark.parametrize("t", ROTATED, ids=["rotated", "sheared", "mirrored"])
def test_world_from_pixel_matches_rasterio_xy_rotated(t):
    rows = np.array([0, 0, 7, 123, 45])
    cols = np.array([0, 9, 0, 77, 300])
    xs, ys = rasterio.transform.xy(t, rows, cols, offset="center")
    ref = np.column_stack([xs, ys])
    assert_allclose(world_from_pixel(t, np.column_stack([cols, rows])), ref, rtol=0, atol=1e-6)
    m = world_from_pixel_matrix(t)
    assert_allclose(np.c_[cols, rows, np.ones(5)] @ m[:2].T, ref, rtol=0, atol=1e-6)
    # the inverse against the inverse Affine (corner convention) minus half a pixel
    inv = ~t
    corner = np.array([inv * (x, y) for x, y in ref])
    assert_allclose(pixel_from_world(t, ref), corner - 0.5, atol=1e-6)
    assert_allclose(corner - 0.5, np.column_stack([cols, rows]), atol=1e-6)


# ------------------------------------------------------------------ warp end to end
def _ramp(h, w):
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    return (3.0 * c + 5.0 * r + 100.0).astype(np.float32)


class _SourceFromWorld:
    """World -> source pixel through the inverse ``Affine`` (corner) minus 0.5: independent of rectify.raster.georef."""

    def __init__(self, t, with_matrix):
        inv = ~t
        m = np.array([[inv.a, inv.b, inv.c - 0.5], [inv.d, inv.e, inv.f - 0.5], [0.0, 0.0, 1.0]])
        self._m = m
        if with_matrix:
            self.matrix = m

    def __call__(self, w):
        w = np.asarray(w, dtype=np.float64)
        return w @ self._m[:2, :2].T + self._m[:2, 2]


@pytest.mark.parametrize("with_matrix", [True, False], ids=["matrix", "callable"])
def test_warp_rotated_grid_other_resolution_against_rasterio(tmp_path, with_matrix):
    """Source 2 m north-up; output 0.7 m pixels rotated by 25 degrees: output values are the ramp where
    rasterio puts the output pixel centres."""
    h, w = 60, 80
    src_t = Affine(2.0, 0.0, 5e5, 0.0, -2.0, 4e6)
    src = tmp_path / "ramp.tif"
    write_raster(src, _ramp(h, w)[:, :, None], src_t, "EPSG:32618")
    a = math.radians(25)
    res = 0.7
    out_t = Affine(res * math.cos(a), -res * math.sin(a), 5e5 + 40.0, -res * math.sin(a), -res * math.cos(a),
                   4e6 - 30.0)
    grid = Grid(90, 70, out_t, "EPSG:32618")
    out = tmp_path / "out.tif"
    warp_raster(src, out, _SourceFromWorld(src_t, with_matrix), grid,
                options=WarpOptions(resampling="bilinear", tile_px=32))
    with rasterio.open(out) as ds:
        data = ds.read(1).astype(np.float64)
        valid = ds.read_masks(1) > 0
    rows, cols = np.mgrid[0:70, 0:90]
    xs, ys = rasterio.transform.xy(out_t, rows.ravel(), cols.ravel(), offset="center")
    inv = ~src_t
    sc, sr = np.array([inv * (x, y) for x, y in zip(xs, ys, strict=True)]).T - 0.5
    expect = (3.0 * sc + 5.0 * sr + 100.0).reshape(70, 90)
    inside = ((sc > 1) & (sc < w - 2) & (sr > 1) & (sr < h - 2)).reshape(70, 90)
    assert inside.sum() > 3000
    assert valid[inside].all()
    # bilinear interpolation of a linear ramp is exact up to float32 storage and map interpolation
    assert np.abs(data[inside] - expect[inside]).max() < 0.05


def test_georectify_targets_from_rasterio_at_another_resolution(tmp_path):
    """GCP targets computed by rasterio (not by the code under test), output at 0.8 of the source pixel:
    output values equal the source ramp at the output pixel centres rasterio computes."""
    from rectify.raster.georectify import georectify

    h, w = 60, 80
    src = tmp_path / "frame.tif"
    write_raster(src, _ramp(h, w)[:, :, None], Affine.translation(0, 0) * Affine.scale(1, 1.0000001), None)
    # the frame's pixels are the pixels of a virtual north-up map raster with 10 m pixels
    map_t = Affine(10.0, 0.0, 600000.0, 0.0, -10.0, 5200000.0)
    rng = np.random.default_rng(5)
    pix = rng.uniform([2, 2], [w - 3, h - 3], (12, 2))
    xs, ys = rasterio.transform.xy(map_t, pix[:, 1], pix[:, 0], offset="center")
    g = GcpTable(tuple(f"g{i}" for i in range(12)), pix, np.column_stack([xs, ys]), None, np.zeros(12, bool),
                 "EPSG:32633")
    out = tmp_path / "rect.tif"
    georectify(src, out, g, method="affine", resolution=8.0, options=WarpOptions(resampling="bilinear"))
    with rasterio.open(out) as ds:
        data = ds.read(1).astype(np.float64)
        valid = ds.read_masks(1) > 0
        ot = ds.transform
        assert ot.a == 8.0 and ot.e == -8.0
    rows, cols = np.mgrid[0:data.shape[0], 0:data.shape[1]]
    xo, yo = rasterio.transform.xy(ot, rows.ravel(), cols.ravel(), offset="center")
    inv = ~map_t
    sc, sr = np.array([inv * (x, y) for x, y in zip(xo, yo, strict=True)]).T - 0.5
    expect = (3.0 * sc + 5.0 * sr + 100.0).reshape(data.shape)
    inside = ((sc > 1) & (sc < w - 2) & (sr > 1) & (sr < h - 2)).reshape(data.shape)
    assert inside.sum() > 3000
    assert valid[inside].all()
    assert np.abs(data[inside] - expect[inside]).max() < 0.05


# ------------------------------------------------------------------ eq. (1) in every order
def _rx(a):
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def _ry(a):
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _rz(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


OMEGA, PHI, KAPPA = 0.08, -0.13, 0.61


@pytest.mark.parametrize("order, angles, R", [
    ("omega-phi-kappa", (OMEGA, PHI, KAPPA), _rx(OMEGA) @ _ry(PHI) @ _rz(KAPPA)),
    ("omega-alpha-chi", (OMEGA, PHI, KAPPA), _rx(OMEGA) @ _ry(PHI) @ _rz(KAPPA)),
    ("phi-omega-kappa", (PHI, OMEGA, KAPPA), _ry(PHI) @ _rx(OMEGA) @ _rz(KAPPA)),
    ("alpha-omega-kappa", (PHI, OMEGA, KAPPA), _ry(PHI) @ _rx(OMEGA) @ _rz(KAPPA)),
])
def test_eq1_every_order_against_a_projection(order, angles, R):
    """A ground point seen by the tilted camera (rotation R, photo vector -> ground) and by a vertical
    camera at the same centre: eq. (1) maps the first image point onto the second."""
    f, f_out, pp = 152.0, 100.0, (0.4, -0.3)
    rng = np.random.default_rng(11)
    C = np.array([100.0, 200.0, 1500.0])
    P = np.column_stack([rng.uniform(-400, 600, 40), rng.uniform(-300, 700, 40), rng.uniform(0, 80, 40)])
    p = (P - C) @ R  # R^T (P - C): tilted camera frame
    tilted = np.column_stack([pp[0] - f * p[:, 0] / p[:, 2], pp[1] - f * p[:, 1] / p[:, 2]])
    d = P - C
    vertical = np.column_stack([-f_out * d[:, 0] / d[:, 2], -f_out * d[:, 1] / d[:, 2]])
    fr = TiltedFrame.from_angles(f, *angles, order=order, principal_point_mm=pp, f_out_mm=f_out)
    assert_allclose(fr.rotation, R, atol=1e-14)
    assert_allclose(fr(tilted), vertical, atol=1e-9)
    assert_allclose(fr.homography(tilted), vertical, atol=1e-9)
    assert_allclose(fr.inverse(vertical), tilted, atol=1e-9)
    assert fr.tilt == pytest.approx(math.acos(R[2, 2]), abs=1e-14)


def test_rotation_orders_differ_with_phi_and_kappa():
    """With non-zero phi the two orders are different matrices (the test above can tell them apart)."""
    a = _rx(OMEGA) @ _ry(PHI) @ _rz(KAPPA)
    b = _ry(PHI) @ _rx(OMEGA) @ _rz(KAPPA)
    assert np.abs(a - b).max() > 5e-3


# ------------------------------------------------------------------ camera frames
def test_camera_pixel_photo_against_the_formulas():
    """col = (W - 1) / 2 + (x + x0) / p, row = (H - 1) / 2 - (y + y0) / p: x right, y up, centres at integers."""
    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152, principal_point_mm=(0.3, -0.2))
    mm = np.array([[0.0, 0.0], [10.0, 20.0], [-30.0, 5.0], [7.5, -60.0]])
    col = (640 - 1) / 2 + (mm[:, 0] + 0.3) / 0.144
    row = (1152 - 1) / 2 - (mm[:, 1] - 0.2) / 0.144
    assert_allclose(cam.pixel_from_photo(mm), np.column_stack([col, row]), atol=1e-9)
    assert_allclose(cam.photo_from_pixel(np.column_stack([col, row])), mm, atol=1e-12)
    assert_allclose(cam.principal_point_px, [(640 - 1) / 2 + 0.3 / 0.144, (1152 - 1) / 2 + 0.2 / 0.144])
    rays = cam.rays_from_pixel(np.column_stack([col, row]))
    assert_allclose(rays, np.column_stack([mm, np.full(4, -120.0)]), atol=1e-12)
    K = cam.K
    assert_allclose(K[:2, 2], cam.principal_point_px)
    assert K[0, 0] == K[1, 1] == pytest.approx(120.0 / 0.144)


def test_camera_json_fields(tmp_path):
    """The camera JSON keys of docs/formats.md, and a round trip that keeps the principal point."""
    import json

    from rectify.formats.camera import read_camera, write_camera

    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152, principal_point_mm=(0.3, -0.2),
                 distortion={"k1": -0.01})
    p = write_camera(tmp_path / "cam.json", cam)
    doc = json.loads(p.read_text())
    assert doc["principal_point_mm"] == [0.3, -0.2]
    assert doc["focal_length_mm"] == 120.0 and doc["pixel_size_mm"] == 0.144
    assert (doc["width"], doc["height"]) == (640, 1152)
    assert doc["distortion"]["k1"] == -0.01
    back = read_camera(p)
    assert back.principal_point_mm == (0.3, -0.2)
    assert_allclose(back.principal_point_px, cam.principal_point_px)


# ------------------------------------------------------------------ weights
def _pts(rng, n, truth):
    s = rng.uniform(0, 1000, (n, 2))
    h = np.c_[s, np.ones(n)] @ truth.T
    return s, h[:, :2] / h[:, 2:] + rng.normal(0, 2.0, (n, 2))


H = np.array([[0.9, 0.12, 35.0], [-0.08, 1.05, 20.0], [2e-4, -1.5e-4, 1.0]])


def _doubled(s, d, k):
    """Point k listed twice (its copy offset by 1e-9 of the extent: exact duplicates are refused)."""
    eps = 1e-9 * 1000
    return np.vstack([s, s[k] + eps]), np.vstack([d, d[k] + eps])


@pytest.mark.parametrize("build", [
    lambda s, d, w: Homography.from_points(s, d, weights=w),
    lambda s, d, w: AffineTransform.from_points(s, d, weights=w),
    lambda s, d, w: PolynomialTransform.from_points(s, d, weights=w, order=2),
    lambda s, d, w: PolynomialTransform.from_points(s, d, weights=w, order=3),
], ids=["homography", "affine", "poly2", "poly3"])
def test_integer_weight_equals_repeated_point(build):
    """(The DLT alone, ``refine=False``, is left out: its algebraic solution depends on the point
    normalisation, which a repeated point shifts, so the two differ by design.)"""
    rng = np.random.default_rng(7)
    s, d = _pts(rng, 14, H)
    k = 3
    w = np.ones(14)
    w[k] = 2.0
    a = build(s, d, w)
    s2, d2 = _doubled(s, d, k)
    b = build(s2, d2, None)
    c = build(s, d, None)
    probe = rng.uniform(0, 1000, (50, 2))
    assert_allclose(a(probe), b(probe), rtol=0, atol=1e-6)
    assert np.abs(a(probe) - c(probe)).max() > 1e-3  # the weight matters at this noise


def test_fit_gcps_weight_equals_repeated_row():
    rng = np.random.default_rng(8)
    s, d = _pts(rng, 12, H)
    w = np.ones(12)
    w[5] = 2.0
    g = GcpTable(tuple(str(i) for i in range(12)), s, d, None, np.zeros(12, bool), None)
    s2, d2 = _doubled(s, d, 5)
    g2 = GcpTable(tuple(str(i) for i in range(13)), s2, d2, None, np.zeros(13, bool), None)
    a = fit_gcps(g, "homography", weights=w)
    b = fit_gcps(g2, "homography")
    assert_allclose(a.model(s), b.model(s), atol=1e-6)
    # sigma0: the same weighted sum of squares; the redundancy differs by 2 (one more point)
    vv = b.table.sigma0 ** 2 * (2 * 13 - 8)
    assert a.table.sigma0 ** 2 * (2 * 12 - 8) == pytest.approx(vv, rel=1e-6)


# ------------------------------------------------------------------ overviews and QGIS files
def test_overview_keypoints_to_full_resolution_against_rasterio():
    """A keypoint at an overview pixel (decimation 4, window origin (100, 40)) lands where rasterio puts that
    overview pixel's centre on the full-resolution grid."""
    from rectify.features import Features

    full_t = Affine(1.0, 0.0, 0.0, 0.0, -1.0, 0.0)
    ov_t = full_t * Affine.translation(100, 40) * Affine.scale(4.0)
    ov = np.array([[0.0, 0.0], [3.0, 7.0], [10.5, 2.25]])
    f = Features(ov, np.ones(3), np.zeros(3), np.ones(3), np.zeros(3, np.int64), np.zeros((3, 4), np.uint8))
    got = f.transformed(4.0, (100.0, 40.0)).xy
    xs, ys = rasterio.transform.xy(ov_t, ov[:, 1], ov[:, 0], offset="center")
    inv = ~full_t
    ref = np.array([inv * (x, y) for x, y in zip(xs, ys, strict=True)]) - 0.5
    assert_allclose(got, ref, atol=1e-12)
    assert_allclose(got[0], [101.5, 41.5])


def test_qgis_points_pixel_convention(tmp_path):
    """QGIS georeferencer .points: sourceX/sourceY are pixel-corner coordinates with y negative down, so
    (0.5, -0.5) is the centre of the top-left pixel, (10.0, -3.0) the corner at column 9.5, row 2.5."""
    p = tmp_path / "g.points"
    p.write_text("#CRS: EPSG:4326\nmapX,mapY,sourceX,sourceY,enable,dX,dY,residual\n"
                 "10,20,0.5,-0.5,1,0,0,0\n11,21,10.0,-3.0,1,0,0,0\n12,19,120.25,-44.75,1,0,0,0\n")
    g = read_gcps(p)
    assert_allclose(g.pixel, [[0.0, 0.0], [9.5, 2.5], [119.75, 44.25]])
    assert_allclose(g.target, [[10, 20], [11, 21], [12, 19]])


# ------------------------------------------------------------------ GCP file fields
def test_write_gcps_fields(tmp_path):
    g = GcpTable(("a", "b", "c"), np.array([[0.0, 0.5], [10.25, 3.0], [4.0, 9.0]]),
                 np.array([[100.0, 200.0], [110.0, 190.0], [105.0, 180.0]]), None, np.array([False, True, False]),
                 "EPSG:32618")
    p = write_gcps(tmp_path / "g.csv", g)
    lines = p.read_text().splitlines()
    assert lines[0] == "# crs=EPSG:32618"
    assert lines[1] == "id,col,row,x,y,check"
    assert lines[2].split(",") == ["a", "0.0", "0.5", "100.0", "200.0", "0"]
    assert lines[3].split(",")[-1] == "1"
    back = read_gcps(p)
    assert back.crs == "EPSG:32618" and back.ids == g.ids
    assert_allclose(back.pixel, g.pixel)
    assert_allclose(back.target, g.target)
    assert back.check.tolist() == [False, True, False]
