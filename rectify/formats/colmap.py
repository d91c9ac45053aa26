"""COLMAP text models in: the cameras and image poses of ``cameras.txt`` and ``images.txt``.

:func:`read_colmap_images` reads a model folder (or one of its files) into the project's cameras and
exterior orientations (:class:`ColmapImages`: what ``rectify ortho --camera/--exterior`` take);
``stereo.formats.colmap`` adds the 3D points and their tracks (``points3D.txt``), the block's poses and
the writer. :func:`detect_colmap` recognises a model.

Conventions, converted once here:

pixels
    COLMAP puts the top-left corner of the image at (0, 0), so the centre of the top-left pixel is at
    (0.5, 0.5); ours is at (0, 0). Principal points and 2D points lose 0.5 on reading (and gain it
    on writing, ``stereo.formats.colmap``).
poses
    An image's ``QW QX QY QZ`` is the unit quaternion (Hamilton, scalar first) of R_cw, the rotation
    world -> camera, and ``TX TY TZ`` the translation t with x_cam = R_cw X + t, camera axes x right,
    y down, z forward (OpenCV's). Our pose is the projection centre C = -R_cw^T t and the rotation
    of photo vectors (x right, y up, z back) into the world, R = R_cw^T diag(1, -1, -1).
cameras
    ``SIMPLE_PINHOLE`` (f, cx, cy), ``PINHOLE`` (fx, fy, cx, cy), ``SIMPLE_RADIAL`` (f, cx, cy, k),
    ``RADIAL`` (f, cx, cy, k1, k2), ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2) and ``FULL_OPENCV``
    (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 with k4 = k5 = k6 = 0) have OpenCV's distortion
    definition, which is ours; fisheye, FOV and thin-prism models are refused by name.
ids
    COLMAP's camera, image and point ids are integers; names kept by our writer in comment lines
    (``# rectify-stereo camera 1: <name>``) are read back as the camera ids.
frame
    COLMAP's world frame is whatever the model was built or aligned in (arbitrary for a plain
    reconstruction, a map CRS after ``model_aligner``): the poses are returned in it and the caller
    names its CRS.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from rectify.errors import InvalidInputError, RasterIOError, RectifyError
from rectify.formats.camera import camera_from_focals
from rectify.formats.common import StrPath, finite_number, read_table_text
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import check_rotation

__all__ = ["COLMAP_FILES", "COLMAP_MODELS", "ColmapImages", "read_colmap_cameras", "read_colmap_images",
           "colmap_lines", "colmap_int", "detect_colmap"]

#: the three files of a text model
COLMAP_FILES = ("cameras.txt", "images.txt", "points3D.txt")
#: COLMAP camera models read here -> their parameter names
COLMAP_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
_REFUSED = ("SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE",
            "RAD_TAN_THIN_PRISM_FISHEYE", "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE")
_FLIP = np.diag([1.0, -1.0, -1.0])
_NAME_LINE = re.compile(r"#\s*rectify-stereo (camera|point) (\d+): (.+)$")

@dataclass(frozen=True, eq=False)
class ColmapImages:
    """The cameras and image poses of a COLMAP text model in the project's terms.

    Attributes
    ----------
    cameras : dict of str -> Camera
        Pixel cameras keyed by COLMAP's camera id (or the name kept in a comment line).
    images : tuple of str
        Image names (n), in the file's order.
    image_camera : tuple of str
        The camera key of each image.
    positions : (n, 3) float64
        Projection centres in the model's frame.
    rotations : (n, 3, 3) float64
        Rotations of photo vectors (x right, y up, z back) into the model's frame.
    image_ids : tuple of int
        COLMAP's IMAGE_ID of each image.
    points2d : tuple of (m_i, 2) float64
        Each image's 2D points (POINTS2D), pixels in our convention.
    folder : Path
        The model folder.
    """

    cameras: dict[str, Camera]
    images: tuple[str, ...]
    image_camera: tuple[str, ...]
    positions: NDArray[np.float64]
    rotations: NDArray[np.float64]
    image_ids: tuple[int, ...]
    points2d: tuple[NDArray[np.float64], ...]
    folder: Path

    def exteriors(self, crs: str | None = None) -> dict[str, dict[str, Any]]:
        """``{image: {"position", "rotation", "crs", "camera"}}`` (``crs``: the CRS the caller names for the frame)."""
        return {n: {"position": p.copy(), "rotation": R.copy(), "crs": crs, "camera": c}
                for n, c, p, R in zip(self.images, self.image_camera, self.positions, self.rotations, strict=True)}


def _folder(path: StrPath) -> Path:
    p = Path(path)
    if p.is_dir():
        if not (p / "cameras.txt").is_file() and (p / "cameras.bin").is_file():
            raise InvalidInputError(f"{str(p)!r} holds a binary COLMAP model; convert it to text first "
                                    "(colmap model_converter --output_type TXT)")
        return p
    if p.suffix == ".bin":
        raise InvalidInputError(f"{str(p)!r} is a binary COLMAP file; convert the model to text first "
                                "(colmap model_converter --output_type TXT)")
    if p.name in COLMAP_FILES:
        return p.parent
    if not p.exists():
        raise RasterIOError(f"file not found: {str(p)!r}")
    raise InvalidInputError(f"{str(p)!r} is not a COLMAP text model (a folder with {list(COLMAP_FILES)})")


def colmap_lines(path: Path) -> tuple[list[tuple[int, str]], dict[str, dict[int, str]]]:
    """A model file's non-comment lines (number, text; empty lines kept) and the names kept in our comment lines."""
    names: dict[str, dict[int, str]] = {"camera": {}, "point": {}}
    out = []
    for no, line in enumerate(read_table_text(path).splitlines(), start=1):
        s = line.strip()
        if s.startswith("#"):
            m = _NAME_LINE.match(s)
            if m:
                names[m[1]][int(m[2])] = m[3].strip()
            continue
        out.append((no, s))
    return out, names


def colmap_int(tok: str, label: str) -> int:
    """An integer of a model file; ``label`` names the file, line and field."""
    try:
        return int(tok)
    except ValueError:
        raise InvalidInputError(f"{label} is not an integer: {tok!r}") from None


def _camera(cells: list[str], path: Path, no: int) -> tuple[int, Camera]:
    where = f"{str(path)!r} line {no}"
    if len(cells) < 4:
        raise InvalidInputError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]; got {' '.join(cells)!r}")
    cid = colmap_int(cells[0], f"{where}: CAMERA_ID")
    model = cells[1].upper()
    if model in _REFUSED:
        raise InvalidInputError(f"{where}: camera model {model!r} is not in the frame camera model; supported: "
                                f"{list(COLMAP_MODELS)}")
    if model not in COLMAP_MODELS:
        raise InvalidInputError(f"{where}: unknown camera model {model!r}; supported: {list(COLMAP_MODELS)}")
    w, h = colmap_int(cells[2], f"{where}: WIDTH"), colmap_int(cells[3], f"{where}: HEIGHT")
    names = COLMAP_MODELS[model]
    if len(cells) - 4 != len(names):
        raise InvalidInputError(f"{where}: {model} takes {len(names)} parameters {list(names)}; got {cells[4:]}")
    v = {k: finite_number(c, f"{where}: {model} parameter {k!r}") for k, c in zip(names, cells[4:], strict=True)}
    for k in ("k4", "k5", "k6"):
        if v.get(k, 0.0) != 0.0:
            raise InvalidInputError(f"{where}: FULL_OPENCV {k} = {v[k]!r}; the frame camera model has no rational "
                                    "distortion (k4, k5, k6 must be 0)")
    fx = v.get("f", v.get("fx", 0.0))
    fy = v.get("f", v.get("fy", 0.0))
    d: dict[str, Any] = {"width": w, "height": h, "principal_point_px": [v["cx"] - 0.5, v["cy"] - 0.5],
                         "distortion": {k: v.get(k, 0.0) for k in ("k1", "k2", "k3", "p1", "p2")}}
    return cid, camera_from_focals(d, fx, fy, where=f"{where}: camera {cid}")


def _read_cameras(folder: Path) -> tuple[dict[int, Camera], dict[int, str]]:
    cam_lines, cam_names = colmap_lines(folder / "cameras.txt")
    raw_cams: dict[int, Camera] = {}
    for no, s in cam_lines:
        if s:
            cid, cam = _camera(s.split(), folder / "cameras.txt", no)
            if cid in raw_cams:
                raise InvalidInputError(f"{str(folder / 'cameras.txt')!r} line {no}: CAMERA_ID {cid} appears twice")
            raw_cams[cid] = cam
    if not raw_cams:
        raise InvalidInputError(f"{str(folder / 'cameras.txt')!r} holds no camera")
    return raw_cams, {cid: cam_names["camera"].get(cid, str(cid)) for cid in raw_cams}


def read_colmap_cameras(path: StrPath) -> dict[str, Camera]:
    """Read the cameras of a COLMAP text model (its folder, or ``cameras.txt``), keyed by camera id.

    Raises
    ------
    RasterIOError, InvalidInputError, CalibrationError
        A missing file, a binary model, a malformed line or an unsupported camera model (file, line
        and value named).
    """
    raw_cams, cam_key = _read_cameras(_folder(path))
    return {cam_key[cid]: cam for cid, cam in raw_cams.items()}


def read_colmap_images(path: StrPath) -> ColmapImages:
    """Read the cameras and image poses of a COLMAP text model (a folder with ``cameras.txt``, ``images.txt``).

    Raises
    ------
    RasterIOError
        A file is missing or unreadable.
    InvalidInputError
        A binary model, a malformed line (file, line and value named), an unsupported camera model
        (named), an image naming an unknown camera, a non-unit quaternion, an image NAME twice.
    """
    folder = _folder(path)
    raw_cams, cam_key = _read_cameras(folder)
    cameras = {cam_key[cid]: cam for cid, cam in raw_cams.items()}
    img_path = folder / "images.txt"
    img_lines, _ = colmap_lines(img_path)
    names: list[str] = []
    cam_of: list[str] = []
    pos: list[NDArray[np.float64]] = []
    rot: list[NDArray[np.float64]] = []
    iids: list[int] = []
    points2d: list[NDArray[np.float64]] = []
    i = 0
    while i < len(img_lines):
        no, s = img_lines[i]
        i += 1
        if not s:
            continue
        c = s.split()
        where = f"{str(img_path)!r} line {no}"
        if len(c) != 10:
            raise InvalidInputError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME; got {s!r:.120}")
        iid = colmap_int(c[0], f"{where}: IMAGE_ID")
        q = np.array([finite_number(x, f"{where}: {k}") for x, k in zip(c[1:5], ("QW", "QX", "QY", "QZ"),
                                                                       strict=True)])
        t = np.array([finite_number(x, f"{where}: {k}") for x, k in zip(c[5:8], ("TX", "TY", "TZ"), strict=True)])
        cid = colmap_int(c[8], f"{where}: CAMERA_ID")
        if cid not in raw_cams:
            raise InvalidInputError(f"{where}: image {c[9]!r} names CAMERA_ID {cid}, which cameras.txt lacks")
        if abs(np.linalg.norm(q) - 1.0) > 1e-6:
            raise InvalidInputError(f"{where}: quaternion {q.tolist()} is not a unit quaternion (norm "
                                    f"{np.linalg.norm(q):.9g})")
        if iid in iids:
            raise InvalidInputError(f"{where}: IMAGE_ID {iid} appears twice")
        R_cw = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        try:
            R = check_rotation(R_cw.T @ _FLIP, "rotation")
        except RectifyError as err:
            raise InvalidInputError(f"{where}: {err}") from None
        names.append(c[9])
        cam_of.append(cam_key[cid])
        pos.append(-R_cw.T @ t)
        rot.append(np.asarray(R, dtype=np.float64))
        iids.append(iid)
        pts = img_lines[i][1].split() if i < len(img_lines) else []
        i += 1
        if len(pts) % 3:
            raise InvalidInputError(f"{str(img_path)!r} line {img_lines[i - 1][0]}: POINTS2D must be triples "
                                    f"(X, Y, POINT3D_ID); got {len(pts)} values")
        xy = np.array([finite_number(x, f"{str(img_path)!r} line {img_lines[i - 1][0]}: POINTS2D value")
                       for k, x in enumerate(pts) if k % 3 != 2], dtype=np.float64).reshape(-1, 2)
        points2d.append(xy - 0.5)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InvalidInputError(f"{str(img_path)!r}: image NAME {dup[0]!r} appears twice")
    return ColmapImages(cameras, tuple(names), tuple(cam_of), np.array(pos, dtype=np.float64).reshape(-1, 3),
                        np.array(rot, dtype=np.float64).reshape(-1, 3, 3), tuple(iids), tuple(points2d), folder)


def detect_colmap(path: StrPath) -> bool:
    """Whether ``path`` is a COLMAP text model: a folder with ``cameras.txt`` and ``images.txt``, or one of
    its files."""
    p = Path(path)
    if p.is_dir():
        return (p / "cameras.txt").is_file() and (p / "images.txt").is_file()
    return p.name in COLMAP_FILES and (p.parent / "cameras.txt").is_file()
