"""Variance components of a bundle adjustment: how many rounds, and which estimates rest on too little.

A group's variance factor is estimated from its redundancy r (:func:`stereo.block.bundle.adjust.adjust_bundle`);
the relative standard deviation of a sigma estimated from redundancy r is about 1 / sqrt(2 r) (a chi-square
with r degrees of freedom): 50 % at r = 2, 22 % at r = 10. An estimate from less than
:data:`VCE_WARN_REDUNDANCY` is flagged, with its redundancy, so that the predicted precisions it scales are
not taken at face value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["VCE_FACTOR_BOUNDS", "VCE_MAX_ROUNDS", "VCE_MIN_REDUNDANCY", "VCE_WARN_REDUNDANCY", "weak_components"]

#: a group's factor is estimated only from this much redundancy on, within these bounds
VCE_MIN_REDUNDANCY = 2.0
VCE_FACTOR_BOUNDS = (1e-3, 1e3)
#: variance-component rounds at most (each a full adjustment with the factors of the round before)
VCE_MAX_ROUNDS = 10
#: a variance factor estimated from less redundancy than this is flagged
VCE_WARN_REDUNDANCY = 10.0


def weak_components(redundancy: Mapping[str, float], factors: Mapping[str, float],
                    estimated_at: Mapping[str, float]) -> list[str]:
    """Warning lines for the variance factors estimated from too little redundancy.

    Parameters
    ----------
    redundancy : mapping group -> float
        Redundancy of each group at the solution.
    factors : mapping group -> float
        The variance factors used (group sigma / a-priori sigma).
    estimated_at : mapping group -> float
        The groups whose factor was estimated, with the redundancy of its latest estimate.
    """
    out = []
    for g, r_est in estimated_at.items():
        r_now = float(redundancy.get(g, r_est))
        r = min(r_est, r_now)
        if r < VCE_WARN_REDUNDANCY:
            out.append(f"group {g}: variance factor {factors[g]:.3f} estimated from a redundancy of {r_est:.1f} "
                       f"({r_now:.1f} at the solution); below {VCE_WARN_REDUNDANCY:g} a sigma is uncertain by about "
                       f"{100 / math.sqrt(2 * max(r, 0.5)):.0f} %, and the predicted precisions it scales with it")
    return out
