"""The true orthomosaic of a rendered block with known surface (issue 27): geolocation and shift figures.

A ``--strips`` x ``--per-strip`` block of 240 x 180 px frames (0.25 m ground pixel, 100 m above the
terrain, 60 % forward and 30 % side overlap; ``tests/support/block_surface.py``; the rendered grey value
is 20 + 215 x the terrain's texture) is orthorectified image by image with the true poses on the true
surface (``rectify.raster.ortho.orthorectify``, ``--true-ortho``, 0.25 m), and the orthophotos are
mosaicked with the least-transformed seams over that surface (``rectify.raster.mosaic.mosaic``,
``dsm=``, provenance). The local ground frame is placed in EPSG:32632 at (500 000, 5 000 000).

Printed: the mosaic's summary; the phase-correlation shift (64 px patches, Hann window) of the mosaic
against the truth (the texture at the mosaic's pixel centres), of the mosaic against each single
orthophoto over the patches lying in its zone (provenance), and of those single orthophotos against the
truth: median, 90th percentile, maximum, in output pixels.

Usage:
    nice python scripts/mosaic_block_study.py [--strips 3] [--per-strip 4] [--seed 5] [--relief 6]
        [--work DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import rasterio
from affine import Affine

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rectify.geometry.sensors import FrameModel  # noqa: E402
from rectify.raster.dem import Dem  # noqa: E402
from rectify.raster.mosaic import MosaicOptions, mosaic  # noqa: E402
from rectify.raster.ortho import OrthoOptions, orthorectify  # noqa: E402
from stereo.formats.block import read_block_orientation  # noqa: E402
from tests.support.block_surface import CAMERA, GSD, make_surface_block  # noqa: E402

CRS = "EPSG:32632"
OFFSET = np.array([500_000.0, 5_000_000.0])


def _shifts(a: np.ndarray, b: np.ndarray, ok: np.ndarray, patch: int = 64) -> list[float]:
    han = cv2.createHanningWindow((patch, patch), cv2.CV_64F)
    out = []
    for r0 in range(0, a.shape[0] - patch + 1, patch // 2):
        for c0 in range(0, a.shape[1] - patch + 1, patch // 2):
            if ok[r0:r0 + patch, c0:c0 + patch].all():
                pa = np.ascontiguousarray(a[r0:r0 + patch, c0:c0 + patch], dtype=np.float64)
                pb = np.ascontiguousarray(b[r0:r0 + patch, c0:c0 + patch], dtype=np.float64)
                if pa.std() > 2:
                    (dx, dy), _ = cv2.phaseCorrelate(pa, pb, han)
                    out.append(float(np.hypot(dx, dy)))
    return out


def _stats(name: str, s: list[float]) -> str:
    if not s:
        return f"{name}: no patch"
    return (f"{name}: {len(s)} patches, median {np.median(s):.4f} px, 90% {np.percentile(s, 90):.4f} px, "
            f"max {max(s):.4f} px")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--strips", type=int, default=3)
    ap.add_argument("--per-strip", type=int, default=4)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--relief", type=float, default=6.0)
    ap.add_argument("--work", type=Path, default=None)
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="mosaic_block_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    blk = make_surface_block(work / "block", strips=a.strips, per_strip=a.per_strip, seed=a.seed,
                             relief_m=a.relief)
    ter = blk.terrain
    # the true surface as a GeoTIFF (cell centres at origin + (c, -r) * cell)
    t = Affine(ter.cell_m, 0, ter.origin[0] + OFFSET[0] - ter.cell_m / 2, 0, -ter.cell_m,
               ter.origin[1] + OFFSET[1] + ter.cell_m / 2)
    dem_path = work / "surface.tif"
    with rasterio.open(dem_path, "w", driver="GTiff", width=ter.dem.shape[1], height=ter.dem.shape[0], count=1,
                       dtype="float32", crs=CRS, transform=t) as ds:
        ds.write(ter.dem.astype(np.float32), 1)
    dem = Dem.from_path(dem_path)
    orient = read_block_orientation(blk.folder / "orientation.json")
    orthos = []
    for pose in orient.poses:
        model = FrameModel(CAMERA, pose.position + np.r_[OFFSET, 0.0], pose.rotation, CRS)
        dst = work / f"ortho_{Path(pose.image).stem}.tif"
        orthorectify(blk.images / pose.image, dst, model, dem, resolution=GSD,
                     options=OrthoOptions(true_ortho=True, threads=2, min_valid_share=0.0), overwrite=True)
        orthos.append(dst)
    t1 = time.perf_counter()
    r = mosaic(orthos, work / "mosaic.tif", options=MosaicOptions(dsm=str(dem_path), feather_px=8),
               provenance=work / "mosaic.source.tif", overwrite=True)
    t2 = time.perf_counter()
    print(f"{len(orthos)} true orthophotos in {t1 - t0:.1f} s (rendering included), mosaic {t2 - t1:.2f} s; {work}")
    for line in r.summary_lines():
        print(line)
    with rasterio.open(work / "mosaic.tif") as ds:
        m, mt = ds.read(1).astype(np.float64), ds.transform
        ok = ds.read_masks(1) > 0
    with rasterio.open(work / "mosaic.source.tif") as ds:
        src = ds.read(1)
    cc, rr = np.meshgrid(np.arange(m.shape[1]) + 0.5, np.arange(m.shape[0]) + 0.5)
    xy = np.column_stack([(mt.c + mt.a * cc).ravel() - OFFSET[0], (mt.f + mt.e * rr).ravel() - OFFSET[1]])
    truth = (20 + 215 * ter._sample(ter.texture, xy)).reshape(m.shape)
    ok &= np.isfinite(truth)
    print(_stats("mosaic against the truth", _shifts(np.nan_to_num(truth), m, ok)))
    err = (m - truth)[ok]
    print(f"grey-value difference mosaic - truth over {ok.sum()} valid pixels: RMS {np.sqrt((err ** 2).mean()):.2f}, "
          f"mean {err.mean():+.2f}")
    per_image: list[float] = []
    single_truth: list[float] = []
    for k, path in enumerate(orthos, start=1):
        with rasterio.open(path) as ds:
            o, to = ds.read(1).astype(np.float64), ds.transform
            vis = ds.read(ds.count) == 2
        dc, dr = int(round((to.c - mt.c) / mt.a)), int(round((to.f - mt.f) / mt.e))
        h, w = o.shape
        if dr < 0 or dc < 0 or dr + h > m.shape[0] or dc + w > m.shape[1]:
            continue
        zone = (src[dr:dr + h, dc:dc + w] == k) & vis
        per_image += _shifts(o, m[dr:dr + h, dc:dc + w], zone)
        single_truth += _shifts(np.nan_to_num(truth[dr:dr + h, dc:dc + w]), o, zone & ok[dr:dr + h, dc:dc + w])
    print(_stats("mosaic against the single orthophotos (their zones)", per_image))
    print(_stats("the single orthophotos against the truth (same patches)", single_truth))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
