"""Refined vs raw tie points on the real NGI aerial pair (../shared/data/ngi_strip05).

For raw (detector) and LSM-refined matches, both verified with a fundamental
matrix, prints
- the Sampson error against the epipolar geometry implied by the known
  exterior orientations (scripts/ngi_geometry.py), and
- the RMS residual parallax of relative orientation (stereo.relative,
  left-image system, no robust weighting) estimated from the matches.

    python scripts/ngi_refinement.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import ngi_geometry as g  # noqa: E402  (after the sys.path set-up above)

from rectify.features import MatcherConfig, match_images  # noqa: E402
from rectify.geometry.camera import Camera  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "ngi_strip05"


def compare(data: Path = DATA, detector: str = "sift") -> dict:
    from stereo.relative import RelativeOrientation

    cam = Camera(focal_length_mm=g.F_MM, pixel_size_mm=g.PIXEL_MM, width=g.WIDTH, height=g.HEIGHT)
    F = g.fundamental()
    out = {}
    res = {}
    for refine in (False, True):
        r = match_images(data / "3324c_2015_1004_05_0182_RGB.tif", data / "3324c_2015_1004_05_0184_RGB.tif",
                         config=MatcherConfig(detector=detector, verify="fundamental", refine=refine))
        res[refine] = r
    # the same physical points in both runs: refined matches keep their left position
    key = {tuple(np.round(p, 6)) for p in res[True].matches.left}
    common = np.array([tuple(np.round(p, 6)) in key for p in res[False].matches.left])
    for refine, r in res.items():
        s = g.sampson(F, r.matches.left, r.matches.right)
        ro = RelativeOrientation.from_pixels(r.matches.left, r.matches.right, cam, system="left-image")
        par_px = np.asarray(ro.parallax_mm) / g.PIXEL_MM
        out["refined" if refine else "raw"] = {
            "n": len(r.matches), "sampson_median_px": float(np.median(s)),
            "sampson_rms_px": float(np.sqrt(np.mean(s ** 2))),
            "ro_rms_parallax_px": float(np.sqrt(np.mean(par_px ** 2))),
            "ro_sigma0_mm": ro.sigma0_mm, "ro_converged": bool(ro.converged)}
    # raw positions restricted to the points that refinement kept (same points, like for like)
    r = res[False]
    lm, rm = r.matches.left[common], r.matches.right[common]
    ro = RelativeOrientation.from_pixels(lm, rm, cam, system="left-image")
    s = g.sampson(F, lm, rm)
    out["raw_same_points"] = {"n": int(common.sum()), "sampson_median_px": float(np.median(s)),
                              "sampson_rms_px": float(np.sqrt(np.mean(s ** 2))),
                              "ro_rms_parallax_px": float(np.sqrt(np.mean((np.asarray(ro.parallax_mm) /
                                                                            g.PIXEL_MM) ** 2)))}
    return out


if __name__ == "__main__":
    print(json.dumps(compare(), indent=1))
