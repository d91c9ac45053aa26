#!/usr/bin/env python3
"""Plant plausible mistakes in a copy of the code, one at a time, and check that the tests catch them.

Each mutation is a record: an id, a description, an ``old`` snippet, its ``new`` replacement and the
tests to run (paths or node ids, relative to the repository root). For each mutation the script

1. copies the repository (tracked and untracked, not ignored files) into a temporary directory,
2. finds ``old`` in the ``*.py`` files under ``rectify/`` and ``stereo/`` of the copy; it must occur
   exactly once across both packages (otherwise the mutation is reported as "not applicable", a
   failure: the snippet moved or became ambiguous, and the list needs updating),
3. replaces it with ``new`` and runs ``python -m pytest -x -q -p no:cacheprovider <tests>`` in the
   copy, with ``PYTHONPATH`` set to the copy so that the copy's code is imported (not the editable
   install), and without the shared data folder,
4. counts the mutation *caught* when pytest reports failing tests (exit status 1), *NOT CAUGHT* when
   the tests pass (exit status 0), and *error* for anything else (collection or usage errors, no
   tests collected, a timeout).

Before the mutations, a baseline run of the union of the selected tests on the unmodified copy must
pass, so that "caught" means something. Snippets are short (one line or a sub-expression) so that
moving code between files, or re-wrapping long lines, does not break them.

Usage::

    python scripts/mutation_check.py              # all mutations, 2 workers
    python scripts/mutation_check.py --list       # the list, no runs
    python scripts/mutation_check.py --only M01 M07 --jobs 1

Exit status 0 only when every selected mutation is caught.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("rectify", "stereo")
TIMEOUT_S = 600


@dataclass(frozen=True)
class Mutation:
    """One planted mistake.

    Attributes
    ----------
    id : str
        Short identifier (``R..`` rectify, ``S..`` stereo).
    description : str
        What the mistake is, in words.
    old, new : str
        The snippet to find (exactly once in the packages) and its replacement.
    tests : tuple of str
        Test paths or node ids, relative to the repository root, expected to catch it.
    """

    id: str
    description: str
    old: str
    new: str
    tests: tuple[str, ...]


T_CONV_R = "tests/rectify/test_conventions.py"
T_CONV_S = "tests/stereo/test_conventions.py"
T_PREC_R = "tests/rectify/test_precision.py"
T_PREC_S = "tests/stereo/test_precision.py"
T_TEXT = "tests/stereo/test_textbook.py"
#: issue 32: the numbers users rely on, computed independently
F_R = "tests/rectify/test_field_numbers.py::"
F_S = "tests/stereo/test_field_numbers.py::"
F_U = "tests/cli/test_field_units.py::"

def _m(id_: str, description: str, old: str, new: str, *tests: str) -> Mutation:
    return Mutation(id_, description, old, new, tuple(tests))


#: the curated list (ids R.. rectify, S.. stereo)
MUTATIONS: tuple[Mutation, ...] = (
    # ------------------------------------------------------------------ rectify: seed formulas, rotations
    _m("R01", "cotangent eq. (2), vectorised chain: the y-line sign as printed (- (x2 - x1))",
       "gy += dx0", "gy -= dx0", "tests/rectify/test_projective.py"),
    _m("R02", "cotangent eq. (2), vectorised chain: sign of the x-line's (y2 - y1) term",
       "gx -= dy0", "gx += dy0", "tests/rectify/test_projective.py"),
    _m("R03", "corrected_eq2 with the printed sign in the y-line",
       "y1 + ((y2 - y1) * cb + (x2 - x1)) / s", "y1 + ((y2 - y1) * cb - (x2 - x1)) / s",
       "tests/rectify/test_projective.py"),
    _m("R04", "phi-omega-kappa built as omega-phi-kappa",
       '"phi-omega-kappa": "yxz"', '"phi-omega-kappa": "xyz"', T_CONV_R),
    _m("R05", "alpha-omega-kappa (alias) built as omega-phi-kappa",
       '"alpha-omega-kappa": "yxz"', '"alpha-omega-kappa": "xyz"', T_CONV_R),
    _m("R06", "rotation about Y with the sine signs swapped (a passive rotation)",
       "rows = [[c, z, s], [z, o, z], [-s, z, c]]", "rows = [[c, z, -s], [z, o, z], [s, z, c]]", T_CONV_R),
    _m("R07", "eq. (1): the focal-length term of X' with the wrong sign",
       "Xp = a1 * dx + a2 * dy - a3 * f", "Xp = a1 * dx + a2 * dy + a3 * f", T_CONV_R),
    _m("R08", "eq. (1) as a homography: principal point added instead of subtracted",
       "A = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, -f]])",
       "A = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, -f]])", T_CONV_R),
    # ------------------------------------------------------------------ rectify: pixel conventions
    _m("R09", "half-pixel shift without the rotation term (x)",
       "c + 0.5 * (a + b)", "c + 0.5 * a", T_CONV_R),
    _m("R10", "half-pixel shift without the rotation term (y)",
       "f + 0.5 * (d + e)", "f + 0.5 * e", T_CONV_R),
    _m("R11", "half-pixel shift with the wrong sign (x)",
       "c + 0.5 * (a + b)", "c - 0.5 * (a + b)", T_CONV_R),
    _m("R12", "GDAL-suggested resolution from the source width instead of its diagonal",
       "res = dist / math.hypot(width, height)", "res = dist / width", "tests/rectify/test_georef.py"),
    _m("R13", "image footprint on pixel centres instead of outer pixel edges",
       "x0, x1, y0, y1 = -0.5, width - 0.5, -0.5, height - 0.5",
       "x0, x1, y0, y1 = 0.0, width - 1.0, 0.0, height - 1.0", "tests/rectify/test_georef.py"),
    _m("R14", "camera: principal point y offset with the wrong sign",
       "cy = (self.height - 1) / 2.0 - self.principal_point_mm[1]",
       "cy = (self.height - 1) / 2.0 + self.principal_point_mm[1]", T_CONV_R),
    _m("R15", "camera: photo y axis not flipped (y down like rows)",
       "np.column_stack([n[:, 0], -n[:, 1]]) * self.focal_length_mm",
       "np.column_stack([n[:, 0], n[:, 1]]) * self.focal_length_mm", T_CONV_R),
    _m("R16", "camera: image centre at width / 2 (pixel corner) instead of (width - 1) / 2",
       "cx = (self.width - 1) / 2.0", "cx = self.width / 2.0", T_CONV_R),
    _m("R17", "QGIS .points: source y not shifted by half a pixel the right way",
       "-cols.numbers[sy] - 0.5", "-cols.numbers[sy] + 0.5", T_CONV_R),
    _m("R18", "SIFT detector offset not removed",
       "return pts - SIFT_OFFSET_PX", "return pts",
       "tests/rectify/test_features.py::test_rotated_copy_has_no_systematic_offset"),
    _m("R19", "ORB pyramid levels scaled without the half-pixel terms",
       "out[sel, 0] = (pts[sel, 0] / f + 0.5) * w / wl - 0.5", "out[sel, 0] = pts[sel, 0] / f * w / wl",
       "tests/rectify/test_features.py::test_rotated_copy_has_no_systematic_offset"),
    _m("R20", "overview keypoints scaled to full resolution without the half-pixel terms",
       "xy = (self.xy + 0.5) * scale - 0.5 + ", "xy = self.xy * scale + ", T_CONV_R),
    # ------------------------------------------------------------------ rectify: weights, precision, formats
    _m("R21", "homography refinement weights rows by w instead of sqrt(w)",
       "\n    sw = np.sqrt(w)\n", "\n    sw = w\n", T_CONV_R),
    _m("R22", "affine fit weights rows by w instead of sqrt(w)",
       "a = np.column_stack([sn, np.ones(len(s))]) * np.sqrt(w)[:, None]",
       "a = np.column_stack([sn, np.ones(len(s))]) * w[:, None]", T_CONV_R),
    _m("R23", "polynomial fit weights rows by w instead of sqrt(w)",
       "a = _poly_design((s - shift) * scale, order) * np.sqrt(w)[:, None]",
       "a = _poly_design((s - shift) * scale, order) * w[:, None]", T_CONV_R),
    _m("R24", "residual table sigma0 divides by the number of observations, not the redundancy",
       "dof = v.size - self.n_params", "dof = v.size", T_PREC_R),
    _m("R25", "residual table sigma0 ignores the weights",
       "np.sum(w[:, None] * v * v)", "np.sum(v * v)", T_PREC_R),
    _m("R26", "write_gcps drops the '# crs=' line",
       'buf.write(f"# crs={gcps.crs}\\n")', "pass", T_CONV_R),
    _m("R27", "camera JSON: the principal point written under another key",
       'out["principal_point_mm"] = list(self.principal_point_mm)',
       'out["principal_point"] = list(self.principal_point_mm)', T_CONV_R),
    # ------------------------------------------------------------------ stereo: relative orientation
    _m("S01", "relative orientation: redundancy n - 6 instead of n - 5",
       "dof = int(used.sum()) - 5", "dof = int(used.sum()) - 6", T_PREC_S),
    _m("S02", "relative orientation: every standard error doubled",
       "cov = sigma0 ** 2 * Qinv", "cov = 4.0 * sigma0 ** 2 * Qinv", T_PREC_S),
    _m("S03", "relative orientation: equations weighted by w^2 (rows by w instead of sqrt(w))",
       "ww = w / e.gn2", "ww = w * w / e.gn2", T_CONV_S),
    _m("S04", "relative orientation: sigma0 without the weights",
       "np.sum(w[used] * res[used] ** 2)", "np.sum(res[used] ** 2)", T_CONV_S),
    _m("S05", "relative orientation: vertical parallax as the normalised residual",
       "return self.F * (self.g1 + self.g2) / self.gn2", "return self.F / np.sqrt(self.gn2)", T_TEXT),
    # ------------------------------------------------------------------ stereo: absolute orientation, resection
    _m("S06", "absolute orientation: sigma0 divides by n instead of n - 7",
       "np.sum(w_final * v * v)) / dof)", "np.sum(w_final * v * v)) / (dof + 7))", T_PREC_S),
    _m("S07", "absolute orientation: covariance not scaled by sigma0^2",
       "cov = s02 * Jt @ Qxx @ Jt.T", "cov = Jt @ Qxx @ Jt.T", T_PREC_S),
    _m("S08", "resection: sigma0 divides by n instead of the redundancy",
       "dof = 2 * nf - nfree", "dof = 2 * nf", T_PREC_S),
    _m("S09", "resection: covariance scaled by sigma0 instead of sigma0^2",
       "cov = (sigma0 ** 2 if math.isfinite(sigma0) else 1.0) * Q",
       "cov = (sigma0 if math.isfinite(sigma0) else 1.0) * Q", T_PREC_S),
    _m("S10", "exterior orientation: principal point subtracted in the projection",
       "self.principal_point_mm[0] - f * p[:, 0] / p[:, 2]", "-self.principal_point_mm[0] - f * p[:, 0] / p[:, 2]",
       T_CONV_S),
    # ------------------------------------------------------------------ stereo: intersection
    _m("S11", "aerial N formula: N2 from the numerator of N1 (d2 instead of d1)",
       "num2 = b2 * d1[0] - b0 * d1[2]", "num2 = b2 * d2[0] - b0 * d2[2]", T_CONV_S),
    _m("S12", "general N formula: N2 with d2 in the first numerator term",
       "num2 = (b1 * d1[2] - b2 * d1[1])", "num2 = (b1 * d2[2] - b2 * d2[1])", T_CONV_S),
    _m("S13", "midpoint: N2 with the wrong sign",
       "N2 = (d12 * e - n1s * g) * idet", "N2 = (n1s * g - d12 * e) * idet", T_CONV_S),
    _m("S14", "least squares: N2 measured from the left centre (base forgotten)",
       "N2 = ((P[0] - b0) * d2[0]", "N2 = ((P[0] - 0.0) * d2[0]", T_CONV_S),
    _m("S15", "intersection covariance scaled by sigma instead of sigma^2",
       "s2 = float(sigma_mm) ** 2", "s2 = float(sigma_mm)", T_PREC_S),
    _m("S16", "seed 001 N formula: the Bz term with the wrong sign",
       "(bx + a2 / focal_length_mm * bz) / p", "(bx - a2 / focal_length_mm * bz) / p", T_CONV_S),
    _m("S17", "collinearity (intersection.project): x without the minus sign",
       "[-focal_length_mm * p[:, 0] / p[:, 2]", "[focal_length_mm * p[:, 0] / p[:, 2]", T_CONV_S),
    # ------------------------------------------------------------------ stereo: shared least squares, formats
    _m("S18", "normal equations (rectify.geometry.lsq, used by absolute orientation) weight rows by w^2",
       "a * np.asarray(weights, dtype=np.float64).reshape(-1, 1)",
       "a * np.asarray(weights, dtype=np.float64).reshape(-1, 1) ** 2", T_CONV_S),
    _m("S19", "exterior orientation JSON: omega and phi values swapped",
       '"system": "omega-phi-kappa", "omega": om, "phi": ph', '"system": "omega-phi-kappa", "omega": ph, "phi": om',
       T_CONV_S),
    # ------------------------------------------------------------------ issue 32: rasters (half pixels, tiles)
    _m("R28", "warp: cubic kernel without its margin (radius 0: a tile's window misses the kernel's tail)",
       '"cubic": (cv2.INTER_CUBIC, 2)', '"cubic": (cv2.INTER_CUBIC, 0)',
       F_R + "test_warp_does_not_depend_on_the_tile_size"),
    _m("R29", "warp: Lanczos kernel with half its margin",
       '"lanczos": (cv2.INTER_LANCZOS4, 4)', '"lanczos": (cv2.INTER_LANCZOS4, 2)',
       F_R + "test_warp_does_not_depend_on_the_tile_size"),
    _m("R30", "warp: source window without the kernel margin on the right",
       "x1 = min(math.ceil(bx[1]) + self.radius + 1, self.W)", "x1 = min(math.ceil(bx[1]) + 1, self.W)",
       F_R + "test_warp_does_not_depend_on_the_tile_size"),
    _m("R31", "warp: sparse map lattice anchored on the tile, not the grid",
       "first = (lo // s) * s", "first = lo", F_R + "test_warp_does_not_depend_on_the_tile_size"),
    _m("R32", "warp: window origin not even (half-way positions round with the tiling)",
       "x0 = max(math.floor(bx[0]) - self.radius, 0) // 2 * 2", "x0 = max(math.floor(bx[0]) - self.radius, 0)",
       F_R + "test_warp_nearest_half_way_positions_do_not_depend_on_the_tile_size"),
    _m("R33", "mosaic: rows sampled at pixel corners instead of centres",
       "(np.arange(r0, r0 + h) + 0.5)\n        X, Y = np.meshgrid(xs, ys)",
       "np.arange(r0, r0 + h)\n        X, Y = np.meshgrid(xs, ys)",
       F_R + "test_mosaic_geotransform_and_half_pixel"),
    _m("R34", "mosaic: a replicated edge divided by the weights of the valid neighbours",
       "borderMode=cv2.BORDER_CONSTANT, borderValue=0) for k in range(inp.count)]",
       "borderMode=cv2.BORDER_REPLICATE) for k in range(inp.count)]", F_R + "test_mosaic_geotransform_and_half_pixel"),
    _m("R35", "mosaic: window origin not even", "c0 = max(int(math.floor(px.min())) - 1, 0) // 2 * 2",
       "c0 = max(int(math.floor(px.min())) - 1, 0)", F_R + "test_mosaic_does_not_depend_on_the_tile_size"),
    _m("R36", "ortho: source window without its pad (tile borders)",
       "        pad = 3\n        c_lo = max(", "        pad = 0\n        c_lo = max(",
       F_R + "test_ortho_does_not_depend_on_the_tile_size"),
    _m("R37", "GCP fit: residual table with observed and adjusted swapped",
       "observed=gcps.target,\n                          adjusted=adjusted,",
       "observed=adjusted,\n                          adjusted=gcps.target,",
       F_R + "test_fit_residuals_are_adjusted_minus_observed"),
    _m("R38", "ortho: output rows sampled at their pixels' corners",
       "ys = t[5] + t[4] * (np.arange(r0, r0 + h) + 0.5)\n        return np.broadcast_to",
       "ys = t[5] + t[4] * np.arange(r0, r0 + h)\n        return np.broadcast_to",
       F_R + "test_ortho_geotransform_from_the_footprint"),
    # ------------------------------------------------------------------ issue 32: stereo numbers
    _m("S20", "DSM: cell centres at the cells' left edges (content half a cell off its geotransform)",
       "self.x0 = left + cell / 2", "self.x0 = left",
       F_S + "test_dsm_geotiff_cells_are_centred_where_the_geotransform_says"),
    _m("S21", "DSM GeoTIFF: geotransform shifted by half a cell",
       'TiledWriter(tmp, W, H, 3, "float32", self.transform,',
       'TiledWriter(tmp, W, H, 3, "float32", self.transform * Affine.translation(0.5, 0.5),',
       F_S + "test_dsm_geotiff_cells_are_centred_where_the_geotransform_says",
       F_S + "test_dense_dsm_cells_hold_the_points_that_fall_in_them"),
    _m("S22", "dense matching: tiles without overlap (seams)", "    overlap: int = 48\n", "    overlap: int = 0\n",
       F_S + "test_dense_matching_does_not_depend_on_the_tile_size"),
    _m("S23", "bundle: covariance scaled by sigma0 instead of sigma0^2",
       "s0v = s0 ** 2 if math.isfinite(s0) else 1.0", "s0v = s0 if math.isfinite(s0) else 1.0",
       F_S + "test_bundle_standard_errors_do_not_depend_on_the_a_priori_scale",
       F_S + "test_bundle_standard_errors_against_monte_carlo_with_pessimistic_priors"),
    _m("S24", "bundle: image residuals computed - observed (its docstring: observed - computed)",
       "residuals_px=_ro(res.image)", "residuals_px=_ro(-res.image)", F_S + "test_bundle_residual_signs_as_documented"),
    _m("S25", "stereo block: --ins-sigma degrees taken as radians",
       "ins_sigma_rad=None if ins_sigma is None else _radians(ins_sigma),",
       "ins_sigma_rad=None if ins_sigma is None else ins_sigma,", F_U + "test_block_angle_options_are_degrees"),
    _m("S26", "stereo block: --boresight degrees taken as radians",
       "boresight_rad=None if boresight is None else _radians(boresight),",
       "boresight_rad=None if boresight is None else boresight,", F_U + "test_block_angle_options_are_degrees"),
    _m("S27", "stereo orient: radians printed with the label deg",
       "{math.degrees(ro.elements[i]):11.5f}", "{ro.elements[i]:11.5f}",
       F_U + "test_orient_prints_degrees_of_the_radians_it_writes"),
    _m("S28", "stereo resect: angles printed in radians", "om, ph, ka = (math.degrees(a) for a in eo.angles)",
       "om, ph, ka = (float(a) for a in eo.angles)", F_U + "test_resect_prints_degrees_of_the_radians_it_writes"),
    _m("S29", "rig summary: relative angles printed in radians",
       "om, ph, ka = (math.degrees(float(x)) for x in self.angles)", "om, ph, ka = (float(x) for x in self.angles)",
       F_U + "test_rig_prints_degrees_of_the_radians_it_writes"),
    _m("S30", "intersection: residuals measured - reprojected", "= -rx1, -ry1, -rx2, -ry2", "= rx1, ry1, rx2, ry2",
       F_S + "test_intersection_residuals_are_reprojected_minus_measured"),
    _m("S31", "calibration: redundancy without the unknowns",
       "dof = 2 * int(used.sum()) - prob.U", "dof = 2 * int(used.sum())",
       F_S + "test_calibration_redundancy_counted_by_hand"),
    _m("S32", "calibration: residuals observed - adjusted", "residuals=r.reshape(-1, 2)", "residuals=-r.reshape(-1, 2)",
       F_S + "test_calibration_residual_sign_is_adjusted_minus_observed"),
    _m("S33", "absolute orientation: model covariance turned R^T C R into the ground covariance",
       'C = C + np.einsum("ij,njk,lk->nil", sR, Cm, sR)', 'C = C + np.einsum("ji,njk,kl->nil", sR, Cm, sR)',
       F_S + "test_absolute_orientation_residuals_and_point_covariance"),
    _m("S34", "stereo model: control weights from covariances turned R^T C R",
       'cg = np.einsum("ij,njk,lk->nil", sR, cov_rows, sR)', 'cg = np.einsum("ji,njk,kl->nil", sR, cov_rows, sR)',
       F_S + "test_model_ground_std_against_monte_carlo_in_a_rotated_frame"),
    _m("S35", "absolute orientation: residual table with observed and adjusted swapped",
       "observed=observed, adjusted=adj_rows,", "observed=adj_rows, adjusted=observed,",
       F_S + "test_absolute_orientation_residuals_and_point_covariance"),
    _m("S36", "resection: residual table with observed and adjusted swapped",
       "observed=prob.x, adjusted=pred_all,", "observed=pred_all, adjusted=prob.x,",
       F_S + "test_resection_residuals_are_adjusted_minus_observed"),
)


# ---------------------------------------------------------------------- machinery
def _repo_files(root: Path) -> list[Path]:
    out = subprocess.run(["git", "ls-files", "-z", "-co", "--exclude-standard"], cwd=root, check=True,
                         capture_output=True).stdout.decode()
    files = []
    for name in out.split("\0"):
        if not name:
            continue
        p = root / name
        if p.is_file() and "__pycache__" not in p.parts:
            files.append(Path(name))
    return files


def _copy_repo(root: Path, dst: Path) -> None:
    for rel in _repo_files(root):
        target = dst / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(root / rel, target)


def _link_tree(src: Path, dst: Path) -> None:
    """Hard-link copy of ``src`` (cheap); files to be changed are replaced, never written through."""
    shutil.copytree(src, dst, copy_function=os.link)


def _package_files(tree: Path) -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (tree / pkg).rglob("*.py") if "__pycache__" not in p.parts)


def locate(tree: Path, old: str) -> tuple[list[tuple[Path, int]], int]:
    """Files under the packages of ``tree`` containing ``old`` and the total count of occurrences."""
    hits = []
    total = 0
    for p in _package_files(tree):
        k = p.read_text(encoding="utf-8").count(old)
        if k:
            hits.append((p, k))
            total += k
    return hits, total


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    # a fresh clone has no shared data folder next to it: make sure none is found
    env["RECTIFY_SHARED_DATA"] = str(tree / "no-shared-data")
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def run_pytest(tree: Path, tests: tuple[str, ...]) -> tuple[int, str, float]:
    """Run pytest on ``tests`` in ``tree``; returns (exit status or -1 on timeout, output tail, seconds)."""
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, cwd=tree, env=_env(tree), capture_output=True, text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return -1, f"timeout after {TIMEOUT_S} s", time.perf_counter() - t0
    tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-15:])
    return r.returncode, tail, time.perf_counter() - t0


@dataclass
class Outcome:
    mutation: Mutation
    status: str  # "caught", "NOT CAUGHT", "error", "not applicable"
    where: str
    seconds: float
    detail: str = ""


def apply_and_run(base: Path, work: Path, m: Mutation) -> Outcome:
    """Copy ``base`` to ``work / m.id``, plant ``m`` and run its tests."""
    tree = work / m.id
    _link_tree(base, tree)
    try:
        hits, total = locate(tree, m.old)
        if total != 1:
            where = ", ".join(f"{p.relative_to(tree)} ({k})" for p, k in hits) or "-"
            return Outcome(m, "not applicable", where, 0.0, f"snippet found {total} times")
        path = hits[0][0]
        text = path.read_text(encoding="utf-8").replace(m.old, m.new)
        path.unlink()  # break the hard link: the base copy stays intact
        path.write_text(text, encoding="utf-8")
        code, tail, secs = run_pytest(tree, m.tests)
        where = str(path.relative_to(tree))
        if code == 1:
            return Outcome(m, "caught", where, secs, tail)
        if code == 0:
            return Outcome(m, "NOT CAUGHT", where, secs, tail)
        return Outcome(m, "error", where, secs, f"pytest exit status {code}: {tail}")
    finally:
        shutil.rmtree(tree, ignore_errors=True)


def _check_import_location(base: Path) -> None:
    code = "import rectify, stereo; print(rectify.__file__); print(stereo.__file__)"
    r = subprocess.run([sys.executable, "-c", code], cwd=base, env=_env(base), capture_output=True, text=True,
                       check=True)
    for line in r.stdout.split():
        if not Path(line).resolve().is_relative_to(base.resolve()):
            raise SystemExit(f"the copy does not import its own packages ({line}); check PYTHONPATH")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--list", action="store_true", help="print the mutations and exit")
    ap.add_argument("--only", nargs="+", metavar="ID", help="run only these mutation ids")
    ap.add_argument("--jobs", type=int, default=2, help="parallel workers (default 2)")
    ap.add_argument("--locate", action="store_true",
                    help="only check that every snippet occurs exactly once in the working tree")
    ap.add_argument("--no-baseline", action="store_true", help="skip the baseline run on unmodified code")
    ap.add_argument("-v", "--verbose", action="store_true", help="print pytest's output tail for each mutation")
    args = ap.parse_args(argv)

    ids = [m.id for m in MUTATIONS]
    if len(set(ids)) != len(ids):
        raise SystemExit("duplicate mutation ids")
    selected = list(MUTATIONS)
    if args.only:
        unknown = sorted(set(args.only) - set(ids))
        if unknown:
            raise SystemExit(f"unknown mutation id(s): {unknown}")
        selected = [m for m in MUTATIONS if m.id in args.only]
    if args.list:
        for m in selected:
            print(f"{m.id}  {m.description}")
            print(f"      {m.old!r} -> {m.new!r}")
            print(f"      tests: {' '.join(m.tests)}")
        print(f"{len(selected)} mutations")
        return 0

    if args.locate:
        bad = 0
        for m in selected:
            hits, total = locate(ROOT, m.old)
            where = ", ".join(f"{p.relative_to(ROOT)} ({k})" for p, k in hits) or "-"
            bad += total != 1
            print(f"{m.id:<5} {'ok' if total == 1 else 'NOT APPLICABLE':<15} {where}")
        return 1 if bad else 0

    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mutation-check-") as tmp:
        work = Path(tmp)
        base = work / "base"
        base.mkdir()
        _copy_repo(ROOT, base)
        _check_import_location(base)
        if not args.no_baseline:
            tests = tuple(dict.fromkeys(t for m in selected for t in m.tests))
            code, tail, secs = run_pytest(base, tests)
            print(f"baseline (unmodified code, {len(tests)} test selections): exit status {code}, {secs:.1f} s")
            if code != 0:
                print(tail)
                print("the baseline must pass before mutations mean anything")
                return 1
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            outcomes = list(pool.map(lambda m: apply_and_run(base, work, m), selected))

    w_where = max([len("file")] + [len(o.where) for o in outcomes])
    print(f"{'id':<5} {'file':<{w_where}} {'result':<15} {'seconds':>7}  description")
    for o in outcomes:
        extra = f" ({o.detail})" if o.status == "not applicable" else ""
        print(f"{o.mutation.id:<5} {o.where:<{w_where}} {o.status:<15} {o.seconds:7.1f}  "
              f"{o.mutation.description}{extra}")
        if args.verbose or o.status == "error":
            print("      " + o.detail.replace("\n", "\n      "))
    n_caught = sum(o.status == "caught" for o in outcomes)
    n_rect = sum(o.mutation.id.startswith("R") for o in outcomes)
    print(f"{n_caught} of {len(outcomes)} mutations caught ({n_rect} rectify, {len(outcomes) - n_rect} stereo); "
          f"wall time {time.perf_counter() - t_start:.0f} s with {args.jobs} worker(s)")
    return 0 if n_caught == len(outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
