"""Views of several RPC images of one scene: viewing directions, intersection angles, overlap, the pairs.

The multi-view chain of ``stereo dense-rpc IMG1 IMG2 IMG3 ...`` (:mod:`stereo.actions.dense_rpc_multi`)
matches the reference image (the first) with each other image over the reference's region of interest
(as s2p does with its reference image) and fuses the pairs. Which pairs: this module measures, at the
scene centre,

- the **viewing direction** of each image: the unit vector (local east, north, up, :class:`LocalFrame`)
  from the ground point to the satellite, the direction of the line of sight through the pixel where the
  RPC sees the scene centre (the RPC localised at two heights ``dh`` apart);
- the **intersection angle** of two views: the angle between their viewing directions (the angle at
  which the two rays meet the ground point; the base-to-height ratio is about ``2 tan(angle / 2)``);
- the **overlap**: the share of the reference's region of interest (a 9 x 9 grid of its pixels localised
  at the scene height) that the other image sees.

A pair is kept when its angle lies in ``[min_angle_deg, max_angle_deg]`` (default 5-45 deg: below 5 deg
a pixel of disparity is more than about 11 ground pixels of height, above 45 deg the two images see
different faces of buildings and match poorly) and its overlap is at least ``min_overlap``.
Acquisition times are not used: the RPC files and GeoTIFF RPC tags carry none.

Units: degrees for angles and ground coordinates (lon, lat), metres for heights, pixels (col, row).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError, StereoError
from stereo.dense.rpc_epipolar import LocalFrame

__all__ = ["PairCandidate", "intersection_angle_deg", "roi_overlap", "select_rpc_pairs", "viewing_direction"]


def viewing_direction(rpc: Any, ground: Sequence[float], *, dh: float = 100.0) -> NDArray[np.float64]:
    """Unit vector (3,) from the ground point ``(lon, lat, h)`` towards the satellite, local east-north-up.

    The pixel where the RPC sees the point is localised again ``dh`` metres higher; the horizontal shift
    of the ray over that height gives its direction.
    """
    g = np.asarray(ground, dtype=np.float64).reshape(1, 3)
    if not np.isfinite(g).all():
        raise InvalidInputError(f"the scene centre must be finite (lon, lat, h); got {ground!r}")
    px = rpc.project(g)
    hi = rpc.localize(px, float(g[0, 2]) + dh, on_failure="nan")
    if not np.isfinite(hi).all():
        raise StereoError(f"the RPC {getattr(rpc, 'source', '')!r} cannot localise its own view of the scene centre "
                          f"(lon {g[0, 0]:.5f}, lat {g[0, 1]:.5f}, h {g[0, 2]:.0f} m)")
    frame = LocalFrame(float(g[0, 0]), float(g[0, 1]), float(g[0, 2]))
    v = frame.to_local(hi)[0] - frame.to_local(g)[0]
    return np.asarray(v / np.linalg.norm(v), dtype=np.float64)


def intersection_angle_deg(u: NDArray[np.float64], v: NDArray[np.float64]) -> float:
    """The angle between two viewing directions (unit vectors), degrees."""
    c = float(np.clip(np.dot(u, v), -1.0, 1.0))
    return math.degrees(math.acos(c))


def roi_overlap(ref_rpc: Any, other_rpc: Any, roi: tuple[int, int, int, int], other_size: tuple[int, int],
                height: float, *, n: int = 9) -> float:
    """Share of a ``n`` x ``n`` grid of the reference's ROI pixels, localised at ``height``, inside the other
    image (``other_size`` = (width, height) px)."""
    x, y, w, h = roi
    cc, rr = np.meshgrid(np.linspace(x, x + w - 1, n), np.linspace(y, y + h - 1, n))
    g = ref_rpc.localize(np.column_stack([cc.ravel(), rr.ravel()]), height, on_failure="nan")
    ok = np.isfinite(g).all(axis=1)
    if not ok.any():
        return 0.0
    p = other_rpc.project(g[ok])
    W, H = other_size
    inside = (p[:, 0] >= -0.5) & (p[:, 0] <= W - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= H - 0.5)
    return float(inside.sum() / len(g))


@dataclass(frozen=True)
class PairCandidate:
    """One candidate pair (reference ``left`` with ``right``, indexes of the images) and why it is kept or not."""

    left: int
    right: int
    angle_deg: float
    overlap: float
    kept: bool
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"left": self.left, "right": self.right, "angle_deg": self.angle_deg, "overlap": self.overlap,
                "kept": self.kept, "reason": self.reason}


def select_rpc_pairs(rpcs: Sequence[Any], sizes: Sequence[tuple[int, int]], roi: tuple[int, int, int, int],
                     centre: Sequence[float], *, reference: int = 0, min_angle_deg: float = 5.0,
                     max_angle_deg: float = 45.0, min_overlap: float = 0.5, max_pairs: int = 0,
                     names: Sequence[str] | None = None) -> list[PairCandidate]:
    """The candidate pairs of the reference image with every other image, each kept or not (module docstring).

    Parameters
    ----------
    rpcs, sizes : the N images' RPC models and (width, height) px.
    roi : (x, y, width, height) of the reference image, px.
    centre : (lon, lat, h) of the scene centre.
    reference : index of the reference image.
    min_angle_deg, max_angle_deg : the intersection angle range, degrees.
    min_overlap : the least share of the ROI the other image must see.
    max_pairs : keep at most this many passing pairs, those whose angle is nearest the middle of the range
        first (0: all).

    Returns
    -------
    list of PairCandidate, in image order (the reference's own entry left out).

    Raises
    ------
    InvalidInputError
        Bad ranges, sizes or reference index.
    StereoError
        No pair passes (the message lists each candidate's angle and overlap).
    """
    n = len(rpcs)
    names = list(names) if names is not None else [f"image {i + 1}" for i in range(n)]
    if len(sizes) != n or len(names) != n:
        raise InvalidInputError(f"one size and one name per RPC; got {n} RPCs, {len(sizes)} sizes, {len(names)} names")
    if not 0 <= reference < n:
        raise InvalidInputError(f"reference index {reference} outside 0..{n - 1}")
    if not (math.isfinite(min_angle_deg) and math.isfinite(max_angle_deg) and 0 <= min_angle_deg < max_angle_deg
            <= 90):
        raise InvalidInputError(f"the intersection angle range must satisfy 0 <= min < max <= 90 deg; got "
                                f"{min_angle_deg!r}..{max_angle_deg!r}")
    if not (math.isfinite(min_overlap) and 0 <= min_overlap <= 1):
        raise InvalidInputError(f"`min_overlap` must be in [0, 1]; got {min_overlap!r}")
    if isinstance(max_pairs, bool) or not isinstance(max_pairs, int) or max_pairs < 0:
        raise InvalidInputError(f"`max_pairs` must be an integer >= 0; got {max_pairs!r}")
    dirs = [viewing_direction(r, centre) for r in rpcs]
    out: list[PairCandidate] = []
    for j in range(n):
        if j == reference:
            continue
        a = intersection_angle_deg(dirs[reference], dirs[j])
        ov = roi_overlap(rpcs[reference], rpcs[j], roi, sizes[j], float(centre[2]))
        if ov < min_overlap:
            out.append(PairCandidate(reference, j, a, ov, False, f"sees {100 * ov:.0f}% of the ROI (< "
                                                                 f"{100 * min_overlap:.0f}%)"))
        elif not min_angle_deg <= a <= max_angle_deg:
            out.append(PairCandidate(reference, j, a, ov, False, f"intersection angle {a:.1f} deg outside "
                                                                 f"{min_angle_deg:g}-{max_angle_deg:g} deg"))
        else:
            out.append(PairCandidate(reference, j, a, ov, True, "kept"))
    kept = [c for c in out if c.kept]
    if max_pairs and len(kept) > max_pairs:
        mid = 0.5 * (min_angle_deg + max_angle_deg)
        best = {(c.left, c.right) for c in sorted(kept, key=lambda c: abs(c.angle_deg - mid))[:max_pairs]}
        out = [c if (c.left, c.right) in best or not c.kept else
               PairCandidate(c.left, c.right, c.angle_deg, c.overlap, False, f"more than {max_pairs} pairs passed")
               for c in out]
    if not any(c.kept for c in out):
        raise StereoError(f"no pair of {names[reference]!r} with another image passes: " + "; ".join(
            f"{names[c.right]}: {c.reason}" for c in out))
    return out
