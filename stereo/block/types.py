"""The data every block step shares: image poses, multi-image tie-point tracks, control and GNSS.

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

__all__ = ["BlockControl", "CONTROL_KINDS", "GnssObservations", "Pose", "Tracks", "cameras_for", "project_pixel"]

F64 = NDArray[np.float64]

#: kinds of control point: all three coordinates, the height only, or the plan position only
CONTROL_KINDS: tuple[str, ...] = ("full", "height", "plan")


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


# ---------------------------------------------------------------------------- control and GNSS
@dataclass(frozen=True, eq=False)
class BlockControl:
    """Ground control and check points of a block.

    Parameters
    ----------
    ids : tuple of str
        Point ids (K,); each is a :class:`Tracks` point id.
    xyz : (K, 3) float64
        Given ground coordinates, m.
    kind : tuple of str
        Per point, one of :data:`CONTROL_KINDS` (``full``, ``height``, ``plan``).
    sigma_m : (K, 3) float64
        A-priori standard deviation of x, y, z, m (> 0; only the used components matter).
    check : (K,) bool
        True for a check point (withheld from the adjustment).
    """

    ids: tuple[str, ...]
    xyz: F64
    kind: tuple[str, ...] = ()
    sigma_m: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    check: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self) -> None:
        ids = tuple(str(i) for i in self.ids)
        k = len(ids)
        if len(set(ids)) != k:
            raise InvalidInputError(f"control: duplicate ids {sorted({i for i in ids if ids.count(i) > 1})[:5]}")
        xyz = np.array(self.xyz, dtype=np.float64, copy=True)
        if xyz.shape != (k, 3) or not np.isfinite(xyz).all():
            raise ShapeError(f"control: `xyz` must be ({k}, 3) finite; got shape {xyz.shape}",
                             actual_shape=xyz.shape, expected_shape=(k, 3))
        kind = tuple(self.kind) if len(self.kind) else ("full",) * k
        if len(kind) != k:
            raise ShapeError(f"control: `kind` must have {k} entries; got {len(kind)}")
        badk = [x for x in kind if x not in CONTROL_KINDS]
        if badk:
            raise InvalidInputError(f"control: unknown kind {badk[0]!r}; expected one of {list(CONTROL_KINDS)}")
        sig = np.array(self.sigma_m, dtype=np.float64, copy=True)
        if sig.size == 0:
            sig = np.full((k, 3), 0.01)
        if sig.shape == (k,):
            sig = np.repeat(sig[:, None], 3, axis=1)
        if sig.shape != (k, 3) or not np.isfinite(sig).all() or (sig <= 0).any():
            raise InvalidInputError(f"control: `sigma_m` must be ({k}, 3) finite values > 0; got "
                                    f"{np.asarray(self.sigma_m).tolist()!r}"[:200])
        chk = np.array(self.check, dtype=bool, copy=True).reshape(-1)
        if chk.size == 0:
            chk = np.zeros(k, bool)
        if chk.shape != (k,):
            raise ShapeError(f"control: `check` must have {k} entries; got {chk.shape}")
        for a in (xyz, sig, chk):
            a.flags.writeable = False
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "sigma_m", sig)
        object.__setattr__(self, "check", chk)

    def used_sigma(self) -> F64:
        """(K, 3) sigma of the observed components, inf elsewhere (and for check points)."""
        s = self.sigma_m.copy()
        for i, k in enumerate(self.kind):
            if k == "height":
                s[i, :2] = np.inf
            elif k == "plan":
                s[i, 2] = np.inf
        s[self.check] = np.inf
        return s


@dataclass(frozen=True, eq=False)
class GnssObservations:
    """GNSS antenna positions (and optional INS angles) of the images.

    Parameters
    ----------
    images : tuple of str
        Image names (n,).
    position : (n, 3) float64
        Antenna positions, ground frame, m.
    sigma_m : (n, 3) float64
        Their standard deviations, m (> 0).
    lever_arm_m : (3,) float64, optional
        Antenna offset from the projection centre in the camera frame (photo axes x, y, and z
        along the optical axis away from the scene), m: ``antenna = C + R @ lever``.
    angles : (n, 3) float64, optional
        INS omega, phi, kappa, rad.
    sigma_rad : (n, 3) float64, optional
        Their standard deviations, rad (required with ``angles``).
    covariance : (n, 3, 3) or (n, 6, 6) float64, optional
        Full covariance of each image's observation: of the position (m^2), or of the position and
        the angles (x, y, z, omega, phi, kappa; m and rad; needs ``angles``). Symmetric positive
        definite; it supersedes ``sigma_m``/``sigma_rad`` in the adjustment
        (:mod:`stereo.block.bundle.systematic`).
    time : (n,) float64, optional
        Exposure times, s (for a GNSS drift per strip).
    strip : tuple of str, optional
        The strip (or flight) of each image (for systematic unknowns per strip).
    """

    images: tuple[str, ...]
    position: F64
    sigma_m: F64
    lever_arm_m: F64 | None = None
    angles: F64 | None = None
    sigma_rad: F64 | None = None
    covariance: F64 | None = None
    time: F64 | None = None
    strip: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        images = tuple(str(i) for i in self.images)
        n = len(images)
        if len(set(images)) != n:
            raise InvalidInputError(f"gnss: duplicate images {sorted({i for i in images if images.count(i) > 1})[:5]}")
        pos = np.array(self.position, dtype=np.float64, copy=True)
        if pos.shape != (n, 3) or not np.isfinite(pos).all():
            raise ShapeError(f"gnss: `position` must be ({n}, 3) finite; got shape {pos.shape}")
        sig = np.array(self.sigma_m, dtype=np.float64, copy=True)
        if sig.shape == (n,):
            sig = np.repeat(sig[:, None], 3, axis=1)
        if sig.shape != (n, 3) or not np.isfinite(sig).all() or (sig <= 0).any():
            raise InvalidInputError(f"gnss: `sigma_m` must be ({n}, 3) finite values > 0; got "
                                    f"{np.asarray(self.sigma_m).tolist()!r}"[:200])
        lever = None
        if self.lever_arm_m is not None:
            lever = np.array(self.lever_arm_m, dtype=np.float64, copy=True).reshape(-1)
            if lever.shape != (3,) or not np.isfinite(lever).all():
                raise ShapeError(f"gnss: `lever_arm_m` must be 3 finite numbers; got {lever.tolist()}")
        ang = sang = None
        if self.angles is not None:
            ang = np.array(self.angles, dtype=np.float64, copy=True)
            if ang.shape != (n, 3) or not np.isfinite(ang).all():
                raise ShapeError(f"gnss: `angles` must be ({n}, 3) finite; got shape {ang.shape}")
            if self.sigma_rad is None:
                raise InvalidInputError("gnss: `angles` need `sigma_rad`; got None")
            sang = np.array(self.sigma_rad, dtype=np.float64, copy=True)
            if sang.shape == (n,):
                sang = np.repeat(sang[:, None], 3, axis=1)
            if sang.shape != (n, 3) or not np.isfinite(sang).all() or (sang <= 0).any():
                raise InvalidInputError(f"gnss: `sigma_rad` must be ({n}, 3) finite values > 0; got "
                                        f"{np.asarray(self.sigma_rad).tolist()!r}"[:200])
        elif self.sigma_rad is not None:
            raise InvalidInputError("gnss: `sigma_rad` given without `angles`")
        cov, tim, strip = _gnss_extras(n, self.covariance, self.time, self.strip, ang is not None)
        for a in (pos, sig, lever, ang, sang, cov, tim):
            if a is not None:
                a.flags.writeable = False
        object.__setattr__(self, "covariance", cov)
        object.__setattr__(self, "time", tim)
        object.__setattr__(self, "strip", strip)
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "sigma_m", sig)
        object.__setattr__(self, "lever_arm_m", lever)
        object.__setattr__(self, "angles", ang)
        object.__setattr__(self, "sigma_rad", sang)


def _gnss_extras(n: int, covariance: ArrayLike | None, time: ArrayLike | None, strip: Sequence[str] | None,
                 has_angles: bool) -> tuple[F64 | None, F64 | None, tuple[str, ...] | None]:
    """Validated ``covariance`` (n, 3, 3) / (n, 6, 6), ``time`` (n,) and ``strip`` of :class:`GnssObservations`."""
    cov = tim = None
    if covariance is not None:
        cov = np.array(covariance, dtype=np.float64, copy=True)
        k = cov.shape[-1] if cov.ndim == 3 else -1
        if cov.shape not in ((n, 3, 3), (n, 6, 6)):
            raise ShapeError(f"gnss: `covariance` must have shape ({n}, 3, 3) or ({n}, 6, 6); got {cov.shape}")
        if k == 6 and not has_angles:
            raise InvalidInputError("gnss: a (n, 6, 6) `covariance` needs `angles`")
        for i in range(n):
            c = cov[i]
            if not np.isfinite(c).all() or not np.allclose(c, c.T, rtol=1e-9, atol=0.0):
                raise InvalidInputError(f"gnss: the covariance of image {i} is not finite and symmetric: {c.tolist()}")
            if np.linalg.eigvalsh(c)[0] <= 1e-12 * max(float(np.max(np.abs(np.diag(c)))), 1e-300):
                raise InvalidInputError(f"gnss: the covariance of image {i} is not positive definite (eigenvalues "
                                        f"{np.linalg.eigvalsh(c).round(15).tolist()})")
    if time is not None:
        tim = np.array(time, dtype=np.float64, copy=True).reshape(-1)
        if tim.shape != (n,) or not np.isfinite(tim).all():
            raise InvalidInputError(f"gnss: `time` must be {n} finite numbers; got {np.asarray(time).tolist()!r}"[:200])
    out_strip = None
    if strip is not None:
        out_strip = tuple(str(s) for s in strip)
        if len(out_strip) != n or any(not s for s in out_strip):
            raise InvalidInputError(f"gnss: `strip` must be {n} non-empty labels; got {list(out_strip)[:5]}")
    return cov, tim, out_strip
