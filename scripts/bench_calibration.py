"""Benchmark: our calibration against OpenCV's calibrateCamera in the same run.

1. Real chessboard views (``--chessboard DIR``, default ``../shared/data/calibration_chessboard``):
   the same corners to both; RMS reprojection error, interior orientation, standard errors
   (ours, OpenCV's ``calibrateCameraExtended`` and a Monte Carlo at the measured sigma0).
2. The published calibration (``--reference FILE``, default ``../shared/data/calibration_reference/calib1.dat``).
3. A synthetic 3D test field with known truth at 0.1-0.5 px noise: ours from DLT starts alone;
   OpenCV without an initial camera matrix (refused for non-planar targets) and with
   ``CALIB_USE_INTRINSIC_GUESS``.
4. A synthetic zoom lens at 5 settings: the model from 4 predicts the held-out one.

Usage: ``python scripts/bench_calibration.py [--mc 200] [--trials 20]``. Sections whose data are
missing are skipped with a note.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository's tests.support, run from anywhere

from rectify.errors import CalibrationError  # noqa: E402
from stereo.calibration.model import Intrinsics  # noqa: E402
from stereo.calibration.result import Calibration  # noqa: E402
from stereo.calibration.views import TargetView  # noqa: E402
from stereo.calibration.zoom import ZoomModel  # noqa: E402
from stereo.features.targets import Chessboard, detect_chessboards  # noqa: E402
from tests.support.calibration_synthetic import board_scene, field_scene, zoom_camera  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT / ".." / "shared" / "data"
NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")  # OpenCV's order of stdDeviationsIntrinsics


def _cv_calibrate(views, size, flags=0, K0=None):
    obj = [v.object_xyz.astype(np.float32) for v in views]
    img = [v.pixel.astype(np.float32).reshape(-1, 1, 2) for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    r = cv2.calibrateCameraExtended(obj, img, size, K0, None, flags=flags, criteria=crit)  # type: ignore[call-overload]
    rms, K, d, _, _, std_i = r[0], r[1], r[2].ravel(), r[3], r[4], r[5].ravel()
    vals = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "k1": d[0], "k2": d[1], "p1": d[2],
            "p2": d[3], "k3": d[4] if len(d) > 4 else 0.0}
    std = dict(zip(NAMES, std_i[[0, 1, 2, 3, 4, 5, 6, 7, 8]], strict=True))
    return float(rms), vals, std


def section_chessboard(folder: Path, n_mc: int) -> None:
    paths = sorted(folder.glob("left*.jpg"))
    if not paths:
        print(f"[chessboard] skipped: no images in {folder}")
        return
    views, missing, size = detect_chessboards(paths, Chessboard(9, 6, 1.0))
    print(f"[chessboard] {len(views)} of {len(paths)} views, {size[0]} x {size[1]} px, 54 corners each; "
          f"not found: {missing or 'none'}")
    t = time.perf_counter()
    cal = Calibration.from_views(views, *size)
    t_ours = time.perf_counter() - t
    t = time.perf_counter()
    rms_cv, cv_vals, cv_std = _cv_calibrate(views, size)
    t_cv = time.perf_counter() - t
    print(f"  RMS reprojection error: ours {cal.rms_px:.9f} px, OpenCV {rms_cv:.9f} px, "
          f"ratio {cal.rms_px / rms_cv:.9f}")
    print(f"  time: ours {t_ours:.2f} s, OpenCV {t_cv:.2f} s; sigma0 {cal.sigma0_px:.4f} px")
    # Monte Carlo: noise at sigma0 on the adjusted image points, re-solve from the solution
    rng = np.random.default_rng(15)
    exact = [TargetView(v.name, tv.object_xyz, v.pixel + v.residuals, v.ids)
             for v, tv in zip(cal.views, views, strict=True)]
    start = (cal.intrinsics.vector, cal.adjustment.poses)
    est = []
    t = time.perf_counter()
    for _ in range(n_mc):
        noisy = [TargetView(v.name, v.object_xyz, v.pixel + rng.normal(0, cal.sigma0_px, v.pixel.shape),
                            v.ids) for v in exact]
        c = Calibration.from_views(noisy, *size, start=start)
        est.append([c.value(n) for n in cal.names])
    mc = np.std(np.array(est), axis=0, ddof=1)
    print(f"  Monte Carlo: {n_mc} trials in {time.perf_counter() - t:.1f} s (relative precision of an MC std "
          f"~{100 / math.sqrt(2 * n_mc):.0f}%)")
    print(f"  {'elem':>4} {'ours':>12} {'+- ours':>10} {'OpenCV':>12} {'+- OpenCV':>10} {'diff/se':>8} "
          f"{'MC std':>10} {'se/MC':>6}")
    for k, n in enumerate(cal.names):
        se = cal.std_errors[n]
        print(f"  {n:>4} {cal.value(n):12.6f} {se:10.6f} {cv_vals[n]:12.6f} {cv_std[n]:10.6f} "
              f"{(cal.value(n) - cv_vals[n]) / se:8.4f} {mc[k]:10.6f} {se / mc[k]:6.3f}")


def section_reference(path: Path) -> None:
    if not path.is_file():
        print(f"[published calibration] skipped: {path} not found")
        return
    from calib1_bouguet import read_calib1  # the one reader of calib1.dat (a script beside this one)

    data = read_calib1(path)
    w, h, views, ref = data.width, data.height, data.views, [float(v) for v in data.published]
    nv, (gc, gr) = len(views), data.grid
    cal = Calibration.from_views(views, w, h, distortion=("k1", "k2", "p1", "p2"))
    rms_cv, cv_vals, _ = _cv_calibrate(views, (w, h), flags=cv2.CALIB_FIX_K3)
    ci = cal.intrinsics
    print(f"[published calibration] {nv} views of a {gc} x {gr} grid, {w} x {h} px (k3 fixed at 0)")
    print(f"  {'':>10} {'published':>11} {'ours':>11} {'OpenCV':>11}")
    for name, r, o in zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), ref[:8],
                          (ci.fx, ci.fy, ci.cx, ci.cy, ci.k1, ci.k2, ci.p1, ci.p2), strict=True):
        print(f"  {name:>10} {r:11.5f} {o:11.5f} {cv_vals[name]:11.5f}")
    ex, ey = cal.pixel_error_std
    print(f"  {'pixel err':>10} {ref[8]:.5f} {ref[9]:.5f} ours {ex:.5f} {ey:.5f}; RMS ours {cal.rms_px:.5f}, "
          f"OpenCV {rms_cv:.5f}")
    print(f"  standard errors (ours): fx {cal.std_errors['fx']:.3f}, fy {cal.std_errors['fy']:.3f}, cx "
          f"{cal.std_errors['cx']:.3f}, cy {cal.std_errors['cy']:.3f} px; published +- / ours: "
          f"{9.48 / cal.std_errors['fx']:.3f}, {8.83 / cal.std_errors['fy']:.3f}, {8.54 / cal.std_errors['cx']:.3f}, "
          f"{13.28 / cal.std_errors['cy']:.3f}")


def section_field(n_trials: int) -> None:
    print("[3D field] synthetic, 3 views of 60 points in a 2 x 1.5 x 0.6 box; truth: 640 x 480, fx 800, fy 796, "
          "k1 -0.15, k2 0.12, p1 0.0012, p2 -0.0008")
    truth = field_scene(np.random.default_rng(0), n_views=1).camera
    dist = ("k1", "k2", "p1", "p2")
    for noise in (0.1, 0.3, 0.5):
        z_ours, z_cv, z_cv_dlt, refused, cv_rms_ratio = [], [], [], 0, []
        for s in range(n_trials):
            sc = field_scene(np.random.default_rng(1000 + s), n_views=3, n_points=60, noise_px=noise)
            cal = Calibration.from_views(sc.views, 640, 480, distortion=dist)
            z_ours += [(cal.value(n) - float(getattr(truth, n))) / cal.std_errors[n] for n in cal.names]
            try:
                _cv_calibrate(sc.views, (640, 480), flags=cv2.CALIB_FIX_K3)
            except cv2.error:
                refused += 1
            K0 = np.array([[640.0, 0, 319.5], [0, 640.0, 239.5], [0, 0, 1]])
            try:
                rms, vals, _ = _cv_calibrate(sc.views, (640, 480), cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3, K0)
                z_cv += [(vals[n] - float(getattr(truth, n))) / cal.std_errors[n] for n in cal.names]
                cv_rms_ratio.append(cal.rms_px / rms)
            except cv2.error:
                pass
            K1 = cal.start.dlt_interiors[0][1].K if cal.start is not None else K0
            K1 = np.array([[K1[0, 0], 0, K1[0, 2]], [0, K1[1, 1], K1[1, 2]], [0, 0, 1]])
            _, vals, _ = _cv_calibrate(sc.views, (640, 480), cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3, K1)
            z_cv_dlt += [(vals[n] - float(getattr(truth, n))) / cal.std_errors[n] for n in cal.names]
        za, zc, zd = np.abs(z_ours), np.abs(z_cv), np.abs(z_cv_dlt)
        print(f"  noise {noise:.1f} px, {n_trials} trials x {len(cal.names)} elements: ours (DLT start): RMS |err|/se "
              f"{np.sqrt(np.mean(za ** 2)):.3f}, within 1.5 se {100 * np.mean(za < 1.5):.0f}%, max {za.max():.2f}")
        print(f"    OpenCV without a guess: refused in {refused} of {n_trials} trials (non-planar rig needs an "
              f"initial camera matrix)")
        if len(zc):
            print(f"    OpenCV with a guess f = 640, centred: {len(zc) // len(cal.names)} ran; RMS |err|/se "
                  f"{np.sqrt(np.mean(zc ** 2)):.3f}, within 1.5 se {100 * np.mean(zc < 1.5):.0f}%, max {zc.max():.2f}; "
                  f"RMS ours/OpenCV {np.mean(cv_rms_ratio):.4f}")
        print(f"    OpenCV with our DLT guess: RMS |err|/se {np.sqrt(np.mean(zd ** 2)):.3f}, within 1.5 se "
              f"{100 * np.mean(zd < 1.5):.0f}%")


def section_zoom() -> None:
    settings = [10.0, 15.0, 20.0, 25.0, 30.0]
    cals = {}
    for z in settings:
        sc = board_scene(np.random.default_rng(int(z)), n_views=8, camera=zoom_camera(z), noise_px=0.3, fill=0.5)
        cals[z] = Calibration.from_views(sc.views, 640, 480, distortion=("k1", "k2", "p1", "p2"))
    train = [10.0, 15.0, 25.0, 30.0]
    zm = ZoomModel.from_calibrations(train, [cals[z] for z in train], degree=2)
    val, se = zm.predict(20.0)
    truth: Intrinsics = zoom_camera(20.0)
    held = cals[20.0]
    print("[zoom] synthetic lens, settings 10-30, 8 board views each at 0.3 px; quadratic model from 10, 15, 25, 30; "
          "held out: 20")
    print(f"  {'elem':>4} {'model':>11} {'+-':>9} {'calibrated':>11} {'+-':>9} {'diff/se':>8} {'truth':>11} "
          f"{'chi2/dof':>8}")
    for n in zm.names:
        d = (val[n] - held.value(n)) / math.hypot(se[n], held.std_errors[n])
        print(f"  {n:>4} {val[n]:11.5f} {se[n]:9.5f} {held.value(n):11.5f} {held.std_errors[n]:9.5f} {d:8.3f} "
              f"{float(getattr(truth, n)):11.5f} {zm.chi2_dof[n]:8.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chessboard", type=Path, default=SHARED / "calibration_chessboard")
    ap.add_argument("--reference", type=Path, default=SHARED / "calibration_reference" / "calib1.dat")
    ap.add_argument("--mc", type=int, default=200, help="Monte Carlo trials for the chessboard standard errors")
    ap.add_argument("--trials", type=int, default=20, help="synthetic 3D-field trials per noise level")
    ap.add_argument("--only", choices=["chessboard", "reference", "field", "zoom"], default=None)
    a = ap.parse_args()
    print(f"OpenCV {cv2.__version__}")
    try:
        if a.only in (None, "reference"):
            section_reference(a.reference)
        if a.only in (None, "chessboard"):
            section_chessboard(a.chessboard, a.mc)
        if a.only in (None, "field"):
            section_field(a.trials)
        if a.only in (None, "zoom"):
            section_zoom()
    except CalibrationError as err:
        raise SystemExit(f"calibration failed: {err}") from err


if __name__ == "__main__":
    main()
