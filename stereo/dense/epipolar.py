"""Normal-case (epipolar) rectification of a frame pair.

Both photos are rotated into one *normal frame* whose x axis is the base and whose z axis is the
mean of the two photos' z axes made perpendicular to the base (the rotation that moves each photo
least, hence the least distortion). Both rectified photos share one principal distance ``focal_px``
and one row origin, so corresponding points lie on the same row: after resampling every pixel is
matched along its row (seed 003, 2.1.3).

Coordinates
-----------
normal pixel (u, w)
    ``u = -focal_px * v0 / v2``, ``w = focal_px * v1 / v2`` where ``v = N.T @ R @ (x, y, -f)`` is
    the photo vector turned into the normal frame (``N``: the normal frame's axes as columns, in the
    orientation's frame; ``R``: ``rotation_left`` or ``rotation_right``). u is right, w down.
rectified pixel (col, row)
    ``col = u - col0`` (one ``col0`` per photo), ``row = w - row0`` (shared). The disparity of a point
    is ``d = col_left - col_right``, so ``u_left - u_right = d + col0_left - col0_right``.

Without lens distortion the map from a rectified pixel to the original pixel is a homography
``H = A R.T N B`` (``B``: rectified pixel -> normal photo vector; ``A``: photo vector -> pixel);
with distortion the exact map goes through :meth:`rectify.geometry.camera.Camera.pixel_from_photo`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from affine import Affine
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError, StereoError
from rectify.features.lsm import LsmConfig, refine_matches
from rectify.geometry.camera import Camera
from rectify.geometry.points import as_pair
from rectify.geometry.rotation import check_rotation
from rectify.raster.io import (
    MaskPolicy,
    TiledWriter,
    WindowReader,
    ignore_not_georeferenced,
    iter_windows,
    raster_info,
)

logger = logging.getLogger(__name__)

__all__ = ["EpipolarRectification", "ParallaxReport", "RectifiedView", "rectify_pair", "resample_view",
           "tie_parallax", "check_base_parallax", "BASE_PRECISION", "MIN_PARALLAX_PX", "MIN_BASE_RATIO"]

StrPath = str | Path

#: a base shorter than this share of the largest coordinate of the left projection centre (at least 1) is zero
BASE_PRECISION = 1e-9
#: the smallest median x-parallax of the tie points in the normal case, px (:func:`check_base_parallax`)
MIN_PARALLAX_PX = 1.0
#: the smallest base-to-distance ratio B / Z of the tie points (:func:`check_base_parallax`)
MIN_BASE_RATIO = 1e-3
#: the rectified photos may cover at most this many times the original area (strongly convergent pairs)
MAX_AREA_RATIO = 4.0


@dataclass(frozen=True, eq=False)
class RectifiedView:
    """One rectified photo.

    Attributes
    ----------
    camera : Camera
        Interior orientation of the original photo.
    rotation : (3, 3) float64
        Original photo vector (x, y, -f) -> orientation frame.
    col0 : float
        Normal-pixel u of rectified column 0.
    width, height : int
        Size of the rectified photo.
    homography : (3, 3) float64
        Rectified pixel (col, row, 1) -> original pixel (homogeneous); exact without distortion.
    """

    camera: Camera
    rotation: NDArray[np.float64]
    col0: float
    width: int
    height: int
    homography: NDArray[np.float64]

    def __post_init__(self) -> None:
        self.rotation.flags.writeable = False
        self.homography.flags.writeable = False


@dataclass(frozen=True, eq=False)
class EpipolarRectification:
    """The normal case of a pair: rotations, shared principal distance, the two rectified views.

    Attributes
    ----------
    normal_rotation : (3, 3) float64
        Axes of the normal frame (columns) in the orientation's frame; column 0 is the base direction.
    focal_px : float
        Principal distance of both rectified photos, pixels.
    row0 : float
        Normal-pixel w of rectified row 0 (both photos).
    left, right : RectifiedView
    base : (3,) float64
        Right projection centre minus left, orientation frame and units.
    centre_left : (3,) float64
        Left projection centre (0 in a model frame).
    """

    normal_rotation: NDArray[np.float64]
    focal_px: float
    row0: float
    left: RectifiedView
    right: RectifiedView
    base: NDArray[np.float64]
    centre_left: NDArray[np.float64]

    def __post_init__(self) -> None:
        for a in (self.normal_rotation, self.base, self.centre_left):
            a.flags.writeable = False

    def view(self, which: str) -> RectifiedView:
        if which not in ("left", "right"):
            raise InvalidInputError(f"`which` must be 'left' or 'right'; got {which!r}")
        return self.left if which == "left" else self.right

    @property
    def disparity_offset(self) -> float:
        """``u_left - u_right`` minus the disparity: ``col0_left - col0_right``."""
        return self.left.col0 - self.right.col0

    # ------------------------------------------------------------------ maps
    def rectified_from_original(self, which: str, pixel: ArrayLike) -> NDArray[np.float64]:
        """Original pixels (N, 2) of one photo -> rectified pixels (N, 2)."""
        v = self.view(which)
        uw = _normal_from_photo(v.camera.photo_from_pixel(pixel), v.camera.focal_length_mm, v.rotation,
                                self.normal_rotation, self.focal_px)
        return np.column_stack([uw[:, 0] - v.col0, uw[:, 1] - self.row0])

    def original_from_rectified(self, which: str, pixel: ArrayLike) -> NDArray[np.float64]:
        """Rectified pixels (N, 2) of one photo -> original pixels (N, 2) (the map back)."""
        v = self.view(which)
        p = _as_points(pixel, "pixel")
        if not v.camera.has_distortion:
            return _apply_h(v.homography, p)
        return v.camera.pixel_from_photo(self.photo_from_rectified(which, p))

    def photo_from_rectified(self, which: str, pixel: ArrayLike) -> NDArray[np.float64]:
        """Rectified pixels (N, 2) -> ideal photo coordinates (N, 2, mm) of the original photo."""
        v = self.view(which)
        p = _as_points(pixel, "pixel")
        u = p[:, 0] + v.col0
        w = p[:, 1] + self.row0
        m = np.column_stack([u, -w, np.full(len(p), -self.focal_px)]) @ (v.rotation.T @ self.normal_rotation).T
        f = v.camera.focal_length_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.column_stack([-f * m[:, 0] / m[:, 2], -f * m[:, 1] / m[:, 2]])

    def source_maps(self, which: str, col_off: int, row_off: int, width: int, height: int
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Original-pixel coordinates (map_x, map_y) of a window of the rectified photo, float32 (h, w)."""
        v = self.view(which)
        cols = np.arange(col_off, col_off + width, dtype=np.float64)
        rows = np.arange(row_off, row_off + height, dtype=np.float64)
        if not v.camera.has_distortion:
            H = v.homography
            cc, rr = np.meshgrid(cols, rows)
            den = H[2, 0] * cc + H[2, 1] * rr + H[2, 2]
            mx = (H[0, 0] * cc + H[0, 1] * rr + H[0, 2]) / den
            my = (H[1, 0] * cc + H[1, 1] * rr + H[1, 2]) / den
            return mx.astype(np.float32), my.astype(np.float32)
        # distortion: exact on a 8-px lattice, bilinear in between (error << 0.01 px for smooth distortion)
        step = 8
        lc = np.arange(0, width + step, step, dtype=np.float64) + col_off
        lr = np.arange(0, height + step, step, dtype=np.float64) + row_off
        gc, gr = np.meshgrid(lc, lr)
        src = self.original_from_rectified(which, np.column_stack([gc.ravel(), gr.ravel()]))
        gx = src[:, 0].reshape(gc.shape).astype(np.float32)
        gy = src[:, 1].reshape(gc.shape).astype(np.float32)
        fx = ((cols - col_off) / step).astype(np.float32)
        fy = ((rows - row_off) / step).astype(np.float32)
        ffx, ffy = np.meshgrid(fx, fy)
        mx = np.asarray(cv2.remap(gx, ffx, ffy, cv2.INTER_LINEAR), dtype=np.float32)
        my = np.asarray(cv2.remap(gy, ffx, ffy, cv2.INTER_LINEAR), dtype=np.float32)
        return mx, my

    def to_dict(self) -> dict:
        """JSON form (for the products' metadata)."""
        return {
            "normal_rotation": self.normal_rotation.tolist(),
            "focal_px": self.focal_px,
            "row0": self.row0,
            "base": self.base.tolist(),
            "centre_left": self.centre_left.tolist(),
            "left": {"col0": self.left.col0, "width": self.left.width, "height": self.left.height,
                     "homography": self.left.homography.tolist()},
            "right": {"col0": self.right.col0, "width": self.right.width, "height": self.right.height,
                      "homography": self.right.homography.tolist()},
        }


def _as_points(a: ArrayLike, name: str) -> NDArray[np.float64]:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim == 1 and p.size == 2:
        p = p.reshape(1, 2)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ShapeError(f"`{name}` must have shape (N, 2); got {p.shape}", actual_shape=p.shape,
                         expected_shape=(None, 2))
    return p


def _apply_h(H: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    q = np.column_stack([p, np.ones(len(p))]) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:3]


def _normal_from_photo(mm: NDArray[np.float64], f_mm: float, R: NDArray[np.float64], N: NDArray[np.float64],
                       focal_px: float) -> NDArray[np.float64]:
    """Photo coordinates (mm) -> normal pixels (u, w)."""
    vec = np.column_stack([mm, np.full(len(mm), -f_mm)]) @ (N.T @ R).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.column_stack([-focal_px * vec[:, 0] / vec[:, 2], focal_px * vec[:, 1] / vec[:, 2]])


def normal_frame(rotation_left: ArrayLike, rotation_right: ArrayLike, base: ArrayLike) -> NDArray[np.float64]:
    """Axes of the normal frame (columns): x along the base, z the mean photo z made perpendicular to it.

    Raises
    ------
    StereoError
        Zero base, or a base along the mean viewing direction (no normal case exists).
    """
    R1 = check_rotation(rotation_left, "rotation_left")
    R2 = check_rotation(rotation_right, "rotation_right")
    b = np.asarray(base, dtype=np.float64).reshape(-1)
    if b.shape != (3,) or not np.isfinite(b).all():
        raise ShapeError(f"`base` must be 3 finite numbers; got {b.tolist()}", actual_shape=b.shape,
                         expected_shape=(3,))
    nb = float(np.linalg.norm(b))
    if not nb > 0:
        raise StereoError(f"the base is zero ({b.tolist()}): no normal case exists")
    e1 = b / nb
    z = R1[:, 2] + R2[:, 2]
    z = z / np.linalg.norm(z)
    e3 = z - (z @ e1) * e1
    n3 = float(np.linalg.norm(e3))
    if n3 < 0.1:
        raise StereoError(f"the base is within {math.degrees(math.asin(min(n3, 1.0))):.1f} deg of the viewing "
                          "direction: no normal case exists (forward-looking pair)")
    e3 /= n3
    e2 = np.cross(e3, e1)
    return np.column_stack([e1, e2, e3])


def check_base_parallax(parallax_px: ArrayLike, focal_px: float, base: NDArray[np.float64]) -> None:
    """Refuse a pair without a usable base, judged by its tie points' x-parallax in the normal case.

    A point at distance Z (along the normal frame's z) has the parallax ``p = focal_px * B / Z``, so
    the median parallax gives the base-to-distance ratio ``B / Z = p / focal_px``. Photos taken from
    one point (a zero or near-zero base: a copied orientation, a mistyped position) give no parallax
    and no heights; a tiny ratio gives heights of no precision.

    Raises
    ------
    StereoError
        "no base", with the median parallax (px), the ratio, the base and the limits
        (:data:`MIN_PARALLAX_PX`, :data:`MIN_BASE_RATIO`).
    """
    p = np.asarray(parallax_px, dtype=np.float64).reshape(-1)
    p = p[np.isfinite(p)]
    if p.size == 0:
        return
    med = float(np.median(p))
    ratio = med / float(focal_px)
    nb = float(np.linalg.norm(base))
    if med < MIN_PARALLAX_PX or ratio < MIN_BASE_RATIO:
        raise StereoError(
            f"no base: the tie points' parallax in the normal case is {med:.3g} px (median of {p.size}; principal "
            f"distance {focal_px:.1f} px), a base-to-distance ratio of {ratio:.2g} (base {nb:.4g} orientation units): "
            f"the photos were taken from (nearly) one point, which gives no heights; at least "
            f"{MIN_PARALLAX_PX:g} px and a ratio of {MIN_BASE_RATIO:g} are needed (check the orientations' positions)")


def _boundary(camera: Camera, n: int = 16) -> NDArray[np.float64]:
    """Points along the border of the image (pixel centres of the outer pixels)."""
    W, H = camera.width - 1, camera.height - 1
    t = np.linspace(0.0, 1.0, n)
    return np.vstack([np.column_stack([t * W, np.zeros(n)]), np.column_stack([t * W, np.full(n, H)]),
                      np.column_stack([np.zeros(n), t * H]), np.column_stack([np.full(n, W), t * H])])


def rectify_pair(
    camera_left: Camera,
    camera_right: Camera,
    *,
    rotation_left: ArrayLike,
    rotation_right: ArrayLike,
    base: ArrayLike,
    centre_left: ArrayLike = (0.0, 0.0, 0.0),
    disparity_range: tuple[float, float] | None = None,
    tie_left: ArrayLike | None = None,
    tie_right: ArrayLike | None = None,
    margin_px: float = 16.0,
) -> EpipolarRectification:
    """The rectifying homographies of a frame pair and the extent of the rectified photos.

    Parameters
    ----------
    camera_left, camera_right : Camera
    rotation_left, rotation_right : (3, 3) array_like
        Photo vector (x, y, -f) -> orientation frame (model frame of a relative orientation, or
        the ground frame of two exterior orientations).
    base : (3,) array_like
        Right projection centre minus left (orientation frame).
    centre_left : (3,) array_like
        Left projection centre (0 for a model).
    disparity_range : (float, float), optional
        Expected ``u_left - u_right`` range (normal pixels). With tie points it is taken from them.
        When known, each rectified photo is cropped to the part that can overlap the other.
    tie_left, tie_right : (N, 2) array_like, optional
        Tie points (original pixels); they give the disparity range (with ``margin_px``).
    margin_px : float
        Added on both sides of the tie-point disparity range.

    Returns
    -------
    EpipolarRectification

    Raises
    ------
    StereoError
        No normal case (zero base or forward motion), the photos do not overlap, or the rectified
        photos would be more than ``MAX_AREA_RATIO`` times the original area (strongly convergent pair).
    InvalidInputError, ShapeError
        Malformed input.
    """
    for name, cam in (("camera_left", camera_left), ("camera_right", camera_right)):
        if not isinstance(cam, Camera):
            raise InvalidInputError(f"`{name}` must be a rectify.geometry.camera.Camera; got {type(cam).__name__}")
    C1 = np.array(centre_left, dtype=np.float64).reshape(-1)
    if C1.shape != (3,) or not np.isfinite(C1).all():
        raise ShapeError(f"`centre_left` must be 3 finite numbers; got {C1.tolist()}", actual_shape=C1.shape,
                         expected_shape=(3,))
    b = np.asarray(base, dtype=np.float64).reshape(-1)
    nb, scale = float(np.linalg.norm(b)), max(1.0, float(np.abs(C1).max()))
    if b.shape == (3,) and np.isfinite(b).all() and nb < BASE_PRECISION * scale:
        raise StereoError(f"no base: the base is zero{'' if nb == 0 else ' as far as the coordinates tell'} (the "
                          f"projection centres are {nb:.3g} orientation units apart, below {BASE_PRECISION:g} of "
                          f"{scale:.6g}): the photos were taken from one point, which gives no heights (check the "
                          "orientations' positions)")
    N = normal_frame(rotation_left, rotation_right, base)
    R1 = np.array(rotation_left, dtype=np.float64)
    R2 = np.array(rotation_right, dtype=np.float64)
    if not (isinstance(margin_px, (int, float)) and math.isfinite(margin_px) and margin_px >= 0):
        raise InvalidInputError(f"`margin_px` must be a finite number >= 0; got {margin_px!r}")
    fpx = 0.5 * (camera_left.focal_px + camera_right.focal_px)
    extents = []
    for cam, R in ((camera_left, R1), (camera_right, R2)):
        mm = cam.photo_from_pixel(_boundary(cam))
        vec = np.column_stack([mm, np.full(len(mm), -cam.focal_length_mm)]) @ (N.T @ R).T
        if not (vec[:, 2] < 0).all():
            raise StereoError("a photo looks more than 90 deg away from the normal direction: no normal case "
                              "(strongly convergent pair)")
        uw = _normal_from_photo(mm, cam.focal_length_mm, R, N, fpx)
        extents.append((uw[:, 0].min(), uw[:, 0].max(), uw[:, 1].min(), uw[:, 1].max()))
    (ul0, ul1, wl0, wl1), (ur0, ur1, wr0, wr1) = extents
    if tie_left is not None or tie_right is not None:
        if tie_left is None or tie_right is None:
            raise InvalidInputError("`tie_left` and `tie_right` must be given together")
        tl, tr = as_pair(tie_left, tie_right, names=("tie_left", "tie_right"))
        if len(tl) == 0:
            raise InvalidInputError("no tie points given (0 rows)")
        ul = _normal_from_photo(camera_left.photo_from_pixel(tl), camera_left.focal_length_mm, R1, N, fpx)
        ur = _normal_from_photo(camera_right.photo_from_pixel(tr), camera_right.focal_length_mm, R2, N, fpx)
        d = ul[:, 0] - ur[:, 0]
        check_base_parallax(d, fpx, np.asarray(base, dtype=np.float64).reshape(3))
        disparity_range = (float(np.min(d)) - margin_px, float(np.max(d)) + margin_px)
    # rows: the common range of both photos
    w0, w1 = max(wl0, wr0), min(wl1, wr1)
    if disparity_range is not None:
        dmin, dmax = (float(disparity_range[0]), float(disparity_range[1]))
        if not (math.isfinite(dmin) and math.isfinite(dmax) and dmin <= dmax):
            raise InvalidInputError(f"`disparity_range` must be two finite numbers, low <= high; got "
                                    f"{disparity_range!r}")
        ul0, ul1 = max(ul0, ur0 + dmin), min(ul1, ur1 + dmax)
        ur0, ur1 = max(ur0, ul0 - dmax), min(ur1, ul1 - dmin)
    if not (w1 - w0 >= 2 and ul1 - ul0 >= 2 and ur1 - ur0 >= 2):
        raise StereoError(f"the photos do not overlap in the normal case (rows {w0:.1f}..{w1:.1f}, left columns "
                          f"{ul0:.1f}..{ul1:.1f}, right columns {ur0:.1f}..{ur1:.1f})")
    row0 = math.floor(w0)
    height = int(math.ceil(w1) - row0 + 1)
    views = []
    area0 = camera_left.width * camera_left.height + camera_right.width * camera_right.height
    area = 0
    for cam, R, u0, u1 in ((camera_left, R1, ul0, ul1), (camera_right, R2, ur0, ur1)):
        col0 = float(math.floor(u0))
        width = int(math.ceil(u1) - col0 + 1)
        area += width * height
        # rectified pixel -> normal photo vector (u, -w, -f) -> original photo vector -> pixel
        B = np.array([[1.0, 0.0, col0], [0.0, -1.0, -float(row0)], [0.0, 0.0, -fpx]])
        A = cam.K @ np.diag([-1.0, 1.0, 1.0])  # photo vector (x, y, z) -> pixel: K (x / -z, -y / -z, 1)
        H = A @ R.T @ N @ B
        H = H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H
        views.append(RectifiedView(cam, R.copy(), col0, width, height, H))
    if area > MAX_AREA_RATIO * area0:
        raise StereoError(f"the rectified photos would cover {area / area0:.1f} times the original area (limit "
                          f"{MAX_AREA_RATIO:g}): the pair is too convergent for a normal case")
    out = EpipolarRectification(N, float(fpx), float(row0), views[0], views[1],
                                np.array(base, dtype=np.float64).reshape(3), C1)
    logger.info("normal case: left %d x %d, right %d x %d, focal %.2f px", views[0].width, height,
                views[1].width, height, fpx)
    return out


def rectify_relative(ro, camera_left: Camera, camera_right: Camera | None = None, **kwargs) -> EpipolarRectification:
    """:func:`rectify_pair` from a relative orientation (``RelativeGeometry`` or ``RelativeOrientation``)."""
    try:
        R1, R2, B = ro.rotation_left, ro.rotation_right, ro.base
    except AttributeError as err:
        raise InvalidInputError(f"`ro` is not a relative orientation: {err}") from err
    return rectify_pair(camera_left, camera_right or camera_left, rotation_left=R1, rotation_right=R2, base=B,
                        **kwargs)


def rectify_exterior(eo_left, eo_right, camera_left: Camera, camera_right: Camera | None = None,
                     **kwargs) -> EpipolarRectification:
    """:func:`rectify_pair` from two exterior orientations (ground frame)."""
    try:
        C1, C2 = np.asarray(eo_left.position, float), np.asarray(eo_right.position, float)
        R1, R2 = eo_left.rotation, eo_right.rotation
    except AttributeError as err:
        raise InvalidInputError(f"not an exterior orientation: {err}") from err
    return rectify_pair(camera_left, camera_right or camera_left, rotation_left=R1, rotation_right=R2,
                        base=C2 - C1, centre_left=C1, **kwargs)


# ------------------------------------------------------------------ resampling
def _check_source(path: StrPath, cam: Camera) -> None:
    info = raster_info(path)
    if (info.width, info.height) != (cam.width, cam.height):
        raise InvalidInputError(f"raster {str(path)!r} is {info.width} x {info.height} px but the camera is "
                                f"{cam.width} x {cam.height} px")


def resample_view(
    rect: EpipolarRectification,
    which: str,
    src: StrPath,
    dst: StrPath,
    *,
    tile: int = 1024,
    interpolation: str = "cubic",
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Resample one photo into its normal-case geometry, window by window.

    The output is a tiled GeoTIFF without georeference (pixel grid of the rectified photo), with
    the source's bands and dtype and an internal mask (False where no source pixel maps). Memory:
    one output tile, its maps and the source window under it.

    Parameters
    ----------
    rect : EpipolarRectification
    which : {"left", "right"}
    src : path
        The original photo (size must equal the camera's).
    dst : path
        The file to write, as given (the caller stages it; it is replaced if it exists).
    tile : int
        Output tile side (multiple of 16).
    interpolation : {"nearest", "linear", "cubic"}
    progress : callable(done, total), optional

    Raises
    ------
    InvalidInputError
        Size mismatch, bad option.
    RasterIOError
        Unreadable source or unwritable destination.
    """
    interp = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}
    if interpolation not in interp:
        raise InvalidInputError(f"unknown interpolation {interpolation!r}; expected one of {list(interp)}")
    if not isinstance(tile, int) or tile < 16 or tile % 16:
        raise InvalidInputError(f"`tile` must be a multiple of 16, at least 16; got {tile!r}")
    v = rect.view(which)
    _check_source(src, v.camera)
    info = raster_info(src)
    windows = list(iter_windows(v.width, v.height, tile))
    pad = 3
    with WindowReader(src) as rd, ignore_not_georeferenced():
        with TiledWriter(dst, v.width, v.height, info.count, info.dtype, Affine.identity(), None,
                         MaskPolicy("mask"), tile=min(512, tile)) as wr:
            for k, (c0, r0, w, h) in enumerate(windows):
                mx, my = rect.source_maps(which, c0, r0, w, h)
                ok = (mx >= -0.5) & (my >= -0.5) & (mx <= info.width - 0.5) & (my <= info.height - 0.5)
                data = np.zeros((h, w, info.count), dtype=info.dtype)
                if ok.any():
                    x0 = max(int(math.floor(float(mx[ok].min()))) - pad, 0)
                    y0 = max(int(math.floor(float(my[ok].min()))) - pad, 0)
                    x1 = min(int(math.ceil(float(mx[ok].max()))) + pad + 1, info.width)
                    y1 = min(int(math.ceil(float(my[ok].max()))) + pad + 1, info.height)
                    img, valid = rd.read(x0, y0, x1 - x0, y1 - y0)
                    mxs, mys = mx - x0, my - y0
                    for b in range(info.count):
                        band = img[:, :, b]
                        work = band.astype(np.float32) if band.dtype not in (np.uint8, np.uint16, np.float32) \
                            else band
                        out = cv2.remap(work, mxs, mys, interp[interpolation], borderMode=cv2.BORDER_REPLICATE)
                        if np.dtype(info.dtype).kind in "ui":
                            lim = np.iinfo(np.dtype(info.dtype))
                            out = np.clip(np.rint(out), lim.min, lim.max) if out.dtype.kind == "f" else out
                        data[:, :, b] = out.astype(info.dtype)
                    if valid is not None:
                        vm = cv2.remap(valid.astype(np.uint8), mxs, mys, cv2.INTER_NEAREST, borderValue=0)
                        ok &= vm > 0
                    data[~ok] = 0
                wr.write(data, c0, r0, ok)
                if progress is not None:
                    progress(k + 1, len(windows))
    return Path(dst)


# ------------------------------------------------------------------ parallax
@dataclass(frozen=True, eq=False)
class ParallaxReport:
    """Vertical parallax of the tie points in the normal case.

    Attributes
    ----------
    geometric_px : (N,) float64
        ``row_right - row_left`` of the tie points mapped through the rectification (the relative
        orientation's residual parallax, seen in the rectified photos).
    measured_px : (N,) float64 or None
        ``row_right - row_left`` re-measured by least-squares matching in the resampled photos
        (NaN where the matching did not converge); None when not measured.
    disparity_px : (N,) float64
        ``col_left - col_right`` in the rectified photos.
    orientation_px : (N,) float64 or None
        The residual vertical parallax of the same points reported by the orientation the
        rectification was built from (pixels, sign of ``geometric_px``); None when not known.
    n_outliers : int
        Tie points left out as outliers of that orientation (not in the N above).
    n_unrefined : int
        Matches left out because least-squares matching had not refined them (not in the N above).
    """

    geometric_px: NDArray[np.float64]
    measured_px: NDArray[np.float64] | None
    disparity_px: NDArray[np.float64]
    orientation_px: NDArray[np.float64] | None = None
    n_outliers: int = 0
    n_unrefined: int = 0

    @property
    def n(self) -> int:
        """Tie points the figures are computed on."""
        return len(self.geometric_px)

    @property
    def rms_geometric_px(self) -> float:
        return float(np.sqrt(np.mean(self.geometric_px ** 2))) if len(self.geometric_px) else float("nan")

    @property
    def rms_orientation_px(self) -> float:
        if self.orientation_px is None or not len(self.orientation_px):
            return float("nan")
        return float(np.sqrt(np.mean(self.orientation_px ** 2)))

    @property
    def rms_measured_px(self) -> float:
        if self.measured_px is None:
            return float("nan")
        m = self.measured_px[np.isfinite(self.measured_px)]
        return float(np.sqrt(np.mean(m ** 2))) if len(m) else float("nan")

    @property
    def n_measured(self) -> int:
        return 0 if self.measured_px is None else int(np.isfinite(self.measured_px).sum())

    def summary_line(self) -> str:
        left_out = []
        if self.n_outliers:
            left_out.append(f"{self.n_outliers} outliers of the orientation")
        if self.n_unrefined:
            left_out.append(f"{self.n_unrefined} unrefined matches")
        s = f"vertical parallax of {len(self.geometric_px)} tie points in the normal case"
        if left_out:
            s += " (" + " and ".join(left_out) + " left out)"
        s += f": RMS {self.rms_geometric_px:.3f} px (mapped"
        if self.orientation_px is not None:
            s += f"; the orientation's own residual {self.rms_orientation_px:.3f} px"
        s += ")"
        if self.measured_px is not None:
            s += f", {self.rms_measured_px:.3f} px (re-measured by LSM in the resampled photos, n={self.n_measured})"
        return s


def _read_rect(path: StrPath, c0: int, r0: int, w: int, h: int) -> NDArray[np.float32]:
    """Grey float32 window of a rectified photo, NaN where invalid (clipped to the raster)."""
    with WindowReader(path) as rd:
        x0, y0 = max(c0, 0), max(r0, 0)
        x1, y1 = min(c0 + w, rd.width), min(r0 + h, rd.height)
        out = np.full((h, w), np.nan, np.float32)
        if x1 <= x0 or y1 <= y0:
            return out
        data, valid = rd.read(x0, y0, x1 - x0, y1 - y0)
        g = data.astype(np.float32).mean(axis=2)
        if valid is not None:
            g[~valid] = np.nan
        out[y0 - r0:y1 - r0, x0 - c0:x1 - c0] = g
    return out


def tie_parallax(rect: EpipolarRectification, tie_left: ArrayLike, tie_right: ArrayLike, *,
                 left_path: StrPath | None = None, right_path: StrPath | None = None, tile: int = 512,
                 lsm_radius_px: int | None = None, orientation_px: ArrayLike | None = None,
                 n_outliers: int = 0, n_unrefined: int = 0) -> ParallaxReport:
    """Vertical parallax of tie points after the normal-case resampling.

    The tie points are mapped through the rectification; with the resampled photos given, each
    right position is also re-measured by least-squares matching (:mod:`rectify.features.lsm`, shift and
    affine shape) in the resampled photos, tile by tile, so the figure includes the resampling.
    The re-measurement uses the window of the matcher's LSM (``LsmConfig().radius_px``, 10 px) by
    default: the tie points were measured with it, and another window measures another point
    where the relief varies inside it (on the NGI pair a 12-px window moves the right rows by
    0.09 px RMS already in the original photos).

    ``orientation_px``, ``n_outliers`` and ``n_unrefined`` are carried into the report (see
    :class:`ParallaxReport`).
    """
    tl, tr = as_pair(tie_left, tie_right, names=("tie_left", "tie_right"))
    if len(tl) == 0:
        raise InvalidInputError("no tie points given (0 rows)")
    oq = None
    if orientation_px is not None:
        oq = np.asarray(orientation_px, dtype=np.float64).reshape(-1)
        if oq.shape != (len(tl),):
            raise ShapeError(f"`orientation_px` must have one value per tie point ({len(tl)}); got {oq.shape}",
                             actual_shape=oq.shape, expected_shape=(len(tl),))
    pl = rect.rectified_from_original("left", tl)
    pr = rect.rectified_from_original("right", tr)
    geo = pr[:, 1] - pl[:, 1]
    disp = pl[:, 0] - pr[:, 0]
    measured = None
    if left_path is not None and right_path is not None:
        measured = np.full(len(pl), np.nan)
        r = int(LsmConfig().radius_px if lsm_radius_px is None else lsm_radius_px)
        cfg = LsmConfig(radius_px=r, max_shift_px=1.0, min_corr=0.7)
        keys = np.floor(pl / tile).astype(np.int64)
        for key in np.unique(keys, axis=0):
            idx = np.flatnonzero((keys == key).all(axis=1))
            lc0, lr0 = int(key[0] * tile) - 2 * r, int(key[1] * tile) - 2 * r
            L = _read_rect(left_path, lc0, lr0, tile + 4 * r, tile + 4 * r)
            q = pr[idx]
            rc0 = int(math.floor(q[:, 0].min())) - 2 * r
            rr0 = int(math.floor(q[:, 1].min())) - 2 * r
            rw = int(math.ceil(q[:, 0].max())) - rc0 + 2 * r + 1
            rh = int(math.ceil(q[:, 1].max())) - rr0 + 2 * r + 1
            Rw = _read_rect(right_path, rc0, rr0, rw, rh)
            res = refine_matches(L, Rw, pl[idx] - [lc0, lr0], q - [rc0, rr0], config=cfg)
            ok = res.converged
            measured[idx[ok]] = res.right[ok, 1] + rr0 - pl[idx[ok], 1]
    return ParallaxReport(geo, measured, disp, oq, int(n_outliers), int(n_unrefined))
