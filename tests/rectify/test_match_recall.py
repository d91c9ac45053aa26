"""Issue 12: refinement keeps the verified matches it cannot refine (raw position, empty score) instead of
dropping them; the CSV writes their score empty and reads it back as NaN."""

from __future__ import annotations

import cv2
import numpy as np
import skimage.data as skd

from rectify.features import MatcherConfig, match_arrays
from rectify.formats.tables import matches_text, read_matches
from rectify.geometry.points import Matches

# a strong viewpoint change (about 50 degrees about the vertical axis, as in the Oxford graf sequence)
H = np.array([[1.93, 0.0, 197.0], [0.36, 2.24, -286.0], [1.1e-3, 0.0, 1.0]])


def _pair():
    img = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)[:480, :480]
    right = cv2.warpPerspective(img, H, (480, 480), flags=cv2.INTER_CUBIC)
    valid = cv2.warpPerspective(np.ones_like(img), H, (480, 480), flags=cv2.INTER_NEAREST) > 0
    return img, right, valid


def test_unrefined_matches_are_kept_and_flagged(tmp_path):
    left, right, valid = _pair()
    kept = match_arrays(left, right, right_valid=valid, config=MatcherConfig())
    dropped = match_arrays(left, right, right_valid=valid, config=MatcherConfig(keep_unrefined=False))
    assert kept.n_refine_failed > 0
    assert kept.matches.score is not None
    flagged = np.isnan(kept.matches.score)
    assert flagged.any() and len(kept.matches) > len(dropped.matches)
    q = np.c_[kept.matches.left, np.ones(len(kept.matches))] @ H.T
    e = np.linalg.norm(q[:, :2] / q[:, 2:] - kept.matches.right, axis=1)
    assert np.median(e[flagged]) < 1.5          # good matches, at their raw positions
    assert np.median(e[~flagged]) < 0.2         # the refined ones keep their precision
    p = tmp_path / "m.csv"
    p.write_text(matches_text(kept.matches))
    back = read_matches(p)
    assert back.score is not None
    assert np.array_equal(np.isnan(back.score), flagged)
    assert ",," in p.read_text()               # the empty score column (the sigma_px column follows it)
    assert isinstance(back, Matches)
