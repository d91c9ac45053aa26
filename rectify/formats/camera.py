"""The camera JSON: one file for the interior orientation of a frame camera (``docs/formats.md``).

``"format": "rectify-stereo/camera"``, version :data:`CAMERA_VERSION` (1: millimetre cameras;
2: also pixel cameras, ``std_errors`` and ``sigma0_px``). Two forms of the same file are written here:

- :func:`camera_document` / :func:`write_camera`: a :class:`rectify.geometry.camera.Camera` (the keys of
  :meth:`~rectify.geometry.camera.Camera.to_dict`), read back by :func:`read_camera`;
- :func:`intrinsics_document`: the interior orientation of a calibration in pixels (``fx``, ``fy``,
  ``cx``, ``cy``, distortion and a separate point of symmetry, as ``stereo calibrate`` writes it), with
  the calibration's standard errors and sigma0 as optional inputs. ``stereo.formats.calibration`` reads
  it back into the calibration's interior orientation; :func:`read_camera` reads it as a ``Camera``
  (fx, fy and skew: ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``) when it has no separate point of
  symmetry.

Pixel camera::

    {"format": "rectify-stereo/camera", "version": 2, "width": 640, "height": 480,
     "fx_px": 809.95, "fy_px": 806.56,            # or "focal_length_px" when fx = fy and no skew
     "skew_px": 0.0,                               # optional, the skew s of K (0 when absent)
     "principal_point_px": [361.99, 214.40],       # pixel frame: col right, row down
     "distortion": {"k1": -0.128, "k2": -0.394, "k3": 0.0, "p1": -0.00435, "p2": -0.00732},
     "point_of_symmetry_px": [360.1, 215.0],       # only when estimated separately
     "std_errors": {"fx_px": 3.16, "fy_px": 2.94, "cx_px": 2.85, ...},
     "sigma0_px": 0.139}

Millimetre camera (the version-1 keys plus the same extras)::

    {"format": ..., "version": 2, "focal_length_mm": 4.2, "pixel_size_mm": 0.0014, "width": ..., "height": ...,
     "principal_point_mm": [x0, y0],               # offset from the image centre, photo axes (y up)
     "distortion": {...}, "std_errors": {"focal_length_mm": ..., "x0_mm": ..., "y0_mm": ..., "k1": ...},
     "sigma0_px": ...}

Zoom camera (``"format": "rectify-stereo/zoom-camera"``, :data:`ZOOM_CAMERA_VERSION`, written by
``stereo calibrate --zoom``): the interior orientation as polynomials of the focal setting
(:class:`rectify.geometry.zoom.ZoomCamera`). :func:`read_camera` gives the camera of one image when
given its focal setting, and refuses a zoom camera without one or outside the calibrated range.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

from rectify.atomic import atomic_write_text, read_json
from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.common import FORMAT_PREFIX, StrPath, check_format, stamp, unstamped
from rectify.geometry.camera import Camera
from rectify.geometry.zoom import ZoomCamera

__all__ = ["CAMERA_VERSION", "ZOOM_CAMERA_VERSION", "PinholeIntrinsics", "read_camera", "write_camera",
           "camera_document", "intrinsics_document", "is_zoom_document", "read_zoom_camera", "zoom_camera_document"]

#: Version of the camera JSON (1: the 0.1.0 keys plus ``format``/``version``).
CAMERA_VERSION = 2  # 2: pixel cameras, std_errors, sigma0_px (1: millimetre cameras)
#: Version of the zoom camera JSON.
ZOOM_CAMERA_VERSION = 1


class PinholeIntrinsics(Protocol):
    """An interior orientation in pixels (``stereo.calibration.model.Intrinsics``): principal distances
    ``fx``, ``fy`` and principal point ``cx``, ``cy`` in the pixel frame, the image size, the point of
    symmetry of distortion ``sx``, ``sy`` (None: the principal point) and the distortion coefficients."""

    @property
    def fx(self) -> float: ...
    @property
    def fy(self) -> float: ...
    @property
    def cx(self) -> float: ...
    @property
    def cy(self) -> float: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def sx(self) -> float | None: ...
    @property
    def sy(self) -> float | None: ...
    @property
    def distortion(self) -> dict[str, float]: ...


def read_camera(path: StrPath, *, focal_setting: float | None = None) -> Camera:
    """Read a camera JSON file (:meth:`Camera.from_dict` keys; ``rectify-stereo/camera``), or a zoom camera
    JSON evaluated at ``focal_setting`` (the image's focal setting, the unit of the zoom calibration).

    Raises
    ------
    InvalidInputError
        A zoom camera without ``focal_setting``; a malformed file.
    CalibrationError
        A bad camera; a focal setting outside the zoom camera's calibrated range.
    """
    doc = read_json(path, "camera file")
    if is_zoom_document(doc):
        zoom = _zoom_from_doc(doc, path)
        if focal_setting is None:
            raise InvalidInputError(f"camera file {str(path)!r} is a zoom camera (calibrated {zoom.low:g}.."
                                    f"{zoom.high:g}{' ' + zoom.unit if zoom.unit else ''}): give the image's focal "
                                    "setting (stereo orient --focal-setting, or an image with EXIF FocalLength)")
        try:
            return zoom.camera(focal_setting)
        except CalibrationError as err:
            raise CalibrationError(f"zoom camera {str(path)!r}: {err}") from None
    check_format(doc, "camera", CAMERA_VERSION, path)
    return Camera.from_dict(unstamped(doc))


def is_zoom_document(doc: Any) -> bool:
    """Whether a parsed JSON document is a zoom camera (``"format": "rectify-stereo/zoom-camera"``)."""
    return isinstance(doc, dict) and doc.get("format") == FORMAT_PREFIX + "zoom-camera"


def _zoom_from_doc(doc: Any, path: StrPath) -> ZoomCamera:
    check_format(doc, "zoom-camera", ZOOM_CAMERA_VERSION, path, what="zoom camera file")
    try:
        return ZoomCamera.from_dict(unstamped(doc))
    except CalibrationError as err:
        raise CalibrationError(f"zoom camera file {str(path)!r}: {err}") from None


def read_zoom_camera(path: StrPath) -> ZoomCamera:
    """Read a zoom camera JSON file (``rectify-stereo/zoom-camera``, ``docs/formats.md``).

    Raises
    ------
    InvalidInputError, CalibrationError
        Not a zoom camera file (its format named); malformed keys.
    """
    return _zoom_from_doc(read_json(path, "zoom camera file"), path)


def zoom_camera_document(zoom: ZoomCamera, **extra: Any) -> dict[str, Any]:
    """The zoom camera JSON object: the format stamp, :meth:`ZoomCamera.to_dict` and ``extra`` keys (the
    calibration of each setting, the fit's chi2/dof: informative, not read back)."""
    return stamp("zoom-camera", ZOOM_CAMERA_VERSION, {**zoom.to_dict(), **extra})


def camera_from_focals(body: Mapping[str, Any], fx: float, fy: float, skew: float = 0.0, *, where: str) -> Camera:
    """A pixel camera from ``body`` (width, height, principal point, distortion) and K's fx, fy, skew (px).

    The one place other tools' camera files become a :class:`Camera`: ``focal_length_px`` when fx = fy and
    skew = 0, else ``fx_px``/``fy_px`` (and ``skew_px``). Errors name ``where`` (the file and entry).
    """
    d = dict(body)
    if fx == fy and skew == 0.0:
        d["focal_length_px"] = fx
    else:
        d.update(fx_px=fx, fy_px=fy)
        if skew != 0.0:
            d["skew_px"] = skew
    try:
        return Camera.from_dict(d)
    except CalibrationError as err:
        raise CalibrationError(f"{where}: {err}") from None


def camera_document(camera: Camera) -> dict[str, Any]:
    """The camera JSON object: the format stamp and :meth:`Camera.to_dict`."""
    return stamp("camera", CAMERA_VERSION, camera.to_dict())


def write_camera(path: StrPath, camera: Camera, *, overwrite: bool = False) -> Path:
    """Write a camera JSON file atomically; return the path."""
    return atomic_write_text(path, json.dumps(camera_document(camera), indent=2) + "\n", overwrite=overwrite)


def intrinsics_document(intr: PinholeIntrinsics, *, std_errors: Mapping[str, float] | None = None,
                        sigma0_px: float | None = None, pixel_size_mm: float | None = None) -> dict[str, Any]:
    """Camera JSON (version 2) of an interior orientation in pixels.

    Parameters
    ----------
    intr : PinholeIntrinsics
    std_errors : dict, optional
        Standard errors keyed by the calibration adjustment's names (``f`` or ``fx``/``fy``,
        ``cx``, ``cy``, ``k1``.., ``sx``, ``sy``), px or unitless; renamed here to
        the file's keys.
    sigma0_px : float, optional
    pixel_size_mm : float, optional
        Write a millimetre camera (needs ``fx == fy``: square pixels).

    Raises
    ------
    InvalidInputError
        A millimetre camera asked for with different fx and fy, or a bad pixel size.
    """
    se = dict(std_errors or {})
    body: dict[str, Any] = {}
    if pixel_size_mm is None:
        body.update(width=intr.width, height=intr.height)
        if intr.fx == intr.fy:
            body["focal_length_px"] = intr.fx
        else:
            body["fx_px"], body["fy_px"] = intr.fx, intr.fy
        body["principal_point_px"] = [intr.cx, intr.cy]
        body["distortion"] = intr.distortion
        if intr.sx is not None:
            body["point_of_symmetry_px"] = [intr.sx, intr.sy]
        ren = {"f": "focal_length_px", "fx": "fx_px", "fy": "fy_px", "cx": "cx_px", "cy": "cy_px",
               "sx": "sx_px", "sy": "sy_px"}
        errs = {ren.get(k, k): float(v) for k, v in se.items()}
    else:
        ps = float(pixel_size_mm)
        if not (math.isfinite(ps) and ps > 0):
            raise InvalidInputError(f"pixel size must be > 0 mm; got {pixel_size_mm!r}")
        if intr.fx != intr.fy:
            raise InvalidInputError(f"a millimetre camera needs square pixels, but fx {intr.fx:.3f} != fy "
                                    f"{intr.fy:.3f} px: estimate one focal length or write pixels")
        xc, yc = (intr.width - 1) / 2.0, (intr.height - 1) / 2.0
        body.update(focal_length_mm=intr.fx * ps, pixel_size_mm=ps, width=intr.width, height=intr.height,
                    principal_point_mm=[(intr.cx - xc) * ps, -(intr.cy - yc) * ps], distortion=intr.distortion)
        if intr.sx is not None and intr.sy is not None:
            body["point_of_symmetry_mm"] = [(intr.sx - xc) * ps, -(intr.sy - yc) * ps]
        ren = {"f": "focal_length_mm", "cx": "x0_mm", "cy": "y0_mm", "sx": "xs_mm", "sy": "ys_mm"}
        errs = {ren.get(k, k): float(v) * (ps if k in ren else 1.0) for k, v in se.items()}
    if errs:
        body["std_errors"] = errs
    if sigma0_px is not None:
        body["sigma0_px"] = float(sigma0_px)
    return stamp("camera", CAMERA_VERSION, body)
