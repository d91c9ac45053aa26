"""Fusion of pair heights, sigma_Z propagation and ``run_surface`` on a rendered 3 x 4 block with known surface."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import InvalidInputError, ShapeError, StereoError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.actions.surface import SurfaceOptions, run_surface
from stereo.block.types import Pose
from stereo.dense.epipolar import rectify_exterior
from stereo.dense.fusion import SigmaGrid, fuse_heights, variance_factor
from stereo.dense.matching import refine_subpixel
from stereo.dense.precision import (
    PointSigmaField,
    disparity_sigma,
    height_sigma_disparity,
    height_sigma_orientation,
    normal_case_sigma_z,
)
from stereo.dense.triangulate import triangulate_disparity
from stereo.formats.block import block_orientation_text
from tests.support.block_surface import CAMERA, GSD, Z0, make_surface_block, read_dsm, truth_on


# --------------------------------------------------------------------------- fusion: known answers
def _cells(*values):
    """(P, 1, 1) arrays of heights / sigmas."""
    return np.array(values, dtype=np.float64).reshape(-1, 1, 1)


def test_two_consistent_pairs_give_the_weighted_mean_and_its_std():
    h, s = _cells(10.0, 10.1), _cells(0.1, 0.2)
    f = fuse_heights(h, s)
    w = np.array([100.0, 25.0])
    assert_allclose(f.height[0, 0], (w @ [10.0, 10.1]) / w.sum(), rtol=0, atol=1e-12)   # 10.02
    # chi2 = 100 * 0.02^2 + 25 * 0.08^2 = 0.2 < 1 (n - 1): no inflation
    assert_allclose(f.sigma[0, 0], 1 / math.sqrt(w.sum()), rtol=1e-12)
    assert f.count[0, 0] == 2 and f.provenance[0, 0] == 0 and f.rejected[0, 0] == 0
    assert_allclose(f.chi2[0, 0], 0.2, rtol=1e-9)
    assert f.dof[0, 0] == 1


def test_a_common_sigma_adds_in_quadrature_and_does_not_weight():
    f = fuse_heights(_cells(10.0, 10.1), _cells(0.1, 0.2), common=np.array([[0.05]]))
    assert_allclose(f.height[0, 0], 10.02, atol=1e-12)
    assert_allclose(f.sigma[0, 0], math.sqrt(1 / 125 + 0.05 ** 2), rtol=1e-12)
    assert_allclose(fuse_heights(_cells(1.0), _cells(0.3), common=np.array([[np.nan]])).sigma, [[0.3]])
    with pytest.raises(ShapeError, match="grid's shape"):
        fuse_heights(_cells(1.0), _cells(0.3), common=np.zeros((2, 2)))


def test_scatter_inflates_the_std_when_larger():
    # two equal sigmas 0.1 two sigmas apart: mean 10.1, std 0.1 / sqrt 2, chi2 = 2 * 100 * 0.01 = 2
    f = fuse_heights(_cells(10.0, 10.2), _cells(0.1, 0.1))
    assert_allclose(f.height[0, 0], 10.1, atol=1e-12)
    assert_allclose(f.sigma[0, 0], 0.1 / math.sqrt(2) * math.sqrt(2.0), rtol=1e-9)


def test_an_inconsistent_third_pair_is_rejected():
    f = fuse_heights(_cells(10.0, 10.1, 12.0), _cells(0.1, 0.2, 0.1))
    assert_allclose(f.height[0, 0], 10.02, atol=1e-12)
    assert f.count[0, 0] == 2 and f.rejected[0, 0] == 1
    assert f.provenance[0, 0] == 0          # the smallest sigma among the kept ones (the third is as precise)


def test_count_and_provenance_bands_on_a_grid():
    nan = np.nan
    h = np.array([[[1.0, nan, 5.0], [nan, nan, 2.0]],
                  [[1.1, 3.0, 5.05], [nan, nan, 9.0]],
                  [[nan, 3.1, 5.02], [nan, 4.0, nan]]])
    s = np.array([[[0.2, 1, 0.1], [1, 1, 0.1]],
                  [[0.1, 0.3, 0.1], [1, 1, 0.1]],
                  [[1, 0.1, 0.05], [1, 0.2, 1]]])
    f = fuse_heights(h, s)
    assert f.count.tolist() == [[2, 2, 3], [0, 1, 1]]
    assert f.provenance.tolist() == [[1, 2, 2], [-1, 2, 0]]    # [1, 2]: 2 vs 9, equal sigmas: the lower median
    assert np.isnan(f.height[1, 0]) and np.isnan(f.sigma[1, 0])
    assert f.rejected.tolist() == [[0, 0, 0], [0, 0, 1]]
    assert_allclose(f.height[1, 1], 4.0)
    assert_allclose(f.sigma[1, 1], 0.2)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-100, 100), st.floats(0.01, 5.0)), min_size=1, max_size=6),
       st.randoms(use_true_random=False), st.floats(-1e3, 1e3), st.floats(0.1, 10.0))
def test_fusion_properties(pairs, rnd, shift, scale):
    """Order of the pairs does not matter; shifting heights shifts the result; scaling heights and
    sigmas together scales it; the fused height lies within the kept heights; sigma never below
    the weighted mean's."""
    h = _cells(*[p[0] for p in pairs])
    s = _cells(*[p[1] for p in pairs])
    f = fuse_heights(h, s)
    order = list(range(len(pairs)))
    rnd.shuffle(order)
    g = fuse_heights(h[order], s[order])
    assert_allclose(g.height, f.height, rtol=1e-9, atol=1e-9)
    assert_allclose(g.sigma, f.sigma, rtol=1e-9)
    assert g.count[0, 0] == f.count[0, 0] and 1 <= f.count[0, 0] <= len(pairs)
    assert s[order[g.provenance[0, 0]], 0, 0] == s[f.provenance[0, 0], 0, 0]   # the same sigma picked
    assert_allclose(fuse_heights(h + shift, s).height, f.height + shift, atol=1e-7)
    k = fuse_heights(h * scale, s * scale)
    assert_allclose(k.height, f.height * scale, rtol=1e-9, atol=1e-9)
    assert_allclose(k.sigma, f.sigma * scale, rtol=1e-9)
    kept = np.abs(h[:, 0, 0] - f.height[0, 0]) <= 3 * np.sqrt(s[:, 0, 0] ** 2 + f.sigma[0, 0] ** 2) + 1e-9
    assert h[kept, 0, 0].min() - 1e-9 <= f.height[0, 0] <= h[kept, 0, 0].max() + 1e-9
    assert f.sigma[0, 0] >= 1 / np.sqrt(np.sum(1 / s[:, 0, 0] ** 2)) * (1 - 1e-12)


def test_fusion_bad_input():
    with pytest.raises(ShapeError, match=r"\(P, H, W\)"):
        fuse_heights(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ShapeError, match="one shape"):
        fuse_heights(np.zeros((2, 3, 3)), np.zeros((2, 3, 4)))
    with pytest.raises(InvalidInputError, match="`k` must be"):
        fuse_heights(_cells(1.0), _cells(1.0), k=0)
    # a non-positive sigma is not used
    f = fuse_heights(_cells(1.0, 2.0), _cells(0.0, 0.5))
    assert f.count[0, 0] == 1 and f.height[0, 0] == 2.0


def test_variance_factor():
    assert variance_factor(8.0, 2) == 2.0
    assert variance_factor(0.5, 2) == 1.0      # never below 1
    assert variance_factor(3.0, 0) == 1.0


def test_sigma_grid_of_a_plane():
    g = SigmaGrid((0, 0, 10, 10), 1.0, edge_cells=1)
    xx, yy = np.meshgrid(np.arange(0.05, 10, 0.25), np.arange(0.05, 10, 0.25))
    xyz = np.column_stack([xx.ravel(), yy.ravel(), 0.1 * xx.ravel() + 5])
    g.add(xyz, np.full(len(xyz), 0.2))
    h, s = g.result()
    ok = np.isfinite(h)
    assert ok.sum() > 50 and not ok[0].any() and not ok[:, 0].any()     # the edge cells dropped
    x = g.transform.c + (np.arange(h.shape[1]) + 0.5) * g.transform.a
    assert_allclose(h[ok], np.broadcast_to(0.1 * x + 5, h.shape)[ok], atol=0.02)
    assert_allclose(s[ok], 0.2, rtol=1e-5)
    with pytest.raises(ShapeError, match="one value per point"):
        g.add(xyz, np.ones(3))
    with pytest.raises(InvalidInputError, match="edge_cells"):
        SigmaGrid((0, 0, 10, 10), 1.0, edge_cells=-1)


# --------------------------------------------------------------------------- precision: closed forms
def test_normal_case_sigma_z_closed_form():
    # Z = 100, B = 40, f = 1000 px, sigma_p = 0.2 px -> 100^2 / 40000 * 0.2 = 0.05
    assert_allclose(normal_case_sigma_z(100.0, 40.0, 1000.0, 0.2), 0.05)
    with pytest.raises(InvalidInputError, match="base and focal"):
        normal_case_sigma_z(1.0, 0.0, 1.0, 1.0)


def test_height_sigma_matches_the_triangulation_derivative():
    cam = Camera(focal_length_mm=20.0, pixel_size_mm=0.05, width=200, height=150)
    left = Pose("a", "c", np.array([0.0, 0.0, 100.0]), matrix_from_angles(0.01, -0.02, 0.0))
    right = Pose("b", "c", np.array([30.0, 1.0, 100.5]), matrix_from_angles(-0.01, 0.015, 0.01))
    rect = rectify_exterior(left, right, cam, cam)
    pix = np.array([[40.0, 30.0], [100.0, 80.0], [150.0, 120.0]])
    d = np.full((150, rect.left.width), np.nan)
    d0 = 120.0 - rect.disparity_offset    # u_l - u_r = 120 px: depth B f / 120
    mask = np.zeros(d.shape, bool)
    for c, r in pix.astype(int):
        d[r, c] = d0 + 0.01 * c
        mask[r, c] = True
    p0 = triangulate_disparity(rect, d, mask=mask)
    p1 = triangulate_disparity(rect, d + 1e-3, mask=mask)
    dz = np.abs(p1.xyz[:, 2] - p0.xyz[:, 2]) / 1e-3
    got = height_sigma_disparity(p0.xyz, rect.centre_left, rect.normal_rotation[:, 2],
                                 float(np.linalg.norm(rect.base)), rect.focal_px, np.ones(len(p0)))
    assert_allclose(got, dz, rtol=2e-3)
    with pytest.raises(ShapeError, match=r"\(N, 3\)"):
        height_sigma_disparity(np.zeros((3, 2)), rect.centre_left, [0, 0, 1], 1.0, 1.0, np.ones(3))
    with pytest.raises(InvalidInputError, match="non-zero vector"):
        height_sigma_disparity(p0.xyz, rect.centre_left, [0, 0, 0], 1.0, 1.0, np.ones(len(p0)))


def test_height_sigma_orientation_closed_form():
    # Z = 100, B = 50: tilt 1e-4 rad each -> (200 * 1e-4)^2 * 2; x, y 0.02 each -> (2 * 0.02)^2 * 2; z 0.04 -> 0.04^2/2
    std = [1e-4, 1e-4, 5e-4, 0.02, 0.02, 0.04]
    want = math.sqrt(2 * (200 * 1e-4) ** 2 + 2 * (2 * 0.02) ** 2 + 2 * 0.04 ** 2 / 4)
    assert_allclose(height_sigma_orientation(100.0, 50.0, std, std), want)
    assert height_sigma_orientation(100.0, 50.0, None, [np.nan] * 6) == 0.0
    with pytest.raises(ShapeError, match="6 values"):
        height_sigma_orientation(100.0, 50.0, [1.0], None)
    with pytest.raises(InvalidInputError, match=">= 0"):
        height_sigma_orientation(100.0, 50.0, [-1.0] * 6, None)


def test_disparity_sigma_predicts_the_lsm_scatter():
    """Textured rows shifted by a known sub-pixel disparity plus noise: the predicted sigma of the
    matcher's one-step LSM refinement (its default) against the RMS of its actual errors."""
    rng = np.random.default_rng(4)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (160, 400)).astype(np.float32), (0, 0), 1.5)
    xs = np.arange(400, dtype=np.float32)[None, :].repeat(160, 0)
    ys = np.arange(160, dtype=np.float32)[:, None].repeat(400, 1)
    ratios = []
    for true_d, noise in ((7.3, 1.0), (7.5, 3.0), (4.25, 2.0)):
        left = tex + rng.normal(0, noise, tex.shape).astype(np.float32)
        # right(x) = tex(x + d), so right(x - d) = left(x) but for the noise
        right = cv2.remap(tex, xs + np.float32(true_d), ys, cv2.INTER_CUBIC) + \
            rng.normal(0, noise, tex.shape).astype(np.float32)
        est = refine_subpixel(left, right, np.full(tex.shape, np.float32(true_d + 0.1)), radius=3, iterations=1)
        sig = disparity_sigma(left, right, est, floor_px=0.0)
        core = (slice(20, -20), slice(30, -30))
        err = (est - true_d)[core]
        ratios.append(float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(sig[core] ** 2))))
    assert all(0.8 <= r <= 1.25 for r in ratios), ratios
    # identical photos: the floor alone
    assert_allclose(disparity_sigma(tex, tex, np.full(tex.shape, 0.0), floor_px=0.05)[20:-20, 20:-20], 0.05,
                    atol=1e-3)
    with pytest.raises(ShapeError):
        disparity_sigma(np.zeros((4, 4)), np.zeros((5, 4)), np.zeros((4, 4)))
    with pytest.raises(InvalidInputError, match="radius"):
        disparity_sigma(np.zeros((4, 4)), np.zeros((4, 4)), np.zeros((4, 4)), radius=0)


def test_point_sigma_field_takes_the_median_of_the_nearest():
    xy = np.array([[0, 0], [1, 0], [0, 1], [10, 10], [11, 10], [10, 11]], float)
    s = np.array([0.1, 0.2, 0.3, 1.0, 2.0, np.nan])
    f = PointSigmaField.from_points(xy, s, k=3)
    assert_allclose(f([[0.2, 0.2], [10.4, 10.3], [2, 3]]), [0.2, 1.0, 0.2])   # the NaN row left out
    assert f.median == 0.3
    with pytest.raises(InvalidInputError, match="no point with a finite"):
        PointSigmaField.from_points(xy[:1], [np.nan])
    with pytest.raises(ShapeError, match="one value per point"):
        PointSigmaField.from_points(xy, s[:2])


# --------------------------------------------------------------------------- the rendered block
@pytest.fixture(scope="module")
def surface_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("surface")
    blk = make_surface_block(root / "block", strips=3, per_strip=4, supersample=1)
    res = run_surface(blk.folder, root / "out", options=SurfaceOptions(ground_z=Z0))
    return blk, res, root


def test_block_dsm_accuracy_and_calibrated_sigma(surface_run):
    blk, res, root = surface_run
    bands, tr, desc = read_dsm(root / "out" / "dsm.tif")
    h, s, count, prov = bands
    err = h - truth_on(tr, h.shape, blk.terrain)
    ok = np.isfinite(err)
    assert ok.sum() > 50_000
    rmse = float(np.sqrt(np.mean(err[ok] ** 2)))
    assert rmse <= 0.5 * GSD, rmse
    z = err[ok] / s[ok]
    assert 0.67 <= float(np.sqrt(np.mean(z ** 2))) <= 1.5
    q = np.quantile(s[ok], np.linspace(0, 1, 11))
    for i in range(10):
        m = (s[ok] >= q[i]) & (s[ok] <= q[i + 1])
        assert 0.67 <= float(np.sqrt(np.mean(z[m] ** 2))) <= 1.5, (i, q[i])
    # the grid on whole multiples of the cell, the bands described, count and provenance consistent
    assert tr.a == res.cell and math.isclose(tr.c / res.cell, round(tr.c / res.cell), abs_tol=1e-9)
    assert desc[0].startswith("height") and desc[1].startswith("sigma_z") and desc[2].startswith("count") \
        and desc[3].startswith("provenance")
    assert (count[ok] >= 1).all() and (count[~ok] == 0).all()
    assert (prov[~ok] == -1).all() and set(np.unique(prov[ok]).astype(int)) <= set(range(len(res.pairs)))
    assert (count[ok] >= 2).mean() > 0.2
    doc = json.loads((root / "out" / "pairs.json").read_text())
    assert [(p["left"], p["right"]) for p in doc["pairs"]] == [(p.left, p.right) for p in res.pairs]
    assert all(p["points"] > 1000 for p in doc["pairs"])
    assert doc["summary"]["variance_factor"] >= 1.0


def _pose_doc(folder, names_positions):
    poses = [Pose(n, "cam", np.array(c, float), matrix_from_angles(0.0, 0.0, 0.0)) for n, c in names_positions]
    (folder / "orientation.json").write_text(block_orientation_text({"cam": CAMERA}, poses), encoding="utf-8")


def test_bad_input_names_the_problem_and_leaves_nothing(surface_run, tmp_path):
    blk, _res, _root = surface_run
    out = tmp_path / "out"
    # an orientation folder without its images
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "orientation.json").write_text((blk.folder / "orientation.json").read_text())
    with pytest.raises(InvalidInputError, match=r"image 'img_1_1.png' of the block orientation is not in"):
        run_surface(tmp_path / "o", out, options=SurfaceOptions(ground_z=Z0))
    # images given in a folder that misses one
    with pytest.raises(InvalidInputError, match="image 'img_1_1.png'"):
        run_surface(tmp_path / "o", out, options=SurfaceOptions(ground_z=Z0, images=str(tmp_path)))
    # a DSM cell smaller than a tenth of the ground pixel
    with pytest.raises(InvalidInputError, match=r"DSM cell 0.01 is smaller than a tenth of the ground pixel"):
        run_surface(blk.folder, out, options=SurfaceOptions(ground_z=Z0, cell=0.01))
    # no stereo overlap: two images side by side with no common ground
    (tmp_path / "far").mkdir()
    _pose_doc(tmp_path / "far", [("img_1_1.png", (0, 0, 150)), ("img_1_2.png", (200, 0, 150))])
    with pytest.raises(StereoError, match=r"no stereo pair passes the thresholds .* the best pair: img_1_1.png \+ "
                                          r"img_1_2.png: overlap 0%"):
        run_surface(tmp_path / "far", out, options=SurfaceOptions(ground_z=Z0, images=str(blk.images)))
    # no points.csv and no --ground-z
    with pytest.raises(InvalidInputError, match="pass --ground-z"):
        run_surface(blk.folder, out)
    assert not out.exists()
    with pytest.raises(InvalidInputError, match="orientation not found"):
        run_surface(tmp_path / "none.json", out)
    with pytest.raises(InvalidInputError, match="`min_overlap` must be"):
        SurfaceOptions(min_overlap=0)
    with pytest.raises(InvalidInputError, match="`orientation_sigma` must be one of"):
        SurfaceOptions(orientation_sigma="bundle")
    with pytest.raises(InvalidInputError, match="the block has no points.csv with standard errors"):
        run_surface(blk.folder, out, options=SurfaceOptions(ground_z=Z0, orientation_sigma="points"))
    assert not out.exists()
