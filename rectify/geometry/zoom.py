"""A zoom camera (seed 003, 1.6): the interior orientation evaluated at an image's focal setting.

``stereo calibrate --zoom`` calibrates a zoom lens at several focal settings ``z_1..z_m`` (a zoom
ring reading, the EXIF focal length in mm, an encoder count) and fits each element ``e`` of the
interior orientation (``f`` or ``fx``/``fy``, ``cx``, ``cy`` in px; ``k1``.. unitless) by a polynomial
of degree ``d`` in the normalised setting ``u = (z - centre) / half_range``::

    e(z) = a_0 + a_1 u + ... + a_d u^d

(:class:`stereo.calibration.zoom.ZoomModel`). A :class:`ZoomCamera` holds the fitted coefficients
and their covariances and gives the :class:`~rectify.geometry.camera.Camera` of one image at its
setting, with the standard errors of the prediction ``sqrt(a(u)^T C a(u))``.

A setting outside the calibrated range is refused: polynomials diverge quickly outside their data.
A margin of :data:`ZOOM_MARGIN` of the calibrated span is accepted on either side (EXIF focal
lengths are rounded; the wide and tele ends are read back as the values calibrated there).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CalibrationError, InvalidInputError
from rectify.geometry.camera import Camera

__all__ = ["ZOOM_MARGIN", "ZOOM_ELEMENTS", "ZoomCamera"]

F64 = NDArray[np.float64]

#: share of the calibrated span (max - min setting) accepted beyond either end of it
ZOOM_MARGIN = 0.01
#: the elements a zoom camera may model (the names of the calibration adjustment)
ZOOM_ELEMENTS = ("f", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
_DIST = ("k1", "k2", "k3", "p1", "p2")


def _number(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise CalibrationError(f"zoom camera `{what}` must be a finite number; got {v!r}")
    return float(v)


@dataclass(frozen=True, eq=False)
class ZoomCamera:
    """Interior orientation of a zoom lens as polynomials of the focal setting.

    Attributes
    ----------
    settings : (m,) float64
        The calibrated settings (their min and max bound the range).
    degree : int
    centre, half_range : float
        Normalisation ``u = (z - centre) / half_range``.
    coefficients : dict name -> (degree + 1,) float64
        Increasing powers of ``u``; ``f`` or ``fx``/``fy`` and ``cx``, ``cy`` in px (pixel frame:
        col right, row down), distortion unitless (Brown ``k1..k3``, ``p1``, ``p2``).
    covariances : dict name -> (degree + 1, degree + 1) float64
    width, height : int
        Image size, px.
    unit : str
        What the setting is (``"mm"`` for EXIF focal lengths), for messages.
    """

    settings: F64
    degree: int
    centre: float
    half_range: float
    coefficients: dict[str, F64]
    covariances: dict[str, F64]
    width: int
    height: int
    unit: str = ""

    def __post_init__(self) -> None:
        names = set(self.coefficients)
        bad = sorted(names - set(ZOOM_ELEMENTS))
        if bad:
            raise CalibrationError(f"zoom camera has unknown element(s) {bad}; known: {list(ZOOM_ELEMENTS)}")
        if not ({"cx", "cy"} <= names and ("f" in names or {"fx", "fy"} <= names)):
            raise CalibrationError(f"zoom camera lacks the focal length or the principal point; has {sorted(names)}")
        if self.degree < 0 or len(self.settings) < self.degree + 1:
            raise CalibrationError(f"zoom camera of degree {self.degree} needs at least {self.degree + 1} "
                                   f"settings; has {len(self.settings)}")
        for n, a in self.coefficients.items():
            cov = self.covariances.get(n)
            if np.shape(a) != (self.degree + 1,) or cov is None or np.shape(cov) != (self.degree + 1,) * 2:
                raise CalibrationError(f"zoom camera element {n!r}: {self.degree + 1} coefficients and a "
                                       f"{self.degree + 1} x {self.degree + 1} covariance expected")

    # ----------------------------------------------------------------- range
    @property
    def low(self) -> float:
        return float(np.min(self.settings))

    @property
    def high(self) -> float:
        return float(np.max(self.settings))

    @property
    def margin(self) -> float:
        """Accepted distance beyond either end of the calibrated range (:data:`ZOOM_MARGIN` of the span)."""
        return ZOOM_MARGIN * (self.high - self.low)

    def check_setting(self, setting: float) -> float:
        """``setting`` as a float when inside the calibrated range (plus the margin).

        Raises
        ------
        InvalidInputError
            Not a finite number.
        CalibrationError
            Outside the calibrated range (the range and the margin named).
        """
        try:
            z = float(setting)
        except (TypeError, ValueError):
            raise InvalidInputError(f"focal setting must be a number; got {setting!r}") from None
        if not math.isfinite(z):
            raise InvalidInputError(f"focal setting must be finite; got {setting!r}")
        m = self.margin
        if z < self.low - m or z > self.high + m:
            u = f" {self.unit}" if self.unit else ""
            raise CalibrationError(f"focal setting {z:g}{u} is outside the zoom camera's calibrated range "
                                   f"{self.low:g}..{self.high:g}{u} (margin {m:.3g}{u}); calibrate that setting "
                                   "or extend the zoom calibration")
        return z

    # ----------------------------------------------------------------- evaluation
    def predict(self, setting: float) -> tuple[dict[str, float], dict[str, float]]:
        """Elements and their standard errors at ``setting`` (refused outside the range, :meth:`check_setting`)."""
        z = self.check_setting(setting)
        a = np.vander([(z - self.centre) / self.half_range], self.degree + 1, increasing=True)[0]
        val = {n: float(a @ c) for n, c in self.coefficients.items()}
        se = {n: float(math.sqrt(max(float(a @ self.covariances[n] @ a), 0.0))) for n in self.coefficients}
        return val, se

    def camera_dict(self, setting: float) -> dict[str, Any]:
        """The pixel camera JSON body (:meth:`Camera.from_dict` keys) at ``setting``, with the prediction's
        standard errors (``std_errors``: ``fx_px``.., ``cx_px``, ``cy_px``, distortion)."""
        v, se = self.predict(setting)
        fx = v.get("fx", v.get("f"))
        fy = v.get("fy", v.get("f"))
        assert fx is not None and fy is not None  # checked in __post_init__
        body: dict[str, Any] = {"width": self.width, "height": self.height}
        if "f" in v:
            body["focal_length_px"] = fx
        else:
            body["fx_px"], body["fy_px"] = fx, fy
        body["principal_point_px"] = [v["cx"], v["cy"]]
        body["distortion"] = {k: v.get(k, 0.0) for k in _DIST}
        ren = {"f": "focal_length_px", "fx": "fx_px", "fy": "fy_px", "cx": "cx_px", "cy": "cy_px"}
        body["std_errors"] = {ren.get(k, k): s for k, s in se.items()}
        return body

    def camera(self, setting: float) -> Camera:
        """The camera of an image taken at ``setting``.

        Raises
        ------
        CalibrationError
            ``setting`` outside the calibrated range; a predicted camera that is not valid.
        """
        return Camera.from_dict(self.camera_dict(setting))

    # ----------------------------------------------------------------- JSON body
    def to_dict(self) -> dict[str, Any]:
        """The body of the zoom camera JSON (``docs/formats.md``; the format stamp is added by the writer)."""
        return {"width": self.width, "height": self.height, "setting_unit": self.unit, "degree": self.degree,
                "settings": [float(z) for z in self.settings], "centre": self.centre,
                "half_range": self.half_range, "margin": ZOOM_MARGIN,
                "elements": {n: {"coefficients": self.coefficients[n].tolist(),
                                 "covariance": self.covariances[n].tolist()} for n in self.coefficients}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ZoomCamera:
        """Build from the zoom camera JSON body; unknown or malformed keys raise :class:`CalibrationError`."""
        if not isinstance(d, Mapping):
            raise CalibrationError(f"zoom camera JSON must be an object; got {type(d).__name__}")
        need = ("width", "height", "degree", "settings", "centre", "half_range", "elements")
        missing = [k for k in need if k not in d]
        if missing:
            raise CalibrationError(f"zoom camera JSON lacks key(s) {missing}")
        w, h, deg = d["width"], d["height"], d["degree"]
        if not all(isinstance(x, int) and not isinstance(x, bool) for x in (w, h, deg)) or w < 1 or h < 1 or deg < 0:
            raise CalibrationError(f"zoom camera `width`, `height`, `degree` must be integers (size > 0); "
                                   f"got {w!r}, {h!r}, {deg!r}")
        s = d["settings"]
        if not isinstance(s, list) or not s:
            raise CalibrationError(f"zoom camera `settings` must be a list of numbers; got {s!r}")
        settings = np.array([_number(z, "settings") for z in s])
        half = _number(d["half_range"], "half_range")
        if half <= 0:
            raise CalibrationError(f"zoom camera `half_range` must be > 0; got {half!r}")
        el = d["elements"]
        if not isinstance(el, Mapping) or not el:
            raise CalibrationError("zoom camera `elements` must be an object of elements")
        coefs, covs = {}, {}
        for n, e in el.items():
            if not isinstance(e, Mapping) or "coefficients" not in e or "covariance" not in e:
                raise CalibrationError(f"zoom camera element {n!r} needs `coefficients` and `covariance`")
            try:
                a = np.asarray(e["coefficients"], dtype=np.float64)
                c = np.asarray(e["covariance"], dtype=np.float64)
            except (TypeError, ValueError):
                raise CalibrationError(f"zoom camera element {n!r}: coefficients and covariance must be "
                                       "numbers") from None
            if not (np.isfinite(a).all() and np.isfinite(c).all()):
                raise CalibrationError(f"zoom camera element {n!r}: coefficients and covariance must be finite")
            coefs[str(n)], covs[str(n)] = a, c
        unit = d.get("setting_unit", "")
        return cls(settings, deg, _number(d["centre"], "centre"), half, coefs, covs, w, h,
                   unit if isinstance(unit, str) else "")
