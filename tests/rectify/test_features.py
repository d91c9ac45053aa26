"""Tie points: detector bias (rotated-copy experiment), refinement gain on known homographies,
real aerial pair against its known epipolar geometry, tiled coarse-to-fine, masks, bad input."""

from __future__ import annotations

import sys
from pathlib import Path

import affine
import cv2
import numpy as np
import pytest
import skimage.data as skd
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import EstimationError, InvalidInputError, RasterIOError
from rectify.features import (
    DETECTORS,
    MatcherConfig,
    akaze_available,
    detect,
    grid_select,
    match_arrays,
    match_descriptors,
    match_images,
    verify_matches,
)
from rectify.raster import io as rio

ROOT = Path(__file__).resolve().parents[2]


def _grey() -> np.ndarray:
    return cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)


IMAGES = {
    "uint8-grey": lambda: _grey()[50:450, 30:487],                       # odd width on purpose
    "uint8-rgb": lambda: skd.astronaut()[10:401, 20:500],
    "uint16": lambda: skd.camera()[:411, :397].astype(np.uint16) * 200 + 1000,
    "float32-4band": lambda: np.dstack([skd.astronaut()[:380, :420].astype(np.float32) / 255.0,
                                        np.ones((380, 420), np.float32)]),
}


def _detectors():
    return [pytest.param(d, marks=pytest.mark.skipif(d == "akaze" and not akaze_available(),
                                                     reason="AKAZE not in this OpenCV build"))
            for d in DETECTORS]


def _apply(H, p):
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:]


# ---------------------------------------------------------------- detector bias (issue 8)
@pytest.mark.parametrize("refine", [False, True], ids=["raw", "refined"])
@pytest.mark.parametrize("kind", list(IMAGES))
@pytest.mark.parametrize("detector", _detectors())
def test_rotated_copy_has_no_systematic_offset(detector, kind, refine):
    """An image against its 180-degree rotation: the truth is x' = W-1-x, y' = H-1-y exactly. (Without turning
    the right image back: turned back, it would be matched against itself, and any offset would cancel.)"""
    img = IMAGES[kind]()
    h, w = img.shape[:2]
    rot = img[::-1, ::-1].copy()
    cfg = MatcherConfig(detector=detector, verify="homography", refine=refine, max_matches=1000, derotate=False)
    r = match_arrays(img, rot, config=cfg)
    assert len(r.matches) > 100
    off = (r.matches.left + r.matches.right - [w - 1, h - 1]) / 2.0   # per-match offset of one image
    assert np.abs(off.mean(axis=0)).max() <= 0.02, off.mean(axis=0)
    assert np.abs(np.median(off, axis=0)).max() <= 0.02


def test_rotated_copy_offset_is_visible_without_correction():
    """Guard that the experiment detects a bias: raw OpenCV SIFT is 0.25 px off in x and y."""
    img = IMAGES["uint8-grey"]()
    h, w = img.shape
    s = cv2.SIFT.create()
    k1, d1 = s.detectAndCompute(img, None)
    k2, d2 = s.detectAndCompute(img[::-1, ::-1].copy(), None)
    m = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(d1, d2)
    tot = np.array([k1[x.queryIdx].pt for x in m]) + np.array([k2[x.trainIdx].pt for x in m]) - [w - 1, h - 1]
    good = np.linalg.norm(tot, axis=1) < 3
    np.testing.assert_allclose(np.median(tot[good], axis=0) / 2, [0.25, 0.25], atol=0.01)
    f = detect(img)
    raw = np.array([k.pt for k in s.detect(img, None)])
    # our positions are OpenCV's minus 0.25 (same keypoints, so the set of x - 0.25 must appear)
    assert np.isin(np.round(f.xy[:50, 0] + 0.25, 3), np.round(raw[:, 0], 3)).all()


def test_akaze_unavailable_raises_clear_error():
    if akaze_available():
        pytest.skip("this OpenCV has AKAZE")
    with pytest.raises(InvalidInputError, match="akaze.*not available"):
        detect(_grey(), detector="akaze")


# ---------------------------------------------------------------- refinement gain (issue 8)
HOMOGRAPHIES = [
    np.array([[0.9, 0.15, 20], [-0.12, 0.95, 30], [2e-4, -1e-4, 1.0]]),
    np.array([[np.cos(0.5) * 1.1, -np.sin(0.5) * 1.1, 150], [np.sin(0.5) * 1.1, np.cos(0.5) * 1.1, -100],
              [1e-4, 2e-4, 1]]),
]


def _synthetic_pair(H, seed):
    rng = np.random.default_rng(seed)
    base = _grey().astype(np.float32)
    right = cv2.warpPerspective(base, H, (512, 512), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=np.nan)
    valid = np.isfinite(right)
    noise = rng.normal(0, 2, size=np.shape(right)).astype(np.float32)
    right = np.asarray(cv2.GaussianBlur(np.nan_to_num(right), (0, 0), 0.8)) + noise
    left = cv2.GaussianBlur(base, (0, 0), 0.5) + rng.normal(0, 2, base.shape).astype(np.float32)
    return left, right, valid


@pytest.mark.parametrize("k", range(len(HOMOGRAPHIES)))
def test_refinement_halves_position_error_on_known_homography(k):
    H = HOMOGRAPHIES[k]
    left, right, valid = _synthetic_pair(H, seed=k + 1)
    err = {}
    for refine in (False, True):
        # keep_unrefined=False: the refined positions only (failures kept unrefined are the default)
        r = match_arrays(left, right, right_valid=valid, config=MatcherConfig(refine=refine, keep_unrefined=False))
        e = np.linalg.norm(_apply(H, r.matches.left) - r.matches.right, axis=1)
        err[refine] = float(np.sqrt(np.mean(e ** 2)))
        assert len(e) > 200
        if refine:
            assert r.n_refined >= len(r.matches)
            assert r.matches.score is not None
            assert np.isfinite(r.matches.score).all() and (r.matches.score < 0.5).all()
            assert r.rmse_px < r.rmse_raw_px
    assert err[True] <= 0.5 * err[False], err


# ---------------------------------------------------------------- real aerial pair (issue 3)
def _ngi():
    sys.path.insert(0, str(ROOT / "scripts"))
    import ngi_geometry

    return ngi_geometry


@pytest.mark.shared
def test_ngi_pair_matches_cover_overlap_and_fit_known_geometry(ngi_pair):
    g = _ngi()
    F = g.fundamental()
    left = ngi_pair / "3324c_2015_1004_05_0182_RGB.tif"
    right = ngi_pair / "3324c_2015_1004_05_0184_RGB.tif"
    med = {}
    for refine in (False, True):
        r = match_images(left, right, config=MatcherConfig(verify="fundamental", refine=refine))
        s = g.sampson(F, r.matches.left, r.matches.right)
        med[refine] = float(np.median(s))
        assert med[refine] <= 0.5, med
        assert len(r.matches) > 300
    assert med[True] < med[False]
    # coverage: 64-px cells of the overlap (known geometry, ground at 400 m) holding a match
    step = 8
    ov = g.left_overlap_mask(z=400.0, step=step)
    cell = 64 // step
    hc, wc = ov.shape[0] // cell, ov.shape[1] // cell
    frac = ov[:hc * cell, :wc * cell].reshape(hc, cell, wc, cell).mean(axis=(1, 3))
    full = frac >= 0.99                                   # cells entirely inside the overlap
    hit = np.zeros((hc, wc), bool)
    ij = (r.matches.left // 64).astype(int)
    ok = (ij[:, 0] < wc) & (ij[:, 1] < hc)
    hit[ij[ok, 1], ij[ok, 0]] = True
    assert full.sum() >= 20
    assert hit[full].mean() >= 0.9, hit[full].mean()


# ---------------------------------------------------------------- tiled coarse-to-fine
def _texture_image(h, w, seed=0):
    tile = skd.astronaut()
    reps = (h // tile.shape[0] + 2, w // tile.shape[1] + 2, 1)
    big = np.tile(tile, reps)
    rng = np.random.default_rng(seed)
    # break the periodicity: random flips of 128-px blocks
    out = big[:h, :w].copy()
    for r in range(0, h, 128):
        for c in range(0, w, 128):
            b = out[r:r + 128, c:c + 128]
            if rng.random() < 0.5:
                out[r:r + 128, c:c + 128] = b[::-1]
            if rng.random() < 0.5:
                out[r:r + 128, c:c + 128] = out[r:r + 128, c:c + 128][:, ::-1]
    return out


def test_tiled_matching_recovers_known_homography_with_nodata(tmp_path):
    h, w = 700, 900
    img = _texture_image(h, w)
    H = np.array([[0.97, 0.05, 25.0], [-0.04, 1.01, -12.0], [1e-5, -2e-5, 1.0]])
    warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_CUBIC)
    valid_r = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST) > 0
    valid_l = np.ones((h, w), bool)
    valid_l[:, :150] = False                               # nodata strip in the left image
    lp, rp = tmp_path / "l.tif", tmp_path / "r.tif"
    rio.write_raster(lp, img, affine.Affine.identity(), None, nodata=0, valid=valid_l)
    rio.write_raster(rp, warped, affine.Affine.identity(), None, nodata=0, valid=valid_r)
    cfg = MatcherConfig(tiled_above_px=400, tile_px=256, overlap_px=24, overview_px=320, max_keypoints=3000)
    ticks = []
    r = match_images(lp, rp, config=cfg, progress=lambda d, t: ticks.append((d, t)))
    assert r.tiled
    assert ticks and ticks[-1][0] == ticks[-1][1]
    assert len(r.matches) > 300
    e = np.linalg.norm(_apply(H, r.matches.left) - r.matches.right, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.3
    assert r.matches.left[:, 0].min() > 150 - 1               # nothing from the nodata strip
    assert r.verification.matrix is not None
    Hn = r.verification.matrix / r.verification.matrix[2, 2]
    corners = np.array([[200, 0], [w - 1, 0], [200, h - 1], [w - 1, h - 1]], float)
    assert np.abs(_apply(Hn, corners) - _apply(H, corners)).max() < 0.5
    # spread: every 128-px cell of the valid left area has matches
    ij = (r.matches.left // 128).astype(int)
    cells = {tuple(x) for x in ij}
    need = {(i, j) for i in range(2, w // 128) for j in range(h // 128)}
    assert len(need - cells) <= 2


def test_whole_and_any_dtype_file_input(tmp_path):
    img = (IMAGES["uint16"]()).astype(np.uint16)
    h, w = img.shape
    H = np.array([[1.0, 0.02, 5.0], [-0.02, 1.0, 3.0], [0, 0, 1.0]])
    warped = cv2.warpPerspective(img.astype(np.float32), H, (w, h), flags=cv2.INTER_CUBIC)
    lp, rp = tmp_path / "l.tif", tmp_path / "r.tif"
    rio.write_raster(lp, img, affine.Affine.identity(), None)
    rio.write_raster(rp, warped, affine.Affine.identity(), None)
    r = match_images(lp, rp)
    assert not r.tiled and len(r.matches) > 100
    e = np.linalg.norm(_apply(H, r.matches.left) - r.matches.right, axis=1)
    assert np.median(e) < 0.2


# ---------------------------------------------------------------- building blocks
def test_grid_select_caps_cells_and_budget():
    rng = np.random.default_rng(0)
    xy = np.r_[rng.uniform(0, 50, (5000, 2)), rng.uniform(0, 1000, (500, 2))]   # a dense cluster
    resp = rng.random(len(xy))
    keep = grid_select(xy, resp, (1000, 1000), 400, cell_cap=4)
    assert len(keep) <= 400
    # the cluster cannot take the whole budget: most kept points lie outside it
    assert (xy[keep] > 50).any(axis=1).mean() > 0.8
    assert len(grid_select(xy[:10], resp[:10], (1000, 1000), 400)) == 10


@settings(max_examples=25, deadline=None)
@given(n=st.integers(0, 3000), budget=st.integers(1, 500), cap=st.integers(1, 8))
def test_grid_select_property(n, budget, cap):
    rng = np.random.default_rng(n)
    xy = rng.uniform(-0.5, 299.5, (n, 2))
    keep = grid_select(xy, rng.random(n), (300, 300), budget, cell_cap=cap)
    assert len(keep) <= budget and len(np.unique(keep)) == len(keep)
    if n <= budget:
        assert len(keep) == n


def test_match_descriptors_mutual_one_to_one():
    img = _grey()
    f1 = detect(img, max_keypoints=2000)
    f2 = detect(img[::-1].copy(), max_keypoints=2000)
    p = match_descriptors(f1, f2, ratio=0.8, mutual=True)
    assert len(np.unique(p.right)) == len(p.right) and len(np.unique(p.left)) == len(p.left)
    assert (p.ratio < 0.8).all()
    p_nm = match_descriptors(f1, f2, ratio=0.8, mutual=False)
    assert len(p_nm.left) >= len(p.left)


def test_verify_fundamental_residual_table_is_sampson():
    rng = np.random.default_rng(2)
    K = np.array([[800, 0, 320], [0, 800, 240], [0, 0, 1.0]])
    X = np.c_[rng.uniform(-5, 5, (200, 2)), rng.uniform(15, 30, 200)]
    R = cv2.Rodrigues(np.array([0.02, -0.1, 0.03]))[0]
    t = np.array([-1.0, 0.1, 0.05])
    pl = (X @ K.T)[:, :2] / X[:, 2:]
    Xr = X @ R.T + t
    pr = (Xr @ K.T)[:, :2] / Xr[:, 2:]
    pr_noisy = pr + rng.normal(0, 0.2, pr.shape)
    pr_noisy[:20] += 25                                          # outliers
    v = verify_matches(pl, pr_noisy, method="fundamental", threshold_px=1.0)
    assert not v.inliers[:20].any() and v.inliers[20:].mean() > 0.9
    assert v.table is not None
    assert v.table.components == ("dx_left", "dy_left", "dx_right", "dy_right")
    np.testing.assert_allclose(v.table.norm, v.errors_px, rtol=1e-9)
    assert v.rmse_px < 0.3


def test_inputs_not_modified():
    img = IMAGES["uint8-rgb"]()
    rot = img[::-1, ::-1].copy()
    a, b = img.copy(), rot.copy()
    match_arrays(img, rot)
    np.testing.assert_array_equal(img, a)
    np.testing.assert_array_equal(rot, b)


# ---------------------------------------------------------------- bad input
def test_blank_image_raises():
    blank = np.full((300, 300), 77, np.uint8)
    with pytest.raises(EstimationError, match="blank"):
        match_arrays(_grey()[:300, :300], blank)


def test_non_overlapping_images_raise():
    a = _grey()
    b = skd.coffee()
    with pytest.raises(EstimationError, match="do not overlap"):
        match_arrays(a, b)


def test_unreadable_file_raises(tmp_path):
    p = tmp_path / "junk.tif"
    p.write_text("not an image")
    with pytest.raises(RasterIOError):
        match_images(p, p)
    with pytest.raises(RasterIOError, match="not found"):
        match_images(tmp_path / "missing.tif", p)


def test_bad_options():
    with pytest.raises(InvalidInputError, match="unknown detector 'surf'"):
        MatcherConfig(detector="surf")
    with pytest.raises(InvalidInputError, match="unknown verification 'affine'"):
        MatcherConfig(verify="affine")
    with pytest.raises(InvalidInputError, match="max_matches"):
        MatcherConfig(max_matches=0)
    with pytest.raises(InvalidInputError, match="ratio"):
        MatcherConfig(ratio=1.5)
    with pytest.raises(InvalidInputError, match="threshold_px"):
        MatcherConfig(threshold_px=-1)
    with pytest.raises(InvalidInputError, match="shape"):
        detect(np.zeros((4, 4)))
    with pytest.raises(InvalidInputError, match="valid"):
        detect(_grey(), valid=np.ones((3, 3), bool))
    with pytest.raises(EstimationError, match="at least 8"):
        verify_matches(np.zeros((5, 2)), np.zeros((5, 2)), method="fundamental")
    with pytest.raises(InvalidInputError, match="unknown verification"):
        verify_matches(np.zeros((5, 2)), np.zeros((5, 2)), method="x")


@pytest.mark.shared
def test_ngi_relative_orientation_parallax_lower_with_refined_matches(ngi_pair):
    import stereo.relative  # noqa: F401  (must exist: the RO parallax comparison of issue 8)
    sys.path.insert(0, str(ROOT / "scripts"))
    import ngi_refinement

    out = ngi_refinement.compare(ngi_pair)
    assert out["refined"]["ro_converged"] and out["raw"]["ro_converged"]
    assert out["refined"]["ro_rms_parallax_px"] < out["raw"]["ro_rms_parallax_px"]
    # like for like: the same points with their raw positions
    assert out["refined"]["ro_rms_parallax_px"] < out["raw_same_points"]["ro_rms_parallax_px"]
    assert out["refined"]["sampson_median_px"] < out["raw_same_points"]["sampson_median_px"]


def test_sparse_tiled_search_bounds_tiles_and_spreads(tmp_path):
    h, w = 700, 900
    img = _texture_image(h, w, seed=3)
    H = np.array([[0.99, -0.08, 40.0], [0.08, 0.99, -20.0], [0, 0, 1.0]])
    warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_CUBIC)
    valid_r = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST) > 0
    lp, rp = tmp_path / "l.tif", tmp_path / "r.tif"
    rio.write_raster(lp, img, affine.Affine.identity(), None)
    rio.write_raster(rp, warped, affine.Affine.identity(), None, nodata=0, valid=valid_r)
    # 4 x 3 tiles of 256 > max_tiles = 3: sparse search with 128-px tiles, at most 9 of them
    cfg = MatcherConfig(tiled_above_px=400, tile_px=256, overlap_px=24, overview_px=320, max_tiles=3,
                        max_matches=400)
    ticks = []
    r = match_images(lp, rp, config=cfg, progress=lambda d, t: ticks.append(t))
    assert r.tiled and ticks[-1] <= 9
    assert len(r.matches) >= 100
    e = np.linalg.norm(_apply(H, r.matches.left) - r.matches.right, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.3
    # the searched tiles are spread over the image: matches in every third of it, both axes
    for ax, size in ((0, w), (1, h)):
        thirds = np.bincount((r.matches.left[:, ax] * 3 // size).astype(int), minlength=3)
        assert (thirds > 0).all(), thirds
