"""Planar transforms for 2D rectification: projective, cotangent four-point,
affine and polynomial models, with one interface (:class:`Transform`).

Modules
-------
base        the abstract base :class:`Transform` and helpers shared by the models
matrix      :class:`Homography`, :class:`AffineTransform` ((3, 3) matrix models)
polynomial  :class:`PolynomialTransform` (orders 1-3) and its fitted inverse
cotangent   :class:`CotangentFourPoint` (seed 001, corrected eq. 2) and the eq. (2) helpers
gcp         :data:`METHODS` (the one list of methods), :func:`fit_gcps`, :class:`FitResult`,
            :func:`transform_to_dict` / :func:`transform_from_dict` (the body of the transform
            JSON, which :mod:`rectify.formats.transform` reads and writes)

The theory and the study are in ``docs/projective.md``.
"""

from rectify.geometry.transforms.base import Transform
from rectify.geometry.transforms.cotangent import (
    COT_MAX_REL_ERROR,
    PAIRS,
    CotangentFourPoint,
    base_cotangents,
    corrected_eq2,
    printed_eq2,
)
from rectify.geometry.transforms.gcp import (
    METHODS,
    FitResult,
    fit_gcps,
    method_of,
    transform_from_dict,
    transform_to_dict,
)
from rectify.geometry.transforms.matrix import AffineTransform, Homography
from rectify.geometry.transforms.polynomial import PolynomialTransform

__all__ = [
    "Transform", "Homography", "AffineTransform", "PolynomialTransform", "CotangentFourPoint",
    "METHODS", "FitResult", "fit_gcps", "method_of", "transform_to_dict", "transform_from_dict",
    "COT_MAX_REL_ERROR", "PAIRS",
    "base_cotangents", "printed_eq2", "corrected_eq2",
]
