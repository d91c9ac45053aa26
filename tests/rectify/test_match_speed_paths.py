"""Issue 12 speed and recall paths: the fast LSM resampling (OpenCV Lanczos-4 with its coordinate rounding
corrected) against the Keys reference, subpixel left positions, the large-image fallback, and the guided
re-admission of matches after homography verification."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data as skd

from rectify.features import MatcherConfig, match_arrays
from rectify.features.lsm import LsmConfig, _Sampler, refine_matches


def _texture(n: int = 96, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, n)).astype(np.float32)
    return cv2.GaussianBlur(a, (0, 0), 1.5) * 100 + 120


def _shifted(img: np.ndarray, t) -> np.ndarray:
    """right(x) = img(x - t) (quintic spline: independent of both samplers)."""
    from scipy import ndimage

    return ndimage.shift(img.astype(np.float64), (t[1], t[0]), order=5, mode="reflect")


@pytest.mark.parametrize("sampler", ["lanczos", "keys"])
def test_subpixel_shifts_on_and_off_the_1_32_grid(sampler):
    """remap rounds coordinates to 1/32 px; the first-order correction leaves no step pattern."""
    L = _texture()
    pl = np.array([[40.0, 40.0], [50.0, 45.0], [38.0, 56.0], [55.0, 52.0]])
    tol = 0.008 if sampler == "lanczos" else 0.02
    for f in (0.0, 1 / 64, 1 / 32, 0.1, 0.25, 0.3, 0.47, 0.5, 0.77):
        t = np.array([f, -0.6 * f])
        R = _shifted(L, t)
        r = refine_matches(L, R, pl, pl + t + 0.3, config=LsmConfig(sampler=sampler))
        assert r.converged.all(), f
        np.testing.assert_allclose(r.right, pl + t, atol=tol, err_msg=f"fraction {f}")


def test_fast_sampler_agrees_with_keys_and_is_faster_on_many_matches():
    import time

    L = _texture(400, seed=7)
    t = np.array([0.37, -0.21])
    rng = np.random.default_rng(0)
    R = 1.3 * _shifted(L, t) + 5.0 + rng.normal(0, 2.0, L.shape)     # noise: the precision is noise-driven
    L = L + rng.normal(0, 2.0, L.shape)
    pl = rng.uniform(20, 380, size=(1500, 2))
    start = pl + t + rng.uniform(-0.5, 0.5, size=pl.shape)
    times = {}
    res = {}
    for s in ("lanczos", "keys"):
        t0 = time.process_time()
        res[s] = refine_matches(L, R, pl, start, config=LsmConfig(sampler=s))
        times[s] = time.process_time() - t0
    a, b = res["lanczos"], res["keys"]
    assert a.converged.mean() > 0.95 and b.converged.mean() > 0.95
    both = a.converged & b.converged
    err_a = np.linalg.norm(a.right[both] - (pl[both] + t), axis=1)
    err_b = np.linalg.norm(b.right[both] - (pl[both] + t), axis=1)
    assert np.sqrt(np.mean(err_a ** 2)) <= np.sqrt(np.mean(err_b ** 2)) + 0.002
    assert np.sqrt(np.mean(err_a ** 2)) < 0.03
    # the a-posteriori precision describes the actual scatter, alike for both samplers
    for r, e in ((a, err_a), (b, err_b)):
        ratio = np.sqrt(np.mean(e ** 2)) / np.sqrt(np.mean(r.std_px[both] ** 2))
        assert 0.5 < ratio < 2.0, ratio
    assert times["lanczos"] < times["keys"]


def test_subpixel_left_positions_keep_their_partner():
    """The window sits on the nearest left pixel; the left point's own partner follows through the affine."""
    L = _texture(128, seed=4)
    A = np.array([[1.05, 0.08], [-0.06, 0.97]])
    tt = np.array([3.3, -2.1])
    from scipy import ndimage

    Ai = np.linalg.inv(A)
    P = np.array([[0, 1], [1, 0]])
    R = ndimage.affine_transform(L.astype(np.float64), P @ Ai @ P, offset=P @ (-Ai @ tt), order=5, mode="reflect")
    pl = np.array([[60.31, 62.77], [70.5, 58.5], [55.93, 66.12]])
    truth = pl @ A.T + tt
    r = refine_matches(L, R, pl, truth + [0.4, -0.5], affine=A + 0.02)
    assert r.converged.all()
    np.testing.assert_allclose(r.right, truth, atol=0.02)


def test_image_beyond_remap_limit_falls_back_to_keys():
    img = np.zeros((8, 32770), np.float32)
    assert _Sampler(img, "lanczos").kind == "keys"
    assert _Sampler(img[:, :1000], "lanczos").kind == "lanczos"
    with pytest.raises(Exception, match="sampler"):
        LsmConfig(sampler="cubic")


# a strong viewpoint change (about 50 degrees about the vertical axis, as in the Oxford graf sequence)
H = np.array([[1.93, 0.0, 197.0], [0.36, 2.24, -286.0], [1.1e-3, 0.0, 1.0]])


def _wide_pair():
    img = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)[:480, :480]
    right = cv2.warpPerspective(img, H, (480, 480), flags=cv2.INTER_CUBIC)
    valid = cv2.warpPerspective(np.ones_like(img), H, (480, 480), flags=cv2.INTER_NEAREST) > 0
    return img, right, valid


def _errors(res) -> np.ndarray:
    q = np.c_[res.matches.left, np.ones(len(res.matches))] @ H.T
    return np.linalg.norm(q[:, :2] / q[:, 2:] - res.matches.right, axis=1)


def test_guided_readmission_adds_correct_matches_only():
    left, right, valid = _wide_pair()
    on = match_arrays(left, right, right_valid=valid, config=MatcherConfig())
    off = match_arrays(left, right, right_valid=valid, config=MatcherConfig(guided=False))
    assert off.n_guided == 0 and on.n_guided > 0
    assert len(on.matches) > len(off.matches)
    e = _errors(on)
    assert (e < 2.0).all()                               # no wrong match among the additions
    assert on.matches.score is not None
    refined = np.isfinite(on.matches.score)
    assert np.median(e[refined]) < 0.1
    assert on.summary()["n_guided"] == on.n_guided
    # one-to-one still
    assert len(np.unique(np.round(on.matches.left / 0.1), axis=0)) == len(on.matches)
    assert len(np.unique(np.round(on.matches.right / 0.1), axis=0)) == len(on.matches)


def test_no_guided_readmission_with_a_fundamental_matrix():
    left, right, valid = _wide_pair()
    r = match_arrays(left, right, right_valid=valid, config=MatcherConfig(verify="fundamental"))
    assert r.n_guided == 0
    with pytest.raises(Exception, match="guided_ratio"):
        MatcherConfig(guided_ratio=0.0)


def test_threaded_chunks_give_the_serial_result():
    L = _texture(200, seed=9)
    t = np.array([0.41, 0.27])
    R = _shifted(L, t)
    rng = np.random.default_rng(1)
    pl = rng.uniform(15, 185, size=(300, 2))
    start = pl + t + rng.uniform(-0.4, 0.4, size=pl.shape)
    seen = []
    a = refine_matches(L, R, pl, start, chunk=37, workers=1)
    b = refine_matches(L, R, pl, start, chunk=37, workers=3, progress=lambda d, n: seen.append((d, n)))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert seen[-1] == (300, 300) and [d for d, _ in seen] == sorted(d for d, _ in seen)


def test_guided_readmission_only_tops_up_scarce_matches():
    left, right, valid = _wide_pair()
    full = match_arrays(left, right, right_valid=valid, config=MatcherConfig())
    n0 = full.n_verified - full.n_guided                      # verified by USAC
    none = match_arrays(left, right, right_valid=valid, config=MatcherConfig(guided_fill=max(1, n0 - 1)))
    assert none.n_guided == 0
    some = match_arrays(left, right, right_valid=valid, config=MatcherConfig(guided_fill=n0 + 5))
    assert 0 < some.n_guided <= 5
    assert (_errors(some) < 2.0).all()
