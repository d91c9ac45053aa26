"""``stereo block`` with a zoom camera: every image's camera evaluated at its own focal setting.

A zoom camera JSON (``stereo calibrate --zoom``, :class:`rectify.geometry.zoom.ZoomCamera`) given as
``--camera`` is evaluated once per image at the image's focal setting, found in this order:

1. the settings CSV of ``--focal-settings`` (``image,setting``; the image's file name or stem; the
   format of ``stereo calibrate --settings``, :func:`stereo.formats.zoom.read_settings_csv`);
2. the image's EXIF FocalLength (mm, :func:`rectify.raster.exif.exif_focal_length`).

The block then has one camera per distinct setting, id ``zoom_<setting><unit>`` (``zoom_18mm``),
and every image names the camera of its setting (overriding the camera ids of a pose file). A
setting outside the calibrated range (plus :data:`rectify.geometry.zoom.ZOOM_MARGIN` of it) is
refused with the image named, as is an image of no setting (the options that give one named).

With ``--self-calibrate`` each setting's camera is calibrated on its own by the bundle (written as
``camera_zoom_<setting>.json``); the zoom camera file is not changed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from rectify.actions.workspace import StrPath
from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.camera import read_zoom_camera
from rectify.formats.detect import input_paths, is_zoom_camera
from rectify.geometry.camera import Camera
from rectify.raster.exif import exif_focal_length
from stereo.block.types import Pose
from stereo.formats.zoom import read_settings_csv, setting_for

__all__ = ["ZOOM_ID_PREFIX", "ZoomBlock", "zoom_block", "zoom_camera_id"]

#: prefix of the camera ids of a zoom block (``zoom_18mm``)
ZOOM_ID_PREFIX = "zoom_"


def zoom_camera_id(setting: float, unit: str) -> str:
    """The block camera id of a focal setting: ``zoom_<setting><unit>`` (``zoom_18mm``, ``zoom_2.5``)."""
    return f"{ZOOM_ID_PREFIX}{setting:g}{unit}"


@dataclass(frozen=True, eq=False)
class ZoomBlock:
    """The cameras of a block taken with a zoom lens.

    Attributes
    ----------
    path : Path
        The zoom camera JSON.
    settings : tuple of float
        Each image's focal setting, in block order (the zoom calibration's unit).
    sources : tuple of str
        Where each setting came from: ``"EXIF"`` or ``"--focal-settings"``.
    cameras : dict id -> Camera
        One camera per distinct setting (pixel frame; the zoom camera evaluated there).
    camera_of : tuple of str
        Each image's camera id, in block order.
    line : str
        The summary line (settings, cameras, what ``--self-calibrate`` does).
    """

    path: Path
    settings: tuple[float, ...]
    sources: tuple[str, ...]
    cameras: dict[str, Camera]
    camera_of: tuple[str, ...]
    line: str

    def assign(self, poses: Sequence[Pose] | None) -> list[Pose] | None:
        """``poses`` (block order) naming each image's zoom camera; None stays None."""
        if poses is None:
            return None
        return [replace(p, camera=c) for p, c in zip(poses, self.camera_of, strict=True)]


def zoom_block(camera: object, images: Sequence[StrPath], names: Sequence[str], settings_csv: StrPath | None,
               *, self_calibrate: bool = False) -> ZoomBlock | None:
    """The zoom cameras of a block when ``camera`` is a zoom camera JSON; None for any other camera file.

    Parameters
    ----------
    camera : path, Camera, mapping or None
        The ``--camera`` value (``PATH`` or ``camera:PATH``); anything but a path gives None.
    images : sequence of paths
        The block's images (their EXIF FocalLength is read when the settings CSV lacks them); may be
        empty (an observations CSV without images: every setting from ``settings_csv``).
    names : sequence of str
        The block's image names, in order.
    settings_csv : path, optional
        ``--focal-settings``: ``image,setting`` rows.
    self_calibrate : bool
        For the summary line.

    Raises
    ------
    InvalidInputError
        ``settings_csv`` with a camera that is not a zoom camera; a settings CSV naming an image the block
        lacks; an image of no setting (neither in the CSV nor in its EXIF; the options named).
    CalibrationError
        A setting outside the calibrated range (the image, the setting and the range named); a malformed
        zoom camera file.
    RasterIOError
        An unreadable image.
    """
    if not (isinstance(camera, (str, Path)) and is_zoom_camera(camera)):
        if settings_csv is not None:
            what = f"{str(camera)!r} is not one" if isinstance(camera, (str, Path)) else "no zoom camera file is given"
            raise InvalidInputError(f"--focal-settings {str(settings_csv)!r} goes with a zoom camera (--camera of "
                                    f"stereo calibrate --zoom); {what}")
        return None
    path = input_paths(camera)[0]
    zoom = read_zoom_camera(path)
    table = read_settings_csv(Path(settings_csv)) if settings_csv is not None else {}
    known = {*names, *(Path(n).stem for n in names)}
    extra = sorted(k for k in table if k not in known)
    if extra:
        raise InvalidInputError(f"settings file {str(settings_csv)!r} names image(s) {extra[:5]} that are not in the "
                                f"block (images: {list(names)[:5]}{' ...' if len(names) > 5 else ''})")
    paths: list[StrPath | None] = list(images) if len(images) == len(names) else [None] * len(names)
    settings: list[float] = []
    sources: list[str] = []
    unit = f" {zoom.unit}" if zoom.unit else ""
    for name, img in zip(names, paths, strict=True):
        z, src = setting_for(name, table), "--focal-settings"
        if z is None and img is not None and Path(img).is_file():
            z, src = exif_focal_length(img), "EXIF"
        if z is None:
            raise InvalidInputError(f"image {name!r} has no focal setting for the zoom camera {str(path)!r} "
                                    f"(calibrated {zoom.low:g}..{zoom.high:g}{unit}): it has no EXIF FocalLength; give "
                                    "its setting in --focal-settings CSV (image,setting)")
        try:
            settings.append(zoom.check_setting(z))
        except (CalibrationError, InvalidInputError) as err:
            raise type(err)(f"image {name!r} ({src}): {err}") from None
        sources.append(src)
    cameras: dict[str, Camera] = {}
    for z in sorted(set(settings)):
        cid = zoom_camera_id(z, zoom.unit)
        if cid in cameras:  # two settings that print alike (beyond 6 significant digits)
            raise InvalidInputError(f"focal settings of the block differ beyond 6 significant digits near {z:g}"
                                    f"{unit}: round them in --focal-settings")
        try:
            cameras[cid] = zoom.camera(z)
        except CalibrationError as err:
            raise CalibrationError(f"zoom camera {str(path)!r} at setting {z:g}{unit}: {err}") from None
    camera_of = tuple(zoom_camera_id(z, zoom.unit) for z in settings)
    counts = ", ".join(f"{cid} ({camera_of.count(cid)} image{'s' if camera_of.count(cid) > 1 else ''})"
                       for cid in cameras)
    srcs = ", ".join(f"{s} {sources.count(s)}" for s in ("--focal-settings", "EXIF") if s in sources)
    line = (f"zoom camera {str(path)!r} (calibrated {zoom.low:g}..{zoom.high:g}{unit}) evaluated at each image's "
            f"focal setting ({srcs}): {len(cameras)} camera{'s' if len(cameras) > 1 else ''} {counts}")
    if self_calibrate:
        line += "; --self-calibrate calibrates each setting's camera on its own (camera_<id>.json)"
    return ZoomBlock(path, tuple(settings), tuple(sources), cameras, camera_of, line)
