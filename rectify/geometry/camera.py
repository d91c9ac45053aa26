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

Interior orientation in pixels is the projective one of seed 003 (1.2, eq. 1.4)::

    K = [[fx, s, cx],
         [0, fy, cy],
         [0,  0,  1]]       fx = f / pixel size, fy = aspect * fx, s = shear * fx

A pixel (u, v) is ``K (xd, yd, 1)`` for the distorted normalised coordinates (xd, yd) in
**OpenCV's frame** (x right, y down, origin at the principal point, unit = principal distance).
Distortion follows OpenCV's Brown-Conrady definition (k1, k2, k3 radial, p1, p2 tangential) on
those normalised coordinates, i.e. before ``K``, as ``cv2.projectPoints`` and the calibration
(:mod:`stereo.calibration.model`) apply it. The photo coordinates are those of the ideal camera of
principal distance ``f = fx * pixel size``: ``x = f xn``, ``y = -f yn`` for the undistorted
normalised (xn, yn), so every consumer that works in photo millimetres with the image vector
(x, y, -f) is exact for non-square pixels and skew as long as it converts pixels only through this
class. ``photo_from_pixel`` removes distortion (returns ideal coordinates); ``pixel_from_photo``
applies it. With ``aspect == 1`` and ``shear == 0`` (square pixels, the default) the arithmetic is
the one of a single focal length, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CalibrationError
from rectify.geometry.points import as_points

__all__ = ["Camera", "DISTORTION_KEYS", "NOMINAL_PIXEL_SIZE_MM"]

DISTORTION_KEYS = ("k1", "k2", "k3", "p1", "p2")

#: pixel size given to a camera read in pixels (no physical pixel size), mm: 1 um
NOMINAL_PIXEL_SIZE_MM = 1e-3

_PIXEL_KEYS = ("focal_length_px", "fx_px", "fy_px", "skew_px", "principal_point_px")
_META_KEYS = ("name", "comment", "format", "version", "std_errors", "sigma0_px", "sigma0_mm")


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
    pixel_camera : bool
        The camera was given in pixels (``focal_length_px``, ``principal_point_px``, no pixel
        size, as from calibration or OpenSfM). It is then held with the nominal pixel size
        :data:`NOMINAL_PIXEL_SIZE_MM` (1 um), so geometry is exact and photo-coordinate figures
        in micrometres read as pixels; :meth:`to_dict` writes it back in pixels.
    std_errors : dict
        Standard errors of the interior orientation from a calibration (name -> value, the
        file's units), carried through unchanged.
    sigma0_px : float or None
        sigma0 of that calibration, pixels.
    aspect : float
        fy / fx, the ratio of the principal distances along rows and columns (1: square pixels; > 0).
    shear : float
        s / fx, the skew of ``K`` relative to fx (0: perpendicular pixel axes).

    ``aspect`` and ``shear`` are relative to fx, so a change of the principal distance (a bundle's
    self-calibration of f) keeps the pixel grid's shape: fy and the skew scale with fx.
    """

    focal_length_mm: float
    pixel_size_mm: float
    width: int
    height: int
    principal_point_mm: tuple[float, float] = (0.0, 0.0)
    distortion: dict[str, float] = field(default_factory=dict)
    pixel_camera: bool = False
    std_errors: dict[str, float] = field(default_factory=dict)
    sigma0_px: float | None = None
    aspect: float = 1.0
    shear: float = 0.0

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
        raw_pp = self.principal_point_mm
        pp: tuple[float, ...] = ()
        if isinstance(raw_pp, (list, tuple, np.ndarray)) and all(_is_number(c) for c in np.asarray(raw_pp).ravel()):
            pp = tuple(float(c) for c in np.asarray(raw_pp, dtype=float).reshape(-1))
        if len(pp) != 2 or not all(math.isfinite(c) for c in pp):
            raise CalibrationError(
                f"camera `principal_point_mm` must be two finite numbers [x0, y0]; got {raw_pp!r}")
        object.__setattr__(self, "principal_point_mm", pp)
        if self.distortion is not None and not isinstance(self.distortion, Mapping):
            raise CalibrationError(f"camera `distortion` must be an object such as {{\"k1\": 0.0, \"p1\": 0.0}}; "
                                   f"got {self.distortion!r}")
        dist = dict(self.distortion or {})
        unknown = set(dist) - set(DISTORTION_KEYS)
        if unknown:
            raise CalibrationError(
                f"unknown distortion coefficient(s) {sorted(unknown)}; expected {list(DISTORTION_KEYS)}")
        clean = {}
        for k in DISTORTION_KEYS:
            raw = dist.get(k, 0.0)
            if not _is_number(raw) or not math.isfinite(float(raw)):
                raise CalibrationError(f"distortion `{k}` must be a finite number; got {raw!r}")
            clean[k] = float(raw)
        object.__setattr__(self, "distortion", clean)
        if self.std_errors is not None and not isinstance(self.std_errors, Mapping):
            raise CalibrationError(f"camera `std_errors` must be an object (name -> value); got {self.std_errors!r}")
        se = dict(self.std_errors or {})
        for k, v in se.items():
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
                raise CalibrationError(f"camera standard error `{k}` must be a finite number >= 0; got {v!r}")
        object.__setattr__(self, "std_errors", {str(k): float(v) for k, v in se.items()})
        if self.sigma0_px is not None:
            v = self.sigma0_px
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
                raise CalibrationError(f"camera `sigma0_px` must be a finite number >= 0; got {v!r}")
            object.__setattr__(self, "sigma0_px", float(v))
        object.__setattr__(self, "pixel_camera", bool(self.pixel_camera))
        for name, low in (("aspect", 0.0), ("shear", None)):
            v = getattr(self, name)
            if not _is_number(v) or not math.isfinite(float(v)) or (low is not None and v <= low):
                raise CalibrationError(f"camera `{name}` must be a finite number{' > 0' if low is not None else ''}; "
                                       f"got {v!r}")
            object.__setattr__(self, name, float(v))

    # ------------------------------------------------------------------ derived
    @property
    def focal_px(self) -> float:
        """Principal distance in pixels along the columns, fx (the one principal distance when pixels are square)."""
        return self.focal_length_mm / self.pixel_size_mm

    @property
    def fy_px(self) -> float:
        """Principal distance in pixels along the rows, fy = aspect * fx."""
        return self.focal_px * self.aspect

    @property
    def skew_px(self) -> float:
        """Skew s of ``K``, px (s = shear * fx)."""
        return self.focal_px * self.shear

    @property
    def square(self) -> bool:
        """One principal distance and perpendicular pixel axes (fx == fy, no skew)."""
        return self.aspect == 1.0 and self.shear == 0.0

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
        if self.square:
            return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        return np.array([[f, self.skew_px, cx], [0.0, self.fy_px, cy], [0.0, 0.0, 1.0]])

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
        if self.square:
            n = (px - c) / self.focal_px  # OpenCV normalised frame, y down, distorted
        else:  # K^-1 (u, v, 1)
            d = px - c
            yn = d[:, 1] / self.fy_px
            n = np.column_stack([(d[:, 0] - self.skew_px * yn) / self.focal_px, yn])
        if self.has_distortion:
            n = self._undistort_normalised(n)
        return np.column_stack([n[:, 0], -n[:, 1]]) * self.focal_length_mm

    def pixel_from_photo(self, photo_mm: ArrayLike) -> NDArray[np.float64]:
        """Ideal photo coordinates (N, 2), mm -> pixel (N, 2) with distortion applied."""
        mm = as_points(photo_mm, "photo_mm")
        n = np.column_stack([mm[:, 0], -mm[:, 1]]) / self.focal_length_mm
        if self.has_distortion:
            n = self._distort_normalised(n)
        if self.square:
            return n * self.focal_px + self.principal_point_px
        cx, cy = self.principal_point_px
        return np.column_stack([self.focal_px * n[:, 0] + self.skew_px * n[:, 1] + cx, self.fy_px * n[:, 1] + cy])

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
        """The camera JSON object (``docs/formats.md``) without the format stamp (it is embedded in other files).

        A pixel camera is written in pixels: ``focal_length_px`` when its pixels are square
        (:attr:`square`), else ``fx_px``, ``fy_px`` and ``skew_px`` (the last only when not 0);
        then ``principal_point_px``.

        Raises
        ------
        CalibrationError
            A millimetre camera with non-square pixels or skew (the millimetre form has one
            principal distance and square pixels: write it as a pixel camera).
        """
        out: dict[str, Any]
        if self.pixel_camera:
            if self.square:
                out = {"focal_length_px": self.focal_px}
            else:
                out = {"fx_px": self.focal_px, "fy_px": self.fy_px}
                if self.shear != 0.0:
                    out["skew_px"] = self.skew_px
            out.update(principal_point_px=[float(c) for c in self.principal_point_px], width=self.width,
                       height=self.height)
        else:
            if not self.square:
                raise CalibrationError(f"a millimetre camera has square pixels and no skew; this one has fy/fx "
                                       f"{self.aspect!r} and skew/fx {self.shear!r}: write it as a pixel camera")
            out = {
                "focal_length_mm": self.focal_length_mm,
                "pixel_size_mm": self.pixel_size_mm,
                "width": self.width,
                "height": self.height,
            }
            if any(self.principal_point_mm):
                out["principal_point_mm"] = list(self.principal_point_mm)
        if self.has_distortion:
            out["distortion"] = dict(self.distortion)
        if self.std_errors:
            out["std_errors"] = dict(self.std_errors)
        if self.sigma0_px is not None:
            out["sigma0_px"] = self.sigma0_px
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """Build from the camera JSON object (``docs/formats.md``); unknown keys are rejected by name.

        Two forms are read: a millimetre camera (``focal_length_mm``, ``pixel_size_mm``, optional
        ``principal_point_mm``; square pixels) and a pixel camera (``focal_length_px``, or ``fx_px`` and
        ``fy_px``; optional ``skew_px``; ``principal_point_px`` in the pixel frame), both with
        ``width``, ``height``, optional
        ``distortion``, ``std_errors`` and ``sigma0_px``. The ``format``/``version`` stamp of a
        camera file is accepted and not checked here (:func:`rectify.formats.camera.read_camera` checks it).
        """
        if not isinstance(d, dict):
            raise CalibrationError(f"camera JSON must be an object; got {type(d).__name__}")
        if any(k in d for k in _PIXEL_KEYS) and "pixel_size_mm" not in d:
            return cls._from_pixel_dict(d)
        required = ("focal_length_mm", "pixel_size_mm", "width", "height")
        missing = [k for k in required if k not in d]
        if missing:
            raise CalibrationError(f"camera JSON lacks required key(s) {missing} (or give focal_length_px and "
                                   "principal_point_px for a camera in pixels)")
        allowed = set(required) | {"principal_point_mm", "distortion", "point_of_symmetry_mm", *_META_KEYS}
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise CalibrationError(f"camera JSON has unknown key(s) {unknown}")
        pp = d.get("principal_point_mm", (0.0, 0.0))
        if not isinstance(pp, (list, tuple)) or len(pp) != 2 or not all(_is_number(c) for c in pp):
            raise CalibrationError(f"camera `principal_point_mm` must be two numbers [x0, y0]; got {pp!r}")
        pp = tuple(pp)
        _same_point(d, "point_of_symmetry_mm", pp)
        return cls(
            focal_length_mm=d["focal_length_mm"],
            pixel_size_mm=d["pixel_size_mm"],
            width=d["width"],
            height=d["height"],
            principal_point_mm=pp,
            distortion=d.get("distortion", {}) or {},
            std_errors=d.get("std_errors", {}) or {},
            sigma0_px=d.get("sigma0_px"),
        )

    @classmethod
    def _from_pixel_dict(cls, d: dict[str, Any]) -> Camera:
        allowed = {"width", "height", "distortion", "point_of_symmetry_px", *_PIXEL_KEYS, *_META_KEYS}
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise CalibrationError(f"camera JSON has unknown key(s) {unknown}")
        missing = [k for k in ("width", "height", "principal_point_px") if k not in d]
        if missing:
            raise CalibrationError(f"camera JSON in pixels lacks required key(s) {missing}")
        fx, fy, skew = _pixel_focals(d)
        w, h = d["width"], d["height"]
        if isinstance(w, bool) or not isinstance(w, int) or w <= 0 or isinstance(h, bool) or not isinstance(h, int) \
                or h <= 0:
            raise CalibrationError(f"camera `width`, `height` must be positive integers; got {w!r}, {h!r}")
        raw_pp = d["principal_point_px"]
        pp = np.asarray(raw_pp, dtype=float).reshape(-1) \
            if isinstance(raw_pp, (list, tuple)) and all(_is_number(c) for c in raw_pp) else np.array([np.nan])
        if pp.shape != (2,) or not np.all(np.isfinite(pp)):
            raise CalibrationError(f"camera `principal_point_px` must be two finite numbers; "
                                   f"got {d['principal_point_px']!r}")
        _same_point(d, "point_of_symmetry_px", tuple(pp))
        ps = NOMINAL_PIXEL_SIZE_MM
        x0 = (pp[0] - (w - 1) / 2.0) * ps
        y0 = -(pp[1] - (h - 1) / 2.0) * ps
        square = fy == fx and skew == 0.0
        return cls(focal_length_mm=fx * ps, pixel_size_mm=ps, width=w, height=h, principal_point_mm=(x0, y0),
                   distortion=d.get("distortion", {}) or {}, pixel_camera=True,
                   std_errors=d.get("std_errors", {}) or {}, sigma0_px=d.get("sigma0_px"),
                   aspect=1.0 if square else fy / fx, shear=0.0 if square else skew / fx)


def _pixel_focals(d: dict[str, Any]) -> tuple[float, float, float]:
    """fx, fy, skew (px) of a pixel camera's JSON: ``focal_length_px`` (fx = fy) or ``fx_px`` and ``fy_px``,
    and ``skew_px`` (default 0). ``focal_length_px`` given with ``fx_px``/``fy_px`` must equal both."""
    vals: dict[str, float] = {}
    for k in ("focal_length_px", "fx_px", "fy_px", "skew_px"):
        if k in d:
            v = d[k]
            if not _is_number(v) or not math.isfinite(float(v)) or (k != "skew_px" and v <= 0):
                bound = "" if k == "skew_px" else " > 0"
                raise CalibrationError(f"camera `{k}` must be a finite number{bound}; got {v!r}")
            vals[k] = float(v)
    has_xy = [k for k in ("fx_px", "fy_px") if k in vals]
    if len(has_xy) == 1:
        missing = "fy_px" if has_xy == ["fx_px"] else "fx_px"
        raise CalibrationError(f"camera JSON in pixels gives `{has_xy[0]}` {vals[has_xy[0]]!r} without `{missing}`; "
                               "give both (or `focal_length_px` for square pixels)")
    if "focal_length_px" in vals:
        f = vals["focal_length_px"]
        if has_xy and (vals["fx_px"] != f or vals["fy_px"] != f):
            raise CalibrationError(f"camera `focal_length_px` {f!r} contradicts `fx_px` {vals['fx_px']!r}, `fy_px` "
                                   f"{vals['fy_px']!r}: give one of them")
        fx = fy = f
    elif has_xy:
        fx, fy = vals["fx_px"], vals["fy_px"]
    else:
        raise CalibrationError("camera JSON in pixels needs `focal_length_px` (or `fx_px` and `fy_px`)")
    return fx, fy, vals.get("skew_px", 0.0)


def _is_number(v: Any) -> bool:
    """A JSON number (not a bool, not a string)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _same_point(d: dict[str, Any], key: str, principal_point: tuple[float, ...]) -> None:
    """Refuse a point of symmetry of distortion apart from the principal point (not in this camera model)."""
    if key not in d:
        return
    try:
        ps = tuple(float(c) for c in d[key])
    except (TypeError, ValueError) as err:
        raise CalibrationError(f"camera `{key}` must be two numbers; got {d[key]!r}") from err
    if len(ps) != 2 or any(abs(a - b) > 1e-9 for a, b in zip(ps, principal_point, strict=False)):
        raise CalibrationError(f"camera `{key}` {list(ps)} differs from the principal point "
                               f"{list(principal_point)}; the frame camera model has no separate point of symmetry: "
                               "calibrate without it")
