#!/usr/bin/env python
"""Study: independent models as a finished method (seed 002, 3.1-3.2) against the bundle adjustment.

The blocks of ``tests/stereo/test_block_models_adjust.py`` (``tests.support.block_synthetic.make_block``
with a 40 mm camera of 2000 x 1500 px of 20 um, base / height 0.4):

1. 3 strips x 6 images, 0.5 px, 5 full control points, 30 check points, seeds 1-6: check-point RMSE
   of ``stereo block`` (``run_block``) with the bundle and with ``--method independent-models`` on the
   same files; then ``adjust_models`` on the generator's tracks: sigma0 and RMS(error / std);
2. one strip of 10 images (9 models), 0.3 px, the camera's radial distortion k1 = -0.01 not given to
   the models, 15 control points (5 stations x 3 rows) and 40 check points: check-point RMSE after the
   similarity alone and after the strip polynomial of degree 2 and 3, for independent and partially
   dependent models, and for the same strip without the distortion;
3. the 140-image block on a curved Earth of ``tests/cli/test_block_observations.py``
   (``tests.support.block_curved``: 10 strips x 14 images, 152 mm, GNSS 5 cm, INS, 28 control and 24
   check points) through ``stereo block --observations`` with either method: check-point RMSE.

The figures of docs/block.md ("Independent models") are this script's output.

Usage::

    PYTHONPATH=. python scripts/independent_models_study.py [--seeds 1,2,3,4,5,6]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from rectify.geometry.camera import Camera
from stereo.actions.block import BlockOptions, run_block
from stereo.block.bundle.adjust import BundleOptions
from stereo.block.independent import independent_models
from stereo.block.model_adjust import ModelAdjustOptions, adjust_models
from stereo.block.models import IndependentOptions
from stereo.block.strip_adjust import correct_strips
from stereo.block.types import BlockControl
from stereo.cli.main import cli
from tests.support.block_curved import make_curved_block, write_curved_block
from tests.support.block_files import write_block_files
from tests.support.block_synthetic import SyntheticBlock, make_block, strip_control


def camera(k1: float = 0.0) -> Camera:
    """The study's 40 mm camera (optionally with radial distortion k1)."""
    return Camera(focal_length_mm=40.0, pixel_size_mm=0.02, width=2000, height=1500, principal_point_mm=(0.0, 0.0),
                  distortion={"k1": k1} if k1 else {})


def rmse3d(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1))))


def compare(seed: int, tmp: Path) -> tuple[float, float]:
    """Check-point RMSE 3D of the bundle and of the independent models through ``run_block``."""
    blk = make_block(seed, control_layout="corners+centre", n_check=30, n_points=1500, camera=camera())
    (tmp / f"s{seed}").mkdir()
    images, cam, _poses, ctrl, ties, checks = write_block_files(tmp / f"s{seed}", blk, gnss=False)
    out = []
    for method in ("bundle", "independent-models"):
        opts = BlockOptions(check_ids=checks, method=method, report=False, stac=False,
                            bundle=BundleOptions(robust="tukey", image_sigma_px=0.5, max_iterations=100))
        res = run_block(images, out_dir=tmp / f"s{seed}" / method, camera=cam, control=ctrl, tracks=ties, options=opts)
        out.append(rmse3d(res.bundle.check_errors))
    return out[0], out[1]


def precision(seed: int) -> str:
    """sigma0 and RMS(error / std) of ``adjust_models`` on the generator's tracks."""
    blk = make_block(seed, control_layout="corners+centre", n_check=30, n_points=1500, camera=camera())
    mb = independent_models(blk.cameras, ["cam"] * len(blk.tracks.images), blk.tracks)
    r = adjust_models(mb, control=blk.control, options=ModelAdjustOptions(image_sigma_px=0.5))
    q = np.asarray(r.check_errors) / np.asarray(r.check_std)
    return (f"sigma0 {r.sigma0:.3f}, RMS(error/std) x y z {np.sqrt(np.mean(q ** 2, axis=0)).round(2).tolist()}, "
            f"max {np.abs(q).max():.2f}")


def strip(k1: float) -> tuple[SyntheticBlock, BlockControl]:
    """The 10-image strip and its control (15 points in 5 stations x 3 rows) and 40 check points."""
    blk = make_block(3, strips=1, images_per_strip=10, camera=camera(k1), n_points=1500, control_layout="none",
                     n_check=0, image_noise_px=0.3)
    return blk, strip_control(blk, 40)

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2,3,4,5,6")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    print("1. check-point RMSE 3D, bundle vs independent models (run_block, same files)")
    with tempfile.TemporaryDirectory() as d:
        for seed in seeds:
            b, m = compare(seed, Path(d))
            print(f"  seed {seed}: bundle {b:.3f} m, independent models {m:.3f} m, ratio {m / b:.2f}; "
                  f"adjust_models: {precision(seed)}")
    print("2. a bent strip: check-point RMSE x, y, z (similarity only -> degree 2 -> degree 3)")
    for k1, dependent, label in ((-0.01, False, "independent"), (-0.01, True, "partially dependent"),
                                 (0.0, False, "independent, no distortion")):
        blk, control = strip(k1)
        mb = independent_models({"cam": camera()}, ["cam"] * len(blk.tracks.images), blk.tracks,
                                options=IndependentOptions(dependent=dependent))
        r2, r3 = (correct_strips(mb, control, degree=d) for d in (2, 3))
        f = [np.sqrt(np.mean(np.asarray(e) ** 2, axis=0)).round(2).tolist()
             for e in (r2.check_before, r2.check_errors, r3.check_errors)]
        print(f"  {label}: {f[0]} -> {f[1]} -> {f[2]} m")
    print("3. the curved 140-image block from its observations CSV (default frame)")
    blk = make_curved_block(0)
    with tempfile.TemporaryDirectory() as d:
        files = write_curved_block(Path(d) / "in", blk)
        for method in ("bundle", "independent-models"):
            r = CliRunner().invoke(cli, ["block", "--observations", str(files["observations"]), "--camera",
                                         str(files["camera"]), "--poses", str(files["poses"]), "--control",
                                         str(files["control"]), "--check", ",".join(blk.check_ids), "-o",
                                         str(Path(d) / method), "--no-report", "--no-stac", "--method", method])
            print(f"  {method}: " + " ".join(ln for ln in r.output.splitlines() if ln.startswith("check:")))


if __name__ == "__main__":
    main()
