"""The interface every planar model implements, and helpers shared by the models.

Every model maps **source** points to **target** points, both (N, 2) float64
arrays in the project's frames (source: pixel frame, x = column right,
y = row down, pixel centres at integers; target: target pixels or map
coordinates; see ``docs/formats.md``). :class:`Transform` is the abstract
base class:

- ``Model.from_points(src, dst, *, weights=None)`` builds a new, immutable
  model (raises :class:`~rectify.errors.EstimationError` on degenerate data,
  :class:`~rectify.errors.InvalidInputError` on malformed data);
- ``model(points)`` maps (N, 2) -> (N, 2);
- ``model.inverse`` returns a new model for the opposite direction (exact for
  the matrix models and the cotangent method, a fitted approximation for
  polynomials);
- ``model.residuals(src, dst)`` returns the (N,) **transfer error**
  ``|model(src) - dst|`` in target units;
- ``model.to_dict()`` returns the parameters as a JSON-ready dict
  (``method``, ``direction`` and the parameters), rebuilt by
  :func:`rectify.geometry.transforms.transform_from_dict`.
"""

from __future__ import annotations

import abc
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.geometry.points import as_pair, check_distinct, check_min_points

__all__ = ["Transform", "F64"]

F64 = NDArray[np.float64]

_CHUNK = 1 << 16  # points per block of the cotangent chain (grouped by base pair)


class Transform(abc.ABC):
    """Abstract base of the planar models (source -> target).

    Subclasses are immutable (frozen dataclasses) and implement every
    abstract member; RANSAC, GCP fitting, warping and the transform file use
    only this interface.
    """

    @classmethod
    @abc.abstractmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None) -> Transform:
        """Estimate the model mapping ``src`` (N, 2) onto ``dst`` (N, 2).

        ``weights`` (N,) are non-negative (1 / variance of the target
        coordinates). Raises EstimationError on degenerate data.
        """

    @abc.abstractmethod
    def __call__(self, points: ArrayLike) -> F64:
        """Map (N, 2) source points to (N, 2) target points."""

    @property
    @abc.abstractmethod
    def inverse(self) -> Transform:
        """A new model for the opposite direction (target -> source)."""

    @abc.abstractmethod
    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error ``|T(src) - dst|``, (N,), target units."""

    @abc.abstractmethod
    def to_dict(self) -> dict[str, Any]:
        """The parameters as a JSON-ready dict: ``method``, ``direction`` and the parameters."""


# --------------------------------------------------------------------------- helpers
def _normalising_similarity(pts: F64, w: F64 | None = None) -> F64:
    """Hartley normalisation: (3, 3) T with T p centred, mean distance sqrt(2)."""
    if w is None:
        c = pts.mean(axis=0)
    else:
        c = (w[:, None] * pts).sum(axis=0) / w.sum()
    d = np.linalg.norm(pts - c, axis=1).mean()
    s = math.sqrt(2.0) / d if d > 0 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _check_model_input(src: ArrayLike, dst: ArrayLike, n_min: int, what: str
                       ) -> tuple[F64, F64]:
    s, d = as_pair(src, dst)
    check_min_points(s, n_min, f"control points for the {what}")
    check_distinct(s, "src")
    check_distinct(d, "dst")
    return s, d
