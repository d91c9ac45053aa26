"""Least-squares adjustment with self-calibration (bundle type) for calibration targets.

Unknowns: the interior orientation of each camera (a chosen subset of
``fx, fy, cx, cy, k1, k2, k3, p1, p2, sx, sy``; see :mod:`.model`), the
exterior orientation of every station (rotation vector and translation of the
object -> OpenCV camera transform) and, for rigs, the fixed relative
orientation of each further camera to the first. Observations: measured
pixels, equal weight. Residuals ``v = adjusted - observed`` (px).

The normal equations are solved with Levenberg-Marquardt damping on a
column-scaled Jacobian (every unknown normalised to unit column norm; seed 003,
1.8: normalisation makes the condition number meaningful and the solution
independent of the units). The Jacobian is by central differences; because
each observation depends on one station and one camera only, a whole block of
columns costs one projection of all points.

After convergence: ``sigma0^2 = v^T W v / (n - u)``, the covariance
``sigma0^2 (J^T W J)^-1``, standard errors and correlations. Robust
estimation (``robust="huber"`` etc.) reweights points by the M-estimators of
:mod:`rectify.geometry.robust` on the residual length standardised by the MAD scale.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CalibrationError, ConvergenceError, InvalidInputError
from rectify.geometry.robust import get_psi, robust_scale
from rectify.geometry.rotation import rodrigues
from stereo.calibration.model import INTERIOR_NAMES, project_vector

logger = logging.getLogger(__name__)

__all__ = ["FREE_NAMES", "Adjustment", "Observations", "adjust", "free_parameters"]

F64 = NDArray[np.float64]

#: Free interior parameter name -> indices in the 11-vector it drives.
FREE_NAMES: dict[str, tuple[int, ...]] = {
    "f": (0, 1), "fx": (0,), "fy": (1,),
    "cx": (2, 9), "cy": (3, 10),  # the point of symmetry follows the principal point ...
    "cx*": (2,), "cy*": (3,),     # ... unless it is free itself
    "k1": (4,), "k2": (5,), "k3": (6,), "p1": (7,), "p2": (8,), "sx": (9,), "sy": (10,),
}


def free_parameters(*, equal_focal: bool = False, principal_point: bool = True,
                    distortion: Sequence[str] = ("k1", "k2", "k3", "p1", "p2"),
                    symmetry: bool = False) -> tuple[str, ...]:
    """Names of the free interior unknowns of one camera (keys of :data:`FREE_NAMES`).

    Raises
    ------
    InvalidInputError
        For unknown distortion names or a point of symmetry without distortion.
    """
    bad = [d for d in distortion if d not in ("k1", "k2", "k3", "p1", "p2")]
    if bad:
        raise InvalidInputError(f"unknown distortion coefficient(s) {bad}; expected k1, k2, k3, p1, p2")
    out = ["f"] if equal_focal else ["fx", "fy"]
    if principal_point:
        out += ["cx*", "cy*"] if symmetry else ["cx", "cy"]
    out += [d for d in ("k1", "k2", "k3", "p1", "p2") if d in distortion]
    if symmetry:
        if not distortion:
            raise InvalidInputError("a separate point of symmetry needs free distortion coefficients")
        out += ["sx", "sy"]
    return tuple(out)


@dataclass(frozen=True, eq=False)
class Observations:
    """All measured target points, concatenated over views.

    Attributes
    ----------
    object_xyz : (N, 3) float64
        Target coordinates, object frame.
    pixel : (N, 2) float64
        Measured pixels.
    camera : (N,) int
        Camera index of each point (0 unless a rig).
    station : (N,) int
        Station (pose) index of each point.
    """

    object_xyz: F64
    pixel: F64
    camera: NDArray[np.intp]
    station: NDArray[np.intp]

    @property
    def n(self) -> int:
        return len(self.pixel)


@dataclass(frozen=True, eq=False)
class Adjustment:
    """Outcome of :func:`adjust`.

    Attributes
    ----------
    interiors : list of (11,) float64
        Interior vectors per camera (:data:`.model.INTERIOR_NAMES`).
    poses : (S, 6) float64
        Rotation vector (rad) and translation (object units) per station,
        object -> OpenCV camera.
    relative : (C - 1, 6) float64
        Relative orientation of cameras 1.. to camera 0 (camera-0 frame ->
        camera-c frame), same layout.
    names : tuple of str
        Names of all unknowns, in covariance order.
    covariance : (U, U) float64
        sigma0^2 (J^T W J)^-1.
    sigma0 : float
        A-posteriori standard deviation of unit weight, px.
    residuals : (N, 2) float64
        ``adjusted - observed`` per point, px.
    weights : (N,) float64
        Final robust weights (1 without robust estimation).
    iterations, reweightings : int
    condition_number : float
        Of the column-scaled normal matrix.
    """

    interiors: list[F64]
    poses: F64
    relative: F64
    names: tuple[str, ...]
    covariance: F64
    sigma0: float
    residuals: F64
    weights: F64
    iterations: int
    reweightings: int
    condition_number: float
    redundancy: int
    extra: dict = field(default_factory=dict)

    @property
    def std_errors(self) -> F64:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def correlation(self) -> F64:
        s = self.std_errors
        d = np.where(s > 0, s, 1.0)
        c = self.covariance / np.outer(d, d)
        return np.clip(c, -1.0, 1.0)


class _Problem:
    def __init__(self, obs: Observations, interiors: Sequence[F64], free: Sequence[Sequence[str]],
                 n_stations: int, n_rel: int) -> None:
        self.obs = obs
        self.base = [np.array(v, dtype=np.float64) for v in interiors]
        self.free = [tuple(f) for f in free]
        self.n_int = [len(f) for f in self.free]
        self.off_pose = sum(self.n_int)
        self.S = n_stations
        self.off_rel = self.off_pose + 6 * n_stations
        self.n_rel = n_rel
        self.U = self.off_rel + 6 * n_rel
        self.cam_rows = [np.flatnonzero(obs.camera == c) for c in range(len(self.base))]

    # parameter vector <-> pieces
    def pack(self, interiors: Sequence[F64], poses: F64, rel: F64) -> F64:
        p = []
        for v, names in zip(interiors, self.free, strict=True):
            p += [v[FREE_NAMES[n][0]] for n in names]
        return np.concatenate([np.array(p, dtype=np.float64), poses.reshape(-1), rel.reshape(-1)])

    def interiors(self, p: F64) -> list[F64]:
        out, k = [], 0
        for v0, names in zip(self.base, self.free, strict=True):
            v = v0.copy()
            for n in names:
                v[list(FREE_NAMES[n])] = p[k]
                k += 1
            out.append(v)
        return out

    def poses(self, p: F64) -> F64:
        return p[self.off_pose:self.off_rel].reshape(self.S, 6)

    def rel(self, p: F64) -> F64:
        return p[self.off_rel:].reshape(self.n_rel, 6)

    def camera_points(self, poses: F64, rel: F64) -> F64:
        o = self.obs
        R = rodrigues(poses[:, :3])[o.station]
        xc = np.einsum("nij,nj->ni", R, o.object_xyz) + poses[o.station, 3:]
        if self.n_rel:
            m = o.camera > 0
            ci = o.camera[m] - 1
            Rr = rodrigues(rel[:, :3])[ci]
            xc[m] = np.einsum("nij,nj->ni", Rr, xc[m]) + rel[ci, 3:]
        return xc

    def project(self, interiors: list[F64], xc: F64) -> F64:
        V = np.array(interiors)[self.obs.camera]
        return project_vector(V, xc)

    def residuals(self, p: F64) -> F64:
        ints = self.interiors(p)
        xc = self.camera_points(self.poses(p), self.rel(p))
        return (self.project(ints, xc) - self.obs.pixel).ravel()

    def jacobian(self, p: F64) -> F64:
        o = self.obs
        n = o.n
        J = np.zeros((n, 2, self.U))
        ints = self.interiors(p)
        poses, rel = self.poses(p), self.rel(p)
        xc = self.camera_points(poses, rel)
        if np.any(xc[:, 2] <= 0):
            raise CalibrationError(f"{int(np.sum(xc[:, 2] <= 0))} target points are behind the camera")
        V = np.array(ints)[o.camera]
        k = 0
        for c, names in enumerate(self.free):
            rows = self.cam_rows[c]
            for name in names:
                idx = list(FREE_NAMES[name])
                val = ints[c][idx[0]]
                h = 1e-6 * max(abs(val), 1.0)
                Vp, Vm = V[rows].copy(), V[rows].copy()
                Vp[:, idx] += h
                Vm[:, idx] -= h
                J[rows, :, k] = (project_vector(Vp, xc[rows]) - project_vector(Vm, xc[rows])) / (2 * h)
                k += 1
        # pose columns: perturb element j of every station at once
        for j in range(6):
            h = np.full(self.S, 1e-7) if j < 3 else 1e-7 * np.maximum(np.linalg.norm(poses[:, 3:], axis=1), 1e-3)
            pp, pm = poses.copy(), poses.copy()
            pp[:, j] += h
            pm[:, j] -= h
            d = (project_vector(V, self.camera_points(pp, rel)) - project_vector(V, self.camera_points(pm, rel))) \
                / (2 * h[o.station])[:, None]
            J[np.arange(n), :, self.off_pose + 6 * o.station + j] = d
        if self.n_rel:
            m = np.flatnonzero(o.camera > 0)
            ci = o.camera[m] - 1
            for j in range(6):
                h = np.full(self.n_rel, 1e-7) if j < 3 else \
                    1e-7 * np.maximum(np.linalg.norm(rel[:, 3:], axis=1), 1e-3)
                rp, rm = rel.copy(), rel.copy()
                rp[:, j] += h
                rm[:, j] -= h
                d = project_vector(V, self.camera_points(poses, rp)) - project_vector(V, self.camera_points(poses, rm))
                J[m, :, self.off_rel + 6 * ci + j] = d[m] / (2 * h[ci])[:, None]
        return J.reshape(2 * n, self.U)

    def names(self, camera_labels: Sequence[str], station_labels: Sequence[str]) -> tuple[str, ...]:
        out = []
        multi = len(self.free) > 1
        for c, names in enumerate(self.free):
            for nm in names:
                nm = nm.rstrip("*")
                out.append(f"{camera_labels[c]}.{nm}" if multi else nm)
        for s in station_labels:
            out += [f"{s}.{e}" for e in ("rx", "ry", "rz", "tx", "ty", "tz")]
        for c in range(1, self.n_rel + 1):
            out += [f"{camera_labels[c]}.rel_{e}" for e in ("rx", "ry", "rz", "tx", "ty", "tz")]
        return tuple(out)


def _gram(J: F64, Jw: F64) -> F64:
    """``J^T Jw`` without multi-threaded BLAS (small matrices: threads only cost time on shared machines)."""
    return np.einsum("ki,kj->ij", J, Jw)


def _lm(prob: _Problem, p: F64, w: F64, *, max_iter: int, tol: float) -> tuple[F64, int, bool]:
    """Levenberg-Marquardt on the column-scaled weighted normal equations."""
    wr = np.repeat(w, 2)
    r = prob.residuals(p)
    cost = float(np.sum(wr * r * r))
    lam = 1e-6
    it = 0
    converged = False
    for it in range(1, max_iter + 1):  # noqa: B007
        J = prob.jacobian(p)
        Jw = J * wr[:, None]
        A = _gram(J, Jw)
        g = np.einsum("ki,k->i", Jw, r)
        d = np.sqrt(np.diag(A))
        d[d == 0] = 1.0
        As = A / np.outer(d, d)
        gs = g / d
        while True:
            try:
                step = -np.linalg.solve(As + lam * np.eye(len(d)), gs) / d
            except np.linalg.LinAlgError:
                lam *= 10
                if lam > 1e12:
                    raise ConvergenceError("calibration adjustment: singular normal equations", iterations=it) \
                        from None
                continue
            pn = p + step
            try:
                rn = prob.residuals(pn)
                cn = float(np.sum(wr * rn * rn)) if np.all(np.isfinite(rn)) else math.inf
            except (FloatingPointError, ValueError):
                cn = math.inf
            if cn <= cost:
                break
            lam *= 10
            if lam > 1e12:
                break
        if cn > cost:  # no decrease possible: at the minimum to rounding
            converged = True
            break
        rel_step = float(np.max(np.abs(step * d)) / max(1.0, float(np.sqrt(np.sum(gs ** 2)))))
        dec = (cost - cn) / max(cost, 1e-300)
        logger.debug('LM %d cost %.12g dec %.3g step %.3g lam %.1g', it, cn, dec, rel_step, lam)
        p, r, cost = pn, rn, cn
        lam = max(lam / 100, 1e-15)
        if dec < tol or rel_step < 1e-12:
            converged = True
            break
    return p, it, converged


def adjust(obs: Observations, interiors: Sequence[F64], free: Sequence[Sequence[str]], poses: F64,
           relative: F64 | None = None, *, robust: str | None = None, max_iter: int = 100, tol: float = 1e-14,
           camera_labels: Sequence[str] | None = None, station_labels: Sequence[str] | None = None
           ) -> Adjustment:
    """Run the adjustment from a start.

    Parameters
    ----------
    obs : Observations
    interiors : list of (11,) float64
        Start (and fixed values) of each camera's interior vector.
    free : list of sequences of str
        Free interior unknowns per camera (see :func:`free_parameters`).
    poses : (S, 6) float64
        Start of each station's rotation vector and translation (object -> OpenCV camera).
    relative : (C - 1, 6) float64, optional
        Start of the rig's relative orientations.
    robust : str, optional
        ``"huber"``, ``"tukey"``, ``"hampel"`` or ``"andrews"``.

    Raises
    ------
    CalibrationError
        Too few observations for the unknowns, or a singular (unobservable) system.
    ConvergenceError
        If the iteration fails.
    """
    poses = np.array(poses, dtype=np.float64).reshape(-1, 6)
    rel = np.zeros((0, 6)) if relative is None else np.array(relative, dtype=np.float64).reshape(-1, 6)
    prob = _Problem(obs, interiors, free, len(poses), len(rel))
    redundancy = 2 * obs.n - prob.U
    if redundancy <= 0:
        raise CalibrationError(f"too few observations: {2 * obs.n} coordinates for {prob.U} unknowns")
    p = prob.pack(interiors, poses, rel)
    w = np.ones(obs.n)
    p, its, conv = _lm(prob, p, w, max_iter=max_iter, tol=tol)
    n_rew = 0
    if robust:
        psi = get_psi(robust)
        for n_rew in range(1, 31):  # noqa: B007
            v = prob.residuals(p).reshape(-1, 2)
            s = robust_scale(v.ravel())
            if s == 0:
                break
            w_new = psi.weight(np.linalg.norm(v, axis=1) / (math.sqrt(2.0) * s))
            if int(np.sum(w_new > 0)) * 2 <= prob.U:
                raise CalibrationError("robust weighting left too few points for the unknowns")
            p, k, conv = _lm(prob, p, w_new, max_iter=max_iter, tol=max(tol, 1e-9))
            its += k
            change = float(np.max(np.abs(w_new - w)))
            w = w_new
            if change < 1e-3:
                break
        p, k, conv = _lm(prob, p, w, max_iter=max_iter, tol=tol)
        its += k
    r = prob.residuals(p)
    J = prob.jacobian(p)
    wr = np.repeat(w, 2)
    A = _gram(J, J * wr[:, None])
    d = np.sqrt(np.diag(A))
    labels_c = camera_labels or [f"camera{c}" for c in range(len(prob.base))]
    labels_s = station_labels or [f"view{s}" for s in range(len(poses))]
    names = prob.names(labels_c, labels_s)
    if np.any(d == 0):
        bad = [names[i] for i in np.flatnonzero(d == 0)]
        raise CalibrationError(f"unknown(s) {bad[:5]} are not observed by any point")
    As = A / np.outer(d, d)
    ev, evec = np.linalg.eigh(As)
    cond = float(ev[-1] / max(ev[0], 1e-300))
    if ev[0] <= 1e-13 * ev[-1]:
        worst = np.argsort(-np.abs(evec[:, 0]))[:3]
        raise CalibrationError(f"the adjustment is singular (condition number {cond:.2g}): "
                               f"{', '.join(names[i] for i in worst)} cannot be separated by these views")
    Q = np.linalg.inv(As) / np.outer(d, d)
    used = w > 0
    dof = 2 * int(used.sum()) - prob.U
    if dof <= 0:
        raise CalibrationError(f"no redundancy left: {2 * int(used.sum())} weighted coordinates for {prob.U} unknowns")
    s0 = math.sqrt(float(np.sum(wr * r * r)) / dof)
    if not conv:
        logger.warning("calibration adjustment stopped after %d iterations without converging", its)
    return Adjustment(interiors=prob.interiors(p), poses=prob.poses(p).copy(), relative=prob.rel(p).copy(),
                      names=names, covariance=s0 * s0 * Q, sigma0=s0, residuals=r.reshape(-1, 2), weights=w,
                      iterations=its, reweightings=n_rew, condition_number=cond, redundancy=dof,
                      extra={"converged": conv, "interior_names": INTERIOR_NAMES})
