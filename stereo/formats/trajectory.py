"""GNSS/INS trajectory CSV, image times, strips and pose covariances (``docs/formats.md``).

Trajectory CSV
    ``time,x,y,z,heading,pitch,roll`` (+ optional ``sx,sy,sz,sheading,spitch,sroll``): seconds,
    antenna positions in the ground CRS (``# crs=`` line or ``.prj`` sidecar; they must agree),
    navigation angles in ``# angles=deg|rad`` (deg when absent); times strictly increasing.
Pose-file extras
    Columns a position/angle CSV (:mod:`stereo.formats.poses`) may carry, and that an image-times
    CSV ``image,time[,strip][,camera]`` (the ``--poses`` file with ``--trajectory``) holds:
    ``time`` (exposure time, s), ``strip`` (strip or flight label) and correlation coefficients
    ``corr_A_B`` of any two of ``x,y,z`` and the file's three angles (``corr_x_y``,
    ``corr_x_heading``, ``corr_pitch_roll``, ...; an absent one is 0), which with the standard
    deviations make each image's full 3 x 3 or 6 x 6 covariance.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.formats.common import TableReader, need_columns, no_duplicates
from rectify.geometry.crs import parse_crs, same_crs
from stereo.block.bundle.systematic import check_inputs
from stereo.block.navigation import boresight_matrix, lever_arm
from stereo.block.trajectory import INTERPOLATIONS, Trajectory, opk_covariance
from stereo.block.types import GnssObservations, Pose
from stereo.formats.detect import OUR_POSES, PoseFile, read_pose_file

__all__ = ["POSE_EXTRA_COLUMNS", "PoseExtras", "TrajectoryFile", "block_gnss", "gnss_with_extras", "image_times_names",
           "read_pose_extras",
           "read_poses_with_extras", "read_trajectory_csv", "trajectory_pose_file"]

StrPath = str | os.PathLike[str]
F64 = NDArray[np.float64]

_POS = ("x", "y", "z")
_NAV = ("heading", "pitch", "roll")
_OPK = ("omega", "phi", "kappa")


def _corr_names(angles: Sequence[str]) -> tuple[str, ...]:
    return tuple(f"corr_{a}_{b}" for a, b in combinations((*_POS, *angles), 2))


#: columns a position/angle CSV may have besides its poses and standard deviations
POSE_EXTRA_COLUMNS: tuple[str, ...] = ("time", "strip", *_corr_names(_NAV),
                                       *(c for c in _corr_names(_OPK) if c not in _corr_names(_NAV)))


@dataclass(frozen=True, eq=False)
class TrajectoryFile:
    """A trajectory CSV read: the samples, their CRS and the file."""

    trajectory: Trajectory
    crs: str | None
    path: Path


def _csv_crs(path: Path, line_crs: str | None) -> str | None:
    """The CRS of a CSV from its ``# crs=`` line and ``.prj`` sidecar (refused when they disagree)."""
    prj = path.with_suffix(".prj")
    side = None
    if prj.is_file():
        try:
            side = prj.read_text(encoding="utf-8-sig").strip()
        except (OSError, UnicodeDecodeError) as err:
            raise RasterIOError(f"cannot read {str(prj)!r}: {err}") from err
        if not side:
            raise InvalidInputError(f"{str(prj)!r} is empty; it should hold the CRS of {str(path)!r}")
    for value, where in ((line_crs, f"the '# crs=' line of {str(path)!r}"), (side, repr(str(prj)))):
        if value:
            try:
                parse_crs(value)
            except CRSError as err:
                raise CRSError(f"{where}: {err}") from None
    if line_crs and side and not same_crs(line_crs, side):
        raise CRSError(f"{str(prj)!r} gives CRS {side[:80]!r}, which contradicts the '# crs=' line of {str(path)!r} "
                       f"({line_crs[:80]!r})")
    return line_crs or side


def _angle_scale(settings: tuple[tuple[int, str, str], ...], path: Path) -> float:
    unit = "deg"
    for no, key, value in settings:
        if key == "angles":
            if value.lower() not in ("deg", "rad"):
                raise InvalidInputError(f"{str(path)!r} line {no}: unknown angle unit {value!r}; expected deg or rad")
            unit = value.lower()
    return np.pi / 180.0 if unit == "deg" else 1.0


def read_trajectory_csv(path: StrPath, *, convention: str = "seed004") -> TrajectoryFile:
    """Read a trajectory CSV (module docstring).

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        Missing or unknown columns, a bad number (line and value named), fewer than two samples, times
        not strictly increasing, a standard deviation <= 0.
    CRSError
        A CRS that is not one, or a ``# crs=`` line and ``.prj`` that disagree.
    """
    p = Path(path)
    sig_cols = ("sx", "sy", "sz", "sheading", "spitch", "sroll")
    with TableReader(p) as t:
        fields = list(t.fields)
        need_columns(fields, ("time", *_POS, *_NAV), p)
        allowed = {"time", *_POS, *_NAV, *sig_cols}
        unknown = [f for f in fields if f not in allowed]
        if unknown:
            raise InvalidInputError(f"{str(p)!r}: unknown column(s) {unknown}; allowed are {sorted(allowed)}")
        present = tuple(c for c in sig_cols if c in fields)
        cols = t.read("trajectory rows", numbers=("time", *_POS, *_NAV, *present), empty=present)
    crs = _csv_crs(p, cols.crs)
    scale = _angle_scale(cols.settings, p)
    num = cols.numbers
    sig = None
    if present:
        sig = np.column_stack([num[c] if c in num else np.full(len(cols), np.nan) for c in sig_cols])
        sig[:, 3:] *= scale
    try:
        traj = Trajectory(num["time"], np.column_stack([num[c] for c in _POS]),
                          np.column_stack([num[c] for c in _NAV]) * scale, sig, convention, f"trajectory {p.name!r}")
    except InvalidInputError as err:
        raise InvalidInputError(f"{str(p)!r}: {err}") from err
    return TrajectoryFile(traj, crs, p)


@dataclass(frozen=True, eq=False)
class PoseExtras:
    """The extra columns of a pose or image-times CSV.

    Attributes
    ----------
    images : tuple of str
    lines : (n,) int64
        File line of each row.
    time : (n,) float64 or None
        Exposure times, s.
    strip : tuple of str or None
    correlation : (n, 6, 6) float64 or None
        Correlation matrices of (x, y, z, three angles of the file), identity where no column.
    angle_system : str
        ``navigation`` or ``omega-phi-kappa`` (the names of the correlation columns).
    """

    images: tuple[str, ...]
    lines: NDArray[np.int64]
    time: F64 | None
    strip: tuple[str, ...] | None
    correlation: F64 | None
    angle_system: str


def read_pose_extras(path: StrPath) -> PoseExtras:
    """The ``time``, ``strip`` and ``corr_*`` columns of a position/angle or image-times CSV (other columns
    are left to :func:`stereo.formats.poses.read_pose_csv`).

    Raises
    ------
    InvalidInputError
        Correlation columns of both angle systems, a correlation outside [-1, 1], an empty strip cell,
        a non-finite time (line named).
    """
    p = Path(path)
    with TableReader(p) as t:
        fields = list(t.fields)
        need_columns(fields, ("image",), p)
        nav_c = [c for c in fields if c in _corr_names(_NAV) and c not in _corr_names(_POS)]
        opk_c = [c for c in fields if c in _corr_names(_OPK) and c not in _corr_names(_POS)]
        if nav_c and opk_c:
            raise InvalidInputError(f"{str(p)!r}: correlation columns of both angle systems ({nav_c[0]}, {opk_c[0]})")
        system = "omega-phi-kappa" if opk_c or any(c in fields for c in _OPK) else "navigation"
        names = _corr_names(_OPK if system == "omega-phi-kappa" else _NAV)
        odd = [c for c in fields if c.startswith("corr_") and c not in names]
        if odd:
            order = [*_POS, *(_OPK if system == "omega-phi-kappa" else _NAV)]
            raise InvalidInputError(f"{str(p)!r}: unknown correlation column {odd[0]!r}; expected corr_A_B with A "
                                    f"before B in {order}")
        corr_cols = tuple(c for c in names if c in fields)
        cols = t.read("pose rows", numbers=(*corr_cols, *(("time",) if "time" in fields else ())),
                      texts=("image", *(("strip",) if "strip" in fields else ())), empty=corr_cols)
    n = len(cols)
    images = tuple(cols.texts["image"])
    no_duplicates(images, p, "image name(s)")
    lines = np.asarray(cols.lines, dtype=np.int64)
    time = cols.numbers.get("time")
    strip = None
    if "strip" in fields:
        strip = tuple(cols.texts["strip"])
        empty = [i for i, s in enumerate(strip) if not s]
        if empty:
            raise InvalidInputError(f"{str(p)!r} line {lines[empty[0]]}: empty strip of image {images[empty[0]]!r}")
    corr = None
    if corr_cols:
        labels = (*_POS, *(_OPK if system == "omega-phi-kappa" else _NAV))
        corr = np.tile(np.eye(6), (n, 1, 1))
        for c in corr_cols:
            a, b = c[5:].split("_")
            i, j = labels.index(a), labels.index(b)
            v = np.nan_to_num(cols.numbers[c], nan=0.0)
            bad = np.flatnonzero(np.abs(v) > 1.0)
            if len(bad):
                k = int(bad[0])
                raise InvalidInputError(f"{str(p)!r} line {lines[k]}: correlation {c!r} of image {images[k]!r} must be "
                                        f"in [-1, 1]; got {float(v[k])!r}")
            corr[:, i, j] = corr[:, j, i] = v
    return PoseExtras(images, lines, None if time is None else np.asarray(time, dtype=np.float64), strip, corr, system)


def image_times_names(path: StrPath) -> list[str]:
    """The image names of an image-times CSV, in file order (the block's images when it is adjusted from an
    observations CSV with ``--trajectory``)."""
    p = Path(path)
    with TableReader(p) as t:
        need_columns(list(t.fields), ("image", "time"), p)
        cols = t.read("image rows", texts=("image",))
    return list(cols.texts["image"])


def trajectory_pose_file(times_path: StrPath, trajectory_path: StrPath, *, camera: str | None = None,
                         boresight_rad: ArrayLike | None = None, lever_arm_m: ArrayLike | None = None,
                         interpolation: str = "cubic", convention: str = "seed004") -> PoseFile:
    """Poses of the images of an image-times CSV (``image,time[,strip][,camera]``) from a trajectory CSV.

    Each image's antenna position and body rotation are the trajectory at its time
    (:meth:`stereo.block.trajectory.Trajectory.sample`); the camera pose follows as for a navigation
    pose CSV: ``R = R_body B``, ``C = A - R_body l``. The standard deviations (when the trajectory has
    them) are interpolated too.

    Raises
    ------
    InvalidInputError
        A times file without ``time``, an image time outside the trajectory's span (image, time and
        span named), an unknown interpolation.
    """
    if interpolation not in INTERPOLATIONS:
        raise InvalidInputError(f"unknown trajectory interpolation {interpolation!r}; expected one of "
                                f"{list(INTERPOLATIONS)}")
    tp = Path(times_path)
    with TableReader(tp) as t:
        fields = list(t.fields)
        need_columns(fields, ("image", "time"), tp)
        cols = t.read("image rows", numbers=("time",), texts=("image", "camera"))
    images = tuple(cols.texts["image"])
    no_duplicates(images, tp, "image name(s)")
    empty = [i for i, s in enumerate(images) if not s]
    if empty:
        raise InvalidInputError(f"{str(tp)!r} line {int(cols.lines[empty[0]])}: empty image name")
    tf = read_trajectory_csv(trajectory_path, convention=convention)
    s = tf.trajectory.sample(cols.numbers["time"], names=images, interpolation=interpolation)
    B = boresight_matrix(boresight_rad)
    lever = lever_arm(lever_arm_m)
    R = s.body_rotation if B is None else s.body_rotation @ B
    pos = s.position if lever is None else s.position - s.body_rotation @ lever
    cams = [c or camera or "camera" for c in cols.texts["camera"]]
    poses = tuple(Pose(images[i], cams[i], pos[i], R[i]) for i in range(len(images)))
    frame = (f"{tf.crs} (the CRS of the trajectory {tf.path.name})" if tf.crs
             else f"the frame of the trajectory {tf.path.name} (no CRS given)")
    return PoseFile(tp, OUR_POSES, poses, {}, tf.crs, frame, sigma=s.sigma, angle_system="navigation")


def _row_of(names: Sequence[str], extras: PoseExtras) -> list[int]:
    """Row of ``extras`` of each name (by name, else by file stem)."""
    by = {n: i for i, n in enumerate(extras.images)}
    stem = {Path(n).stem: i for i, n in enumerate(extras.images)}
    return [by[n] if n in by else stem[Path(n).stem] for n in names]


def gnss_with_extras(gnss: GnssObservations, extras: PoseExtras, poses: Sequence[Pose], sigma: ArrayLike | None, *,
                     boresight_rad: ArrayLike | None = None, convention: str = "seed004") -> GnssObservations:
    """``gnss`` with the exposure times, strips and (with correlation columns) full covariances of ``extras``.

    Parameters
    ----------
    gnss : GnssObservations
        The pose file's observations (positions, optional INS angles).
    extras : PoseExtras
    poses : sequence of Pose
        The pose file's poses, in the order of ``sigma`` (their rotations carry a navigation file's
        angles into omega, phi, kappa).
    sigma : (n, 6) array_like or None
        The pose file's standard deviations (x, y, z, three angles in the file's system), NaN where none.

    The correlations scale the file's standard deviations (positions without them: ``gnss.sigma_m``, i.e.
    ``--gnss-sigma``); the angles' correlations are used when the file has the angles' standard deviations
    and the angles are observed (a 6 x 6 covariance), else the covariance is the position's 3 x 3.

    Raises
    ------
    InvalidInputError
        A correlation matrix that is not positive definite (the image and file line named).
    """
    names = list(gnss.images)
    rows = _row_of(names, extras)
    time = None if extras.time is None else extras.time[rows]
    strip = None if extras.strip is None else tuple(extras.strip[i] for i in rows)
    cov = None
    if extras.correlation is not None:
        by_pose = {p.image: k for k, p in enumerate(poses)}
        k = [by_pose[n] for n in names]
        sig = np.full((len(names), 6), np.nan) if sigma is None else np.array(sigma, dtype=np.float64)[k]
        sig[:, :3] = np.where(np.isfinite(sig[:, :3]), sig[:, :3], gnss.sigma_m)  # else --gnss-sigma
        corr = extras.correlation[rows]
        with_angles = gnss.angles is not None and np.isfinite(sig[:, 3:]).all()
        m = 6 if with_angles else 3
        s = sig[:, :m]
        cov = corr[:, :m, :m] * s[:, :, None] * s[:, None, :]
        for i in range(len(names)):
            ev = np.linalg.eigvalsh(corr[i, :m, :m])[0]
            if not ev > 1e-12:
                raise InvalidInputError(f"image {names[i]!r} (line {int(extras.lines[rows[i]])}): its correlation "
                                        f"matrix is not positive definite (smallest eigenvalue {ev:.3g})")
        if m == 6 and extras.angle_system == "navigation":
            R = np.array([poses[j].rotation for j in k])
            cov = opk_covariance(R, cov, boresight_rad=boresight_rad, convention=convention)
        if m == 6:
            sig_rad = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)[:, 3:])
            return GnssObservations(gnss.images, gnss.position, np.sqrt(np.diagonal(cov, axis1=1, axis2=2)[:, :3]),
                                    gnss.lever_arm_m, gnss.angles, sig_rad, cov, time, strip)
    return GnssObservations(gnss.images, gnss.position, gnss.sigma_m, gnss.lever_arm_m, gnss.angles, gnss.sigma_rad,
                            cov, time, strip)



def read_poses_with_extras(poses: StrPath, trajectory: StrPath | None, *, camera: str | None = None,
                           boresight_rad: ArrayLike | None = None, lever_arm_m: ArrayLike | None = None,
                           crs: str | None = None, interpolation: str = "cubic") -> tuple[PoseFile, PoseExtras | None]:
    """A ``--poses`` file (any kind, :func:`stereo.formats.detect.read_pose_file`) and, for a position/angle CSV,
    its extra columns; with ``trajectory`` the ``--poses`` file is an image-times CSV and the poses are the
    trajectory's at the images' times (:func:`trajectory_pose_file`)."""
    if trajectory is not None:
        pf = trajectory_pose_file(poses, trajectory, camera=camera, boresight_rad=boresight_rad,
                                  lever_arm_m=lever_arm_m, interpolation=interpolation)
        if crs is not None and pf.crs is not None and not same_crs(crs, pf.crs):
            raise CRSError(f"the trajectory's CRS {pf.crs[:80]!r} differs from the control's {crs[:80]!r}")
        return pf, read_pose_extras(pf.path)
    pf = read_pose_file(poses, camera=camera, boresight_rad=boresight_rad, lever_arm_m=lever_arm_m, crs=crs)
    return pf, (read_pose_extras(pf.path) if pf.kind is OUR_POSES else None)


def block_gnss(gnss: GnssObservations | None, extras: PoseExtras | None, poses: Sequence[Pose] | None,
               sigma: ArrayLike | None, *, boresight_rad: ArrayLike | None, gnss_drift: str,
               boresight: str) -> GnssObservations | None:
    """The block's GNSS/INS observations with the pose file's times, strips and covariances
    (:func:`gnss_with_extras`), checked against what the systematic unknowns need
    (:func:`stereo.block.bundle.systematic.check_inputs`) before any matching."""
    if gnss is not None and extras is not None and poses is not None:
        gnss = gnss_with_extras(gnss, extras, poses, sigma, boresight_rad=boresight_rad)
    check_inputs(gnss, gnss_drift, boresight)
    return gnss
