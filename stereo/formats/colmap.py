"""COLMAP text models in and out: ``cameras.txt``, ``images.txt``, ``points3D.txt``.

:func:`read_colmap` reads a model folder (or one of its three files) into the project's cameras,
poses and tie points (:class:`ColmapModel`; the cameras and image poses through
:func:`rectify.formats.colmap.read_colmap_images`); :func:`write_colmap` writes cameras and poses (and,
optionally, points with their tracks) as a model COLMAP and pycolmap open; :func:`detect_colmap`
recognises one. Numbers are written as ``repr`` (17 significant digits), so our model -> COLMAP ->
our model is exact to rounding.

Conventions: the pixel origin (0.5 px), the world -> camera quaternions and the camera models are
converted where they are read, in :mod:`rectify.formats.colmap` (its docstring states them); writing
applies the inverse conversions. Here:

writing
    the smallest exact camera model is chosen; a camera with skew is refused (COLMAP has none).
ids
    COLMAP's camera, image and point ids are integers. Ours are kept when they are positive
    integers; otherwise they are numbered from 1 and the names are kept in comment lines
    (``# rectify-stereo camera 1: <name>``, ``# rectify-stereo point 1: <name>``), which COLMAP
    ignores and :func:`read_colmap` reads back. Image names are COLMAP's ``NAME`` (no spaces).
frame
    COLMAP's world frame is whatever the model was built or aligned in (arbitrary for a plain
    reconstruction, a map CRS after ``model_aligner``): the poses are returned in it and the caller
    names its CRS.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from rectify.atomic import atomic_write_text
from rectify.errors import InvalidInputError, RasterIOError, RectifyError
from rectify.formats.colmap import (
    COLMAP_FILES,
    COLMAP_MODELS,
    ColmapImages,
    colmap_int,
    colmap_lines,
    detect_colmap,
    read_colmap_images,
)
from rectify.formats.common import StrPath, finite_number
from rectify.geometry.camera import Camera
from stereo.block.types import Pose, Tracks

__all__ = ["COLMAP_FILES", "COLMAP_MODELS", "ColmapModel", "read_colmap", "colmap_texts", "write_colmap",
           "detect_colmap"]

_FLIP = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True, eq=False)
class ColmapModel:
    """A COLMAP text model in the project's terms.

    Parameters
    ----------
    cameras : dict of str -> Camera
        Pixel cameras keyed by COLMAP's camera id (or the name kept in a comment line).
    poses : tuple of Pose
        One per image, in the file's order: projection centre and rotation photo vector -> world.
    point_ids : tuple of str
        The 3D points' ids (P).
    points : (P, 3) float64
        Their world coordinates.
    colors : (P, 3) uint8
    errors : (P,) float64
        COLMAP's mean reprojection error of each point, px.
    tracks : Tracks or None
        The points' image observations (pixels in our convention); None when there are no points.
    source : Path or None
        The folder read.
    """

    cameras: dict[str, Camera]
    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8]
    errors: NDArray[np.float64]
    tracks: Tracks | None = None
    source: Path | None = None


def read_colmap(path: StrPath) -> ColmapModel:
    """Read a COLMAP text model (a folder with ``cameras.txt``, ``images.txt`` and optionally ``points3D.txt``).

    Raises
    ------
    RasterIOError
        A file is missing or unreadable.
    InvalidInputError
        A binary model, a malformed line (file, line and value named), an unsupported camera model
        (named), an image naming an unknown camera, a track naming an unknown image or 2D point,
        a non-unit quaternion.
    """
    im = read_colmap_images(path)
    poses = tuple(Pose(n, c, p, R) for n, c, p, R in zip(im.images, im.image_camera, im.positions, im.rotations,
                                                        strict=True))
    return _with_points(im, poses)


def _with_points(im: ColmapImages, poses: tuple[Pose, ...]) -> ColmapModel:
    p3 = im.folder / "points3D.txt"
    image_index = {iid: k for k, iid in enumerate(im.image_ids)}
    points2d = im.points2d
    ids: list[str] = []
    xyz, rgb, err = [], [], []
    o_pt: list[int] = []
    o_im: list[int] = []
    o_px: list[NDArray[np.float64]] = []
    if p3.is_file():
        lines, names = colmap_lines(p3)
        for no, s in lines:
            if not s:
                continue
            c = s.split()
            where = f"{str(p3)!r} line {no}"
            if len(c) < 8 or (len(c) - 8) % 2:
                raise InvalidInputError(f"{where}: expected POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...; "
                                        f"got {s!r:.120}")
            pid = colmap_int(c[0], f"{where}: POINT3D_ID")
            ids.append(names["point"].get(pid, str(pid)))
            xyz.append([finite_number(x, f"{where}: {k}") for x, k in zip(c[1:4], "XYZ", strict=True)])
            col = [colmap_int(x, f"{where}: {k}") for x, k in zip(c[4:7], "RGB", strict=True)]
            if any(not 0 <= v <= 255 for v in col):
                raise InvalidInputError(f"{where}: colour {col} is not 0..255")
            rgb.append(col)
            err.append(finite_number(c[7], f"{where}: ERROR"))
            for a in range(8, len(c), 2):
                iid, idx = colmap_int(c[a], f"{where}: IMAGE_ID"), colmap_int(c[a + 1], f"{where}: POINT2D_IDX")
                if iid not in image_index:
                    raise InvalidInputError(f"{where}: track names IMAGE_ID {iid}, which images.txt lacks")
                k = image_index[iid]
                if not 0 <= idx < len(points2d[k]):
                    raise InvalidInputError(f"{where}: track names POINT2D_IDX {idx} of image {poses[k].image!r}, "
                                            f"which has {len(points2d[k])} 2D points")
                o_pt.append(len(ids) - 1)
                o_im.append(k)
                o_px.append(points2d[k][idx])
    tracks = None
    if ids:
        try:
            tracks = Tracks(tuple(p.image for p in poses), tuple(ids), np.array(o_pt, dtype=np.int64),
                            np.array(o_im, dtype=np.int64), np.array(o_px, dtype=np.float64).reshape(-1, 2))
        except RectifyError as exc:
            raise InvalidInputError(f"{str(p3)!r}: {exc}") from None
    return ColmapModel(cameras=dict(im.cameras), poses=poses, point_ids=tuple(ids),
                       points=np.array(xyz, dtype=np.float64).reshape(-1, 3),
                       colors=np.array(rgb, dtype=np.uint8).reshape(-1, 3), errors=np.array(err, dtype=np.float64),
                       tracks=tracks, source=im.folder)


# --------------------------------------------------------------------------- writing
def _r(v: float) -> str:
    return repr(float(v))


def _int_ids(keys: Sequence[str]) -> dict[str, int]:
    """Our ids -> COLMAP's: the ids themselves when all are positive integers, else 1, 2, ..."""
    if all(re.fullmatch(r"[1-9]\d{0,9}", k) for k in keys) and len(set(map(int, keys))) == len(keys):
        return {k: int(k) for k in keys}
    return {k: i + 1 for i, k in enumerate(keys)}


def _camera_line(cid: int, cam: Camera, name: str) -> str:
    K = np.asarray(cam.K, dtype=np.float64)
    if K[0, 1] != 0.0:
        raise InvalidInputError(f"camera {name!r} has skew {float(K[0, 1])!r} px, which COLMAP's camera models "
                                "cannot hold")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
    d = cam.distortion
    tangential = d["p1"] != 0.0 or d["p2"] != 0.0
    if fx == fy and d["k3"] == 0.0 and not tangential:
        if d["k2"] != 0.0:
            model, vals = "RADIAL", [fx, cx, cy, d["k1"], d["k2"]]
        elif d["k1"] != 0.0:
            model, vals = "SIMPLE_RADIAL", [fx, cx, cy, d["k1"]]
        else:
            model, vals = "SIMPLE_PINHOLE", [fx, cx, cy]
    elif not cam.has_distortion:
        model, vals = "PINHOLE", [fx, fy, cx, cy]
    elif d["k3"] == 0.0:
        model, vals = "OPENCV", [fx, fy, cx, cy, d["k1"], d["k2"], d["p1"], d["p2"]]
    else:
        model, vals = "FULL_OPENCV", [fx, fy, cx, cy, d["k1"], d["k2"], d["p1"], d["p2"], d["k3"], 0.0, 0.0, 0.0]
    return f"{cid} {model} {cam.width} {cam.height} " + " ".join(map(_r, vals))


def colmap_texts(cameras: Mapping[str, Camera], poses: Sequence[Pose], *, points: ArrayLike | None = None,
                 tracks: Tracks | None = None, colors: ArrayLike | None = None,
                 errors: ArrayLike | None = None) -> dict[str, str]:
    """The three files of a COLMAP text model (name -> text); see :func:`write_colmap`."""
    cam_ids = _int_ids([str(k) for k in cameras])
    for p in poses:
        if p.camera not in cameras:
            raise InvalidInputError(f"image {p.image!r} names camera {p.camera!r}, which is not given "
                                    f"(cameras: {sorted(cameras)})")
        if not p.image or re.search(r"\s", p.image):
            raise InvalidInputError(f"image name {p.image!r} has white space, which COLMAP's images.txt cannot hold")
    if len({p.image for p in poses}) != len(poses):
        raise InvalidInputError("two poses have the same image name")
    cam_txt = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
               f"# Number of cameras: {len(cameras)}"]
    cam_txt += [f"# rectify-stereo camera {cam_ids[str(k)]}: {k}" for k in cameras if str(cam_ids[str(k)]) != str(k)]
    cam_txt += [_camera_line(cam_ids[str(k)], c, str(k)) for k, c in cameras.items()]
    # observations per image (POINTS2D) and tracks per point
    n_img = len(poses)
    per_image: list[list[tuple[float, float, int]]] = [[] for _ in range(n_img)]
    track_of: list[list[tuple[int, int]]] = []
    pt_ids: dict[str, int] = {}
    xyz = np.zeros((0, 3))
    if tracks is not None or points is not None:
        if tracks is None or points is None:
            raise InvalidInputError("COLMAP points need both `points` (P, 3) and their `tracks`")
        xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(xyz) != tracks.n_points:
            raise InvalidInputError(f"`points` has {len(xyz)} rows for {tracks.n_points} tracks")
        pose_of = {p.image: k for k, p in enumerate(poses)}
        missing = sorted(set(tracks.images) - set(pose_of))
        if missing:
            raise InvalidInputError(f"tracks observe images without a pose: {missing[:5]}")
        pt_ids = _int_ids(list(tracks.point_ids))
        track_of = [[] for _ in range(tracks.n_points)]
        for pt, im, px in zip(tracks.obs_point, tracks.obs_image, tracks.obs_pixel, strict=True):
            k = pose_of[tracks.images[int(im)]]
            track_of[int(pt)].append((k + 1, len(per_image[k])))
            per_image[k].append((float(px[0]) + 0.5, float(px[1]) + 0.5, pt_ids[tracks.point_ids[int(pt)]]))
    n_obs = sum(len(v) for v in per_image)
    img_txt = ["# Image list with two lines of data per image:",
               "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
               "#   POINTS2D[] as (X, Y, POINT3D_ID)",
               f"# Number of images: {n_img}, mean observations per image: {n_obs / max(n_img, 1):.17g}"]
    for k, p in enumerate(poses):
        R_cw = _FLIP @ p.rotation.T
        t = -R_cw @ p.position
        qx, qy, qz, qw = Rotation.from_matrix(R_cw).as_quat()
        if qw < 0:
            qx, qy, qz, qw = -qx, -qy, -qz, -qw
        img_txt.append(" ".join([str(k + 1), *map(_r, (qw, qx, qy, qz, *t)), str(cam_ids[p.camera]), p.image]))
        img_txt.append(" ".join(f"{_r(x)} {_r(y)} {i}" for x, y, i in per_image[k]))
    rgb = np.zeros((len(xyz), 3), dtype=np.int64) if colors is None else np.asarray(colors).reshape(-1, 3)
    err = np.zeros(len(xyz)) if errors is None else np.asarray(errors, dtype=np.float64).reshape(-1)
    if len(rgb) != len(xyz) or len(err) != len(xyz):
        raise InvalidInputError(f"`colors` and `errors` need one row per point ({len(xyz)})")
    mean_track = sum(len(t) for t in track_of) / max(len(track_of), 1)
    pts_txt = ["# 3D point list with one line of data per point:",
               "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
               f"# Number of points: {len(xyz)}, mean track length: {mean_track:.17g}"]
    if tracks is not None:
        pts_txt += [f"# rectify-stereo point {pt_ids[k]}: {k}" for k in tracks.point_ids if str(pt_ids[k]) != k]
        for j, pid in enumerate(tracks.point_ids):
            track = " ".join(f"{a} {b}" for a, b in track_of[j])
            pts_txt.append(" ".join([str(pt_ids[pid]), *map(_r, xyz[j]), *(str(int(v)) for v in rgb[j]),
                                     _r(err[j]), track]).rstrip())
    return {"cameras.txt": "\n".join(cam_txt) + "\n", "images.txt": "\n".join(img_txt) + "\n",
            "points3D.txt": "\n".join(pts_txt) + "\n"}


def write_colmap(folder: StrPath, cameras: Mapping[str, Camera], poses: Sequence[Pose], *,
                 points: ArrayLike | None = None, tracks: Tracks | None = None, colors: ArrayLike | None = None,
                 errors: ArrayLike | None = None, overwrite: bool = False) -> tuple[Path, ...]:
    """Write cameras and poses (and points with their tracks) as a COLMAP text model in ``folder``.

    Parameters
    ----------
    folder : path
        An existing folder; ``cameras.txt``, ``images.txt`` and ``points3D.txt`` are written in it,
        each atomically.
    cameras : dict of str -> Camera
    poses : sequence of Pose
        Each names one of ``cameras``; image names without white space.
    points : (P, 3) array_like, optional
        World coordinates of the tracks' points (``tracks.point_ids`` order).
    tracks : Tracks, optional
        Their observations (pixels, our convention).
    colors : (P, 3) array_like of 0..255, optional
    errors : (P,) array_like, optional
        Reprojection errors, px (COLMAP's ``ERROR``; 0 when not given).
    overwrite : bool

    Returns
    -------
    tuple of Path
        The three files.

    Raises
    ------
    InvalidInputError
        A camera with skew, an image name with white space, a pose naming an unknown camera,
        points without tracks (or the reverse), an existing file without ``overwrite``.
    """
    texts = colmap_texts(cameras, poses, points=points, tracks=tracks, colors=colors, errors=errors)
    d = Path(folder)
    if not d.is_dir():
        raise RasterIOError(f"COLMAP model folder {str(d)!r} does not exist")
    return tuple(atomic_write_text(d / name, text, overwrite=overwrite) for name, text in texts.items())
