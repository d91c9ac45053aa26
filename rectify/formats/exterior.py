"""The exterior orientation JSON (``eo.json``, ``stereo resect -o``): the one reader of its geometry.

``rectify-stereo/exterior-orientation`` version 1 (``docs/formats.md``): ``position`` (X, Y, Z of the
projection centre, ground units), ``rotation`` (3 x 3, photo vector (x, y, -f) -> ground) or ``angles``
(``omega``, ``phi``, ``kappa`` in radians, ``system`` default ``omega-phi-kappa``), ``crs`` (or null),
and the keys of the resection (focal length, principal point, standard errors, ...). Unversioned files
of release 0.1.0 are read as version 1.

:func:`exterior_fields` checks a parsed document (format and version, position, rotation or angles,
CRS) and returns the geometry; :func:`read_exterior` reads it from a file (what ``rectify ortho``
needs) and :func:`stereo.formats.orientation.read_exterior` builds the full
``ExteriorOrientation`` from the same fields. :func:`read_frame_model` makes the orthorectifier's
:class:`rectify.geometry.sensors.FrameModel` from a camera JSON and an EO JSON.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rectify.atomic import read_json
from rectify.errors import CRSError, InvalidInputError
from rectify.formats.camera import read_camera
from rectify.formats.common import StrPath, check_format, check_numbers
from rectify.geometry.rotation import check_rotation, matrix_from_angles
from rectify.geometry.sensors import FrameModel

__all__ = ["EXTERIOR_NAME", "EXTERIOR_VERSION", "exterior_fields", "read_exterior",
           "read_frame_model"]

#: format name (after ``rectify-stereo/``) and newest version of the exterior orientation JSON
EXTERIOR_NAME = "exterior-orientation"
EXTERIOR_VERSION = 1

def exterior_fields(doc: Any, path: StrPath) -> dict[str, Any]:
    """Check a parsed exterior orientation document; return its geometry.

    Returns
    -------
    dict
        ``{"position": (3,) float64, "rotation": (3, 3) float64, "crs": str | None}``; the rotation is
        ``rotation`` (photo vector -> ground), or is built from ``angles`` (radians, ``system``
        default omega-phi-kappa).

    Raises
    ------
    InvalidInputError
        Not a JSON object, another format or a newer version, a missing or bad ``position``,
        ``rotation`` or ``angles`` (named).
    """
    check_format(doc, EXTERIOR_NAME, EXTERIOR_VERSION, path, what="exterior orientation file")
    if "position" not in doc:
        raise InvalidInputError(f"exterior orientation {str(path)!r} lacks 'position'")
    check_numbers(doc, "position", (3,), path)
    if "rotation" in doc:
        check_numbers(doc, "rotation", (3, 3), path)
        R = check_rotation(doc["rotation"], "rotation")
    elif isinstance(doc.get("angles"), dict):
        a = doc["angles"]
        for k in ("omega", "phi", "kappa"):
            if k in a:
                check_numbers(a, k, (), path)
        try:
            R = matrix_from_angles(float(a["omega"]), float(a["phi"]), float(a["kappa"]),
                                   a.get("system", "omega-phi-kappa"))
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"exterior orientation {str(path)!r}: bad 'angles': {err}") from None
    else:
        raise InvalidInputError(f"exterior orientation {str(path)!r} lacks 'rotation' (or 'angles')")
    return {"position": np.asarray(doc["position"], dtype=np.float64), "rotation": np.asarray(R, dtype=np.float64),
            "crs": doc.get("crs")}


def read_exterior(path: StrPath) -> dict[str, Any]:
    """Read the geometry of an exterior orientation JSON (:func:`exterior_fields`).

    Raises
    ------
    RasterIOError, InvalidInputError
        Missing file, bad JSON, another format or a newer version, missing or bad keys (named).
    """
    return exterior_fields(read_json(path, "exterior orientation file"), path)


def read_frame_model(camera_json: StrPath, exterior_json: StrPath, *, crs: str | None = None) -> FrameModel:
    """A frame camera model from a camera JSON and an exterior orientation JSON (``crs`` overrides the EO file's).

    Raises
    ------
    CRSError
        Neither ``crs`` nor a ``crs`` in the EO file.
    """
    cam = read_camera(camera_json)
    eo = read_exterior(exterior_json)
    c = crs or eo["crs"]
    if c is None:
        raise CRSError(f"exterior orientation {str(exterior_json)!r} has no 'crs'; pass the CRS of its "
                       f"coordinates")
    return FrameModel(cam, eo["position"], eo["rotation"], c)
