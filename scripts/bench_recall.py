"""Benchmark: wide-baseline recall of ``rectify match`` against plain OpenCV on graf-like pairs.

A textured plane is seen frontally (left) and from a viewpoint turned by 20-60 degrees about the
vertical axis (right), as in the Oxford "graf" sequence; the plane-induced homography is the truth.
Ours: :func:`rectify.features.match_arrays` with the defaults (SIFT, homography verification, guided
re-admission, least-squares refinement). Peer, in the same run: OpenCV SIFT + FLANN ratio test 0.8 + USAC
MAGSAC++ ``findHomography`` (1.5 px). Scored: verified matches, correct ones (transfer error below
``--tol`` px against the truth), distinct correct ones (left positions 0.1 px apart: SIFT puts several
keypoints at one position and the peer keeps them all, ours is one-to-one), median error of the
correct ones, time.

    python scripts/bench_recall.py [--angles 20 40 50 60] [--size 800] [--tol 2] [--repeat 5]

Precision beside recall (issue 30): correct / returned, the error of the correct matches (median, RMS) and of
the refined ones alone (the matches kept unrefined carry a larger sigma); ``--repeat N`` times each pair N
times, alternating with the peer, and keeps the fastest.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def texture(size: int, seed: int = 0) -> np.ndarray:
    """A graffiti-like grey texture: natural image tiles plus shapes (uint8, size x size)."""
    import skimage.data as skd

    rng = np.random.default_rng(seed)
    srcs = [skd.astronaut()[..., 1], skd.coffee()[..., 0], skd.chelsea()[..., 2], skd.rocket()[..., 1]]
    img = np.zeros((size, size), np.uint8)
    half = size // 2
    for k, s in enumerate(srcs):
        t = cv2.resize(s, (half, half), interpolation=cv2.INTER_AREA)
        r, c = divmod(k, 2)
        img[r * half:(r + 1) * half, c * half:(c + 1) * half] = t
    for _ in range(60):
        cv2.circle(img, tuple(int(v) for v in rng.integers(0, size, 2)), int(rng.integers(5, 40)),
                   int(rng.integers(0, 255)), int(rng.integers(-1, 4)))
    return img


def viewpoint_homography(size: int, angle_deg: float, f: float | None = None) -> np.ndarray:
    """H (right from left) of the plane z = 0 seen frontally and from ``angle_deg`` about the y axis,
    both cameras aimed at the plane's centre from the same distance."""
    f = f or 1.2 * size
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    D = f  # distance in plane pixels: the frontal image is the plane itself (H1 = identity)

    def P(theta):
        t = np.radians(theta)
        C = np.array([D * np.sin(t), 0.0, -D * np.cos(t)])        # camera centre, aimed at the origin
        R = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])  # world -> camera
        return K @ np.c_[R, -R @ C]

    def plane(p):  # plane pixel (u, v) -> world (u - size/2, v - size/2, 0)
        return p[:, [0, 1, 3]] @ np.array([[1, 0, -size / 2], [0, 1, -size / 2], [0, 0, 1.0]])

    H1, H2 = plane(P(0.0)), plane(P(angle_deg))
    H = H2 @ np.linalg.inv(H1)
    return H / H[2, 2]


def _apply(H, p):
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:]


def score(left, right, H, tol, refined=None):
    """Returned, correct (and distinct correct) matches, the precision (correct / returned) and the error of the
    correct ones (median, RMS; of the ``refined`` ones alone too)."""
    if len(left) == 0:
        return {"verified": 0, "correct": 0, "median_error_px": None}
    e = np.linalg.norm(_apply(H, left) - right, axis=1)
    ok = e < tol
    # distinct correct matches: SIFT puts several keypoints (orientations) at one position; the peer keeps them
    uniq = len(np.unique(np.round(left[ok] / 0.1).astype(np.int64), axis=0)) if ok.any() else 0
    out = {"verified": int(len(left)), "correct": int(ok.sum()), "correct_distinct": int(uniq),
           "precision": round(float(ok.mean()), 4),
           "median_error_px": round(float(np.median(e[ok])), 4) if ok.any() else None,
           "rms_error_px": round(float(np.sqrt(np.mean(e[ok] ** 2))), 4) if ok.any() else None}
    if refined is not None:
        r = ok & refined
        out.update(refined=int(refined.sum()),
                   median_error_refined_px=round(float(np.median(e[r])), 4) if r.any() else None,
                   rms_error_refined_px=round(float(np.sqrt(np.mean(e[r] ** 2))), 4) if r.any() else None)
    return out


def peer(a, b):
    s = cv2.SIFT.create()
    k1, d1 = s.detectAndCompute(a, None)
    k2, d2 = s.detectAndCompute(b, None)
    m = cv2.FlannBasedMatcher(dict(algorithm=1, trees=4), dict(checks=64)).knnMatch(d1, d2, k=2)
    good = [x[0] for x in m if len(x) == 2 and x[0].distance < 0.8 * x[1].distance]
    p1 = np.array([k1[g.queryIdx].pt for g in good], dtype=np.float64).reshape(-1, 2)
    p2 = np.array([k2[g.trainIdx].pt for g in good], dtype=np.float64).reshape(-1, 2)
    if len(p1) < 4:
        return p1[:0], p2[:0]
    H, mask = cv2.findHomography(p1, p2, cv2.USAC_MAGSAC, 1.5, maxIters=10000, confidence=0.9999)
    if mask is None:
        return p1[:0], p2[:0]
    inl = mask.ravel().astype(bool)
    return p1[inl], p2[inl]


def main() -> None:
    from rectify.errors import RectifyError
    from rectify.features import MatcherConfig, match_arrays

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--angles", type=float, nargs="+", default=[20, 40, 50, 60])
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--tol", type=float, default=2.0, help="correct: transfer error below this, px")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1, help="time each pair this many times (the fastest counts)")
    a = ap.parse_args()
    img = texture(a.size, a.seed)
    rows = []
    for ang in a.angles:
        H = viewpoint_homography(a.size, ang)
        right = cv2.warpPerspective(img, H, (a.size, a.size), flags=cv2.INTER_CUBIC, borderValue=0)
        valid = cv2.warpPerspective(np.ones_like(img), H, (a.size, a.size), flags=cv2.INTER_NEAREST) > 0
        t_ours, t_peer, c_ours, c_peer = [], [], [], []
        for _ in range(max(1, a.repeat) - 1):    # extra timed runs, alternating with the peer's (fastest counts)
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                match_arrays(img, right, right_valid=valid, config=MatcherConfig())
            except RectifyError:
                pass
            t_ours.append(time.perf_counter() - t0)
            c_ours.append(time.process_time() - c0)
            t0, c0 = time.perf_counter(), time.process_time()
            peer(img, right)
            t_peer.append(time.perf_counter() - t0)
            c_peer.append(time.process_time() - c0)
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            r = match_arrays(img, right, right_valid=valid, config=MatcherConfig())
            sc = r.matches.score
            refined = None if sc is None else np.isfinite(sc)
            ours = {**score(r.matches.left, r.matches.right, H, a.tol, refined), "n_duplicates": r.n_duplicates,
                    "n_guided": r.n_guided, "refine_failed": r.n_refine_failed,
                    "unrefined_kept": int(np.isnan(r.matches.score).sum()) if r.matches.score is not None else 0}
        except RectifyError as err:
            ours = {"verified": 0, "correct": 0, "median_error_px": None, "error": str(err)}
        ours["time_s"] = round(min([time.perf_counter() - t0, *t_ours]), 3)
        ours["cpu_s"] = round(min([time.process_time() - c0, *c_ours]), 3)     # CPU of all threads
        t0, c0 = time.perf_counter(), time.process_time()
        pl, pr = peer(img, right)
        pe = {**score(pl, pr, H, a.tol), "time_s": round(min([time.perf_counter() - t0, *t_peer]), 3),
              "cpu_s": round(min([time.process_time() - c0, *c_peer]), 3)}
        row = {"angle_deg": ang, "ours": ours, "peer": pe}
        rows.append(row)
        print(json.dumps(row), flush=True)
    for row in rows:
        o, p = row["ours"], row["peer"]
        print(f"{row['angle_deg']:g} deg: ours {o['correct']} correct of {o['verified']} (precision "
              f"{o.get('precision', 0):.2%}), median {o['median_error_px']} px (refined "
              f"{o.get('median_error_refined_px')}, RMS {o.get('rms_error_refined_px')} px), {o['time_s']} s "
              f"(cpu {o.get('cpu_s')}); peer {p['correct']} of {p['verified']}, median {p['median_error_px']} px, "
              f"{p['time_s']} s (cpu {p['cpu_s']})", flush=True)
    print(json.dumps({"size": a.size, "tol_px": a.tol, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
