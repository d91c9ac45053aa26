"""Checks of a `stereo surface` output folder shared by its tests and `scripts/surface_chain_study.py` (issue 27):
the NGI pair's block orientation from orthority's files, and the orthomosaic's shift against the single
orthophotos (``--keep-orthophotos``)."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import rasterio
from numpy.typing import NDArray

from rectify.formats.orthority import read_ext_param, read_int_param
from stereo.block.types import Pose
from stereo.formats.block import block_orientation_text


def write_orthority_orientation(folder: Path, out: Path) -> Path:
    """Write ``out/orientation.json``: the block orientation (cameras, poses, CRS) of orthority's
    ``orthority_int_param.yaml`` and ``orthority_ext_param.geojson`` in ``folder``. Returns the folder ``out``."""
    cams = read_int_param(folder / "orthority_int_param.yaml")
    ext = read_ext_param(folder / "orthority_ext_param.geojson")
    poses = [Pose(name, e["camera"] or next(iter(cams)), np.asarray(e["position"]), np.asarray(e["rotation"]))
             for name, e in ext.items()]
    out.mkdir(parents=True, exist_ok=True)
    (out / "orientation.json").write_text(block_orientation_text(cams, poses, crs=next(iter(ext.values()))["crs"]))
    return out


def mosaic_patches(out: Path, patch: int = 32) -> Iterator[tuple[int, int, NDArray[np.float64], NDArray[np.float64]]]:
    """Every ``patch`` x ``patch`` block of the orthomosaic ``out/ortho.tif`` (band 1) taken wholly from one image
    (``ortho.source.tif``), with texture (std >= 3 DN) and no nodata in that image's single orthophoto
    ``out/ortho_<stem>.tif`` (``--keep-orthophotos``): ``(row, col, mosaic block, orthophoto block)``, the
    orthophoto read at the same ground position (its grid must be aligned with the mosaic's: checked)."""
    names = json.loads((out / "pairs.json").read_text())["ortho"]["images"]
    with rasterio.open(out / "ortho.tif") as ds:
        mos = ds.read(1).astype(np.float64)
        mt = ds.transform
    with rasterio.open(out / "ortho.source.tif") as ds:
        src = ds.read(1)
    for r0 in range(0, mos.shape[0] - patch, patch):
        for c0 in range(0, mos.shape[1] - patch, patch):
            s = src[r0:r0 + patch, c0:c0 + patch]
            k = int(s[0, 0])
            if k == 0 or not (s == k).all():
                continue
            a = mos[r0:r0 + patch, c0:c0 + patch]
            with rasterio.open(out / f"ortho_{Path(names[k - 1]).stem}.tif") as ds:
                cc, rr = ~ds.transform * (mt * (c0, r0))
                if abs(cc - round(cc)) > 1e-6 or abs(rr - round(rr)) > 1e-6:
                    raise AssertionError(f"orthophoto grid of {names[k - 1]!r} not aligned with the mosaic's")
                b = ds.read(1, window=((round(rr), round(rr) + patch), (round(cc), round(cc) + patch)),
                            boundless=True, fill_value=0).astype(np.float64)
            if (b == 0).any() or a.std() < 3:
                continue
            yield r0, c0, a, b


def mosaic_shifts(out: Path, patch: int = 32) -> list[float]:
    """Shift (px) of the orthomosaic against the single orthophotos by phase correlation, one per block of
    :func:`mosaic_patches`."""
    win = cv2.createHanningWindow((patch, patch), cv2.CV_64F)
    return [math.hypot(*cv2.phaseCorrelate(a, b, win)[0]) for _r, _c, a, b in mosaic_patches(out, patch)]
