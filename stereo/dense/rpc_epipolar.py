"""Local epipolar resampling of an RPC (pushbroom) pair by affine camera approximation.

A pushbroom image has no global epipolar geometry, but over a small tile (a few hundred pixels)
each RPC is very close to an *affine camera*: ``pixel = M @ X + t`` with ``X`` the ground point in
a local frame. Two affine cameras have an affine fundamental matrix (the epipolar lines are
parallel in each image), so a similarity of each image turns the epipolar lines of the tile into
rows, as satellite stereo pipelines do (s2p, de Franchis et al. 2014).

Per tile:

1. :func:`fit_affine_camera`: the least-squares affine camera of each RPC over the tile's ground
   footprint (a grid of tile pixels localised at a few heights of the tile's height range); its
   fit residual is reported.
2. :func:`affine_fundamental`: the constraint ``a xl + b yl + c xr + d yr + e = 0`` of the two
   affine cameras (the left null vector of the stacked 4 x 3 matrices).
3. :func:`rectify_affine`: a rotation of the left image and a similarity of the right one so that
   corresponding points share their rectified row; disparity ``d = x_left - x_right`` grows with
   the height and is 0 at the tile centre at the middle height.
4. :meth:`AffineRectification.with_tie_points`: the RPCs' relative pointing error (s2p's
   "pointing correction") as a row shift of the right image, the median vertical parallax of the
   tile's tie points; :class:`TileParallax` reports their residual parallax after it.
5. :func:`resample_rectified`: a window of the rectified frame read from the original raster
   (by a window of it) with bicubic interpolation, and its validity mask.

Coordinates: pixels are (N, 2) (col, row), pixel centres at integers (see :mod:`rectify.geometry.rpc`). The
local ground frame (:class:`LocalFrame`) is a linear function of (lon, lat, h) in metres, so an
affine camera in it is an affine camera in (lon, lat, h).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.raster.io import read_window

__all__ = ["AffineCamera", "AffineRectification", "LocalFrame", "TileParallax", "affine_fundamental",
           "fit_affine_camera", "fit_affine_pair", "rectify_affine", "resample_rectified", "tile_parallax"]

#: metres per degree of latitude (sphere of the WGS 84 semi-major axis; only the frame's scale)
_M_PER_DEG = math.pi / 180.0 * 6378137.0


def _pixels(p: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(p, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == 2:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 2:
        raise ShapeError(f"`{name}` must be (N, 2) (col, row); got shape {np.shape(p)}", actual_shape=np.shape(p),
                         expected_shape=(None, 2))
    return a


@dataclass(frozen=True)
class LocalFrame:
    """A local metric frame: ``E = (lon - lon0) cos(lat0) m``, ``N = (lat - lat0) m``, ``U = h - h0``.

    Linear in (lon, lat, h) (``m`` metres per degree), so affine models in it are affine in
    (lon, lat, h); it only conditions the least squares.
    """

    lon0: float
    lat0: float
    h0: float

    def to_local(self, g: ArrayLike) -> NDArray[np.float64]:
        a = np.asarray(g, dtype=np.float64).reshape(-1, 3)
        c = math.cos(math.radians(self.lat0))
        return np.column_stack([(a[:, 0] - self.lon0) * c * _M_PER_DEG, (a[:, 1] - self.lat0) * _M_PER_DEG,
                                a[:, 2] - self.h0])

    def to_ground(self, xyz: ArrayLike) -> NDArray[np.float64]:
        a = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        c = math.cos(math.radians(self.lat0))
        return np.column_stack([self.lon0 + a[:, 0] / (c * _M_PER_DEG), self.lat0 + a[:, 1] / _M_PER_DEG,
                                a[:, 2] + self.h0])


@dataclass(frozen=True, eq=False)
class AffineCamera:
    """``pixel = matrix @ X + offset`` for ``X`` in ``frame`` (local metres).

    Attributes
    ----------
    matrix : (2, 3) float64
    offset : (2,) float64
    frame : LocalFrame
    fit_rms_px, fit_max_px : float
        Residuals of the fit against the RPC at the sampled points.
    """

    matrix: NDArray[np.float64]
    offset: NDArray[np.float64]
    frame: LocalFrame
    fit_rms_px: float = 0.0
    fit_max_px: float = 0.0

    def project(self, ground: ArrayLike) -> NDArray[np.float64]:
        """Ground (lon, lat, h) (N, 3) -> pixels (N, 2)."""
        return self.project_local(self.frame.to_local(ground))

    def project_local(self, xyz: ArrayLike) -> NDArray[np.float64]:
        return np.asarray(xyz, dtype=np.float64).reshape(-1, 3) @ self.matrix.T + self.offset

    @property
    def gsd_m(self) -> float:
        """Ground sampling distance (m per pixel) on the horizontal plane: the mean of the singular
        values' inverses of the horizontal 2 x 2 part."""
        s = np.linalg.svd(self.matrix[:, :2], compute_uv=False)
        return float(np.mean(1.0 / s)) if s.min() > 0 else float("nan")


def fit_affine_camera(rpc: Any, window: tuple[float, float, float, float], heights: tuple[float, float], *,
                      frame: LocalFrame | None = None, n: int = 7, n_heights: int = 3) -> AffineCamera:
    """The least-squares affine camera of ``rpc`` over a window of its image and a height range.

    Parameters
    ----------
    rpc : RPC or RPCRefinement (``project`` and ``localize``)
    window : (col0, row0, width, height)
        Pixels of the image; an ``n`` x ``n`` grid of them is localised at ``n_heights`` heights.
    heights : (h_min, h_max)
        Metres above the ellipsoid; a range narrower than 10 m is widened to 10 m about its middle
        (the fit needs to see the height direction).
    frame : LocalFrame, optional
        Default: the window centre localised at the middle height.

    Raises
    ------
    InvalidInputError
        A window or height range that is not finite or empty.
    EstimationError
        Too few grid points could be localised.
    """
    (c0, r0, w, h), (lo, hi) = _check_window(window, heights, n, n_heights)
    g, frame = _footprint(rpc, (c0, r0, w, h), (lo, hi), frame, n, n_heights)
    return _fit_on_ground(rpc, g, frame)


def _check_window(window: tuple[float, float, float, float], heights: tuple[float, float], n: int,
                  n_heights: int) -> tuple[tuple[float, float, float, float], tuple[float, float]]:
    c0, r0, w, h = (float(v) for v in window)
    if not all(math.isfinite(v) for v in (c0, r0, w, h)) or w <= 0 or h <= 0:
        raise InvalidInputError(f"affine camera window must be finite with a positive size; got {window!r}")
    lo, hi = (float(v) for v in heights)
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
        raise InvalidInputError(f"height range must be finite with min <= max; got {heights!r}")
    if n < 2 or n_heights < 2:
        raise InvalidInputError(f"the affine fit needs n >= 2 and n_heights >= 2; got n={n}, n_heights={n_heights}")
    if hi - lo < 10.0:
        mid = 0.5 * (lo + hi)
        lo, hi = mid - 5.0, mid + 5.0
    return (c0, r0, w, h), (lo, hi)


def _footprint(rpc: Any, window: tuple[float, float, float, float], heights: tuple[float, float],
               frame: LocalFrame | None, n: int, n_heights: int) -> tuple[NDArray[np.float64], LocalFrame]:
    """Ground points of an n x n pixel grid of ``window`` at ``n_heights`` heights, and the frame."""
    c0, r0, w, h = window
    lo, hi = heights
    cc, rr = np.meshgrid(np.linspace(c0, c0 + w - 1, n), np.linspace(r0, r0 + h - 1, n))
    px = np.column_stack([cc.ravel(), rr.ravel()])
    g = np.vstack([rpc.localize(px, hh, on_failure="nan") for hh in np.linspace(lo, hi, n_heights)])
    ok = np.isfinite(g).all(axis=1)
    if ok.sum() < 8:
        raise EstimationError(f"affine camera of window {window!r}: only {int(ok.sum())} grid points could be "
                              "localised (is the window inside the image and the height range valid?)")
    g = g[ok]
    if frame is None:
        gc = rpc.localize(np.array([[c0 + (w - 1) / 2, r0 + (h - 1) / 2]]), 0.5 * (lo + hi), on_failure="nan")
        gc = gc[0] if np.isfinite(gc).all() else g.mean(axis=0)
        frame = LocalFrame(float(gc[0]), float(gc[1]), float(0.5 * (lo + hi)))
    return g, frame


def _fit_on_ground(rpc: Any, g: NDArray[np.float64], frame: LocalFrame) -> AffineCamera:
    X = frame.to_local(g)
    p = np.asarray(rpc.project(g), dtype=np.float64)
    A = np.column_stack([X, np.ones(len(X))])
    sol, *_ = np.linalg.lstsq(A, p, rcond=None)
    res = np.hypot(*(A @ sol - p).T)
    return AffineCamera(sol[:3].T.copy(), sol[3].copy(), frame, float(np.sqrt(np.mean(res ** 2))),
                        float(res.max()))


def fit_affine_pair(left_rpc: Any, right_rpc: Any, window: tuple[float, float, float, float],
                    heights: tuple[float, float], *, n: int = 7, n_heights: int = 3
                    ) -> tuple[AffineCamera, AffineCamera]:
    """Affine cameras of both RPCs fitted on the same ground points: the footprint of a window of the
    *left* image over a height range (see :func:`fit_affine_camera`), in one local frame."""
    win, hr = _check_window(window, heights, n, n_heights)
    g, frame = _footprint(left_rpc, win, hr, None, n, n_heights)
    return _fit_on_ground(left_rpc, g, frame), _fit_on_ground(right_rpc, g, frame)


def affine_fundamental(left: AffineCamera, right: AffineCamera) -> NDArray[np.float64]:
    """The affine epipolar constraint ``a xl + b yl + c xr + d yr + e = 0`` as (a, b, c, d, e).

    Normalised so that ``hypot(a, b) = 1``. As a 3 x 3 fundamental matrix (``xr.T F xl = 0``):
    ``[[0, 0, c], [0, 0, d], [a, b, e]]``.

    Raises
    ------
    InvalidInputError
        The cameras are in different local frames.
    EstimationError
        Degenerate cameras (no stereo: the stacked matrix has rank < 3, or an image has no epipolar
        direction).
    """
    if left.frame != right.frame:
        raise InvalidInputError(f"affine cameras in different local frames: {left.frame} and {right.frame}")
    A = np.vstack([left.matrix, right.matrix])
    U, s, _ = np.linalg.svd(A)
    if s[2] <= 1e-9 * s[0]:
        raise EstimationError(f"affine cameras are degenerate (singular values {s.tolist()}): no stereo geometry")
    nvec = U[:, 3]
    e = -float(nvec @ np.concatenate([left.offset, right.offset]))
    f = np.array([nvec[0], nvec[1], nvec[2], nvec[3], e])
    sl, sr = math.hypot(f[0], f[1]), math.hypot(f[2], f[3])
    if sl < 1e-12 * max(sr, 1.0) or sr < 1e-12 * max(sl, 1.0):
        raise EstimationError("affine epipolar geometry is degenerate: an image has no epipolar direction")
    return f / sl


def _similarity(a: float, b: float, tx: float, ty: float) -> NDArray[np.float64]:
    """The 2 x 3 rotation-scale ``x' = b x - a y + tx``, ``y' = a x + b y + ty``."""
    return np.array([[b, -a, tx], [a, b, ty]], dtype=np.float64)


def _apply(S: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    return p @ S[:, :2].T + S[:, 2]


def _invert(S: NDArray[np.float64]) -> NDArray[np.float64]:
    Mi = np.linalg.inv(S[:, :2])
    return np.column_stack([Mi, -Mi @ S[:, 2]])


@dataclass(frozen=True, eq=False)
class AffineRectification:
    """Similarities of the left and right images that make the tile's epipolar lines rows.

    ``rectified = S[:, :2] @ original + S[:, 2]``; corresponding points share their rectified row
    and ``d = x_left - x_right`` grows with the height (0 at the tile centre at the middle height,
    before any tie-point correction).

    Attributes
    ----------
    left, right : (2, 3) float64
        The similarities (the left one is a rotation: the left pixel size is kept).
    fundamental : (5,) float64
        ``(a, b, c, d, e)`` of :func:`affine_fundamental`.
    cameras : (AffineCamera, AffineCamera)
    row_shift_px : float
        Row shift added to the right image by :meth:`with_tie_points` (the pointing correction).
    disparity_per_m : float
        d(disparity)/d(height), px per metre (from the affine cameras).
    """

    left: NDArray[np.float64]
    right: NDArray[np.float64]
    fundamental: NDArray[np.float64]
    cameras: tuple[AffineCamera, AffineCamera]
    row_shift_px: float = 0.0
    disparity_per_m: float = 0.0

    def matrix(self, side: str) -> NDArray[np.float64]:
        if side == "left":
            return self.left
        if side == "right":
            return self.right
        raise InvalidInputError(f"side must be 'left' or 'right'; got {side!r}")

    def rectified_from_original(self, side: str, pixels: ArrayLike) -> NDArray[np.float64]:
        """Original pixels (N, 2) of ``side`` -> rectified (N, 2)."""
        return _apply(self.matrix(side), _pixels(pixels, "pixels"))

    def original_from_rectified(self, side: str, pixels: ArrayLike) -> NDArray[np.float64]:
        """Rectified pixels (N, 2) of ``side`` -> original (N, 2)."""
        return _apply(_invert(self.matrix(side)), _pixels(pixels, "pixels"))

    def vertical_parallax(self, left: ArrayLike, right: ArrayLike) -> NDArray[np.float64]:
        """``row_right - row_left`` in the rectified frame of corresponding original pixels (N,)."""
        pl, pr = _pixels(left, "left"), _pixels(right, "right")
        if len(pl) != len(pr):
            raise ShapeError(f"`left` ({len(pl)}) and `right` ({len(pr)}) must have the same length",
                             actual_shape=pr.shape, expected_shape=pl.shape)
        return _apply(self.right, pr)[:, 1] - _apply(self.left, pl)[:, 1]

    def disparity(self, left: ArrayLike, right: ArrayLike) -> NDArray[np.float64]:
        """``x_left - x_right`` in the rectified frame of corresponding original pixels (N,)."""
        return _apply(self.left, _pixels(left, "left"))[:, 0] - _apply(self.right, _pixels(right, "right"))[:, 0]

    def shifted(self, row_shift_px: float) -> AffineRectification:
        """The same rectification with the right image moved by ``row_shift_px`` more rows."""
        S = self.right.copy()
        S[1, 2] += float(row_shift_px)
        return replace(self, right=S, row_shift_px=self.row_shift_px + float(row_shift_px))

    def with_tie_points(self, left: ArrayLike, right: ArrayLike, *, reject_px: float = 3.0
                        ) -> tuple[AffineRectification, TileParallax]:
        """Correct the relative pointing error with tie points: the right image moves by the median
        vertical parallax (of the points within ``reject_px`` of it, iterated once).

        Returns the corrected rectification and the tie points' parallax before and after.

        Raises
        ------
        EstimationError
            No tie points.
        """
        pl, pr = _pixels(left, "left"), _pixels(right, "right")
        if len(pl) == 0:
            raise EstimationError("no tie points to correct the pointing error of the tile")
        q = self.vertical_parallax(pl, pr)
        med = float(np.median(q))
        keep = np.abs(q - med) <= reject_px
        if keep.any():
            med = float(np.median(q[keep]))
            keep = np.abs(q - med) <= reject_px
        out = self.shifted(-med)
        return out, tile_parallax(out, pl, pr, before=q, keep=keep)

    def to_dict(self) -> dict[str, Any]:
        cl, cr = self.cameras
        return {"left": self.left.tolist(), "right": self.right.tolist(), "fundamental": self.fundamental.tolist(),
                "row_shift_px": self.row_shift_px, "disparity_per_m": self.disparity_per_m,
                "affine_fit_rms_px": [cl.fit_rms_px, cr.fit_rms_px],
                "affine_fit_max_px": [cl.fit_max_px, cr.fit_max_px]}


@dataclass(frozen=True, eq=False)
class TileParallax:
    """Vertical parallax (``row_right - row_left``, rectified) of a tile's tie points.

    Attributes
    ----------
    before_px : (N,) float64
        With the RPCs alone (the affine epipolar geometry, no correction).
    after_px : (N,) float64
        After the pointing correction.
    keep : (N,) bool
        Tie points within the rejection threshold (the others are matching blunders).
    """

    before_px: NDArray[np.float64]
    after_px: NDArray[np.float64]
    keep: NDArray[np.bool_]

    @staticmethod
    def _rms(a: NDArray[np.float64]) -> float:
        return float(np.sqrt(np.mean(a ** 2))) if len(a) else float("nan")

    @property
    def n(self) -> int:
        return int(self.keep.sum())

    @property
    def rms_before_px(self) -> float:
        return self._rms(self.before_px[self.keep])

    @property
    def rms_after_px(self) -> float:
        return self._rms(self.after_px[self.keep])

    @property
    def max_after_px(self) -> float:
        a = np.abs(self.after_px[self.keep])
        return float(a.max()) if len(a) else float("nan")

    @property
    def median_before_px(self) -> float:
        return float(np.median(self.before_px[self.keep])) if self.n else float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "n_rejected": int((~self.keep).sum()), "rms_before_px": self.rms_before_px,
                "median_before_px": self.median_before_px, "rms_after_px": self.rms_after_px,
                "max_after_px": self.max_after_px}


def tile_parallax(rect: AffineRectification, left: ArrayLike, right: ArrayLike, *,
                  before: NDArray[np.float64] | None = None, keep: NDArray[np.bool_] | None = None,
                  reject_px: float = 3.0) -> TileParallax:
    """The vertical parallax of tie points under ``rect`` (``before``: the uncorrected values)."""
    q = rect.vertical_parallax(left, right)
    b = q if before is None else np.asarray(before, dtype=np.float64)
    k = (np.abs(q - np.median(q)) <= reject_px) if keep is None and len(q) else \
        (np.ones(len(q), bool) if keep is None else np.asarray(keep, bool))
    return TileParallax(b, q, k)


def rectify_affine(left: AffineCamera, right: AffineCamera) -> AffineRectification:
    """Rectifying similarities of an affine camera pair (see :class:`AffineRectification`).

    The left image is rotated so that ``y' = a x + b y`` (its epipolar lines become rows, pixel size
    kept); the right one gets ``y' = -(c x + d y + e)``, hence the same row for every
    correspondence, with ``x'`` along its epipolar lines at the same scale. Both are turned by 180
    degrees if needed so that the disparity grows with the height, and the right one is shifted
    along the rows so that the tile centre at the middle height (the frame origin) has disparity 0.

    Raises
    ------
    EstimationError
        Degenerate cameras (see :func:`affine_fundamental`), or no disparity change with height.
    """
    f = affine_fundamental(left, right)
    a, b, c, d, e = (float(v) for v in f)
    Sl = _similarity(a, b, 0.0, 0.0)
    Sr = _similarity(-c, -d, 0.0, -e)
    # disparity change per metre of height: along the frame's up direction
    up = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pl, pr = left.project_local(up), right.project_local(up)
    dd = (_apply(Sl, pl)[1, 0] - _apply(Sl, pl)[0, 0]) - (_apply(Sr, pr)[1, 0] - _apply(Sr, pr)[0, 0])
    if not math.isfinite(dd) or abs(dd) < 1e-9:
        raise EstimationError("affine cameras give no disparity change with height: no stereo (zero base?)")
    if dd < 0:
        Sl, Sr, dd = -Sl, -Sr, -dd
    # disparity 0 at the frame origin
    xl, xr = _apply(Sl, pl[:1])[0, 0], _apply(Sr, pr[:1])[0, 0]
    Sr[0, 2] -= xr - xl
    return AffineRectification(Sl, Sr, f, (left, right), 0.0, float(dd))


def resample_rectified(path: str | Path, S: NDArray[np.float64], col0: int, row0: int, width: int, height: int, *,
                       band: int = 1, interpolation: str = "cubic") -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """A ``width`` x ``height`` window of the rectified image (its top-left pixel at rectified (col0, row0)).

    Reads only the window of the original raster under it (plus a 3 px margin); rectified pixels
    outside the raster or on its nodata are invalid.

    Returns
    -------
    data : (height, width) float32 (0 where invalid)
    valid : (height, width) bool
    """
    if width <= 0 or height <= 0:
        raise InvalidInputError(f"rectified window size must be positive; got {width} x {height}")
    flags = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}
    if interpolation not in flags:
        raise InvalidInputError(f"unknown interpolation {interpolation!r}; expected one of {list(flags)}")
    Si = _invert(np.asarray(S, dtype=np.float64))
    xx, yy = np.meshgrid(np.arange(col0, col0 + width, dtype=np.float64),
                         np.arange(row0, row0 + height, dtype=np.float64))
    ox = Si[0, 0] * xx + Si[0, 1] * yy + Si[0, 2]
    oy = Si[1, 0] * xx + Si[1, 1] * yy + Si[1, 2]
    m = 3
    c0, r0 = int(math.floor(ox.min())) - m, int(math.floor(oy.min())) - m
    c1, r1 = int(math.ceil(ox.max())) + m, int(math.ceil(oy.max())) + m
    data, valid = read_window(path, c0, r0, c1 - c0 + 1, r1 - r0 + 1, bands=[band])
    src = data[:, :, 0].astype(np.float32)
    mx = (ox - c0).astype(np.float32)
    my = (oy - r0).astype(np.float32)
    out = np.asarray(cv2.remap(src, mx, my, flags[interpolation], borderMode=cv2.BORDER_CONSTANT, borderValue=0),
                     dtype=np.float32)
    # valid where every source pixel of the cubic kernel is valid
    inval = np.asarray((~valid).astype(np.uint8))
    if interpolation != "nearest":
        inval = np.asarray(cv2.dilate(inval, np.ones((3, 3) if interpolation == "linear" else (5, 5), np.uint8)),
                           dtype=np.uint8)
    v = np.asarray(cv2.remap(inval, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=1) == 0,
                   dtype=bool)
    out[~v] = 0
    return out, v
