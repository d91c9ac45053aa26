"""The orientation files of the stereo side: one reader and one writer per artefact.

=========================================  ==========================================  =======
artefact (default names)                   ``format`` key                              version
=========================================  ==========================================  =======
relative orientation JSON (``ro.json``,    ``rectify-stereo/relative-orientation``     1
``relative.json``)
exterior orientation JSON (``eo.json``)    ``rectify-stereo/exterior-orientation``     1
model orientation JSON                     ``rectify-stereo/model-orientation``        1
(``points.orientation.json``,
``orientation.json``)
=========================================  ==========================================  =======

The points PLY and CSV written beside them are in :mod:`stereo.formats.points`.

JSON outputs carry ``"format"`` and ``"version"`` keys; readers accept the unversioned files of
release 0.1.0 and reject another format name or a newer version with a one-line error naming the
file and the value. Each writer comes in two forms: ``dump_*`` writes to a path as given (a
temporary path of :meth:`rectify.actions.workspace.Workspace.output`, inside a transaction), ``write_*``
writes atomically on its own (:func:`rectify.atomic.atomic_output`) and refuses to replace a file
without ``overwrite``. The fields, units and frames are documented in ``docs/formats.md``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rectify.atomic import atomic_output, read_json, write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError
from rectify.formats.common import check_format, check_numbers, malformed
from rectify.formats.exterior import exterior_fields
from rectify.report.builder import json_safe
from stereo.pair.resection import ExteriorOrientation
from stereo.relative import RelativeGeometry

if TYPE_CHECKING:  # type hints only: stereo.pair.model imports this module
    from stereo.pair.model import StereoModel

__all__ = [
    "EXTERIOR_FORMAT",
    "FORMAT_VERSION",
    "ORIENTATION_FORMAT",
    "RELATIVE_FORMAT",
    "dump_exterior",
    "dump_orientation",
    "dump_relative",
    "exterior_dict",
    "orientation_dict",
    "read_exterior",
    "read_orientation",
    "read_relative",
    "relative_dict",
    "relative_json_text",
    "write_exterior",
    "write_orientation",
    "write_relative",
]

StrPath = str | os.PathLike[str]

RELATIVE_FORMAT = "rectify-stereo/relative-orientation"
EXTERIOR_FORMAT = "rectify-stereo/exterior-orientation"
ORIENTATION_FORMAT = "rectify-stereo/model-orientation"
#: current version of every stereo JSON format (release 0.1.0 files have no version: read as 1)
FORMAT_VERSION = 1


# ---------------------------------------------------------------------- helpers
def _versioned(name: str, d: dict[str, Any]) -> dict[str, Any]:
    """``d`` with the ``format`` and ``version`` keys first."""
    rest = {k: v for k, v in d.items() if k not in ("format", "version")}
    return {"format": name, "version": FORMAT_VERSION, **rest}


def _write_text_file(tmp: StrPath, text: str) -> None:
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as err:
        raise RasterIOError(f"cannot write {str(tmp)!r}: {write_failure_reason(err, tmp)}") from err


def _atomic(path: StrPath, overwrite: bool, dump: Callable[[Path], None]) -> Path:
    with atomic_output(path, overwrite=overwrite) as tmp:
        dump(tmp)
    return Path(path)


# ---------------------------------------------------------- relative orientation
def relative_dict(ro: Any, *, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The relative orientation JSON as a dict: format, version, ``ro.to_dict()`` and ``extra`` (cameras).

    Parameters
    ----------
    ro : RelativeOrientation or dict
        The estimate, or its dict form.
    extra : dict, optional
        More keys, e.g. ``{"camera": camera.to_dict()}`` (``stereo orient`` stores the cameras).
    """
    d = ro if isinstance(ro, dict) else ro.to_dict()
    return _versioned(RELATIVE_FORMAT, {**d, **(extra or {})})


def relative_json_text(ro: Any, *, extra: dict[str, Any] | None = None) -> str:
    """The text of the relative orientation JSON (indented, no trailing newline)."""
    return json.dumps(relative_dict(ro, extra=extra), indent=2)


def dump_relative(path: StrPath, ro: Any, *, extra: dict[str, Any] | None = None) -> None:
    """Write the relative orientation JSON to ``path`` as given (no overwrite check)."""
    _write_text_file(path, relative_json_text(ro, extra=extra) + "\n")


def write_relative(path: StrPath, ro: Any, *, extra: dict[str, Any] | None = None,
                   overwrite: bool = False) -> Path:
    """Write the relative orientation JSON atomically (see :func:`relative_dict`)."""
    return _atomic(path, overwrite, lambda tmp: dump_relative(tmp, ro, extra=extra))


def read_relative(path: StrPath) -> RelativeGeometry:
    """Read a relative orientation JSON (``stereo orient``'s ``ro.json``, ``stereo run``'s ``relative.json``).

    Returns
    -------
    RelativeGeometry
        Rotations, base and focal lengths; ``raw`` holds the whole file (points, cameras).

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Not JSON, another format or a newer version, or a key intersection needs is missing.
    """
    p = Path(path)
    d = read_json(p, "relative orientation")
    check_format(d, "relative-orientation", FORMAT_VERSION, p, what="relative orientation file")
    missing = [k for k in ("rotation_left", "rotation_right", "base", "focal_length_mm") if k not in d]
    if missing:
        raise InvalidInputError(f"{str(p)!r} is not a relative orientation JSON: missing {missing}")
    check_numbers(d, "rotation_left", (3, 3), p)
    check_numbers(d, "rotation_right", (3, 3), p)
    check_numbers(d, "base", (3,), p)
    f = d["focal_length_mm"]
    check_numbers(d, "focal_length_mm", (2,) if isinstance(f, list) else (), p)
    for key in ("sigma0_mm", "pixel_size_mm"):
        if d.get(key) is not None:
            check_numbers(d, key, (), p)
    with malformed(f"relative orientation file {str(p)!r}"):
        return RelativeGeometry.from_dict(d, source=repr(str(p)))


# ---------------------------------------------------------- exterior orientation
def exterior_dict(eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None) -> dict[str, Any]:
    """The exterior orientation JSON as a dict: format, version, ``eo.to_dict()`` and the camera."""
    d = eo.to_dict()
    s0 = d.get("sigma0_mm")
    if s0 is not None and not math.isfinite(float(s0)):
        d["sigma0_mm"] = None  # not adjusted (no redundancy): JSON null, not NaN
    if camera is not None:
        d["camera"] = camera
    return _versioned(EXTERIOR_FORMAT, d)


def dump_exterior(path: StrPath, eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None) -> None:
    """Write the exterior orientation JSON to ``path`` as given."""
    _write_text_file(path, json.dumps(exterior_dict(eo, camera=camera), indent=2))


def write_exterior(path: StrPath, eo: ExteriorOrientation, *, camera: dict[str, Any] | None = None,
                   overwrite: bool = False) -> Path:
    """Write the exterior orientation JSON (``stereo resect``'s ``eo.json``) atomically."""
    return _atomic(path, overwrite, lambda tmp: dump_exterior(tmp, eo, camera=camera))


def read_exterior(path: StrPath) -> ExteriorOrientation:
    """Read an exterior orientation JSON.

    Format, version, position, rotation (or omega-phi-kappa angles) and CRS are checked and read by
    :func:`rectify.formats.exterior.exterior_fields` (the one reader of the EO geometry); the focal
    length and principal point are read here; the covariance is rebuilt from ``std_errors`` and
    ``correlation`` when both are present, and ``sigma0_mm``, ``iterations``, ``converged`` when present.
    Other keys (camera, points, residual summary) are kept in ``extra``.

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Not JSON, another format or a newer version, a missing or bad key.
    """
    p = Path(path)
    d = read_json(p, "exterior orientation file")
    geometry = exterior_fields(d, p)
    with malformed(f"exterior orientation file {str(p)!r}"):
        return _exterior(d, p, geometry)


def _exterior(d: dict[str, Any], p: Path, geometry: dict[str, Any]) -> ExteriorOrientation:
    if "focal_length_mm" in d:
        check_numbers(d, "focal_length_mm", (), p)
    if d.get("principal_point_mm") is not None:
        check_numbers(d, "principal_point_mm", (2,), p)
    for key in ("sigma0_mm", "iterations"):
        if d.get(key) is not None:
            check_numbers(d, key, (), p)
    if d.get("converged") is not None and not isinstance(d["converged"], bool):
        raise InvalidInputError(f"{str(p)!r}: `converged` must be true or false; got {d['converged']!r}")
    try:
        eo = ExteriorOrientation(position=geometry["position"], rotation=geometry["rotation"],
                                 focal_length_mm=d["focal_length_mm"],
                                 principal_point_mm=d.get("principal_point_mm", (0.0, 0.0)), crs=geometry["crs"])
    except KeyError as err:
        raise InvalidInputError(f"{str(p)!r}: exterior orientation JSON lacks or has a bad key: {err}") from err
    except (InvalidInputError, TypeError, ValueError) as err:
        raise InvalidInputError(f"{str(p)!r}: {err}") from err
    cov = None
    corr = d.get("correlation")
    std = d.get("std_errors")
    names: tuple[str, ...] = eo.param_names
    if isinstance(corr, dict) and isinstance(std, dict) and corr.get("matrix") is not None:
        given = corr.get("names") or names
        if not isinstance(given, (list, tuple)) or not all(isinstance(k, str) for k in given):
            raise InvalidInputError(f"{str(p)!r}: `correlation.names` must be a list of parameter names; "
                                    f"got {given!r:.80}")
        names = tuple(given)
        try:
            s = np.array([float(std[k]) for k in names])
            cov = np.array(corr["matrix"], dtype=np.float64) * np.outer(s, s)
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"{str(p)!r}: bad std_errors/correlation: {err}") from err
    sigma0 = d.get("sigma0_mm")
    known = {"format", "version", "position", "rotation", "rotation_convention", "angles", "focal_length_mm",
             "principal_point_mm", "std_errors", "sigma0_mm", "iterations", "converged", "crs", "correlation",
             "residuals", "points"}
    return ExteriorOrientation(
        position=eo.position, rotation=eo.rotation, focal_length_mm=eo.focal_length_mm,
        principal_point_mm=eo.principal_point_mm, covariance=cov, param_names=names,
        sigma0=float("nan") if sigma0 is None else float(sigma0), iterations=int(d.get("iterations") or 0),
        converged=d.get("converged") is not False, crs=eo.crs,
        extra={k: v for k, v in d.items() if k not in known})


# --------------------------------------------------------- model orientation JSON
def orientation_dict(model: StereoModel, *, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The model orientation JSON as a dict: frame, CRS, summary, absolute orientation (NaN -> null)."""
    d: dict[str, Any] = {"frame": model.frame, "crs": model.crs, "summary": model.summary}
    if model.absolute is not None:
        d["absolute"] = model.absolute.to_dict()
    if extra:
        d.update(extra)
    return _versioned(ORIENTATION_FORMAT, json_safe(d))


def dump_orientation(path: StrPath, d: dict[str, Any]) -> None:
    """Write a model orientation dict (:func:`orientation_dict`) to ``path`` as given."""
    _write_text_file(path, json.dumps(json_safe(_versioned(ORIENTATION_FORMAT, d)), indent=2))


def write_orientation(path: StrPath, d: dict[str, Any], *, overwrite: bool = False) -> Path:
    """Write a model orientation dict (:func:`orientation_dict`) atomically."""
    return _atomic(path, overwrite, lambda tmp: dump_orientation(tmp, d))


def read_orientation(path: StrPath) -> dict[str, Any]:
    """Read a model orientation JSON (``points.orientation.json``, ``orientation.json``).

    Returns
    -------
    dict
        ``frame`` (``name``; ``origin_lon_lat_h`` for the topocentric frame), ``crs``, ``summary``
        and, when the model was oriented to control, ``absolute``.

    Raises
    ------
    RasterIOError, InvalidInputError
        Missing file, not JSON, another format or a newer version, no ``frame``/``summary``.
    """
    p = Path(path)
    d = read_json(p, "orientation file")
    check_format(d, "model-orientation", FORMAT_VERSION, p, what="orientation file")
    missing = [k for k in ("frame", "summary") if not isinstance(d.get(k), dict)]
    if missing:
        raise InvalidInputError(f"{str(p)!r} is not a model orientation JSON: missing {missing}")
    if not isinstance(d["frame"].get("name"), str):
        raise InvalidInputError(f"{str(p)!r}: the frame has no name")
    return d
