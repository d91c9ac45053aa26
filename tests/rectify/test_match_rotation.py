"""Least-squares matching for any relative rotation and scale of the pair (issue 30), on synthetic pairs with a
known homography: the right image turned back by quarter turns, the start shapes (homography Jacobian, the
neighbours' affine checked against the keypoints' similarity), the windows that follow the scale, the screening
of wrong convergences, and what a result says about its unrefined matches."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data as skd

from rectify.errors import ShapeError
from rectify.features import MatcherConfig, detect, match_arrays, match_descriptors
from rectify.features.match import _quarter_turns, _turn_matrix
from rectify.features.shape import _keypoint_similarity, _median_similarity, local_affine
from rectify.features.verify import screen_refined, verify_matches
from rectify.geometry.residuals import rms


def _apply(H, p):
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:]


def _pair(angle_deg: float, scale: float, seed: int = 1):
    """The astronaut (grey, 512 x 512) and its copy turned by ``angle_deg`` about the centre, scaled by ``scale``
    and seen in mild perspective, blurred (0.8 px) and noisy (2 grey levels, both); NaN outside. Returns
    left, right, right's validity, H_right_from_left."""
    rng = np.random.default_rng(seed)
    base = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY).astype(np.float32)
    h, w = base.shape
    a = np.radians(angle_deg)
    side = int(np.ceil(max(h, w) * scale))
    c, oc = np.array([w / 2 - 0.5, h / 2 - 0.5]), np.full(2, side / 2 - 0.5)
    H = np.eye(3)
    H[:2, :2] = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H[:2, 2] = oc - H[:2, :2] @ c
    T = np.array([[1, 0, -oc[0]], [0, 1, -oc[1]], [0, 0, 1.0]])
    P = np.array([[1, 0.03, 0], [-0.02, 1, 0], [1e-4 / scale, -0.8e-4 / scale, 1]])
    H = np.linalg.inv(T) @ P @ T @ H
    right = cv2.warpPerspective(base, H, (side, side), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=np.nan)
    valid = np.isfinite(right)
    right = np.asarray(cv2.GaussianBlur(np.nan_to_num(right), (0, 0), 0.8)) + rng.normal(0, 2, right.shape)
    left = cv2.GaussianBlur(base, (0, 0), 0.5) + rng.normal(0, 2, base.shape)
    return left.astype(np.float32), right.astype(np.float32), valid, H


def _figures(res, H, scale: float) -> dict:
    """Refined share, and the error against the truth of the refined matches in the coarser image's pixels."""
    m = res.matches
    e = np.linalg.norm(_apply(H, m.left) - m.right, axis=1) / max(scale, 1.0)
    ref = res.refined
    return {"n": len(m), "share": float(ref.mean()), "rms": rms(e[ref]), "median": float(np.median(e[ref])),
            "correct": float((e < 1.0).mean())}


@pytest.fixture(scope="module")
def reference():
    """The unturned, unscaled pair and its figures (share about 0.90, RMS 0.084 px, median 0.05 px)."""
    left, right, valid, H = _pair(0.0, 1.0)
    res = match_arrays(left, right, right_valid=valid)
    return (left, right, valid, H), res, _figures(res, H, 1.0)


# ------------------------------------------------------------------------------------------ quarter turns
@pytest.mark.parametrize("k", [1, 2, 3])
def test_quarter_turned_right_image_matches_as_the_unturned_one(reference, k):
    """The right image turned by np.rot90(., k) is turned back (exactly): the same matches, in its own pixels."""
    (left, right, valid, H), ref, _ = reference
    res = match_arrays(left, np.rot90(right, k), right_valid=np.rot90(valid, k))
    assert res.n_turns == (4 - k) % 4
    T = _turn_matrix(res.n_turns, np.rot90(right, k).shape)          # pixel of rot90(turned, j) -> turned
    back = np.c_[ref.matches.right, np.ones(len(ref.matches))] @ T.T
    np.testing.assert_array_equal(res.matches.left, ref.matches.left)
    np.testing.assert_allclose(res.matches.right, back[:, :2], atol=1e-9)
    np.testing.assert_array_equal(res.refined, ref.refined)
    assert res.rmse_px == pytest.approx(ref.rmse_px, rel=1e-9)
    # the model is in the given images' pixels: its transfer errors are those of the matches
    e = np.linalg.norm(_apply(res.verification.matrix, res.matches.left) - res.matches.right, axis=1)
    np.testing.assert_allclose(e, res.verification.errors_px, atol=1e-6)
    assert res.image_shapes[1] == np.rot90(right, k).shape


def test_turn_matrix_and_quarter_turns_on_a_non_square_image():
    img = np.arange(12.0).reshape(3, 4)
    for k in range(4):
        t = np.rot90(img, k)
        T = _turn_matrix(k, img.shape)
        rows, cols = np.mgrid[0:t.shape[0], 0:t.shape[1]]
        p = np.c_[cols.ravel(), rows.ravel(), np.ones(rows.size)] @ T.T
        np.testing.assert_array_equal(img[p[:, 1].astype(int), p[:, 0].astype(int)], t.ravel())
    g = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)[40:440, 60:400]
    fl = detect(g, max_keypoints=1500)
    for k in range(4):
        fr = detect(np.rot90(g, k), max_keypoints=1500)
        pairs = match_descriptors(fl, fr)
        assert _quarter_turns(fl, fr, pairs, np.ones(len(pairs.left), bool)) == (4 - k) % 4


# ------------------------------------------------------------------------------ rotation and scale
@pytest.mark.parametrize("angle", [90.0, 180.0, 270.0, 33.0])
def test_turned_pairs_refine_like_the_unturned_one_without_turning_back(reference, angle):
    """derotate=False: the homography's Jacobian starts the windows; share and precision as unturned."""
    left, right, valid, H = _pair(angle, 1.0)
    res = match_arrays(left, right, right_valid=valid, config=MatcherConfig(derotate=False))
    f, f0 = _figures(res, H, 1.0), reference[2]
    assert res.n_turns == 0
    assert f["correct"] >= 0.98
    assert f["share"] >= f0["share"] - 0.04, (f, f0)
    assert f["rms"] <= 1.25 * f0["rms"] + 0.01, (f, f0)
    assert f["median"] <= 1.25 * f0["median"] + 0.005, (f, f0)


@pytest.mark.parametrize("scale", [0.5, 0.7, 1.5, 2.0])
def test_scaled_pairs_refine_like_the_unscaled_one(reference, scale):
    """Turned by 33 degrees and scaled: refined share and precision (in the coarser image's pixels) as for the
    unscaled pair. Before the scaled windows, the half-size pair's refined matches were 0.23 px off (RMS, right
    pixels) and 78 % of them refined."""
    left, right, valid, H = _pair(33.0, scale)
    res = match_arrays(left, right, right_valid=valid)
    f, f0 = _figures(res, H, scale), reference[2]
    assert f["correct"] >= 0.97
    assert f["share"] >= f0["share"] - 0.06, (f, f0)
    assert f["rms"] <= 1.3 * f0["rms"], (f, f0)


# ----------------------------------------------------------------------------------------- start shapes
def test_keypoint_similarity_follows_a_known_rotation_and_scale():
    """OpenCV's orientations (x right, y down): the right keypoint is the left one turned by angle_r - angle_l."""
    g = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)
    h, w = g.shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), 30, 1.3)            # A = M[:, :2], right from left
    fl, fr = detect(g), detect(cv2.warpAffine(g, M, (w, h)))
    p = match_descriptors(fl, fr)
    kp = np.c_[fl.size[p.left], fl.angle[p.left], fr.size[p.right], fr.angle[p.right]]
    c, s = _median_similarity(_keypoint_similarity(kp)[None])[0]
    np.testing.assert_allclose([[c, -s], [s, c]], M[:, :2], atol=0.04)


def test_local_affine_ignores_a_wrong_neighbour_and_falls_back_to_the_keypoints():
    rng = np.random.default_rng(3)
    A = 0.8 * np.array([[np.cos(2.0), -np.sin(2.0)], [np.sin(2.0), np.cos(2.0)]])
    pl = rng.uniform(0, 500, (200, 2))
    pr = pl @ A.T + [40.0, 700.0] + rng.normal(0, 0.2, (200, 2))
    pr[7] += [25.0, -30.0]                                            # one wrong match among the neighbours
    got = local_affine(pl, pr, None)
    np.testing.assert_allclose(got[np.arange(200) != 7], np.broadcast_to(A, (199, 2, 2)), atol=0.02)
    # neighbours on a line: their fit is singular; the keypoints' similarity (noisy, median of the neighbours) wins
    line = np.c_[np.linspace(0, 300, 30), np.full(30, 100.0)]
    kp = np.c_[np.full(30, 4.0), rng.normal(0.3, 0.05, 30), np.full(30, 3.2), rng.normal(2.3, 0.05, 30)]
    got = local_affine(line, line @ A.T, None, keypoints=kp)
    np.testing.assert_allclose(got, np.broadcast_to(A, (30, 2, 2)), atol=0.06)
    # no keypoints and too few matches: identity; with keypoints: their median similarity
    np.testing.assert_array_equal(local_affine(line[:4], line[:4] @ A.T, None), np.broadcast_to(np.eye(2), (4, 2, 2)))
    np.testing.assert_allclose(local_affine(line[:4], line[:4] @ A.T, None, keypoints=kp[:4]),
                               np.broadcast_to(A, (4, 2, 2)), atol=0.08)


# -------------------------------------------------------------------------------- screening, results
def test_screening_moves_wrong_convergences_back_and_keeps_them_out_of_the_rmse():
    rng = np.random.default_rng(5)
    H = np.array([[0.9, 0.1, 20.0], [-0.1, 0.95, 10.0], [1e-4, 0, 1]])
    pl = rng.uniform(0, 800, (300, 2))
    truth = _apply(H, pl)
    pr = truth + rng.normal(0, 0.03, (300, 2))                        # refined: 0.04 px (2D)
    raw = truth + rng.normal(0, 0.3, (300, 2))
    score = np.full(300, 0.04)
    pr[:6] += [0.6, -0.5]                                             # six wrong convergences
    ver = verify_matches(pl, pr, method="homography", threshold_px=1.5)
    out = screen_refined(ver, pl, pr, raw, score, threshold_px=1.5, min_inliers=15, keep_unrefined=True)
    v, ql, qr, qraw, qs, n = out
    assert n == 6 and len(ql) == 300
    assert np.isnan(qs[:6]).all() and np.isfinite(qs[6:]).all()
    np.testing.assert_array_equal(qr[:6], raw[:6])                   # the raw positions agree better
    assert rms(np.linalg.norm(_apply(v.matrix, pl[6:]) - truth[6:], axis=1)) < 0.02   # the refined ones' model
    dropped = screen_refined(ver, pl, pr, raw, score, threshold_px=1.5, min_inliers=15, keep_unrefined=False)
    assert len(dropped[1]) == 294 and dropped[5] == 6


def test_result_tells_refined_from_unrefined(reference):
    """rmse_px counts the refined matches only; the unrefined ones are check points of the residual table, with
    their own, larger sigma."""
    (left, right, valid, H), res, _ = reference
    ref = res.refined
    assert 0 < res.n_unrefined == int((~ref).sum()) < 0.15 * len(ref)
    assert res.rmse_px == pytest.approx(rms(res.verification.errors_px[ref]))
    assert res.rmse_unrefined_px > 2 * res.rmse_px
    table = res.verification.table
    np.testing.assert_array_equal(table.check, ~ref)
    assert table.summary()["rmse"] == pytest.approx(res.rmse_px)
    sig = res.sigma_px
    np.testing.assert_array_equal(sig[ref], res.matches.score[ref])
    assert np.isnan(res.matches.score[~ref]).all()
    assert (sig[~ref] > 3 * np.median(sig[ref])).all() and np.unique(sig[~ref]).size == 1
    s = res.summary()
    assert s["n_unrefined"] == res.n_unrefined and s["n_turns"] == 0 and s["n_screened"] == res.n_screened
    off = match_arrays(left, right, right_valid=valid, config=MatcherConfig(refine=False))
    assert off.refined is None and off.sigma_px is None and off.n_unrefined == 0


def test_shift_limit_per_match_and_its_shape():
    from rectify.features.lsm import refine_matches

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.normal(size=(120, 120)).astype(np.float32), (0, 0), 3.0) * 300 + 120
    shifted = np.roll(img, (0, 3), axis=(0, 1))                      # right = left moved 3 px in x
    pl = np.array([[60.0, 60.0]])
    start = pl + [0.6, 0.1]                                           # 2.4 px from the truth: beyond max_shift_px
    assert not refine_matches(img, shifted, pl, start).converged[0]
    r = refine_matches(img, shifted, pl, start, shift_limit_px=[4.0])
    assert r.converged[0]
    np.testing.assert_allclose(r.right[0], pl[0] + [3.0, 0.0], atol=0.01)
    with pytest.raises(ShapeError, match="shift_limit_px"):
        refine_matches(img, shifted, pl, start, shift_limit_px=[4.0, 1.0])


def test_a_wrong_partner_along_the_epipolar_line_is_off_its_neighbours():
    """Fundamental verification cannot see a partner displaced along its epipolar line; its neighbours can (the
    parallax of the relief varies smoothly; here +-6 px)."""
    from rectify.features.match import _off_neighbours
    from rectify.features.shape import neighbour_residuals

    rng = np.random.default_rng(2)
    pl = rng.uniform(0, 600, (400, 2))
    parallax = 6.0 * np.sin(pl[:, 0] / 90.0) * np.cos(pl[:, 1] / 120.0)
    pr = pl + np.c_[-420.0 + parallax, np.full(400, -12.0)] + rng.normal(0, 0.1, (400, 2))
    pr[[5, 50]] += [[150.0, 0.0], [-35.0, 0.0]]                      # two wrong partners on their (horizontal) lines
    e = neighbour_residuals(pl, pr)
    assert e[5] > 100 and e[50] > 25 and np.median(e) < 1.0
    odd = _off_neighbours(pl, pr)
    assert np.flatnonzero(odd).tolist() == [5, 50]
    assert not _off_neighbours(pl[:15], pr[:15]).any()               # too few matches to judge
    assert np.isnan(neighbour_residuals(pl[:8], pr[:8])).all()


def test_a_good_match_among_wrong_neighbours_is_kept():
    """Five wrong partners around a good match outvote its neighbours' first prediction; judged again against
    the others only, the good match stays and the five go."""
    from rectify.features.match import _off_neighbours
    from rectify.features.shape import _nearest

    rng = np.random.default_rng(4)
    pl = rng.uniform(0, 600, (300, 2))
    pr = pl @ np.array([[0.0, -1.0], [1.0, 0.0]]).T + [700.0, 40.0] + rng.normal(0, 0.1, (300, 2))   # turned 90
    bad = _nearest(pl, 6)[17, 1:]                                    # the five nearest to match 17
    pr[bad] += [60.0, -45.0]
    assert sorted(np.flatnonzero(_off_neighbours(pl, pr)).tolist()) == sorted(bad.tolist())
