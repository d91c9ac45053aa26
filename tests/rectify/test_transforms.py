"""Contract tests of rectify.geometry.transforms: every model implements the Transform interface
(from_points, __call__, inverse, residuals, to_dict) and transform_from_dict rebuilds it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.transforms import (
    METHODS,
    AffineTransform,
    CotangentFourPoint,
    Homography,
    PolynomialTransform,
    Transform,
    transform_from_dict,
    transform_to_dict,
)
from rectify.geometry.transforms.base import Transform as BaseTransform

H_TRUE = np.array([[1.1, 0.05, 10.0], [-0.02, 0.95, 20.0], [1e-4, -5e-5, 1.0]])
SIZE = 1000.0


def _grid(n: int, lo: float, hi: float) -> np.ndarray:
    g = np.linspace(lo, hi, n)
    gx, gy = np.meshgrid(g, g)
    return np.column_stack([gx.ravel(), gy.ravel()])


def _smooth(p: np.ndarray) -> np.ndarray:
    """A mildly non-linear source -> target map for the polynomials (pixels -> pixels)."""
    x, y = p[:, 0], p[:, 1]
    return np.column_stack([15.0 + 1.02 * x + 0.03 * y + 2e-5 * x * y + 1e-5 * x * x,
                            -8.0 - 0.02 * x + 0.97 * y + 1.5e-5 * y * y - 1e-5 * x * y])


SRC4 = np.array([[0.0, 0.0], [1000.0, 0.0], [1000.0, 800.0], [0.0, 800.0]])
SRC_N = _grid(6, 0.0, SIZE)

#: name -> (class, builder of a fitted model, tolerance of inverse(forward(p)) == p in px; None: the
#: polynomial's documented bound, ``inverse.inverse_max_error``)
CASES = {
    "homography": (Homography, lambda: Homography.from_points(SRC_N, Homography(H_TRUE)(SRC_N)), 1e-9),
    "affine": (AffineTransform,
               lambda: AffineTransform.from_points(SRC_N, SRC_N @ [[1.1, 0.1], [-0.05, 0.9]] + [5.0, 7.0]), 1e-9),
    "cotangent": (CotangentFourPoint, lambda: CotangentFourPoint.from_points(SRC4, Homography(H_TRUE)(SRC4)), 1e-8),
    "poly1": (PolynomialTransform, lambda: PolynomialTransform.from_points(SRC_N, _smooth(SRC_N), order=1), None),
    "poly2": (PolynomialTransform, lambda: PolynomialTransform.from_points(SRC_N, _smooth(SRC_N), order=2), None),
    "poly3": (PolynomialTransform, lambda: PolynomialTransform.from_points(SRC_N, _smooth(SRC_N), order=3), None),
}


@pytest.fixture(params=sorted(CASES))
def case(request):
    cls, build, tol = CASES[request.param]
    return request.param, cls, build(), tol


def test_every_model_is_a_transform(case):
    _, cls, model, _ = case
    assert isinstance(model, Transform)
    assert Transform is BaseTransform
    assert issubclass(cls, Transform)
    assert not getattr(cls, "__abstractmethods__", frozenset())


def test_every_registry_class_is_a_transform():
    for m in METHODS.values():
        assert issubclass(m.cls, Transform), m


def test_abstract_base_cannot_be_instantiated():
    with pytest.raises(TypeError):
        Transform()  # type: ignore[abstract]


def test_inverse_of_forward_is_identity(case):
    _, _, model, tol = case
    rng = np.random.default_rng(3)
    p = rng.uniform(50.0, 950.0, (200, 2))
    inv = model.inverse
    back = inv(model(p))
    if tol is None:
        tol = inv.inverse_max_error + 1e-9
    assert np.linalg.norm(back - p, axis=1).max() < tol
    assert isinstance(model.inverse, Transform)


def test_polynomial_inverse_error_bound_reported():
    model = PolynomialTransform.from_points(SRC_N, _smooth(SRC_N), order=2)
    assert model.inverse_rmse is None and model.inverse_max_error is None
    inv = model.inverse
    assert inv.inverse_rmse is not None and inv.inverse_max_error is not None
    assert 0.0 <= inv.inverse_rmse <= inv.inverse_max_error < 0.2
    # on the fitting grid (41 x 41 nodes of the domain) the error is within the reported bound
    g = np.linspace(0.0, 1.0, 41)
    gx, gy = np.meshgrid(g, g)
    grid = np.column_stack([gx.ravel(), gy.ravel()]) * SIZE
    err = np.linalg.norm(inv(model(grid)) - grid, axis=1)
    assert err.max() <= inv.inverse_max_error * (1 + 1e-9) + 1e-12


def test_polynomial_inverse_of_degenerate_image_raises():
    # the forward map folds the domain onto a line: no inverse
    coef = np.array([[0.0, 1.0, 1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 2.0, 0.0, 0.0, 0.0]])
    model = PolynomialTransform(2, coef, [500.0, 500.0], 1 / 500, [[0.0, 0.0], [1000.0, 1000.0]])
    with pytest.raises(EstimationError):
        _ = model.inverse


def test_residuals_shape_and_value(case):
    _, _, model, _ = case
    p = _grid(5, 100.0, 900.0)
    q = model(p)
    q_off = q + [3.0, 4.0]
    r = model.residuals(p, q_off)
    assert r.shape == (len(p),)
    assert_allclose(r, 5.0, rtol=1e-9)


def test_to_dict_round_trip(case):
    name, cls, model, _ = case
    d = model.to_dict()
    assert d["direction"] == "target_from_source"
    assert d["method"] in METHODS
    d2 = json.loads(json.dumps(d))          # JSON-ready
    back = transform_from_dict(d2)
    assert type(back) is cls
    p = _grid(7, -100.0, 1100.0)
    assert_allclose(back(p), model(p), rtol=0, atol=1e-9 * SIZE)
    assert back.to_dict() == d2
    # the body of the transform JSON is the same dict; extra keys (the file's stamp) are ignored
    assert transform_to_dict(model) == d
    stamped = {"format": "rectify-stereo/transform", "version": 2, "crs": "EPSG:32633", **d2}
    assert_allclose(transform_from_dict(stamped)(p), model(p), rtol=0, atol=1e-9 * SIZE)


def test_polynomial_order_is_kept(case):
    name, _, model, _ = case
    if name.startswith("poly"):
        assert transform_from_dict(model.to_dict()).order == int(name[-1])


# degenerate inputs: collinear source points (or three collinear for the four-point models)
LINE = np.column_stack([np.linspace(0.0, 900.0, 12), np.linspace(10.0, 460.0, 12)])
DEGENERATE = {
    "homography": (Homography.from_points, {}),
    "affine": (AffineTransform.from_points, {}),
    "cotangent": (CotangentFourPoint.from_points, {}),
    "poly1": (PolynomialTransform.from_points, {"order": 1}),
    "poly2": (PolynomialTransform.from_points, {"order": 2}),
    "poly3": (PolynomialTransform.from_points, {"order": 3}),
}


@pytest.mark.parametrize("name", sorted(DEGENERATE))
def test_collinear_points_raise_estimation_error(name):
    fn, kw = DEGENERATE[name]
    src = LINE[:4] if name == "cotangent" else LINE
    dst = src * 1.5 + [3.0, -2.0]
    with pytest.raises(EstimationError):
        fn(src, dst, **kw)


@pytest.mark.parametrize("name", sorted(DEGENERATE))
def test_too_few_points_raise_estimation_error(name):
    fn, kw = DEGENERATE[name]
    src = SRC4[:2]
    with pytest.raises(EstimationError):
        fn(src, src + 1.0, **kw)


def test_three_collinear_of_four_raise_for_cotangent_and_homography():
    src = np.array([[0.0, 0.0], [500.0, 0.0], [1000.0, 0.0], [0.0, 800.0]])
    dst = Homography(H_TRUE)(src)
    for fn in (CotangentFourPoint.from_points, Homography.from_points):
        with pytest.raises(EstimationError):
            fn(src, dst)


def test_transform_from_dict_reads_order1_polynomial_as_polynomial():
    model = PolynomialTransform.from_points(SRC_N, _smooth(SRC_N), order=1)
    d = transform_to_dict(model)
    assert d["method"] == "affine" and "matrix" not in d
    assert isinstance(transform_from_dict(d), PolynomialTransform)


@pytest.mark.parametrize("d, match", [
    ({"method": "nope"}, "unknown method"),
    ({"method": "homography"}, "misses key"),
    ({"method": "poly2", "coefficients": [[1.0]], "shift": [0, 0]}, "misses key"),
    ([1, 2], "must be an object"),
])
def test_transform_from_dict_rejects_bad_input(d, match):
    with pytest.raises(InvalidInputError, match=match):
        transform_from_dict(d)
