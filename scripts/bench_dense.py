"""Dense matching benchmark: ours vs OpenCV StereoSGBM (OpenCV sample settings) on Motorcycle, same run.

Usage: nice python scripts/bench_dense.py
"""

from __future__ import annotations

import time

import numpy as np
from skimage import data

from stereo.dense.matching import match_pair, sgbm_baseline


def occlusion_from_truth(gt: np.ndarray) -> np.ndarray:
    H, W = gt.shape
    yy, xx = np.mgrid[0:H, 0:W]
    known = np.isfinite(gt)
    d = np.where(known, gt, -1)
    xt = np.rint(xx - d).astype(int)
    ok = known & (xt >= 0) & (xt < W)
    zb = np.full((H, W), -1.0)
    np.maximum.at(zb, (yy[ok], xt[ok]), d[ok])
    occ = np.ones((H, W), bool)
    occ[ok] = zb[yy[ok], xt[ok]] > d[ok] + 1.0
    return occ | ~known


def best_time(f, n: int = 3):
    ts, out = [], None
    for _ in range(n):
        t = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t)
    return out, min(ts)


def main() -> None:
    left, right, gt = data.stereo_motorcycle()
    m = ~occlusion_from_truth(gt)
    base, tb = best_time(lambda: sgbm_baseline(left, right))
    ours, to = best_time(lambda: match_pair(left, right).disparity)
    for name, d, t in (("OpenCV StereoSGBM (sample settings)", base, tb), ("stereo.dense.match_pair", ours, to)):
        v = np.isfinite(d) & m
        print(f"{name}: density {v.sum() / m.sum():.3f}, bad-2.0 {(np.abs(d - gt) > 2)[v].mean():.4f}, "
              f"time {t:.3f} s")
    print(f"time ratio ours / SGBM: {to / tb:.2f}")


if __name__ == "__main__":
    main()
