"""One exception tree for the whole project (``stereo`` reuses it).

Every error carries a message that names the offending value. Third-party
errors (rasterio, pyproj, OpenCV) are wrapped with ``raise ... from err``.
"""

from __future__ import annotations

__all__ = [
    "RectifyError",
    "InvalidInputError",
    "ShapeError",
    "EstimationError",
    "ConvergenceError",
    "CRSError",
    "RasterIOError",
    "StereoError",
    "CalibrationError",
    "SchedulerError",
    "RectifyWarning",
    "WeakGeometryWarning",
    "NotGeoreferencedWarning",
]


class RectifyError(Exception):
    """Root of every error raised by :mod:`rectify` and :mod:`stereo`."""


class InvalidInputError(RectifyError, ValueError):
    """An argument has a bad value: NaN, too few points, unknown option, ..."""


class ShapeError(InvalidInputError):
    """An array has the wrong shape.

    Attributes
    ----------
    actual_shape, expected_shape : tuple
        What was given and what was expected (``None`` stands for "any").
    """

    def __init__(self, message: str, *, actual_shape=None, expected_shape=None):
        super().__init__(message)
        self.actual_shape = actual_shape
        self.expected_shape = expected_shape


class EstimationError(RectifyError):
    """A model cannot be estimated from the data (degenerate, too few points)."""


class ConvergenceError(EstimationError):
    """An iterative estimator did not converge.

    Attributes
    ----------
    iterations : int or None
        Iterations performed before giving up.
    """

    def __init__(self, message: str, *, iterations: int | None = None):
        super().__init__(message)
        self.iterations = iterations


class CRSError(RectifyError, ValueError):
    """A coordinate reference system is unknown, missing or mismatched."""


class RasterIOError(RectifyError, OSError):
    """A raster or table cannot be read or written."""


class StereoError(RectifyError):
    """A stereo-specific failure (orientation, intersection, model)."""


class CalibrationError(StereoError):
    """Interior orientation (camera) is invalid or inconsistent."""


class SchedulerError(RectifyError, OSError):
    """A Dask scheduler cannot be reached, a cluster cannot be started, or it lost a task
    (:mod:`rectify.raster.distributed`)."""


class RectifyWarning(UserWarning):
    """Base of the project's warnings."""


class WeakGeometryWarning(RectifyWarning):
    """The normal equations are badly conditioned: results are imprecise."""


class NotGeoreferencedWarning(RectifyWarning):
    """A raster has no CRS or geotransform."""
