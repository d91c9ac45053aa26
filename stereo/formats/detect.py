"""Which reader a block's ``--poses`` and ``--control`` files need, by content (:mod:`rectify.formats.detect`'s rule).

Each family is a tuple of :class:`rectify.formats.detect.FileKind`; one kind that recognises the file
reads it, none gives the project's own format (the position/angle CSV, or an OpenSfM
``reconstruction.json`` for a ``.json``; the block control CSV), several are refused with the choices
named (``KIND:PATH`` picks one). ``--camera`` is :func:`rectify.formats.detect.read_camera_file`.

=============  ===================================================================================
family         kinds (prefix: reader)
=============  ===================================================================================
poses          ``poses``: position/angle CSV; ``opensfm``: OpenSfM/ODM ``reconstruction.json``;
               ``colmap``: COLMAP text model (cameras, poses and its tracks); ``metashape``:
               Metashape cameras XML; ``orthority``: ext_param GeoJSON; ``orthority-csv``: CSV
               (+ .prj); ``odm-geo``: ODM ``geo.txt`` (positions only: GNSS observations)
control        ``control``: block control CSV; ``odm``: ODM ``gcp_list.txt``; ``metashape``:
               Metashape markers XML
=============  ===================================================================================

The poses of every kind come out as :class:`PoseFile`: :class:`stereo.block.types.Pose` objects in
the file's frame (with the file's CRS when it names one), the cameras the file holds, and what the
kind adds (an OpenSfM reconstruction's GPS, a COLMAP model's tracks, a pose CSV's standard
deviations, ``geo.txt``'s positions and accuracies).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath
from rectify.formats.detect import FileKind, detect_pose_csv, resolve_kind
from rectify.formats.metashape import detect_metashape
from rectify.formats.orthority import detect_ext_param, detect_frame_csv, read_ext_param, read_frame_csv
from rectify.geometry.camera import Camera
from stereo.block.types import Pose, Tracks
from stereo.formats.block import BlockControlTable, read_block_control
from stereo.formats.colmap import detect_colmap, read_colmap
from stereo.formats.metashape import read_metashape
from stereo.formats.odm import OdmGeo, detect_odm_gcps, detect_odm_geo, read_odm_gcps, read_odm_geo
from stereo.formats.opensfm import OpenSfMReconstruction, read_opensfm
from stereo.formats.poses import read_pose_csv

__all__ = ["POSE_KINDS", "CONTROL_KINDS", "PoseFile", "read_pose_file", "resolve_control", "read_control_file",
           "detect_opensfm"]

_SNIFF_BYTES = 1 << 16


def detect_opensfm(path: StrPath) -> bool:
    """Whether ``path`` is an OpenSfM ``reconstruction.json``: a ``.json`` list of reconstructions with ``shots``."""
    p = Path(path)
    if p.suffix.lower() != ".json" or not p.is_file():
        return False
    try:
        with open(p, encoding="utf-8-sig", errors="replace") as fh:
            head = fh.read(_SNIFF_BYTES)
    except OSError:
        return False
    return head.lstrip().startswith("[") and '"shots"' in head


OUR_POSES = FileKind("poses", "position/angle CSV", detect_pose_csv)
OPENSFM = FileKind("opensfm", "OpenSfM/ODM reconstruction.json", detect_opensfm)
#: the kinds ``stereo block --poses`` reads
POSE_KINDS: tuple[FileKind, ...] = (
    OUR_POSES,
    OPENSFM,
    FileKind("colmap", "COLMAP text model", detect_colmap),
    FileKind("metashape", "Metashape cameras XML", detect_metashape),
    FileKind("orthority", "orthority exterior parameters", detect_ext_param),
    FileKind("orthority-csv", "orthority CSV of exterior parameters", detect_frame_csv),
    FileKind("odm-geo", "OpenDroneMap geo.txt", detect_odm_geo),
)
OUR_CONTROL = FileKind("control", "block control CSV", lambda p: False)
#: the kinds ``stereo block --control`` reads
CONTROL_KINDS: tuple[FileKind, ...] = (
    OUR_CONTROL,
    FileKind("odm", "OpenDroneMap gcp_list.txt", detect_odm_gcps),
    FileKind("metashape", "Metashape markers XML", detect_metashape),
)


@dataclass(frozen=True, eq=False)
class PoseFile:
    """The poses of a ``--poses`` file, in the file's frame.

    Attributes
    ----------
    path : Path
    kind : FileKind
    poses : tuple of Pose
        One per image of the file (none for ``geo.txt``, which has no rotations).
    cameras : dict of str -> Camera
        The cameras the file holds (OpenSfM, COLMAP, Metashape), by the ids the poses name.
    crs : str or None
        The CRS of the positions (None: the file names none).
    frame : str
        What the coordinates are.
    sigma : (n, 6) float64 or None
        A pose CSV's standard deviations (x, y, z, three angles).
    angle_system : str
        ``omega-phi-kappa`` or ``navigation`` (a pose CSV's angles).
    reconstruction : OpenSfMReconstruction or None
        The OpenSfM reconstruction (its GPS, reference and frame conversion).
    tracks : Tracks or None
        A COLMAP model's tracks (pixels in our convention; image names as in the model).
    geo : OdmGeo or None
        ``geo.txt``'s positions and accuracies.
    """

    path: Path
    kind: FileKind
    poses: tuple[Pose, ...]
    cameras: dict[str, Camera]
    crs: str | None
    frame: str
    sigma: NDArray[np.float64] | None = None
    angle_system: str = "omega-phi-kappa"
    reconstruction: OpenSfMReconstruction | None = None
    tracks: Tracks | None = None
    geo: OdmGeo | None = None


def _poses_of(exteriors: dict[str, dict[str, Any]], default_camera: str, path: Path) -> tuple[Pose, ...]:
    out = []
    for name, eo in exteriors.items():
        try:
            out.append(Pose(name, str(eo.get("camera") or default_camera), eo["position"], eo["rotation"]))
        except InvalidInputError as err:
            raise InvalidInputError(f"{str(path)!r}: {err}") from None
    return tuple(out)


def read_pose_file(value: StrPath, *, camera: str | None = None, boresight_rad: ArrayLike | None = None,
                   lever_arm_m: ArrayLike | None = None, crs: str | None = None) -> PoseFile:
    """Read a ``--poses`` file of any kind of :data:`POSE_KINDS` (``KIND:PATH`` picks one).

    Parameters
    ----------
    value : path or ``KIND:PATH``
    camera : str, optional
        The camera id of poses whose file names none (default ``camera``).
    boresight_rad, lever_arm_m : (3,) array_like, optional
        A pose CSV's boresight and lever arm (:func:`stereo.formats.poses.read_pose_csv`).
    crs : str, optional
        The projected CRS to return georeferenced poses in (a georeferenced Metashape chunk, geo.txt),
        or the CRS of a frame the file does not name (COLMAP); checked against an orthority CSV's.

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        The reader's one-line errors (file, key and value named); an ambiguous file (choices named).
    """
    kind, path = resolve_kind(value, POSE_KINDS, "pose file")
    if kind is OUR_POSES and not kind.detect(path) and path.suffix.lower() == ".json":
        kind = OPENSFM  # what a .json --poses has always been read as; its reader names what is wrong
    if kind is OPENSFM:
        rec = read_opensfm(path)
        return PoseFile(path, kind, tuple(rec.poses), dict(rec.cameras), rec.crs, rec.frame, reconstruction=rec)
    if kind.name == "colmap":
        model = read_colmap(path)
        return PoseFile(path, kind, tuple(model.poses), dict(model.cameras), crs,
                        f"the COLMAP model's frame{f' (taken as {crs})' if crs else ''}", tracks=model.tracks)
    if kind.name == "metashape":  # a georeferenced chunk is converted into crs; a local one keeps its frame
        doc = read_metashape(path)
        if doc.reference_crs is not None and crs is not None:
            doc = read_metashape(path, crs=crs)
        return PoseFile(path, kind, doc.poses, dict(doc.cameras), doc.crs, doc.frame)
    if kind.name == "orthority":
        eos = read_ext_param(path)
        c = next(iter(eos.values()))["crs"]
        return PoseFile(path, kind, _poses_of(eos, camera or "camera", path), {}, c,
                        "the world_crs of the exterior parameters")
    if kind.name == "orthority-csv":
        eos = read_frame_csv(path, crs=crs)
        c = next(iter(eos.values()))["crs"]
        return PoseFile(path, kind, _poses_of(eos, camera or "camera", path), {}, c,
                        "the CRS of the orthority CSV (.prj or '# crs=')" if c else "the CSV's frame (no CRS)")
    if kind.name == "odm-geo":
        geo = read_odm_geo(path, crs=crs)
        return PoseFile(path, kind, (), {}, geo.crs, f"{geo.crs} (geo.txt's positions, projected as ODM does)",
                        geo=geo)
    table = read_pose_csv(path, camera=camera, boresight_rad=boresight_rad, lever_arm_m=lever_arm_m)
    return PoseFile(path, kind, tuple(table.poses), {}, table.crs, "", sigma=table.sigma,
                    angle_system=table.angle_system)


def resolve_control(value: StrPath) -> tuple[FileKind, Path]:
    """The kind of a ``--control`` file (:data:`CONTROL_KINDS`) and its path."""
    return resolve_kind(value, CONTROL_KINDS, "control file")


def read_control_file(value: StrPath, *, crs: str | None = None) -> tuple[BlockControlTable, str]:
    """Read a ``--control`` file of any kind of :data:`CONTROL_KINDS`; the table and a note of where it came from
    ('' for the block control CSV).

    ``crs``: the projected CRS to return ODM and Metashape coordinates in (the poses' frame).

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        The reader's one-line errors; an ambiguous file (choices named).
    """
    kind, path = resolve_control(value)
    if kind.name == "odm":
        g = read_odm_gcps(path, crs=crs)
        return g.control_table(), (f"control: the {len(g.ids)} GCPs of {str(path)!r} (OpenDroneMap gcp_list.txt, "
                                   f"{len(g.meas_id)} image measurements, in {g.crs})")
    if kind.name == "metashape":  # a georeferenced chunk is converted into crs; a local one keeps its frame
        doc = read_metashape(path)
        if doc.reference_crs is not None and crs is not None:
            doc = read_metashape(path, crs=crs)
        t = doc.control_table()
        n_full = sum(k == "full" for k in t.kind)
        return t, (f"control: the {len(t.ids)} markers of {str(path)!r} (Metashape XML, {n_full} with reference "
                   f"coordinates, {len(t.meas_id)} image measurements, in {doc.crs or 'its local frame'})")
    return read_block_control(path), ""
