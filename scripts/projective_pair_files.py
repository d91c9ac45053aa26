#!/usr/bin/env python
"""Write the synthetic uncalibrated pair of docs/universal.md ("What is measured") as files.

The scene is ``tests/support/projective_scene.pair_scene`` (f = 24 mm, 5 um pixels, fy = 1.04 fx,
skew 0.015 fx, principal point off centre; 0.5 px noise): 50 tie points (``m.csv``), 30 control
points ``c0``..``c29`` (``control.csv``; use ``c14``..``c29`` as checks), the true camera as a pixel
camera (``cam.json``) and a wrong one (``wrongcam.json``: f + 10 %, square pixels, no skew, centred
principal point).

Usage::

    python scripts/projective_pair_files.py OUT_DIR [--seed 31] [--noise 0.5]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rectify.formats.tables import write_control, write_matches  # noqa: E402
from rectify.geometry.points import ControlTable, Matches  # noqa: E402
from tests.support.projective_scene import pair_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=31)
    ap.add_argument("--noise", type=float, default=0.5)
    a = ap.parse_args()
    d = a.out_dir
    d.mkdir(parents=True, exist_ok=True)
    sc = pair_scene(a.seed, n=80, noise_px=a.noise)
    write_matches(d / "m.csv", Matches(tuple(f"t{i}" for i in range(50)), sc.left[:50], sc.right[:50]))
    ids = tuple(f"c{i}" for i in range(30))
    write_control(d / "control.csv", ControlTable(ids, sc.left[50:], sc.right[50:], sc.X[50:]))
    cam = sc.camera
    (d / "cam.json").write_text(json.dumps({
        "fx_px": cam.focal_px, "fy_px": cam.fy_px, "skew_px": cam.skew_px,
        "principal_point_px": [float(c) for c in cam.principal_point_px], "width": cam.width, "height": cam.height}))
    (d / "wrongcam.json").write_text(json.dumps({
        "focal_length_px": cam.focal_px * 1.1, "principal_point_px": [cam.width / 2, cam.height / 2],
        "width": cam.width, "height": cam.height}))
    print(f"wrote {d}/m.csv, control.csv, cam.json, wrongcam.json")


if __name__ == "__main__":
    main()
