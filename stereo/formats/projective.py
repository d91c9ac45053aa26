"""The projective pair JSON: relative orientation of a pair without a camera (seed 003, 3.2.2).

Written by ``stereo orient --system projective`` when no camera is given; read by ``stereo model
--transform projective``. Fields (``docs/formats.md``, "projective pair JSON"):

- ``format`` = ``rectify-stereo/projective-pair``, ``version`` = 1;
- ``fundamental``: F (3 x 3), pixels (x = column right, y = row down), ``x_right^T F x_left = 0``;
- ``camera_left``, ``camera_right``: the canonical projective cameras P1 = [I | 0],
  P2 = [[e']x F | e'] (3 x 4, homogeneous model point -> homogeneous pixel);
- ``metric``: false (no rotations, base or focal length: the model is projective);
- ``sampson_rms_px``, ``sigma0_px`` (sqrt(sum d^2 / (n - 7))), ``redundancy``, ``iterations``,
  ``condition`` (of the normalised eight-point design), ``n_points``;
- ``points``: per tie point ``id`` and ``residual_px`` (signed Sampson distance).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rectify.atomic import read_json
from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath, check_format, stamp
from stereo.pair.projective import FundamentalFit

__all__ = ["PROJECTIVE_PAIR_FORMAT", "ProjectivePair", "projective_pair_dict", "dump_projective_pair",
           "read_projective_pair", "is_projective_pair"]

PROJECTIVE_PAIR_FORMAT = "rectify-stereo/projective-pair"
_NAME = "projective-pair"
_VERSION = 1


def projective_pair_dict(F: ArrayLike, fit: FundamentalFit, cameras: tuple[ArrayLike, ArrayLike],
                         ids: Sequence[str]) -> dict[str, Any]:
    """The JSON document (with its format stamp)."""
    P1, P2 = (np.asarray(c, dtype=np.float64) for c in cameras)
    return stamp(_NAME, _VERSION, {
        "fundamental": np.asarray(F, dtype=np.float64).tolist(), "camera_left": P1.tolist(),
        "camera_right": P2.tolist(), "metric": False,
        "note": "projective model: no camera, so no rotations, base or focal length",
        "sampson_rms_px": fit.rms_px, "sigma0_px": fit.sigma0_px, "redundancy": fit.redundancy,
        "iterations": fit.iterations, "condition": fit.condition, "n_points": len(ids),
        "points": [{"id": str(i), "residual_px": float(d), "used": bool(u)}
                   for i, d, u in zip(ids, fit.sampson_px, fit.inliers, strict=True)],
    })


def dump_projective_pair(path: StrPath, doc: dict[str, Any]) -> None:
    """Write the document to ``path`` as given (a workspace's temporary path)."""
    Path(path).write_text(json.dumps(doc, indent=2), encoding="utf-8")


def is_projective_pair(doc: Any) -> bool:
    """True for a parsed projective pair JSON."""
    return isinstance(doc, dict) and doc.get("format") == PROJECTIVE_PAIR_FORMAT


class ProjectivePair:
    """A read projective pair: ``F`` (3, 3), ``cameras`` ((3, 4), (3, 4)), ``ids`` (tie point ids), ``raw``."""

    def __init__(self, F: np.ndarray, cameras: tuple[np.ndarray, np.ndarray], ids: tuple[str, ...],
                 raw: dict[str, Any]) -> None:
        self.F, self.cameras, self.ids, self.raw = F, cameras, ids, raw


def read_projective_pair(path: StrPath) -> ProjectivePair:
    """Read a projective pair JSON.

    Raises
    ------
    InvalidInputError
        Another format, a newer version, missing or malformed matrices (the message names the file).
    """
    p = Path(path)
    d = read_json(p, what="projective pair JSON")
    check_format(d, _NAME, _VERSION, p, what="projective pair JSON")
    try:
        F = np.array(d["fundamental"], dtype=np.float64)
        P1 = np.array(d["camera_left"], dtype=np.float64)
        P2 = np.array(d["camera_right"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as err:
        raise InvalidInputError(f"{str(p)!r} is not a valid projective pair JSON: {err}") from err
    if F.shape != (3, 3) or P1.shape != (3, 4) or P2.shape != (3, 4) or not (
            np.isfinite(F).all() and np.isfinite(P1).all() and np.isfinite(P2).all()):
        raise InvalidInputError(f"{str(p)!r}: fundamental must be finite 3 x 3 and the cameras 3 x 4; got "
                                f"{F.shape}, {P1.shape}, {P2.shape}")
    ids = tuple(str(q.get("id")) for q in d.get("points", []) if isinstance(q, dict))
    return ProjectivePair(F, (P1, P2), ids, d)
