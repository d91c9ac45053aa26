"""Initial interior and exterior orientation with no initial guess.

Plane views: homographies (the project's :class:`Homography`) -> ``K`` by
:func:`.dlt.interior_from_homographies` -> each pose from its homography.
3D views: the DLT of each view, decomposed; the interior start is the median
of the views' projective interior orientations (skew dropped), and each pose
comes from its own DLT. Distortion starts at zero.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CalibrationError, EstimationError
from rectify.geometry.rotation import rotvec_from_matrix
from rectify.geometry.transforms import Homography
from stereo.calibration.dlt import DLT, interior_from_homographies, perspective_strength, pose_from_homography
from stereo.calibration.views import TargetView

logger = logging.getLogger(__name__)

__all__ = ["Start", "initial_orientation", "MIN_PERSPECTIVE"]

F64 = NDArray[np.float64]

#: Below this relative depth variation in every view, the principal distance is unobservable.
MIN_PERSPECTIVE = 0.005


@dataclass(frozen=True, eq=False)
class Start:
    """A start: interior vector (11,), poses (S, 6), how it was found, per-view DLT/homography figures."""

    interior: F64
    poses: F64
    method: str
    perspective: F64
    dlt_interiors: tuple = ()


def _plane_frame(X: F64) -> tuple[F64, F64, F64]:
    """Plane coordinates (N, 2) of coplanar points, with the plane's origin c and axes E (3, 3), det +1."""
    if np.allclose(X[:, 2], X[0, 2], atol=1e-12 * max(1.0, float(np.abs(X).max()))):
        c = np.array([0.0, 0.0, X[0, 2]])
        return X[:, :2].copy(), c, np.eye(3)
    c = X.mean(axis=0)
    _, _, vt = np.linalg.svd(X - c)
    E = vt.T.copy()
    if np.linalg.det(E) < 0:
        E[:, 2] = -E[:, 2]
    return (X - c) @ E[:, :2], c, E


def _homography(v: TargetView) -> tuple[F64, F64, F64, F64]:
    xy, c, E = _plane_frame(v.object_xyz)
    try:
        H = np.asarray(Homography.from_points(xy, v.pixel).matrix, dtype=np.float64)
    except EstimationError as err:
        raise CalibrationError(f"view {v.name!r}: no homography of the target plane: {err}") from err
    return H, xy, c, E


def _pose_plane(K: F64, H: F64, c: F64, E: F64) -> F64:
    Rp, tp = pose_from_homography(K, H)
    R = Rp @ E.T
    t = tp - R @ c
    return np.concatenate([rotvec_from_matrix(R), t])


def initial_orientation(views: Sequence[TargetView], width: int, height: int, *, equal_focal: bool = False
                        ) -> Start:
    """Start values for the adjustment, found without any guess.

    Raises
    ------
    CalibrationError
        When the principal distance is unobservable (every plane view parallel to
        the image plane) or a view has too few points.
    """
    planar = [v.is_planar for v in views]
    for v, pl in zip(views, planar, strict=True):
        need = 4 if pl else 6
        if v.n < need:
            raise CalibrationError(f"view {v.name!r} has {v.n} points; a {'plane' if pl else '3D'} view needs "
                                   f"at least {need}")
    hom = {i: _homography(v) for i, v in enumerate(views) if planar[i]}
    persp = np.full(len(views), np.nan)
    for i, (H, xy, _, _) in hom.items():
        persp[i] = perspective_strength(H, xy)
    dlts: dict[int, DLT] = {}
    for i, v in enumerate(views):
        if not planar[i]:
            try:
                dlts[i] = DLT.from_points(v.object_xyz, v.pixel)
            except EstimationError as err:
                raise CalibrationError(f"view {v.name!r}: {err}") from err
    if dlts:
        dec = {i: d.decompose() for i, d in dlts.items()}
        fx = float(np.median([d.fx for d in dec.values()]))
        fy = float(np.median([d.fy for d in dec.values()]))
        if equal_focal:
            fx = fy = (fx + fy) / 2
        cx = float(np.median([d.cx for d in dec.values()]))
        cy = float(np.median([d.cy for d in dec.values()]))
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        method = f"DLT ({len(dlts)} view{'s' if len(dlts) > 1 else ''})"
        for i in dec:
            persp[i] = np.inf
        dlt_int = tuple((views[i].name, dec[i]) for i in sorted(dec))
    else:
        if np.nanmax(persp) < MIN_PERSPECTIVE:
            raise CalibrationError(
                f"focal length unobservable: all {len(views)} views are parallel to the image plane "
                f"(largest depth variation over the target {100 * np.nanmax(persp):.2f}%); "
                "tilt the target by 20-45 deg in several views")
        K, how = interior_from_homographies([hom[i][0] for i in sorted(hom)], width, height, equal_focal=equal_focal)
        method = how
        dlt_int = ()
    poses = np.zeros((len(views), 6))
    for i in range(len(views)):
        if i in dlts:
            d = dlts[i].decompose()
            poses[i] = np.concatenate([rotvec_from_matrix(d.rotation_cv), d.translation_cv])
        else:
            H, _, c, E = hom[i]
            poses[i] = _pose_plane(K, H, c, E)
    interior = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0, 0, 0, 0, 0, K[0, 2], K[1, 2]], dtype=np.float64)
    logger.info("start (%s): fx %.2f fy %.2f cx %.2f cy %.2f", method, *interior[:4])
    return Start(interior, poses, method, persp, dlt_int)
