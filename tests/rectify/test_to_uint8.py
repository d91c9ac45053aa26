"""``rectify.raster.io.to_uint8``: the look-up-table path of one uint8/uint16 band gives the float path's grey."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.raster import io as rio


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), h=st.integers(1, 40), w=st.integers(1, 40),
       dtype=st.sampled_from(["uint8", "uint16"]), levels=st.sampled_from([2, 7, 256, 4096, 65536]),
       masked=st.booleans(), lo=st.floats(0, 49), hi=st.floats(51, 100))
def test_lut_path_equals_float_path(seed, h, w, dtype, levels, masked, lo, hi):
    rng = np.random.default_rng(seed)
    top = min(levels, np.iinfo(dtype).max + 1)
    a = rng.integers(0, top, (h, w)).astype(dtype)
    valid = rng.random((h, w)) > 0.3 if masked else None
    fast = rio.to_uint8(a, valid, percentiles=(lo, hi))
    ref = rio.to_uint8(a.astype(np.float32), valid, percentiles=(lo, hi))   # the float path
    assert fast.dtype == np.uint8 and fast.shape == a.shape
    np.testing.assert_array_equal(fast, ref)


def test_lut_path_with_fixed_limits_and_empty_mask():
    a = np.arange(0, 400, dtype=np.uint16).reshape(20, 20)
    np.testing.assert_array_equal(rio.to_uint8(a, limits=(100.0, 300.0)),
                                  rio.to_uint8(a.astype(np.float32), limits=(100.0, 300.0)))
    none = np.zeros(a.shape, bool)
    assert not rio.to_uint8(a, none).any()
    flat = np.full((5, 5), 7, np.uint8)               # hi == lo: a one-level stretch, no division by zero
    np.testing.assert_array_equal(rio.to_uint8(flat), rio.to_uint8(flat.astype(np.float32)))


def test_large_band_is_sampled_like_the_float_path():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 1024, (1200, 1000)).astype(np.uint16)       # 1.2 M px: a strided 1 M sample
    np.testing.assert_array_equal(rio.to_uint8(a, percentiles=(0.5, 99.5)),
                                  rio.to_uint8(a.astype(np.float32), percentiles=(0.5, 99.5)))
