"""Rotated-copy experiment: mean systematic offset (px) of plain OpenCV vs rectify.features, raw and refined.

    python scripts/rotated_copy_offsets.py
"""
import cv2
import numpy as np
import skimage.data as skd

from rectify.features import MatcherConfig, match_arrays

g = cv2.cvtColor(skd.astronaut(), cv2.COLOR_RGB2GRAY)
IM = {"uint8 grey": g[50:450, 30:487], "uint8 RGB": skd.astronaut()[10:401, 20:500],
      "uint16": skd.camera()[:411, :397].astype(np.uint16) * 200 + 1000}
for det in ("sift", "orb"):
    for k, img in IM.items():
        h, w = img.shape[:2]
        rot = img[::-1, ::-1].copy()
        gi = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        gi = cv2.normalize(gi.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        d = cv2.SIFT_create() if det == "sift" else cv2.ORB_create(5000)
        k1, d1 = d.detectAndCompute(gi, None)
        k2, d2 = d.detectAndCompute(gi[::-1, ::-1].copy(), None)
        m = cv2.BFMatcher(cv2.NORM_L2 if det == "sift" else cv2.NORM_HAMMING, crossCheck=True).match(d1, d2)
        s = (np.array([k1[x.queryIdx].pt for x in m]) + np.array([k2[x.trainIdx].pt for x in m]) - [w - 1, h - 1]) / 2
        s = s[np.linalg.norm(s, axis=1) < 1.5]
        row = [f"{det}", k, f"{s.mean(0)[0]:+.3f}, {s.mean(0)[1]:+.3f}"]
        for ref in (False, True):
            r = match_arrays(img, rot, config=MatcherConfig(detector=det, refine=ref))
            o = (r.matches.left + r.matches.right - [w - 1, h - 1]) / 2
            row.append(f"{o.mean(0)[0]:+.4f}, {o.mean(0)[1]:+.4f} (n={len(o)})")
        print("| " + " | ".join(row) + " |")
