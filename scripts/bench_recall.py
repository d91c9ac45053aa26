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

Ours runs in a worker process (this script with ``--serve ROOT``, importing the packages of the checkout ROOT),
warmed up on the first pair before any timing. ``--baseline PATH`` adds a second worker with the packages of another
checkout (e.g. the version before a change: ``git worktree add /tmp/base <commit>``): each pair is matched by both,
alternating (the order flips from one repetition to the next) with the peer in between, and the summary gives both
versions' recall, precision and fastest time, and the ratio this / baseline:

    python scripts/bench_recall.py --repeat 5 --baseline /tmp/base
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


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


def _pair(size: int, seed: int, angle: float):
    """The graf-like pair of one view change: left, right, the right image's valid mask and H (right from left)."""
    img = texture(size, seed)
    H = viewpoint_homography(size, angle)
    right = cv2.warpPerspective(img, H, (size, size), flags=cv2.INTER_CUBIC, borderValue=0)
    valid = cv2.warpPerspective(np.ones_like(img), H, (size, size), flags=cv2.INTER_NEAREST) > 0
    return img, right, valid, H


def serve(root: str) -> None:
    """Worker: match the pairs asked for on stdin (one JSON line each: size, seed, angle, tol, score) with the
    packages of the checkout ``root`` and answer one JSON line each: wall and CPU time of ``match_arrays`` (the
    process's CPU, all threads), and with ``score`` the scores of the matches."""
    sys.path.insert(0, root)
    from rectify.errors import RectifyError
    from rectify.features import MatcherConfig, match_arrays

    pairs: dict = {}
    for line in sys.stdin:
        q = json.loads(line)
        key = (q["size"], q["seed"], q["angle"])
        if key not in pairs:
            pairs[key] = _pair(*key)
        img, right, valid, H = pairs[key]
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            r = match_arrays(img, right, right_valid=valid, config=MatcherConfig())
            err = None
        except RectifyError as e:
            r, err = None, str(e)
        out: dict = {"time_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
        if q.get("score"):
            if r is None:
                out.update({"verified": 0, "correct": 0, "median_error_px": None, "error": err})
            else:
                sc = r.matches.score
                refined = None if sc is None else np.isfinite(sc)
                out.update(**score(r.matches.left, r.matches.right, H, q["tol"], refined),
                           n_duplicates=r.n_duplicates, n_guided=r.n_guided, refine_failed=r.n_refine_failed,
                           unrefined_kept=int(np.isnan(sc).sum()) if sc is not None else 0)
        print(json.dumps(out), flush=True)


class Worker:
    """A :func:`serve` process for the checkout ``root``."""

    def __init__(self, label: str, root: Path):
        self.label = label
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", ""))
                                                           if p)}
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--serve", str(root)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)

    def ask(self, **q) -> dict:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(q) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the {self.label} worker stopped (exit {self.proc.wait()})")
        return json.loads(line)

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--angles", type=float, nargs="+", default=[20, 40, 50, 60])
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--tol", type=float, default=2.0, help="correct: transfer error below this, px")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1, help="time each pair this many times (the fastest counts)")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="also match each pair with the packages of this checkout (an earlier version), "
                         "alternating with this one; the summary compares them")
    ap.add_argument("--serve", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.serve is not None:
        serve(a.serve)
        return
    if a.baseline is not None and not (a.baseline / "rectify" / "__init__.py").is_file():
        ap.error(f"--baseline {str(a.baseline)!r} is not a checkout of this project (no rectify/__init__.py)")
    workers = [Worker("ours", ROOT)] + ([Worker("baseline", a.baseline.resolve())] if a.baseline else [])
    rows = []
    try:
        for w in workers:      # warm-up (first-call imports), untimed
            w.ask(size=a.size, seed=a.seed, angle=a.angles[0], tol=a.tol)
        for ang in a.angles:
            img, right, _, H = _pair(a.size, a.seed, ang)
            times: dict = {w.label: [] for w in workers} | {"peer": []}
            row: dict = {"angle_deg": ang, "load_before": round(os.getloadavg()[0], 2)}
            for i in range(max(1, a.repeat)):
                last = i == max(1, a.repeat) - 1
                for w in (workers if i % 2 == 0 else workers[::-1]):
                    r = w.ask(size=a.size, seed=a.seed, angle=ang, tol=a.tol, score=last)
                    times[w.label].append((r.pop("time_s"), r.pop("cpu_s")))
                    if last:
                        row[w.label] = r
                t0, c0 = time.perf_counter(), time.process_time()
                pl, pr = peer(img, right)
                times["peer"].append((time.perf_counter() - t0, time.process_time() - c0))
            row["peer"] = score(pl, pr, H, a.tol)
            for label, tc in times.items():
                row[label]["time_s"] = round(min(t for t, _ in tc), 3)
                row[label]["cpu_s"] = round(min(c for _, c in tc), 3)      # CPU of all threads
            rows.append(row)
            print(json.dumps(row), flush=True)
    finally:
        for w in workers:
            w.close()
    for row in rows:
        o, p = row["ours"], row["peer"]
        print(f"{row['angle_deg']:g} deg: ours {o['correct']} correct of {o['verified']} (precision "
              f"{o.get('precision', 0):.2%}), median {o['median_error_px']} px (refined "
              f"{o.get('median_error_refined_px')}, RMS {o.get('rms_error_refined_px')} px), {o['time_s']} s "
              f"(cpu {o.get('cpu_s')}); peer {p['correct']} of {p['verified']}, median {p['median_error_px']} px, "
              f"{p['time_s']} s (cpu {p['cpu_s']})", flush=True)
        if "baseline" in row:
            b = row["baseline"]
            print(f"    baseline {b['correct']} correct of {b['verified']} (precision {b.get('precision', 0):.2%}), "
                  f"median {b['median_error_px']} px (refined {b.get('median_error_refined_px')}, RMS "
                  f"{b.get('rms_error_refined_px')} px), {b['time_s']} s (cpu {b['cpu_s']}): ratio this / baseline "
                  f"{o['time_s'] / b['time_s']:.3f} wall, {o['cpu_s'] / b['cpu_s']:.3f} CPU (load "
                  f"{row['load_before']})", flush=True)
    if a.baseline is not None and rows:
        tot = {k: (sum(r[k]["time_s"] for r in rows), sum(r[k]["cpu_s"] for r in rows)) for k in ("ours", "baseline")}
        print(f"total: this {tot['ours'][0]:.3f} s (cpu {tot['ours'][1]:.3f}), baseline {tot['baseline'][0]:.3f} s "
              f"(cpu {tot['baseline'][1]:.3f}): ratio {tot['ours'][0] / tot['baseline'][0]:.3f} wall, "
              f"{tot['ours'][1] / tot['baseline'][1]:.3f} CPU", flush=True)
    print(json.dumps({"size": a.size, "tol_px": a.tol, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
