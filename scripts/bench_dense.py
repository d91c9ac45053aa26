"""Dense matching benchmarks (issues 14, 30).

Default: on Motorcycle (scikit-image, true disparity) and Cones (shared data, ``dense_cones``), OpenCV
StereoSGBM (OpenCV sample settings) and three settings of ours (``match_pair`` default, the exact
left-right check ``right_check='sgbm'``, and the half-resolution hole pass ``hole_p2=128`` that
``stereo dense`` uses), all in the same run: timed alternately, ``--repeat`` times each, the fastest
run of each compared (the machine may be shared: alternating spreads the load over all; the load
average is printed beside the times). For every case: density and bad-2.0 (Motorcycle) / bad-1.0
(Cones) on the non-occluded pixels, the same at the previous round's density (the most confident
pixels by the product's confidence band), the roughness (second-difference NMAD of the disparity,
px) and the time as a multiple of SGBM's. Non-occluded pixels of Motorcycle come from the true
disparity's own z-buffer. Then the NGI strip DSM (shared data, aero-triangulated EOs, ``run_dense``)
against ``dem.tif``: coverage of the overlap, RMSE in cells, NMAD, roughness (second-difference NMAD
of the DSM, m), with and without the hole pass (``--no-ngi``: skipped). ``--pandora``: CNES pandora
with its libSGM plugin as a further peer when it is installed (census cost, SGM, cross-check).

``--size N``: a synthetic N x N normal-case pair (procedural texture, smooth known disparity 8..40 px)
is written to ``--work`` as tiled GeoTIFFs, strip by strip, then matched tile by tile by
:func:`stereo.dense.matching.match_rasters` in a child process, which prints its peak resident memory
(VmHWM), time, density and the bad-1.0 share on a sample of pixels.

``--size N --chain``: the whole :func:`stereo.actions.dense.run_dense` chain on that pair taken as two
nadir frame photos (normal case, matching, points to LAS, DSM with a cell of ``--dsm-cell`` ground
pixels), in a child process that prints its peak resident memory.

``--stages``: only the CPU time of each stage of ``match_pair`` (coarse pass, tests, hole pass,
depth-edge step, median, sub-pixel step, confidence) beside SGBM's, with one OpenCV thread: the
default and the hole pass of ``stereo dense`` (``hole_p2=128``), alternating.

Usage:
    nice python scripts/bench_dense.py [--repeat 7] [--no-ngi] [--work DIR] [--pandora] [--stages]
    nice python scripts/bench_dense.py --size 10000 [--work /tmp/bench_dense] [--chain [--dsm-cell 2]]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereo.dense.matching import MatchOptions, match_pair, sgbm_baseline  # noqa: E402  (after the sys.path set-up)
from tests.support.stereo_support import occlusion_from_truth, read_grey, read_rgb  # noqa: E402

SHARED = Path(os.environ.get("RECTIFY_SHARED_DATA", ROOT / ".." / "shared" / "data"))
CONES = SHARED / "dense_cones"
NGI = SHARED / "ngi_strip05"
PANDORA = False  # --pandora
STAGES_ONLY = False  # --stages


def alternate(fns: dict, repeat: int) -> dict[str, tuple[object, float]]:
    """Run each function ``repeat`` times, alternating; the last output and the fastest wall time of each."""
    best = {k: float("inf") for k in fns}
    out: dict[str, object] = {}
    for _ in range(repeat):
        for k, f in fns.items():
            t = time.perf_counter()
            out[k] = f()
            best[k] = min(best[k], time.perf_counter() - t)
    return {k: (out[k], best[k]) for k in fns}


def alternate_cpu(fns: dict, repeat: int) -> dict[str, float]:
    """The fastest CPU time (``time.process_time``) of each function, alternating, with one OpenCV
    thread (so that SGBM's own threads do not count as the machine's load)."""
    import cv2

    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        best = {k: float("inf") for k in fns}
        for _ in range(repeat):
            for k, f in fns.items():
                t = time.process_time()
                f()
                best[k] = min(best[k], time.process_time() - t)
    finally:
        cv2.setNumThreads(n)
    return best


def roughness(z: np.ndarray) -> float:
    """Second-difference NMAD of a surface (disparity or DSM) along its rows and columns, NaN-aware."""
    s = []
    for a in (z, z.T):
        d2 = a[:, 2:] - 2 * a[:, 1:-1] + a[:, :-2]
        s.append(d2[np.isfinite(d2)])
    v = np.concatenate(s)
    return float(1.4826 * np.median(np.abs(v - np.median(v)))) if v.size else float("nan")


def load() -> str:
    return "load average " + " ".join(f"{v:.2f}" for v in os.getloadavg())


#: the compared matchers: OpenCV's sample SGBM and three settings of ours
CASES = {
    "OpenCV StereoSGBM (sample settings)": None,
    "match_pair (default)": MatchOptions(),
    "match_pair right_check='sgbm'": MatchOptions(right_check="sgbm"),
    "match_pair hole_p2=128 (stereo dense default)": MatchOptions(hole_p2=128.0),
}

#: the densities of the previous round (docs/dense.md, issue 14/24): precision compared at these
PREVIOUS = {"Motorcycle": (0.959, 0.0264), "Cones": (0.932, 0.0276)}


def compare(name: str, left: np.ndarray, right: np.ndarray, gt: np.ndarray, nocc: np.ndarray, thr: float,
            repeat: int) -> None:
    """Every case on one pair: density, bad-thr, bad-thr at the previous density, roughness, time, ratio."""
    fns = {k: ((lambda: sgbm_baseline(left, right)) if o is None else (lambda o=o: match_pair(left, right, options=o)))
           for k, o in CASES.items()}
    res = alternate(fns, repeat)
    cpu = alternate_cpu(fns, repeat)
    t_sgbm = res["OpenCV StereoSGBM (sample settings)"][1]
    c_sgbm = cpu["OpenCV StereoSGBM (sample settings)"]
    dens0, bad0 = PREVIOUS[name]
    for k, (out, t) in res.items():
        d = out if isinstance(out, np.ndarray) else out.disparity  # type: ignore[attr-defined]
        v = np.isfinite(d) & nocc
        err = (np.abs(d - gt) > thr)[v]
        at = "n/a"
        n = int(round(dens0 * nocc.sum()))
        if not isinstance(out, np.ndarray) and n <= v.sum():
            # the n most confident pixels (the product's own confidence band): precision at equal density
            idx = np.argsort(-out.confidence[v], kind="stable")[:n]  # type: ignore[attr-defined]
            at = f"{100 * err[idx].mean():.2f} %"
        print(f"{name} {k}: density {100 * v.sum() / nocc.sum():.1f} %, bad-{thr:.1f} {100 * err.mean():.2f} % "
              f"(at the previous density {100 * dens0:.1f} %: {at}; previous {100 * bad0:.2f} %), roughness "
              f"{roughness(np.where(nocc, d, np.nan)):.3f} px, time {t:.3f} s = {t / t_sgbm:.2f} x SGBM, "
              f"CPU time (one OpenCV thread) {cpu[k]:.3f} s = {cpu[k] / c_sgbm:.2f} x SGBM")
    print(f"{name}: fastest of {repeat} alternating runs each (wall, then CPU); {load()}")


def pandora_case(name: str, left: np.ndarray, right: np.ndarray, gt: np.ndarray, nocc: np.ndarray, thr: float,
                 disp_max: int) -> None:
    """CNES pandora with its libSGM plugin (census 5 x 5, SGM P1/P2 8/32, WTA, V-fit, 3 x 3 median,
    accurate cross-check) when installed (``pip install pandora pandora_plugin_libsgm``): precision on
    its valid pixels (validity mask 0) and ours at its density (most confident pixels), one run each."""
    try:
        import pandora  # local: optional peer, not a dependency
    except ImportError:
        print(f"{name} pandora: skipped (not installed)")
        return
    import cv2
    import rasterio
    from affine import Affine

    grey = [np.asarray(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)) if a.ndim == 3 else a for a in (left, right)]
    pandora.import_plugin()
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        for nm, a in zip(("l", "r"), grey, strict=True):
            with rasterio.open(t / f"{nm}.tif", "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1,
                               dtype="float32", transform=Affine.identity()) as ds:
                ds.write(a.astype(np.float32), 1)
        cfg = {"input": {"left": {"img": str(t / "l.tif"), "disp": [-disp_max, 0], "nodata": -9999},
                         "right": {"img": str(t / "r.tif"), "nodata": -9999}},
               "pipeline": {"matching_cost": {"matching_cost_method": "census", "window_size": 5, "subpix": 1},
                            "optimization": {"optimization_method": "sgm", "overcounting": False,
                                             "penalty": {"P1": 8, "P2": 32, "p2_method": "constant",
                                                         "penalty_method": "sgm_penalty"}},
                            "disparity": {"disparity_method": "wta", "invalid_disparity": "NaN"},
                            "refinement": {"refinement_method": "vfit"},
                            "filter": {"filter_method": "median", "filter_size": 3},
                            "validation": {"validation_method": "cross_checking_accurate"}}}
        (t / "cfg.json").write_text(json.dumps(cfg))
        t0 = time.perf_counter()
        pandora.main(str(t / "cfg.json"), str(t / "out"), False)
        dt = time.perf_counter() - t0
        with rasterio.open(t / "out" / "left_disparity.tif") as ds:
            d = -ds.read(1)  # pandora: col_right - col_left
        with rasterio.open(t / "out" / "left_validity_mask.tif") as ds:
            ok = ds.read(1) == 0
    v = np.isfinite(d) & ok & nocc
    dens = v.sum() / nocc.sum()
    ours = match_pair(left, right)
    vo = ours.valid & nocc
    err = (np.abs(ours.disparity - gt) > thr)[vo]
    idx = np.argsort(-ours.confidence[vo], kind="stable")[:int(round(dens * nocc.sum()))]
    t0 = time.perf_counter()
    sgbm_baseline(left, right)
    ts = time.perf_counter() - t0
    print(f"{name} pandora + libSGM (census): density {100 * dens:.1f} %, bad-{thr:.1f} "
          f"{100 * (np.abs(d - gt) > thr)[v].mean():.2f} %, time {dt:.2f} s = {dt / ts:.0f} x SGBM (one run); "
          f"ours at its density: bad-{thr:.1f} {100 * err[idx].mean():.2f} %")


#: the stages of :func:`stereo.dense.matching.match_pair` timed by ``--stages`` (names in that module)
STAGES = {"_coarse": "coarse pass (with its SGBM)", "_tests": "tests after SGBM (both passes)",
          "_fill_holes_half": "hole pass (with its SGBM)", "_post": "post-processing",
          "edge_classify": "  depth-edge step", "_median_valid": "  median",
          "refine_subpixel": "  sub-pixel step", "_confidence": "  confidence"}


def stages(name: str, left: np.ndarray, right: np.ndarray, repeat: int) -> None:
    """CPU time of each stage of ``match_pair`` (one OpenCV thread, fastest of ``repeat``) beside SGBM's:
    the default and the hole pass (``hole_p2=128``), run alternately."""
    import functools

    import cv2

    import stereo.dense.matching as mm

    spent: dict[str, float] = {}
    saved = {k: getattr(mm, k) for k in STAGES if hasattr(mm, k)}
    saved_sgbm = mm._sgbm

    def timed(key: str, f):
        @functools.wraps(f)
        def g(*a, **kw):
            t = time.process_time()
            try:
                return f(*a, **kw)
            finally:
                spent[key] = spent.get(key, 0.0) + time.process_time() - t
        return g

    class Sgbm:
        def __init__(self, m: object) -> None:
            self.m = m

        def compute(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return timed("sgbm", self.m.compute)(a, b)  # type: ignore[attr-defined]

    cases = {"match_pair": MatchOptions(), "match_pair hole_p2=128": MatchOptions(hole_p2=128.0)}
    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    best: dict[str, dict[str, float]] = {k: {} for k in cases}
    try:
        for k, f in saved.items():
            setattr(mm, k, timed(k, f))
        mm._sgbm = lambda *a, **kw: Sgbm(saved_sgbm(*a, **kw))  # type: ignore[assignment]
        for _ in range(repeat):
            for case, o in cases.items():
                spent.clear()
                t = time.process_time()
                match_pair(left, right, options=o)
                spent["total"] = time.process_time() - t
                t = time.process_time()
                sgbm_baseline(left, right)
                spent["baseline"] = time.process_time() - t
                for k, v in spent.items():
                    best[case][k] = min(best[case].get(k, float("inf")), v)
    finally:
        for k, f in saved.items():
            setattr(mm, k, f)
        mm._sgbm = saved_sgbm
        cv2.setNumThreads(n)
    for case, b in best.items():
        print(f"{name} {case} stages, CPU time with one OpenCV thread, fastest of {repeat}: total "
              f"{1000 * b['total']:.1f} ms = {b['total'] / b['baseline']:.2f} x OpenCV's sample SGBM "
              f"({1000 * b['baseline']:.1f} ms); SGBM compute (all passes) {1000 * b.get('sgbm', 0):.1f} ms; "
              + "; ".join(f"{label.strip()} {1000 * b[k]:.1f} ms" for k, label in STAGES.items() if k in b)
              + f"; {load()}")


def motorcycle(repeat: int) -> None:
    from skimage import data

    left, right, gt = data.stereo_motorcycle()
    nocc = ~occlusion_from_truth(gt)
    if STAGES_ONLY:
        stages("Motorcycle", left, right, repeat)
        return
    compare("Motorcycle", left, right, gt, nocc, 2.0, repeat)
    if PANDORA:
        pandora_case("Motorcycle", left, right, gt, nocc, 2.0, 72)


def cones(repeat: int) -> None:
    if not CONES.is_dir():
        print(f"Cones: skipped ({CONES} absent)")
        return
    import rasterio

    L = read_rgb(CONES / "left.png")
    R = read_rgb(CONES / "right.png")
    with rasterio.open(CONES / "disp_left.tif") as ds:
        gt = ds.read(1)
    nocc = (read_grey(CONES / "occlusion.png") > 0) & (gt > 0)
    if STAGES_ONLY:
        stages("Cones", L, R, repeat)
        return
    compare("Cones", L, R, gt, nocc, 1.0, repeat)
    if PANDORA:
        pandora_case("Cones", L, R, gt, nocc, 1.0, 60)


def ngi(work: Path) -> None:
    """The NGI strip DSM (aero-triangulated EOs) against dem.tif: coverage, RMSE, roughness, time."""
    import rasterio

    from rectify.geometry.camera import Camera
    from rectify.geometry.rotation import matrix_from_angles
    from stereo.actions.dense import DenseOptions, run_dense
    from stereo.formats.orientation import write_exterior
    from stereo.pair.resection import ExteriorOrientation

    d = NGI
    if not d.is_dir():
        print(f"NGI strip: skipped ({d} absent)")
        return
    lo25 = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m"
    eos = {"0182": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702),
           "0184": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883)}
    cam = Camera.from_dict({"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152})
    work.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, v in eos.items():
        eo = ExteriorOrientation(position=np.array(v[:3]), rotation=matrix_from_angles(*np.radians(v[3:])),
                                 focal_length_mm=120.0, crs=lo25)
        p = work / f"eo_{k}.json"
        p.unlink(missing_ok=True)
        paths.append(write_exterior(p, eo, camera=cam.to_dict()))
    for label, mo in (("stereo dense default (hole_p2=128)", DenseOptions().matching),
                      ("without the hole pass (hole_p2=0)", replace(DenseOptions().matching, hole_p2=0.0))):
        out = work / "dense"
        if out.exists():
            shutil.rmtree(out)
        t = time.perf_counter()
        r = run_dense(paths[0], d / "3324c_2015_1004_05_0182_RGB.tif", d / "3324c_2015_1004_05_0184_RGB.tif", out,
                      right_orientation=paths[1], options=DenseOptions(
                          cloud_format="none", reference_dem=str(d / "dem.tif"), measure_parallax=False, matching=mo))
        dt = time.perf_counter() - t
        with rasterio.open(out / "dsm.tif") as ds:
            z = ds.read(1).astype(np.float64)
            z[z == ds.nodata] = np.nan
        c = r.comparison
        assert c is not None
        print(f"NGI strip DSM, {label}: coverage {100 * c.coverage:.1f} % of the overlap, RMSE {c.rmse:.2f} m "
              f"({c.rmse / r.dsm_cell:.2f} cells), NMAD {c.nmad:.2f} m, blunders {100 * c.blunder_share:.1f} %, "
              f"roughness {roughness(z):.3f} m, time {dt:.1f} s ({load()})")


# ------------------------------------------------------------------ large synthetic pair
def disparity_field(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The known smooth disparity (8..40 px) of the synthetic pair, at right-photo pixels."""
    return (24.0 + 12.0 * np.sin(2 * np.pi * x / 3000.0) * np.cos(2 * np.pi * y / 2500.0)
            + 4.0 * np.sin(2 * np.pi * (x + y) / 700.0))


def texture(x0: int, y0: int, w: int, h: int) -> np.ndarray:
    """Procedural texture (a function of the pixel position): hashed noise, blurred, two scales; uint8."""
    import cv2

    pad = 8
    yy, xx = np.mgrid[y0 - pad:y0 + h + pad, x0 - pad:x0 + w + pad].astype(np.uint64)
    v = (xx * np.uint64(73856093)) ^ (yy * np.uint64(19349663)) ^ np.uint64(0x9E3779B9)
    v = (v * np.uint64(0x2545F4914F6CDD1D)) >> np.uint64(40)
    n = (v & np.uint64(255)).astype(np.float32)
    t = cv2.GaussianBlur(n, (0, 0), 1.0) * 1.0 + cv2.GaussianBlur(n, (0, 0), 3.0) * 2.0
    t = t[pad:-pad, pad:-pad]
    return np.clip((t - t.mean()) * 2.5 + 128, 0, 255).astype(np.uint8)


def make_pair(work: Path, size: int, strip: int = 256) -> tuple[Path, Path]:
    """Left = texture, right(x', y) = left(x' + d(x', y), y); tiled GeoTIFFs written strip by strip."""
    import cv2
    from affine import Affine

    from rectify.raster.io import MaskPolicy, TiledWriter

    lp, rp = work / "left.tif", work / "right.tif"
    if lp.exists() and rp.exists():
        return lp, rp
    dmax = 48
    with TiledWriter(lp, size, size, 1, "uint8", Affine.identity(), None, MaskPolicy("none", None)) as wl, \
            TiledWriter(rp, size, size, 1, "uint8", Affine.identity(), None, MaskPolicy("none", None)) as wr:
        for r0 in range(0, size, strip):
            h = min(strip, size - r0)
            L = texture(0, r0, size + dmax, h)
            wl.write(L[:, :size, None], 0, r0)
            ys, xs = np.mgrid[r0:r0 + h, 0:size].astype(np.float32)
            mx = (xs + disparity_field(xs, ys)).astype(np.float32)
            R = cv2.remap(L, mx, ys - r0, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
            wr.write(R[:, :, None], 0, r0)
    return lp, rp


CHILD = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, {root!r})
from stereo.dense.matching import match_rasters
t = time.perf_counter()
st = match_rasters({left!r}, {right!r}, {disp!r}, {conf!r}, disparity_range=(0, 48))
dt = time.perf_counter() - t
peak = float("nan")
with open("/proc/self/status") as f:
    for line in f:
        if line.startswith("VmHWM:"):
            peak = int(line.split()[1]) / 1024
print(json.dumps({{"seconds": dt, "peak_mb": peak, "density": st.density, "tiles": st.n_tiles}}))
"""


def large(size: int, work: Path) -> None:
    import rasterio
    from rasterio.windows import Window

    work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    lp, rp = make_pair(work, size)
    print(f"synthetic {size} x {size} normal-case pair in {work} ({time.perf_counter() - t:.0f} s to write)")
    disp, conf = work / "disparity.tif", work / "confidence.tif"
    for p in (disp, conf):
        p.unlink(missing_ok=True)
    code = CHILD.format(root=str(ROOT), left=str(lp), right=str(rp), disp=str(disp), conf=str(conf))
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    # accuracy on 64 windows of 128 x 128 spread over the photo
    rng = np.random.default_rng(0)
    errs = []
    with rasterio.open(disp) as ds:
        for _ in range(64):
            c0, r0 = (int(v) for v in rng.integers(0, size - 128, 2))
            d = ds.read(1, window=Window(c0, r0, 128, 128)).astype(np.float64)
            d[d == -9999] = np.nan
            ys, xs = np.mgrid[r0:r0 + 128, c0:c0 + 128].astype(np.float64)
            truth = disparity_field(xs, ys)
            for _ in range(3):  # left disparity: d_l(x) = d_r(x - d_l(x))
                truth = disparity_field(xs - truth, ys)
            ok = np.isfinite(d) & (xs - truth >= 0)
            errs.append(np.abs(d - truth)[ok])
    e = np.concatenate(errs)
    print(f"match_rasters {size} x {size}: {res['tiles']} tiles, time {res['seconds']:.0f} s, density "
          f"{res['density']:.3f}, bad-1.0 {np.mean(e > 1):.4f} (sample of {e.size} px), "
          f"peak memory {res['peak_mb']:.0f} MB (VmHWM of the matching process)")


CHILD_CHAIN = r"""
import json, sys, time
sys.path.insert(0, {root!r})
from stereo.actions.dense import DenseOptions, run_dense
t = time.perf_counter()
res = run_dense({eo_l!r}, {left!r}, {right!r}, {out!r}, right_orientation={eo_r!r}, matches={ties!r},
                options=DenseOptions(cloud_format="las", dsm_cell={cell!r}, measure_parallax=False))
dt = time.perf_counter() - t
peak = float("nan")
with open("/proc/self/status") as f:
    for line in f:
        if line.startswith("VmHWM:"):
            peak = int(line.split()[1]) / 1024
print("\n".join(res.summary_lines()))
print(json.dumps({{"seconds": dt, "peak_mb": peak}}))
"""


def chain(size: int, work: Path, cell_gsd: float) -> None:
    """run_dense on the synthetic pair taken as two nadir frame photos (identity rotations, base along x).

    The right camera's principal point is offset by 2000 px along x, so that the photos' 8..40 px
    disparities are parallaxes of 2008..2040 px: a flying height of 3000 m, a base of about 600 m and
    a relief of about 50 m (ground pixel 0.3 m).
    """
    from rectify.geometry.camera import Camera
    from stereo.formats.orientation import write_exterior
    from stereo.pair.resection import ExteriorOrientation

    work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    lp, rp = make_pair(work, size)
    print(f"synthetic {size} x {size} pair in {work} ({time.perf_counter() - t:.0f} s to write)")
    pix, f_mm, shift = 0.012, 120.0, 2000.0
    f_px, H = f_mm / pix, 3000.0
    base = (shift + 24.0) * H / f_px
    cam_l = Camera(focal_length_mm=f_mm, pixel_size_mm=pix, width=size, height=size)
    cam_r = Camera(focal_length_mm=f_mm, pixel_size_mm=pix, width=size, height=size,
                   principal_point_mm=(shift * pix, 0.0))
    paths = {}
    for name, cam, x in (("l", cam_l, 0.0), ("r", cam_r, base)):
        eo = ExteriorOrientation(position=np.array([500_000.0 + x, 5_000_000.0, H]), rotation=np.eye(3),
                                 focal_length_mm=f_mm, sigma0=0.0, crs="EPSG:32633")
        paths[name] = work / f"eo_{name}.json"
        paths[name].unlink(missing_ok=True)
        write_exterior(paths[name], eo, camera=cam.to_dict())
    # tie points from the known disparity: a 20 x 20 lattice
    g = np.linspace(0.05 * size, 0.95 * size, 20)
    xs, ys = (a.ravel() for a in np.meshgrid(g, g))
    d = disparity_field(xs, ys)
    for _ in range(3):
        d = disparity_field(xs - d, ys)
    ties = work / "ties.csv"
    ties.write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"{i},{a},{b},{a - dd},{b}\n" for i, (a, b, dd) in enumerate(zip(xs, ys, d, strict=True))))
    out = work / "dense"
    if out.exists():
        shutil.rmtree(out)
    cell = cell_gsd * H / f_px
    code = CHILD_CHAIN.format(root=str(ROOT), eo_l=str(paths["l"]), eo_r=str(paths["r"]), left=str(lp),
                              right=str(rp), out=str(out), ties=str(ties), cell=cell)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if res.returncode:
        print(res.stderr[-3000:])
        raise SystemExit(1)
    lines = res.stdout.strip().splitlines()
    print("\n".join(lines[:-1]))
    r = json.loads(lines[-1])
    print(f"run_dense {size} x {size} (DSM cell {cell:.2f} m = {cell_gsd:g} ground pixels): time {r['seconds']:.0f} s, "
          f"peak memory {r['peak_mb']:.0f} MB (VmHWM of the run_dense process)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7, help="timed runs of each matcher (alternating)")
    ap.add_argument("--size", type=int, default=0, help="run the tiled N x N synthetic benchmark instead")
    ap.add_argument("--work", type=Path, default=None, help="folder for the large pair (default: a temporary one)")
    ap.add_argument("--chain", action="store_true",
                    help="with --size: the whole run_dense chain (normal case, matching, points, LAS, DSM)")
    ap.add_argument("--dsm-cell", type=float, default=2.0, help="with --chain: DSM cell in ground pixels")
    ap.add_argument("--no-ngi", action="store_true", help="skip the NGI strip DSM (shared data)")
    ap.add_argument("--stages", action="store_true",
                    help="only the CPU time of match_pair's stages on Motorcycle and Cones (one OpenCV thread)")
    ap.add_argument("--pandora", action="store_true",
                    help="also CNES pandora + libSGM (census) when installed, one run each (slow)")
    a = ap.parse_args()
    if a.size:
        def go(work: Path) -> None:
            if a.chain:
                chain(a.size, work, a.dsm_cell)
            else:
                large(a.size, work)
        if a.work is not None:
            go(a.work)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                go(Path(tmp))
        return
    global PANDORA, STAGES_ONLY
    PANDORA = a.pandora
    STAGES_ONLY = a.stages
    print(load())
    motorcycle(a.repeat)
    cones(a.repeat)
    if not a.no_ngi and not a.stages:
        if a.work is not None:
            ngi(a.work)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                ngi(Path(tmp))


if __name__ == "__main__":
    main()
