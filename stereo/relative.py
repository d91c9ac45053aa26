"""Relative orientation of a stereo pair by the coplanarity condition.

Three systems of elements share one model frame (DESIGN.md, "Relative
orientation: one frame, three systems"); each fixes three of the eight angular
elements of the pair and estimates the other five:

=====================  ====================================  ==============================
system                 estimated elements (radians)          fixed
=====================  ====================================  ==============================
``basis``              alpha1, kappa1, alpha2, omega2, kappa2  base along +X, omega1 = 0
``left-image``         tau, nu, alpha2, omega2, kappa2         left bundle = model frame
``dobrynin-pimshina``  tau, omega1, alpha1, alpha2, chi2       nu = 0 (B'z = 0), chi1 = omega2 = 0
=====================  ====================================  ==============================

Rotations take a photo vector (x, y, -f) into the model frame, X' = R (x, y, -f).
``basis`` and ``left-image`` use R = Ry(alpha) Rx(omega) Rz(kappa) for each
image; ``dobrynin-pimshina`` uses R = Rx(omega) Ry(alpha) Rz(chi) (seed 000,
eq. 1). The base is the unit vector

    b = (cos tau cos nu, sin tau cos nu, sin nu) = Bx (1, tan tau, tan nu / cos tau),
    Bx = cos tau cos nu,

so tau > 0 turns the base from +X towards +Y and nu > 0 lifts it towards +Z.

Coplanarity
-----------
For a tie point with photo vectors u1 = (x1, y1, -f1), u2 = (x2, y2, -f2) and
model rays r1 = R1 u1, r2 = R2 u2 the misclosure is the triple product

    F = b . (r1 x r2) = det [b; r1; r2],

which for the ``dobrynin-pimshina`` system is seed 000's eq. (2) times cos tau.
The partial derivatives with respect to the elements are analytic (rotation
generators, see :func:`_chain`); with respect to the photo coordinates they
are g1 = R1^T (r2 x b) and g2 = R2^T (b x r1) (first two components).

Adjustment (seed 002, section 2.1; Gauss-Helmert with one condition per point):
each equation F_i + J_i dp = 0 is weighted by 1 / (|g1|^2 + |g2|^2), so the
normalised residual e_i = F_i / sqrt(|g1|^2 + |g2|^2) is the smallest total
correction (mm) of the four photo coordinates that puts the two rays into one
epipolar plane. sigma0 = sqrt(sum w e^2 / (n - 5)) is the standard deviation
of unit weight of one photo coordinate (mm). The *residual vertical parallax*
of a point is the sum of the perpendicular corrections in the two images,
q_i = F_i (|g1| + |g2|) / (|g1|^2 + |g2|^2): the distance between the two
epipolar lines (mm; px with the pixel size).

Initial values
--------------
Zero angles serve near-vertical aerial pairs. Otherwise (``initial="essential"``,
or ``"auto"`` after a failed zero start, or when robust estimation is asked
for) the essential matrix of OpenCV's five-point solver with USAC (MAGSAC) and
``recoverPose`` gives the relative rotation and base, which are converted into
the chosen system by :meth:`System.elements_from_relative`. Its inlier mask is
the RANSAC first filter of robust estimation, followed by IRLS
(:func:`rectify.robust.irls`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import (
    ConvergenceError,
    EstimationError,
    InvalidInputError,
    WeakGeometryWarning,
)
from rectify.points import as_ids, as_pair, as_weights
from rectify.residuals import ResidualTable, rms
from rectify.robust import ROBUST_METHODS, get_psi, irls
from rectify.rotation import angles_from_matrix, check_rotation

logger = logging.getLogger(__name__)

__all__ = [
    "INITIAL_METHODS",
    "SYSTEMS",
    "PrecisionStructure",
    "RelativeGeometry",
    "RelativeOptions",
    "RelativeOrientation",
    "System",
    "WesternForm",
    "coplanarity",
    "precision_structure",
    "relative_from_essential",
]

#: initial values of the adjustment (see :meth:`RelativeOrientation.from_points`)
INITIAL_METHODS = ("auto", "zero", "essential")

# rotation generators: d/da R_axis(a) = R_axis(a) @ G_axis
_G = {
    "x": np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "y": np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]]),
    "z": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]]),
}


def _rot(axis: str, a: float) -> NDArray[np.float64]:
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _chain(axes: str, angles: Sequence[float]) -> tuple[NDArray[np.float64], list[NDArray[np.float64]]]:
    """R = E1 E2 E3 and the analytic dR/d(angle_i) = E1..Ei G_i ..E3."""
    E = [_rot(ax, a) for ax, a in zip(axes, angles)]
    R = E[0] @ E[1] @ E[2]
    d = [E[0] @ _G[axes[0]] @ E[1] @ E[2],
         E[0] @ E[1] @ _G[axes[1]] @ E[2],
         E[0] @ E[1] @ E[2] @ _G[axes[2]]]
    return R, d


def _base(tau: float, nu: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    ct, st, cn, sn = math.cos(tau), math.sin(tau), math.cos(nu), math.sin(nu)
    b = np.array([ct * cn, st * cn, sn])
    return b, np.array([-st * cn, ct * cn, 0.0]), np.array([-ct * sn, -st * sn, cn])


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v)


# ------------------------------------------------------------------ systems
@dataclass(frozen=True)
class System:
    """One system of relative orientation elements.

    Attributes
    ----------
    name : str
    names : tuple of 5 str
        Estimated elements, in the order of the parameter vector.
    order : str
        Rotation order of each image (``"alpha-omega-kappa"`` or ``"omega-alpha-chi"``).
    fixed : tuple of str
        The three elements held at zero.
    """

    name: str
    names: tuple[str, ...]
    order: str
    fixed: tuple[str, ...]

    # --------------------------------------------------------------- geometry
    def geometry(self, p: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
        """(R1, R2, b): rotations photo -> model (3, 3) and unit base (3,) for elements p (5,)."""
        R1, R2, b, *_ = self._geometry_and_derivatives(np.asarray(p, dtype=np.float64))
        return R1, R2, b

    def derivatives(self, p: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
        """dR1 (5, 3, 3), dR2 (5, 3, 3), db (5, 3): analytic partials by each element."""
        _, _, _, dR1, dR2, db = self._geometry_and_derivatives(np.asarray(p, dtype=np.float64))
        return dR1, dR2, db

    def _geometry_and_derivatives(self, p):
        dR1 = np.zeros((5, 3, 3))
        dR2 = np.zeros((5, 3, 3))
        db = np.zeros((5, 3))
        if self.name == "basis":  # alpha1, kappa1, alpha2, omega2, kappa2
            R1, d1 = _chain("yxz", [p[0], 0.0, p[1]])
            R2, d2 = _chain("yxz", [p[2], p[3], p[4]])
            b = np.array([1.0, 0.0, 0.0])
            dR1[0], dR1[1] = d1[0], d1[2]
            dR2[2], dR2[3], dR2[4] = d2
        elif self.name == "left-image":  # tau, nu, alpha2, omega2, kappa2
            R1 = np.eye(3)
            R2, d2 = _chain("yxz", [p[2], p[3], p[4]])
            b, db[0], db[1] = _base(p[0], p[1])
            dR2[2], dR2[3], dR2[4] = d2
        else:  # dobrynin-pimshina: tau, omega1, alpha1, alpha2, chi2
            R1, d1 = _chain("xyz", [p[1], p[2], 0.0])
            R2, d2 = _chain("xyz", [0.0, p[3], p[4]])
            b, db[0], _ = _base(p[0], 0.0)
            dR1[1], dR1[2] = d1[0], d1[1]
            dR2[3], dR2[4] = d2[1], d2[2]
        return R1, R2, b, dR1, dR2, db

    # ------------------------------------------------------------- conversion
    def elements_from_relative(self, R_rel: ArrayLike, base_left: ArrayLike) -> NDArray[np.float64]:
        """Elements (5,) of this system for a relative geometry.

        Parameters
        ----------
        R_rel : (3, 3)
            Right photo frame -> left photo frame.
        base_left : (3,)
            Right projection centre minus left, in the left photo frame, any scale.

        Raises
        ------
        EstimationError
            If the geometry cannot be expressed in this system (e.g. for
            ``dobrynin-pimshina``, a base parallel to the right image's y axis).
        """
        Rr = check_rotation(R_rel, "R_rel")
        bc = np.asarray(base_left, dtype=np.float64).reshape(3)
        if not np.isfinite(bc).all() or np.linalg.norm(bc) == 0:
            raise EstimationError(f"base vector must be finite and non-zero; got {bc.tolist()}")
        bc = _unit(bc)
        if self.name == "left-image":
            tau = math.atan2(bc[1], bc[0])
            nu = math.atan2(bc[2], math.hypot(bc[0], bc[1]))
            a2, w2, k2 = angles_from_matrix(Rr, "phi-omega-kappa")
            return np.array([tau, nu, a2, w2, k2])
        if self.name == "basis":
            a1 = math.asin(max(-1.0, min(1.0, bc[2])))
            k1 = math.atan2(-bc[1], bc[0])
            M = _rot("y", a1) @ _rot("z", k1)
            a2, w2, k2 = angles_from_matrix(M @ Rr, "phi-omega-kappa")
            return np.array([a1, k1, a2, w2, k2])
        # dobrynin-pimshina, from the parametrisation (seed 000, eq. 4):
        #   chi1 = 0   <=> model X is normal to the left image's y axis: X = (cos a1, 0, sin a1);
        #   omega2 = 0 <=> model Y is normal to the right optical axis z2;
        #   nu = 0     <=> model Z is normal to the base.
        # Y normal to X and z2 gives Z = unit(z2 - X (X.z2)); Z.b = 0 then reads
        #   g(a1) = (X.b)(X.z2) - b.z2 = 0, i.e. P cos 2a1 + Q sin 2a1 = K.
        z2 = Rr[:, 2]
        P = (bc[0] * z2[0] - bc[2] * z2[2]) / 2
        Q = (bc[0] * z2[2] + bc[2] * z2[0]) / 2
        K = float(bc @ z2) - (bc[0] * z2[0] + bc[2] * z2[2]) / 2
        amp = math.hypot(P, Q)
        if amp < 1e-12 or abs(K) > amp * (1 + 1e-12):
            raise EstimationError(
                "the dobrynin-pimshina system is undefined for this pair: no model frame has chi1 = omega2 = "
                f"B'z = 0 (base {bc.round(6).tolist()}, right optical axis {z2.round(6).tolist()})")
        delta = math.atan2(Q, P)
        acos_ = math.acos(max(-1.0, min(1.0, K / amp)))
        best = None
        for two_a in (delta + acos_, delta - acos_):
            for a in (two_a / 2, two_a / 2 + math.pi):
                a = (a + math.pi) % (2 * math.pi) - math.pi
                if math.cos(a) <= 0:
                    continue
                for _ in range(3):  # polish: acos loses digits near +-1
                    X, dX = np.array([math.cos(a), 0.0, math.sin(a)]), np.array([-math.sin(a), 0.0, math.cos(a)])
                    g = (X @ bc) * (X @ z2) - bc @ z2
                    dg = (dX @ bc) * (X @ z2) + (X @ bc) * (dX @ z2)
                    if dg != 0:
                        a -= g / dg
                X = np.array([math.cos(a), 0.0, math.sin(a)])
                Z = z2 - X * (X @ z2)
                if np.linalg.norm(Z) < 1e-9:
                    continue
                Z = _unit(Z)
                if Z[2] < 0:
                    Z = -Z
                M = np.vstack([X, np.cross(Z, X), Z])  # left photo -> model, right-handed
                w = math.atan2(M[2, 1], M[1, 1])
                cost = abs(a) + abs(w)
                if best is None or cost < best[0]:
                    best = (cost, M)
        if best is None:
            raise EstimationError("the dobrynin-pimshina system is undefined for this pair "
                                  f"(base {bc.round(6).tolist()})")
        M = best[1]
        w1, a1, _ = angles_from_matrix(M, "omega-alpha-chi")
        _, a2, c2 = angles_from_matrix(M @ Rr, "omega-alpha-chi")
        bm = M @ bc
        tau = math.atan2(bm[1], bm[0])
        return np.array([tau, w1, a1, a2, c2])


SYSTEMS: dict[str, System] = {
    "basis": System("basis", ("alpha1", "kappa1", "alpha2", "omega2", "kappa2"), "alpha-omega-kappa",
                    ("tau", "nu", "omega1")),
    "left-image": System("left-image", ("tau", "nu", "alpha2", "omega2", "kappa2"), "alpha-omega-kappa",
                         ("alpha1", "omega1", "kappa1")),
    "dobrynin-pimshina": System("dobrynin-pimshina", ("tau", "omega1", "alpha1", "alpha2", "chi2"),
                                "omega-alpha-chi", ("nu", "chi1", "omega2")),
}


def _get_system(system: str | System) -> System:
    if isinstance(system, System):
        return system
    try:
        return SYSTEMS[str(system)]
    except KeyError:
        raise InvalidInputError(f"unknown system {system!r}; expected one of {list(SYSTEMS)}") from None


# -------------------------------------------------------------- coplanarity
@dataclass(frozen=True)
class _Eval:
    F: NDArray[np.float64]        # (N,) misclosure
    J: NDArray[np.float64]        # (N, 5) dF/dp
    g1: NDArray[np.float64]       # (N,) |dF/d(x1, y1)|
    g2: NDArray[np.float64]       # (N,) |dF/d(x2, y2)|

    @property
    def gn2(self):
        return self.g1 ** 2 + self.g2 ** 2

    @property
    def normalised(self):
        return self.F / np.sqrt(self.gn2)

    @property
    def parallax(self):
        return self.F * (self.g1 + self.g2) / self.gn2


def _cross(a: NDArray, b: NDArray) -> NDArray:
    """Row-wise cross product of (N, 3) arrays (or (N, 3) with (3,)), faster than np.cross."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _evaluate(sys_: System, p: NDArray, u1: NDArray, u2: NDArray, *, jac: bool = True) -> _Eval:
    R1, R2, b, dR1, dR2, db = sys_._geometry_and_derivatives(p)
    r1 = u1 @ R1.T
    r2 = u2 @ R2.T
    c = _cross(r1, r2)
    F = c @ b
    w2 = _cross(r2, b)   # dF/dr1
    w1 = _cross(b, r1)   # dF/dr2
    h1 = w2 @ R1         # dF/du1
    h2 = w1 @ R2         # dF/du2
    g1 = np.hypot(h1[:, 0], h1[:, 1])
    g2 = np.hypot(h2[:, 0], h2[:, 1])
    n = len(F)
    if jac:
        # dF/dp_k = c . db_k + w2 . (dR1_k u1) + w1 . (dR2_k u2)
        J = c @ db.T
        J += ((w2 @ dR1.transpose(1, 0, 2).reshape(3, 15)).reshape(n, 5, 3) * u1[:, None, :]).sum(axis=2)
        J += ((w1 @ dR2.transpose(1, 0, 2).reshape(3, 15)).reshape(n, 5, 3) * u2[:, None, :]).sum(axis=2)
    else:
        J = np.empty((n, 0))
    return _Eval(F, J, g1, g2)


def coplanarity(system: str | System, elements: ArrayLike, left_mm: ArrayLike, right_mm: ArrayLike,
                focal_length_mm: float | tuple[float, float]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Coplanarity misclosure F (N,) and its analytic Jacobian dF/d(elements) (N, 5).

    Parameters
    ----------
    system : str
        One of :data:`SYSTEMS`.
    elements : (5,) float64
        Elements in the system's order, radians.
    left_mm, right_mm : (N, 2) float64
        Photo coordinates, mm (x right, y up, origin at the principal point).
    focal_length_mm : float or (float, float)
        Principal distance(s) of the left and right camera.

    Returns
    -------
    F : (N,) float64
        b . (r1 x r2) with a unit base, mm^2.
    J : (N, 5) float64
    """
    s = _get_system(system)
    p = np.asarray(elements, dtype=np.float64).reshape(5)
    l, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    f1, f2 = _focals(focal_length_mm)
    e = _evaluate(s, p, _rays(l, f1), _rays(r, f2))
    return e.F, e.J


def _rays(mm: NDArray, f: float) -> NDArray:
    return np.column_stack([mm, np.full(len(mm), -f)])


def _focals(focal_length_mm) -> tuple[float, float]:
    f = np.asarray(focal_length_mm, dtype=np.float64).reshape(-1)
    if f.size == 1:
        f = np.array([f[0], f[0]])
    if f.size != 2 or not np.isfinite(f).all() or (f <= 0).any():
        raise InvalidInputError(f"`focal_length_mm` must be one or two finite numbers > 0; got {focal_length_mm!r}")
    return float(f[0]), float(f[1])


class PrecisionStructure(NamedTuple):
    """A-priori precision of the elements for given points (sigma0 = 1).

    Attributes
    ----------
    cofactor : (5, 5) float64
        (J^T W J)^-1, rad^2 per mm^2 of unit-weight variance.
    correlation : (5, 5) float64
    condition_number : float
        Of the column-scaled normal matrix.
    condition_number_raw : float
        Of the normal matrix J^T W J.
    """

    cofactor: NDArray[np.float64]
    correlation: NDArray[np.float64]
    condition_number: float
    condition_number_raw: float


def precision_structure(system: str | System, elements: ArrayLike, left_mm: ArrayLike, right_mm: ArrayLike,
                        focal_length_mm: float | tuple[float, float]) -> PrecisionStructure:
    """Cofactor and correlation matrix of the elements at ``elements`` for these tie points.

    Uses the same weighted normal equations as :meth:`RelativeOrientation.from_points`,
    so it applies to exact (noise-free) point sets as well.

    Raises
    ------
    EstimationError
        When the normal matrix is singular (degenerate configuration).
    """
    s = _get_system(system)
    p = np.asarray(elements, dtype=np.float64).reshape(5)
    l, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    f1, f2 = _focals(focal_length_mm)
    e = _evaluate(s, p, _rays(l, f1), _rays(r, f2))
    A = e.J / np.sqrt(e.gn2)[:, None]
    N = A.T @ A
    d = np.sqrt(np.diag(N))
    if not (d > 0).all():
        raise EstimationError("degenerate configuration: an element has no influence on the coplanarity")
    Ns = N / np.outer(d, d)
    cond = float(np.linalg.cond(Ns))
    if not np.isfinite(cond) or cond > 1e14:
        raise EstimationError(f"degenerate configuration: normal matrix condition number {cond:.3g}")
    Q = np.linalg.inv(N)
    q = np.sqrt(np.diag(Q))
    return PrecisionStructure(Q, Q / np.outer(q, q), cond, float(np.linalg.cond(N)))


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
    import cv2

    l, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    if len(l) < 5:
        raise EstimationError(f"too few tie points for the essential matrix: {len(l)} given, at least 5 needed")
    f1, f2 = _focals(focal_length_mm)
    # OpenCV camera frame: x right, y down, z forward = diag(1, -1, -1) * photo frame
    n1 = np.column_stack([l[:, 0] / f1, -l[:, 1] / f1])
    n2 = np.column_stack([r[:, 0] / f2, -r[:, 1] / f2])
    flag = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}[method]
    thr = threshold_mm / math.sqrt(f1 * f2)
    try:
        cv2.setRNGSeed(int(rng_seed))
        E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), method=flag, prob=confidence, threshold=thr)
    except cv2.error as err:
        raise EstimationError(f"OpenCV findEssentialMat failed: {err}") from err
    if E is None or E.shape[0] < 3:
        raise EstimationError(f"OpenCV found no essential matrix for {len(l)} tie points (degenerate configuration?)")
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


# ------------------------------------------------------------------ results
@dataclass(frozen=True)
class WesternForm:
    """Relative orientation as omega-phi-kappa of the right image and (bx, by, bz).

    The left photo frame is the model frame (Wolf & Dewitt's left-image
    convention: left omega = phi = kappa = 0). Angles in radians; R_rel =
    Rx(omega) Ry(phi) Rz(kappa) takes right photo vectors into the left photo
    frame (Dewitt's M = R_rel^T). ``by``, ``bz`` are scaled so that the base
    has the given ``bx``.
    """

    omega: float
    phi: float
    kappa: float
    bx: float
    by: float
    bz: float
    std_omega: float | None
    std_phi: float | None
    std_kappa: float | None
    std_by: float | None
    std_bz: float | None

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


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


def _inplane_rotation(l: NDArray, r: NDArray) -> float:
    """|angle| (rad) of the 2D similarity that best maps left photo points onto the right ones."""
    a = l - l.mean(axis=0)
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


@dataclass(frozen=True, eq=False)
class RelativeOrientation:
    """Relative orientation of a stereo pair (immutable; build with :meth:`from_points`).

    Attributes
    ----------
    system : str
    names : tuple of 5 str
    elements : (5,) float64
        Estimated elements, radians.
    covariance : (5, 5) float64 or None
        sigma0^2 (J^T W J)^-1, rad^2; ``None`` without redundancy (5 points).
    sigma0_mm : float or None
        Standard deviation of unit weight (one photo coordinate), mm.
    iterations : int
        Gauss-Newton iterations of the final adjustment.
    irls_iterations : int
        Robust reweightings (0 without robust estimation).
    converged : bool
    condition_number : float
        Of the column-scaled normal matrix (the correlation structure).
    condition_number_raw : float
        Of the normal matrix itself (all elements are angles, radians).
    focal_length_mm : (float, float)
    ids : tuple of str
    left_mm, right_mm : (N, 2) float64
        Input photo coordinates.
    parallax_mm : (N,) float64
        Residual vertical parallax, signed, mm.
    residual_mm : (N,) float64
        Normalised coplanarity residual (smallest total photo correction), mm.
    weights : (N,) float64
        Final weights (0 for rejected points).
    outlier : (N,) bool
    pixel_size_mm : float or None
        For pixel figures.
    robust : str
    scale_mm : float or None
        Final robust scale of the residuals (robust estimation only).
    initial_method : str
        ``"zero"``, ``"essential"`` or ``"given"``.
    elapsed_s : float
    """

    system: str
    names: tuple[str, ...]
    elements: NDArray[np.float64]
    covariance: NDArray[np.float64] | None
    sigma0_mm: float | None
    iterations: int
    irls_iterations: int
    converged: bool
    condition_number: float
    condition_number_raw: float
    focal_length_mm: tuple[float, float]
    ids: tuple[str, ...]
    left_mm: NDArray[np.float64]
    right_mm: NDArray[np.float64]
    parallax_mm: NDArray[np.float64]
    residual_mm: NDArray[np.float64]
    weights: NDArray[np.float64]
    outlier: NDArray[np.bool_]
    pixel_size_mm: float | None = None
    robust: str = "none"
    scale_mm: float | None = None
    initial_method: str = "zero"
    elapsed_s: float = 0.0
    left_px: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        for name in ("elements", "covariance", "left_mm", "right_mm", "parallax_mm", "residual_mm", "weights",
                     "outlier", "left_px"):
            a = getattr(self, name)
            if a is None:
                continue
            a = np.array(a, copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    # ------------------------------------------------------------ estimation
    @classmethod
    def from_points(
        cls,
        left_mm: ArrayLike,
        right_mm: ArrayLike,
        *,
        focal_length_mm: float | tuple[float, float],
        system: str = "left-image",
        robust: str = "none",
        initial: str | ArrayLike | dict[str, float] = "auto",
        ids: Sequence[str] | None = None,
        weights: ArrayLike | None = None,
        pixel_size_mm: float | None = None,
        options: RelativeOptions | None = None,
    ) -> RelativeOrientation:
        """Estimate the five elements of relative orientation by least squares.

        Parameters
        ----------
        left_mm, right_mm : (N, 2) float64
            Photo coordinates of N >= 5 tie points, mm, x right, y up, origin
            at the principal point (see :meth:`rectify.camera.Camera.photo_from_pixel`).
        focal_length_mm : float or (float, float)
            Principal distance of both cameras, or (left, right).
        system : {"basis", "left-image", "dobrynin-pimshina"}
        robust : {"none", "huber", "tukey", "hampel", "andrews"}
            ``"none"``: plain least squares on all points. Otherwise the
            essential-matrix RANSAC rejects gross errors first, then IRLS with
            the named psi function (scale: median |e| / 0.6745).
        initial : "auto", "zero", "essential", (5,) array or dict name -> value
            ``"auto"`` starts from zero angles (from the essential matrix when
            robust) and falls back to the essential matrix when the zero start
            fails or puts points behind a camera.
        ids : (N,) str, optional
        weights : (N,) float64, optional
            A-priori weights of the points.
        pixel_size_mm : float, optional
            For residuals in pixels and the RANSAC threshold.
        options : RelativeOptions, optional

        Returns
        -------
        RelativeOrientation

        Raises
        ------
        InvalidInputError
            Unknown system / robust / initial, bad shapes, NaN.
        EstimationError
            Fewer than 5 points, degenerate configuration (message names it).
        ConvergenceError
            No convergence within the iteration limit.

        Warns
        -----
        WeakGeometryWarning
            When the condition number exceeds ``options.weak_condition``.
        """
        t0 = time.perf_counter()
        opts = options or RelativeOptions()
        sys_ = _get_system(system)
        robust = str(robust).lower()
        if robust not in ROBUST_METHODS:
            raise InvalidInputError(f"unknown robust method {robust!r}; expected one of {list(ROBUST_METHODS)}")
        l, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
        n = len(l)
        if n < 5:
            raise EstimationError(f"too few tie points for relative orientation: {n} given, at least 5 needed")
        f1, f2 = _focals(focal_length_mm)
        if pixel_size_mm is not None and not (math.isfinite(pixel_size_mm) and pixel_size_mm > 0):
            raise InvalidInputError(f"`pixel_size_mm` must be finite and > 0; got {pixel_size_mm!r}")
        w0 = as_weights(weights, n)
        id_list = as_ids(ids, n)
        u1, u2 = _rays(l, f1), _rays(r, f2)
        pix = pixel_size_mm or _DEFAULT_PIXEL_MM

        essential_cache: dict[str, Any] = {}

        def essential():
            if not essential_cache:
                R_rel, bl, inl = relative_from_essential(l, r, (f1, f2), threshold_mm=opts.ransac_threshold_px * pix,
                                                         rng_seed=opts.rng_seed)
                essential_cache.update(p=sys_.elements_from_relative(R_rel, bl), inliers=inl)
            return essential_cache["p"], essential_cache["inliers"]

        # ---- initial values
        if isinstance(initial, str):
            init = initial.lower()
            if init not in INITIAL_METHODS:
                raise InvalidInputError(f"unknown initial {initial!r}; expected 'auto', 'zero', 'essential', "
                                        "5 values or a dict of elements")
            given = None
        else:
            init = "given"
            given = _initial_vector(sys_, initial)

        prior = w0.copy()
        if robust != "none":
            _, inl = essential()
            prior = np.where(inl, w0, 0.0)
            logger.info("RANSAC (essential matrix): %d of %d tie points kept", int(inl.sum()), n)
        starts: list[tuple[str, NDArray]] = []
        if init == "given":
            starts.append(("given", given))
        elif init == "zero":
            starts.append(("zero", np.zeros(5)))
        elif init == "essential" or (init == "auto" and robust != "none"):
            starts.append(("essential", None))
        elif _inplane_rotation(l, r) > opts.zero_start_max_rotation:
            starts.append(("essential", None))  # e.g. relative kappa near 180 deg: zero angles cannot serve
        else:
            starts += [("zero", np.zeros(5)), ("essential", None)]

        last_err: Exception | None = None
        result = None
        for label, p0 in starts:
            try:
                if p0 is None:
                    p0 = essential()[0]
                result = _solve(sys_, p0, u1, u2, prior, robust, opts)
                frac = _cheirality(sys_, result[0], u1, u2, result[1] > 0)
                if frac < 0.5:
                    raise EstimationError(
                        f"solution from the {label} start puts {100 * (1 - frac):.0f}% of the points behind a camera")
                used_label = label
                break
            except EstimationError as err:
                logger.info("start %r failed: %s", label, err)
                last_err = err
                result = None
        if result is None:
            raise last_err if last_err is not None else EstimationError("relative orientation failed")
        p, w, it, irls_it, scale, _irls_converged = result
        p = _wrap(p)

        # ---- precision
        e = _evaluate(sys_, p, u1, u2)
        W = w / e.gn2
        A = e.J * np.sqrt(W)[:, None]
        N = A.T @ A
        d = np.sqrt(np.diag(N))
        Ns = N / np.outer(d, d)
        cond = float(np.linalg.cond(Ns))
        cond_raw = float(np.linalg.cond(N))
        if cond > opts.weak_condition:
            warnings.warn(f"weak geometry: condition number {cond:.3g} of the normal matrix "
                          f"(> {opts.weak_condition:.0e}); the elements are poorly determined",
                          WeakGeometryWarning, stacklevel=2)
        res = e.normalised
        used = w > 0
        dof = int(used.sum()) - 5
        if dof > 0:
            sigma0 = float(math.sqrt(float(np.sum(w[used] * res[used] ** 2)) / dof))
            Qinv = np.linalg.inv(N)
            cov = sigma0 ** 2 * Qinv
        else:
            sigma0, cov = None, None
        if robust != "none":
            outl = (w <= 0) | (np.abs(res) > opts.outlier_threshold * (scale or 0.0)) if scale else (w <= 0)
        else:
            outl = np.zeros(n, dtype=bool)
        out = cls(
            system=sys_.name, names=sys_.names, elements=p, covariance=cov, sigma0_mm=sigma0,
            iterations=it, irls_iterations=irls_it, converged=True, condition_number=cond,
            condition_number_raw=cond_raw, focal_length_mm=(f1, f2), ids=id_list, left_mm=l, right_mm=r,
            parallax_mm=e.parallax, residual_mm=res, weights=w, outlier=outl, pixel_size_mm=pixel_size_mm,
            robust=robust, scale_mm=scale, initial_method=used_label,
            elapsed_s=time.perf_counter() - t0,
        )
        logger.info("relative orientation (%s): %d iterations, sigma0 %s mm", sys_.name, it, sigma0)
        return out

    @classmethod
    def from_pixels(cls, left_px: ArrayLike, right_px: ArrayLike, camera, *, camera_right=None,
                    **kwargs: Any) -> RelativeOrientation:
        """Like :meth:`from_points` for pixel coordinates (N, 2) and :class:`rectify.camera.Camera` objects.

        Pixels go to photo mm through the camera (principal point, distortion);
        the pixel size of the left camera is used for pixel figures.
        """
        cam_r = camera_right or camera
        l = camera.photo_from_pixel(left_px)
        r = cam_r.photo_from_pixel(right_px)
        kwargs.setdefault("pixel_size_mm", camera.pixel_size_mm)
        ro = cls.from_points(l, r, focal_length_mm=(camera.focal_length_mm, cam_r.focal_length_mm), **kwargs)
        return dataclasses.replace(ro, left_px=np.asarray(left_px, dtype=np.float64))

    # --------------------------------------------------------------- geometry
    @property
    def std_errors(self) -> NDArray[np.float64] | None:
        """(5,) standard errors of the elements, radians (``None`` without redundancy)."""
        return None if self.covariance is None else np.sqrt(np.diag(self.covariance))

    @property
    def correlation(self) -> NDArray[np.float64] | None:
        """(5, 5) correlation matrix of the elements."""
        if self.covariance is None:
            return None
        s = np.sqrt(np.diag(self.covariance))
        return self.covariance / np.outer(s, s)

    @property
    def element_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.names, self.elements)}

    @property
    def rotation_left(self) -> NDArray[np.float64]:
        """(3, 3) left photo vector (x, y, -f) -> model frame."""
        return SYSTEMS[self.system].geometry(self.elements)[0]

    @property
    def rotation_right(self) -> NDArray[np.float64]:
        """(3, 3) right photo vector (x, y, -f) -> model frame."""
        return SYSTEMS[self.system].geometry(self.elements)[1]

    @property
    def base(self) -> NDArray[np.float64]:
        """(3,) unit base, right projection centre minus left, model frame."""
        return SYSTEMS[self.system].geometry(self.elements)[2]

    @property
    def relative_rotation(self) -> NDArray[np.float64]:
        """(3, 3) right photo frame -> left photo frame (R_left^T R_right)."""
        return self.rotation_left.T @ self.rotation_right

    @property
    def base_left(self) -> NDArray[np.float64]:
        """(3,) unit base in the left photo frame."""
        return self.rotation_left.T @ self.base

    @property
    def n_points(self) -> int:
        return len(self.ids)

    @property
    def n_used(self) -> int:
        return int(np.count_nonzero((self.weights > 0) & ~self.outlier))

    @property
    def parallax_px(self) -> NDArray[np.float64]:
        """Residual vertical parallax in pixels (needs ``pixel_size_mm``)."""
        if self.pixel_size_mm is None:
            raise InvalidInputError("pixel size unknown: build with pixel_size_mm= or from_pixels()")
        return self.parallax_mm / self.pixel_size_mm

    def rms_parallax_mm(self) -> float:
        """RMS residual vertical parallax of the points used (not outliers), mm."""
        m = (self.weights > 0) & ~self.outlier
        return rms(self.parallax_mm[m])

    def residuals(self, left_mm: ArrayLike, right_mm: ArrayLike) -> NDArray[np.float64]:
        """Residual vertical parallax (N,), mm, of other tie points under this orientation."""
        l, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
        f1, f2 = self.focal_length_mm
        return _evaluate(SYSTEMS[self.system], self.elements, _rays(l, f1), _rays(r, f2), jac=False).parallax

    def to_system(self, system: str) -> NDArray[np.float64]:
        """Elements (5,) of the same relative geometry in another system (no re-adjustment)."""
        return _get_system(system).elements_from_relative(self.relative_rotation, self.base_left)

    def western(self, bx: float = 1.0) -> WesternForm:
        """Omega-phi-kappa of the right image in the left photo frame and (bx, by, bz), with std errors.

        Standard errors are propagated from the covariance of the elements
        with the (central-difference) Jacobian of the conversion; the
        propagation is exact to first order since both forms parametrise the
        same five degrees of freedom.
        """
        sys_ = SYSTEMS[self.system]

        def conv(p):
            R1, R2, b = sys_.geometry(p)
            ang = angles_from_matrix(R1.T @ R2, "omega-phi-kappa")
            bl = R1.T @ b
            return np.array([*ang, bl[1] / bl[0], bl[2] / bl[0]])

        v = conv(self.elements)
        if self.covariance is not None:
            h = 1e-7
            G = np.empty((5, 5))
            for k in range(5):
                dp = np.zeros(5)
                dp[k] = h
                G[:, k] = (conv(self.elements + dp) - conv(self.elements - dp)) / (2 * h)
            C = G @ self.covariance @ G.T
            s = np.sqrt(np.diag(C))
            std = [float(s[0]), float(s[1]), float(s[2]), float(abs(bx) * s[3]), float(abs(bx) * s[4])]
        else:
            std = [None] * 5
        return WesternForm(float(v[0]), float(v[1]), float(v[2]), float(bx), float(bx * v[3]), float(bx * v[4]),
                           *std)

    # ------------------------------------------------------------- reporting
    def residual_table(self, *, units: str | None = None) -> ResidualTable:
        """Per-point residual vertical parallax as a :class:`ResidualTable`.

        Component ``py``: observed = residual parallax, adjusted = 0 (the
        oriented pair has none), so v = -parallax. Units are px when the pixel
        size is known, mm otherwise (or as ``units`` says). The table's sigma0
        is that of the parallax (sqrt(sum w q^2 / (n - 5))); ``sigma0_mm`` of one
        photo coordinate is in ``extra``. Positions are the left pixels when
        the orientation was built by :meth:`from_pixels`.
        """
        if units is None:
            units = "px" if self.pixel_size_mm is not None else "mm"
        if units not in ("px", "mm"):
            raise InvalidInputError(f"`units` must be 'px' or 'mm'; got {units!r}")
        q = self.parallax_px if units == "px" else self.parallax_mm
        return ResidualTable(
            step=f"relative orientation ({self.system})", ids=self.ids, observed=q.reshape(-1, 1),
            adjusted=np.zeros((self.n_points, 1)), units=units, components=("py",), weights=self.weights,
            outlier=self.outlier, n_params=5, position_px=self.left_px,
            extra={"iterations": self.iterations, "irls_iterations": self.irls_iterations,
                   "condition_number": self.condition_number, "system": self.system,
                   "sigma0_mm": self.sigma0_mm, "robust": self.robust},
        )

    def summary(self) -> dict[str, Any]:
        """Short figures for the CLI and reports."""
        out = {
            "system": self.system, "n_points": self.n_points, "n_used": self.n_used,
            "n_outliers": int(self.outlier.sum()), "iterations": self.iterations,
            "irls_iterations": self.irls_iterations, "sigma0_mm": self.sigma0_mm,
            "rms_parallax_mm": self.rms_parallax_mm(), "condition_number": self.condition_number,
            "initial": self.initial_method, "robust": self.robust,
        }
        if self.pixel_size_mm is not None:
            out["rms_parallax_px"] = out["rms_parallax_mm"] / self.pixel_size_mm
        return out

    def to_dict(self) -> dict[str, Any]:
        """The dict form of the relative orientation JSON (see :mod:`stereo.formats` and ``docs/formats.md``)."""
        corr = self.correlation
        std = self.std_errors
        wf = self.western()
        pts = []
        for i in range(self.n_points):
            item = {"id": self.ids[i], "residual_mm": float(self.parallax_mm[i]),
                    "weight": float(self.weights[i]), "outlier": bool(self.outlier[i])}
            if self.pixel_size_mm is not None:
                item["residual_px"] = float(self.parallax_mm[i] / self.pixel_size_mm)
            pts.append(item)
        return {
            "system": self.system,
            "elements": self.element_dict,
            "std_errors": None if std is None else {k: float(v) for k, v in zip(self.names, std)},
            "correlation": {"names": list(self.names), "matrix": None if corr is None else corr.tolist()},
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "sigma0_mm": self.sigma0_mm,
            "iterations": self.iterations,
            "irls_iterations": self.irls_iterations,
            "converged": self.converged,
            "condition_number": self.condition_number,
            "rotation_left": self.rotation_left.tolist(),
            "rotation_right": self.rotation_right.tolist(),
            "base": self.base.tolist(),
            "relative": {"order": "omega-phi-kappa", "omega": wf.omega, "phi": wf.phi, "kappa": wf.kappa,
                         "bx": wf.bx, "by": wf.by, "bz": wf.bz,
                         "std_omega": wf.std_omega, "std_phi": wf.std_phi, "std_kappa": wf.std_kappa,
                         "std_by": wf.std_by, "std_bz": wf.std_bz},
            "focal_length_mm": self.focal_length_mm[0] if self.focal_length_mm[0] == self.focal_length_mm[1]
            else list(self.focal_length_mm),
            "pixel_size_mm": self.pixel_size_mm,
            "robust": self.robust,
            "initial": self.initial_method,
            "rms_parallax_mm": self.rms_parallax_mm(),
            "n_points": self.n_points,
            "n_used": self.n_used,
            "points": pts,
        }


@dataclass(frozen=True, eq=False)
class RelativeGeometry:
    """What intersection needs from a relative orientation: the two rotations, the base, the focal lengths.

    Built one way, from the relative orientation's dict form (:meth:`RelativeOrientation.to_dict`, which
    is also the content of the relative orientation JSON read by :func:`stereo.formats.read_relative`).

    Attributes
    ----------
    rotation_left, rotation_right : (3, 3) float64
        Photo vector (x, y, -f) -> model frame.
    base : (3,) float64
        Unit base (right projection centre minus left), model frame.
    focal_length_mm : (float, float)
        Left and right principal distance, mm.
    sigma0_mm : float or None
        Standard deviation of unit weight of one photo coordinate, mm.
    pixel_size_mm : float or None
    system : str
    raw : dict
        The whole dict (points, camera, ...).
    """

    rotation_left: NDArray[np.float64]
    rotation_right: NDArray[np.float64]
    base: NDArray[np.float64]
    focal_length_mm: tuple[float, float]
    sigma0_mm: float | None = None
    pixel_size_mm: float | None = None
    system: str = ""
    raw: dict[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "relative orientation") -> RelativeGeometry:
        """From the dict form of a relative orientation; ``source`` names it in errors (e.g. the file)."""
        missing = [k for k in ("rotation_left", "rotation_right", "base", "focal_length_mm") if k not in d]
        if missing:
            raise InvalidInputError(f"{source} is not a relative orientation JSON: missing {missing}")
        f = d["focal_length_mm"]
        f = (float(f[0]), float(f[1])) if isinstance(f, list) else (float(f), float(f))
        return cls(np.array(d["rotation_left"], float), np.array(d["rotation_right"], float),
                   np.array(d["base"], float), f, d.get("sigma0_mm"), d.get("pixel_size_mm"),
                   d.get("system", ""), d)

    @classmethod
    def from_relative(cls, ro: RelativeOrientation) -> RelativeGeometry:
        """From an estimated :class:`RelativeOrientation` (through its dict form)."""
        return cls.from_dict(ro.to_dict())


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
