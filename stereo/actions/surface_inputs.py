"""The block orientation `stereo surface` starts from: ours, or another tool's cameras and poses.

``stereo surface ORIENTATION`` reads

- the output folder of ``stereo block`` (its ``orientation.json``, and ``points.csv`` beside it for the
  terrain height and the orientation's share of sigma_Z) or a block orientation JSON;
- any pose file ``stereo block --poses`` reads (:data:`stereo.formats.detect.POSE_KINDS`: orthority
  ``ext_param.geojson`` or CSV, COLMAP text model, Metashape cameras XML, OpenSfM/ODM
  ``reconstruction.json``, our position/angle CSV; ``KIND:PATH`` names a kind), with ``--camera``
  (any camera file, :func:`rectify.formats.detect.read_camera_file`) when the file holds no cameras.

Another tool's orientation carries no standard errors and no points: the orientation's share of sigma_Z
is then none (``auto``), and the terrain height is ``--ground-z``, or else the median of the reference
DEM under the images' nadir points.

An orientation in OpenSfM's topocentric frame (an ODM/OpenSfM reconstruction, or a ``stereo block`` run
on one), which a GeoTIFF cannot record as its CRS, is converted into the WGS 84 UTM zone of the block's
centre (:func:`to_map_frame`: positions through pyproj, rotations turned by the frame's local rotation;
heights become ellipsoidal), and so are the block's points, so that the DSM, the orthomosaic and the cloud
carry a CRS.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath
from rectify.formats.detect import read_camera_file
from rectify.geometry.camera import Camera
from rectify.geometry.crs import transform_xyz, utm_crs
from rectify.raster.dem import Dem
from stereo.block.types import Pose
from stereo.formats.block import BlockOrientation, read_block_orientation
from stereo.formats.detect import read_pose_file
from stereo.formats.opensfm import OpenSfMReconstruction
from stereo.formats.points import PointsTable, read_points_csv

__all__ = ["SurfaceOrientation", "load_orientation", "dem_ground_z", "to_map_frame", "read_block_points",
           "TOPOCENTRIC_METHOD"]

#: the conversion method of OpenSfM's topocentric frame in its WKT2 (EPSG method 9837)
TOPOCENTRIC_METHOD = "Geographic/topocentric conversions"


@dataclass(frozen=True, eq=False)
class SurfaceOrientation:
    """The orientation of a surface run.

    Attributes
    ----------
    orientation : BlockOrientation
        Cameras and poses (positions in ground units of ``orientation.crs``; rotations camera -> ground).
    path : Path
        The file read (``orientation.json`` or the other tool's file).
    folder : Path
        Where the images are looked for by default, and ``points.csv`` (ours only).
    source : str
        What was read, for the summary: ``"block orientation"`` or the other tool's kind label.
    inputs : tuple of Path
        Every file read (kept from being overwritten by an output).
    converted_from : str or None
        The CRS the orientation was converted from (:func:`to_map_frame`); None when read as it is.
    """

    orientation: BlockOrientation
    path: Path
    folder: Path
    source: str
    inputs: tuple[Path, ...]
    converted_from: str | None = None

    @property
    def ours(self) -> bool:
        """True for a block orientation of ``stereo block`` (points.csv may lie beside it)."""
        return self.source == "block orientation"


def _is_block_orientation(p: Path) -> bool:
    if p.suffix.lower() != ".json":
        return False
    try:
        with open(p, encoding="utf-8", errors="replace") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return "block-orientation" in head  # its format key, rectify-stereo/block-orientation


def load_orientation(path: StrPath, *, camera: StrPath | None = None, crs: str | None = None) -> SurfaceOrientation:
    """Read the orientation of ``stereo surface`` (module docstring).

    Parameters
    ----------
    path : path or ``KIND:PATH``
        A ``stereo block`` output folder, a block orientation JSON, or another tool's pose file.
    camera : path, optional
        The camera file for a pose file that holds no cameras (orthority, pose CSV); refused with ours.
    crs : str, optional
        The projected CRS of a pose file that names none (COLMAP) or to convert a georeferenced Metashape
        chunk into.

    Raises
    ------
    InvalidInputError, RasterIOError, CRSError
        A missing file or folder (named), a folder without ``orientation.json``, a pose file without
        rotations (ODM ``geo.txt``) or without a camera, a camera the poses name but the files lack.
    """
    text = str(path)
    p = Path(text)
    if p.is_dir():
        f = p / "orientation.json"
        if not f.is_file():
            raise InvalidInputError(f"no orientation.json in the orientation folder {text!r}")
        p = f
    if p.is_file() and _is_block_orientation(p):
        if camera is not None:
            raise InvalidInputError(f"--camera is for another tool's pose file; the block orientation {str(p)!r} "
                                    "holds its cameras")
        return to_map_frame(SurfaceOrientation(read_block_orientation(p), p, p.parent, "block orientation", (p,)))
    if not p.is_file() and ":" not in text:
        raise InvalidInputError(f"orientation not found: {text!r}")
    pf = read_pose_file(text, crs=crs)
    if not pf.poses:
        raise InvalidInputError(f"{pf.kind.label} {str(pf.path)!r} has positions only (no rotations): a surface "
                                "needs the images' full poses")
    cams: dict[str, Camera] = dict(pf.cameras)
    inputs = [pf.path]
    if camera is not None:
        cf = read_camera_file(camera)
        inputs.append(cf.path)
        for pose in pf.poses:
            if pose.camera not in cams:
                cams[pose.camera] = cf.choose(pose.camera, named_by=f"image {pose.image!r}")[1]
    missing = sorted({q.camera for q in pf.poses} - set(cams))
    if missing:
        raise InvalidInputError(f"{pf.kind.label} {str(pf.path)!r} holds no camera {missing[0]!r}: pass --camera")
    poses: list[Pose] = list(pf.poses)
    bo = BlockOrientation(cams, poses, np.full((len(poses), 6), np.nan), crs=pf.crs, frame=pf.frame or None)
    return to_map_frame(SurfaceOrientation(bo, pf.path, pf.path.parent, pf.kind.label, tuple(inputs)))


def to_map_frame(so: SurfaceOrientation) -> SurfaceOrientation:
    """``so`` converted into the WGS 84 UTM zone of its centre when its CRS is OpenSfM's topocentric frame
    (module docstring); else ``so`` itself."""
    bo = so.orientation
    if bo.crs is None or TOPOCENTRIC_METHOD not in bo.crs:
        return so
    C = np.array([p.position for p in bo.poses], dtype=np.float64).reshape(-1, 3)
    lon, lat = (float(v) for v in transform_xyz(bo.crs, "EPSG:4979", C.mean(axis=0, keepdims=True))[0, :2])
    utm = utm_crs(lon, lat)
    n = len(bo.poses)
    rec = OpenSfMReconstruction(cameras=bo.cameras, poses=tuple(bo.poses), point_ids=(), points=np.zeros((0, 3)),
                                colors=None, reference_lonlat_h=None, frame=bo.frame or "OpenSfM's topocentric frame",
                                gps_position=np.full((n, 3), np.nan), gps_dop=np.full(n, np.nan),
                                crs=bo.crs).to_crs(utm)
    out = replace(bo, poses=list(rec.poses), crs=utm, frame=rec.frame)
    return replace(so, orientation=out, converted_from=bo.crs)


def read_block_points(so: SurfaceOrientation) -> PointsTable | None:
    """The block's ``points.csv`` beside a ``stereo block`` orientation (None: another tool's, or no file), in the
    orientation's frame (converted as the poses were; the standard errors kept: the conversion is a rotation
    and a translation to within the projection's scale, 1.0004 at most in a UTM zone)."""
    pts = so.folder / "points.csv"
    if not so.ours or not pts.is_file():
        return None
    t = read_points_csv(pts)
    if so.converted_from is None or so.orientation.crs is None:
        return t
    xyz = np.asarray(t.xyz, dtype=np.float64)
    ok = np.isfinite(xyz).all(axis=1)
    conv = np.full_like(xyz, np.nan)
    if ok.any():
        conv[ok] = transform_xyz(so.converted_from, so.orientation.crs, xyz[ok])
    return replace(t, xyz=conv, crs=so.orientation.crs)


def dem_ground_z(dem_path: StrPath, xy: np.ndarray, crs: str | None) -> float | None:
    """Median height of the DEM (its file heights, no datum conversion: those of a frame block's poses) at
    (N, 2) ground points in ``crs`` (None: the DEM's); None when none falls on it."""
    dem = Dem.from_path(Path(dem_path), convert_declared=False)
    z = np.asarray(dem.sample(np.asarray(xy, dtype=np.float64), crs=crs), dtype=np.float64)
    z = z[np.isfinite(z)]
    return float(np.median(z)) if z.size else None
