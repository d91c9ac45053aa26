#!/usr/bin/env python
"""Seed 000's open question: how do the correlations between the errors of the
relative-orientation elements compare across the three systems?

On the same point sets -- the six classical standard (von Gruber) points, a
3 x 3 grid, Wolf & Dewitt's relor sample and real matches of the NGI
``ngi_strip05`` pair -- compute the a-priori correlation matrix of the five
elements of each system (``basis``, ``left-image``, ``dobrynin-pimshina``)
from the weighted normal equations of the coplanarity adjustment, and
tabulate the largest |correlation| and the condition numbers. Output is
Markdown on stdout (or ``--out FILE``).

Usage::

    python scripts/ro_correlation_study.py [--shared ../shared/data] [--out study.md]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

from stereo.relative import SYSTEMS, RelativeOrientation, precision_structure

ROOT = Path(__file__).resolve().parents[1]


def standard_sets(f: float = 152.0, b: float = 92.0, d: float = 90.0) -> dict[str, tuple]:
    """Classical vertical pair (flat terrain, 60 % overlap, 230 mm frame): exact photo coordinates."""
    six = np.array([[0, 0], [b, 0], [0, d], [b, d], [0, -d], [b, -d]], dtype=float)
    grid = np.array([[x, y] for y in (d, 0, -d) for x in (0, b / 2, b)], dtype=float)
    out = {}
    for name, left in (("six standard points", six), ("3 x 3 grid", grid)):
        right = left - [b, 0.0]
        out[name] = (left, right, f, "exact vertical pair, f = 152 mm, photo base 92 mm, d = 90 mm")
    return out


def dewitt_set(shared: Path):
    p = shared / "dewitt_samples" / "relor_sample.dat"
    if not p.is_file():
        return None
    lines = [ln.split() for ln in p.read_text().splitlines() if ln.strip()]
    f = float(lines[0][0])
    d = np.array([[float(v) for v in r[1:]] for r in lines[1:]])
    return d[:, :2], d[:, 2:], f, "Wolf & Dewitt relor_sample (6 measured points, f = 152.113 mm)"


def ngi_set(shared: Path):
    p = shared / "ngi_strip05"
    if not (p / "3324c_2015_1004_05_0182_RGB.tif").is_file():
        return None
    from rectify.features import MatcherConfig, match_images
    from rectify.geometry.camera import Camera

    res = match_images(p / "3324c_2015_1004_05_0182_RGB.tif", p / "3324c_2015_1004_05_0184_RGB.tif",
                       config=MatcherConfig(verify="fundamental"))
    cam = Camera(120.0, 0.144, 640, 1152)
    left, right = cam.photo_from_pixel(res.matches.left), cam.photo_from_pixel(res.matches.right)
    return left, right, 120.0, f"NGI strip 05, images 0182/0184: {len(left)} SIFT+LSM matches, f = 120 mm"


def study(sets: dict[str, tuple]) -> str:
    out = ["# Correlation of relative-orientation elements in three systems", "",
           "A-priori correlation matrices (sigma0 = 1) from the weighted normal equations of the "
           "coplanarity adjustment at the solution; condition numbers of the column-scaled normal "
           "matrix (= of the correlation structure) and of the raw normal matrix (all elements are "
           "angles in radians).", ""]
    summary = ["| point set | system | largest abs(r) (pair) | 2nd largest | mean abs(r) | cond (scaled) "
               "| cond (raw) |",
               "|---|---|---|---|---|---|---|"]
    details = []
    for set_name, (left, right, f, desc) in sets.items():
        # solution in one system (exact sets converge to zero angles), then each system at the same geometry
        ro = RelativeOrientation.from_points(left, right, focal_length_mm=f, system="left-image")
        details += [f"## {set_name}", "", desc + ".", ""]
        for sname, sys_ in SYSTEMS.items():
            p = ro.to_system(sname)
            ps = precision_structure(sname, p, left, right, f)
            C = ps.correlation
            pairs = sorted(((abs(C[i, j]), C[i, j], sys_.names[i], sys_.names[j])
                            for i, j in itertools.combinations(range(5), 2)), reverse=True)
            mean = float(np.mean([a for a, *_ in pairs]))
            summary.append(f"| {set_name} | {sname} | {pairs[0][1]:+.3f} ({pairs[0][2]}, {pairs[0][3]}) | "
                           f"{pairs[1][1]:+.3f} ({pairs[1][2]}, {pairs[1][3]}) | {mean:.3f} | "
                           f"{ps.condition_number:.3g} | {ps.condition_number_raw:.3g} |")
            details += [f"**{sname}** (elements {', '.join(sys_.names)}; values in degrees: "
                        + ", ".join(f"{np.degrees(v):.4f}" for v in p) + ")", "",
                        "| | " + " | ".join(sys_.names) + " |", "|---" * 6 + "|"]
            for i in range(5):
                details.append(f"| {sys_.names[i]} | " + " | ".join(f"{C[i, j]:+.3f}" for j in range(5)) + " |")
            details.append("")
    return "\n".join(out + summary + [""] + details)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    sets = standard_sets()
    for name, fn in (("Dewitt relor sample", dewitt_set), ("NGI real matches", ngi_set)):
        s = fn(a.shared)
        if s is None:
            print(f"note: {name} skipped (data not found under {a.shared})", file=sys.stderr)
        else:
            sets[name] = s
    text = study(sets)
    if a.out:
        a.out.write_text(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
