"""Interior orientation: the one place that knows the image frame.

Frames
------
pixel
    (N, 2) float64, x = column (right), y = row (down), the centre of the
    top-left pixel at (0, 0).
photo
    (N, 2) float64 millimetres from the principal point, x right, y up. The
    projection centre is at (0, 0, +f), so an image point is the vector
    (x, y, -f).

Distortion follows OpenCV's Brown-Conrady definition (k1, k2, k3 radial, p1, p2
tangential) on coordinates normalised by the focal length **in OpenCV's frame**
(x right, y down, origin at the principal point). ``photo_from_pixel`` removes
distortion (returns ideal coordinates); ``pixel_from_photo`` applies it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import CalibrationError
from .points import as_points

__all__ = ["Camera", "DISTORTION_KEYS"]

DISTORTION_KEYS = ("k1", "k2", "k3", "p1", "p2")


@dataclass(frozen=True, eq=False)
class Camera:
    """Frame camera interior orientation.

    Parameters
    ----------
    focal_length_mm : float
        Principal distance f, mm (> 0).
    pixel_size_mm : float
        Side of a square pixel, mm (> 0).
    width, height : int
        Image size in pixels.
    principal_point_mm : (2,) float
        Offset (x0, y0) of the principal point from the image centre, photo
        axes (x right, y up), mm.
    distortion : dict
        Brown-Conrady coefficients ``k1, k2, k3, p1, p2`` (missing ones are 0).
    """

    focal_length_mm: float
    pixel_size_mm: float
    width: int
    height: int
    principal_point_mm: tuple[float, float] = (0.0, 0.0)
    distortion: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "pixel_size_mm"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise CalibrationError(f"camera `{name}` must be a finite number > 0; got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
                raise CalibrationError(f"camera `{name}` must be a positive integer; got {v!r}")
            object.__setattr__(self, name, int(v))
        pp = tuple(float(c) for c in np.asarray(self.principal_point_mm, dtype=float).reshape(-1))
        if len(pp) != 2 or not all(math.isfinite(c) for c in pp):
            raise CalibrationError(
                f"camera `principal_point_mm` must be two finite numbers; got {self.principal_point_mm!r}")
        object.__setattr__(self, "principal_point_mm", pp)
        dist = dict(self.distortion or {})
        unknown = set(dist) - set(DISTORTION_KEYS)
        if unknown:
            raise CalibrationError(
                f"unknown distortion coefficient(s) {sorted(unknown)}; expected {list(DISTORTION_KEYS)}")
        clean = {}
        for k in DISTORTION_KEYS:
            v = float(dist.get(k, 0.0))
            if not math.isfinite(v):
                raise CalibrationError(f"distortion `{k}` must be finite; got {v!r}")
            clean[k] = v
        object.__setattr__(self, "distortion", clean)

    # ------------------------------------------------------------------ derived
    @property
    def focal_px(self) -> float:
        """Principal distance in pixels."""
        return self.focal_length_mm / self.pixel_size_mm

    @property
    def principal_point_px(self) -> NDArray[np.float64]:
        """Principal point (col, row) in the pixel frame, (2,)."""
        cx = (self.width - 1) / 2.0 + self.principal_point_mm[0] / self.pixel_size_mm
        cy = (self.height - 1) / 2.0 - self.principal_point_mm[1] / self.pixel_size_mm
        return np.array([cx, cy])

    @property
    def K(self) -> NDArray[np.float64]:
        """OpenCV intrinsic matrix (3, 3), pixel frame (x right, y down)."""
        cx, cy = self.principal_point_px
        f = self.focal_px
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> NDArray[np.float64]:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        d = self.distortion
        return np.array([d["k1"], d["k2"], d["p1"], d["p2"], d["k3"]])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.distortion.values())

    # ------------------------------------------------------------- conversions
    def photo_from_pixel(self, pixel: ArrayLike) -> NDArray[np.float64]:
        """Pixel (N, 2) -> ideal (undistorted) photo coordinates (N, 2), mm."""
        px = as_points(pixel, "pixel")
        c = self.principal_point_px
        n = (px - c) / self.focal_px  # OpenCV normalised frame, y down, distorted
        if self.has_distortion:
            n = self._undistort_normalised(n)
        return np.column_stack([n[:, 0], -n[:, 1]]) * self.focal_length_mm

    def pixel_from_photo(self, photo_mm: ArrayLike) -> NDArray[np.float64]:
        """Ideal photo coordinates (N, 2), mm -> pixel (N, 2) with distortion applied."""
        mm = as_points(photo_mm, "photo_mm")
        n = np.column_stack([mm[:, 0], -mm[:, 1]]) / self.focal_length_mm
        if self.has_distortion:
            n = self._distort_normalised(n)
        return n * self.focal_px + self.principal_point_px

    def _distort_normalised(self, n: NDArray[np.float64]) -> NDArray[np.float64]:
        d = self.distortion
        x, y = n[:, 0], n[:, 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (d["k1"] + r2 * (d["k2"] + r2 * d["k3"]))
        xd = x * radial + 2 * d["p1"] * x * y + d["p2"] * (r2 + 2 * x * x)
        yd = y * radial + d["p1"] * (r2 + 2 * y * y) + 2 * d["p2"] * x * y
        return np.column_stack([xd, yd])

    def _undistort_normalised(self, nd: NDArray[np.float64], *, iterations: int = 50,
                              tol: float = 1e-14) -> NDArray[np.float64]:
        """Invert the distortion by Newton iteration with a numeric Jacobian."""
        n = nd.copy()
        eps = 1e-7
        for _ in range(iterations):
            f = self._distort_normalised(n) - nd
            if np.max(np.abs(f), initial=0.0) < tol:
                break
            fx = (self._distort_normalised(n + [eps, 0.0]) - self._distort_normalised(n - [eps, 0.0])) / (2 * eps)
            fy = (self._distort_normalised(n + [0.0, eps]) - self._distort_normalised(n - [0.0, eps])) / (2 * eps)
            det = fx[:, 0] * fy[:, 1] - fy[:, 0] * fx[:, 1]
            if np.any(np.abs(det) < 1e-12):
                raise CalibrationError("distortion model is not invertible at some image points")
            n[:, 0] -= (fy[:, 1] * f[:, 0] - fy[:, 0] * f[:, 1]) / det
            n[:, 1] -= (-fx[:, 1] * f[:, 0] + fx[:, 0] * f[:, 1]) / det
        return n

    def rays_from_pixel(self, pixel: ArrayLike) -> NDArray[np.float64]:
        """Image-space vectors (x, y, -f), (N, 3) mm, for pixels (N, 2)."""
        mm = self.photo_from_pixel(pixel)
        return np.column_stack([mm, np.full(len(mm), -self.focal_length_mm)])

    # -------------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        """The camera JSON object (``docs/formats.md``) without the format stamp (it is embedded in other files)."""
        out: dict[str, Any] = {
            "focal_length_mm": self.focal_length_mm,
            "pixel_size_mm": self.pixel_size_mm,
            "width": self.width,
            "height": self.height,
        }
        if any(self.principal_point_mm):
            out["principal_point_mm"] = list(self.principal_point_mm)
        if self.has_distortion:
            out["distortion"] = dict(self.distortion)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """Build from the camera JSON object (``docs/formats.md``); unknown keys are rejected by name.

        The ``format``/``version`` stamp of a camera file is accepted and not checked here
        (:func:`rectify.formats.read_camera` checks it).
        """
        if not isinstance(d, dict):
            raise CalibrationError(f"camera JSON must be an object; got {type(d).__name__}")
        required = ("focal_length_mm", "pixel_size_mm", "width", "height")
        missing = [k for k in required if k not in d]
        if missing:
            raise CalibrationError(f"camera JSON lacks required key(s) {missing}")
        allowed = set(required) | {"principal_point_mm", "distortion", "name", "comment", "format", "version"}
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise CalibrationError(f"camera JSON has unknown key(s) {unknown}")
        return cls(
            focal_length_mm=d["focal_length_mm"],
            pixel_size_mm=d["pixel_size_mm"],
            width=d["width"],
            height=d["height"],
            principal_point_mm=tuple(d.get("principal_point_mm", (0.0, 0.0))),
            distortion=d.get("distortion", {}) or {},
        )

    @classmethod
    def from_json(cls, path: str | Path) -> Camera:
        """Read a camera JSON file (:func:`rectify.formats.read_camera`)."""
        from .formats import read_camera  # import cycle: rectify.formats builds cameras

        return read_camera(path)
