"""OpenCV calibration files in and out: ``camera_matrix``, ``distortion_coefficients``, image size.

The files OpenCV's calibration sample (``calibration.cpp``, the ``camera_calibration`` tutorial) writes
with ``cv::FileStorage`` in YAML, XML or JSON, and the ROS ``camera_info`` YAML (the same keys, the
matrices as ``rows``/``cols``/``data`` mappings), read with :class:`cv2.FileStorage`:

- :func:`read_opencv_calibration` -> :class:`rectify.geometry.camera.Camera` (a pixel camera);
- :func:`opencv_calibration_text` / :func:`write_opencv_calibration` <- a camera (YAML, XML or JSON by
  the file's suffix; doubles with 17 significant digits, so a round trip is exact);
- :func:`detect_opencv_calibration`: a ``.yml``/``.yaml``/``.xml``/``.json`` file naming ``camera_matrix``.

Conventions: OpenCV's pixel frame is ours (x = column right, y = row down, the centre of the
top-left pixel at (0, 0)), so K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] is taken as it is. Its
distortion vector (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tx, ty]]]]) has the
definition of :mod:`rectify.geometry.camera`; the rational (k4-k6), thin-prism (s1-s4) and tilt
(tx, ty) terms are not in the frame camera model and must be 0 (refused by name otherwise), as is
ROS's ``equidistant`` (fisheye) model.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.atomic import atomic_write_text
from rectify.errors import InvalidInputError
from rectify.formats.camera import camera_from_focals
from rectify.formats.common import StrPath, read_table_text
from rectify.geometry.camera import Camera

__all__ = ["OPENCV_DISTORTION_NAMES", "OPENCV_SUFFIXES", "read_opencv_calibration", "opencv_calibration_text",
           "write_opencv_calibration", "detect_opencv_calibration"]

#: names of OpenCV's distortion coefficients, in the order of its vector
OPENCV_DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")
#: suffix -> cv2.FileStorage format
OPENCV_SUFFIXES = {".yml": cv2.FILE_STORAGE_FORMAT_YAML, ".yaml": cv2.FILE_STORAGE_FORMAT_YAML,
                   ".xml": cv2.FILE_STORAGE_FORMAT_XML, ".json": cv2.FILE_STORAGE_FORMAT_JSON}
_KEYS = {"camera_matrix": ("camera_matrix", "Camera_Matrix"),
         "distortion_coefficients": ("distortion_coefficients", "Distortion_Coefficients"),
         "image_width": ("image_width", "image_Width"), "image_height": ("image_height", "image_Height")}
_MODEL_COUNT = (0, 4, 5, 8, 12, 14)


def _node(fs: Any, key: str) -> Any:
    for name in _KEYS[key]:
        n = fs.getNode(name)
        if not n.empty():
            return n
    return None


def _matrix(node: Any, key: str, where: str) -> NDArray[np.float64]:
    """A matrix node: OpenCV's ``!!opencv-matrix`` or ROS's ``{rows, cols, data}`` mapping."""
    if node.isMap() and not node.getNode("dt").empty():
        m = node.mat()
        if m is None:
            raise InvalidInputError(f"{where}: `{key}` is not a readable OpenCV matrix")
        return np.asarray(m, dtype=np.float64)
    data = node.getNode("data") if node.isMap() else node
    if not data.isSeq():
        raise InvalidInputError(f"{where}: `{key}` must be a matrix (rows, cols, data); got a "
                                f"{'mapping' if node.isMap() else 'scalar'}")
    vals = []
    for i in range(data.size()):
        e = data.at(i)
        if not (e.isReal() or e.isInt()):
            raise InvalidInputError(f"{where}: `{key}` element {i} is not a number: {e.string()!r}")
        vals.append(e.real())
    a = np.array(vals, dtype=np.float64)
    if node.isMap():
        rows, cols = node.getNode("rows"), node.getNode("cols")
        if not rows.empty() and not cols.empty():
            r, c = int(rows.real()), int(cols.real())
            if r * c != a.size:
                raise InvalidInputError(f"{where}: `{key}` has rows {r} x cols {c} but {a.size} values")
            a = a.reshape(r, c)
    return a


def _int(node: Any, key: str, where: str) -> int:
    if node is None:
        raise InvalidInputError(f"{where} lacks `{key}`")
    if not node.isInt() or node.real() <= 0:
        raise InvalidInputError(f"{where}: `{key}` must be a positive integer; got "
                                f"{node.string() or node.real()!r}")
    return int(node.real())


def read_opencv_calibration(path: StrPath) -> Camera:
    """Read an OpenCV calibration file (YAML, XML or JSON; or a ROS ``camera_info`` YAML) into a pixel camera.

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Not a ``cv2.FileStorage`` file, a missing key, a matrix of the wrong shape, a distortion
        vector of a length OpenCV does not define, a nonzero term outside the frame camera model, a
        fisheye model (each named with the file, the key and the value).
    CalibrationError
        A camera the project's model refuses.
    """
    text = read_table_text(path)
    where = repr(str(path))
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as err:
        reason = str(err.__cause__ or err).strip().splitlines()[-1]
        raise InvalidInputError(f"{where} is not an OpenCV FileStorage file (YAML, XML, JSON): {reason}") from None
    try:
        model = fs.getNode("distortion_model")
        if not model.empty() and model.string().lower() in ("equidistant", "fisheye", "kannala_brandt"):
            raise InvalidInputError(f"{where}: `distortion_model` {model.string()!r} (fisheye) is not in the frame "
                                    "camera model")
        km = _node(fs, "camera_matrix")
        if km is None:
            raise InvalidInputError(f"{where} lacks `camera_matrix`")
        K = _matrix(km, "camera_matrix", where)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise InvalidInputError(f"{where}: `camera_matrix` must be 3 x 3 finite numbers; got {K.tolist()}")
        if K[1, 0] != 0.0 or K[2, 0] != 0.0 or K[2, 1] != 0.0 or K[2, 2] != 1.0:
            raise InvalidInputError(f"{where}: `camera_matrix` must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]; "
                                    f"got {K.tolist()}")
        dn = _node(fs, "distortion_coefficients")
        dist = np.zeros(0) if dn is None else _matrix(dn, "distortion_coefficients", where).reshape(-1)
        if dist.size not in _MODEL_COUNT or not np.isfinite(dist).all():
            raise InvalidInputError(f"{where}: `distortion_coefficients` must hold 4, 5, 8, 12 or 14 finite numbers "
                                    f"(OpenCV's models); got {dist.tolist()}")
        extra = {OPENCV_DISTORTION_NAMES[i]: float(v) for i, v in enumerate(dist) if i >= 5 and v != 0.0}
        if extra:
            raise InvalidInputError(f"{where}: `distortion_coefficients` has nonzero {extra}; the frame camera model "
                                    "has only k1, k2, p1, p2, k3")
        w = _int(_node(fs, "image_width"), "image_width", where)
        h = _int(_node(fs, "image_height"), "image_height", where)
    finally:
        fs.release()
    d: dict[str, Any] = {"width": w, "height": h, "principal_point_px": [float(K[0, 2]), float(K[1, 2])],
                         "distortion": {OPENCV_DISTORTION_NAMES[i]: float(v) for i, v in enumerate(dist[:5])}}
    fx, fy, s = float(K[0, 0]), float(K[1, 1]), float(K[0, 1])
    return camera_from_focals(d, fx, fy, s, where=where)


def opencv_calibration_text(camera: Camera, *, fmt: str = ".yml") -> str:
    """The OpenCV calibration file of ``camera`` (``image_width``, ``image_height``, ``camera_matrix`` 3 x 3,
    ``distortion_coefficients`` 5 x 1) in the format of the suffix ``fmt`` (``.yml``, ``.yaml``, ``.xml``,
    ``.json``), as ``cv::FileStorage`` writes it."""
    if fmt not in OPENCV_SUFFIXES:
        raise InvalidInputError(f"unknown OpenCV FileStorage format {fmt!r}; expected one of {list(OPENCV_SUFFIXES)}")
    fs = cv2.FileStorage("", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | OPENCV_SUFFIXES[fmt])
    fs.write("image_width", int(camera.width))
    fs.write("image_height", int(camera.height))
    fs.write("camera_matrix", np.asarray(camera.K, dtype=np.float64))
    fs.write("distortion_coefficients", np.asarray(camera.dist_coeffs, dtype=np.float64).reshape(5, 1))
    return str(fs.releaseAndGetString())


def write_opencv_calibration(path: StrPath, camera: Camera, *, overwrite: bool = False) -> Path:
    """Write :func:`opencv_calibration_text` atomically in the format of the path's suffix; return the path."""
    suffix = Path(path).suffix.lower()
    if suffix not in OPENCV_SUFFIXES:
        raise InvalidInputError(f"{str(path)!r}: an OpenCV calibration file ends in one of {list(OPENCV_SUFFIXES)}")
    return atomic_write_text(path, opencv_calibration_text(camera, fmt=suffix), overwrite=overwrite)


def detect_opencv_calibration(path: StrPath) -> bool:
    """Whether ``path`` (``.yml``, ``.yaml``, ``.xml``, ``.json``) names a ``camera_matrix`` in its first 64 KiB."""
    if Path(path).suffix.lower() not in OPENCV_SUFFIXES:
        return False
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return False
    return any(k in head for k in _KEYS["camera_matrix"]) and "image_width" in head
