"""Inclined-convergent versus normal-case terrestrial stereo (seed 003, 2.1.1-2.1.2): how precise is each?

Seed 003 holds only the titles of 2.1.1 ("requirements; the essence of the inclined-convergent
method") and 2.1.2 ("why the convergent case is more precise; comparison with the normal case"):
no formula or number of those sections survived. What the seed does give is the setting of its
experiments: a facade about 15 m away photographed from a 5 m base (4.2), or 25 m away (2.2.2),
with a 2048 x 1536 px camera (HP PhotoSmart 715). This study computes, for that setting, the
precision of intersected facade points

- by the textbook formulas of the normal case (depth ``m_Y = Y^2 / (B f) * m_p``, ``m_p = sqrt(2) m_x``;
  lateral and height ``m_X = m_Z ~ Y / f * m_x``),
- by first-order propagation through the project's least-squares intersection
  (:func:`stereo.pair.intersection.intersect` with ``sigma_mm``), and
- by Monte Carlo with the same code (noise added to the photo coordinates, orientation exact),

and compares the two shooting methods for a facade of width W: the normal case can use at most
the base that keeps W inside both frames (``B <= Y * w / f - W``), the convergent case turns each
camera towards the facade centre by ``atan(B / 2Y)`` and can use a longer base.

    python scripts/convergent_study.py [--trials 2000] [--seed 0]

Frames: object X along the facade (right), Y up, Z towards the cameras (depth = -Z), metres;
photo coordinates in pixels (x right, y up), so "mm" of the intersection API are pixels here.
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

from stereo.pair.intersection import intersect, project  # noqa: E402

F64 = NDArray[np.float64]

#: the seed's camera format (HP PhotoSmart 715, 2048 x 1536 px); the focal length is assumed (mid zoom)
WIDTH_PX, HEIGHT_PX, FOCAL_PX = 2048, 1536, 2400.0


def normal_case_sigmas(depth: float, base: float, focal: float, sigma: float) -> tuple[float, float, float]:
    """Textbook precision of one point on the axis of the normal case: lateral, height, depth (m).

    ``m_Y = Y^2 / (B f) sqrt(2) m_x`` (parallax of two independent coordinates), ``m_X = m_Z = Y / (f sqrt 2)
    m_x`` (the mean of two rays; a point midway between the centres)."""
    return depth / focal * sigma / math.sqrt(2.0), depth / focal * sigma / math.sqrt(2.0), \
        depth ** 2 / (base * focal) * math.sqrt(2.0) * sigma


def rot_y(angle: float) -> F64:
    """Rotation about the object Y axis (up); a positive angle turns the camera axis (-Z) towards +X."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


@dataclass(frozen=True)
class Pair:
    """A terrestrial pair: centres (0,0,0) and (B,0,0); ``convergence`` turns each camera towards the other."""

    base: float
    convergence: float = 0.0

    @property
    def rotations(self) -> tuple[F64, F64]:
        return rot_y(self.convergence), rot_y(-self.convergence)


def facade(depth: float, width: float, base: float, n: int = 15, relief: float = 0.0) -> F64:
    """(n*n, 3) points of a facade of ``width`` (centred on the base) and height 0.6 ``width``, at ``depth``."""
    xs = np.linspace(-width / 2, width / 2, n) + base / 2
    ys = np.linspace(-0.3 * width, 0.3 * width, n)
    X, Yv = np.meshgrid(xs, ys)
    Z = -depth + relief * np.sin(X) * np.cos(Yv)
    return np.column_stack([X.ravel(), Yv.ravel(), Z.ravel()])


def in_frame(px: F64) -> NDArray[np.bool_]:
    return (np.abs(px[:, 0]) <= WIDTH_PX / 2) & (np.abs(px[:, 1]) <= HEIGHT_PX / 2)


def precision(pair: Pair, P: F64, sigma: float, trials: int, rng: np.random.Generator
              ) -> tuple[F64, F64, float]:
    """RMS over the points of the propagated and the Monte Carlo standard errors (X, Y, Z), m, and the share
    of the points inside both frames."""
    R1, R2 = pair.rotations
    B = np.array([pair.base, 0.0, 0.0])
    x1 = project(P, rotation=R1, centre=np.zeros(3), focal_length_mm=FOCAL_PX)
    x2 = project(P, rotation=R2, centre=B, focal_length_mm=FOCAL_PX)
    inside = float(np.mean(in_frame(x1) & in_frame(x2)))
    r = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=FOCAL_PX, sigma_mm=sigma)
    assert r.std is not None
    prop = np.sqrt(np.mean(r.std ** 2, axis=0))
    err = np.zeros(3)
    if trials:
        n = len(P)
        y1 = np.tile(x1, (trials, 1)) + rng.normal(0, sigma, (trials * n, 2))
        y2 = np.tile(x2, (trials, 1)) + rng.normal(0, sigma, (trials * n, 2))
        m = intersect(y1, y2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=FOCAL_PX)
        err = np.sqrt(np.mean((m.points - np.tile(P, (trials, 1))) ** 2, axis=0))
    return prop, err, inside


def table_formula(trials: int, rng: np.random.Generator, sigma: float = 0.5) -> list[str]:
    """Normal case, one point midway in front of the base: formula vs propagation vs Monte Carlo."""
    out = [f"### 1. Normal case, a point on the middle of the base: formula, propagation, Monte Carlo "
           f"(f = {FOCAL_PX:g} px, m_x = {sigma:g} px, {trials} trials)", "",
           "| Y m | B m | B/Y | formula m_X | m_Z (height) | m_Y (depth) | propagated m_X, m_Z, m_Y | "
           "Monte Carlo m_X, m_Z, m_Y |", "|---|---|---|---|---|---|---|---|"]
    for depth, base in ((15.0, 5.0), (15.0, 2.0), (25.0, 5.0), (25.0, 10.0)):
        P = np.array([[base / 2, 0.0, -depth]])
        prop, mc, _ = precision(Pair(base), P, sigma, trials * 20, rng)
        fx, fz, fy = normal_case_sigmas(depth, base, FOCAL_PX, sigma)
        out.append(f"| {depth:g} | {base:g} | {base / depth:.2f} | {fx * 1000:.2f} mm | {fz * 1000:.2f} mm | "
                   f"{fy * 1000:.2f} mm | {prop[0] * 1000:.2f}, {prop[1] * 1000:.2f}, {prop[2] * 1000:.2f} mm | "
                   f"{mc[0] * 1000:.2f}, {mc[1] * 1000:.2f}, {mc[2] * 1000:.2f} mm |")
    return out


def table_same_base(trials: int, rng: np.random.Generator, sigma: float = 0.5) -> list[str]:
    """Same base, same points: the convergence alone changes little; it moves the points into both frames."""
    depth, width = 15.0, 6.0
    out = [f"### 2. Same base, same facade (Y = {depth:g} m, W = {width:g} m): normal vs convergent "
           f"(RMS over 225 points; m_x = {sigma:g} px)", "",
           "| B m | convergence (each camera) | points in both frames | propagated m_X, m_Z, m_Y mm | "
           "Monte Carlo m_X, m_Z, m_Y mm |", "|---|---|---|---|---|"]
    for base in (2.0, 5.0):
        P = facade(depth, width, base)
        for conv in (0.0, math.atan(base / 2 / depth)):
            prop, mc, inside = precision(Pair(base, conv), P, sigma, trials, rng)
            out.append(f"| {base:g} | {math.degrees(conv):.2f} deg | {inside * 100:.0f} % | "
                       f"{prop[0] * 1000:.2f}, {prop[1] * 1000:.2f}, {prop[2] * 1000:.2f} | "
                       f"{mc[0] * 1000:.2f}, {mc[1] * 1000:.2f}, {mc[2] * 1000:.2f} |")
    return out


def normal_max_base(depth: float, width: float) -> float:
    """Longest normal-case base keeping a facade of ``width`` inside both frames (0 when it does not fit)."""
    return max(depth * WIDTH_PX / FOCAL_PX - width, 0.0)


def table_facade(trials: int, rng: np.random.Generator, sigma: float = 0.5) -> list[str]:
    """A facade of width W at 15 m: normal case at its longest base vs convergent at B = 5 m and B = Y/2."""
    depth = 15.0
    out = [f"### 3. Facade of width W at Y = {depth:g} m: the normal case at its longest base "
           f"(both frames hold W) vs the convergent case (m_x = {sigma:g} px)", "",
           "| W m | normal: B max m | normal m_Y mm (formula / propagated / MC) | convergent B = 5 m: m_Y mm "
           "(propagated / MC), in frames | convergent B = 7.5 m: m_Y mm (propagated / MC), in frames | "
           "gain m_Y normal / convergent 5 m |", "|---|---|---|---|---|---|"]
    for width in (4.0, 6.0, 8.0, 10.0, 12.0):
        P = facade(depth, width, 0.0, n=11)
        bn = normal_max_base(depth, width)
        if bn > 0.05:
            Pn = P + np.array([bn / 2, 0, 0])
            prop_n, mc_n, inside_n = precision(Pair(bn), Pn, sigma, trials, rng)
            f_n = normal_case_sigmas(depth, bn, FOCAL_PX, sigma)[2]
            normal = f"{f_n * 1000:.1f} / {prop_n[2] * 1000:.1f} / {mc_n[2] * 1000:.1f}"
        else:
            prop_n, normal = np.full(3, np.nan), "does not fit"
        cells = []
        for base in (5.0, 7.5):
            Pc = P + np.array([base / 2, 0, 0])
            prop_c, mc_c, inside_c = precision(Pair(base, math.atan(base / 2 / depth)), Pc, sigma, trials, rng)
            cells.append((prop_c, mc_c, inside_c))
        c5, c75 = cells
        gain = prop_n[2] / c5[0][2]
        out.append(f"| {width:g} | {bn:.2f} | {normal} | {c5[0][2] * 1000:.1f} / {c5[1][2] * 1000:.1f}, "
                   f"{c5[2] * 100:.0f} % | {c75[0][2] * 1000:.1f} / {c75[1][2] * 1000:.1f}, {c75[2] * 100:.0f} % | "
                   f"{'-' if math.isnan(gain) else f'{gain:.1f}'} |")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=2000, help="Monte Carlo trials per configuration")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    print(f"camera {WIDTH_PX} x {HEIGHT_PX} px, f = {FOCAL_PX:g} px (assumed); seed {a.seed}, {a.trials} trials\n")
    for table in (table_formula(a.trials, rng), table_same_base(a.trials, rng), table_facade(a.trials, rng)):
        print("\n".join(table) + "\n")


if __name__ == "__main__":
    main()
