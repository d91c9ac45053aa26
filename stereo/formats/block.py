"""Files of a block job: the block control CSV, the observations CSV and the block orientation JSON.

Formats (``docs/formats.md``):

Block control CSV
    Header ``id,image,col,row,x,y,z`` with optional ``sx,sy,sz`` (a-priori standard deviations of
    the ground coordinates, ground units) and a ``# crs=...`` comment line. One row per image
    measurement of a control point (``col,row`` in that image's pixels); the ground coordinates
    may be repeated on every row of an id (they must agree) or given once. A row with an empty
    ``image`` gives ground coordinates only. Empty ``x,y`` with ``z`` make a height-only point,
    empty ``z`` with ``x,y`` a plan-only point; an id with no ground coordinates at all is a tie
    point measured by hand.
Observations CSV (written)
    ``image,id,col,row,sigma_px,residual_x_px,residual_y_px,weight,flagged[,redundancy]``: every
    image measurement of the adjustment with its residual (adjusted - observed), final weight,
    blunder flag and redundancy number (mean of x and y; written by ``stereo block`` when computed).
Block orientation JSON (written and read)
    ``format: rectify-stereo/block-orientation``, ``version``, ``crs``, ``frame`` (a sentence: what
    the coordinates are), ``reference_lla`` (OpenSfM's topocentric origin, when the poses came from
    a reconstruction), ``cameras`` (id -> camera JSON, with ``std_errors`` when self-calibrated),
    ``images`` (a list of ``{image, camera, position, rotation, angles_rad: {omega, phi, kappa},
    std_errors}``), ``sigma0`` (overall and per group), ``datum`` (the datum statements),
    ``summary`` and ``residuals`` (per group RMS). ``frame`` and ``reference_lla`` are optional
    (files written before them read as before).
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.atomic import read_json
from rectify.errors import InvalidInputError
from rectify.formats.common import (
    FORMAT_PREFIX,
    TableReader,
    check_format,
    check_numbers,
    malformed,
    need_columns,
)
from rectify.formats.tables import check_crs_comment
from rectify.geometry.camera import Camera
from rectify.report.builder import json_safe
from stereo.block.types import Pose, Tracks

__all__ = [
    "BLOCK_FORMAT",
    "BlockControlTable",
    "BlockOrientation",
    "block_orientation_text",
    "observations_text",
    "read_block_control",
    "read_block_orientation",
]

StrPath = str | os.PathLike[str]

BLOCK_FORMAT = FORMAT_PREFIX + "block-orientation"
BLOCK_VERSION = 1

#: kinds of control point by which ground coordinates are given
CONTROL_KINDS = ("full", "height", "plan", "tie")


@dataclass(frozen=True, eq=False)
class BlockControlTable:
    """Control of a block as read from a block control CSV.

    Attributes
    ----------
    ids : tuple of str
        One per point (K).
    xyz : (K, 3) float64
        Ground coordinates; NaN where not given (height-only: x, y NaN; plan-only: z NaN; tie: all).
    kind : tuple of str
        ``"full"``, ``"height"``, ``"plan"`` or ``"tie"`` per point.
    sigma_m : (K, 3) float64
        A-priori standard deviations of x, y, z, ground units (NaN where the file gives none).
    meas_id, meas_image : tuple of str
        Point id and image name of each image measurement (L).
    meas_pixel : (L, 2) float64
        The measured pixels (x = column, y = row).
    crs : str or None
    """

    ids: tuple[str, ...]
    xyz: NDArray[np.float64]
    kind: tuple[str, ...]
    sigma_m: NDArray[np.float64]
    meas_id: tuple[str, ...]
    meas_image: tuple[str, ...]
    meas_pixel: NDArray[np.float64]
    crs: str | None = None

    def __len__(self) -> int:
        return len(self.ids)

    def index(self) -> dict[str, int]:
        return {k: i for i, k in enumerate(self.ids)}


def read_block_control(path: StrPath) -> BlockControlTable:
    """Read a block control CSV (see the module docstring).

    Read as a stream into arrays (:class:`rectify.formats.common.TableReader`); a file of more than
    :data:`rectify.formats.common.MAX_POINT_ROWS` rows is refused. When a file has several faults, the one
    on the earliest line is named.

    Raises
    ------
    InvalidInputError
        Missing columns, a non-numeric value (line and value named), an id whose rows give
        different ground coordinates, a negative or zero sigma, an id measured twice in one image,
        too many rows.
    CRSError
        The ``# crs=`` value is not a CRS (line named).
    RasterIOError
        The file cannot be read.
    """
    with TableReader(path) as t:
        fields = list(t.fields)
        need_columns(fields, ("id", "image", "col", "row", "x", "y", "z"), path)
        has_sigma = all(k in fields for k in ("sx", "sy", "sz"))
        sig_cols = ("sx", "sy", "sz") if has_sigma else ()
        cols = t.read("rows", numbers=("col", "row", "x", "y", "z", *sig_cols), texts=("id", "image"),
                      empty=("col", "row", "x", "y", "z", *sig_cols))
    check_crs_comment(cols)
    label, lines, num = repr(str(path)), cols.lines, cols.numbers
    ids, images = cols.texts["id"], cols.texts["image"]
    n = len(cols)
    order: dict[str, int] = {}
    point = np.fromiter((order.setdefault(pid, len(order)) for pid in ids), dtype=np.int64, count=n)
    g = np.column_stack([num["x"], num["y"], num["z"]])
    s = np.column_stack([num[k] for k in sig_cols]) if has_sigma else np.full((n, 3), np.nan)
    px = np.column_stack([num["col"], num["row"]])
    faults: list[tuple[int, str]] = []  # (row, message): the earliest row's fault is raised

    def first(mask: Any) -> int | None:
        k = np.flatnonzero(mask)
        return int(k[0]) if k.size else None

    if (i := first(np.array([pid == "" for pid in ids], dtype=bool))) is not None:
        faults.append((i, f"{label} line {lines[i]}: empty id"))
    if (i := first(np.isnan(g[:, 0]) != np.isnan(g[:, 1]))) is not None:
        faults.append((i, f"{label} line {lines[i]}: x and y must be both given or both empty (id {ids[i]!r})"))
    xyz = _first_given(g, point, len(order))
    ref = xyz[point]
    both = np.isfinite(g) & np.isfinite(ref)
    with np.errstate(invalid="ignore"):
        differ = both & (np.abs(g - ref) > 1e-9 * np.maximum(1.0, np.abs(ref)))
    if (i := first(differ.any(axis=1))) is not None:
        earlier = _first_given(g[:i], point[:i], len(order))[point[i]]
        faults.append((i, f"{label} line {lines[i]}: id {ids[i]!r} has ground coordinates {g[i].tolist()} here and "
                          f"{earlier.tolist()} on an earlier row"))
    with np.errstate(invalid="ignore"):
        if (i := first((s <= 0).any(axis=1))) is not None:
            faults.append((i, f"{label} line {lines[i]}: standard deviations must be > 0; got {s[i].tolist()}"))
    no_image = np.array([im == "" for im in images], dtype=bool)
    if (i := first(no_image & np.isfinite(px).any(axis=1))) is not None:
        faults.append((i, f"{label} line {lines[i]}: col/row given without an image (id {ids[i]!r})"))
    if (i := first(~no_image & np.isnan(px).any(axis=1))) is not None:
        c = "col" if np.isnan(px[i, 0]) else "row"
        faults.append((i, f"{label} line {lines[i]}: column {c!r} is not a number: ''"))
    meas = np.flatnonzero(~no_image)
    image_no: dict[str, int] = {}
    img = np.fromiter((image_no.setdefault(images[k], len(image_no)) for k in meas), dtype=np.int64, count=meas.size)
    key = point[meas] * max(len(image_no), 1) + img
    srt = np.argsort(key, kind="stable")
    twice = srt[1:][key[srt][1:] == key[srt][:-1]]
    if twice.size:
        i = int(meas[twice.min()])
        faults.append((i, f"{label} line {lines[i]}: id {ids[i]!r} is measured twice in image {images[i]!r}"))
    if faults:
        raise InvalidInputError(min(faults)[1])
    sigma = _last_given(s, point, len(order))
    kinds = []
    for q in xyz:
        if np.isfinite(q).all():
            kinds.append("full")
        elif np.isfinite(q[2]):
            kinds.append("height")
        elif np.isfinite(q[:2]).all():
            kinds.append("plan")
        else:
            kinds.append("tie")
    return BlockControlTable(tuple(order), xyz.reshape(-1, 3), tuple(kinds), sigma.reshape(-1, 3),
                             tuple(ids[k] for k in meas), tuple(images[k] for k in meas),
                             px[meas].reshape(-1, 2), cols.crs)


def _first_given(v: NDArray[np.float64], group: NDArray[np.int64], k: int) -> NDArray[np.float64]:
    """(k, 3): for each group and column, the value of its first row where ``v`` is finite (NaN if none)."""
    out = np.full((k, v.shape[1]), np.nan)
    for c in range(v.shape[1]):
        rows = np.flatnonzero(np.isfinite(v[:, c]))
        groups, at = np.unique(group[rows], return_index=True)  # the first occurrence of each group
        out[groups, c] = v[rows[at], c]
    return out


def _last_given(v: NDArray[np.float64], group: NDArray[np.int64], k: int) -> NDArray[np.float64]:
    """(k, 3): for each group and column, the value of its last row where ``v`` is finite (NaN if none)."""
    return _first_given(v[::-1], group[::-1], k)


def observations_text(tracks: Tracks, residual_px: NDArray[np.float64] | None = None,
                      weight: NDArray[np.float64] | None = None, flagged: NDArray[np.bool_] | None = None,
                      redundancy: NDArray[np.float64] | None = None) -> str:
    """The observations CSV of a block (see the module docstring); residuals in pixels.

    ``redundancy`` (M, 2) or (M,): the observations' redundancy numbers (x and y; written as their mean in
    a ``redundancy`` column, 0..1: the share of an error that shows in the residual).
    """
    m = tracks.n_obs
    res = np.full((m, 2), np.nan) if residual_px is None else np.asarray(residual_px, dtype=np.float64)
    w = np.ones(m) if weight is None else np.asarray(weight, dtype=np.float64)
    fl = np.zeros(m, dtype=bool) if flagged is None else np.asarray(flagged, dtype=bool)
    red = None
    if redundancy is not None:
        r = np.asarray(redundancy, dtype=np.float64)
        red = r.reshape(m, -1).mean(axis=1) if r.size else np.full(m, np.nan)
    buf = io.StringIO()
    buf.write("image,id,col,row,sigma_px,residual_x_px,residual_y_px,weight,flagged"
              + (",redundancy" if red is not None else "") + "\n")
    for k in range(m):
        vals = [tracks.images[tracks.obs_image[k]], tracks.point_ids[tracks.obs_point[k]],
                f"{tracks.obs_pixel[k, 0]:.4f}", f"{tracks.obs_pixel[k, 1]:.4f}", f"{tracks.obs_sigma_px[k]:.4g}",
                _fmt(res[k, 0], 5), _fmt(res[k, 1], 5), _fmt(w[k], 4), "1" if fl[k] else "0"]
        if red is not None:
            vals.append(_fmt(red[k], 4))
        buf.write(",".join(vals) + "\n")
    return buf.getvalue()


def _fmt(v: float, nd: int) -> str:
    return "" if not math.isfinite(v) else f"{v:.{nd}f}"


# --------------------------------------------------------------------------- block orientation JSON
@dataclass(frozen=True, eq=False)
class BlockOrientation:
    """A block orientation JSON as read back.

    Attributes
    ----------
    cameras : dict str -> Camera
    poses : list of Pose
        In file order.
    std_errors : (n, 6) float64
        omega, phi, kappa (rad), x, y, z (ground units); NaN where the file gives none.
    crs : str or None
    sigma0 : dict
        Overall (``"all"``) and per observation group.
    datum : list of str
    summary : dict
    frame : str or None
        What the coordinates are (None in files written before the key).
    reference_lonlat_h : (3,) float64 or None
        OpenSfM's topocentric origin (lon, lat in degrees, h in metres), when recorded.
    """

    cameras: dict[str, Camera]
    poses: list[Pose]
    std_errors: NDArray[np.float64]
    crs: str | None = None
    sigma0: dict[str, Any] = field(default_factory=dict)
    datum: list[str] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    frame: str | None = None
    reference_lonlat_h: NDArray[np.float64] | None = None

    def pose(self, image: str) -> Pose:
        for p in self.poses:
            if p.image == image:
                return p
        raise InvalidInputError(f"image {image!r} is not in the block (images: {[p.image for p in self.poses][:10]})")


_STD_NAMES = ("omega", "phi", "kappa", "x", "y", "z")


def block_orientation_dict(cameras: Mapping[str, Camera], poses: Sequence[Pose], *,
                           std_errors: NDArray[np.float64] | None = None, crs: str | None = None,
                           sigma0: Mapping[str, Any] | None = None, datum: Sequence[str] = (),
                           summary: Mapping[str, Any] | None = None, frame: str | None = None,
                           reference_lonlat_h: Sequence[float] | None = None) -> dict[str, Any]:
    """The block orientation JSON object (see the module docstring)."""
    std = np.full((len(poses), 6), np.nan) if std_errors is None else np.asarray(std_errors, dtype=np.float64)
    images = []
    for i, p in enumerate(poses):
        a = p.angles
        d: dict[str, Any] = {"image": p.image, "camera": p.camera, "position": [float(v) for v in p.position],
                             "rotation": [[float(v) for v in row] for row in p.rotation],
                             "angles_rad": {"omega": float(a[0]), "phi": float(a[1]), "kappa": float(a[2])}}
        if np.isfinite(std[i]).any():
            d["std_errors"] = {n: float(v) for n, v in zip(_STD_NAMES, std[i], strict=True) if math.isfinite(v)}
        images.append(d)
    head: dict[str, Any] = {"format": BLOCK_FORMAT, "version": BLOCK_VERSION, "crs": crs}
    if frame is not None:
        head["frame"] = frame
    if reference_lonlat_h is not None:
        lon, lat, h = (float(v) for v in reference_lonlat_h)
        head["reference_lla"] = {"longitude": lon, "latitude": lat, "altitude": h}
    return {**head,
            "angles": "omega-phi-kappa (R = Rx(omega) Ry(phi) Rz(kappa) takes (x, y, -f) into the ground frame)",
            "cameras": {k: c.to_dict() for k, c in cameras.items()}, "images": images,
            "sigma0": dict(sigma0 or {}), "datum": list(datum), "summary": dict(summary or {})}


def block_orientation_text(cameras: Mapping[str, Camera], poses: Sequence[Pose], **kwargs: Any) -> str:
    """:func:`block_orientation_dict` as indented JSON text (NaN refused: the report values are finite or null)."""
    return json.dumps(json_safe(block_orientation_dict(cameras, poses, **kwargs)), indent=2, allow_nan=False) + "\n"


def read_block_orientation(path: StrPath) -> BlockOrientation:
    """Read a block orientation JSON.

    Raises
    ------
    InvalidInputError
        Another format, a newer version, a missing or malformed key (named with its image).
    """
    d = read_json(path, "block orientation file")
    check_format(d, "block-orientation", BLOCK_VERSION, path, what="block orientation file")
    with malformed(f"block orientation file {str(path)!r}"):
        return _block_orientation(d, path)


def _block_orientation(d: dict[str, Any], path: StrPath) -> BlockOrientation:
    if d.get("format") != BLOCK_FORMAT:
        raise InvalidInputError(f"{str(path)!r} is not a block orientation file (no format {BLOCK_FORMAT!r})")
    cams_raw = d.get("cameras")
    imgs = d.get("images")
    if not isinstance(cams_raw, dict) or not cams_raw:
        raise InvalidInputError(f"{str(path)!r}: `cameras` must be a non-empty object (id -> camera)")
    if not isinstance(imgs, list) or not imgs:
        raise InvalidInputError(f"{str(path)!r}: `images` must be a non-empty list")
    for key, kind in (("sigma0", dict), ("summary", dict), ("datum", list)):
        if d.get(key) is not None and not isinstance(d[key], kind):
            raise InvalidInputError(f"{str(path)!r}: `{key}` must be {'an object' if kind is dict else 'a list'}; "
                                    f"got {d[key]!r:.80}")
    cameras = {}
    for k, v in cams_raw.items():
        if not isinstance(v, dict):
            raise InvalidInputError(f"{str(path)!r}: camera {k!r} must be an object; got {v!r}")
        cameras[str(k)] = Camera.from_dict(v)
    poses, std = [], []
    for i, im in enumerate(imgs):
        if not isinstance(im, dict):
            raise InvalidInputError(f"{str(path)!r}: images[{i}] must be an object; got {im!r}")
        name = im.get("image")
        for key, shape in (("position", (3,)), ("rotation", (3, 3))):
            if key not in im:
                raise InvalidInputError(f"{str(path)!r}: image {name!r} lacks {key!r}")
            try:
                check_numbers(im, key, shape, path)
            except InvalidInputError as err:
                raise InvalidInputError(f"{err} (image {name!r})") from None
        try:
            pose = Pose(str(name), str(im.get("camera")), np.asarray(im.get("position"), dtype=np.float64),
                        np.asarray(im.get("rotation"), dtype=np.float64))
        except (TypeError, ValueError) as err:
            raise InvalidInputError(f"{str(path)!r}: image {name!r}: {err}") from err
        if pose.camera not in cameras:
            raise InvalidInputError(f"{str(path)!r}: image {name!r} names camera {pose.camera!r}, which is not "
                                    f"in `cameras` {sorted(cameras)}")
        poses.append(pose)
        se = im.get("std_errors") or {}
        if not isinstance(se, dict):
            raise InvalidInputError(f"{str(path)!r}: image {name!r}: `std_errors` must be an object; got {se!r}")
        std.append([float(se[n]) if isinstance(se.get(n), (int, float)) else math.nan for n in _STD_NAMES])
    crs = d.get("crs")
    frame = d.get("frame")
    ref = None
    lla = d.get("reference_lla")
    if isinstance(lla, dict):
        try:
            ref = np.array([float(lla["longitude"]), float(lla["latitude"]), float(lla["altitude"])])
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"{str(path)!r}: `reference_lla` must hold longitude, latitude and altitude; "
                                    f"got {lla!r}") from err
    return BlockOrientation(cameras, poses, np.array(std, dtype=np.float64).reshape(-1, 6),
                            crs if isinstance(crs, str) else None, dict(d.get("sigma0") or {}),
                            list(d.get("datum") or []), dict(d.get("summary") or {}),
                            frame if isinstance(frame, str) else None, ref)
