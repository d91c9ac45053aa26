"""Issue 30, dense matching: the hole pass, the sub-pixel window, the depth-edge classification, the
strip-wise post-processing, and the real-data figures with tolerances.

Figures measured with ``nice python scripts/bench_dense.py`` (docs/dense.md, "Figures measured"); the
tolerances leave room for OpenCV's thread scheduling and the shared machine, not for a lost method.
The shared-data tests skip when ``../shared/data`` (``$RECTIFY_SHARED_DATA``) is absent.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import rasterio

import stereo.dense.checks as checks
from rectify.errors import InvalidInputError, ShapeError
from stereo.actions.dense import DenseOptions, run_dense
from stereo.dense.checks import row_tests
from stereo.dense.holes import RANGE_MARGIN, hole_boxes
from stereo.dense.matching import MatchOptions, _fill_holes_half, match_pair
from stereo.dense.refine import edge_classify, median_valid
from tests.support.ngi_pair import write_ngi_exteriors
from tests.support.shared_data import SHARED_DATA
from tests.support.stereo_support import occlusion_from_truth, read_grey, read_rgb


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 1.2)
    return np.clip(128 + 60 * t / t.std(), 0, 255).astype(np.uint8)


def _pair(d: float, flat: tuple[slice, slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A textured plane at disparity ``d`` (left(x) = right(x - d)); ``flat``: a constant patch in both."""
    H, W = 120, 200
    src = _texture(H, W + 40, 4)
    if flat is not None:
        src[flat] = 128
    xs = np.arange(W)[None, :].repeat(H, 0).astype(np.float32)
    ys = np.arange(H)[:, None].repeat(W, 1).astype(np.float32)
    L = np.ascontiguousarray(src[:, 20:W + 20])
    R = cv2.remap(src, xs + 20 + d, ys, cv2.INTER_CUBIC)
    return L, np.asarray(R)


def test_hole_pass_fills_a_large_textured_hole_with_the_right_disparity():
    """A 50 x 64 hole punched into a correct disparity map of a textured plane (d = 11.5 px) is filled
    by the half-resolution pass to within 1 px (before the sub-pixel step); a 20 x 20 hole (100
    half-resolution px, below ``MIN_HOLE``) is left; every pixel that had a disparity keeps it, bit
    for bit, and the masks are not changed."""
    L, R = _pair(11.5)
    H, W = L.shape
    d = np.full((H, W), 11.5, np.float32)
    d[35:85, 70:134] = np.nan
    d[5:25, 160:180] = np.nan
    before = d.copy()
    ones = np.ones((H, W), bool)
    out = _fill_holes_half(d, L, R, ones, ones, 0, 24, MatchOptions(hole_p2=128.0))
    hole = out[35:85, 70:134]
    assert np.isfinite(hole).mean() >= 0.9, np.isfinite(hole).mean()  # measured 0.96
    assert np.nanmax(np.abs(hole - 11.5)) <= 1.0, np.nanmax(np.abs(hole - 11.5))
    assert np.isnan(out[5:25, 160:180]).all()
    had = np.isfinite(before)
    assert np.array_equal(out[had], before[had]) and ones.all()
    assert np.isnan(_fill_holes_half(before.copy(), L, R, ones, ones, 0, 24, MatchOptions())[35:85, 70:134]).all()


def test_hole_pass_leaves_a_textureless_hole_empty():
    """Where both photos are constant nothing can be matched: the ZNCC test keeps such a hole empty
    (SGBM's own paths carry a disparity into it; the hole pass adds none)."""
    L, R = _pair(11.5, (slice(25, 95), slice(80, 170)))  # constant in the left photo at cols 60..150
    H, W = L.shape
    d = np.full((H, W), 11.5, np.float32)
    d[35:85, 70:134] = np.nan
    ones = np.ones((H, W), bool)
    out = _fill_holes_half(d, L, R, ones, ones, 0, 24, MatchOptions(hole_p2=128.0))
    assert not np.isfinite(out[35:85, 70:134]).any()
    res = match_pair(L, R, disparity_range=(0, 24), options=MatchOptions(hole_p2=128.0))
    assert np.abs(res.disparity[res.valid] - 11.5).max() < 1.0 and res.density > 0.5


def test_hole_boxes_skip_the_left_edge_band_and_small_holes():
    """The holes' boxes (half resolution): the band at the window's left edge whose matches lie beyond
    the right photo's edge (x - d < 4 px, the right window's first usable column) is no hole, though
    large enough; a 40 x 60 hole is one box covering it, with the range of the disparities around it
    (10 and 30 px) widened by ``RANGE_MARGIN``; a 10 x 10 hole (25 half-resolution px) is one only
    when ``min_hole`` allows."""
    H, W = 200, 240
    d = np.full((H, W), 10.0, np.float32)
    d[:, 120:] = 30.0
    d[60:100, 100:160] = np.nan
    d[10:20, 200:210] = np.nan
    band = d.copy()
    band[:, :12] = np.nan  # 600 half-resolution px
    labels, boxes = hole_boxes(~np.isfinite(band), band, 0, 40, 4)
    assert labels.shape == (H // 2, W // 2) and len(boxes) == 1
    _, y0, y1, x0, x1, dl, dh = (int(v) for v in boxes[0])
    assert (y0, y1, x0, x1) == (30, 50, 50, 80)
    assert (dl, dh) == (10 - RANGE_MARGIN, 30 + RANGE_MARGIN)
    assert len(hole_boxes(~np.isfinite(band), band, 0, 40, 4, min_hole=20)[1]) == 2
    # a band whose pixels can be matched (x - d >= 4 from x = 14 on) is a hole
    band[:, :40] = np.nan
    assert len(hole_boxes(~np.isfinite(band), band, 0, 40, 4)[1]) == 2


def test_hole_pass_changes_nothing_away_from_the_pixels_it_fills():
    """Motorcycle with and without the hole pass: disparity and confidence are equal, bit for bit,
    farther than 24 px (the post-processing's reach: depth-edge step 12, median 1, sub-pixel step 7,
    confidence 1) from every pixel the hole pass added; it adds some."""
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    a = match_pair(left, right)
    b = match_pair(left, right, options=MatchOptions(hole_p2=128.0))
    added = b.valid & ~a.valid
    assert added.sum() > 1000, added.sum()
    near = cv2.dilate(added.astype(np.uint8), np.ones((49, 49), np.uint8)) > 0
    assert (~near).mean() > 0.3
    assert np.array_equal(a.disparity[~near], b.disparity[~near], equal_nan=True)
    assert np.array_equal(a.confidence[~near], b.confidence[~near])


def test_hole_options_bad_input():
    for kw, msg in ((dict(hole_p2=-1.0), "hole_p2"), (dict(hole_p2=float("nan")), "hole_p2"),
                    (dict(hole_p2=4.0), "hole_p2` must exceed"), (dict(hole_zncc=1.5), "hole_zncc"),
                    (dict(hole_p2=True), "hole_p2"), (dict(hole_zncc="0.3"), "hole_zncc")):
        with pytest.raises(InvalidInputError, match=msg):
            MatchOptions(**kw)
    assert DenseOptions().matching.hole_p2 == 128.0 and MatchOptions().hole_p2 == 0.0


def test_refine_window_default():
    """The sub-pixel step's window (issue 30: radius 6, was 3) and its result on a plane: unbiased."""
    assert MatchOptions().refine_radius == 6
    L, R = _pair(11.3)
    res = match_pair(L, R, disparity_range=(0, 24))
    e = res.disparity[res.valid] - 11.3
    assert abs(float(np.median(e))) < 0.03 and float(np.percentile(np.abs(e), 95)) < 0.15


def _edge_scene(seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bright textured square (disparity 20) on a dark textured ground (disparity 10): the grey
    photo, the true disparity and a disparity fattened by 3 px around the square (as SGM leaves it)."""
    rng = np.random.default_rng(seed)
    H, W = 80, 120
    near = np.zeros((H, W), bool)
    near[25:55, 40:80] = True
    grey = np.where(near, 180, 60) + rng.normal(0, 8, (H, W))
    grey = np.clip(grey, 0, 255).astype(np.uint8)
    truth = np.where(near, 20.0, 10.0).astype(np.float32) + rng.uniform(-0.3, 0.3, (H, W)).astype(np.float32)
    fat = cv2.dilate(near.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    d = np.where(fat, np.where(near, truth, 20.0), truth).astype(np.float32)
    return grey, truth, d


def test_edge_classify_moves_a_fattened_edge_onto_the_photo_edge():
    """The 3-px band of near disparity around the square goes back to the ground's (at least 95 % of it
    within 0.5 px of the truth; the rest, isolated pixels, is what the 3 x 3 median after it removes);
    no pixel is made worse, the pixels away from the edge and the NaN are unchanged."""
    grey, truth, d = _edge_scene()
    d[5, 5] = np.nan
    band = (d - truth) > 5
    assert band.sum() > 300
    out = edge_classify(d, grey, radius=4)
    assert np.isnan(out[5, 5])
    ok = np.abs(out - truth)[band] < 0.5
    assert ok.mean() >= 0.95, ok.mean()
    # a ground pixel whose grey is 2-3 sigma off the ground's can join the near surface (whose grey
    # spread, band and square, is wide): isolated pixels, which the 3 x 3 median then removes
    worse = np.abs(out - truth) > np.abs(d - truth) + 0.5
    assert worse.sum() <= 3, worse.sum()
    far = cv2.dilate(band.astype(np.uint8), np.ones((19, 19), np.uint8)) == 0
    assert np.array_equal(out[far & np.isfinite(d)], d[far & np.isfinite(d)])
    med = median_valid(out)
    assert (np.abs(med - truth) > 0.5)[band].sum() <= 2  # of 456: corners of the square
    off, off0 = (np.abs(med - truth) > 0.5).sum(), (np.abs(median_valid(d) - truth) > 0.5).sum()
    assert off0 > 300 and off <= 0.03 * off0, (off, off0)  # with the median alone: the whole band (8 of 457)
    assert np.array_equal(edge_classify(d, grey, radius=0), d, equal_nan=True)
    assert edge_classify(d, grey, radius=4) is not d and np.isnan(d[5, 5])  # the input is not changed


def test_edge_classify_leaves_a_slanted_surface_and_a_true_edge_unchanged():
    """No jump above 2 px in any window: nothing changes; a correct depth edge stays where the photo's is."""
    grey, truth, _ = _edge_scene(4)
    slope = (np.arange(120, dtype=np.float32)[None, :] * 0.02 + np.zeros((80, 1), np.float32))
    assert np.array_equal(edge_classify(slope, grey), slope)
    out = edge_classify(truth, grey)
    assert (np.abs(out - truth) > 1).sum() == 0


def test_edge_classify_bad_input():
    grey, _, d = _edge_scene()
    with pytest.raises(ShapeError, match="one shape"):
        edge_classify(d, grey[:, :-1])
    with pytest.raises(ShapeError, match="one shape"):
        edge_classify(d[0], grey[0])
    for kw in ({"radius": -1}, {"radius": 2.5}, {"strip": 0}, {"noise": 0.0}, {"jump": float("nan")}):
        with pytest.raises(InvalidInputError, match=next(iter(kw))):
            edge_classify(d, grey, **kw)


def test_edge_radius_option_bad_input():
    for v in (-1, 1.5, True):
        with pytest.raises(InvalidInputError, match="edge_radius"):
            MatchOptions(edge_radius=v)  # type: ignore[arg-type]
    assert MatchOptions().edge_radius == 4


def test_strips_give_the_whole_window_result(monkeypatch):
    """The post-processing by strips of rows (halo rows either side) equals the whole window's, bit for bit."""
    L, R = _pair(11.3)
    whole = match_pair(L, R, disparity_range=(0, 24), options=MatchOptions(hole_p2=128.0))
    monkeypatch.setattr(checks, "_STRIP_PX", 16 * 200)  # strips of 16 rows
    assert checks.strip_rows(200) == 16
    strips = match_pair(L, R, disparity_range=(0, 24), options=MatchOptions(hole_p2=128.0))
    assert np.array_equal(whole.disparity, strips.disparity, equal_nan=True)
    assert np.array_equal(whole.confidence, strips.confidence)
    rows = checks.strips(100, 3, 200)
    assert rows[0][0] == 0 and rows[-1][1] == 100 and all(a[1] == b[0] for a, b in zip(rows, rows[1:], strict=False))
    assert all(a0 == max(0, r0 - 3) and a1 == min(100, r1 + 3) for r0, r1, a0, a1 in rows)


def test_row_tests_column_interval_equals_the_lookup():
    """The border rule as a column interval (nodata only beyond the right photo's edges) gives the same
    disparities as the pixel-by-pixel lookup."""
    rng = np.random.default_rng(5)
    raw = rng.integers(-16, 40 * 16, (20, 90)).astype(np.int16)
    lve = np.ones((20, 90), bool)
    rve = np.zeros((20, 90), bool)
    rve[:, 7:71] = True
    a = row_tests(raw, lve, rve, None, 1.0, 1)
    b = row_tests(raw, lve, rve, None, 1.0, 1, (7, 70))
    assert np.array_equal(a, b, equal_nan=True) and np.isfinite(a).sum() > 100


def test_motorcycle_precision_not_below_the_recorded_figure():
    """Motorcycle: bad-2.0 2.31 % at 95.9 % density measured (2.29 % at the previous density, the most
    confident pixels; 2.60 % before the depth-edge classification, 2.64 % before issue 30; the issue
    asks <= 2.38 %)."""
    from skimage import data

    left, right, gt = data.stereo_motorcycle()
    res = match_pair(left, right)
    m = ~occlusion_from_truth(gt)
    v = res.valid & m
    err = (np.abs(res.disparity - gt) > 2)[v]
    density, bad2 = v.sum() / m.sum(), err.mean()
    assert density >= 0.955 and bad2 <= 0.0245, (density, bad2)
    top = np.argsort(-res.confidence[v], kind="stable")[:int(round(0.959 * m.sum()))]
    assert err[top].mean() <= 0.0238, err[top].mean()


@pytest.mark.shared
def test_cones_precision_at_the_previous_density():
    """Cones: bad-1.0 2.59 % at 95.3 % density; at the previous round's density (93.2 %, the most
    confident pixels) 2.11 % (2.26 % before the depth-edge classification, 2.76 % before issue 30)."""
    d = SHARED_DATA / "dense_cones"
    if not d.is_dir():
        pytest.skip(f"shared data absent: {d}")
    L = read_rgb(d / "left.png")
    R = read_rgb(d / "right.png")
    with rasterio.open(d / "disp_left.tif") as ds:
        gt = ds.read(1)
    nocc = (read_grey(d / "occlusion.png") > 0) & (gt > 0)
    res = match_pair(L, R)
    v = res.valid & nocc
    err = (np.abs(res.disparity - gt) > 1)[v]
    assert v.sum() / nocc.sum() >= 0.945 and err.mean() <= 0.028, (v.sum() / nocc.sum(), err.mean())
    n = int(round(0.932 * nocc.sum()))
    top = np.argsort(-res.confidence[v], kind="stable")[:n]
    assert err[top].mean() <= 0.0226, err[top].mean()


def _precision(res, gt: np.ndarray, nocc: np.ndarray, thr: float, density0: float) -> tuple[float, float, float]:
    """Density, bad-thr and bad-thr at ``density0`` (the most confident pixels) on the non-occluded pixels."""
    v = res.valid & nocc
    err = (np.abs(res.disparity - gt) > thr)[v]
    top = np.argsort(-res.confidence[v], kind="stable")[:int(round(density0 * nocc.sum()))]
    return float(v.sum() / nocc.sum()), float(err.mean()), float(err[top].mean())


def test_motorcycle_hole_pass_precision():
    """The hole pass of ``stereo dense`` (``hole_p2=128``) on Motorcycle: bad-2.0 2.34 % at the
    previous density (95.9 %) measured, at 96.4 % density 2.49 % (the whole-window pass before: 2.41 %
    and 2.56 % at 96.4 %): at least as precise at equal density."""
    from skimage import data

    left, right, gt = data.stereo_motorcycle()
    density, bad, at0 = _precision(match_pair(left, right, options=MatchOptions(hole_p2=128.0)), gt,
                                   ~occlusion_from_truth(gt), 2.0, 0.959)
    assert density >= 0.962 and bad <= 0.0256 and at0 <= 0.0241, (density, bad, at0)


@pytest.mark.shared
def test_cones_hole_pass_precision():
    """The hole pass on Cones: bad-1.0 2.19 % at the previous density (93.2 %) measured, 2.69 % at
    95.4 % (the whole-window pass before: 2.26 %, and 2.81 % at 95.6 %)."""
    d = SHARED_DATA / "dense_cones"
    if not d.is_dir():
        pytest.skip(f"shared data absent: {d}")
    with rasterio.open(d / "disp_left.tif") as ds:
        gt = ds.read(1)
    nocc = (read_grey(d / "occlusion.png") > 0) & (gt > 0)
    res = match_pair(read_rgb(d / "left.png"), read_rgb(d / "right.png"), options=MatchOptions(hole_p2=128.0))
    density, bad, at0 = _precision(res, gt, nocc, 1.0, 0.932)
    assert density >= 0.952 and bad <= 0.0281 and at0 <= 0.0226, (density, bad, at0)


@pytest.mark.shared
def test_ngi_strip_dsm_coverage_and_rmse(ngi_pair, tmp_path):
    """The NGI strip DSM (aero-triangulated EOs, ``stereo dense`` defaults) against dem.tif: at least
    90 % of the overlap within 1.5 cells RMSE (issue 30; measured 91.6 % and 1.01 cells with the hole
    pass on the large holes' boxes, 91.1 % and 1.02 cells with the whole-window pass; before issue 30
    87.1 % and 1.03 cells), and smoother than before (second-difference NMAD 1.17 m, was 1.67 m)."""
    paths = write_ngi_exteriors(tmp_path)
    r = run_dense(paths[0], ngi_pair / "3324c_2015_1004_05_0182_RGB.tif", ngi_pair / "3324c_2015_1004_05_0184_RGB.tif",
                  tmp_path / "out", right_orientation=paths[1],
                  options=DenseOptions(cloud_format="none", reference_dem=str(ngi_pair / "dem.tif"),
                                       measure_parallax=False))
    c = r.comparison
    assert c is not None
    assert c.coverage >= 0.90 and c.rmse <= 1.5 * r.dsm_cell, c.summary_line(cell=r.dsm_cell)
    assert c.rmse <= 1.15 * r.dsm_cell and c.nmad <= 4.0, c.summary_line(cell=r.dsm_cell)
    with rasterio.open(tmp_path / "out" / "dsm.tif") as ds:
        z = ds.read(1).astype(np.float64)
        z[z == ds.nodata] = np.nan
    s = np.concatenate([(a[:, 2:] - 2 * a[:, 1:-1] + a[:, :-2]).ravel() for a in (z, z.T)])
    s = s[np.isfinite(s)]
    rough = 1.4826 * np.median(np.abs(s - np.median(s)))
    assert rough <= 1.4, rough
