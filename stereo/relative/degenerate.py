"""A pair without a base: identical photos, or photos taken from one point (a pure rotation).

Such a pair has no parallax: every ray of the right photo is a ray of the left photo turned by one
rotation, so the coplanarity condition holds for any base direction and relative orientation has
no answer (it would return an arbitrary base fitted to the noise). :func:`check_base` finds it
before the adjustment: it fits the rotation that best maps the right rays onto the left rays
(orthogonal Procrustes, the outliers trimmed twice) and measures what the rotation leaves over.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError

__all__ = ["rotation_residuals_px", "check_base", "NO_BASE_PX"]

#: median ray misfit (pixels) below which a rotation alone explains the pair: no base
NO_BASE_PX = 0.5


def _rays(xy: NDArray[np.float64], f: float) -> NDArray[np.float64]:
    r = np.column_stack([xy, np.full(len(xy), -f)])
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def rotation_residuals_px(left_mm: ArrayLike, right_mm: ArrayLike, focal_length_mm: float | tuple[float, float],
                          pixel_size_mm: float) -> NDArray[np.float64]:
    """Per point, the angle (in pixels at the principal distance) between the left ray and the right
    ray turned by the best-fitting rotation, (N,).

    The rotation is the orthogonal Procrustes solution on the unit rays, refitted twice on the 80 %
    of points with the smallest misfit (so a few gross mismatches do not hide a pure rotation).
    """
    lm = np.asarray(left_mm, dtype=np.float64).reshape(-1, 2)
    rm = np.asarray(right_mm, dtype=np.float64).reshape(-1, 2)
    if isinstance(focal_length_mm, tuple):
        f1, f2 = float(focal_length_mm[0]), float(focal_length_mm[1])
    else:
        f1 = f2 = float(focal_length_mm)
    a, b = _rays(lm, f1), _rays(rm, f2)
    keep = np.ones(len(a), dtype=bool)
    ang = np.zeros(len(a))
    for _ in range(3):
        u, _s, vt = np.linalg.svd(b[keep].T @ a[keep])
        d = np.sign(np.linalg.det(u @ vt)) or 1.0
        R = (u @ np.diag([1.0, 1.0, d]) @ vt).T  # R b ~ a
        ang = np.linalg.norm(a - b @ R.T, axis=1)
        keep = ang <= np.quantile(ang, 0.8) if len(a) >= 10 else keep
    return ang * f1 / float(pixel_size_mm)


def check_base(left_mm: ArrayLike, right_mm: ArrayLike, focal_length_mm: float | tuple[float, float],
               pixel_size_mm: float | None, *, threshold_px: float = NO_BASE_PX) -> None:
    """Raise when a rotation alone explains the pair (identical images or a pure rotation).

    Raises
    ------
    EstimationError
        ``no base: the images show no parallax ...`` with the median misfit in pixels.
    """
    lm = np.asarray(left_mm, dtype=np.float64).reshape(-1, 2)
    if len(lm) < 5:
        return
    ps = float(pixel_size_mm) if pixel_size_mm else 0.01
    res = rotation_residuals_px(lm, right_mm, focal_length_mm, ps)
    med = float(np.median(res))
    if med < threshold_px:
        same = float(np.median(np.linalg.norm(lm - np.asarray(right_mm, dtype=np.float64).reshape(-1, 2), axis=1)))
        what = "identical images" if same / ps < threshold_px else "a pure rotation (photos taken from one point)"
        raise EstimationError(
            f"no base: the images show no parallax ({what}: one rotation maps the right rays onto the left "
            f"ones to a median of {med:.3f} px over {len(lm)} tie points); relative orientation needs two "
            "viewpoints")
