"""Which reader a user's file needs: the cameras, exterior orientations and GCPs of every tool, by content.

The options that take a user's file (``--camera``, ``--exterior``, ``--gcps``; in ``stereo`` also
``--poses`` and ``--control``, :mod:`stereo.formats.detect`) accept every format the project reads
without being told which. Each family is a tuple of :class:`FileKind` (a name, a label and the
format's ``detect_*`` function: content first, the suffix only where the content cannot tell), and
:func:`resolve_kind` asks each in turn:

- one kind recognises the file: its reader reads it;
- none does: the project's own format (camera JSON; EO JSON, block ``orientation.json`` or
  ``poses.csv``; GCP CSV, QGIS ``.points``, GeoJSON, GeoPackage or GeoTIFF), whose reader names what
  is wrong with the file;
- several do: the file is refused with the choices named, and the user names one by prefixing the
  path with the kind's name, ``opencv:calib.json`` (a prefix is also accepted when the detection
  would have chosen another kind).

=============  ===================================================================================
family         kinds (prefix: reader)
=============  ===================================================================================
camera         ``camera``: camera JSON; ``orthority``: int_param YAML/JSON; ``opencv``: OpenCV/ROS
               calibration; ``colmap``: COLMAP text model (``cameras.txt``); ``metashape``:
               Metashape cameras XML
exterior       ``exterior``: EO JSON, block ``orientation.json``, ``poses.csv`` (``--image-id``);
               ``orthority``: ext_param GeoJSON; ``orthority-csv``: xyz_opk/lla_rpy CSV (+ .prj);
               ``colmap``: COLMAP text model; ``metashape``: Metashape cameras XML
GCPs           ``gcps``: GCP CSV, QGIS ``.points``, GeoJSON, GeoPackage, GeoTIFF-embedded;
               ``orthority``: GCP GeoJSON with ``ji``; ``odm``: ODM ``gcp_list.txt``;
               ``metashape``: Metashape markers XML
=============  ===================================================================================

Files that hold several images (orthority, COLMAP, Metashape exteriors; orthority, ODM and Metashape
GCPs) give the one of the image being processed (matched by file name or stem,
:func:`rectify.formats.orthority.match_image`); files that hold several cameras give the one the
exterior orientation names, or the only one, or the one named by the caller.

GCPs embedded in a GeoTIFF carry no pixel convention: GDAL's corner reading (the top-left corner of
the image at (0, 0), :func:`rectify.formats.gcps.read_gcps_embedded`) is the default, and
``pixel="centre"`` reads them as orthority writes them (the centre of the top-left pixel at (0, 0),
:func:`rectify.formats.orthority.read_embedded_gcps_centre`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rectify.errors import CalibrationError, CRSError, InvalidInputError
from rectify.formats.camera import read_camera
from rectify.formats.colmap import detect_colmap, read_colmap_cameras, read_colmap_images
from rectify.formats.common import FORMAT_PREFIX, StrPath
from rectify.formats.exterior import CameraChooser, FrameSource, read_frame_source
from rectify.formats.gcps import TIFF_SUFFIXES, read_gcps
from rectify.formats.metashape import detect_metashape, read_metashape_chunk
from rectify.formats.odm import detect_odm_gcps, read_odm_gcp_list
from rectify.formats.opencv import detect_opencv_calibration, read_opencv_calibration
from rectify.formats.orthority import (
    EMBEDDED_CONVENTIONS,
    detect_ext_param,
    detect_frame_csv,
    detect_int_param,
    detect_oty_gcps,
    match_image,
    read_embedded_gcps_centre,
    read_ext_param,
    read_frame_csv,
    read_int_param,
    read_oty_gcps,
)
from rectify.geometry.camera import Camera
from rectify.geometry.crs import horizontal_crs, vertical_datum
from rectify.geometry.points import GcpTable
from rectify.geometry.sensors import FrameModel
from rectify.raster.exif import exif_focal_length

__all__ = ["FileKind", "CAMERA_KINDS", "EXTERIOR_KINDS", "GCP_KINDS", "GCP_PIXEL", "STEREO_KIND_NAMES", "split_kind",
           "resolve_kind", "input_paths", "CameraFile", "read_camera_file", "read_one_camera", "ExteriorFile",
           "read_exterior_file", "read_frame_source_any", "GcpSource", "read_gcp_file", "pick_image",
           "head_has_format", "detect_pose_csv", "image_focal_setting", "is_zoom_camera"]

#: pixel conventions of GCPs embedded in a GeoTIFF (``--gcp-pixel``)
GCP_PIXEL = tuple(EMBEDDED_CONVENTIONS)
_SNIFF_BYTES = 1 << 16
_PREFIX = re.compile(r"^([a-z][a-z0-9-]+):(.+)$")


@dataclass(frozen=True)
class FileKind:
    """One format a user's file may be in.

    Attributes
    ----------
    name : str
        The prefix that names it on the command line (``opencv:calib.yml``).
    label : str
        What it is, for messages.
    detect : callable
        ``path -> bool``: whether the file is in this format (never raises).
    """

    name: str
    label: str
    detect: Callable[[Path], bool] = field(repr=False)


def head_has_format(path: StrPath, *names: str) -> bool:
    """Whether the first 64 KiB of ``path`` carry ``"format": "rectify-stereo/<name>"`` for one of ``names``."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            head = fh.read(_SNIFF_BYTES)
    except OSError:
        return False
    return any(re.search(r'"format"\s*:\s*"' + re.escape(FORMAT_PREFIX + n) + '"', head) for n in names)


def detect_pose_csv(path: StrPath) -> bool:
    """Whether ``path`` is a position/angle CSV (``stereo block``'s poses.csv): a ``.csv`` whose header (after
    ``#`` lines) starts with the column ``image``."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        return False
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            for line in fh.read(_SNIFF_BYTES).splitlines():
                s = line.strip()
                if s and not s.startswith("#"):
                    return s.split(",")[0].strip().lower() == "image"
    except OSError:
        return False
    return False


OUR_CAMERA = FileKind("camera", "camera JSON", lambda p: head_has_format(p, "camera"))
OUR_EXTERIOR = FileKind("exterior", "exterior orientation (EO JSON, block orientation.json or poses.csv)",
                        lambda p: head_has_format(p, "exterior-orientation", "block-orientation")
                        or detect_pose_csv(p))
OUR_GCPS = FileKind("gcps", "GCP file (CSV, QGIS .points, GeoJSON, GeoPackage or GeoTIFF)", lambda p: False)

#: the kinds ``--camera`` reads
CAMERA_KINDS: tuple[FileKind, ...] = (
    OUR_CAMERA,
    FileKind("orthority", "orthority interior parameters", detect_int_param),
    FileKind("opencv", "OpenCV calibration file", detect_opencv_calibration),
    FileKind("colmap", "COLMAP text model", detect_colmap),
    FileKind("metashape", "Metashape cameras XML", detect_metashape),
)
#: the kinds ``rectify ortho --exterior`` reads
EXTERIOR_KINDS: tuple[FileKind, ...] = (
    OUR_EXTERIOR,
    FileKind("orthority", "orthority exterior parameters", detect_ext_param),
    FileKind("orthority-csv", "orthority CSV of exterior parameters", detect_frame_csv),
    FileKind("colmap", "COLMAP text model", detect_colmap),
    FileKind("metashape", "Metashape cameras XML", detect_metashape),
)
#: the kinds ``--gcps`` reads
GCP_KINDS: tuple[FileKind, ...] = (
    OUR_GCPS,
    FileKind("orthority", "orthority GCP GeoJSON", detect_oty_gcps),
    FileKind("odm", "OpenDroneMap gcp_list.txt", detect_odm_gcps),
    FileKind("metashape", "Metashape markers XML", detect_metashape),
)


#: names of the kinds of ``stereo.formats.detect``'s families (poses, control) that are not names here
STEREO_KIND_NAMES = ("poses", "opensfm", "odm-geo", "control", "odm")


def split_kind(value: StrPath, kinds: Sequence[FileKind]) -> tuple[FileKind | None, Path]:
    """``KIND:PATH`` -> (the kind, the path); a plain path (or an existing file whose name has a colon) -> (None, path).

    Raises
    ------
    InvalidInputError
        A prefix that names no kind of the family while the rest names an existing file.
    """
    if not isinstance(value, str) or Path(value).exists():
        return None, Path(value)
    m = _PREFIX.match(value)
    if m is None:
        return None, Path(value)
    for k in kinds:
        if k.name == m[1]:
            return k, Path(m[2])
    if Path(m[2]).exists():
        raise InvalidInputError(f"unknown file kind {m[1]!r} in {value!r}; expected one of {[k.name for k in kinds]}")
    return None, Path(value)


def input_paths(*values: StrPath | bool | None) -> list[Path]:
    """The files named by option values (``KIND:PATH`` prefixes of any family dropped; None and flags skipped)."""
    names = {k.name for k in (*CAMERA_KINDS, *EXTERIOR_KINDS, *GCP_KINDS)} | set(STEREO_KIND_NAMES)
    out = []
    for v in values:
        if v is None or isinstance(v, bool):
            continue
        if isinstance(v, str) and not Path(v).exists():
            m = _PREFIX.match(v)
            if m is not None and m[1] in names:
                out.append(Path(m[2]))
                continue
        out.append(Path(v))
    return out


def resolve_kind(value: StrPath, kinds: Sequence[FileKind], what: str) -> tuple[FileKind, Path]:
    """The kind of the file ``value`` (``KIND:PATH`` or a path): the prefix, else the one kind that detects it,
    else the first (the project's own format).

    Raises
    ------
    InvalidInputError
        Several kinds recognise the file (the choices named, with the prefix that picks one), or an
        unknown prefix.
    """
    kind, path = split_kind(value, kinds)
    if kind is not None:
        return kind, path
    hits = [k for k in kinds if k.detect(path)]
    if len(hits) > 1:
        names = [k.name for k in hits]
        raise InvalidInputError(f"{what} {str(path)!r} could be read as any of: "
                                f"{'; '.join(f'{k.name} ({k.label})' for k in hits)}; name one by prefixing the path, "
                                f"e.g. {names[0]}:{path} (choices: {', '.join(names)})")
    return (hits[0] if hits else kinds[0]), path


def pick_image(names: Sequence[str], image: StrPath | None, path: StrPath, what: str, option: str) -> str:
    """The entry of ``names`` for ``image`` (file name or stem); the only entry when ``image`` is None.

    Raises
    ------
    InvalidInputError
        No entry matches (the file's names listed), or several; no image given for a file of several.
    """
    if image is None:
        if len(names) == 1:
            return names[0]
        raise InvalidInputError(f"{what} {str(path)!r} holds {len(names)} images {list(names)[:10]}"
                                f"{' ...' if len(names) > 10 else ''}: name the image ({option})")
    try:
        return str(match_image({n: n for n in names}, image))
    except InvalidInputError as err:
        raise InvalidInputError(f"{what} {str(path)!r}: {err}") from None


# --------------------------------------------------------------------------- cameras
@dataclass(frozen=True, eq=False)
class CameraFile:
    """The cameras of a ``--camera`` file.

    Attributes
    ----------
    path : Path
    kind : FileKind
    cameras : dict of str -> Camera
        Keyed by the file's camera ids (``"camera"`` for a file of one unnamed camera).
    """

    path: Path
    kind: FileKind
    cameras: dict[str, Camera]

    def choose(self, camera_id: str | None = None, *, named_by: str | None = None) -> tuple[str, Camera]:
        """The camera ``camera_id`` (when the file holds it, or must: ``named_by`` None), else the only one.

        Parameters
        ----------
        camera_id : str, optional
            The id asked for.
        named_by : str, optional
            Who names ``camera_id`` (an exterior orientation): then a file of one camera gives that
            camera even under another id.

        Raises
        ------
        InvalidInputError
            An id the file lacks (its ids listed), or no id for a file of several cameras.
        """
        ids = sorted(self.cameras)
        if camera_id is not None and camera_id in self.cameras:
            return camera_id, self.cameras[camera_id]
        if len(self.cameras) == 1 and (camera_id is None or named_by is not None):
            k = next(iter(self.cameras))
            return k, self.cameras[k]
        if camera_id is not None:
            by = f" (named by {named_by})" if named_by else ""
            raise InvalidInputError(f"{self.kind.label} {str(self.path)!r} has no camera {camera_id!r}{by}; it has "
                                    f"{ids}")
        raise InvalidInputError(f"{self.kind.label} {str(self.path)!r} holds {len(ids)} cameras {ids}; name one "
                                "(--camera-id)")

    def note(self, camera_id: str) -> str:
        """``camera 'id' of <label> 'path'`` (just the path for the camera JSON)."""
        if self.kind is OUR_CAMERA:
            return f"camera {str(self.path)!r}"
        return f"camera {camera_id!r} of {self.kind.label} {str(self.path)!r}"

    def chooser(self, camera_id: str | None = None) -> CameraChooser:
        """A function giving the camera an orientation names (``camera_id`` given by the user wins)."""
        def pick(named: str | None) -> Camera:
            if camera_id is not None:
                return self.choose(camera_id)[1]
            return self.choose(named, named_by="the exterior orientation" if named else None)[1]
        return pick


def image_focal_setting(focal_setting: float | None, image: StrPath | None) -> float | None:
    """The focal setting of an image: ``focal_setting`` when given (``--focal-setting``), else the image's
    EXIF FocalLength (mm, :func:`rectify.raster.exif.exif_focal_length`), else None."""
    if focal_setting is not None:
        return float(focal_setting)
    return exif_focal_length(image) if image is not None else None


def is_zoom_camera(value: StrPath) -> bool:
    """Whether a ``--camera`` value (``PATH`` or ``KIND:PATH``) names a zoom camera JSON (stereo calibrate --zoom)."""
    kind, path = split_kind(value, CAMERA_KINDS)
    return kind in (None, OUR_CAMERA) and head_has_format(path, "zoom-camera")


def read_camera_file(value: StrPath, *, focal_setting: float | None = None,
                     image: StrPath | None = None, setting_option: str = "--focal-setting") -> CameraFile:
    """Read a ``--camera`` file of any kind of :data:`CAMERA_KINDS` (``KIND:PATH`` picks one).

    A zoom camera (``stereo calibrate --zoom``) gives the camera at the image's focal setting:
    ``focal_setting`` when given, else the EXIF FocalLength of ``image`` (read only for a zoom camera).
    ``setting_option`` is the option that gives the setting, for the message when there is none.

    Raises
    ------
    RasterIOError, InvalidInputError, CalibrationError, CRSError
        The reader's one-line errors (file, key and value named); an ambiguous file (choices named); a
        zoom camera without a focal setting, or one outside its calibrated range (the image named).
    """
    kind, path = resolve_kind(value, CAMERA_KINDS, "camera file")
    if kind is OUR_CAMERA and head_has_format(path, "zoom-camera"):
        setting = image_focal_setting(focal_setting, image)
        if setting is None and image is not None:
            raise InvalidInputError(f"camera file {str(path)!r} is a zoom camera, but image {str(image)!r} has no "
                                    f"EXIF FocalLength: give its focal setting ({setting_option})")
        try:
            return CameraFile(path, kind, {"camera": read_camera(path, focal_setting=setting)})
        except CalibrationError as err:
            if image is None or setting is None:
                raise
            raise CalibrationError(f"image {str(image)!r}: {err}") from None
    cams: dict[str, Camera]
    if kind.name == "orthority":
        cams = read_int_param(path)
    elif kind.name == "opencv":
        cams = {"camera": read_opencv_calibration(path)}
    elif kind.name == "colmap":
        cams = read_colmap_cameras(path)
    elif kind.name == "metashape":
        cams = dict(read_metashape_chunk(path).cameras)
        if not cams:
            raise InvalidInputError(f"{kind.label} {str(path)!r} holds no calibrated sensor")
    else:
        cams = {"camera": read_camera(path)}
    return CameraFile(path, kind, cams)


def read_one_camera(value: StrPath, camera_id: str | None = None, *, named_by: str | None = None,
                    focal_setting: float | None = None, image: StrPath | None = None) -> Camera:
    """The one camera of a ``--camera`` file of any kind (:func:`read_camera_file`, :meth:`CameraFile.choose`);
    a zoom camera at ``focal_setting`` or at the EXIF focal length of ``image``.

    Raises
    ------
    RasterIOError, InvalidInputError, CalibrationError
        As :func:`read_camera_file`; a file of several cameras without a choice (their ids named).
    """
    return read_camera_file(value, focal_setting=focal_setting, image=image).choose(camera_id, named_by=named_by)[1]


# --------------------------------------------------------------------------- exterior orientations
@dataclass(frozen=True, eq=False)
class ExteriorFile:
    """The exterior orientations of another tool's file.

    Attributes
    ----------
    path : Path
    kind : FileKind
    exteriors : dict of str -> dict
        ``{image: {"position": (3,), "rotation": (3, 3), "crs": str or None, "camera": str or None}}``.
    cameras : dict of str -> Camera
        The cameras the same file holds (COLMAP, Metashape), by the ids the exteriors name.
    frame : str
        What the coordinates are.
    """

    path: Path
    kind: FileKind
    exteriors: dict[str, dict[str, Any]]
    cameras: dict[str, Camera]
    frame: str = ""


def read_exterior_file(path: Path, kind: FileKind, *, crs: str | None = None) -> ExteriorFile:
    """Read the exterior orientations of a file of another tool (a kind of :data:`EXTERIOR_KINDS` but the first).

    ``crs``: the world CRS (orthority CSV: checked against the file's; a georeferenced Metashape chunk:
    the projected CRS to return the poses in; COLMAP, a local Metashape chunk: the CRS of the frame).

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        The reader's one-line errors.
    """
    if kind.name == "orthority":
        return ExteriorFile(path, kind, read_ext_param(path), {}, "the file's world_crs")
    if kind.name == "orthority-csv":
        return ExteriorFile(path, kind, read_frame_csv(path, crs=crs), {}, "the file's CRS (.prj or '# crs=')")
    if kind.name == "colmap":
        im = read_colmap_images(path)
        return ExteriorFile(path, kind, im.exteriors(crs), dict(im.cameras), "the COLMAP model's frame")
    if kind.name == "metashape":  # a georeferenced chunk is converted into crs; crs names a local chunk's frame
        doc = read_metashape_chunk(path)
        if doc.reference_crs is not None and crs is not None:
            doc = read_metashape_chunk(path, crs=crs)
        eos = doc.exteriors()
        if doc.crs is None:
            eos = {n: {**eo, "crs": crs} for n, eo in eos.items()}
        return ExteriorFile(path, kind, eos, dict(doc.cameras), doc.frame)
    raise InvalidInputError(f"{str(path)!r}: {kind.label} is read by rectify.formats.exterior")


def read_frame_source_any(camera: StrPath | None, exterior: StrPath, *, crs: str | None = None,
                          image_id: str | None = None, image_path: StrPath | None = None,
                          camera_id: str | None = None, focal_setting: float | None = None) -> FrameSource:
    """The frame model of one image from a camera file and an exterior orientation file of any kind.

    Parameters
    ----------
    camera : path, optional
        Any kind of :data:`CAMERA_KINDS`; optional when the exterior file holds the cameras
        (block orientation JSON, COLMAP model, Metashape XML).
    exterior : path
        Any kind of :data:`EXTERIOR_KINDS`.
    crs : str, optional
        The orientation's CRS (overrides the file's; names a COLMAP model's frame; the projected CRS
        Metashape poses are returned in).
    image_id : str, optional
        The image in a file of several (name or stem); default the file name of ``image_path``.
    image_path : path, optional
        The image being processed.
    camera_id : str, optional
        The camera of a camera file of several (default: the one the orientation names, else the only one).
    focal_setting : float, optional
        A zoom camera's focal setting of the image (``--focal-setting``); default the EXIF FocalLength of
        ``image_path``. Ignored by other cameras.

    Raises
    ------
    InvalidInputError
        An image or camera the files lack (theirs listed), a file of several cameras without a
        choice, no camera model, an ambiguous file (the choices named).
    CRSError
        No CRS for the orientation.
    """
    zoom = camera is not None and is_zoom_camera(camera)  # evaluated at the image's focal setting
    if focal_setting is not None and not zoom:
        raise InvalidInputError(f"--focal-setting {focal_setting:g} goes with a zoom camera (stereo calibrate --zoom);"
                                f" {'no --camera is' if camera is None else repr(str(camera)) + ' is not one'}")
    cam_file = (read_camera_file(camera, focal_setting=focal_setting, image=image_path if zoom else None)
                if camera is not None else None)
    kind, path = resolve_kind(exterior, EXTERIOR_KINDS, "exterior orientation file")
    if kind is OUR_EXTERIOR:
        if cam_file is None or (cam_file.kind is OUR_CAMERA and not zoom):
            if camera_id is not None and cam_file is not None:
                cam_file.choose(camera_id)  # refuses an id the camera JSON (one camera) does not carry
            return read_frame_source(None if cam_file is None else cam_file.path, path, crs=crs, image_id=image_id,
                                     image_path=image_path)
        note = (f"zoom camera {str(cam_file.path)!r} at focal setting "
                f"{image_focal_setting(focal_setting, image_path):g}" if zoom else
                f"{cam_file.kind.label} {str(cam_file.path)!r}")
        return read_frame_source(cam_file.chooser(camera_id), path, crs=crs, image_id=image_id, image_path=image_path,
                                 camera_note=note)
    ef = read_exterior_file(path, kind, crs=crs)
    target = image_id if image_id is not None else image_path
    name = pick_image(list(ef.exteriors), target, path, kind.label, "--image-id")
    eo = ef.exteriors[name]
    if cam_file is not None:
        if camera_id is not None:
            cid, cam = cam_file.choose(camera_id)
        else:
            named = eo.get("camera")
            cid, cam = cam_file.choose(named, named_by=f"image {name!r} of {str(path)!r}" if named else None)
        cam_note = cam_file.note(cid)
    elif ef.cameras:
        cid = str(eo.get("camera"))
        cam, cam_note = ef.cameras[cid], f"camera {cid!r} of the same file"
    else:
        raise InvalidInputError(f"{kind.label} {str(path)!r} has no camera model: pass --camera (orthority's "
                                "int_param.yaml, a camera JSON, an OpenCV calibration ...)")
    c = crs or eo.get("crs")
    if c is None:
        raise CRSError(f"image {name!r} of {kind.label} {str(path)!r} has no CRS ({ef.frame}); pass the CRS of its "
                       "coordinates (--eo-crs)")
    model = FrameModel(cam, eo["position"], eo["rotation"], horizontal_crs(c))
    return FrameSource(model, f"image {name!r} of {kind.label} {str(path)!r}, {cam_note}", name, vertical_datum(c))


# --------------------------------------------------------------------------- GCPs
@dataclass(frozen=True, eq=False)
class GcpSource:
    """A GCP table and where it came from.

    Attributes
    ----------
    table : GcpTable
    path : Path
        The file read.
    kind : FileKind
    description : str
        One line: the kind, the file and the image.
    image : str or None
        The image of a file of several.
    """

    table: GcpTable
    path: Path
    kind: FileKind
    description: str
    image: str | None = None


def read_gcp_file(value: StrPath, *, image: StrPath | None = None, pixel: str | None = None,
                  option: str = "--image") -> GcpSource:
    """Read a ``--gcps`` file of any kind of :data:`GCP_KINDS`; a file of several images gives ``image``'s GCPs.

    Parameters
    ----------
    value : path or ``KIND:PATH``
    image : path, optional
        The image the GCPs are measured in (file name or stem); needed for a file of several images.
    pixel : {"corner", "centre"}, optional
        Pixel convention of GCPs embedded in a GeoTIFF (default ``corner``: GDAL's); refused for any
        other file.
    option : str
        The option that names the image, for the message of a file of several images.

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        The reader's one-line errors; an ambiguous file (choices named); an image the file lacks (its
        images listed); ``pixel`` for a file that is not a GeoTIFF.
    """
    kind, path = resolve_kind(value, GCP_KINDS, "GCP file")
    tiff = kind is OUR_GCPS and path.suffix.lower() in TIFF_SUFFIXES
    if pixel is not None:
        if pixel not in GCP_PIXEL:
            raise InvalidInputError(f"unknown GCP pixel convention {pixel!r}; expected one of {list(GCP_PIXEL)}")
        if not tiff:
            raise InvalidInputError(f"--gcp-pixel {pixel} applies to GCPs embedded in a GeoTIFF; {str(path)!r} is "
                                    f"a {kind.label if kind is not OUR_GCPS else 'GCP table'}")
    if kind.name == "orthority":
        tables = read_oty_gcps(path)
        name = pick_image(list(tables), image, path, kind.label, option)
        return GcpSource(tables[name], path, kind, f"{kind.label} {str(path)!r}, image {name!r}", name)
    if kind.name in ("odm", "metashape"):
        src: Any = read_odm_gcp_list(path) if kind.name == "odm" else read_metashape_chunk(path)
        names = list(dict.fromkeys(src.meas_image))
        if not names:
            raise InvalidInputError(f"{kind.label} {str(path)!r} has no image measurement")
        name = pick_image(names, image, path, kind.label, option)
        return GcpSource(src.gcp_table(name), path, kind, f"{kind.label} {str(path)!r}, image {name!r}", name)
    if tiff and pixel == "centre":
        return GcpSource(read_embedded_gcps_centre(path), path, kind,
                         f"GCPs embedded in {str(path)!r} (pixel centres, orthority's convention)")
    table = read_gcps(path)
    how = f"GCPs embedded in {str(path)!r} (GDAL's pixel corners)" if tiff else f"GCP file {str(path)!r}"
    return GcpSource(table, path, kind, how)

