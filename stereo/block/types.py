"""The data every block step shares: image poses and multi-image tie-point tracks.

Frames
------
ground
    A right-handed Cartesian frame (a projected map CRS with heights, or a local/topocentric
    frame), metres. Poses, points, control and GNSS positions are all in it.
photo
    Millimetres from the principal point, x right, y up; the projection centre at (0, 0, +f),
    so an image point is the vector (x, y, -f) (see :mod:`rectify.geometry.camera`).
pixel
    (N, 2) float64, x = column right, y = row down, pixel centres at integers.

A pose's ``rotation`` takes a photo vector (x, y, -f) into the ground frame
(R = Rx(omega) Ry(phi) Rz(kappa), :mod:`rectify.geometry.rotation`), so a ground point P projects by
``p = R.T @ (P - C); x = x0 - f p0 / p2; y = y0 - f p1 / p2`` and then through the camera's
distortion to pixels (:meth:`rectify.geometry.camera.Camera.pixel_from_photo`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import angles_from_matrix, check_rotation

__all__ = ["Pose", "Tracks", "cameras_for", "project_pixel"]


@dataclass(frozen=True, eq=False)
class Pose:
    """Exterior orientation of one image of a block.

    Parameters
    ----------
    image : str
        The image's name (its id in the block; unique).
    camera : str
        Id of the camera (interior orientation) the image was taken with.
    position : (3,) float64
        Projection centre, ground frame, metres.
    rotation : (3, 3) float64
        Photo vector (x, y, -f) -> ground frame.
    """

    image: str
    camera: str
    position: NDArray[np.float64]
    rotation: NDArray[np.float64]

    def __post_init__(self) -> None:
        if not isinstance(self.image, str) or not self.image:
            raise InvalidInputError(f"a pose needs a non-empty image name; got {self.image!r}")
        if not isinstance(self.camera, str) or not self.camera:
            raise InvalidInputError(f"pose of {self.image!r}: camera id must be a non-empty string; "
                                    f"got {self.camera!r}")
        pos = np.array(self.position, dtype=np.float64, copy=True).reshape(-1)
        if pos.shape != (3,) or not np.isfinite(pos).all():
            raise ShapeError(f"pose of {self.image!r}: `position` must be 3 finite numbers; got {pos.tolist()}")
        R = np.array(check_rotation(self.rotation, f"rotation of {self.image!r}"), dtype=np.float64, copy=True)
        pos.flags.writeable = False
        R.flags.writeable = False
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "rotation", R)

    @property
    def angles(self) -> NDArray[np.float64]:
        """(omega, phi, kappa), rad."""
        return angles_from_matrix(self.rotation, "omega-phi-kappa")

    def photo_from_ground(self, camera: Camera, ground: ArrayLike) -> NDArray[np.float64]:
        """Ground points (N, 3) -> ideal photo coordinates (N, 2), mm (no distortion).

        Points behind the camera (p2 >= 0) come out as NaN.
        """
        P = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        p = (P - self.position) @ self.rotation
        f = camera.focal_length_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]])
        out[p[:, 2] >= 0] = np.nan
        return out

    def pixel_from_ground(self, camera: Camera, ground: ArrayLike) -> NDArray[np.float64]:
        """Ground points (N, 3) -> pixels (N, 2), distortion applied; NaN behind the camera."""
        return project_pixel(camera, self, ground)


def project_pixel(camera: Camera, pose: Pose, ground: ArrayLike) -> NDArray[np.float64]:
    """Project ground points (N, 3) through ``pose`` and ``camera`` to pixels (N, 2).

    The photo coordinates are taken relative to the principal point, so the camera's
    principal point and distortion are applied by :meth:`Camera.pixel_from_photo`.
    """
    mm = pose.photo_from_ground(camera, ground)
    out = np.full_like(mm, np.nan)
    ok = np.isfinite(mm).all(axis=1)
    if ok.any():
        out[ok] = camera.pixel_from_photo(mm[ok])
    return out


@dataclass(frozen=True, eq=False)
class Tracks:
    """Multi-image tie points: each track is one ground point seen in two or more images.

    Observations are stored flat (one row per image measurement), sorted by track.

    Parameters
    ----------
    images : tuple of str
        Image names of the block, in block order; ``obs_image`` indexes this.
    point_ids : tuple of str
        One id per track (P tracks); ``obs_point`` indexes this.
    obs_point : (M,) int64
        Track index of each observation.
    obs_image : (M,) int64
        Image index of each observation.
    obs_pixel : (M, 2) float64
        Measured pixel coordinates (x = column, y = row) in that image.
    obs_sigma_px : (M,) float64
        A-priori standard deviation of each measurement (both coordinates), pixels.
    """

    images: tuple[str, ...]
    point_ids: tuple[str, ...]
    obs_point: NDArray[np.int64]
    obs_image: NDArray[np.int64]
    obs_pixel: NDArray[np.float64]
    obs_sigma_px: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        images = tuple(str(s) for s in self.images)
        ids = tuple(str(s) for s in self.point_ids)
        if len(set(images)) != len(images):
            raise InvalidInputError(f"tracks: duplicate image names {sorted(_dupes(images))[:5]}")
        if len(set(ids)) != len(ids):
            raise InvalidInputError(f"tracks: duplicate point ids {sorted(_dupes(ids))[:5]}")
        pt = np.array(self.obs_point, dtype=np.int64, copy=True).reshape(-1)
        im = np.array(self.obs_image, dtype=np.int64, copy=True).reshape(-1)
        px = np.array(self.obs_pixel, dtype=np.float64, copy=True).reshape(-1, 2)
        m = len(pt)
        if len(im) != m or len(px) != m:
            raise ShapeError(f"tracks: obs_point, obs_image and obs_pixel must have one row per observation; "
                             f"got {m}, {len(im)} and {len(px)}")
        sig = np.array(self.obs_sigma_px, dtype=np.float64, copy=True).reshape(-1)
        if sig.size == 0:
            sig = np.ones(m)
        if len(sig) != m or not np.all(np.isfinite(sig)) or np.any(sig <= 0):
            raise InvalidInputError("tracks: obs_sigma_px must be one finite positive value per observation")
        if m and (pt.min() < 0 or pt.max() >= len(ids)):
            raise InvalidInputError(f"tracks: obs_point out of range 0..{len(ids) - 1}")
        if m and (im.min() < 0 or im.max() >= len(images)):
            raise InvalidInputError(f"tracks: obs_image out of range 0..{len(images) - 1}")
        if not np.isfinite(px).all():
            raise InvalidInputError("tracks: obs_pixel must be finite")
        key = pt * max(len(images), 1) + im
        if len(np.unique(key)) != m:
            raise InvalidInputError("tracks: a track holds two observations in one image")
        order = np.lexsort((im, pt))
        for a in (pt, im, px, sig):
            a.flags.writeable = False
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "point_ids", ids)
        object.__setattr__(self, "obs_point", pt[order])
        object.__setattr__(self, "obs_image", im[order])
        object.__setattr__(self, "obs_pixel", px[order])
        object.__setattr__(self, "obs_sigma_px", sig[order])

    @property
    def n_points(self) -> int:
        return len(self.point_ids)

    @property
    def n_obs(self) -> int:
        return len(self.obs_point)

    def rays_per_point(self) -> NDArray[np.int64]:
        """(P,) number of images that see each track."""
        return np.bincount(self.obs_point, minlength=self.n_points).astype(np.int64)

    def points_per_image(self) -> NDArray[np.int64]:
        """(n_images,) number of observations in each image."""
        return np.bincount(self.obs_image, minlength=len(self.images)).astype(np.int64)

    def subset(self, keep_obs: ArrayLike) -> Tracks:
        """The tracks restricted to the observations where ``keep_obs`` (M,) bool is True; tracks
        left with fewer than two observations are dropped, point ids are kept."""
        k = np.asarray(keep_obs, dtype=bool).reshape(-1)
        if k.shape != (self.n_obs,):
            raise ShapeError(f"keep_obs must have shape ({self.n_obs},); got {k.shape}")
        counts = np.bincount(self.obs_point[k], minlength=self.n_points)
        k = k & (counts[self.obs_point] >= 2)
        used = np.unique(self.obs_point[k])
        remap = np.full(self.n_points, -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        return Tracks(self.images, tuple(self.point_ids[i] for i in used), remap[self.obs_point[k]],
                      self.obs_image[k], self.obs_pixel[k], self.obs_sigma_px[k])


def cameras_for(poses: Sequence[Pose], cameras: Mapping[str, Camera]) -> list[Camera]:
    """The camera of each pose, in order; an unknown camera id is an error naming it."""
    out = []
    for p in poses:
        if p.camera not in cameras:
            raise InvalidInputError(f"image {p.image!r} names camera {p.camera!r}, which is not given "
                                    f"(cameras: {sorted(cameras)})")
        out.append(cameras[p.camera])
    return out


def _dupes(names: Sequence[str]) -> set[str]:
    seen: set[str] = set()
    return {n for n in names if n in seen or seen.add(n)}  # type: ignore[func-returns-value]
