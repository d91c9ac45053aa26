"""Generate a large textured test scene and a warped copy with a known homography, streamed by strips.

The texture is a deterministic function of the pixel position: the plane is cut
into 384-px blocks, and each block shows a randomly chosen, flipped/transposed
and gain-adjusted crop of a real image (the Landsat crop of ../shared/data when
present, and scikit-image's sample photographs). The warped copy is computed
window by window from that function (no need to hold either image), so the
memory used is a few strips whatever the size; GeoTIFFs are tiled and
deflate-compressed, single band uint8, nodata 0 outside the warped footprint.

    python scripts/make_large_scene.py OUTDIR --size 33000 [--seed 0]

writes OUTDIR/left.tif, OUTDIR/right.tif and OUTDIR/truth.json
(H_right_from_left, pixel-centre convention).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import affine
import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rectify.raster import io as rio  # noqa: E402  (after the sys.path set-up above)

BLOCK = 384


def _sources() -> list[np.ndarray]:
    import skimage.data as sd

    imgs = []
    landsat = ROOT.parent / "shared" / "data" / "landsat_rgb" / "RGB.byte.tif"
    if landsat.is_file():
        d, v = rio.read_window(landsat, 0, 0, 791, 718)
        g = d.astype(np.float32).mean(axis=2)
        # the scene's valid core only
        ys, xs = np.nonzero(v)
        g = g[ys.min() + 60:ys.max() - 60, xs.min() + 60:xs.max() - 60]
        imgs.append(cv2.normalize(g, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8))
    for name in ("astronaut", "camera", "brick", "grass", "gravel", "coffee", "rocket"):
        a = getattr(sd, name)()
        if a.ndim == 3:
            a = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
        imgs.append(np.ascontiguousarray(a))
    return [a for a in imgs if min(a.shape) >= BLOCK]


class Texture:
    """Deterministic texture value at any integer pixel, evaluated by windows."""

    def __init__(self, seed: int = 0):
        self.src = _sources()
        self.seed = seed

    def _block(self, bi: int, bj: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, bi, bj])
        a = self.src[rng.integers(len(self.src))]
        r0 = rng.integers(0, a.shape[0] - BLOCK + 1)
        c0 = rng.integers(0, a.shape[1] - BLOCK + 1)
        b = a[r0:r0 + BLOCK, c0:c0 + BLOCK]
        v = rng.integers(8)
        if v & 1:
            b = b[::-1]
        if v & 2:
            b = b[:, ::-1]
        if v & 4:
            b = b.T
        gain = rng.uniform(0.7, 1.2)
        return np.clip(b.astype(np.float32) * gain + rng.uniform(-20, 20), 1, 255)

    def window(self, c0: int, r0: int, w: int, h: int) -> np.ndarray:
        out = np.empty((h, w), np.float32)
        for bi in range(r0 // BLOCK, (r0 + h - 1) // BLOCK + 1):
            for bj in range(c0 // BLOCK, (c0 + w - 1) // BLOCK + 1):
                b = self._block(bi, bj)
                y0, x0 = max(bi * BLOCK, r0), max(bj * BLOCK, c0)
                y1, x1 = min((bi + 1) * BLOCK, r0 + h), min((bj + 1) * BLOCK, c0 + w)
                out[y0 - r0:y1 - r0, x0 - c0:x1 - c0] = b[y0 - bi * BLOCK:y1 - bi * BLOCK,
                                                          x0 - bj * BLOCK:x1 - bj * BLOCK]
        return out


def truth_homography(size: int) -> np.ndarray:
    """H_right_from_left: rotation 8 deg, scale 0.93, mild perspective, about the centre."""
    c = (size - 1) / 2
    a, s = np.deg2rad(8.0), 0.93
    T1 = np.array([[1, 0, -c], [0, 1, -c], [0, 0, 1.0]])
    R = np.array([[s * np.cos(a), -s * np.sin(a), 0], [s * np.sin(a), s * np.cos(a), 0], [0, 0, 1]])
    P = np.array([[1, 0, 0], [0, 1, 0], [2e-6 * 8000 / size, -1.5e-6 * 8000 / size, 1]])
    T2 = np.array([[1, 0, c + 0.013 * size], [0, 1, c - 0.011 * size], [0, 0, 1.0]])
    return T2 @ P @ R @ T1


def generate(out: Path, size: int, seed: int = 0, strip: int = 512) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    tex = Texture(seed)
    H = truth_homography(size)
    Hi = np.linalg.inv(H)
    t0 = time.perf_counter()
    policy_l = rio.MaskPolicy("none")
    with rio.TiledWriter(out / "left.tif", size, size, 1, "uint8", affine.Affine.identity(), None, policy_l,
                         tile=512) as wl:
        for r0 in range(0, size, strip):
            h = min(strip, size - r0)
            wl.write(tex.window(0, r0, size, h).astype(np.uint8)[:, :, None], 0, r0)
    t1 = time.perf_counter()
    with rio.TiledWriter(out / "right.tif", size, size, 1, "uint8", affine.Affine.identity(), None,
                         rio.MaskPolicy("nodata", 0.0), tile=512) as wr:
        for r0 in range(0, size, strip):
            h = min(strip, size - r0)
            for c0 in range(0, size, 4096):
                w = min(4096, size - c0)
                ys, xs = np.mgrid[r0:r0 + h, c0:c0 + w].astype(np.float64)
                q = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]) 
                p = Hi @ q
                sx = (p[0] / p[2]).reshape(h, w)
                sy = (p[1] / p[2]).reshape(h, w)
                inside = (sx >= 0) & (sy >= 0) & (sx <= size - 1) & (sy <= size - 1)
                tile = np.zeros((h, w), np.uint8)
                if inside.any():
                    x0 = int(max(np.floor(sx[inside].min()) - 3, 0))
                    y0 = int(max(np.floor(sy[inside].min()) - 3, 0))
                    x1 = int(min(np.ceil(sx[inside].max()) + 3, size - 1))
                    y1 = int(min(np.ceil(sy[inside].max()) + 3, size - 1))
                    src = tex.window(x0, y0, x1 - x0 + 1, y1 - y0 + 1)
                    v = cv2.remap(src, (sx - x0).astype(np.float32), (sy - y0).astype(np.float32),
                                  cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
                    tile = np.where(inside, np.clip(v, 1, 255), 0).astype(np.uint8)
                wr.write(tile[:, :, None], c0, r0)
    t2 = time.perf_counter()
    truth = {"H_right_from_left": H.tolist(), "size": size, "seed": seed,
             "time_left_s": t1 - t0, "time_right_s": t2 - t1}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", type=int, default=33000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    t = generate(a.out, a.size, a.seed)
    print(json.dumps({k: v for k, v in t.items() if k != "H_right_from_left"}))


if __name__ == "__main__":
    main()
