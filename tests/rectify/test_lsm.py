"""Least-squares matching: known shifts, affine shapes, radiometry, failures, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import InvalidInputError, ShapeError
from rectify.features.lsm import LsmConfig, bilinear, refine_matches


def _texture(n: int = 96, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    import cv2

    a = rng.normal(size=(n, n)).astype(np.float32)
    return cv2.GaussianBlur(a, (0, 0), 1.5) * 100 + 120


def _warp(img: np.ndarray, A: np.ndarray, t: np.ndarray) -> np.ndarray:
    """right(x) = img(A^-1 (x - t)): a point x_l of img lands at A x_l + t (quintic spline, exact enough)."""
    from scipy import ndimage

    Ai = np.linalg.inv(A)
    P = np.array([[0, 1], [1, 0]])          # (x, y) <-> (row, col)
    return ndimage.affine_transform(img.astype(np.float64), P @ Ai @ P, offset=P @ (-Ai @ t), order=5,
                                    mode="reflect")


def test_bilinear_known_values():
    img = np.arange(12, dtype=float).reshape(3, 4)   # value = 4 r + c
    v = bilinear(img, np.array([0.0, 1.5, 3.0, 3.5]), np.array([0.0, 0.5, 2.0, 0.0]))
    np.testing.assert_allclose(v[:3], [0.0, 1.5 + 2.0, 11.0])
    assert np.isnan(v[3])                            # outside


@pytest.mark.parametrize("shift", [(0.3, -0.45), (1.2, 0.7), (-0.8, 0.15)])
def test_recovers_subpixel_shift_with_gain_offset(shift):
    L = _texture()
    t = np.array(shift)
    R = 1.7 * _warp(L, np.eye(2), t) - 30.0          # radiometric gain and offset
    pl = np.array([[40.0, 40.0], [50.0, 45.0], [38.0, 56.0]])
    start = pl + t + np.array([0.4, -0.3])
    r = refine_matches(L, R, pl, start)
    assert r.converged.all()
    np.testing.assert_allclose(r.right, pl + t, atol=0.02)
    assert (r.std_px < 0.05).all()
    assert (r.corr > 0.99).all()


def test_recovers_affine_shape():
    L = _texture(128)
    A = np.array([[1.08, 0.12], [-0.1, 0.95]])
    c = np.array([64.0, 64.0])
    t = c - A @ c + np.array([0.3, 0.2])
    R = _warp(L, A, t)
    pl = np.array([[60.0, 62.0], [70.0, 58.0]])
    truth = pl @ A.T + t
    r = refine_matches(L, R, pl, truth + 0.6)                       # identity start
    assert r.converged.all()
    np.testing.assert_allclose(r.right, truth, atol=0.03)
    np.testing.assert_allclose(r.affine[0], A, atol=0.03)


def test_flat_window_does_not_converge_and_keeps_input():
    L = np.full((64, 64), 100.0)
    R = np.full((64, 64), 100.0)
    r = refine_matches(L, R, [[30.0, 30.0]], [[31.0, 30.0]])
    assert not r.converged[0]
    np.testing.assert_array_equal(r.right[0], [31.0, 30.0])
    assert np.isnan(r.std_px[0])


def test_window_on_nan_does_not_converge_and_border_windows_move_inward():
    L = _texture()
    R = L.copy()
    R[30:50, 30:50] = np.nan
    pts = [[2.0, 2.0], [40.0, 40.0], [70.0, 70.0]]
    r = refine_matches(L, R, pts, pts)
    # (2, 2): the window moves inward (the point stays inside it) and finds the point; on nodata: no
    assert r.converged.tolist() == [True, False, True]
    np.testing.assert_allclose(r.right[[0, 2]], [[2.0, 2.0], [70.0, 70.0]], atol=0.01)
    off = refine_matches(L, R, pts, pts, config=LsmConfig(border_shift=False))
    assert off.converged.tolist() == [False, False, True]
    # a point whose window cannot hold it inside the image (a right partner off the right image) fails
    far = refine_matches(L, R[:60, :60], [[70.0, 70.0]], [[70.0, 70.0]])
    assert not far.converged.any()


def test_border_shift_off_centre_window_is_accurate():
    """Points 0-8 px from the left or right image border, off-centre in their window: known subpixel truth."""
    L = _texture(128, seed=5)
    t = np.array([0.37, -0.21])
    R = _warp(L, np.eye(2), t)
    pl = np.array([[1.0, 60.0], [4.3, 30.6], [60.2, 2.4], [123.0, 80.0], [70.4, 126.0], [40.0, 7.7]])
    r = refine_matches(L, R, pl, pl + t + 0.3)
    assert r.converged.all()
    np.testing.assert_allclose(r.right, pl + t, atol=0.03)
    assert (r.std_px < 0.1).all()


def test_wrong_partner_is_rejected():
    L = _texture(seed=1)
    R = _texture(seed=2)            # unrelated texture: no true partner
    r = refine_matches(L, R, [[40.0, 40.0], [50.0, 50.0]], [[40.0, 40.0], [50.0, 50.0]])
    assert not r.converged.any()


def test_inputs_not_modified_and_empty():
    L = _texture()
    pl = np.array([[40.0, 40.0]])
    pr = pl + 0.3
    before = pr.copy()
    refine_matches(L, L, pl, pr)
    np.testing.assert_array_equal(pr, before)
    r = refine_matches(L, L, np.zeros((0, 2)), np.zeros((0, 2)))
    assert r.right.shape == (0, 2) and r.converged.shape == (0,)


def test_bad_input():
    L = _texture()
    with pytest.raises(ShapeError, match="must have the same number"):
        refine_matches(L, L, [[1.0, 2.0]], [[1.0, 2.0], [3.0, 4.0]])
    with pytest.raises(ShapeError, match="left_img"):
        refine_matches(np.zeros((2, 3, 4, 5)), L, [[1.0, 2.0]], [[1.0, 2.0]])
    with pytest.raises(ShapeError, match="affine"):
        refine_matches(L, L, [[40.0, 40.0]], [[40.0, 40.0]], affine=np.eye(3))
    with pytest.raises(InvalidInputError, match="non-finite"):
        refine_matches(L, L, [[np.nan, 40.0]], [[40.0, 40.0]])
    with pytest.raises(InvalidInputError, match="radius_px"):
        LsmConfig(radius_px=1)
    with pytest.raises(InvalidInputError, match="min_corr"):
        LsmConfig(min_corr=2.0)


@settings(max_examples=15, deadline=None)
@given(dx=st.floats(-1.0, 1.0), dy=st.floats(-1.0, 1.0))
def test_property_translation_recovered(dx, dy):
    L = _texture(80, seed=5)
    R = _warp(L, np.eye(2), np.array([dx, dy]))
    r = refine_matches(L, R, [[40.0, 40.0]], [[40.0 + dx * 0.5, 40.0 + dy * 0.5]])
    assert r.converged[0]
    np.testing.assert_allclose(r.right[0], [40.0 + dx, 40.0 + dy], atol=0.03)


@pytest.mark.parametrize(("scale", "angle_deg"), [(0.5, -50.0), (0.6, 10.0), (1.6, 120.0), (2.0, 30.0)])
def test_turned_and_scaled_windows(scale, angle_deg):
    """A right image turned and scaled (quintic spline, noise 1 grey level), the start affine known: every window
    converges to the truth; where the right image is coarser the larger template halves the error (issue 30)."""
    from scipy import ndimage

    rng = np.random.default_rng(1)
    L = _texture(160, seed=7)
    a = np.radians(angle_deg)
    A = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    side = int(160 * max(scale, 1.0))
    t = np.full(2, side / 2) - A @ [80.0, 80.0] + [0.3, -0.2]
    Ai, P = np.linalg.inv(A), np.array([[0, 1], [1, 0]])
    R = ndimage.affine_transform(L.astype(np.float64), P @ Ai @ P, offset=P @ (-Ai @ t), order=5, mode="constant",
                                 cval=np.nan, output_shape=(side, side)) + rng.normal(0, 1.0, (side, side))
    pl = 80.0 + rng.uniform(-25, 25, (40, 2))
    truth = pl @ A.T + t
    start = truth + rng.normal(0, 0.3, truth.shape)
    err = {}
    for scaled in (True, False):
        r = refine_matches(L, R, pl, start, affine=A, config=LsmConfig(scale_windows=scaled))
        assert r.converged.all()
        err[scaled] = float(np.sqrt(np.mean(np.sum((r.right - truth) ** 2, axis=1))))
    assert err[True] <= 0.03 * max(scale, 1.0)
    if scale < 1:
        assert err[True] <= 0.7 * err[False], err
