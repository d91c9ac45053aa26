"""Pairwise height agreement before and after the RPC block adjustment (issue 28), on the tie tracks.

For every track seen in all three images of a triplet, intersect it from each pair that shares the
reference image (the first listed) with the plain RPCs and with the adjusted ones (``adjustment.json`` of
``rectify rpc-adjust``), and print the median and NMAD of the height difference between the two pairs:
the constant height bias between pair DSMs that the adjustment should remove.

    rectify rpc-adjust IMG1 IMG2 IMG3 -o OUT
    python scripts/rpc_adjust_pairs.py OUT/adjustment.json OUT/residuals.csv [--reference IMG_NAME]

Heights: metres above the ellipsoid; pixel convention of ``rectify.geometry.rpc``.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from rectify.formats.rpc import rpc_from_raster
from rectify.geometry.rpc import RPCRefinement


def intersect(models, pixels, h0: float, iterations: int = 20) -> np.ndarray:
    """Least-squares ground (N, 3) of measurements pixels[k] (N, 2) in models[k] (numeric Jacobians)."""
    g = models[0].localize(pixels[0], h0)
    m_lon = 111_320.0 * np.cos(np.radians(g[:, 1]))
    for _ in range(iterations):
        J = np.zeros((len(g), 2 * len(models), 3))
        r = np.zeros((len(g), 2 * len(models)))
        for k, (m, p) in enumerate(zip(models, pixels, strict=True)):
            r[:, 2 * k:2 * k + 2] = p - m.project(g)
            for a, step in enumerate((0.5 / m_lon, np.full(len(g), 0.5 / 111_132.0), np.full(len(g), 0.5))):
                d = np.zeros_like(g)
                d[:, a] = step
                J[:, 2 * k:2 * k + 2, a] = (m.project(g + d) - m.project(g - d))
        dx = np.linalg.solve(np.einsum("nia,nib->nab", J, J), np.einsum("nia,ni->na", J, r)[..., None])[..., 0]
        g = g + np.column_stack([dx[:, 0] / m_lon, dx[:, 1] / 111_132.0, dx[:, 2]])
    return g


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("adjustment", type=Path)
    ap.add_argument("residuals", type=Path)
    ap.add_argument("--reference", default=None, help="image name shared by the two pairs (default: the first)")
    a = ap.parse_args()
    doc = json.loads(a.adjustment.read_text())
    imgs = doc["images"]
    names = [im["name"] for im in imgs]
    ref = names.index(a.reference) if a.reference else 0
    others = [j for j in range(len(names)) if j != ref][:2]
    plain = [rpc_from_raster(im["image"]) for im in imgs]
    adjusted = [RPCRefinement(r, doc["model"], np.array(im["params_plain"])) for r, im in zip(plain, imgs, strict=True)]
    tracks: dict[str, dict[int, tuple[float, float]]] = {}
    for row in csv.DictReader(a.residuals.open()):
        if float(row["weight"]) > 0.5:
            tracks.setdefault(row["id"], {})[names.index(row["image"])] = (float(row["col"]), float(row["row"]))
    full = [t for t in tracks.values() if all(j in t for j in (ref, *others))]
    if not full:
        raise SystemExit("no track is seen in all three images")
    px = {j: np.array([t[j] for t in full]) for j in (ref, *others)}
    h0 = float(plain[ref].height_off)
    print(f"{len(full)} tracks in {names[ref]} + {names[others[0]]} + {names[others[1]]}")
    for label, models in (("plain RPCs", plain), ("adjusted", adjusted)):
        h = [intersect([models[ref], models[o]], [px[ref], px[o]], h0)[:, 2] for o in others]
        d = h[0] - h[1]
        nmad = 1.4826 * np.median(np.abs(d - np.median(d)))
        print(f"{label}: height pair {names[ref]}/{names[others[0]]} minus pair {names[ref]}/{names[others[1]]}: "
              f"median {np.median(d):+.3f} m, NMAD {nmad:.3f} m")


if __name__ == "__main__":
    main()
