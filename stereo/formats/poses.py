"""Known poses in and out: the position/angle CSV (``docs/formats.md``).

Columns ``omega,phi,kappa`` (the camera's own angles, R = Rx(omega) Ry(phi) Rz(kappa) taking the
photo vector (x, y, -f) into the ground frame, :func:`rectify.geometry.rotation.matrix_from_angles`)
or ``heading,pitch,roll`` (GNSS/INS navigation angles with an optional boresight and lever arm;
frames and conventions in :mod:`stereo.block.navigation`). OpenSfM's ``reconstruction.json`` is
read by :mod:`stereo.formats.opensfm`.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import atomic_write_text
from rectify.errors import CRSError, InvalidInputError, ShapeError
from rectify.formats.common import TableReader, need_columns, no_duplicates
from rectify.geometry.crs import parse_crs
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles
from stereo.block.navigation import body_rotation, boresight_matrix, check_convention, lever_arm
from stereo.block.types import Pose

__all__ = [
    "ANGLE_UNITS",
    "DEFAULT_CAMERA_ID",
    "PoseTable",
    "pose_csv_text",
    "read_pose_csv",
    "write_pose_csv",
]

StrPath = str | os.PathLike[str]

#: angle units of the position/angle CSV (``# angles=deg|rad``; ``deg`` when the line is absent)
ANGLE_UNITS = ("deg", "rad")
#: camera id of the rows of a pose CSV that name none (no ``camera`` column, empty cell, no ``camera=``)
DEFAULT_CAMERA_ID = "camera"

_OPK = ("omega", "phi", "kappa")
_NAV = ("heading", "pitch", "roll")
_POS = ("x", "y", "z")
_POS_SIGMA = ("sx", "sy", "sz")
_OPK_SIGMA = ("somega", "sphi", "skappa")
_NAV_SIGMA = ("sheading", "spitch", "sroll")


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses read from a position/angle CSV.

    Parameters
    ----------
    poses : tuple of Pose
        One per row, in file order: projection centre (ground frame, metres; lever arm applied) and
        rotation (photo vector -> ground; boresight applied).
    crs : str or None
        The ``# crs=`` value (validated by :mod:`rectify.geometry.crs`), or None.
    sigma : (n, 6) float64 or None
        A-priori standard deviations of x, y, z (metres) and of the three angles (radians) in the
        file's angle system (``angle_system``); NaN where a cell or column is absent; None when
        the file has no standard-deviation column.
    angle_unit : {"deg", "rad"}
        The unit of the angles in the file.
    angle_system : {"omega-phi-kappa", "navigation"}
        ``omega,phi,kappa`` or ``heading,pitch,roll`` columns.
    source : Path or None
        The file read.
    """

    poses: tuple[Pose, ...]
    crs: str | None
    sigma: NDArray[np.float64] | None
    angle_unit: str
    angle_system: str
    source: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "poses", tuple(self.poses))
        if self.sigma is not None:
            s = np.array(self.sigma, dtype=np.float64, copy=True).reshape(-1, 6)
            if len(s) != len(self.poses):
                raise ShapeError(f"sigma must have shape ({len(self.poses)}, 6); got {s.shape}",
                                 actual_shape=s.shape, expected_shape=(len(self.poses), 6))
            s.flags.writeable = False
            object.__setattr__(self, "sigma", s)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def images(self) -> tuple[str, ...]:
        """Image names, in file order."""
        return tuple(p.image for p in self.poses)


def _comment_settings(settings: tuple[tuple[int, str, str], ...], path: StrPath
                      ) -> tuple[str, str | None, int | None]:
    """The ``# angles=`` unit (default ``deg``), the ``# crs=`` value and its line, from a table's
    ``# key=value`` comment lines (:attr:`rectify.formats.common.Columns.settings`)."""
    unit: str | None = None
    unit_line: int | None = None
    crs: str | None = None
    crs_line: int | None = None
    for no, key, value in settings:
        if key == "angles":
            u = value.lower()
            if u not in ANGLE_UNITS:
                raise InvalidInputError(f"{str(path)!r} line {no}: unknown angle unit {value!r}; "
                                        f"expected one of {list(ANGLE_UNITS)}")
            if unit is not None and u != unit:
                raise InvalidInputError(f"{str(path)!r} line {no}: second angle unit {value!r} contradicts "
                                        f"{unit!r} of line {unit_line}")
            unit, unit_line = u, no
        elif key == "crs":
            crs, crs_line = value, no
    return unit or "deg", crs, crs_line


def read_pose_csv(path: StrPath, *, camera: str | None = None, boresight_rad: ArrayLike | None = None,
                  lever_arm_m: ArrayLike | None = None, convention: str = "seed004") -> PoseTable:
    """Read a position/angle CSV (``docs/formats.md``) into poses.

    Header ``image,x,y,z,omega,phi,kappa`` or ``image,x,y,z,heading,pitch,roll``, optional
    ``camera`` and standard deviations ``sx,sy,sz`` and ``somega,sphi,skappa`` (or
    ``sheading,spitch,sroll``), in the units of the values. Comment lines ``# crs=EPSG:nnnn`` and
    ``# angles=deg|rad`` (``deg`` when absent). A byte-order mark is accepted.

    Parameters
    ----------
    path : str or path-like
        The CSV file.
    camera : str, optional
        Camera id of the rows that name none (no ``camera`` column, or an empty cell); default
        :data:`DEFAULT_CAMERA_ID`.
    boresight_rad : (3,) array_like, optional
        Boresight angles (radians) of the camera in the GNSS/INS body frame; navigation files only.
    lever_arm_m : (3,) array_like, optional
        Vector from the projection centre to the antenna phase centre, metres, in the body frame
        (navigation files) or the camera's photo frame (omega-phi-kappa files); the file's
        positions are then antenna positions and C = A - R_body @ lever_arm_m.
    convention : {"seed004", "euler"}
        Roll definition of navigation files (:func:`stereo.block.navigation.rotation_from_navigation`).

    Returns
    -------
    PoseTable

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Missing or unknown columns, both angle systems, non-numeric or non-finite values (naming the
        line and value), negative standard deviations, duplicate or empty image names, an unknown
        angle unit, a boresight with omega-phi-kappa angles.
    CRSError
        The ``# crs=`` value is not a CRS (naming the line).
    """
    p = Path(path)
    conv = check_convention(convention)
    if camera is not None and (not isinstance(camera, str) or not camera):
        raise InvalidInputError(f"camera must be a non-empty camera id; got {camera!r}")
    default_camera = camera or DEFAULT_CAMERA_ID
    with TableReader(p) as t:
        fields = list(t.fields)
        has_opk = any(f in fields for f in _OPK)
        has_nav = any(f in fields for f in _NAV)
        if has_opk and has_nav:
            raise InvalidInputError(f"{str(p)!r}: give either omega,phi,kappa or heading,pitch,roll, not both; "
                                    f"header is {fields}")
        nav = has_nav
        angle_cols = _NAV if nav else _OPK
        angle_sigma_cols = _NAV_SIGMA if nav else _OPK_SIGMA
        need_columns(fields, ("image", *_POS, *angle_cols), p)
        allowed = {"image", "camera", *_POS, *angle_cols, *_POS_SIGMA, *angle_sigma_cols}
        # time, strip and corr_* columns: read by stereo.formats.trajectory.read_pose_extras
        unknown = [f for f in fields if f not in allowed and f not in ("time", "strip") and not f.startswith("corr_")]
        if unknown:
            raise InvalidInputError(f"{str(p)!r}: unknown column(s) {unknown}; allowed are {sorted(allowed)} "
                                    "(and time, strip, corr_*)")
        if boresight_rad is not None and not nav:
            raise InvalidInputError(f"{str(p)!r}: boresight_rad applies to heading,pitch,roll files only; this "
                                    "file has omega,phi,kappa (the camera's own angles)")
        sigma_cols = (*_POS_SIGMA, *angle_sigma_cols)
        present_sigma = tuple(k for k in sigma_cols if k in fields)
        cols = t.read("pose rows", numbers=(*_POS, *angle_cols, *present_sigma), texts=("image", "camera"),
                      empty=present_sigma)
    unit, crs, crs_line = _comment_settings(cols.settings, p)
    if crs is not None:
        try:
            parse_crs(crs)
        except CRSError as err:
            raise CRSError(f"{str(p)!r} line {crs_line}: {err}") from err
    lever = lever_arm(lever_arm_m)
    has_sigma = bool(present_sigma)
    scale = math.pi / 180.0 if unit == "deg" else 1.0
    lines, num = cols.lines, cols.numbers
    images = cols.texts["image"]
    n = len(cols)
    empty = next((i for i, name in enumerate(images) if not name), None)
    if empty is not None:
        raise InvalidInputError(f"{str(p)!r} line {lines[empty]}: empty image name")
    cams = [c or default_camera for c in cols.texts["camera"]]
    pos = np.column_stack([num[k] for k in _POS])
    ang = np.column_stack([num[k] for k in angle_cols]) * scale
    sig = np.full((n, 6), np.nan)
    for j, k in enumerate(sigma_cols):
        if k not in num:
            continue
        v = num[k]
        with np.errstate(invalid="ignore"):
            neg = np.flatnonzero(v < 0)
        if neg.size:
            i = int(neg[0])
            raise InvalidInputError(f"{str(p)!r} line {lines[i]}: standard deviation {k!r} must be >= 0; "
                                    f"got {str(float(v[i]))!r}")
        sig[:, j] = v * (scale if j >= 3 else 1.0)
    no_duplicates(images, p, "image name(s)")

    if nav:
        try:
            Rb = body_rotation(ang[:, 0], ang[:, 1], ang[:, 2], convention=conv)
        except InvalidInputError:
            for i, ln in enumerate(lines):  # name the line
                try:
                    body_rotation(ang[i, 0], ang[i, 1], ang[i, 2], convention=conv)
                except InvalidInputError as err:
                    raise InvalidInputError(f"{str(p)!r} line {ln}: {err}") from err
            raise
        B = boresight_matrix(boresight_rad)
        R = Rb if B is None else Rb @ B
    else:
        R = matrix_from_angles(ang[:, 0], ang[:, 1], ang[:, 2], "omega-phi-kappa")
        Rb = R
    if lever is not None:
        pos = pos - Rb @ lever
    poses = tuple(Pose(images[i], cams[i], pos[i], R[i]) for i in range(n))
    return PoseTable(poses, crs, sig if has_sigma else None, unit, "navigation" if nav else "omega-phi-kappa", p)


def _fmt(v: float) -> str:
    return repr(float(v) + 0.0)  # + 0.0: no "-0.0"


def pose_csv_text(poses: Sequence[Pose], *, crs: str | None, angles: str = "deg",
                  std: ArrayLike | None = None) -> str:
    """The position/angle CSV text of ``poses`` (omega-phi-kappa; see :func:`write_pose_csv`)."""
    if angles not in ANGLE_UNITS:
        raise InvalidInputError(f"unknown angle unit {angles!r}; expected one of {list(ANGLE_UNITS)}")
    if crs is not None:
        parse_crs(crs)
    poses = list(poses)
    if not all(isinstance(q, Pose) for q in poses):
        raise InvalidInputError("poses must be a sequence of stereo.block.types.Pose")
    no_duplicates([q.image for q in poses], "poses", "image name(s)")
    for q in poses:
        if any(c in q.image + q.camera for c in ",\"\n\r") or q.image != q.image.strip() \
                or q.camera != q.camera.strip():
            raise InvalidInputError(f"image name {q.image!r} / camera id {q.camera!r} cannot be written to a CSV "
                                    "cell (comma, quote, line break or surrounding spaces)")
    s: NDArray[np.float64] | None = None
    if std is not None:
        s = np.asarray(std, dtype=np.float64)
        if s.shape != (len(poses), 6):
            raise ShapeError(f"std must have shape ({len(poses)}, 6); got {s.shape}", actual_shape=s.shape,
                             expected_shape=(len(poses), 6))
        if np.any(s < 0) or np.any(np.isinf(s)):
            raise InvalidInputError(f"std must be >= 0 and finite (NaN for unknown); got {s.tolist()}")
    to_unit = 180.0 / math.pi if angles == "deg" else 1.0
    buf = io.StringIO()
    if crs is not None:
        buf.write(f"# crs={crs}\n")
    buf.write(f"# angles={angles}\n")
    buf.write("# R = Rx(omega) Ry(phi) Rz(kappa) takes the photo vector (x, y, -f) into the ground frame\n")
    cols = ["image", "camera", *_POS, *_OPK] + ([*_POS_SIGMA, *_OPK_SIGMA] if s is not None else [])
    buf.write(",".join(cols) + "\n")
    for i, q in enumerate(poses):
        a = angles_from_matrix(q.rotation, "omega-phi-kappa") * to_unit
        vals = [q.image, q.camera, *(_fmt(v) for v in q.position), *(_fmt(v) for v in a)]
        if s is not None:
            vals += ["" if math.isnan(v) else _fmt(v * (to_unit if j >= 3 else 1.0)) for j, v in enumerate(s[i])]
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def write_pose_csv(path: StrPath, poses: Sequence[Pose], *, crs: str | None, angles: str = "deg",
                   std: ArrayLike | None = None, overwrite: bool = False) -> Path:
    """Write poses as a position/angle CSV (omega, phi, kappa), atomically; return the path.

    Parameters
    ----------
    path : str or path-like
        The output; an existing file is replaced only with ``overwrite``.
    poses : sequence of Pose
        Projection centres (ground, metres) and rotations (photo -> ground).
    crs : str or None
        Written as the ``# crs=`` line (validated); None writes none.
    angles : {"deg", "rad"}
        Unit of the angle columns (written as the ``# angles=`` line).
    std : (n, 6) array_like, optional
        Standard deviations of x, y, z (metres) and omega, phi, kappa (radians); NaN cells are left
        empty. Written as ``sx,sy,sz,somega,sphi,skappa`` in the file's units.

    Numbers are written with :func:`repr` (17 significant digits), so they read back exactly.

    Raises
    ------
    InvalidInputError
        Unknown angle unit, duplicate image names, names a CSV cell cannot hold, a bad ``std``, an
        existing output without ``overwrite``.
    CRSError
        ``crs`` is not a CRS.
    RasterIOError
        The file cannot be written (nothing is left behind).
    """
    text = pose_csv_text(poses, crs=crs, angles=angles, std=std)
    return atomic_write_text(path, text, overwrite=overwrite)
