"""Render the synthetic stereo pair (DEM + texture, two frame cameras) with its control file.

    python scripts/render_synthetic_pair.py OUTDIR [--seed 0] [--size 480]

Writes left.png, right.png, camera.json and control.csv (DEM points projected into both photos).
"""

from __future__ import annotations

import argparse

from stereo.actions.scene import make_scene, write_scene_inputs

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=480)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args()
    s = make_scene(a.seed, size_px=a.size)
    r = write_scene_inputs(s, a.out, seed=a.seed, overwrite=a.overwrite)
    print(f"wrote {r['left']}, {r['right']}, {r['camera']}, {r['control']}")
