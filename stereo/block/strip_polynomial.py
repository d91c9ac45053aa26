"""Polynomial correction of strip deformation (seed 002, 3.1.1, eqs. 3.8-3.15).

A strip joined model by model (independent models, 3.1.1, or partially dependent models, 3.2)
is not similar to the terrain when it is long: the residual systematic errors of each relative
orientation accumulate into a bend and a twist. Seed 002 orients the joined strip by a spatial
similarity to the control (eq. 3.3) and then removes the deformation by polynomials of the plan
coordinates of the deformed model (eq. 3.8):

    R_G,i = R'_G,i + D_i diag(B),    D_i = E (x) d(x_i, y_i)

one polynomial per ground coordinate; the coefficients B come from the control points, where
the free terms are L_i = R_G,i - R'_G,i (eqs. 3.10-3.12), by least squares with the same
matrix Q = sum d d^T for the three coordinates (eqs. 3.13-3.15). Seed 002 counts six terms per
coordinate (18 unknowns, at least six control points): the complete quadratic. Here the plan
coordinates are those of the strip, ``u`` along it and ``v`` across, both divided by the half
length of the strip (origin at the mean projection centre), and three degrees are offered:

======  ===========================================  =====
degree  terms d(u, v)                                count
======  ===========================================  =====
1       1, u, v                                       3
2       1, u, v, u^2, uv, v^2 (seed 002)              6
3       1, u, v, u^2, uv, v^2, u^3, u^2 v             8
======  ===========================================  =====

(degree 3 adds the cubic bend along the strip and its twist, the classic strip terms; a strip
is too narrow for the cubic terms across it). Optionally the fit is repeated with Huber weights
on all 3n residuals together (seed 002, after eq. 3.15).

:func:`find_strips` groups the models of a block into strips: chains of models whose bases run
in the block's dominant flight direction (within :data:`STRIP_ANGLE_DEG`), linked by a shared
image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.robust import robust_scale

__all__ = ["STRIP_DEGREES", "STRIP_ANGLE_DEG", "Strip", "StripPolynomial", "check_strip_control", "find_strips",
           "strip_terms"]

F64 = NDArray[np.float64]

#: degrees of the strip polynomial and their number of terms per coordinate
STRIP_DEGREES = {1: 3, 2: 6, 3: 8}
#: a model belongs to a strip when its base is within this angle of the dominant flight direction, degrees
STRIP_ANGLE_DEG = 25.0
#: Huber's constant of the robust refit, in robust standard deviations
HUBER_K = 1.5


def strip_terms(uv: F64, degree: int) -> F64:
    """(N, n_terms) the polynomial terms d(u, v) of ``degree`` (see the module table) at (N, 2) strip coordinates."""
    if degree not in STRIP_DEGREES:
        raise InvalidInputError(f"strip polynomial degree must be one of {sorted(STRIP_DEGREES)}; got {degree!r}")
    u, v = uv[:, 0], uv[:, 1]
    cols = [np.ones_like(u), u, v]
    if degree >= 2:
        cols += [u * u, u * v, v * v]
    if degree >= 3:
        cols += [u ** 3, u * u * v]
    return np.column_stack(cols)


def check_strip_control(n_control: NDArray[np.int64], degree: int, label: str) -> None:
    """Raise unless each coordinate has as many control values (``n_control``, (3,)) as the polynomial has terms."""
    nt = STRIP_DEGREES.get(degree)
    if nt is None:
        raise InvalidInputError(f"strip polynomial degree must be one of {sorted(STRIP_DEGREES)}; got {degree!r}")
    n = np.asarray(n_control)
    if (n < nt).any():
        k = int(np.argmin(n))
        raise EstimationError(f"the degree-{degree} strip polynomial needs at least {nt} control points with "
                              f"{'xyz'[k]} per strip (seed 002, eq. 3.12: {nt} coefficients per coordinate); "
                              f"{label} has {int(n[k])}")


@dataclass(frozen=True)
class Strip:
    """A strip of a model block: its images in flight order and its models (indices into ``tree``)."""

    images: tuple[int, ...]
    models: tuple[int, ...]


def find_strips(tree: Sequence[tuple[int, int]], positions: F64, *, angle_deg: float = STRIP_ANGLE_DEG
                ) -> list[Strip]:
    """Group the models into strips by the direction of their bases.

    Parameters
    ----------
    tree : sequence of (int, int)
        The models as image index pairs.
    positions : (n, 3) float64
        Projection centres of the images (any frame whose x, y plane is the terrain's).
    angle_deg : float
        Largest angle between a strip model's base and the dominant direction, degrees.

    Returns
    -------
    list of Strip
        Sorted by their first image; the images of each in order along the strip.
    """
    pos = np.asarray(positions, dtype=np.float64)
    d = np.array([pos[b, :2] - pos[a, :2] for a, b in tree]).reshape(-1, 2)
    theta = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    diff = np.abs(theta[:, None] - theta[None, :])
    diff = np.minimum(diff, np.pi - diff)
    tol = math.radians(angle_deg)
    dominant = int(np.argmax((diff <= tol).sum(axis=1))) if len(tree) else 0
    along = (diff[dominant] <= tol) if len(tree) else np.zeros(0, bool)
    n = len(pos)
    rows = [a for (a, _b), s in zip(tree, along, strict=True) if s]
    cols = [b for (_a, b), s in zip(tree, along, strict=True) if s]
    adj = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _ncomp, lab = connected_components(adj, directed=False)
    axis = np.array([math.cos(theta[dominant]), math.sin(theta[dominant])]) if len(tree) else np.array([1.0, 0.0])
    strips = []
    for c in np.unique(lab):
        models = tuple(int(j) for j in np.flatnonzero(along) if lab[tree[int(j)][0]] == c)
        if not models:
            continue
        imgs = np.flatnonzero(lab == c)
        imgs = imgs[np.argsort(pos[imgs, :2] @ axis, kind="stable")]
        strips.append(Strip(tuple(int(i) for i in imgs), models))
    return sorted(strips, key=lambda s: s.images[0])


@dataclass(frozen=True, eq=False)
class StripPolynomial:
    """Seed 002's polynomial correction of one strip (eq. 3.8), fitted to control (eqs. 3.10-3.15).

    Attributes
    ----------
    degree : int
        1, 2 or 3 (:data:`STRIP_DEGREES`).
    origin : (2,) float64
        Plan origin of the strip coordinates (ground frame).
    axis : (2,) float64
        Unit plan direction of ``u`` (along the strip); ``v`` is 90 degrees to its left.
    half_length : float
        Divides the plan offsets (ground units).
    coefficients : (3, n_terms) float64
        B of dX, dY, dZ, ground units.
    covariance : (3, n_terms, n_terms) float64
        sigma0^2 Q^-1 of each coordinate's coefficients.
    sigma0 : float
        RMS fit residual of unit weight (control weights 1: ground units); NaN without redundancy.
    n_control : (3,) int64
        Control values used per coordinate.
    residuals : (K, 3) float64
        Corrected minus given at the control points (NaN for components not given).
    weights : (K, 3) float64
        Final Huber weights (1 without the robust refit; 0 where not given).
    """

    degree: int
    origin: F64
    axis: F64
    half_length: float
    coefficients: F64
    covariance: F64
    sigma0: float
    n_control: NDArray[np.int64]
    residuals: F64
    weights: F64

    def __post_init__(self) -> None:
        for name in ("origin", "axis", "coefficients", "covariance", "n_control", "residuals", "weights"):
            a = np.array(getattr(self, name), copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    def strip_coordinates(self, points: F64) -> F64:
        """(N, 2) scaled strip coordinates (u along, v across) of (N, 3) ground points."""
        p = np.asarray(points, dtype=np.float64)[:, :2] - self.origin
        a = self.axis
        return np.column_stack([p @ a, p @ np.array([-a[1], a[0]])]) / self.half_length

    def correction(self, points: F64) -> F64:
        """(N, 3) D_i diag(B) at the (N, 3) deformed points (eq. 3.8), ground units."""
        return strip_terms(self.strip_coordinates(points), self.degree) @ self.coefficients.T

    def correct(self, points: F64) -> F64:
        """(N, 3) corrected points R_G = R'_G + D diag(B)."""
        p = np.asarray(points, dtype=np.float64)
        return p + self.correction(p)

    def variance(self, points: F64) -> F64:
        """(N, 3) variance of the correction of each coordinate (from the coefficients' covariance)."""
        D = strip_terms(self.strip_coordinates(points), self.degree)
        return np.stack([np.einsum("ni,ij,nj->n", D, self.covariance[k], D) for k in range(3)], axis=1)

    def jacobian(self, points: F64, step: float = 1e-3) -> F64:
        """(N, 3, 3) derivative of the corrected point by the deformed one (numerical, ``step`` ground units)."""
        p = np.asarray(points, dtype=np.float64)
        J = np.repeat(np.eye(3)[None], len(p), axis=0)
        for k in range(2):
            e = np.zeros(3)
            e[k] = step
            J[:, :, k] += (self.correction(p + e) - self.correction(p - e)) / (2 * step)
        return J

    @classmethod
    def from_points(cls, deformed: F64, given: F64, *, degree: int, origin: F64, axis: F64, half_length: float,
                    robust: bool = False, label: str = "the strip") -> StripPolynomial:
        """Fit the correction: ``given - deformed = D b`` per coordinate (eqs. 3.10-3.15).

        Parameters
        ----------
        deformed : (K, 3) float64
            Control points in the deformed strip (after its similarity), ground frame.
        given : (K, 3) float64
            Their given coordinates; NaN for a component not given (plan of a height point, height
            of a plan point).
        degree : int
        origin, axis, half_length
            The strip coordinates (see the attributes).
        robust : bool
            Repeat the fit with Huber weights on the 3K residuals (seed 002, after eq. 3.15).
        label : str
            Names the strip in errors.

        Raises
        ------
        EstimationError
            Fewer control values for a coordinate than terms (the named minimum), or control that does
            not determine the polynomial (all on a line across which it must vary).
        """
        nt = STRIP_DEGREES.get(degree)
        if nt is None:
            raise InvalidInputError(f"strip polynomial degree must be one of {sorted(STRIP_DEGREES)}; got {degree!r}")
        dfm = np.asarray(deformed, dtype=np.float64).reshape(-1, 3)
        giv = np.asarray(given, dtype=np.float64).reshape(-1, 3)
        if not (math.isfinite(half_length) and half_length > 0):
            raise InvalidInputError(f"`half_length` must be a finite number > 0; got {half_length!r}")
        have = np.isfinite(giv) & np.asarray(np.isfinite(dfm).all(axis=1), dtype=bool)[:, None]
        n_ctrl = have.sum(axis=0)
        check_strip_control(n_ctrl, degree, label)
        a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        probe = cls(degree, np.asarray(origin, dtype=np.float64)[:2], a, float(half_length), np.zeros((3, nt)),
                    np.zeros((3, nt, nt)), float("nan"), n_ctrl, np.zeros((0, 3)), np.zeros((0, 3)))
        D = strip_terms(probe.strip_coordinates(dfm), degree)
        L = np.where(have, giv - dfm, 0.0)
        w = have.astype(np.float64)
        coef = np.zeros((3, nt))
        Qs = np.zeros((3, nt, nt))
        for rnd in range(6 if robust else 1):
            for k in range(3):
                Nk = (D * w[:, k, None]).T @ D
                if np.linalg.matrix_rank(Nk, tol=1e-10 * max(float(np.abs(Nk).max()), 1e-300)) < nt:
                    raise EstimationError(
                        f"the control points of {label} do not determine the degree-{degree} strip polynomial of "
                        f"{'xyz'[k]} (rank {np.linalg.matrix_rank(Nk)} < {nt}): spread them across the strip as "
                        "well as along it")
                Qs[k] = np.linalg.inv(Nk)
                coef[k] = Qs[k] @ (D * w[:, k, None]).T @ L[:, k]
            v = D @ coef.T - L
            if rnd == 5 or not robust:
                break
            sc = robust_scale(v[have])
            if sc <= 0:
                break
            u = np.abs(v) / (HUBER_K * sc)
            w = np.where(have, np.minimum(1.0, 1.0 / np.maximum(u, 1e-300)), 0.0)
        v = D @ coef.T - L
        dof = int(have.sum()) - 3 * nt
        vpv = float(np.sum(w * v * v))
        sigma0 = math.sqrt(vpv / dof) if dof > 0 else float("nan")
        s02 = sigma0 ** 2 if dof > 0 else 0.0
        return cls(degree, probe.origin, a, float(half_length), coef, Qs * s02, sigma0, n_ctrl,
                   np.where(have, v, np.nan), w)
