"""Space resection: exterior orientation of one photo from ground control.

Collinearity (seed 002, sections 1.3-1.4), with R taking a photo vector into
the ground frame and C the projection centre::

    p = R.T @ (P - C);   x = x0 - f p0 / p2;   y = y0 - f p1 / p2

``R = Rx(omega) @ Ry(phi) @ Rz(kappa)`` (= Wolf & Dewitt's ``M.T``). The six
exterior elements (omega, phi, kappa, XL, YL, ZL) -- and optionally the
interior elements f, x0, y0 ("interior orientation free", at least 5 points,
badly conditioned over flat ground) -- are estimated by Gauss-Newton least
squares on the photo coordinates (mm) from initial values of a direct
solution: OpenCV's ``solvePnP`` (SQPnP, at least 3 points) or a DLT (at
least 6 points not on one plane; also gives initial interior elements).
Ground coordinates are centred internally, so map coordinates of any size
keep full precision.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError, ShapeError
from rectify.geometry import lsq
from rectify.geometry.points import as_ids, as_mask, as_pair
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.rotation import angles_from_matrix, check_rotation, matrix_from_angles, rot_x, rot_y, rot_z

logger = logging.getLogger(__name__)

__all__ = ["ExteriorOrientation", "resect", "INITIAL_METHODS"]

INITIAL_METHODS = ("pnp", "dlt")
_K = [np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
      np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]]),
      np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])]
_D = np.diag([1.0, -1.0, -1.0])  # our camera axes (x right, y up, z back) <-> OpenCV's
_D2 = np.diag([1.0, 1.0, -1.0])


@dataclass(frozen=True, eq=False)
class ExteriorOrientation:
    """Exterior (and the used interior) orientation of one photo.

    Attributes
    ----------
    position : (3,) float64
        Projection centre (XL, YL, ZL), ground frame and units.
    rotation : (3, 3) float64
        Photo vector (x, y, -f) -> ground frame; Rx(omega) Ry(phi) Rz(kappa).
    focal_length_mm : float
    principal_point_mm : (2,) float64
        (x0, y0) in the photo frame used by the observations, mm.
    covariance : (k, k) float64 or None
        Of ``param_names`` (angles rad, positions ground units, IO mm).
    param_names : tuple of str
    sigma0 : float
        A-posteriori standard deviation of unit weight, mm.
    residuals : ResidualTable or None
        Photo residuals (mm) of the control points.
    """

    position: NDArray[np.float64]
    rotation: NDArray[np.float64]
    focal_length_mm: float
    principal_point_mm: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))
    covariance: NDArray[np.float64] | None = None
    param_names: tuple[str, ...] = ("omega", "phi", "kappa", "x", "y", "z")
    sigma0: float = float("nan")
    residuals: ResidualTable | None = None
    iterations: int = 0
    converged: bool = True
    crs: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        pos = np.array(self.position, dtype=np.float64, copy=True).reshape(-1)
        if pos.shape != (3,) or not np.isfinite(pos).all():
            raise ShapeError(f"`position` must be 3 finite numbers; got {pos.tolist()}")
        R = check_rotation(self.rotation, "rotation")
        pp = np.array(self.principal_point_mm, dtype=np.float64, copy=True).reshape(-1)
        for a in (pos, R, pp):
            a.flags.writeable = False
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "principal_point_mm", pp)
        object.__setattr__(self, "focal_length_mm", float(self.focal_length_mm))
        if self.covariance is not None:
            c = np.array(self.covariance, dtype=np.float64, copy=True)
            c.flags.writeable = False
            object.__setattr__(self, "covariance", c)

    @property
    def angles(self) -> NDArray[np.float64]:
        """(omega, phi, kappa), rad."""
        return angles_from_matrix(self.rotation, "omega-phi-kappa")

    @property
    def std_errors(self) -> dict[str, float]:
        if self.covariance is None:
            return {}
        return dict(zip(self.param_names, map(float, np.sqrt(np.diag(self.covariance))), strict=True))

    def project(self, ground: ArrayLike) -> NDArray[np.float64]:
        """Ground points (N, 3) -> photo coordinates (N, 2), mm."""
        P = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        p = (P - self.position) @ self.rotation
        f = self.focal_length_mm
        return np.column_stack([self.principal_point_mm[0] - f * p[:, 0] / p[:, 2],
                                self.principal_point_mm[1] - f * p[:, 1] / p[:, 2]])

    @classmethod
    def from_points(
        cls,
        photo_mm: ArrayLike,
        ground: ArrayLike,
        *,
        focal_length_mm: float,
        principal_point_mm: ArrayLike = (0.0, 0.0),
        ids: Sequence[str] | None = None,
        check: ArrayLike | None = None,
        free_interior: bool = False,
        initial: str = "pnp",
        max_iterations: int = 50,
        tol: float = 1e-10,
        crs: str | None = None,
    ) -> ExteriorOrientation:
        """Space resection by collinearity least squares (validate, start values, Gauss-Newton, precision).

        Parameters
        ----------
        photo_mm : (N, 2) array_like
            Photo coordinates (mm, x right, y up, from the nominal principal point).
        ground : (N, 3) array_like
            Ground coordinates of the same points.
        focal_length_mm : float
            Principal distance (the initial value when ``free_interior``).
        principal_point_mm : (2,) array_like
            (x0, y0), mm (initial value when ``free_interior``).
        ids : sequence of str, optional
        check : (N,) bool, optional
            Check points: not used in the fit, residuals reported.
        free_interior : bool
            Also estimate f, x0, y0 (at least 5 control points).
        initial : {"pnp", "dlt"}
            Direct solution for the initial values.
        max_iterations, tol : int, float
            Gauss-Newton limits (tol on the largest correction: rad, ground units, mm).
        crs : str, optional
            Recorded in the result.

        Returns
        -------
        ExteriorOrientation

        Raises
        ------
        EstimationError
            Too few points (3 for the exterior elements, 5 with the interior
            elements free), collinear control, failed initial solution, singular
            normal equations or no convergence.
        """
        prob = _validate(photo_mm, ground, focal_length_mm=focal_length_mm, ids=ids, check=check,
                         free_interior=free_interior, initial=initial)
        params0 = _initial_values(prob, focal_length_mm=focal_length_mm, principal_point_mm=principal_point_mm,
                                  initial=initial)
        params, N, it = _solve(prob, params0, max_iterations=max_iterations, tol=tol)
        pred_all, sigma0, cov, cond = _precision(prob, params, N)
        names = ("omega", "phi", "kappa", "x", "y", "z") + (("f", "x0", "y0") if free_interior else ())
        table = ResidualTable(step="space resection", ids=prob.ids, observed=prob.x, adjusted=pred_all, units="mm",
                              components=("dx", "dy"), check=prob.chk, sigma0=sigma0, n_params=prob.nfree,
                              extra={"condition_number": cond, "free_interior": free_interior})
        R = matrix_from_angles(params[0], params[1], params[2], order="omega-phi-kappa")
        logger.info("space resection: %d points, sigma0 %.4g mm, %d iterations", prob.nf, sigma0, it)
        return cls(position=params[3:6] + prob.gm, rotation=R, focal_length_mm=float(params[6]),
                   principal_point_mm=params[7:9], covariance=cov, param_names=names, sigma0=sigma0,
                   residuals=table, iterations=it, converged=True, crs=crs,
                   extra={"initial": initial, "free_interior": free_interior})

    def to_dict(self) -> dict[str, Any]:
        """The dict form of the exterior orientation JSON (``stereo resect``; see :mod:`stereo.formats.orientation`)."""
        om, ph, ka = map(float, self.angles)
        d: dict[str, Any] = {
            "position": self.position.tolist(),
            "rotation": self.rotation.tolist(),
            "rotation_convention": "photo vector (x, y, -f) -> ground; R = Rx(omega) @ Ry(phi) @ Rz(kappa)",
            "angles": {"system": "omega-phi-kappa", "omega": om, "phi": ph, "kappa": ka},
            "focal_length_mm": self.focal_length_mm,
            "principal_point_mm": self.principal_point_mm.tolist(),
            "std_errors": self.std_errors,
            "sigma0_mm": self.sigma0,
            "iterations": self.iterations,
            "converged": self.converged,
            "crs": self.crs,
        }
        if self.covariance is not None:
            d["correlation"] = {"names": list(self.param_names), "matrix": _corr(self.covariance).tolist()}
        if self.residuals is not None:
            d["residuals"] = self.residuals.summary()
            d["points"] = [{"id": r["id"], "residual_mm": [r["dx"], r["dy"]], "check": bool(r["check"])}
                           for r in self.residuals.rows()]
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ExteriorOrientation:
        """Rebuild from :meth:`to_dict` output (position + rotation or angles)."""
        try:
            pos = d["position"]
            if "rotation" in d:
                R = d["rotation"]
            else:
                a = d["angles"]
                R = matrix_from_angles(a["omega"], a["phi"], a["kappa"], a.get("system", "omega-phi-kappa"))
            return cls(position=pos, rotation=R, focal_length_mm=d["focal_length_mm"],
                       principal_point_mm=d.get("principal_point_mm", (0.0, 0.0)), crs=d.get("crs"))
        except (KeyError, TypeError) as err:
            raise InvalidInputError(f"exterior orientation JSON lacks or has a bad key: {err}") from err


def _corr(c: NDArray) -> NDArray:
    s = np.sqrt(np.diag(c))
    with np.errstate(divide="ignore", invalid="ignore"):
        return c / np.outer(s, s)


def _initial_pnp(photo: NDArray, ground_c: NDArray, f: float) -> tuple[NDArray, NDArray]:
    K = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]])
    img = np.column_stack([photo[:, 0], -photo[:, 1]]).reshape(-1, 1, 2)
    obj = ground_c.reshape(-1, 1, 3)
    last: Exception | None = None
    for flag in (cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE):
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=flag)
        except cv2.error as err:
            last = err
            continue
        if ok and np.isfinite(rvec).all() and np.isfinite(tvec).all():
            Rcv, _ = cv2.Rodrigues(rvec)
            R = Rcv.T @ _D
            C = -Rcv.T @ tvec.reshape(3)
            return R, C
    raise EstimationError(f"cv2.solvePnP found no initial exterior orientation ({last})")


def _initial_dlt(photo: NDArray, ground_c: NDArray) -> tuple[NDArray, NDArray, float, NDArray]:
    """DLT: 11 parameters, >= 6 points off a plane; returns R, C, f, (x0, y0)."""
    n = len(photo)
    if n < 6:
        raise EstimationError(f"too few points for the DLT: {n} given, 6 needed (use initial='pnp')")
    s = np.linalg.svd(ground_c - ground_c.mean(0), compute_uv=False)
    if s[2] <= 1e-6 * s[0]:
        raise EstimationError("the DLT needs control points off a plane; these are coplanar "
                              f"(singular values {np.round(s, 6).tolist()}); use initial='pnp'")
    # normalise
    gs = np.sqrt(3) / np.sqrt(((ground_c - ground_c.mean(0)) ** 2).sum(1).mean())
    gm = ground_c.mean(0)
    ps = np.sqrt(2) / np.sqrt(((photo - photo.mean(0)) ** 2).sum(1).mean())
    pm = photo.mean(0)
    X = (ground_c - gm) * gs
    u = (photo - pm) * ps
    A = np.zeros((2 * n, 12))
    Xh = np.column_stack([X, np.ones(n)])
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -u[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -u[:, 1:2] * Xh
    _, _, Vt = np.linalg.svd(A)
    Pn = Vt[-1].reshape(3, 4)
    Tp = np.array([[ps, 0, -ps * pm[0]], [0, ps, -ps * pm[1]], [0, 0, 1]])
    Tg = np.eye(4)
    Tg[:3, :3] *= gs
    Tg[:3, 3] = -gs * gm
    P = np.linalg.inv(Tp) @ Pn @ Tg
    # P ~ K [M | -M C] with photo frame: (x, y) = K-projection of q = M (X - C), our z axis backwards
    C = -np.linalg.solve(P[:, :3], P[:, 3])
    H = P[:, :3]
    # RQ decomposition of H = Kq Q
    Kq, Q = scipy.linalg.rq(H)
    S = np.diag(np.sign(np.diag(Kq)))
    Kq, Q = Kq @ S, S @ Q
    Kq = Kq / Kq[2, 2]
    # P ~ K D R.T [I | -C] with K = [[f, 0, x0], [0, f, y0], [0, 0, 1]] and D = diag(1, 1, -1)
    # (x = x0 - f p0/p2). With K's diagonal made positive, Q = +-D R.T and det(D R.T) = -1:
    Rt = -np.linalg.det(Q) * (_D2 @ Q)
    f = float((Kq[0, 0] + Kq[1, 1]) / 2)
    x0, y0 = float(Kq[0, 2]), float(Kq[1, 2])
    R = Rt.T
    return R, C, f, np.array([x0, y0])


def resect(
    photo_mm: ArrayLike,
    ground: ArrayLike,
    *,
    focal_length_mm: float,
    principal_point_mm: ArrayLike = (0.0, 0.0),
    ids: Sequence[str] | None = None,
    check: ArrayLike | None = None,
    free_interior: bool = False,
    initial: str = "pnp",
    max_iterations: int = 50,
    tol: float = 1e-10,
    crs: str | None = None,
) -> ExteriorOrientation:
    """Space resection by collinearity least squares: the function form of
    :meth:`ExteriorOrientation.from_points`, with the same parameters, result and errors."""
    return ExteriorOrientation.from_points(
        photo_mm, ground, focal_length_mm=focal_length_mm, principal_point_mm=principal_point_mm, ids=ids,
        check=check, free_interior=free_interior, initial=initial, max_iterations=max_iterations, tol=tol, crs=crs)


# ------------------------------------------------------------------ stages of ExteriorOrientation.from_points
@dataclass(frozen=True, eq=False)
class _Problem:
    """Stage 1: validated observations of a resection (ground coordinates centred on the control)."""

    x: NDArray[np.float64]         # (N, 2) photo coordinates, mm
    Gc: NDArray[np.float64]        # (N, 3) ground coordinates minus gm
    gm: NDArray[np.float64]        # (3,) centroid of the control
    ids: tuple[str, ...]
    chk: NDArray[np.bool_]
    fit: NDArray[np.bool_]
    nfree: int                     # 6, or 9 with the interior elements free
    free_interior: bool

    @property
    def nf(self) -> int:
        return int(self.fit.sum())


def _validate(photo_mm: ArrayLike, ground: ArrayLike, *, focal_length_mm: float, ids: Sequence[str] | None,
              check: ArrayLike | None, free_interior: bool, initial: str) -> _Problem:
    """Stage 1: shapes, options, enough and non-collinear control."""
    x, G = as_pair(photo_mm, ground, dim_src=2, dim_dst=3, names=("photo_mm", "ground"))
    if initial not in INITIAL_METHODS:
        raise InvalidInputError(f"unknown initial method {initial!r}; expected one of {list(INITIAL_METHODS)}")
    if not (math.isfinite(focal_length_mm) and focal_length_mm > 0):
        raise InvalidInputError(f"`focal_length_mm` must be > 0; got {focal_length_mm!r}")
    n = len(x)
    ids_t = as_ids(ids, n)
    chk = as_mask(check, n, "check")
    fit = ~chk
    nf = int(fit.sum())
    k = 9 if free_interior else 6
    n_min = 5 if free_interior else 3
    if nf < n_min:
        raise EstimationError(f"too few control points for space resection: {nf} given, at least {n_min} "
                              f"needed ({k} unknowns, 2 equations per point)")
    c = G[fit] - G[fit].mean(0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[1] <= 1e-9 * sv[0]:
        raise EstimationError(f"control points are collinear (singular values {np.round(sv, 6).tolist()}); "
                              "the photo cannot be oriented")
    gm = G[fit].mean(0)
    return _Problem(x, G - gm, gm, ids_t, chk, fit, k, free_interior)


def _initial_values(prob: _Problem, *, focal_length_mm: float, principal_point_mm: ArrayLike,
                    initial: str) -> NDArray[np.float64]:
    """Stage 2a: (omega, phi, kappa, XL, YL, ZL (centred), f, x0, y0) from a direct solution."""
    x, Gc, fit = prob.x, prob.Gc, prob.fit
    pp = np.array(principal_point_mm, dtype=np.float64).reshape(-1)
    f = float(focal_length_mm)
    if initial == "dlt":
        R, C, f_dlt, pp_dlt = _initial_dlt(x[fit], Gc[fit])
        if prob.free_interior:
            f, pp = f_dlt, pp_dlt
    else:
        R, C = _initial_pnp(x[fit] - pp, Gc[fit], f)
    ang = angles_from_matrix(R, "omega-phi-kappa")
    return np.concatenate([ang, C, [f, pp[0], pp[1]]])


def _collinearity(pv: NDArray, Gp: NDArray) -> tuple[NDArray, NDArray]:
    """Predicted photo coordinates (N, 2) and their derivatives (N, 2, 9) by the 9 elements ``pv``."""
    om, ph, ka = pv[0:3]
    Rx, Ry, Rz = rot_x(om), rot_y(ph), rot_z(ka)
    Rm = Rx @ Ry @ Rz
    dR = [Rx @ _K[0] @ Ry @ Rz, Rx @ Ry @ _K[1] @ Rz, Rm @ _K[2]]
    d = Gp - pv[3:6]
    p = d @ Rm
    fv, x0, y0 = pv[6], pv[7], pv[8]
    w = 1.0 / p[:, 2]
    pred = np.column_stack([x0 - fv * p[:, 0] * w, y0 - fv * p[:, 1] * w])
    # d pred / d p
    J = np.zeros((len(Gp), 2, 9))
    dxdp = np.stack([-fv * w, np.zeros_like(w), fv * p[:, 0] * w * w], axis=1)
    dydp = np.stack([np.zeros_like(w), -fv * w, fv * p[:, 1] * w * w], axis=1)
    for a in range(3):
        dp = d @ dR[a]
        J[:, 0, a] = (dxdp * dp).sum(1)
        J[:, 1, a] = (dydp * dp).sum(1)
    # d p / d C = -R.T
    J[:, 0, 3:6] = -dxdp @ Rm.T
    J[:, 1, 3:6] = -dydp @ Rm.T
    J[:, 0, 6] = -p[:, 0] * w
    J[:, 1, 6] = -p[:, 1] * w
    J[:, 0, 7] = 1.0
    J[:, 1, 8] = 1.0
    return pred, J


def _solve(prob: _Problem, params: NDArray, *, max_iterations: int, tol: float
           ) -> tuple[NDArray, NDArray, int]:
    """Stage 2b: Gauss-Newton on the photo coordinates; returns (parameters, normal matrix, iterations)."""
    params = params.copy()
    nfree, x, fit = prob.nfree, prob.x, prob.fit
    conv = False
    it = 0
    N = np.eye(nfree)
    dp: NDArray = np.zeros(nfree)
    while it < max_iterations:
        it += 1
        pred, J = _collinearity(params, prob.Gc[fit])
        A = J[:, :, :nfree].reshape(-1, nfree)
        lvec = (x[fit] - pred).reshape(-1)
        N, rhs = lsq.normal_equations(A, lvec)
        assert rhs is not None
        try:
            dp = np.linalg.solve(N, rhs)
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"singular normal equations in space resection: {err}") from err
        if not np.isfinite(dp).all():
            raise EstimationError("space resection diverged (non-finite correction)")
        params[:nfree] += dp
        scale = np.concatenate([np.ones(3), np.full(3, max(1.0, float(np.linalg.norm(params[3:6])))),
                                np.full(3, params[6])])[:nfree]
        if np.all(np.abs(dp) <= tol * scale):
            conv = True
            break
    if not conv:
        pred, _ = _collinearity(params, prob.Gc[fit])
        v = np.linalg.norm(x[fit] - pred, axis=1)
        ids = np.asarray(prob.ids)[fit]
        worst = ", ".join(f"{ids[i]} {v[i]:.4g}" for i in np.argsort(-v)[:3])
        raise ConvergenceError(f"space resection did not converge in {max_iterations} iterations "
                               f"(last correction {np.abs(dp).max():.3g}); largest residuals: {worst} mm "
                               "(check these control points)", iterations=it)
    return params, N, it


def _precision(prob: _Problem, params: NDArray, N: NDArray) -> tuple[NDArray, float, NDArray, float]:
    """Stage 3: residuals, sigma0 with the redundancy 2 n - u, covariance; returns (pred, sigma0, cov, cond)."""
    nf, nfree, x, fit = prob.nf, prob.nfree, prob.x, prob.fit
    pred_all, _ = _collinearity(params, prob.Gc)
    v = (pred_all - x)[fit].reshape(-1)
    dof = 2 * nf - nfree
    sigma0 = math.sqrt(float(v @ v) / dof) if dof > 0 else float("nan")
    cond = float(np.linalg.cond(N))
    if cond > 1e12:
        logger.warning("space resection: normal equations badly conditioned (cond %.3g)", cond)
    Q = lsq.cofactor(N)
    cov = (sigma0 ** 2 if math.isfinite(sigma0) else 1.0) * Q
    return pred_all, sigma0, cov, cond
