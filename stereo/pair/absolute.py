"""Absolute orientation: the 7-parameter spatial similarity from model to ground.

    G = s R m + T

with ``m`` a model point, ``G`` its ground point (both (3,), right-handed
frames), ``s`` the scale, ``R = Rx(omega) @ Ry(phi) @ Rz(kappa)`` (the
omega-phi-kappa order of :mod:`rectify.geometry.rotation`, identical to Wolf & Dewitt's
``M.T`` with ``M = R3(kappa) R2(phi) R1(omega)``) and ``T`` the translation.

Control comes as full points (X, Y, Z known: three observation equations
each) and height points (only Z known, X and Y NaN: one equation each). As in
seed 002 (section 3.1.1) at least two full points and one height point are
needed (7 equations for 7 unknowns), not all on one line. The parameters are
estimated by Gauss-Newton least squares on centred coordinates, optionally
robust (IRLS with the psi functions of :mod:`rectify.geometry.robust`), with their
covariance ``sigma0^2 (A^T P A)^-1`` and a residual table (v = adjusted -
observed, ground units).

An optional polynomial correction of model deformation (seed 002, eqs.
3.8-3.15) follows the similarity: each ground coordinate j gets
``dG_j = D(X, Y) b_j`` with ``D = (1, X, Y, XY, X^2, Y^2)`` (order 2, 6
coefficients per coordinate, at least 6 full control points) or the 10 terms
of order 3, X and Y being the planimetric coordinates of the transformed
(deformed) model, centred and scaled for conditioning.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError, ShapeError
from rectify.geometry import lsq
from rectify.geometry.points import as_ids, as_mask, as_points
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.robust import ROBUST_METHODS, irls
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles, rot_x, rot_y, rot_z

logger = logging.getLogger(__name__)

__all__ = ["AbsoluteOrientation", "PolynomialCorrection", "DEFORMATION_ORDERS", "PARAM_NAMES",
           "similarity_from_points"]

PARAM_NAMES = ("scale", "omega", "phi", "kappa", "tx", "ty", "tz")
#: orders of seed 002's polynomial deformation correction
DEFORMATION_ORDERS = (2, 3)
_K = [np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
      np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]]),
      np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])]


def _poly_terms(xy: NDArray, order: int) -> NDArray:
    x, y = xy[:, 0], xy[:, 1]
    cols = [np.ones_like(x), x, y]
    if order >= 2:
        cols += [x * y, x * x, y * y]
    if order >= 3:
        cols += [x * x * y, x * y * y, x ** 3, y ** 3]
    return np.column_stack(cols)


@dataclass(frozen=True, eq=False)
class PolynomialCorrection:
    """Seed 002's polynomial correction of model deformation (applied after the similarity).

    Attributes
    ----------
    order : int
        2 (6 terms per coordinate) or 3 (10 terms).
    centre, scale_xy : (2,) float64, float
        Normalisation of the planimetric coordinates: (XY - centre) / scale_xy.
    coefficients : (3, n_terms) float64
        Coefficients b_j of dX, dY, dZ, ground units.
    covariance : (3, n_terms, n_terms) float64
        Their covariance.
    """

    order: int
    centre: NDArray[np.float64]
    scale_xy: float
    coefficients: NDArray[np.float64]
    covariance: NDArray[np.float64]

    def terms(self, ground_xy: NDArray) -> NDArray:
        return _poly_terms((np.asarray(ground_xy)[:, :2] - self.centre) / self.scale_xy, self.order)

    def __call__(self, ground: NDArray) -> NDArray:
        """Correction dG (N, 3) at points ``ground`` (N, 3) of the deformed model."""
        D = self.terms(ground)
        return D @ self.coefficients.T

    def variance(self, ground: NDArray) -> NDArray:
        """(N, 3) variance of the correction of each coordinate."""
        D = self.terms(ground)
        return np.stack([np.einsum("ni,ij,nj->n", D, self.covariance[j], D) for j in range(3)], axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {"order": self.order, "centre": self.centre.tolist(), "scale_xy": self.scale_xy,
                "coefficients": {"dx": self.coefficients[0].tolist(), "dy": self.coefficients[1].tolist(),
                                 "dz": self.coefficients[2].tolist()}}


def _umeyama(m: NDArray, g: NDArray, w: NDArray | None = None) -> tuple[float, NDArray, NDArray]:
    """Closed-form similarity g ~ s R m + t (Umeyama 1991) on >= 3 non-collinear points."""
    w = np.ones(len(m)) if w is None else w
    W = w / w.sum()
    mc = W @ m
    gc = W @ g
    A = (g - gc).T @ ((m - mc) * W[:, None])
    U, S, Vt = np.linalg.svd(A)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_m = float(W @ ((m - mc) ** 2).sum(1))
    s = float(np.trace(np.diag(S) @ D) / var_m)
    return s, R, gc - s * R @ mc


def similarity_from_points(model: ArrayLike, ground: ArrayLike) -> tuple[float, NDArray, NDArray]:
    """Closed-form 7-parameter similarity from >= 3 full, non-collinear points.

    Returns ``(scale, R (3, 3), T (3,))`` with ``ground ~ scale R model + T``.
    """
    m = as_points(model, "model", 3)
    g = as_points(ground, "ground", 3)
    if len(m) != len(g):
        raise ShapeError(f"`model` and `ground` must have the same length; got {len(m)} and {len(g)}")
    if len(m) < 3:
        raise EstimationError(f"too few points for a closed-form similarity: {len(m)} given, 3 needed")
    _check_not_collinear(m, "model points")
    return _umeyama(m, g)


def _check_not_collinear(pts: NDArray, what: str, rtol: float = 1e-6) -> None:
    c = pts - pts.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] == 0 or s[1] <= rtol * s[0]:
        raise EstimationError(
            f"{what} are collinear (singular values {np.round(s, 6).tolist()}): the rotation about "
            f"their line is undetermined; add control off that line")


def _initial(m: NDArray, g: NDArray, full: NDArray, zonly: NDArray) -> tuple[float, NDArray, NDArray]:
    mf, gf = m[full], g[full]
    if full.sum() >= 3:
        c = mf - mf.mean(0)
        sv = np.linalg.svd(c, compute_uv=False)
        if sv[1] > 1e-6 * sv[0]:
            return _umeyama(mf, gf)
    # two full points (or collinear full points) + a height point: place the height point in
    # plan from its model distances to two full points and its Z, then solve in closed form
    i, j = 0, int(np.argmax(np.linalg.norm(mf - mf[0], axis=1)))
    s = np.linalg.norm(gf[j] - gf[i]) / np.linalg.norm(mf[j] - mf[i])
    best = None
    for k in np.flatnonzero(zonly):
        hm, hz = m[k], g[k, 2]
        r1 = s * np.linalg.norm(hm - mf[i])
        r2 = s * np.linalg.norm(hm - mf[j])
        # horizontal radii
        h1 = r1 * r1 - (hz - gf[i, 2]) ** 2
        h2 = r2 * r2 - (hz - gf[j, 2]) ** 2
        if h1 < 0 or h2 < 0:
            continue
        p1, p2 = gf[i, :2], gf[j, :2]
        d = np.linalg.norm(p2 - p1)
        a = (h1 - h2 + d * d) / (2 * d)
        hh = h1 - a * a
        if hh < 0:
            continue
        base = p1 + a * (p2 - p1) / d
        perp = np.array([-(p2 - p1)[1], (p2 - p1)[0]]) / d
        for sign in (1.0, -1.0):
            xy = base + sign * math.sqrt(hh) * perp
            mm = np.vstack([mf[i], mf[j], hm])
            gg = np.vstack([gf[i], gf[j], [xy[0], xy[1], hz]])
            sc, R, t = _umeyama(mm, gg)
            pred = sc * m[full | zonly] @ R.T + t
            obs = g[full | zonly]
            r = np.concatenate([(pred - obs)[full[full | zonly]].ravel(),
                                (pred - obs)[zonly[full | zonly], 2]])
            cost = float(r @ r)
            if best is None or cost < best[0]:
                best = (cost, sc, R, t)
        if best is not None:
            break
    if best is None:
        raise EstimationError("cannot find initial values for the absolute orientation from two full "
                              "control points and the height points (inconsistent distances)")
    return best[1], best[2], best[3]


def _design(m_c: NDArray, s: float, ang: NDArray) -> tuple[NDArray, NDArray]:
    """Predicted (N, 3) and Jacobian (N, 3, 7) of G' = s R m_c + T' at (s, angles, T')."""
    Rx, Ry, Rz = rot_x(ang[0]), rot_y(ang[1]), rot_z(ang[2])
    R = Rx @ Ry @ Rz
    dR = [Rx @ _K[0] @ Ry @ Rz, Rx @ Ry @ _K[1] @ Rz, R @ _K[2]]
    Rm = m_c @ R.T
    J = np.zeros((len(m_c), 3, 7))
    J[:, :, 0] = Rm
    for k in range(3):
        J[:, :, 1 + k] = s * m_c @ dR[k].T
    J[:, :, 4:7] = np.eye(3)
    return s * Rm, J


@dataclass(frozen=True, eq=False)
class AbsoluteOrientation:
    """Model -> ground similarity ``G = s R m + T`` (plus optional deformation correction).

    Attributes
    ----------
    scale : float
    rotation : (3, 3) float64
        R = Rx(omega) Ry(phi) Rz(kappa), model axes -> ground axes.
    translation : (3,) float64
        T, ground units.
    covariance : (7, 7) float64
        Of (scale, omega, phi, kappa, tx, ty, tz); angles in rad.
    sigma0 : float
        A-posteriori standard deviation of unit weight: ground units without
        weights, unitless when the weights are inverse variances.
    residuals : ResidualTable
        Per control point (v = adjusted - observed, ground units); check points
        included with ``check`` set. For height points the X, Y rows are not
        observed and show a zero residual.
    deformation : PolynomialCorrection or None
    iterations : int
    converged : bool
    robust : str
    """

    scale: float
    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    covariance: NDArray[np.float64]
    sigma0: float
    residuals: ResidualTable
    deformation: PolynomialCorrection | None = None
    iterations: int = 0
    converged: bool = True
    robust: str = "none"
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("rotation", "translation", "covariance"):
            a = np.array(getattr(self, name), dtype=np.float64, copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    # ------------------------------------------------------------------ derived
    @property
    def angles(self) -> NDArray[np.float64]:
        """(omega, phi, kappa), rad."""
        return angles_from_matrix(self.rotation, "omega-phi-kappa")

    @property
    def parameters(self) -> NDArray[np.float64]:
        """(scale, omega, phi, kappa, tx, ty, tz)."""
        return np.concatenate([[self.scale], self.angles, self.translation])

    @property
    def std_errors(self) -> NDArray[np.float64]:
        """(7,) standard errors of :attr:`parameters`."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def matrix(self) -> NDArray[np.float64]:
        """(4, 4) homogeneous similarity (without the deformation correction)."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def similarity(self, model: ArrayLike) -> NDArray[np.float64]:
        """Similarity only: model (N, 3) -> ground (N, 3)."""
        m = as_points(model, "model", 3)
        return self.scale * m @ self.rotation.T + self.translation

    def __call__(self, model: ArrayLike) -> NDArray[np.float64]:
        """Model points (N, 3) -> ground points (N, 3), deformation corrected when fitted."""
        g = self.similarity(model)
        if self.deformation is not None:
            g = g + self.deformation(g)
        return g

    def point_covariance(self, model: ArrayLike, model_covariance: ArrayLike | None = None
                         ) -> NDArray[np.float64]:
        """Covariance (N, 3, 3) of transformed points, ground units squared.

        Propagates the parameter covariance and, when given, the covariance of
        the model points themselves (N, 3, 3): ``J C J^T + s^2 R C_m R^T``.
        """
        m = as_points(model, "model", 3)
        ang = self.angles
        _, J = _design(m, self.scale, ang)
        C = np.einsum("nik,kl,njl->nij", J, self.covariance, J)
        if model_covariance is not None:
            Cm = np.asarray(model_covariance, dtype=np.float64)
            if Cm.shape != (len(m), 3, 3):
                raise ShapeError(f"`model_covariance` must have shape ({len(m)}, 3, 3); got {Cm.shape}",
                                 actual_shape=Cm.shape, expected_shape=(len(m), 3, 3))
            sR = self.scale * self.rotation
            C = C + np.einsum("ij,njk,lk->nil", sR, Cm, sR)
        if self.deformation is not None:
            var = self.deformation.variance(self.similarity(m))
            C = C + np.einsum("ni,ij->nij", var, np.eye(3))
        return C

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (angles in rad)."""
        se = self.std_errors
        d: dict[str, Any] = {
            "model": "G = scale * R @ m + T, R = Rx(omega) @ Ry(phi) @ Rz(kappa)",
            "scale": self.scale,
            "angles": {"omega": float(self.angles[0]), "phi": float(self.angles[1]),
                       "kappa": float(self.angles[2])},
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "std_errors": dict(zip(PARAM_NAMES, map(float, se), strict=True)),
            "covariance": {"names": list(PARAM_NAMES), "matrix": self.covariance.tolist()},
            "sigma0": self.sigma0,
            "iterations": self.iterations,
            "converged": self.converged,
            "robust": self.robust,
            "residuals": self.residuals.summary(),
            "points": [{"id": r["id"], "residual": [r[c] for c in self.residuals.components],
                        "weight": r["weight"], "outlier": bool(r["outlier"]), "check": bool(r["check"])}
                       for r in self.residuals.rows()],
        }
        if self.deformation is not None:
            d["deformation"] = self.deformation.to_dict()
        d.update(self.extra)
        return d

    # -------------------------------------------------------------- estimation
    @classmethod
    def from_points(
        cls,
        model: ArrayLike,
        ground: ArrayLike,
        *,
        ids: Sequence[str] | None = None,
        check: ArrayLike | None = None,
        weights: ArrayLike | None = None,
        robust: str = "none",
        deformation_order: int | None = None,
        max_iterations: int = 50,
        tol: float = 1e-10,
        units: str = "ground units",
        min_scale: float | None = None,
    ) -> AbsoluteOrientation:
        """Estimate the similarity from control points.

        Parameters
        ----------
        model : (N, 3) array_like
            Model coordinates of the control points.
        ground : (N, 3) array_like
            Ground coordinates; a row with X and Y NaN and Z finite is a height
            point; a row of three NaN is ignored (tie point).
        ids : sequence of str, optional
            Point names (default "1".."N").
        check : (N,) bool, optional
            Points withheld from the fit and only checked.
        weights : (N,) or (N, 3) or (N, 3, 3) float, optional
            A-priori weights per point, per coordinate (e.g. the inverse
            variances of the model coordinates after rotation to ground), or
            full symmetric positive definite 3x3 weight matrices per point
            (the inverse covariance of the control point's ground error:
            X, Y and Z of an intersected point are correlated); for a height
            point only the (Z, Z) element of its matrix is used.
        robust : {"none", "huber", "tukey", "hampel", "andrews"}
            IRLS M-estimation over the coordinate observations.
        deformation_order : {None, 2, 3}
            Fit seed 002's polynomial deformation correction after the
            similarity (needs 6 or 10 full control points).
        max_iterations, tol : int, float
            Gauss-Newton limits (tol on the largest parameter correction:
            relative for the scale, rad for the angles, relative to the
            ground extent of the control for T).
        units : str
            Name of the ground unit for the residual table (e.g. ``"m"`` when
            the ground frame is metric; default ``"ground units"``).
        min_scale : float, optional
            Smallest robust scale of the whitened residuals: with 3 x 3 weight
            matrices that are inverse covariances, 1, so that a control point is
            flagged only when a residual exceeds 3 predicted standard deviations
            (times the robust scale when that is larger). Without it the scale is the
            residuals' own (median absolute residual / 0.6745), which, with a
            redescending estimator and little redundancy, shrinks onto a subset
            of the control that the similarity fits nearly exactly and flags
            good points (issue 24). The test and its figures are in
            ``extra["outlier_test"]``.

        Raises
        ------
        EstimationError
            Too few control points (fewer than 2 full + 1 height point, or
            fewer equations than parameters), control on one line, or no
            convergence.
        ShapeError, InvalidInputError
            Malformed input or unknown option.
        """
        c = _validate(model, ground, ids=ids, check=check, weights=weights, robust=robust,
                      deformation_order=deformation_order)
        adj = _Adjustment(c, max_iterations=max_iterations, tol=tol)
        if min_scale is not None and not (isinstance(min_scale, (int, float)) and math.isfinite(min_scale)
                                          and min_scale > 0):
            raise InvalidInputError(f"`min_scale` must be a finite number > 0 or None; got {min_scale!r}")
        adj = _Adjustment(c, max_iterations=max_iterations, tol=tol)
        x, N, iters, conv, w_final, outl_obs, test = _solve(adj, robust, min_scale)
        if not conv:
            raise ConvergenceError(f"absolute orientation did not converge in {max_iterations} iterations; "
                                   f"largest residuals: {_largest_residuals(adj, x, c.ids)} (check these "
                                   "control points)", iterations=iters)
        s, R, T, cov, sigma0 = _precision(adj, x, N, w_final)
        return cls._result(c, adj, s, R, T, cov, sigma0, w_final, outl_obs, iters, conv, units, test)

    @classmethod
    def _result(cls, c: _Control, adj: _Adjustment, s: float, R: NDArray, T: NDArray, cov: NDArray, sigma0: float,
                w_final: NDArray, outl_obs: NDArray, iters: int, conv: bool, units: str,
                test: _OutlierTest | None = None) -> AbsoluteOrientation:
        """Stage 4: deformation correction, residual table, the result object."""
        m, g, n = c.m, c.g, len(c.m)
        sim = s * m @ R.T + T
        deformation = None
        adjusted = sim.copy()
        if c.deformation_order is not None:
            w_def = w_final if adj.U is None else w_final * adj.w_obs  # full matrices: their diagonal here
            deformation, sigma0 = _fit_deformation(sim, g, c.full, c.zonly, c.deformation_order,
                                                   w_def, adj.obs_pt, adj.obs_c, adj.n_obs)
            adjusted = sim + deformation(sim)
        # residual table: control and check points with ground coordinates
        rows = np.flatnonzero(c.full_all | c.zonly_all)
        observed = g[rows].copy()
        adj_rows = adjusted[rows]
        zo = c.zonly_all[rows]
        observed[zo, 0:2] = adj_rows[zo, 0:2]  # X, Y not observed for height points
        pw = np.ones(n)
        po = np.zeros(n, bool)
        for k in range(adj.n_obs):
            pt = adj.obs_pt[k]
            pw[pt] = min(pw[pt], w_final[k] / max(adj.w_obs_fit[k], 1e-300))
            po[pt] |= bool(outl_obs[k])
        n_params = 7 + (0 if deformation is None else 3 * deformation.coefficients.shape[1])
        table = ResidualTable(
            step="absolute orientation" + ("" if deformation is None else f" + order-{c.deformation_order} "
                                           "deformation correction"),
            ids=[c.ids[i] for i in rows], observed=observed, adjusted=adj_rows, units=units,
            components=("dX", "dY", "dZ"), weights=pw[rows], outlier=po[rows], check=c.chk[rows],
            sigma0=sigma0, n_params=n_params,
            extra={"n_full": c.nf, "n_height": c.nz, "n_equations": adj.n_obs, "robust": c.robust})
        logger.info("absolute orientation: %d full + %d height points, sigma0 %.4g, %d iterations",
                    c.nf, c.nz, sigma0, iters)
        extra: dict[str, Any] = {"height_points": [c.ids[i] for i in np.flatnonzero(c.zonly_all)]}
        if test is not None:
            z = np.zeros(n)
            np.maximum.at(z, adj.obs_pt, test.standardised)
            used = np.unique(adj.obs_pt)
            extra["outlier_test"] = {
                "rule": "a control point is an outlier when one of its standardised residuals exceeds the "
                        "threshold: its residuals (with 3 x 3 weight matrices: decorrelated and divided by their "
                        "predicted standard deviations) divided by the robust scale",
                "threshold": test.threshold, "scale": test.scale, "own_scale": test.own_scale,
                "min_scale": test.min_scale, "scale_floored": test.floored,
                "standardised": {c.ids[i]: float(z[i]) for i in used}}
        return cls(scale=float(s), rotation=R, translation=T, covariance=cov, sigma0=float(sigma0),
                   residuals=table, deformation=deformation, iterations=iters, converged=conv,
                   robust=c.robust, extra=extra)

    def outlier_text(self) -> str | None:
        """The robust fit's flag criterion with its figures, or None for a least-squares fit.

        E.g. ``"tukey: a control point is an outlier when one of its standardised residuals exceeds 3 x the
        robust scale 1 (the a-priori one; the residuals' own, 0.07, is smaller); flagged: c2 10.017 m
        (standardised 10.55); largest kept: c5 0.934 m (0.12)"``: each point with the length of its
        residual vector and its largest standardised residual (in units of the scale).
        """
        t = self.extra.get("outlier_test")
        if not t:
            return None
        rows = {r["id"]: r for r in self.residuals.rows() if not r["check"]}
        u = self.residuals.units
        z = t["standardised"]

        def item(pid: str, label: str = "") -> str:
            r = rows[pid]
            v = math.sqrt(sum(float(r[c]) ** 2 for c in self.residuals.components))
            return f"{pid} {v:.3f} {u} ({label}{z[pid]:.2f})"

        flagged = sorted((i for i in z if i in rows and rows[i]["outlier"]), key=lambda i: -z[i])
        kept = [i for i in z if i in rows and not rows[i]["outlier"]]
        own = t["own_scale"]
        if t["min_scale"] is None:
            scale = f"the robust scale {t['scale']:.3g} {u} (median absolute residual / 0.6745)"
        elif t["scale_floored"]:
            scale = (f"the robust scale {t['scale']:g} (the a-priori one: predicted standard deviations; the "
                     f"residuals' own, {own:.3g}, is smaller)")
        else:
            scale = f"the robust scale {t['scale']:.3g} (the residuals' own; at least the a-priori {t['min_scale']:g})"
        out = (f"{self.robust}: a control point is an outlier when one of its standardised residuals exceeds "
               f"{t['threshold']:g} x {scale}; flagged: ")
        out += ", ".join(item(i, "standardised " if k == 0 else "") for k, i in enumerate(flagged)) or "none"
        if kept:
            out += f"; largest kept: {item(max(kept, key=lambda i: z[i]), '' if flagged else 'standardised ')}"
        return out


# ------------------------------------------------------------------ stages of from_points
@dataclass(frozen=True, eq=False)
class _Control:
    """Stage 1: validated control (model and ground points, weights, which points are used how)."""

    m: NDArray[np.float64]
    g: NDArray[np.float64]
    ids: tuple[str, ...]
    chk: NDArray[np.bool_]
    w_in: NDArray[np.float64]            # (N, 3) weights per coordinate
    w_blk: NDArray[np.float64] | None    # (N, 3, 3) full weight matrices, symmetrised
    full_all: NDArray[np.bool_]          # X, Y, Z known
    zonly_all: NDArray[np.bool_]         # only Z known (height point)
    full: NDArray[np.bool_]              # used full points (not checks, weight > 0)
    zonly: NDArray[np.bool_]             # used height points
    robust: str
    deformation_order: int | None

    @property
    def nf(self) -> int:
        return int(self.full.sum())

    @property
    def nz(self) -> int:
        return int(self.zonly.sum())


def _validate(model: ArrayLike, ground: ArrayLike, *, ids: Sequence[str] | None, check: ArrayLike | None,
              weights: ArrayLike | None, robust: str, deformation_order: int | None) -> _Control:
    """Stage 1: shapes, options, weights, point kinds, enough and non-collinear control."""
    m = as_points(model, "model", 3)
    g = np.array(ground, dtype=np.float64, copy=True)
    if g.ndim != 2 or g.shape != (len(m), 3):
        raise ShapeError(f"`ground` must have shape ({len(m)}, 3) like `model`; got {g.shape}",
                         actual_shape=g.shape, expected_shape=(len(m), 3))
    if robust not in ROBUST_METHODS:
        raise InvalidInputError(f"unknown robust option {robust!r}; expected one of {list(ROBUST_METHODS)}")
    if deformation_order is not None and deformation_order not in DEFORMATION_ORDERS:
        raise InvalidInputError(f"`deformation_order` must be None, 2 or 3; got {deformation_order!r}")
    n = len(m)
    ids_t = as_ids(ids, n)
    chk = as_mask(check, n, "check")
    w_in = np.ones(n) if weights is None else np.array(weights, dtype=np.float64, copy=True)
    w_blk = None
    if w_in.shape == (n, 3, 3):
        if not np.isfinite(w_in).all():
            raise InvalidInputError("`weights` (N, 3, 3) must be finite")
        w_blk = 0.5 * (w_in + np.transpose(w_in, (0, 2, 1)))
        w_in = np.einsum("nii->ni", w_blk).copy()
    if w_in.shape == (n,):
        w_in = np.repeat(w_in[:, None], 3, axis=1)
    if w_in.shape != (n, 3) or not np.isfinite(w_in).all() or (w_in < 0).any():
        raise InvalidInputError(f"`weights` must be ({n},) or ({n}, 3), finite and >= 0; got shape "
                                f"{np.shape(np.asarray(weights))}")
    w_pt = w_in.max(axis=1)
    fin = np.isfinite(g)
    full_all = np.asarray(fin.all(1), dtype=bool)
    zonly_all = ~fin[:, 0] & ~fin[:, 1] & fin[:, 2]
    bad = ~(full_all | zonly_all | ~fin.any(1))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidInputError(
            f"ground point {ids_t[i]!r} has {g[i].tolist()}: give X, Y, Z (full point), only Z "
            f"(height point) or nothing (tie point)")
    used = ~chk & (w_pt > 0)
    full = full_all & used
    zonly = zonly_all & used
    nf, nz = int(full.sum()), int(zonly.sum())
    if nf < 2 or 3 * nf + nz < 7:
        raise EstimationError(
            f"too few control points: {nf} full and {nz} height point(s) give {3 * nf + nz} equations; "
            f"at least 2 full points and 1 height point (7 equations) are needed")
    _check_not_collinear(m[full | zonly], f"the {nf + nz} control points (model coordinates)")
    if nz == 0:
        _check_not_collinear(g[full], f"the {nf} control points (ground coordinates)")
    if deformation_order is not None:
        nt = 6 if deformation_order == 2 else 10
        if nf < nt:
            raise EstimationError(
                f"too few full control points for the order-{deformation_order} deformation "
                f"correction: {nf} given, {nt} needed (seed 002: 6 for order 2)")
    return _Control(m, g, ids_t, chk, w_in, w_blk, full_all, zonly_all, full, zonly, robust, deformation_order)


class _Adjustment:
    """Stage 2: the linearised similarity on centred coordinates (one row per observed coordinate)."""

    def __init__(self, c: _Control, *, max_iterations: int, tol: float) -> None:
        m, g, full, zonly = c.m, c.g, c.full, c.zonly
        nf, nz = c.nf, c.nz
        self.max_iterations, self.tol, self.nf = max_iterations, tol, nf
        # observation bookkeeping: rows (point, coordinate)
        self.obs_pt = np.concatenate([np.repeat(np.flatnonzero(full), 3), np.flatnonzero(zonly)])
        self.obs_c = np.concatenate([np.tile([0, 1, 2], nf), np.full(nz, 2)])
        self.n_obs = len(self.obs_pt)
        self.w_obs = c.w_in[self.obs_pt, self.obs_c]
        # centring for conditioning
        sel = full | zonly
        self.mc = m[sel].mean(0)
        self.gc_full = g[full].mean(0)
        self.m_c = m - self.mc
        s0, R0, t0 = _initial(m, g, full, zonly)
        ang = angles_from_matrix(R0, "omega-phi-kappa")
        # T' such that G = s R (m - mc) + T'
        self.x0 = np.concatenate([[s0], ang, t0 + s0 * R0 @ self.mc - self.gc_full])
        self.gobs = g - self.gc_full
        self.extent = float(np.abs(self.m_c[sel]).max()) or 1.0
        # full weight matrices: whiten each full point's 3 rows with U (U^T U = P), then unit weights
        self.U: NDArray | None = None
        self.w_z: NDArray | None = None
        if c.w_blk is not None:
            fidx = np.flatnonzero(full)
            try:
                self.U = np.transpose(np.linalg.cholesky(c.w_blk[fidx]), (0, 2, 1))
            except np.linalg.LinAlgError as err:
                raise InvalidInputError("`weights` (N, 3, 3) must be positive definite for every full control "
                                        f"point: {err}") from err
            self.w_z = np.sqrt(c.w_blk[np.flatnonzero(zonly), 2, 2])
        self.w_obs_fit = np.ones(self.n_obs) if self.U is not None else self.w_obs

    def whiten(self, X: NDArray) -> NDArray:
        if self.U is None:
            return X
        assert self.w_z is not None
        X = np.asarray(X, dtype=np.float64)
        k = 3 * self.nf
        head = X[:k].reshape(self.nf, 3, -1)
        out = np.empty_like(X)
        out[:k] = np.einsum("nij,njk->nik", self.U, head).reshape(X[:k].shape)
        out[k:] = X[k:] * (self.w_z if X.ndim == 1 else self.w_z[:, None])
        return out

    def conv_scale(self, xk: NDArray) -> NDArray:
        # relative for the scale, rad for the angles, ground extent for the translation
        ge = abs(xk[0]) * self.extent
        return np.array([abs(xk[0]), 1.0, 1.0, 1.0, ge, ge, ge])

    def gauss_newton(self, w: NDArray, x0: NDArray) -> tuple[NDArray, NDArray, int, bool]:
        """Gauss-Newton with observation weights ``w``; returns (x, N, iterations, converged)."""
        xk = x0.copy()
        conv = False
        it = 0
        rows = np.arange(self.n_obs)
        N = np.eye(7)
        while it < self.max_iterations:
            it += 1
            pred, J = _design(self.m_c[self.obs_pt], xk[0], xk[1:4])
            pred = pred + xk[4:7]
            A = self.whiten(J[rows, self.obs_c])
            misclosure = self.whiten(self.gobs[self.obs_pt, self.obs_c] - pred[rows, self.obs_c])
            N, rhs = lsq.normal_equations(A, misclosure, w)
            assert rhs is not None
            try:
                dx = np.linalg.solve(N, rhs)
            except np.linalg.LinAlgError as err:
                raise EstimationError(f"singular normal equations in the absolute orientation: {err}") from err
            xk = xk + dx
            if np.all(np.abs(dx) <= self.tol * self.conv_scale(xk)):
                conv = True
                break
        return xk, N, it, conv

    def residuals(self, xk: NDArray) -> NDArray:
        """Whitened residuals v = computed - observed (n_obs,)."""
        rows = np.arange(self.n_obs)
        pred, _ = _design(self.m_c[self.obs_pt], xk[0], xk[1:4])
        pred = pred + xk[4:7]
        return self.whiten(pred[rows, self.obs_c] - self.gobs[self.obs_pt, self.obs_c])


def _largest_residuals(adj: _Adjustment, x: NDArray, ids: tuple[str, ...], k: int = 3) -> str:
    """``"G4 12.3, G7 8.1, G1 2.2 (ground units)"``: the points with the largest residual vectors at ``x``."""
    rows = np.arange(adj.n_obs)
    pred, _ = _design(adj.m_c[adj.obs_pt], x[0], x[1:4])
    v = pred[rows, adj.obs_c] + x[4:7][adj.obs_c] - adj.gobs[adj.obs_pt, adj.obs_c]
    sq = np.zeros(len(adj.m_c))
    np.add.at(sq, adj.obs_pt, v * v)
    used = np.unique(adj.obs_pt)
    order = used[np.argsort(-sq[used])][:k]
    return ", ".join(f"{ids[i]} {math.sqrt(sq[i]):.4g}" for i in order) + " (ground units)"


@dataclass(frozen=True, eq=False)
class _OutlierTest:
    """The robust fit's outlier test: |residual| / scale > threshold per (whitened) observation."""

    standardised: NDArray[np.float64]   # (n_obs,) |whitened residual| / scale
    scale: float
    own_scale: float                    # the residuals' own robust scale
    threshold: float
    min_scale: float | None
    floored: bool


#: a robust fit flags an observation whose standardised residual exceeds this many scales
OUTLIER_THRESHOLD = 3.0


def _solve(adj: _Adjustment, robust: str, min_scale: float | None = None
           ) -> tuple[NDArray, NDArray, int, bool, NDArray, NDArray, _OutlierTest | None]:
    """Stage 2: plain or robust (IRLS) adjustment; returns (x, N, iterations, converged, weights, outliers,
    the outlier test of a robust fit)."""
    w_final = adj.w_obs_fit.copy()
    outl_obs = np.zeros(adj.n_obs, bool)
    if robust == "none":
        x, N, iters, conv = adj.gauss_newton(adj.w_obs_fit, adj.x0)
        return x, N, iters, conv, w_final, outl_obs, None

    def fit(w: NDArray, prev: Any) -> NDArray:
        return adj.gauss_newton(w, adj.x0 if prev is None else prev)[0]

    res = irls(fit, adj.residuals, adj.n_obs, psi=robust, prior_weights=adj.w_obs_fit, min_used=7,
               outlier_threshold=OUTLIER_THRESHOLD)
    floored = False
    own = float(res.scale)
    if min_scale is not None and res.scale < min_scale:
        # the residuals' own robust scale fell below the a-priori one (a redescending estimator fitting a
        # subset of the control nearly exactly flags good points): rerun with the a-priori scale, so that
        # no residual within OUTLIER_THRESHOLD predicted standard deviations is flagged
        res = irls(fit, adj.residuals, adj.n_obs, psi=robust, prior_weights=adj.w_obs_fit, min_used=7,
                   scale=min_scale, outlier_threshold=OUTLIER_THRESHOLD)
        floored = True
    w_final = res.weights
    z = np.abs(res.residuals) / res.scale if res.scale > 0 else np.zeros(adj.n_obs)
    test = _OutlierTest(z, float(res.scale), own, OUTLIER_THRESHOLD, min_scale, floored)
    # final covariance with the final weights
    x, N, iters, conv = adj.gauss_newton(np.maximum(w_final, 0.0), res.model)
    return x, N, iters, conv, w_final, res.outlier_mask, test


def _precision(adj: _Adjustment, x: NDArray, N: NDArray, w_final: NDArray
               ) -> tuple[float, NDArray, NDArray, NDArray, float]:
    """Stage 3: sigma0 with the redundancy n - 7, the parameters back from centred coordinates and their
    covariance; returns (scale, R, T, covariance, sigma0)."""
    v = adj.residuals(x)
    dof = adj.n_obs - 7
    sigma0 = math.sqrt(float(np.sum(w_final * v * v)) / dof) if dof > 0 else float("nan")
    Qxx = lsq.cofactor(N)
    s, ang, tp = x[0], x[1:4], x[4:7]
    R = matrix_from_angles(ang[0], ang[1], ang[2], order="omega-phi-kappa")
    T = tp + adj.gc_full - s * R @ adj.mc
    # covariance of (s, ang, T) from that of (s, ang, T'): T = T' + gc - s R mc
    Jt = np.eye(7)
    Jt[4:7, 0] = -R @ adj.mc
    Rx, Ry, Rz = rot_x(ang[0]), rot_y(ang[1]), rot_z(ang[2])
    dR = [Rx @ _K[0] @ Ry @ Rz, Rx @ Ry @ _K[1] @ Rz, R @ _K[2]]
    for k in range(3):
        Jt[4:7, 1 + k] = -s * dR[k] @ adj.mc
    s02 = sigma0 ** 2 if math.isfinite(sigma0) else 1.0
    cov = s02 * Jt @ Qxx @ Jt.T
    return float(s), R, T, cov, sigma0


def _fit_deformation(sim: NDArray, g: NDArray, full: NDArray, zonly: NDArray, order: int, w_obs: NDArray,
                     obs_pt: NDArray, obs_c: NDArray, n_obs: int) -> tuple[PolynomialCorrection, float]:
    """Least-squares polynomial corrections per coordinate on the similarity's residuals."""
    centre = sim[full, :2].mean(0)
    scale_xy = float(np.abs(sim[full, :2] - centre).max()) or 1.0
    D_all = _poly_terms((sim[:, :2] - centre) / scale_xy, order)
    nt = D_all.shape[1]
    coef = np.zeros((3, nt))
    covs = np.zeros((3, nt, nt))
    vtpv = 0.0
    Qs = []
    for j in range(3):
        k = obs_c == j
        pts = obs_pt[k]
        w = w_obs[k]
        D = D_all[pts]
        lv = g[pts, j] - sim[pts, j]
        if len(pts) < nt:
            raise EstimationError(f"too few points for the deformation polynomial of coordinate {j}: "
                                  f"{len(pts)} < {nt}")
        Nj = (D * w[:, None]).T @ D
        if np.linalg.matrix_rank(Nj) < nt:
            raise EstimationError(f"the control points do not determine the order-{order} deformation "
                                  f"polynomial (rank {np.linalg.matrix_rank(Nj)} < {nt})")
        Q = np.linalg.inv(Nj)
        b = Q @ (D * w[:, None]).T @ lv
        coef[j] = b
        v = D @ b - lv
        vtpv += float(np.sum(w * v * v))
        Qs.append(Q)
    dof = n_obs - 7 - 3 * nt
    sigma0 = math.sqrt(vtpv / dof) if dof > 0 else float("nan")
    s02 = sigma0 ** 2 if math.isfinite(sigma0) else 1.0
    for j in range(3):
        covs[j] = s02 * Qs[j]
    return PolynomialCorrection(order=order, centre=centre, scale_xy=scale_xy, coefficients=coef,
                                covariance=covs), sigma0
