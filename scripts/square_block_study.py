"""The square-symmetric block (seed 003, 2.2.1, Table 2.2) against the traditional block scheme.

Seed 003, 2.2.1: a traditional aerial block has 60 % forward and (OCR-damaged) "JO %" side overlap,
so its adjustment is not homogeneous in X and Y (error ellipses, as ORIMA shows them); symmetric
forward and side overlaps of more than 60 % with the projection centres on the nodes of a square grid
(the square-symmetric block, "KSB") let stereo models be formed along, across and diagonally, show a
point in up to 9 images and up to 20 models, and "somewhat increase the useful area of the block".
Table 2.2 compares the useful area (bounded by the projection centres) of the two schemes for blocks
of 20 strips of 20 images. The text of the seed holds the caption and these assumptions, not the
numbers of the table.

This script computes

1. Table 2.2 from its stated assumptions (20 x 20 images; square frames of side l; the useful area
   bounded by the projection centres), with the covered area, the multiplicity of images and models
   over the block, for the traditional 60/30 and 60/20 schemes and the square-symmetric 60/60 one;
2. the precision of synthetic blocks of both schemes adjusted by the project's bundle
   (:func:`stereo.block.bundle.adjust_bundle`, the covariance of every point): the mean standard
   errors in X, Y, Z and their ratio (the shape of the error ellipses), and the check-point errors.

    python scripts/square_block_study.py [--seeds 10] [--points 1500]

Models counted: pairs of images whose projection centres are neighbours on the grid (one step along,
across or diagonal), both seeing the point.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rectify.geometry.camera import Camera  # noqa: E402
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle  # noqa: E402
from tests.support.block_synthetic import make_block  # noqa: E402


@dataclass(frozen=True)
class Scheme:
    """A block scheme: forward and side overlap of square frames of side 1."""

    name: str
    forward: float
    side: float

    @property
    def base(self) -> float:
        return 1.0 - self.forward

    @property
    def spacing(self) -> float:
        return 1.0 - self.side


TRADITIONAL = Scheme("traditional 60/30", 0.6, 0.3)
TRADITIONAL_20 = Scheme("traditional 60/20", 0.6, 0.2)
SQUARE = Scheme("square-symmetric 60/60", 0.6, 0.6)


@dataclass(frozen=True)
class Geometry:
    """Table 2.2's quantities of a block of ``strips`` x ``images`` square frames of side 1 (areas in l^2)."""

    useful_area: float
    covered_area: float
    max_images: int
    max_models: int
    mean_images: float
    mean_models: float


def block_geometry(s: Scheme, strips: int = 20, images: int = 20, samples: int = 200) -> Geometry:
    """Areas and multiplicities; the means over the useful area (a ``samples`` x ``samples`` grid)."""
    useful = (images - 1) * s.base * (strips - 1) * s.spacing
    covered = ((images - 1) * s.base + 1.0) * ((strips - 1) * s.spacing + 1.0)
    cx = np.arange(images) * s.base
    cy = np.arange(strips) * s.spacing
    gx = np.linspace(0.0, cx[-1], samples)
    gy = np.linspace(0.0, cy[-1], samples)
    inx = np.abs(gx[:, None] - cx[None, :]) <= 0.5 + 1e-12  # (samples, images): frame covers the x of a point
    iny = np.abs(gy[:, None] - cy[None, :]) <= 0.5 + 1e-12
    nx, ny = inx.sum(1), iny.sum(1)
    imgs = nx[:, None] * ny[None, :]
    # neighbour pairs among the covering images: along (same strip, next image), across, diagonal
    ax = np.array([np.sum(r[:-1] & r[1:]) for r in inx])  # adjacent covering pairs along x
    ay = np.array([np.sum(r[:-1] & r[1:]) for r in iny])
    models = ax[:, None] * ny[None, :] + nx[:, None] * ay[None, :] + 2 * ax[:, None] * ay[None, :]
    return Geometry(useful, covered, int(imgs.max()), int(models.max()), float(imgs.mean()), float(models.mean()))


def table_2_2() -> list[str]:
    out = ["### Table 2.2 from its assumptions: blocks of 20 strips x 20 images, square frames of side l", "",
           "| scheme | base b / l | strip spacing a / l | useful area (bounded by centres) l^2 | covered area l^2 | "
           "useful / covered | most images on a point | most models on a point | mean images, models over "
           "the useful area |", "|---|---|---|---|---|---|---|---|---|"]
    for s in (TRADITIONAL, TRADITIONAL_20, SQUARE):
        g = block_geometry(s)
        out.append(f"| {s.name} | {s.base:.2f} | {s.spacing:.2f} | {g.useful_area:.2f} | {g.covered_area:.2f} | "
                   f"{g.useful_area / g.covered_area:.3f} | {g.max_images} | {g.max_models} | "
                   f"{g.mean_images:.2f}, {g.mean_models:.2f} |")
    t, q = block_geometry(TRADITIONAL), block_geometry(SQUARE)
    n_trad = 20 * 20
    # the square block covering the traditional block's useful area: strips needed
    strips_sq = math.ceil(19 * TRADITIONAL.spacing / SQUARE.spacing) + 1
    out += ["", f"Useful area, square-symmetric / traditional 60/30 (same 400 images): "
                f"{q.useful_area / t.useful_area:.3f}. Covering the useful area of the traditional block "
                f"({t.useful_area:.2f} l^2) with the square-symmetric scheme takes {strips_sq} strips of 20 "
                f"images ({strips_sq * 20} images, {strips_sq * 20 / n_trad:.2f} times as many)."]
    return out


def _square_camera() -> Camera:
    return Camera(focal_length_mm=30.0, pixel_size_mm=0.02, width=1500, height=1500)


@dataclass(frozen=True)
class BlockFigures:
    images: int
    points: int
    rays: float
    sx: float
    sy: float
    sz: float
    axis_ratio: float
    check: tuple[float, float, float]
    check_pred: tuple[float, float, float]
    sigma0: float


def adjust_scheme(s: Scheme, strips: int, per_strip: int, seed: int, n_points: int,
                  noise_px: float = 0.5) -> BlockFigures:
    """A synthetic block of scheme ``s`` adjusted by the bundle (corners + centre full control, 10 check points).

    Standard errors are averaged over the points inside the hull of the projection centres (the useful area)."""
    b = make_block(seed, strips=strips, images_per_strip=per_strip, forward_overlap=s.forward,
                   side_overlap=s.side, relief_m=30.0, n_points=n_points, image_noise_px=noise_px,
                   camera=_square_camera(), n_check=10, control_layout="corners+centre")
    res = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control,
                        options=BundleOptions(image_sigma_px=noise_px, covariance="full"))
    C = np.array([p.position for p in b.true_poses])
    inside = ((b.true_points[:, 0] >= C[:, 0].min()) & (b.true_points[:, 0] <= C[:, 0].max())
              & (b.true_points[:, 1] >= C[:, 1].min()) & (b.true_points[:, 1] <= C[:, 1].max()))
    ok = inside & np.isfinite(res.point_std).all(axis=1)
    std = res.point_std[ok]
    rms = np.sqrt(np.mean(std ** 2, axis=0))
    ratio = float("nan")
    if res.point_covariance is not None:  # horizontal error ellipses: semi-axis ratio a / b of each point
        ev = np.linalg.eigvalsh(res.point_covariance[ok][:, :2, :2])
        ratio = float(np.mean(np.sqrt(ev[:, 1] / ev[:, 0])))
    chk = np.sqrt(np.nanmean(np.asarray(res.check_errors) ** 2, axis=0))
    pred = np.sqrt(np.nanmean(np.asarray(res.check_std) ** 2, axis=0))
    rays = float(len(b.tracks.obs_point) / len(b.tracks.point_ids))
    return BlockFigures(len(b.true_poses), int(ok.sum()), rays, float(rms[0]), float(rms[1]), float(rms[2]), ratio,
                        (float(chk[0]), float(chk[1]), float(chk[2])), (float(pred[0]), float(pred[1]), float(pred[2])),
                        float(res.sigma0))


def table_bundle(seeds: int, n_points: int) -> list[str]:
    out = ["### Bundle on synthetic blocks (square 1500 x 1500 px frame, f = 30 mm, pixel 20 um, H = 1000 m, "
           "image noise 0.5 px, relief 30 m, 5 full control points, 10 check points)", "",
           "| scheme | strips x images | seed | images | points in the useful area (rays a point) | "
           "RMS sigma X, Y, Z m | sigma X / sigma Y | mean ellipse a / b | check-point RMSE X, Y, Z m (predicted) "
           "| sigma0 |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    agg: dict[str, list[BlockFigures]] = {}
    for (s, strips, per), seed in itertools.product(((TRADITIONAL, 4, 8), (SQUARE, 6, 8)), range(seeds)):
        f = adjust_scheme(s, strips, per, seed, n_points)
        agg.setdefault(s.name, []).append(f)
        chk = ", ".join(f"{v:.3f}" for v in f.check)
        pred = ", ".join(f"{v:.3f}" for v in f.check_pred)
        out.append(f"| {s.name} | {strips} x {per} | {seed} | {f.images} | {f.points} ({f.rays:.2f}) | {f.sx:.3f}, "
                   f"{f.sy:.3f}, {f.sz:.3f} | {f.sx / f.sy:.2f} | {f.axis_ratio:.2f} | {chk} ({pred}) | "
                   f"{f.sigma0:.3f} |")
    out += ["", "| scheme | mean sigma X, Y, Z m | mean sigma X / sigma Y | mean ellipse a / b | "
                "mean check RMSE X, Y, Z m | its prediction X, Y, Z m |", "|---|---|---|---|---|---|"]
    for name, fs in agg.items():
        sx, sy, sz = (float(np.mean([getattr(f, k) for f in fs])) for k in ("sx", "sy", "sz"))
        ch = np.sqrt(np.mean(np.square([f.check for f in fs]), axis=0))
        cp = np.sqrt(np.mean(np.square([f.check_pred for f in fs]), axis=0))
        ab = float(np.mean([f.axis_ratio for f in fs]))
        out.append(f"| {name} | {sx:.3f}, {sy:.3f}, {sz:.3f} | {sx / sy:.2f} | {ab:.2f} | {ch[0]:.3f}, {ch[1]:.3f}, "
                   f"{ch[2]:.3f} | {cp[0]:.3f}, {cp[1]:.3f}, {cp[2]:.3f} |")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="synthetic blocks per scheme")
    ap.add_argument("--points", type=int, default=1500, help="object points drawn per block")
    a = ap.parse_args(argv)
    print("\n".join(table_2_2()) + "\n")
    print("\n".join(table_bundle(a.seeds, a.points)) + "\n")


if __name__ == "__main__":
    main()
