"""The focal setting an image records: its EXIF ``FocalLength`` (mm), read through GDAL's metadata.

GDAL exposes the EXIF tags of JPEG and TIFF files in the default metadata domain, as
``EXIF_FocalLength = "(24.5)"`` (a rational printed in parentheses). A zoom camera
(:class:`rectify.geometry.zoom.ZoomCamera`) calibrated over EXIF focal lengths is evaluated at this
value; ``--focal-setting`` overrides it.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

from rectify.errors import InvalidInputError
from rectify.raster.io import open_raster

__all__ = ["EXIF_FOCAL_TAG", "exif_focal_length", "parse_exif_number"]

#: GDAL's metadata key of EXIF FocalLength
EXIF_FOCAL_TAG = "EXIF_FocalLength"
_NUMBER = re.compile(r"^\(?\s*([-+0-9.eE]+)\s*(?:/\s*([-+0-9.eE]+))?\s*\)?$")


def parse_exif_number(text: str) -> float | None:
    """``"(24.5)"``, ``"24.5"`` or ``"245/10"`` -> 24.5; None when the text is no positive finite number."""
    m = _NUMBER.match(text.strip())
    if m is None:
        return None
    try:
        v = float(m.group(1)) / (float(m.group(2)) if m.group(2) else 1.0)
    except (ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def exif_focal_length(image: str | os.PathLike[str]) -> float | None:
    """The EXIF focal length (mm) of ``image``, or None when the image records none.

    Raises
    ------
    RasterIOError
        The image is missing or unreadable.
    InvalidInputError
        The tag is present but not a positive number (its text named).
    """
    with open_raster(Path(image)) as src:
        tag = src.tags().get(EXIF_FOCAL_TAG)
    if tag is None:
        return None
    v = parse_exif_number(tag)
    if v is None:
        raise InvalidInputError(f"image {str(image)!r}: EXIF FocalLength {tag!r} is not a positive number")
    return v
