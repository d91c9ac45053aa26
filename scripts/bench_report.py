"""Benchmark: QA plots and the full report for 10 000 residuals (matplotlib Agg).

Target (issue 7): the plots for 10 000 residuals in under 10 s.
Peer, measured in the same run: a minimal hand-written pyplot version of the same
three plots (quiver over the image, histogram + scipy.stats.probplot Q-Q, |v| vs
radius), without legends, scale key, colour bar, outlier marks or binned curves,
i.e. the least a user would write by hand. Ratio = ours / peer.

Usage: python scripts/bench_report.py [--n 10000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np

from rectify.geometry.residuals import ResidualTable
from rectify.report.builder import write_report
from rectify.report.figures import histogram_qq_figure, radial_figure, residual_vector_figure

DPI = 110


def make_table(n: int, seed: int = 0) -> ResidualTable:
    rng = np.random.default_rng(seed)
    w, h = 8000, 8000
    pos = rng.uniform(0, [w, h], (n, 2))
    d = pos - [w / 2, h / 2]
    r2 = np.sum(d * d, axis=1) / (w / 2) ** 2
    v = rng.normal(0, 0.4, (n, 2)) + 0.3 * r2[:, None] * d / (w / 2)  # noise + radial distortion trend
    outlier = rng.random(n) < 0.02
    v[outlier] += rng.normal(0, 8, (int(outlier.sum()), 2))
    check = (rng.random(n) < 0.05) & ~outlier
    return ResidualTable("tie points (homography)", [f"p{i}" for i in range(n)], pos, pos + v, "px",
                         outlier=outlier, check=check, position_px=pos, n_params=8)


def ours(t: ResidualTable, out: Path) -> float:
    t0 = time.perf_counter()
    residual_vector_figure(t, image_shape=(8000, 8000)).savefig(out / "v.png", dpi=DPI)
    histogram_qq_figure(t).savefig(out / "h.png", dpi=DPI)
    radial_figure(t, (3999.5, 3999.5)).savefig(out / "r.png", dpi=DPI)
    return time.perf_counter() - t0


def peer(t: ResidualTable, out: Path) -> float:
    import matplotlib.pyplot as plt
    from scipy import stats

    t0 = time.perf_counter()
    v, p = t.residual, t.position_px
    fig = plt.figure(figsize=(8, 6.4))
    plt.quiver(p[:, 0], p[:, 1], v[:, 0], v[:, 1], t.normalised)
    plt.gca().invert_yaxis()
    fig.savefig(out / "pv.png", dpi=DPI)
    plt.close(fig)
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4.2))
    a.hist(t.normalised[np.isfinite(t.normalised)], bins=60)
    stats.probplot((v / t.sigma0).ravel(), plot=b)
    fig.savefig(out / "ph.png", dpi=DPI)
    plt.close(fig)
    fig = plt.figure(figsize=(10, 4.2))
    plt.scatter(np.hypot(*(p - 3999.5).T), t.norm, s=4)
    fig.savefig(out / "pr.png", dpi=DPI)
    plt.close(fig)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    t = make_table(args.n)
    with tempfile.TemporaryDirectory() as d:
        out = Path(d)
        ours(t, out)  # warm-up (font cache, imports)
        peer(t, out)
        o = min(ours(t, out) for _ in range(args.repeat))
        p = min(peer(t, out) for _ in range(args.repeat))
        t0 = time.perf_counter()
        write_report(out / "report", title=f"bench {args.n}", tables=[t], image_shapes={t.step: (8000, 8000)})
        full = time.perf_counter() - t0
        html_mb = (out / "report" / "report.html").stat().st_size / 1e6
    print(f"residuals: {args.n}, best of {args.repeat}, matplotlib {matplotlib.__version__} "
          f"backend {matplotlib.get_backend()}, PNG dpi {DPI}")
    print(f"ours  (vectors + histogram/Q-Q + radial, full styling): {o:7.2f} s   target < 10 s: "
          f"{'PASS' if o < 10 else 'FAIL'}")
    print(f"peer  (minimal pyplot quiver + hist/probplot + scatter):  {p:7.2f} s")
    print(f"ratio ours / peer: {o / p:.2f}")
    print(f"full write_report (CSV, 3 PNG, JSON, HTML with 500 rows): {full:7.2f} s, report.html {html_mb:.2f} MB")


if __name__ == "__main__":
    main()
