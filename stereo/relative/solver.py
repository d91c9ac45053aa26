"""Estimation of a relative orientation in stages (see :mod:`stereo.relative`).

:meth:`stereo.relative.RelativeOrientation.from_points` runs

1. :func:`validate`: inputs (shapes, system, robust method, initial values, weights) -> :class:`Problem`;
2. :func:`solve`: start values (zero angles, the essential matrix of :func:`relative_from_essential`,
   or given ones), Gauss-Newton on the weighted coplanarity equations, robust reweighting (IRLS),
   the cheirality test -> :class:`Solution`;
3. :func:`precision`: normal equations, condition numbers, sigma0 with the redundancy n - 5,
   covariance and outlier flags (:mod:`rectify.geometry.lsq`) -> :class:`Precision`.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError, WeakGeometryWarning
from rectify.geometry import lsq
from rectify.geometry.points import as_ids, as_pair, as_weights
from rectify.geometry.robust import ROBUST_METHODS, get_psi, irls
from stereo.relative.projective import relative_from_fundamental
from stereo.relative.systems import System, _evaluate, _focals, _rays, _unit, dobrynin_pimshina_for_base, get_system
from stereo.relative.universal import solve_universal

logger = logging.getLogger(__name__)

__all__ = ["INITIAL_METHODS", "Precision", "Problem", "RelativeOptions", "Solution", "precision",
           "relative_from_essential", "solve", "validate", "choose_frame"]

#: initial values of the adjustment (see :meth:`stereo.relative.RelativeOrientation.from_points`)
INITIAL_METHODS = ("auto", "zero", "essential")


# ------------------------------------------------------------ essential matrix
def relative_from_essential(left_mm: ArrayLike, right_mm: ArrayLike, focal_length_mm, *,
                            threshold_mm: float = 0.15, confidence: float = 0.999,
                            method: str = "magsac", rng_seed: int = 0
                            ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Relative rotation and base from OpenCV's five-point essential matrix.

    Parameters
    ----------
    left_mm, right_mm : (N, 2) float64
        Photo coordinates, mm.
    focal_length_mm : float or (float, float)
    threshold_mm : float
        RANSAC inlier threshold on the image, mm.
    method : {"magsac", "ransac"}
        ``cv2.USAC_MAGSAC`` or ``cv2.RANSAC``.

    Returns
    -------
    R_rel : (3, 3)
        Right photo frame -> left photo frame.
    base_left : (3,)
        Unit base (right centre minus left) in the left photo frame.
    inlier_mask : (N,) bool
        RANSAC inliers that also pass the cheirality test of ``recoverPose``.

    Raises
    ------
    EstimationError
        When OpenCV finds no essential matrix or fewer than 5 inliers.
    """
    lm, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    if len(lm) < 5:
        raise EstimationError(f"too few tie points for the essential matrix: {len(lm)} given, at least 5 needed")
    f1, f2 = _focals(focal_length_mm)
    # OpenCV camera frame: x right, y down, z forward = diag(1, -1, -1) * photo frame
    n1 = np.column_stack([lm[:, 0] / f1, -lm[:, 1] / f1])
    n2 = np.column_stack([r[:, 0] / f2, -r[:, 1] / f2])
    flag = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}[method]
    thr = threshold_mm / math.sqrt(f1 * f2)
    try:
        cv2.setRNGSeed(int(rng_seed))
        E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), method=flag, prob=confidence, threshold=thr)
    except cv2.error as err:
        raise EstimationError(f"OpenCV findEssentialMat failed: {err}") from err
    if E is None or E.shape[0] < 3:
        raise EstimationError(f"OpenCV found no essential matrix for {len(lm)} tie points (degenerate configuration?)")
    E = E[:3]
    try:
        _ninl, R, t, mask2 = cv2.recoverPose(E, n1, n2, np.eye(3), mask=mask.copy())
    except cv2.error as err:
        raise EstimationError(f"OpenCV recoverPose failed: {err}") from err
    inl = (mask2.reshape(-1) > 0)
    if inl.sum() < 5:
        raise EstimationError(f"the essential matrix has only {int(inl.sum())} inliers in front of both cameras")
    D = np.diag([1.0, -1.0, -1.0])
    R_rel = D @ R.T @ D
    base = -(D @ R.T @ t.reshape(3))
    return R_rel, _unit(base), inl


@dataclass(frozen=True)
class RelativeOptions:
    """Numerical options of :meth:`RelativeOrientation.from_points`.

    Attributes
    ----------
    max_iterations : int
        Gauss-Newton iteration limit (per reweighting).
    tol_rad : float
        Convergence: largest correction to any element, radians.
    max_irls_iterations : int
        Reweighting limit of robust estimation.
    ransac_threshold_px : float
        Inlier threshold of the essential-matrix RANSAC, pixels (converted with
        the pixel size; 0.144 mm is assumed when it is unknown).
    outlier_threshold : float
        Flag |e| > threshold * robust scale.
    weak_condition : float
        WeakGeometryWarning above this condition number of the (column-scaled)
        normal matrix.
    singular_condition : float
        EstimationError ("degenerate configuration") above this.
    rng_seed : int
        Seed of OpenCV's RANSAC.
    zero_start_max_rotation : float
        With ``initial="auto"``, go straight to the essential-matrix start when
        the in-plane rotation between the two point sets exceeds this (rad).
    """

    max_iterations: int = 30
    tol_rad: float = 1e-10
    max_irls_iterations: int = 30
    ransac_threshold_px: float = 2.0
    outlier_threshold: float = 3.0
    weak_condition: float = 1e5
    singular_condition: float = 1e12
    rng_seed: int = 0
    zero_start_max_rotation: float = 0.5


_DEFAULT_PIXEL_MM = 0.144


def _gauss_newton(sys_: System, p0: NDArray, u1: NDArray, u2: NDArray, w: NDArray, opts: RelativeOptions,
                  *, steps: int | None = None, check: bool = True) -> tuple[NDArray, int]:
    """Gauss-Newton on the weighted coplanarity equations.

    ``steps``: take at most this many steps and return without a convergence
    error (used inside IRLS). ``check``: test the conditioning at the first step.
    """
    p = p0.copy()
    used = int(np.count_nonzero(w > 0))
    if used < 5:
        raise EstimationError(f"only {used} tie point(s) with positive weight; at least 5 needed")
    last = math.inf
    for it in range(1, (steps or opts.max_iterations) + 1):
        e = _evaluate(sys_, p, u1, u2)
        ww = w / e.gn2
        if not np.isfinite(ww).all():
            raise EstimationError("a tie point has zero coplanarity gradient (ray along the base?)")
        A = e.J * np.sqrt(ww)[:, None]
        y = e.F * np.sqrt(ww)
        N = A.T @ A
        d = np.sqrt(np.diag(N))
        if not (d > 0).all():
            k = int(np.flatnonzero(~(d > 0))[0])
            raise EstimationError(
                f"degenerate configuration: the tie points do not determine element {sys_.names[k]!r} "
                "(no parallax, or all points on one line)")
        if check and it == 1:
            Ns = N / np.outer(d, d)
            cond = np.linalg.cond(Ns)
            if not np.isfinite(cond) or cond > opts.singular_condition:
                raise EstimationError(
                    f"degenerate configuration: normal matrix condition number {cond:.3g} "
                    f"(> {opts.singular_condition:.0e}); points collinear, coplanar with the base, or no parallax")
        try:
            dp = -np.linalg.solve(N, A.T @ y)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"degenerate configuration: singular normal matrix at iteration {it}") from err
        if not np.isfinite(dp).all():
            raise ConvergenceError(f"iteration {it} produced non-finite corrections", iterations=it)
        p = p + dp
        step = float(np.max(np.abs(dp)))
        logger.debug("GN %s it %d: max |dp| = %.3g rad", sys_.name, it, step)
        if step < opts.tol_rad or (steps is not None and it == steps):
            return p, it
        if it > 5 and step > 1.0 and step >= last:
            raise ConvergenceError(
                f"relative orientation diverges: correction {step:.3g} rad at iteration {it}", iterations=it)
        last = step
    raise ConvergenceError(
        f"relative orientation did not converge in {opts.max_iterations} iterations "
        f"(last correction {last:.3g} rad > {opts.tol_rad:g})", iterations=opts.max_iterations)


def _inplane_rotation(lm: NDArray, r: NDArray) -> float:
    """|angle| (rad) of the 2D similarity that best maps left photo points onto the right ones."""
    a = lm - lm.mean(axis=0)
    b = r - r.mean(axis=0)
    return abs(math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b))))


def _wrap(p: NDArray) -> NDArray:
    return (p + np.pi) % (2 * np.pi) - np.pi


def _cheirality(sys_: System, p: NDArray, u1: NDArray, u2: NDArray, mask: NDArray) -> float:
    """Fraction of points (in mask) in front of both cameras."""
    R1, R2, b = sys_.geometry(p)
    r1 = u1[mask] @ R1.T
    r2 = u2[mask] @ R2.T
    c = np.cross(r1, r2)
    cc = np.einsum("ij,ij->i", c, c)
    ok = cc > 0
    l1 = np.einsum("ij,ij->i", np.cross(b, r2), c)[ok] / cc[ok]
    l2 = np.einsum("ij,ij->i", np.cross(b, r1), c)[ok] / cc[ok]
    return float(np.mean((l1 > 0) & (l2 > 0))) if ok.any() else 0.0


def _initial_vector(sys_: System, initial) -> NDArray[np.float64]:
    if isinstance(initial, dict):
        unknown = sorted(set(initial) - set(sys_.names))
        if unknown:
            raise InvalidInputError(f"initial values for unknown element(s) {unknown} of system {sys_.name!r}; "
                                    f"elements are {list(sys_.names)}")
        v = np.array([float(initial.get(k, 0.0)) for k in sys_.names])
    else:
        v = np.array(initial, dtype=np.float64).reshape(-1)
    if v.shape != (5,) or not np.isfinite(v).all():
        raise InvalidInputError(f"`initial` must be 5 finite angles (rad); got {initial!r}")
    return v


def _solve(sys_: System, p0, u1, u2, prior, robust: str, opts: RelativeOptions):
    """Plain or robust adjustment; returns (p, weights, gn_iterations, irls_iterations, scale, converged)."""
    if sys_.name == "universal" and robust == "none":  # the linear iterations found p; no Gauss-Newton
        return p0, prior.copy(), 0, 0, None, True
    if robust == "none":
        p, it = _gauss_newton(sys_, p0, u1, u2, prior, opts)
        return p, prior.copy(), it, 0, None, True
    # IRLS: one Gauss-Newton step per reweighting, then a full adjustment with the final weights
    p_start, _ = _gauss_newton(sys_, p0, u1, u2, prior, opts)

    def fit(w, prev):
        return _gauss_newton(sys_, prev, u1, u2, w, opts, steps=1, check=False)[0]

    def resid(p):
        return _evaluate(sys_, p, u1, u2, jac=False).normalised

    res = irls(fit, resid, len(u1), psi=get_psi(robust), initial=p_start, prior_weights=prior, min_used=6,
               max_iterations=opts.max_irls_iterations, tol=1e-3, outlier_threshold=opts.outlier_threshold)
    p, it = _gauss_newton(sys_, res.model, u1, u2, res.weights, opts)
    return p, res.weights, it, res.iterations, res.scale, res.converged


# ------------------------------------------------------------------ stages
@dataclass(frozen=True, eq=False)
class Problem:
    """Validated input of a relative orientation (stage 1).

    Attributes
    ----------
    system : System
    robust : str
    left_mm, right_mm : (N, 2) float64
        Photo coordinates, mm.
    focal_length_mm : (float, float)
    pixel_size_mm : float or None
    weights : (N,) float64
        A-priori weights.
    ids : tuple of str
    initial : str
        ``"auto"``, ``"zero"``, ``"essential"`` or ``"given"``.
    given : (5,) float64 or None
        The given start values (``initial == "given"``).
    """

    system: System
    robust: str
    left_mm: NDArray[np.float64]
    right_mm: NDArray[np.float64]
    focal_length_mm: tuple[float, float]
    pixel_size_mm: float | None
    weights: NDArray[np.float64]
    ids: tuple[str, ...]
    initial: str
    given: NDArray[np.float64] | None

    @property
    def n(self) -> int:
        return len(self.left_mm)

    @property
    def rays(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Photo vectors (x, y, -f) of both images, (N, 3) each."""
        return _rays(self.left_mm, self.focal_length_mm[0]), _rays(self.right_mm, self.focal_length_mm[1])


def validate(left_mm: ArrayLike, right_mm: ArrayLike, *, focal_length_mm: float | tuple[float, float],
             system: str | System = "left-image", robust: str = "none",
             initial: str | ArrayLike | dict[str, float] = "auto", ids: Sequence[str] | None = None,
             weights: ArrayLike | None = None, pixel_size_mm: float | None = None) -> Problem:
    """Stage 1: check the inputs of :meth:`RelativeOrientation.from_points` (its parameters)."""
    sys_ = get_system(system)
    robust = str(robust).lower()
    if robust not in ROBUST_METHODS:
        raise InvalidInputError(f"unknown robust method {robust!r}; expected one of {list(ROBUST_METHODS)}")
    lm, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    n = len(lm)
    if n < 5:
        raise EstimationError(f"too few tie points for relative orientation: {n} given, at least 5 needed")
    f1, f2 = _focals(focal_length_mm)
    if pixel_size_mm is not None and not (math.isfinite(pixel_size_mm) and pixel_size_mm > 0):
        raise InvalidInputError(f"`pixel_size_mm` must be finite and > 0; got {pixel_size_mm!r}")
    w0 = as_weights(weights, n)
    id_list = as_ids(ids, n)
    given = None
    if isinstance(initial, str):
        init = initial.lower()
        if init not in INITIAL_METHODS:
            raise InvalidInputError(f"unknown initial {initial!r}; expected 'auto', 'zero', 'essential', "
                                    "5 values or a dict of elements")
    else:
        init = "given"
        given = _initial_vector(sys_, initial)
    if sys_.name in ("universal", "projective") and init != "auto":
        raise InvalidInputError(f"system {sys_.name!r} needs no initial values (it starts from the "
                                f"{'identity' if sys_.name == 'universal' else 'fundamental matrix'}); got "
                                f"initial {initial!r}")
    if sys_.name == "projective" and robust != "none":
        raise InvalidInputError(f"robust estimation ({robust!r}) is not available with system 'projective' "
                                "(the fundamental matrix is fitted by least squares); use --robust none")
    if sys_.name == "projective" and n < 8:
        raise EstimationError(f"too few tie points for relative orientation by the fundamental matrix: {n} given, "
                              "at least 8 needed (the eight-point method; 7 is the algebraic minimum)")
    return Problem(sys_, robust, lm, r, (f1, f2), pixel_size_mm, w0, id_list, init, given)


@dataclass(frozen=True, eq=False)
class Solution:
    """Stage 2: the estimated elements and how they were found.

    Attributes
    ----------
    elements : (5,) float64
        Radians, wrapped to (-pi, pi].
    weights : (N,) float64
        Final weights (0 for rejected points).
    iterations, irls_iterations : int
    scale : float or None
        Final robust scale of the normalised residuals, mm.
    initial : str
        The start that succeeded: ``"zero"``, ``"essential"`` or ``"given"`` (``"universal"``,
        ``"fundamental"`` for the method systems).
    extra : dict or None
        Figures of the method's own stage (system ``projective``: the fundamental matrix and its
        Sampson fit).
    """

    elements: NDArray[np.float64]
    weights: NDArray[np.float64]
    iterations: int
    irls_iterations: int
    scale: float | None
    initial: str
    extra: dict[str, Any] | None = None


def choose_frame(prob: Problem, opts: RelativeOptions) -> Problem:
    """For the dobrynin-pimshina system, turn the photo frames so that the base runs along +x
    (:func:`~stereo.relative.systems.dobrynin_pimshina_for_base`, from the essential-matrix base);
    other systems, given start values and turned systems are kept."""
    sys_ = prob.system
    if sys_.name != "dobrynin-pimshina" or prob.initial == "given":
        return prob
    pix = prob.pixel_size_mm or _DEFAULT_PIXEL_MM
    try:
        _, bl, _ = relative_from_essential(prob.left_mm, prob.right_mm, prob.focal_length_mm,
                                           threshold_mm=opts.ransac_threshold_px * pix, rng_seed=opts.rng_seed)
    except EstimationError:
        return prob  # the solver names the problem
    turned = dobrynin_pimshina_for_base(bl)
    if turned is not sys_:
        logger.info("dobrynin-pimshina: base %s in the left photo frame; photo frames turned by %d degrees",
                    np.round(_unit(bl), 3).tolist(), turned.turn_deg)
    return replace(prob, system=turned)


def solve(prob: Problem, opts: RelativeOptions) -> Solution:
    """Stage 2: start values, Gauss-Newton (and IRLS), cheirality; tries the next start on failure."""
    sys_, robust, lm, r, n = prob.system, prob.robust, prob.left_mm, prob.right_mm, prob.n
    u1, u2 = prob.rays
    pix = prob.pixel_size_mm or _DEFAULT_PIXEL_MM
    essential_cache: dict[str, Any] = {}

    def essential() -> tuple[NDArray, NDArray]:
        if not essential_cache:
            R_rel, bl, inl = relative_from_essential(lm, r, prob.focal_length_mm,
                                                     threshold_mm=opts.ransac_threshold_px * pix,
                                                     rng_seed=opts.rng_seed)
            essential_cache.update(p=sys_.elements_from_relative(R_rel, bl), inliers=inl)
        return essential_cache["p"], essential_cache["inliers"]

    init = prob.initial
    prior = prob.weights.copy()
    extra: dict[str, Any] | None = None
    universal_iterations = 0
    if robust != "none":
        _, inl = essential()
        prior = np.where(inl, prob.weights, 0.0)
        logger.info("RANSAC (essential matrix): %d of %d tie points kept", int(inl.sum()), n)
    starts: list[tuple[str, NDArray | None]] = []
    if sys_.name == "universal":  # seed 003, 3.2.1: linear iterations from the identity
        p_universal, universal_iterations = solve_universal(u1, u2, prior)
        starts.append(("universal", p_universal))
    elif sys_.name == "projective":  # seed 003, 3.2.2: the elements from the fundamental matrix
        used = prior > 0
        R_rel, bl, F, fit = relative_from_fundamental(lm[used], r[used], prob.focal_length_mm, pix)
        logger.info("fundamental matrix: Sampson rms %.3g px, %d LM iterations", fit.rms_px, fit.iterations)
        extra = {"fundamental_matrix_photo_px": F.tolist(), "sampson_rms_px": fit.rms_px,
                 "sampson_sigma0_px": fit.sigma0_px, "redundancy": fit.redundancy, "iterations": fit.iterations,
                 "condition": fit.condition}
        starts.append(("fundamental", sys_.elements_from_relative(R_rel, bl)))
    elif init == "given":
        starts.append(("given", prob.given))
    elif init == "zero":
        starts.append(("zero", np.zeros(5)))
    elif init == "essential" or (init == "auto" and robust != "none"):
        starts.append(("essential", None))
    elif _inplane_rotation(lm, r) > opts.zero_start_max_rotation:
        starts.append(("essential", None))  # e.g. relative kappa near 180 deg: zero angles cannot serve
    else:
        starts += [("zero", np.zeros(5)), ("essential", None)]

    last_err: Exception | None = None
    for label, p0 in starts:
        try:
            if p0 is None:
                p0 = essential()[0]
            p, w, it, irls_it, scale, _irls_converged = _solve(sys_, p0, u1, u2, prior, robust, opts)
            if label == "universal":
                it += universal_iterations
            frac = _cheirality(sys_, p, u1, u2, w > 0)
            if frac < 0.5:
                raise EstimationError(
                    f"solution from the {label} start puts {100 * (1 - frac):.0f}% of the points behind a camera")
            return Solution(_wrap(p), w, it, irls_it, scale, label, extra)
        except EstimationError as err:
            logger.info("start %r failed: %s", label, err)
            last_err = err
    raise last_err if last_err is not None else EstimationError("relative orientation failed")


@dataclass(frozen=True, eq=False)
class Precision:
    """Stage 3: residuals and precision at the solution.

    Attributes
    ----------
    parallax_mm, residual_mm : (N,) float64
        Residual vertical parallax and normalised coplanarity residual, mm.
    covariance : (5, 5) float64 or None
        sigma0^2 (J^T W J)^-1, rad^2 (``None`` without redundancy).
    sigma0_mm : float or None
    condition_number, condition_number_raw : float
    outlier : (N,) bool
    """

    parallax_mm: NDArray[np.float64]
    residual_mm: NDArray[np.float64]
    covariance: NDArray[np.float64] | None
    sigma0_mm: float | None
    condition_number: float
    condition_number_raw: float
    outlier: NDArray[np.bool_]


def precision(prob: Problem, sol: Solution, opts: RelativeOptions) -> Precision:
    """Stage 3: normal equations at the solution, sigma0 with the redundancy n - 5, covariance, outliers.

    Warns
    -----
    WeakGeometryWarning
        When the condition number exceeds ``opts.weak_condition``.
    """
    u1, u2 = prob.rays
    p, w = sol.elements, sol.weights
    e = _evaluate(prob.system, p, u1, u2)
    W = w / e.gn2
    A = e.J * np.sqrt(W)[:, None]
    N, _ = lsq.normal_equations(A)
    cond, cond_raw = lsq.condition_numbers(N)
    if cond > opts.weak_condition:
        warnings.warn(f"weak geometry: condition number {cond:.3g} of the normal matrix "
                      f"(> {opts.weak_condition:.0e}); the elements are poorly determined",
                      WeakGeometryWarning, stacklevel=3)
    res = e.normalised
    used = w > 0
    dof = int(used.sum()) - 5
    sigma0 = lsq.sigma0(np.sum(w[used] * res[used] ** 2), dof)
    cov = None
    if sigma0 is not None:
        Qinv = lsq.cofactor(N)
        cov = sigma0 ** 2 * Qinv
    scale = sol.scale
    if prob.robust != "none":
        outl = (w <= 0) | (np.abs(res) > opts.outlier_threshold * (scale or 0.0)) if scale else (w <= 0)
    else:
        outl = np.zeros(prob.n, dtype=bool)
    return Precision(e.parallax, res, cov, sigma0, cond, cond_raw, outl)
