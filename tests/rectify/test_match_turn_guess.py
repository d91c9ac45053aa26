"""The quarter-turn guess of the whole-image matcher (issue 30, speed): a small copy of the right image against the
left keypoints says how far to turn the right image back before its one full detection; the full matches check
the guess, and a wrong one costs a second pass but never changes the result."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data as skd

import rectify.features.match as fm
from rectify.features import MatcherConfig, detect, match_arrays


@pytest.fixture(scope="module")
def pair():
    """The astronaut (grey, 512 x 512) and a copy seen in mild perspective (blurred, noisy); the right image's
    validity."""
    rng = np.random.default_rng(3)
    base = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY).astype(np.float32)
    H = np.array([[0.97, 0.03, 8.0], [-0.02, 1.01, -5.0], [2e-5, -1e-5, 1.0]])
    right = cv2.warpPerspective(base, H, (512, 512), flags=cv2.INTER_CUBIC, borderValue=np.nan)
    valid = np.isfinite(right)
    right = np.asarray(cv2.GaussianBlur(np.nan_to_num(right), (0, 0), 0.8)) + rng.normal(0, 2, right.shape)
    left = base + rng.normal(0, 2, base.shape)
    return left.astype(np.float32), right.astype(np.float32), valid


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_guess_turns_the_right_image_back(pair, k):
    """np.rot90(right, k) is turned back by np.rot90(., (4 - k) % 4); the right image is 2 x COARSE_TURN_PX px."""
    left, right, valid = pair
    fl = detect(left)
    turned, tv = np.rot90(right, k), np.rot90(valid, k)
    assert fm._coarse_turns(fl, left.shape, turned, tv, MatcherConfig()) == (4 - k) % 4
    # colour and 16-bit images take the same path (area-reduced by OpenCV, stretched by the detector)
    rgb = np.repeat((np.nan_to_num(turned) * 200).astype(np.uint16)[..., None], 3, axis=2)
    assert fm._coarse_turns(fl, left.shape, rgb, tv, MatcherConfig()) == (4 - k) % 4


def test_no_guess_for_small_images_or_without_keypoints(pair):
    left, right, valid = pair
    fl = detect(left)
    small = right[:200, :240]
    assert fm._coarse_turns(fl, left.shape, np.rot90(small, 2), np.ones((240, 200), bool), MatcherConfig()) == 0
    blank = np.zeros((600, 600), np.float32)
    assert fm._coarse_turns(fl, left.shape, blank, np.ones(blank.shape, bool), MatcherConfig()) == 0


def test_a_wrong_guess_is_corrected_by_the_full_matches(pair, monkeypatch):
    """Guessed right: one pass (no "first_pass" time). Guessed wrong (either way): the full matches' orientations
    say so, the right image is matched again turned by what they say, and the result is the same matches."""
    left, right, valid = pair
    turned, tv = np.rot90(right, 1), np.rot90(valid, 1)
    ref = match_arrays(left, turned, right_valid=tv)
    assert ref.n_turns == 3 and "first_pass" not in ref.timings_s and "coarse_turns" in ref.timings_s
    for wrong in (0, 2):
        monkeypatch.setattr(fm, "_coarse_turns", lambda *a, w=wrong, **kw: w)
        res = match_arrays(left, turned, right_valid=tv)
        assert res.n_turns == 3 and "first_pass" in res.timings_s
        np.testing.assert_array_equal(res.matches.left, ref.matches.left)
        np.testing.assert_array_equal(res.matches.right, ref.matches.right)
        np.testing.assert_array_equal(res.refined, ref.refined)
    # derotate=False: no guess, matched as given
    monkeypatch.setattr(fm, "_coarse_turns", lambda *a, **kw: pytest.fail("guessed with derotate=False"))
    res = match_arrays(left, turned, right_valid=tv, config=MatcherConfig(derotate=False))
    assert res.n_turns == 0 and "coarse_turns" not in res.timings_s


def test_a_wrong_turn_that_fails_falls_back_to_the_image_as_given(pair, monkeypatch):
    """A guess whose turned matching fails (too few consistent matches) is dropped: matched as given."""
    left, right, valid = pair
    ref = match_arrays(left, right, right_valid=valid)
    monkeypatch.setattr(fm, "_coarse_turns", lambda *a, **kw: 1)
    cfg = MatcherConfig(min_inliers=10**6 // 2)        # nothing passes: both the turned and the given pass fail
    with pytest.raises(fm.EstimationError, match="do not overlap"):
        match_arrays(left, right, right_valid=valid, config=cfg)
    real = fm._match_pass
    calls = []

    def failing_turned(L, lv, R, rv, cfg, progress, names, fl, k, check, t0):
        calls.append(k)
        if k:
            raise fm.EstimationError("images do not overlap (turned)")
        return real(L, lv, R, rv, cfg, progress, names, fl, k, check, t0)

    monkeypatch.setattr(fm, "_match_pass", failing_turned)
    res = match_arrays(left, right, right_valid=valid)
    assert calls == [1, 0] and res.n_turns == 0
    np.testing.assert_array_equal(res.matches.left, ref.matches.left)
