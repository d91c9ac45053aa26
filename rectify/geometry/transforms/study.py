"""The comparison study: Kushtin's cotangent four-point method against the
8-parameter homography (issue 2).

:func:`run_study` returns a :class:`StudyResults` with five parts:

1. **agreement** on exact data: the largest difference between the two
   methods over many random well-posed configurations (and the error of
   eq. (2) as printed in seed 001);
2. **noise**: Monte Carlo with Gaussian noise on the control points for
   realistic tilted-frame geometry (seed 001's Resurs-F: f = 1000 mm,
   300 x 300 mm frame, 10 deg tilt; an aerial frame camera: f = 153 mm,
   230 x 230 mm, 3 deg tilt), RMSE at check points for the cotangent method
   (4 points), the homography (same 4 points) and the least-squares
   homography (all N points);
3. **propagation**: first-order error propagation of the control points'
   covariance to the rectified check points for each method (numerical
   Jacobian of the whole estimator), validated against the Monte Carlo;
4. **conditioning** near degenerate configurations (one control point
   moved towards the line through two others);
5. **speed**: points per second of both methods, measured in the same run.

:func:`rectify.actions.compare.write_study` writes ``study.md`` (Markdown tables), ``study.json``
and PNG plots. ``scripts/compare_cotangent_homography.py`` and
``rectify compare`` are thin wrappers.

Frames: the tilted image (source) and the horizontal image (target) are in
pixels of the stated pixel size, centred on the principal point, y up;
noise is added independently to both coordinates of every control point in
both planes.
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.analytic import TiltedFrame
from rectify.geometry.transforms import CotangentFourPoint, Homography, base_cotangents, corrected_eq2, printed_eq2
from rectify.geometry.transforms.base import _normalising_similarity

logger = logging.getLogger(__name__)

__all__ = ["CameraGeometry", "StudyConfig", "StudyResults", "run_study", "comparison_summary",
           "summary_lines",
           "CAMERAS"]

F64 = NDArray[np.float64]
Progress = Callable[[int, int], None] | None


@dataclass(frozen=True)
class CameraGeometry:
    """A tilted-frame scenario.

    Attributes
    ----------
    name : str
    focal_length_mm, frame_mm, pixel_size_mm : float
    omega, phi, kappa : float
        Orientation (rad, omega-phi-kappa) of the tilted frame.
    """

    name: str
    focal_length_mm: float
    frame_mm: float
    pixel_size_mm: float
    omega: float
    phi: float
    kappa: float

    @property
    def size_px(self) -> float:
        return self.frame_mm / self.pixel_size_mm

    @property
    def tilt_deg(self) -> float:
        return math.degrees(TiltedFrame.from_angles(self.focal_length_mm, self.omega, self.phi, self.kappa).tilt)

    def frame(self) -> TiltedFrame:
        return TiltedFrame.from_angles(self.focal_length_mm, self.omega, self.phi, self.kappa)

    def to_target(self, src_px: F64) -> F64:
        """Tilted image px (centred, y up) -> horizontal image px (same pixel size)."""
        return self.frame()(src_px * self.pixel_size_mm) / self.pixel_size_mm


#: Resurs-F (seed 001): f = 1000 mm, 300 x 300 mm frame scanned at 10 um, 10 deg tilt;
#: an aerial frame camera: f = 153 mm, 230 x 230 mm at 12 um, 3 deg tilt.
CAMERAS: tuple[CameraGeometry, ...] = (
    CameraGeometry("Resurs-F (f=1000 mm, 300 mm frame, tilt 10 deg)", 1000.0, 300.0, 0.010,
                   math.radians(6.0), math.radians(8.0), math.radians(25.0)),
    CameraGeometry("aerial (f=153 mm, 230 mm frame, tilt 3 deg)", 153.0, 230.0, 0.012,
                   math.radians(2.0), math.radians(-2.24), math.radians(-40.0)),
)


@dataclass(frozen=True)
class StudyConfig:
    """Sizes of the study (defaults: the full script run; ``rectify compare`` uses smaller ones).

    Attributes
    ----------
    n_configs : int
        Random configurations for the agreement test.
    n_trials : int
        Monte Carlo trials per camera and noise level.
    noise_px : tuple of float
        Standard deviations of the control-point noise, px.
    n_lsq : int
        Control points of the least-squares homography (a jittered grid; the
        4 points of the four-point methods are among them).
    n_check_side : int
        Check points form an n x n grid over the frame.
    n_speed_points : int
        Points for the speed test.
    speed_repeats : int
    seed : int
    """

    n_configs: int = 3000
    n_trials: int = 300
    noise_px: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0, 2.0)
    n_lsq: int = 9
    n_check_side: int = 10
    n_speed_points: int = 1_000_000
    speed_repeats: int = 7
    seed: int = 0

    @classmethod
    def quick(cls, **overrides: Any) -> StudyConfig:
        """The small preset of ``rectify compare`` (about a minute on a busy 2-core machine)."""
        base: dict[str, Any] = dict(n_configs=500, n_trials=60, n_speed_points=200_000, speed_repeats=5)
        base.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**base)

    def __post_init__(self) -> None:
        for name in ("n_configs", "n_trials", "n_check_side", "n_speed_points", "speed_repeats"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"`{name}` must be a positive integer; got {v!r}")
        if self.n_lsq not in (9, 16, 25):
            raise InvalidInputError(f"`n_lsq` must be 9, 16 or 25 (a square grid); got {self.n_lsq!r}")
        if not self.noise_px or any(not (math.isfinite(s) and s > 0) for s in self.noise_px):
            raise InvalidInputError(f"`noise_px` must be positive numbers; got {self.noise_px!r}")


@dataclass
class StudyResults:
    """Everything the study measured (plain numbers; see :meth:`to_markdown`)."""

    config: StudyConfig
    agreement: dict[str, Any] = field(default_factory=dict)
    noise: list[dict[str, Any]] = field(default_factory=list)
    propagation: list[dict[str, Any]] = field(default_factory=list)
    conditioning: list[dict[str, Any]] = field(default_factory=list)
    speed: dict[str, Any] = field(default_factory=dict)
    cameras: list[dict[str, Any]] = field(default_factory=list)
    #: per-configuration arrays behind the figures (``agreement_rel``: (n,) largest difference / image size)
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {"config": asdict(self.config), "cameras": self.cameras, "agreement": self.agreement,
                "noise": self.noise, "propagation": self.propagation, "conditioning": self.conditioning,
                "speed": self.speed}

    # ------------------------------------------------------------------ markdown
    def to_markdown(self) -> str:
        c = self.config
        a = self.agreement
        L: list[str] = ["# Cotangent four-point method vs 8-parameter homography", ""]
        L += [f"Seed {c.seed}; {c.n_configs} random configurations, {c.n_trials} Monte Carlo trials per "
              f"cell, {c.n_check_side}x{c.n_check_side} check points, least squares on {c.n_lsq} points.", ""]
        L += ["## 1. Agreement on exact data", "",
              "| quantity | value |", "|---|---|",
              f"| configurations (well-posed, random) | {a['n_configs']} |",
              f"| points compared per configuration | {a['n_points']} |",
              f"| max \\|cotangent - homography\\| / image size | {a['max_rel']:.2e} |",
              f"| 99th percentile / image size | {a['p99_rel']:.2e} |",
              f"| median / image size | {a['median_rel']:.2e} |",
              f"| eq. (2) as printed: median error / image size | {a['printed_median_rel']:.2e} |",
              f"| corrected eq. (2): max error / image size | {a['corrected_max_rel']:.2e} |", ""]
        L += ["## 2. Accuracy under noise (RMSE at check points, target px)", "",
              "| camera | sigma [px] | cotangent (4) | homography (4) | homography LSQ (" + str(c.n_lsq)
              + ") | max \\|cot - H4\\| per trial [px] |", "|---|---|---|---|---|---|"]
        for r in self.noise:
            L.append(f"| {r['camera']} | {r['sigma_px']:g} | {r['rmse_cotangent']:.3f} | "
                     f"{r['rmse_homography4']:.3f} | {r['rmse_homography_lsq']:.3f} | {r['max_diff_cot_h4']:.1e} |")
        L += ["", "## 3. First-order error propagation vs Monte Carlo (RMSE at check points, px)", "",
              "| camera | sigma [px] | method | predicted | Monte Carlo | ratio |", "|---|---|---|---|---|---|"]
        for r in self.propagation:
            L.append(f"| {r['camera']} | {r['sigma_px']:g} | {r['method']} | {r['predicted']:.3f} | "
                     f"{r['monte_carlo']:.3f} | {r['ratio']:.3f} |")
        L += ["", "## 4. Conditioning near degenerate configurations", "",
              "Control point 3 of a 1000 px square moved towards the diagonal through points 2 and 4; "
              "eps = its distance from that line / side; target points exact from one fixed homography; "
              "errors over a 15x15 grid covering the square.", "",
              "| eps | max \\|cot - H\\| / size | max error cot / size | max error H / size | "
              "noise gain cot (4) | noise gain H (4) | DLT condition number | cot error bound / size |",
              "|---|---|---|---|---|---|---|---|"]
        for r in self.conditioning:
            if "error" in r:
                eh = f"{r['err_homography_rel']:.1e}" if "err_homography_rel" in r else ""
                L.append(f"| {r['eps']:.0e} | rejected: {r['error'][:110]} | | {eh} | | | | |")
                continue
            L.append(f"| {r['eps']:.0e} | {r['max_diff_rel']:.1e} | {r['err_cotangent_rel']:.1e} | "
                     f"{r['err_homography_rel']:.1e} | {r['gain_cotangent']:.3g} | "
                     f"{r['gain_homography']:.3g} | {r['dlt_condition']:.3g} | {r['max_error_bound_rel']:.1e} |")
        L += ["", "noise gain = predicted RMSE at check points per 1 px of control-point noise.", ""]
        s = self.speed
        L += ["## 5. Speed (same run, interleaved, median)", "",
              "| method | points | time [ms] | points/s |", "|---|---|---|---|",
              f"| homography (ours) | {s['n_points']} | {s['homography_s'] * 1e3:.1f} | "
              f"{s['homography_pts_per_s']:,.0f} |",
              f"| cotangent four-point | {s['n_points']} | {s['cotangent_s'] * 1e3:.1f} | "
              f"{s['cotangent_pts_per_s']:,.0f} |",
              f"| ratio cotangent / homography | | | {s['ratio']:.2f} |", ""]
        return "\n".join(L)

    # ------------------------------------------------------------------ figures

# ---------------------------------------------------------------------------- helpers
def _random_quad(rng: np.random.Generator, size: float, jitter: float = 0.15) -> F64:
    base = np.array([[-0.4, -0.4], [0.4, -0.4], [0.4, 0.4], [-0.4, 0.4]])
    return (base + rng.uniform(-jitter, jitter, (4, 2))) * size


def _grid(n: int, half: float) -> F64:
    g = np.linspace(-half, half, n)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def _fit_all(src4: F64, dst4: F64, src_n: F64, dst_n: F64, check: F64) -> dict[str, F64]:
    return {
        "cotangent (4)": CotangentFourPoint.from_points(src4, dst4)(check),
        "homography (4)": Homography.from_points(src4, dst4)(check),
        "homography LSQ": Homography.from_points(src_n, dst_n)(check),
    }


def _jacobian_rmse(method: str, src: F64, dst: F64, check: F64, *, step: float = 1e-3) -> float:
    """First-order RMSE at the check points per 1 px of iid noise on all control coordinates.

    Numerical (central-difference) Jacobian of the rectified check points
    with respect to every control-point coordinate in both planes;
    predicted RMSE = sqrt(mean_i trace(J_i J_i^T)) * sigma.
    """
    def estimate(s: F64, d: F64) -> F64:
        if method == "cotangent (4)":
            return CotangentFourPoint.from_points(s, d)(check)
        return Homography.from_points(s, d)(check)

    h = step
    acc = np.zeros(len(check))
    for plane in (0, 1):
        for i in range(len(src)):
            for j in range(2):
                sp, dp = src.copy(), dst.copy()
                sm, dm = src.copy(), dst.copy()
                (sp if plane == 0 else dp)[i, j] += h
                (sm if plane == 0 else dm)[i, j] -= h
                col = (estimate(sp, dp) - estimate(sm, dm)) / (2 * h)
                acc += np.sum(col * col, axis=1)
    return float(np.sqrt(np.mean(acc)))


# ---------------------------------------------------------------------------- parts
def _agreement(cfg: StudyConfig, rng: np.random.Generator, progress: Progress, done: list[int],
               total: int) -> tuple[dict[str, Any], F64]:
    size = 1000.0
    check = _grid(12, 0.5 * size)
    rel = np.empty(cfg.n_configs)
    n_ok = 0
    printed, corrected = [], []
    for k in range(cfg.n_configs):
        src = _random_quad(rng, size)
        dst = _random_quad(rng, size)
        try:
            H = Homography.from_points(src, dst)
            C = CotangentFourPoint.from_points(src, dst)
        except EstimationError:
            rel[k] = np.nan
            continue
        hp = H(check)
        keep = np.abs(hp).max(axis=1) < 5 * size  # away from the vanishing line
        rel[k] = np.abs(C(check[keep]) - hp[keep]).max() / size
        n_ok += 1
        if k < 200:
            cb, cg = base_cotangents(src[0], src[1], check)
            off = np.abs(cb) < 1e6
            p = printed_eq2(src[0], src[1], cb[off], cg[off])
            printed.append(np.median(np.linalg.norm(p - check[off], axis=1)) / size)
            q = corrected_eq2(src[0], src[1], cb[off], cg[off])
            corrected.append(np.abs(q - check[off]).max() / size)
        done[0] += 1
        if progress and k % 50 == 0:
            progress(done[0], total)
    r = rel[np.isfinite(rel)]
    out = {"n_configs": int(n_ok), "n_points": int(len(check)), "image_size_px": size,
           "max_rel": float(r.max()), "p99_rel": float(np.percentile(r, 99)), "median_rel": float(np.median(r)),
           "printed_median_rel": float(np.median(printed)), "corrected_max_rel": float(np.max(corrected))}
    return out, r


def _noise_and_propagation(cfg: StudyConfig, rng: np.random.Generator, progress: Progress, done: list[int],
                           total: int) -> tuple[list, list, list]:
    noise_rows, prop_rows, cams = [], [], []
    side = int(round(math.sqrt(cfg.n_lsq)))
    for cam in CAMERAS:
        size = cam.size_px
        # control points: jittered grid; the 4 corners are the four-point set
        g = _grid(side, 0.4 * size) + rng.uniform(-0.04, 0.04, (side * side, 2)) * size
        corners = [0, side - 1, side * side - 1, side * (side - 1)]
        src_n = g
        dst_n = cam.to_target(src_n)
        src4, dst4 = src_n[corners], dst_n[corners]
        check = _grid(cfg.n_check_side, 0.45 * size)
        truth = cam.to_target(check)
        cams.append({"name": cam.name, "focal_length_mm": cam.focal_length_mm, "frame_mm": cam.frame_mm,
                     "pixel_size_mm": cam.pixel_size_mm, "size_px": size, "tilt_deg": cam.tilt_deg,
                     "omega_phi_kappa_rad": [cam.omega, cam.phi, cam.kappa]})
        gains = {m: _jacobian_rmse(m, src4, dst4, check) for m in ("cotangent (4)", "homography (4)")}
        gains["homography LSQ"] = _jacobian_rmse("homography LSQ", src_n, dst_n, check)
        for sigma in cfg.noise_px:
            sq = {m: 0.0 for m in gains}
            max_diff = 0.0
            for _ in range(cfg.n_trials):
                ns = rng.normal(0.0, sigma, src_n.shape)
                nd = rng.normal(0.0, sigma, dst_n.shape)
                s_obs, d_obs = src_n + ns, dst_n + nd
                res = _fit_all(s_obs[corners], d_obs[corners], s_obs, d_obs, check)
                for m, v in res.items():
                    sq[m] += float(np.sum((v - truth) ** 2))
                max_diff = max(max_diff, float(np.abs(res["cotangent (4)"] - res["homography (4)"]).max()))
                done[0] += 1
                if progress and done[0] % 25 == 0:
                    progress(done[0], total)
            n_obs = cfg.n_trials * len(check)
            rm = {m: math.sqrt(v / n_obs) for m, v in sq.items()}
            noise_rows.append({"camera": cam.name, "sigma_px": sigma, "rmse_cotangent": rm["cotangent (4)"],
                               "rmse_homography4": rm["homography (4)"],
                               "rmse_homography_lsq": rm["homography LSQ"], "max_diff_cot_h4": max_diff})
            for m in gains:
                pred = gains[m] * sigma
                prop_rows.append({"camera": cam.name, "sigma_px": sigma, "method": m, "predicted": pred,
                                  "monte_carlo": rm[m], "ratio": pred / rm[m] if rm[m] > 0 else float("nan")})
    return noise_rows, prop_rows, cams


def _conditioning(cfg: StudyConfig) -> list[dict[str, Any]]:
    """Point 3 (index 2) of a square moved onto the diagonal 2-4; data exact from one fixed homography."""
    size = 1000.0
    H_true = Homography(np.array([[0.95, 0.08, 20.0], [-0.05, 1.05, 10.0], [6e-5, -4e-5, 1.0]]))
    check = _grid(15, 0.5 * size) + 500.0
    rows: list[dict[str, Any]] = []
    for eps in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-9):
        src = np.array([[0.0, 0.0], [1000.0, 0.0], [1000.0, 1000.0], [0.0, 1000.0]])
        mid = (src[1] + src[3]) / 2
        src[2] = mid + np.array([1.0, 1.0]) / math.sqrt(2) * eps * size
        dst = H_true(src)
        try:
            H = Homography.from_points(src, dst)
            C = CotangentFourPoint.from_points(src, dst)
        except EstimationError as err:
            rows.append({"eps": eps, "error": str(err)})
            continue
        truth = H_true(check)
        try:
            c_check = C(check)
            _, bound = C.base_pairs(check)
        except EstimationError as err:  # the cotangent guard: estimated error above COT_MAX_REL_ERROR
            rows.append({"eps": eps, "error": f"cotangent raises: {err}",
                         "err_homography_rel": float(np.abs(H(check) - truth).max()) / size})
            continue
        diff = float(np.abs(c_check - H(check)).max()) / size
        err_c = float(np.abs(c_check - truth).max()) / size
        err_h = float(np.abs(H(check) - truth).max()) / size
        step = min(1e-3, 1e-2 * eps * size)  # finite-difference step well inside the degeneracy scale
        ts, td = _normalising_similarity(src), _normalising_similarity(dst)
        sn = src @ ts[:2, :2].T + ts[:2, 2]
        dn = dst @ td[:2, :2].T + td[:2, 2]
        A = []
        for (x, y), (u, v) in zip(sn, dn, strict=True):
            A.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
            A.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
        sv = np.linalg.svd(np.array(A), compute_uv=False)
        rows.append({"eps": eps, "max_diff_rel": diff, "err_cotangent_rel": err_c, "err_homography_rel": err_h,
                     "gain_cotangent": _jacobian_rmse("cotangent (4)", src, dst, check, step=step),
                     "gain_homography": _jacobian_rmse("homography (4)", src, dst, check, step=step),
                     "dlt_condition": float(sv[0] / sv[7]),
                     "max_error_bound_rel": float(bound.max()) / size})
    return rows


#: Side of the speed scene's frame, px.
SPEED_FRAME_PX = 10_000.0


def speed_scene(n_points: int, rng: np.random.Generator
                ) -> tuple[Homography, CotangentFourPoint, NDArray[np.float64]]:
    """The throughput scene shared by the study and ``scripts/bench_projective.py``.

    A mild perspective map of a 10 000 px frame, fitted to four control points
    by both methods, and ``n_points`` source points (N, 2) spread over the
    frame and 10 % beyond it.
    """
    size = SPEED_FRAME_PX
    src4 = np.array([[500.0, 700.0], [9300.0, 400.0], [9600.0, 9100.0], [300.0, 9500.0]])
    H0 = np.array([[1.02, 0.04, 120.0], [-0.03, 0.97, -80.0], [2e-6, -1.5e-6, 1.0]])
    dst4 = Homography(H0)(src4)
    pts = rng.uniform(-0.1 * size, 1.1 * size, (n_points, 2))
    return Homography.from_points(src4, dst4), CotangentFourPoint.from_points(src4, dst4), pts


def _speed(cfg: StudyConfig, rng: np.random.Generator) -> dict[str, Any]:
    H, C, pts = speed_scene(cfg.n_speed_points, rng)
    th, tc = [], []
    H(pts[:1000])
    C(pts[:1000])
    for _ in range(cfg.speed_repeats):
        t0 = time.perf_counter()
        H(pts)
        th.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        C(pts)
        tc.append(time.perf_counter() - t0)
    h, c = statistics.median(th), statistics.median(tc)
    n = cfg.n_speed_points
    return {"n_points": n, "repeats": cfg.speed_repeats, "homography_s": h, "cotangent_s": c,
            "homography_pts_per_s": n / h, "cotangent_pts_per_s": n / c, "ratio": h / c}


def run_study(config: StudyConfig | None = None, *, progress: Progress = None) -> StudyResults:
    """Run the five parts of the comparison study.

    Parameters
    ----------
    config : StudyConfig, optional
        Sizes and seed (default :class:`StudyConfig()`, the full run).
    progress : callable(done, total), optional

    Returns
    -------
    StudyResults
    """
    cfg = config or StudyConfig()
    if not isinstance(cfg, StudyConfig):
        raise InvalidInputError(f"`config` must be a StudyConfig; got {type(cfg).__name__}")
    rng = np.random.default_rng(cfg.seed)
    total = cfg.n_configs + len(CAMERAS) * len(cfg.noise_px) * cfg.n_trials
    done = [0]
    res = StudyResults(cfg)
    t0 = time.perf_counter()
    res.agreement, rel = _agreement(cfg, rng, progress, done, total)
    res.raw["agreement_rel"] = rel
    logger.info("agreement: %d configs, max %.3g of image size", res.agreement["n_configs"],
                res.agreement["max_rel"])
    res.noise, res.propagation, res.cameras = _noise_and_propagation(cfg, rng, progress, done, total)
    res.conditioning = _conditioning(cfg)
    res.speed = _speed(cfg, rng)
    if progress:
        progress(total, total)
    logger.info("study done in %.1f s", time.perf_counter() - t0)
    return res


def comparison_summary(*, n_configs: int = 200, n_trials: int = 20, n_speed_points: int = 100_000,
                       seed: int = 0, progress: Progress = None) -> dict[str, Any]:
    """A small run of the study, condensed to a flat dict of its key numbers (for ``rectify demo``).

    Keys: ``agreement_max_rel`` (largest |cotangent - homography| / image size),
    ``printed_eq2_median_rel``, per camera ``rmse_1px_<camera>_{cotangent,homography4,homography_lsq}``
    (px at sigma = 1 px), ``propagation_ratio_min/max`` (predicted / Monte Carlo),
    ``speed_ratio`` (cotangent / homography throughput) and the sizes used.
    """
    cfg = StudyConfig(n_configs=n_configs, n_trials=n_trials, noise_px=(1.0,), n_speed_points=n_speed_points,
                      speed_repeats=3, seed=seed)
    res = run_study(cfg, progress=progress)
    out: dict[str, Any] = {"n_configs": res.agreement["n_configs"], "n_trials": n_trials,
                           "agreement_max_rel": res.agreement["max_rel"],
                           "printed_eq2_median_rel": res.agreement["printed_median_rel"]}
    for r in res.noise:
        key = r["camera"].split(" (")[0].lower().replace("-", "_")
        out[f"rmse_1px_{key}_cotangent"] = r["rmse_cotangent"]
        out[f"rmse_1px_{key}_homography4"] = r["rmse_homography4"]
        out[f"rmse_1px_{key}_homography_lsq"] = r["rmse_homography_lsq"]
    ratios = [r["ratio"] for r in res.propagation]
    out["propagation_ratio_min"] = min(ratios)
    out["propagation_ratio_max"] = max(ratios)
    out["speed_ratio"] = res.speed["ratio"]
    return out


_CAMERA_LABELS = {"resurs_f": "Resurs-F", "aerial": "aerial frame"}


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The dict of :func:`comparison_summary` as a few readable, labelled lines with units.

    Unknown or missing keys are skipped, so a partial summary gives fewer lines.

    Examples
    --------
    >>> summary_lines({"n_configs": 200, "agreement_max_rel": 3.8e-14, "speed_ratio": 1.0})[0]
    'cotangent vs homography on exact data: max difference 3.8e-14 of the image size (200 configurations)'
    """
    lines: list[str] = []
    if "agreement_max_rel" in summary:
        n = summary.get("n_configs")
        lines.append(f"cotangent vs homography on exact data: max difference {summary['agreement_max_rel']:.2g} "
                     f"of the image size" + (f" ({n} configurations)" if n is not None else ""))
    if "printed_eq2_median_rel" in summary:
        lines.append(f"seed 001 eq. (2) as printed (sign error): median error {summary['printed_eq2_median_rel']:.2f} "
                     "of the image size; corrected formula used")
    cams = sorted({k[len("rmse_1px_"):].rsplit("_", 1)[0] for k in summary
                   if k.startswith("rmse_1px_") and k.endswith("_cotangent")})
    for cam in cams:
        vals = [summary.get(f"rmse_1px_{cam}_{m}") for m in ("cotangent", "homography4", "homography_lsq")]
        if any(v is None for v in vals):
            continue
        trials = summary.get("n_trials")
        lines.append(f"check-point RMSE at 1 px noise, {_CAMERA_LABELS.get(cam, cam)}: cotangent {vals[0]:.2f} px, "
                     f"homography (4 pts) {vals[1]:.2f} px, homography LSQ (all pts) {vals[2]:.2f} px"
                     + (f" ({trials} trials)" if trials is not None else ""))
    if "propagation_ratio_min" in summary and "propagation_ratio_max" in summary:
        lines.append(f"first-order error propagation / Monte Carlo RMSE: {summary['propagation_ratio_min']:.2f} to "
                     f"{summary['propagation_ratio_max']:.2f}")
    if "speed_ratio" in summary:
        lines.append(f"throughput cotangent/homography: {summary['speed_ratio']:.2f}")
    return lines
