"""Systems of relative orientation elements and the coplanarity condition (see :mod:`stereo.relative`).

The three systems (:data:`SYSTEMS`) parametrise the two rotations and the unit base of a pair
with five angles each; :func:`coplanarity` evaluates the misclosure F = b . (r1 x r2) and its
analytic Jacobian; :func:`precision_structure` the a-priori cofactor and correlation matrices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry import lsq
from rectify.geometry.points import as_pair
from rectify.geometry.rotation import angles_from_matrix, check_rotation

__all__ = ["METHOD_SYSTEMS", "SYSTEMS", "PrecisionStructure", "System", "coplanarity", "get_system",
           "precision_structure"]


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
    E = [_rot(ax, a) for ax, a in zip(axes, angles, strict=True)]
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
    turn_deg: int = 0

    @property
    def turn(self) -> NDArray[np.float64]:
        """(3, 3) rotation of the photo frames by ``turn_deg`` about their z axis (photo vector -> turned
        photo vector); the elements refer to the turned frames (identity for ``turn_deg = 0``)."""
        c, s = round(math.cos(math.radians(self.turn_deg))), round(math.sin(math.radians(self.turn_deg)))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

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
        if self.name in ("basis", "universal"):  # alpha1, kappa1, alpha2, omega2, kappa2
            R1, d1 = _chain("yxz", [p[0], 0.0, p[1]])
            R2, d2 = _chain("yxz", [p[2], p[3], p[4]])
            b = np.array([1.0, 0.0, 0.0])
            dR1[0], dR1[1] = d1[0], d1[2]
            dR2[2], dR2[3], dR2[4] = d2
        elif self.name in ("left-image", "projective"):  # tau, nu, alpha2, omega2, kappa2
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
            if self.turn_deg:  # elements of the turned photo frames: R = R' Q
                Q = self.turn
                R1, R2, dR1, dR2 = R1 @ Q, R2 @ Q, dR1 @ Q, dR2 @ Q
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
        if self.name in ("left-image", "projective"):
            tau = math.atan2(bc[1], bc[0])
            nu = math.atan2(bc[2], math.hypot(bc[0], bc[1]))
            a2, w2, k2 = angles_from_matrix(Rr, "phi-omega-kappa")
            return np.array([tau, nu, a2, w2, k2])
        if self.name in ("basis", "universal"):
            a1 = math.asin(max(-1.0, min(1.0, bc[2])))
            k1 = math.atan2(-bc[1], bc[0])
            M = _rot("y", a1) @ _rot("z", k1)
            a2, w2, k2 = angles_from_matrix(M @ Rr, "phi-omega-kappa")
            return np.array([a1, k1, a2, w2, k2])
        if self.turn_deg:  # the relative geometry in the turned photo frames
            Q = self.turn
            Rr, bc = Q @ Rr @ Q.T, Q @ bc
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
                        a -= float(g / dg)
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


#: The dobrynin-pimshina system on photo frames turned by 90, 180 or 270 degrees about z (issue 12): its
#: model X axis lies in the left photo's xz plane (chi1 = 0), so a base along the photo y axis (pairs from
#: adjacent strips) or against x has no solution in the unturned frames. Chosen automatically
#: (:func:`dobrynin_pimshina_for_base`); the names are stored in the relative orientation JSON.
TURNED_SYSTEMS: dict[str, System] = {
    f"dobrynin-pimshina-rot{t}": System(f"dobrynin-pimshina-rot{t}", SYSTEMS["dobrynin-pimshina"].names,
                                        "omega-alpha-chi", ("nu", "chi1", "omega2"), turn_deg=t)
    for t in (90, 180, 270)}


#: Systems named by the method that finds them (seed 003, 3.2.1-3.2.2; docs/universal.md), not by new
#: elements: ``universal`` (linear iterations with the p, q, r matrices and Gram-Schmidt,
#: :mod:`stereo.relative.universal`) reports the elements of the ``basis`` system (the seed's first
#: scheme, fixed base), ``projective`` (the fundamental matrix, :mod:`stereo.relative.projective`) those
#: of the ``left-image`` system. Kept apart from :data:`SYSTEMS` (the three systems of elements).
METHOD_SYSTEMS: dict[str, System] = {
    "universal": System("universal", SYSTEMS["basis"].names, "alpha-omega-kappa", ("tau", "nu", "omega1")),
    "projective": System("projective", SYSTEMS["left-image"].names, "alpha-omega-kappa",
                         ("alpha1", "omega1", "kappa1")),
}


def dobrynin_pimshina_for_base(base_left: ArrayLike) -> System:
    """The dobrynin-pimshina system whose turned photo frames put ``base_left`` (left photo frame) nearest
    to +x: unturned when the base runs along +x, turned by 270 degrees for +y, 90 for -y, 180 for -x."""
    b = np.asarray(base_left, dtype=np.float64).reshape(3)
    along = {0: b[0], 90: -b[1], 180: -b[0], 270: b[1]}  # x component of Rz(t) b
    t = max(along, key=lambda k: along[k])
    return SYSTEMS["dobrynin-pimshina"] if t == 0 else TURNED_SYSTEMS[f"dobrynin-pimshina-rot{t}"]


def get_system(system: str | System) -> System:
    """The :class:`System` named ``system`` (or ``system`` itself); the turned dobrynin-pimshina
    systems (:data:`TURNED_SYSTEMS`) are found too."""
    if isinstance(system, System):
        return system
    if str(system) in TURNED_SYSTEMS:
        return TURNED_SYSTEMS[str(system)]
    if str(system) in METHOD_SYSTEMS:
        return METHOD_SYSTEMS[str(system)]
    try:
        return SYSTEMS[str(system)]
    except KeyError:
        raise InvalidInputError(f"unknown system {system!r}; expected one of "
                                f"{[*SYSTEMS, *METHOD_SYSTEMS]}") from None


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
    s = get_system(system)
    p = np.asarray(elements, dtype=np.float64).reshape(5)
    lm, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    f1, f2 = _focals(focal_length_mm)
    e = _evaluate(s, p, _rays(lm, f1), _rays(r, f2))
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
    s = get_system(system)
    p = np.asarray(elements, dtype=np.float64).reshape(5)
    lm, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
    f1, f2 = _focals(focal_length_mm)
    e = _evaluate(s, p, _rays(lm, f1), _rays(r, f2))
    A = e.J / np.sqrt(e.gn2)[:, None]
    N, _ = lsq.normal_equations(A)
    if not (np.diag(N) > 0).all():
        raise EstimationError("degenerate configuration: an element has no influence on the coplanarity")
    cond, cond_raw = lsq.condition_numbers(N)
    if not np.isfinite(cond) or cond > 1e14:
        raise EstimationError(f"degenerate configuration: normal matrix condition number {cond:.3g}")
    Q = lsq.cofactor(N)
    return PrecisionStructure(Q, lsq.correlation(Q), cond, cond_raw)


