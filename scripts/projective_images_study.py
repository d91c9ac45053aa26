"""Simulated projective images with set random errors (seed 003, 2.3).

Seed 003 keeps only the title of 2.3, "mathematical modelling of projective images with given
parameters of random errors"; its method runs through the whole work: an image is a projective
image of the object (interior orientation K with per-axis principal distances fx, fy and a skew s,
1.2), measured with random errors of a set standard deviation. This script

1. simulates such images of a 3D test field (2048 x 1536 px, fx = 2400 px, fy / fx = 1.004,
   skew 1.5 px) with set errors sigma, checks that the realised errors have the set statistics, and
   recovers the projective interior orientation by the DLT (:class:`stereo.calibration.dlt.DLT`):
   the RMS residual against its closed form ``sigma sqrt((2N - 11) / 2N)`` and the Monte Carlo
   scatter of fx, fy, s, cx, cy (which must scale with sigma);
2. fits the classical interior orientation (one principal distance, no skew:
   :meth:`stereo.calibration.result.Calibration.from_points` with ``equal_focal``, no distortion) and
   the projective one to the same images for growing affinity and skew, showing the residual the
   classical model leaves and the bias it takes.

    python scripts/projective_images_study.py [--trials 300] [--seed 0]
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stereo.calibration.dlt import DLT  # noqa: E402
from stereo.calibration.result import Calibration  # noqa: E402

F64 = NDArray[np.float64]

WIDTH, HEIGHT = 2048, 1536


@dataclass(frozen=True)
class ProjectiveCamera:
    """A projective interior orientation (px): ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``."""

    fx: float = 2400.0
    fy: float = 2409.6
    skew: float = 1.5
    cx: float = 1030.0
    cy: float = 760.0

    @property
    def K(self) -> F64:
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def test_field(rng: np.random.Generator, n: int = 60) -> F64:
    """(n, 3) points of a 3D test field: a 4 x 3 m wall with 1 m of depth, m (object z towards the camera)."""
    return rng.uniform([-2.0, -1.5, 0.0], [2.0, 1.5, 1.0], (n, 3))


def exact_image(cam: ProjectiveCamera, X: F64) -> F64:
    """Noise-free pixels of ``X`` seen from 6 m with a small tilt (every point inside the frame)."""
    a, b = math.radians(3.0), math.radians(-2.5)
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    px = DLT.from_elements(cam.K, Rx @ Ry, np.array([0.1, -0.1, 7.0])).project(X)
    assert np.all((px > 0) & (px < [WIDTH - 1, HEIGHT - 1])), "test field outside the frame"
    return px


def expected_dlt_rms(sigma: float, n: int) -> float:
    """Expected RMS residual (one coordinate) of the 11-parameter DLT on ``n`` points with errors ``sigma``:
    ``sigma sqrt((2n - 11) / (2n))`` (redundancy over observations)."""
    return sigma * math.sqrt((2 * n - 11) / (2 * n))


def simulate(cam: ProjectiveCamera, sigma: float, trials: int, rng: np.random.Generator, n: int = 60
             ) -> dict[str, float]:
    """Monte Carlo of the DLT on images with set errors ``sigma``: realised error statistics, mean RMS residual,
    scatter of the recovered elements."""
    X = test_field(np.random.default_rng(7), n)
    exact = exact_image(cam, X)
    errs, rms, el = [], [], []
    for _ in range(trials):
        e = rng.normal(0.0, sigma, exact.shape)
        d = DLT.from_points(X, exact + e)
        k = d.decompose()
        errs.append(e)
        rms.append(d.rmse_px / math.sqrt(2.0))  # per coordinate (DLT.rmse_px is per point)
        el.append((k.fx, k.fy, k.skew, k.cx, k.cy))
    E = np.concatenate(errs)
    A = np.array(el)
    return {"mean_x": float(E[:, 0].mean()), "mean_y": float(E[:, 1].mean()), "std_x": float(E[:, 0].std()),
            "std_y": float(E[:, 1].std()), "rms": float(np.sqrt(np.mean(np.square(rms)))),
            **{f"sd_{n}": float(v) for n, v in zip(("fx", "fy", "skew", "cx", "cy"), A.std(axis=0), strict=True)},
            **{f"bias_{n}": float(v) for n, v in zip(("fx", "fy", "skew", "cx", "cy"),
                                                      A.mean(axis=0) - np.array([cam.fx, cam.fy, cam.skew, cam.cx,
                                                                                 cam.cy]), strict=True)}}


def table_errors(trials: int, rng: np.random.Generator) -> list[str]:
    cam, n = ProjectiveCamera(), 60
    out = [f"### 1. Set errors, realised errors and the DLT (N = {n} points, {trials} images per row; camera "
           f"fx {cam.fx:g}, fy {cam.fy:g}, s {cam.skew:g}, cx {cam.cx:g}, cy {cam.cy:g} px)", "",
           "| set sigma px | realised mean x, y px | realised std x, y px | DLT RMS residual (a coordinate) px | "
           "closed form px | "
           "sd fx, fy px | sd s px | sd cx, cy px | sd fx / sigma |", "|---|---|---|---|---|---|---|---|---|"]
    for sigma in (0.1, 0.25, 0.5, 1.0):
        r = simulate(cam, sigma, trials, rng, n)
        out.append(f"| {sigma:g} | {r['mean_x']:+.4f}, {r['mean_y']:+.4f} | {r['std_x']:.4f}, {r['std_y']:.4f} | "
                   f"{r['rms']:.4f} | {expected_dlt_rms(sigma, n):.4f} | {r['sd_fx']:.2f}, {r['sd_fy']:.2f} | "
                   f"{r['sd_skew']:.2f} | {r['sd_cx']:.2f}, {r['sd_cy']:.2f} | {r['sd_fx'] / sigma:.1f} |")
    return out


def table_models(rng: np.random.Generator, sigma: float = 0.25, views: int = 1) -> list[str]:
    out = [f"### 2. Classical (f, cx, cy) vs projective (fx, fy, s, cx, cy) interior orientation on projective "
           f"images (sigma {sigma:g} px, one image of 60 points)", "",
           "| fy / fx | skew px | classical: RMS residual (a coordinate) px, f px | projective (DLT): RMS residual "
           "(a coordinate) px, fx, fy, s px |",
           "|---|---|---|---|"]
    X = test_field(np.random.default_rng(7), 60)
    for aff, skew in ((1.0, 0.0), (1.001, 0.0), (1.004, 0.0), (1.004, 1.5), (1.01, 5.0)):
        cam = ProjectiveCamera(fx=2400.0, fy=2400.0 * aff, skew=skew)
        px = exact_image(cam, X) + rng.normal(0.0, sigma, (len(X), 2))
        cal = Calibration.from_points(X, px, WIDTH, HEIGHT, equal_focal=True, distortion=())
        d = DLT.from_points(X, px)
        k = d.decompose()
        out.append(f"| {aff:g} | {skew:g} | {cal.rms_px / math.sqrt(2):.3f}, {cal.value('f'):.1f} | "
                   f"{d.rmse_px / math.sqrt(2):.3f}, {k.fx:.1f}, {k.fy:.1f}, {k.skew:.1f} |")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    print("\n".join(table_errors(a.trials, rng)) + "\n")
    print("\n".join(table_models(rng)) + "\n")


if __name__ == "__main__":
    main()
