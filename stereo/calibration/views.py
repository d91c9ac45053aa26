"""Measured target points of one image (a view of a plane target or of a 3D test field).

A :class:`TargetView` holds the object coordinates of the target points and their measured pixels;
views come from chessboard detection (:mod:`stereo.features.targets`) or from observation and field
CSV files (:mod:`stereo.formats.calibration`), and the calibration (:mod:`stereo.calibration.result`)
adjusts them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError, ShapeError

__all__ = ["TargetView", "check_inside"]

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class TargetView:
    """The measured target points of one image.

    Attributes
    ----------
    name : str
        View name (file stem or the CSV's ``view``).
    object_xyz : (N, 3) float64
        Target coordinates, object frame and units.
    pixel : (N, 2) float64
        Measured pixels (col, row).
    ids : tuple of str, length N
        Point identifiers.
    """

    name: str
    object_xyz: F64
    pixel: F64
    ids: tuple[str, ...]

    def __post_init__(self) -> None:
        X = np.array(self.object_xyz, dtype=np.float64, copy=True)
        x = np.array(self.pixel, dtype=np.float64, copy=True)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ShapeError(f"view {self.name!r}: `object_xyz` must have shape (N, 3); got {X.shape}",
                             actual_shape=X.shape, expected_shape=(None, 3))
        if x.shape != (len(X), 2):
            raise ShapeError(f"view {self.name!r}: `pixel` must have shape ({len(X)}, 2); got {x.shape}",
                             actual_shape=x.shape, expected_shape=(len(X), 2))
        if not (np.isfinite(X).all() and np.isfinite(x).all()):
            raise InvalidInputError(f"view {self.name!r} has NaN or infinite coordinates")
        ids = tuple(str(i) for i in self.ids) if self.ids is not None else tuple(str(i) for i in range(len(X)))
        if len(ids) != len(X):
            raise ShapeError(f"view {self.name!r}: {len(ids)} ids for {len(X)} points", actual_shape=(len(ids),))
        X.flags.writeable = False
        x.flags.writeable = False
        object.__setattr__(self, "object_xyz", X)
        object.__setattr__(self, "pixel", x)
        object.__setattr__(self, "ids", ids)

    @property
    def n(self) -> int:
        return len(self.ids)

    @property
    def is_planar(self) -> bool:
        """True when the object points lie on one plane (thickness < 1e-6 of the extent)."""
        if self.n < 4:
            return True
        sv = np.linalg.svd(self.object_xyz - self.object_xyz.mean(axis=0), compute_uv=False)
        return bool(sv[2] <= 1e-6 * sv[0])


def check_inside(views: Iterable[TargetView], width: int, height: int) -> None:
    """Raise :class:`InvalidInputError` naming the first point outside the image."""
    for v in views:
        x = v.pixel
        bad = (x[:, 0] < -0.5) | (x[:, 0] > width - 0.5) | (x[:, 1] < -0.5) | (x[:, 1] > height - 0.5)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidInputError(
                f"view {v.name!r}: point {v.ids[i]!r} at ({x[i, 0]:.2f}, {x[i, 1]:.2f}) px is outside the "
                f"{width} x {height} image ({int(bad.sum())} such points)")
