"""Test support for the transforms side (rectify.geometry.transforms, rectify.geometry.analytic): test-only helpers."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.geometry.analytic import TiltedFrame

__all__ = ["rectify_tilted"]


def rectify_tilted(photo_mm: ArrayLike, *, focal_length_mm: float, angles: tuple[float, float, float],
                   order: str = "omega-phi-kappa", principal_point_mm: tuple[float, float] = (0.0, 0.0),
                   f_out_mm: float | None = None) -> NDArray[np.float64]:
    """Functional form of eq. (1): tilted photo mm (N, 2) -> horizontal image mm (N, 2).

    ``angles`` are radians in the named ``order``.
    """
    return TiltedFrame.from_angles(focal_length_mm, *angles, order=order,
                                   principal_point_mm=principal_point_mm, f_out_mm=f_out_mm)(photo_mm)
