"""Exterior orientations for ``rectify ortho``: the EO JSON (the one reader of its geometry), and one image of a block.

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

A block's outputs feed the orthophoto directly, per image (:func:`read_frame_source`, ``--exterior``
with ``--image-id``, default the source image's file stem):

- the block orientation JSON (``rectify-stereo/block-orientation``, ``stereo block``'s
  ``orientation.json``): the image's ``position`` and ``rotation``, the file's ``crs`` and the image's
  camera from the file's ``cameras`` (unless a camera JSON is given);
- the position/angle CSV (``stereo block``'s ``poses.csv``: ``image,[camera,]x,y,z,omega,phi,kappa``
  with optional standard deviations, ``# crs=`` and ``# angles=deg|rad`` comment lines; R = Rx(omega)
  Ry(phi) Rz(kappa)); it carries no camera model, so a camera JSON is needed.

An image id matches an image name exactly or by file stem (``IMG_1`` matches ``IMG_1.JPG``).
Parsed here with :mod:`rectify.formats.common` (``rectify`` never imports ``stereo``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rectify.atomic import read_json
from rectify.errors import CRSError, InvalidInputError, RectifyError
from rectify.formats.camera import read_camera
from rectify.formats.common import (
    FORMAT_PREFIX,
    StrPath,
    TableReader,
    check_format,
    check_numbers,
    finite_number,
    need_columns,
)
from rectify.geometry.camera import Camera
from rectify.geometry.crs import VerticalDatum, horizontal_crs, parse_crs, vertical_datum
from rectify.geometry.rotation import check_rotation, matrix_from_angles
from rectify.geometry.sensors import FrameModel

__all__ = ["EXTERIOR_NAME", "EXTERIOR_VERSION", "BLOCK_ORIENTATION_NAME", "CameraChooser", "FrameSource",
           "exterior_fields", "read_exterior", "read_frame_model", "read_frame_source"]

#: format name (after ``rectify-stereo/``) and newest version of the block orientation JSON read here
BLOCK_ORIENTATION_NAME = "block-orientation"
BLOCK_ORIENTATION_VERSION = 1

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


@dataclass(frozen=True, eq=False)
class FrameSource:
    """A frame model and where it came from.

    Attributes
    ----------
    model : FrameModel
    description : str
        One line: the file, its kind, the image id and the camera's origin.
    image_id : str or None
        The image of a block or pose file (None for an EO JSON).
    vertical : VerticalDatum or None
        The heights the orientation's CRS declares (a compound CRS); the model's CRS is its horizontal part.
    """

    model: FrameModel
    description: str
    image_id: str | None = None
    vertical: VerticalDatum | None = None


def _pick_image(names: list[str], image_id: str, path: StrPath, what: str, *, defaulted: bool) -> int:
    """Index of the image ``image_id`` among ``names``: exact, else by file stem; one line when absent or ambiguous."""
    exact = [i for i, n in enumerate(names) if n == image_id]
    if exact:
        return exact[0]
    stem = Path(image_id).stem
    by_stem = [i for i, n in enumerate(names) if Path(n).stem in (image_id, stem)]
    if len(by_stem) == 1:
        return by_stem[0]
    how = f"image id {image_id!r}" + (" (the source image's file stem; pass --image-id)" if defaulted else "")
    if by_stem:
        raise InvalidInputError(f"{how} matches several images of {what} {str(path)!r}: "
                                f"{[names[i] for i in by_stem][:10]}; pass the full name with --image-id")
    raise InvalidInputError(f"{how} is not in {what} {str(path)!r} ({len(names)} images: {names[:10]}"
                            f"{' ...' if len(names) > 10 else ''})")


def _block_image(doc: dict[str, Any], path: StrPath, image_id: str, defaulted: bool
                 ) -> tuple[dict[str, Any], Camera, str]:
    """Position, rotation and CRS of one image of a block orientation JSON, its camera and the camera id."""
    check_format(doc, BLOCK_ORIENTATION_NAME, BLOCK_ORIENTATION_VERSION, path, what="block orientation file")
    images, cameras = doc.get("images"), doc.get("cameras")
    if not isinstance(images, list) or not images or not all(isinstance(im, dict) for im in images):
        raise InvalidInputError(f"{str(path)!r}: `images` must be a non-empty list of objects")
    if not isinstance(cameras, dict):
        raise InvalidInputError(f"{str(path)!r}: `cameras` must be an object (camera id -> camera)")
    names = [str(im.get("image")) for im in images]
    im = images[_pick_image(names, image_id, path, "block orientation", defaulted=defaulted)]
    where = f"{str(path)!r} image {im.get('image')!r}"
    for key, shape in (("position", (3,)), ("rotation", (3, 3))):
        if key not in im:
            raise InvalidInputError(f"{where} lacks {key!r}")
        check_numbers(im, key, shape, path)
    try:
        R = check_rotation(im["rotation"], "rotation")
    except RectifyError as err:
        raise InvalidInputError(f"{where}: {err}") from err
    cam_id = str(im.get("camera"))
    if cam_id not in cameras or not isinstance(cameras[cam_id], dict):
        raise InvalidInputError(f"{where} names camera {cam_id!r}, which is not in `cameras` {sorted(cameras)}")
    try:
        cam = Camera.from_dict(cameras[cam_id])
    except RectifyError as err:
        raise InvalidInputError(f"{str(path)!r} camera {cam_id!r}: {err}") from err
    crs = doc.get("crs")
    return ({"position": np.asarray(im["position"], dtype=np.float64), "rotation": np.asarray(R, dtype=np.float64),
             "crs": crs if isinstance(crs, str) else None, "image": str(im.get("image"))}, cam, cam_id)


def _pose_row(path: StrPath, image_id: str, defaulted: bool) -> dict[str, Any]:
    """Position, rotation and CRS of one image of a position/angle CSV (omega, phi, kappa)."""
    with TableReader(path) as t:  # read as a stream (a pose file may list many images)
        fields = list(t.fields)
        if any(f in fields for f in ("heading", "pitch", "roll")):
            raise InvalidInputError(f"{str(path)!r} gives navigation angles (heading, pitch, roll); rectify ortho "
                                    f"reads poses with omega,phi,kappa, as `stereo block` writes them in its poses.csv")
        need_columns(fields, ("image", "x", "y", "z", "omega", "phi", "kappa"), path)
        angles = ("omega", "phi", "kappa")
        cols = t.read("pose rows", numbers=("x", "y", "z", *angles), texts=("image", "camera"),
                      empty=("x", "y", "z", *angles))
    unit = "deg"
    for no, key, value in cols.settings:
        if key == "angles":
            unit = value.lower()
            if unit not in ("deg", "rad"):
                raise InvalidInputError(f"{str(path)!r} line {no}: unknown angle unit {value!r}; "
                                        f"expected 'deg' or 'rad'")
    crs = cols.crs
    names = cols.texts["image"]
    k = _pick_image(names, image_id, path, "pose file", defaulted=defaulted)
    ln = int(cols.lines[k])
    for c in ("x", "y", "z", *angles):
        if math.isnan(cols.numbers[c][k]):
            finite_number("", f"{str(path)!r} line {ln}: column {c!r}")
    pos = [float(cols.numbers[c][k]) for c in ("x", "y", "z")]
    scale = math.pi / 180.0 if unit == "deg" else 1.0
    ang = [float(cols.numbers[c][k]) * scale for c in angles]
    r = {"camera": cols.texts["camera"][k]}
    if crs is not None:
        try:
            parse_crs(crs)
        except CRSError as err:
            raise CRSError(f"{str(path)!r}: {err}") from err
    return {"position": np.asarray(pos, dtype=np.float64),
            "rotation": matrix_from_angles(ang[0], ang[1], ang[2], "omega-phi-kappa"), "crs": crs,
            "image": names[k], "camera": r.get("camera", "")}


#: picks a camera of a file holding several, given the camera id the orientation names (None: it names none)
CameraChooser = Callable[[str | None], Camera]


def _camera(camera: StrPath | Camera | CameraChooser, camera_id: str | None) -> Camera:
    if isinstance(camera, Camera):
        return camera
    if callable(camera):
        return camera(camera_id)
    return read_camera(camera)


def read_frame_source(camera_json: StrPath | Camera | CameraChooser | None, exterior: StrPath, *,
                      crs: str | None = None, image_id: str | None = None, image_path: StrPath | None = None,
                      camera_note: str | None = None) -> FrameSource:
    """The frame model of one image from an EO JSON, a block orientation JSON or a position/angle CSV.

    Parameters
    ----------
    camera_json : path, Camera, callable or None
        A camera JSON; or a camera read from another file, or a function choosing one of a file's
        cameras by the camera id the orientation names (``camera_note`` says which file); None takes
        the image's camera from a block orientation JSON.
    exterior : path
        EO JSON (``stereo resect``), block orientation JSON (``stereo block``'s ``orientation.json``)
        or position/angle CSV (``.csv``, ``stereo block``'s ``poses.csv``).
    crs : str, optional
        CRS of the orientation (overrides the file's).
    image_id : str, optional
        The image of a block or pose file (exact name or file stem); default the stem of ``image_path``.
        Refused with an EO JSON, which holds one image.
    image_path : path, optional
        The source image, whose file stem is the default image id.

    Raises
    ------
    InvalidInputError
        Unknown image id (the file's ids listed), no camera (neither a camera JSON nor a block camera),
        an image id with an EO JSON, malformed files (named).
    CRSError
        No CRS in the file and none given.
    """
    ext = Path(exterior)
    explicit = image_id is not None
    iid = image_id if explicit else (Path(image_path).stem if image_path is not None else None)
    cam_note = camera_note or (f"camera {str(camera_json)!r}" if camera_json is not None else "")
    if ext.suffix.lower() == ".csv":
        if iid is None:
            raise InvalidInputError(f"pose file {str(ext)!r} holds several images: name one (--image-id)")
        eo = _pose_row(ext, iid, not explicit)
        if camera_json is None:
            raise InvalidInputError(f"pose file {str(ext)!r} has no camera model: pass the camera JSON (--camera) "
                                    f"of its camera {eo['camera'] or '(unnamed)'!r}")
        cam = _camera(camera_json, eo["camera"] or None)
        what = f"image {eo['image']!r} of pose file {str(ext)!r}"
    else:
        doc = read_json(ext, "exterior orientation file")
        if isinstance(doc, dict) and doc.get("format") == FORMAT_PREFIX + BLOCK_ORIENTATION_NAME:
            if iid is None:
                raise InvalidInputError(f"block orientation {str(ext)!r} holds several images: name one "
                                        f"(--image-id)")
            eo, block_cam, cam_id = _block_image(doc, ext, iid, not explicit)
            if camera_json is None:
                cam, cam_note = block_cam, f"camera {cam_id!r} of the block"
            else:
                cam = _camera(camera_json, cam_id)
            what = f"image {eo['image']!r} of block orientation {str(ext)!r}"
        else:
            if explicit:
                raise InvalidInputError(f"--image-id {image_id!r} names an image of a block orientation or pose "
                                        f"file; {str(ext)!r} is the exterior orientation of one image")
            if camera_json is None:
                raise InvalidInputError(f"exterior orientation {str(ext)!r} has no camera model: pass the camera "
                                        f"JSON (--camera)")
            eo = exterior_fields(doc, ext)
            cam = _camera(camera_json, None)
            what = f"exterior orientation {str(ext)!r}"
    c = crs or eo["crs"]
    if c is None:
        raise CRSError(f"{what} has no 'crs'; pass the CRS of its coordinates (--eo-crs)")
    model = FrameModel(cam, eo["position"], eo["rotation"], horizontal_crs(c))
    return FrameSource(model, f"{what}, {cam_note}", eo.get("image"), vertical_datum(c))


def read_frame_model(camera_json: StrPath | None, exterior_json: StrPath, *, crs: str | None = None,
                     image_id: str | None = None) -> FrameModel:
    """A frame camera model from a camera JSON and an exterior orientation (``crs`` overrides the file's).

    ``exterior_json`` is an EO JSON, or a block orientation JSON / position-angle CSV with ``image_id``
    (:func:`read_frame_source`).

    Raises
    ------
    CRSError
        Neither ``crs`` nor a ``crs`` in the file.
    """
    return read_frame_source(camera_json, exterior_json, crs=crs, image_id=image_id).model
