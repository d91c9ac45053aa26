"""Kushtin's cotangent four-point method and the eq. (2) helpers.

The cotangent four-point method (seed 001, eq. 2)
-------------------------------------------------
V. I. Kushtin's method maps a point without solving a linear system. Take
two control points a, b as the *base*. A point p defines the signed
cotangents of the angles at a and b between the base and the rays to p,

    cot B = (d . (p - a)) / (d x (p - a)),
    cot G = ((a - b) . (p - b)) / (d x (p - b)),      d = b - a,

where ``u . v`` is the dot and ``u x v = u_x v_y - u_y v_x`` the 2D cross
product. Each cotangent is an affine coordinate on the pencil of lines
through its vertex, with the base line at infinity. A projective map sends
the pencil at a to the pencil at a0 and the base line to the base line, so
it acts *affinely* on the cotangent: the cross-ratio of the four rays
(base, to c, to e, to p) is the ratio of cotangent differences

    (cot B_p - cot B_c) / (cot B_e - cot B_c),

and it is invariant. With the two remaining control points c, e this carries
the cotangents from the source to the target plane,

    cot B0_p = cot B0_c + (cot B_p - cot B_c) (cot B0_e - cot B0_c) / (cot B_e - cot B_c),

(likewise for G), and eq. (2) intersects the two rays in the target plane:

    x0 = xa0 + ((xb0 - xa0) cot B0 - (yb0 - ya0)) / (cot B0 + cot G0)
    y0 = ya0 + ((yb0 - ya0) cot B0 + (xb0 - xa0)) / (cot B0 + cot G0)

**Sign correction.** Seed 001 prints the y-line with ``- (x2 - x1)``. That is
inconsistent: the offset ``(-(y2-y1), -(x2-x1))`` is not perpendicular to the
base, so the printed formula misplaces every point not on the base line
(checked numerically against the homography in
``tests/rectify/test_projective.py::test_printed_eq2_is_wrong``). The
corrected y-line has ``+ (x2 - x1)``. The formula then holds in any
rectangular frame with the *signed* cotangents above (cross product
``x_u y_v - y_u x_v`` of that frame's axes): with positive angles it
describes a point that lies on the side of the base reached by turning the
base direction from the x axis towards the y axis, i.e. to the **right** of
a -> b in the pixel frame (x right, y down) and in the geodetic frame
(x north, y east), to the left in a mathematical frame (x right, y up).

Eq. (2) divides by zero for points on the base line (cot B -> inf), and
the whole chain can lose accuracy through the cross-ratio denominators
``cot B_e - cot B_c`` and through a small angle at the target point between
the two rays. For every point, :class:`CotangentFourPoint` estimates the
rounding error of the whole chain for each of the six pairs of control
points (the measure M of :meth:`CotangentFourPoint.error_bound`, derived
there), uses the pair with the smallest one, and raises EstimationError
only when even that one exceeds :data:`COT_MAX_REL_ERROR` of the target
extent. The computation is vectorised in blocks of points: the measure of
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, ClassVar, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError
from rectify.geometry.points import as_pair, as_points, as_weights, check_distinct, check_no_three_collinear
from rectify.geometry.transforms.base import _CHUNK, F64, Transform

__all__ = ["CotangentFourPoint", "COT_MAX_REL_ERROR", "PAIRS", "base_cotangents", "printed_eq2", "corrected_eq2"]

#: Largest accepted estimated rounding error of the cotangent method for a
#: point, relative to ``|p0 - centre0| + extent0`` (target plane: distance of
#: the image from the centroid of the target control points plus their
#: extent); above it the point raises EstimationError. See
#: :meth:`CotangentFourPoint.error_bound`.
COT_MAX_REL_ERROR = 1e-9

_EPS = float(np.finfo(np.float64).eps)

_SEL_CHUNK = 1 << 13  # points per block of the pair selection: its float32 (6, n) work arrays stay in cache


_PAIRS: tuple[tuple[int, int, int, int], ...] = cast(tuple[tuple[int, int, int, int], ...], tuple(
    (a, b, *[k for k in range(4) if k not in (a, b)]) for a, b in combinations(range(4), 2)))

#: The six base pairs (a, b) of the cotangent method, as indices of the control points.
PAIRS: tuple[tuple[int, int], ...] = tuple((a, b) for a, b, _, _ in _PAIRS)


def _cot_tables(src: F64, dst: F64) -> dict[str, Any]:
    """Per-base-pair constants of the cotangent method and of its error measure.

    Source coordinates are taken relative to ``centre`` (the centroid of the
    four source control points) for numerical range. For base pair
    k = (a, b) with carriers (c, e), d = b - a:

    - ``cross(d, p - a) = dx*y - dy*x + e1`` and ``dot(d, p - a) = dx*x + dy*y + e2``;
      ``dot(a - b, p - b) = b2 - dot(d, p - a)`` with ``b2 = |d|^2``, so
      ``cot B = dot / cross`` and ``cot G = (b2 - dot) / cross``;
    - the carriage ``cot0 = k * cot + m`` for B and G (through c and e);
    - the target base ``xa0, ya0, dx0, dy0`` for eq. (2);
    - ``sel_w`` (24, 2), ``sel_c`` (24,) float32: the affine forms
      ``C' = cross / b2``, ``NB' = cot B0 * C'``, ``NG' = cot G0 * C'`` and
      ``T'' = (NB' + NG') / sqrt(b0)`` of the six pairs (rows 0-5, 6-11,
      12-17, 18-23), and ``sel_alpha``, ``sel_kb``, ``sel_kg``, ``sel_gamma``
      (6, 1) float32: the constants of the error measure
      (see :meth:`CotangentFourPoint.error_bound`).
    """
    centre = src.mean(axis=0)
    sc = src - centre
    ext = float(2.0 * np.abs(sc).max())            # source extent L
    consts = []
    forms = []                                      # per pair: C', NB', NG', T'' as (w_x, w_y, c)
    meas = []                                       # per pair: alpha, K_B, K_G, gamma
    for a, b, c, e in _PAIRS:
        pa, pb = sc[a], sc[b]
        dx, dy = pb - pa
        b2 = dx * dx + dy * dy
        e1 = dy * pa[0] - dx * pa[1]
        e2 = -(dx * pa[0] + dy * pa[1])
        d0 = dst[b] - dst[a]
        b20 = d0[0] ** 2 + d0[1] ** 2
        cot = {}
        for j in (c, e):
            cr = dx * sc[j, 1] - dy * sc[j, 0] + e1
            da = dx * sc[j, 0] + dy * sc[j, 1] + e2
            q0 = dst[j] - dst[a]
            cr0 = d0[0] * q0[1] - d0[1] * q0[0]
            da0 = d0[0] * q0[0] + d0[1] * q0[1]
            cot[j] = (da / cr, (b2 - da) / cr, da0 / cr0, (b20 - da0) / cr0)
        (bc, gc, bc0, gc0), (be, ge, be0, ge0) = cot[c], cot[e]
        # cot0 = cot0_c + (cot - cot_c) (cot0_e - cot0_c) / (cot_e - cot_c)  ==  k cot + m
        kb = (be0 - bc0) / (be - bc)
        kg = (ge0 - gc0) / (ge - gc)
        mb, mg = bc0 - kb * bc, gc0 - kg * gc
        consts.append((dx, dy, e1, e2, b2, kb, mb, kg, mg, dst[a, 0], dst[a, 1], d0[0], d0[1]))
        # error measure: amplification of the cross-ratio denominators and carriage constants
        # rounding of a control point's cotangent ~ moving the point by eps L: |d cot| = eps (1 + cot^2) L / r
        ext0 = float(2.0 * np.abs(dst - dst.mean(axis=0)).max())
        rs = {j: (np.hypot(*(sc[j] - pa)), np.hypot(*(sc[j] - pb)),
                  np.hypot(*(dst[j] - dst[a])), np.hypot(*(dst[j] - dst[b]))) for j in (c, e)}
        with np.errstate(divide="ignore", invalid="ignore"):
            alpha_b = 1.0 + (((1 + be * be) / rs[e][0] + (1 + bc * bc) / rs[c][0]) * ext / abs(be - bc)
                             + ((1 + be0 * be0) / rs[e][2] + (1 + bc0 * bc0) / rs[c][2]) * ext0 / abs(be0 - bc0))
            alpha_g = 1.0 + (((1 + ge * ge) / rs[e][1] + (1 + gc * gc) / rs[c][1]) * ext / abs(ge - gc)
                             + ((1 + ge0 * ge0) / rs[e][3] + (1 + gc0 * gc0) / rs[c][3]) * ext0 / abs(ge0 - gc0))
        k_b = alpha_b * (abs(mb) + abs(kb * bc)) + abs(bc0)
        k_g = alpha_g * (abs(mg) + abs(kg * gc)) + abs(gc0)
        b0 = math.sqrt(b20)
        cf = np.array([-dy, dx, e1]) / b2                      # C' = cross / b2 = h / b
        df = np.array([dx, dy, e2]) / b2                       # D' = dot / b2
        nb = kb * df + mb * cf                                 # NB' = cot B0 * C'
        ng = kg * (np.array([0.0, 0.0, 1.0]) - df) + mg * cf   # NG' = cot G0 * C'
        forms.append((cf, nb, ng, (nb + ng) / math.sqrt(b0)))
        meas.append((alpha_b + alpha_g + 1.0, k_b, k_g, _COT_NU * b0 / math.sqrt(b2)))
    arr = np.array(consts, dtype=np.float64)  # (6, 13)
    f = np.array([[forms[k][r] for k in range(6)] for r in range(4)]).reshape(24, 3)
    m = np.array(meas)
    return {
        "centre": centre,
        "consts": tuple(tuple(float(v) for v in row) for row in arr),
        "packed": arr,
        "measure": m,
        "forms": f,
        "sel_w": f.astype(np.float32),
        "sel_c": f[:, 2:].astype(np.float32),
        "sel_alpha": m[:, :1].astype(np.float32),
        "sel_kb": m[:, 1:2].astype(np.float32),
        "sel_kg": m[:, 2:3].astype(np.float32),
        "sel_gamma": m[:, 3:4].astype(np.float32),
        "src_extent": ext,
        "dst_centre": dst.mean(axis=0),
        "dst_extent": float(2.0 * np.abs(dst - dst.mean(axis=0)).max()),
    }


_ROWS = np.arange(len(_PAIRS), dtype=np.int32)[:, None]

#: Weight of the source-side guard term ``nu (L + |x| + |y|) / (b |C'|)`` of
#: the error measure: a pair whose relative height |h| / b = |C'| falls to the
#: float32 noise of the selection (~6e-8 (L + |x| + |y|) / b; L = source
#: extent, x, y centred source coordinates) gets M >= 1e4, so points on or at
#: the ends of a base line (cross = 0) never use it.
_COT_NU = 1e-3


def _sel_buffers(n: int) -> dict[str, np.ndarray]:
    """Work arrays of :func:`_select_pairs` for blocks of up to n points (float32)."""
    p = np.empty((3, n), np.float32)
    p[2] = 1.0
    return {"p": p, "f": np.empty((24, n), np.float32), "b": np.empty((4, 6, n), np.float32),
            "best": np.empty(n, np.int32)}


def _select_pairs(x: F64, y: F64, t: dict[str, Any], buf: dict[str, np.ndarray] | None = None
                  ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Per point, the pair with the smallest error measure M (without the guard term), and 1 / M.

    ``x, y`` (n,) are centred source coordinates. The 24 affine forms
    (C', NB', NG', T'' of the six pairs) are one float32 (24, 3) @ (3, n)
    product, and the measure of all six pairs about 20 float32 operations on
    (6, n), all in place in the work arrays ``buf`` (:func:`_sel_buffers`;
    fresh allocations of this size cost more than the arithmetic). The
    quality ``Q = 1 / M`` is maximised: the pair index is stored in the 3
    lowest mantissa bits of each Q, so one integer maximum over the six rows
    yields the argmax (Q >= 0, whose float32 bit patterns order like the
    values; NaN from 0/0 has the sign bit set on x86 and so never wins; the
    3 bits change Q by < 1e-6 relative). The guard term of M is left out
    here: a point exactly on the chosen base line gives a non-finite result
    and is re-chosen in float64 by the caller. Returns the pair index (n,)
    and Q of the chosen pair (n,) float32.
    """
    n = len(x)
    if buf is None or buf["best"].shape[0] < n:
        buf = _sel_buffers(n)
    p = buf["p"][:, :n]
    f = buf["f"][:, :n]
    u, v, w, num = (b[:, :n] for b in buf["b"])
    p[0] = x
    p[1] = y
    np.matmul(t["sel_w"], p, out=f)
    ab = f[:18]
    np.abs(ab, out=ab)
    a_c, a_b, a_g, tt = f[0:6], f[6:12], f[12:18], f[18:24]
    np.add(a_c, a_b, out=u)                        # ~ sqrt(C^2 + NB^2)
    np.add(a_c, a_g, out=v)                        # ~ sqrt(C^2 + NG^2)
    np.multiply(t["sel_kb"], v, out=w)
    np.multiply(t["sel_kg"], u, out=num)
    w += num
    w *= a_c                                       # carriage constants: |C| (K_B v + K_G u)
    np.multiply(t["sel_alpha"], v, out=num)
    num += u
    num *= u                                       # eq. (2) and carriage of cot: u (u + alpha v)
    num += w
    den = np.multiply(tt, tt, out=tt)              # (NB + NG)^2 / b0
    den /= num                                     # Q = 1 / M
    v32 = den.view(np.int32)
    v32 &= ~7
    v32 |= _ROWS
    best = np.max(v32, axis=0, out=buf["best"][:n])
    q = (best & ~7).view(np.float32)
    k = best & 7
    return k, q


@dataclass(frozen=True, eq=False)
class CotangentFourPoint(Transform):
    """Kushtin's cotangent four-point method (seed 001, corrected eq. 2).

    Maps source points to target points through four control points, no
    three collinear, by carrying the cotangents of the base angles through
    the cross-ratio of the pencil of rays (see the module docstring). It is
    the same projective map as :class:`Homography` fitted to the four points,
    computed without a linear system.

    Parameters
    ----------
    src, dst : (4, 2) array_like
        The control points in the source and the target plane.

    Examples
    --------
    >>> src = [[0, 0], [100, 0], [100, 80], [0, 80]]
    >>> dst = [[10, 12], [215, 5], [190, 170], [3, 160]]
    >>> C = CotangentFourPoint.from_points(src, dst)
    >>> p = [[50, 40], [0, 40], [120, -30]]
    >>> from rectify.geometry.transforms import Homography
    >>> np.allclose(C(p), Homography.from_points(src, dst)(p))
    True
    """

    src: F64
    dst: F64
    _tables: dict[str, Any] = field(init=False, repr=False, compare=False)

    n_params: ClassVar[int] = 8
    min_points: ClassVar[int] = 4

    def __post_init__(self) -> None:
        s, d = as_pair(self.src, self.dst)
        if len(s) != 4:
            raise EstimationError(f"the cotangent method needs exactly 4 control points; got {len(s)}")
        check_distinct(s, "src")
        check_distinct(d, "dst")
        check_no_three_collinear(s, "src")
        check_no_three_collinear(d, "dst")
        tabs = _cot_tables(s, d)
        if not np.isfinite(tabs["packed"]).all():
            raise EstimationError(f"cotangent carriage is undefined for control points src={s.tolist()} "
                                  f"dst={d.tolist()}")
        for name, a in (("src", s), ("dst", d)):
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        for a in tabs.values():
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
        object.__setattr__(self, "_tables", tabs)

    @classmethod
    def from_points(cls, src: ArrayLike, dst: ArrayLike, *, weights: ArrayLike | None = None
                    ) -> CotangentFourPoint:
        """Build the method from exactly four control points.

        ``weights`` is accepted for interface compatibility; four points
        determine the map exactly, so weights other than all-positive are
        rejected.

        Raises
        ------
        EstimationError
            Not exactly 4 points, duplicates, three collinear points.
        """
        s, d = as_pair(src, dst)
        if weights is not None:
            w = as_weights(weights, len(s))
            if (w <= 0).any():
                raise EstimationError("the cotangent method uses all four points; zero weights given: "
                                      f"{w.tolist()}")
        if len(s) < 4:
            raise EstimationError(f"too few control points for the cotangent method: {len(s)} given, "
                                  "exactly 4 needed")
        return cls(s, d)

    @property
    def inverse(self) -> CotangentFourPoint:
        """The same method with the roles of the planes swapped (target -> source)."""
        return CotangentFourPoint(self.dst, self.src)

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> F64:
        """Transfer error ``|T(src) - dst|``, (N,), target units."""
        s, d = as_pair(src, dst)
        return np.linalg.norm(self._map(s) - d, axis=1)

    def to_dict(self) -> dict[str, Any]:
        """``{"method": "cotangent", "direction": "target_from_source", "src": (4, 2), "dst": (4, 2)}``."""
        return {"method": "cotangent", "direction": "target_from_source", "src": self.src.tolist(),
                "dst": self.dst.tolist()}

    def __call__(self, points: ArrayLike) -> F64:
        """Map (N, 2) source points to (N, 2) target points.

        Points on the vanishing line (mapped to infinity) give inf/NaN, as
        with :class:`Homography`.

        Raises
        ------
        EstimationError
            If for some point even the best base pair has an estimated
            rounding error (:meth:`error_bound`) above
            ``COT_MAX_REL_ERROR * (|p0 - centre0| + extent0)`` in the target
            plane: control quadrilaterals close to three collinear points
            (cross-ratio denominators near 0), or points mapped very far
            (about 1e6 target extents and more) towards the vanishing line.
        """
        return self._map(as_points(points, "points"))

    def base_pairs(self, points: ArrayLike) -> tuple[NDArray[np.intp], F64]:
        """The base pair chosen for each point and its estimated rounding error.

        Parameters
        ----------
        points : (N, 2) array_like
            Source points.

        Returns
        -------
        pair : (N,) int
            Index into :data:`PAIRS`, the six pairs ``(0,1), (0,2), (0,3),
            (1,2), (1,3), (2,3)`` of control points.
        error_bound : (N,) float
            ``eps * M`` of the chosen pair, target units: the first-order
            estimate of the rounding error of the whole chain (cotangents,
            carriage, eq. 2) for that point, ``eps = 2.2e-16``; see
            :meth:`error_bound`. inf for points on the vanishing line.
        """
        p = as_points(points, "points")
        ks, qs = [], []
        for s0 in range(0, len(p), _CHUNK):
            k, q = self._map_block(p[s0:s0 + _CHUNK], np.empty_like(p[s0:s0 + _CHUNK]), check=False)
            ks.append(k)
            qs.append(q)
        k_all = np.concatenate(ks) if ks else np.empty(0, np.int32)
        q_all = np.concatenate(qs).astype(np.float64) if qs else np.empty(0)
        with np.errstate(divide="ignore"):
            return k_all.astype(np.intp), np.asarray(_EPS / q_all, dtype=np.float64)

    def error_bound(self, points: ArrayLike) -> F64:
        """Error measure M_k(p) of all six base pairs, times eps, (6, N), target units.

        Derivation (first order in the unit round-off ``eps``). Write, for
        pair k = (a, b) with carriers (c, e), the three affine functions of
        the source point ``C = cross(d, p - a)``, ``NB = cot B0 * C`` and
        ``NG = cot G0 * C`` (carried cotangents times C; affine because the
        carriage ``cot0 = k cot + m`` is), so that ``cot B0 = NB / C``,
        ``cot G0 = NG / C``. Let ``u = |C| + |NB|`` and ``v = |C| + |NG|``
        (within sqrt 2 of ``sqrt(C^2 + NB^2)`` and ``sqrt(C^2 + NG^2)``).

        1. Source cotangents: rounding in ``cross`` and ``dot`` is a
           perturbation of p by ``O(eps L)`` (L = extent of the control
           points), the same for every pair and for the homography, so it
           does not enter the choice -- except that ``C = 0`` exactly (a
           point on the base line) divides by zero; the guard term
           ``nu (L + |x| + |y|) / (b |C'|)`` with ``nu = 1e-3``,
           ``C' = C / b^2`` (the relative height h / b) and x, y the centred
           source point excludes such pairs even where the float32 selection
           cannot resolve C' from 0.
        2. Carriage through the cross-ratio: ``cot B0 = k_B cot B + m_B`` with
           ``k_B = (cot B0_e - cot B0_c) / (cot B_e - cot B_c)``. Rounding of
           the cotangent of a control point q seen from a is a shift of q by
           ``eps L``: ``|d cot B_q| = eps (1 + cot^2 B_q) L / |q - a|``. Divided
           by the cross-ratio denominators this gives the relative error of
           ``k_B``, ``eps (alpha_B - 1)`` with
           ``alpha_B = 1 + [(1 + cot^2 B_e) / |e - a| + (1 + cot^2 B_c) / |c - a|] L / |cot B_e - cot B_c|``
           ``+ (the same in the target plane, with L0)``, so
           ``|d cot B0| <= eps (alpha_B |NB| + K_B |C|) / |C|`` with
           ``K_B = alpha_B (|m_B| + |k_B cot B_c|) + |cot B0_c|``; likewise G.
        3. Eq. (2) in the TARGET plane: ``|dp0 / d cot B0| = |p0 - a0|
           sin^2 B0 / |sin(B0 + G0)|`` -- the perpendicular shift of the ray
           from a0 amplified by ``1 / |sin|`` of the angle at p0 between the
           two rays; in the forms above ``= b0 |C| v / (NB + NG)^2`` (and
           ``b0 |C| u / (NB + NG)^2`` for G0). Rounding of eq. (2) itself
           (``cot B0 + cot G0`` cancels when the rays are nearly parallel)
           adds ``b0 u (u + v) / (NB + NG)^2``.

        Summing (with ``alpha = alpha_B + alpha_G + 1``):

            M = b0 [u (u + alpha v) + |C| (K_B v + K_G u)] / (NB + NG)^2
                + b0 nu (L + |x| + |y|) / (b |C'|).

        ``NB + NG = 0`` is the vanishing line (the same for all pairs): there
        M is infinite for every pair, as the homography's error is. Checked
        against 40-digit arithmetic: the actual error of the chosen pair is
        below ``eps M`` (except at the level of one ulp of the output).
        :meth:`__call__` uses the pair of smallest M, computed in float32.
        """
        p = as_points(points, "points")
        t = self._tables
        x = p[:, 0] - t["centre"][0]
        y = p[:, 1] - t["centre"][1]
        f = t["forms"][:, :2] @ np.vstack([x, y]) + t["forms"][:, 2:]
        a_c, a_b, a_g, tt = np.abs(f[0:6]), np.abs(f[6:12]), np.abs(f[12:18]), f[18:24]
        m = t["measure"]
        u, v = a_c + a_b, a_c + a_g
        with np.errstate(divide="ignore", invalid="ignore"):
            r = t["src_extent"] + np.abs(x) + np.abs(y)
            out = (u * (u + m[:, :1] * v) + a_c * (m[:, 1:2] * v + m[:, 2:3] * u)) / (tt * tt) + m[:, 3:4] * r / a_c
        return _EPS * np.where(np.isnan(out) | (a_c == 0), np.inf, out)

    def _map(self, p: F64) -> F64:
        out = np.empty_like(p)
        buf = _sel_buffers(min(len(p), _SEL_CHUNK))
        for s0 in range(0, len(p), _CHUNK):
            self._map_block(p[s0:s0 + _CHUNK], out[s0:s0 + _CHUNK], buf)
        return out

    def _map_block(self, pc: F64, out: F64, buf: dict[str, np.ndarray] | None = None, check: bool = True
                   ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
        """Eq. (2) with carried cotangents on one block; writes ``out`` (n, 2).

        Points are grouped by their chosen base pair, so every group is
        computed with scalar constants. With ``check``, raises
        EstimationError where the estimated error of the best pair exceeds
        :data:`COT_MAX_REL_ERROR`. Returns the chosen pair and ``Q = 1 / M``.
        """
        t = self._tables
        x = pc[:, 0] - t["centre"][0]
        y = pc[:, 1] - t["centre"][1]
        k = np.empty(len(x), np.int32)
        q = np.empty(len(x), np.float32)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for s0 in range(0, len(x), _SEL_CHUNK):
                sl = slice(s0, s0 + _SEL_CHUNK)
                k[sl], q[sl] = _select_pairs(x[sl], y[sl], t, buf)
        ox = np.empty_like(x)
        oy = np.empty_like(y)
        for j in range(len(_PAIRS)):
            idx = np.flatnonzero(k == j)
            if idx.size == len(x):
                ox, oy = self._chain(j, x, y)
                break
            if idx.size:
                ox[idx], oy[idx] = self._chain(j, x[idx], y[idx])
        out[:, 0] = ox
        out[:, 1] = oy
        nf = np.flatnonzero(~np.isfinite(ox + oy))
        if nf.size:
            # the float32 choice cannot resolve cross = 0 (a point on the chosen base line, with all other
            # pairs poorly conditioned): choose again in float64 among the pairs with cross != 0
            eb = self.error_bound(pc[nf])
            k2 = np.argmin(eb, axis=0)
            q[nf] = (_EPS / eb[k2, np.arange(nf.size)]).astype(np.float32)
            k[nf] = k2
            for j in np.unique(k2):
                sel = nf[k2 == j]
                out[sel, 0], out[sel, 1] = self._chain(int(j), x[sel], y[sel])
        # guard: estimated error eps / Q against COT_MAX_REL_ERROR * (|p0 - centre0| + extent0);
        # candidates first (|p0 - centre0| >= 0), then the exact test on those few
        cand = np.flatnonzero(q < _EPS / (COT_MAX_REL_ERROR * t["dst_extent"]))
        if cand.size:
            lim = (np.abs(out[cand, 0] - t["dst_centre"][0]) + np.abs(out[cand, 1] - t["dst_centre"][1])
                   + t["dst_extent"]) * q[cand]
            bad = cand[lim < _EPS / COT_MAX_REL_ERROR]     # False for NaN / inf (vanishing line)
        else:
            bad = cand
        if bad.size and check:
            i = int(bad[0])
            est = _EPS / float(q[i]) if q[i] > 0 else math.inf
            rel = est / (abs(out[i, 0] - t["dst_centre"][0]) + abs(out[i, 1] - t["dst_centre"][1])
                         + t["dst_extent"])
            raise EstimationError(
                f"point {[float(pc[i, 0]), float(pc[i, 1])]} has no well-conditioned base pair: the best "
                f"(pair {PAIRS[int(k[i])]}) has an estimated rounding error of {est:.3g} target units = "
                f"{rel:.3g} of the target extent, above COT_MAX_REL_ERROR = {COT_MAX_REL_ERROR:g} "
                f"({bad.size} of {len(q)} points in this block)")
        return k, q

    def _chain(self, j: int, xs: F64, ys: F64) -> tuple[F64, F64]:
        """Cotangents, carriage and eq. (2) with base pair ``j`` for centred source points (n,) -> (x0, y0)."""
        dx, dy, e1, e2, b2, kb, mb, kg, mg, xa0, ya0, dx0, dy0 = self._tables["consts"][j]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # signed cotangents of the base angles in the source plane
            cr = dx * ys
            cr -= dy * xs
            cr += e1                                   # cross(d, p - a) = b * h
            da = dx * xs
            da += dy * ys
            da += e2                                   # dot(d, p - a)
            inv_cr = 1.0 / cr
            cot_b = da * inv_cr                        # cot B
            cot_g = b2 - da
            cot_g *= inv_cr                            # cot G
            # carriage through the cross-ratio of the pencil (affine in the cotangent)
            cot_b *= kb
            cot_b += mb                                # cot B0
            cot_g *= kg
            cot_g += mg                                # cot G0
            # eq. (2), corrected y-line
            inv_s = 1.0 / (cot_b + cot_g)
            gx = dx0 * cot_b
            gx -= dy0
            gx *= inv_s
            gx += xa0
            gy = dy0 * cot_b
            gy += dx0
            gy *= inv_s
            gy += ya0
        return gx, gy


def printed_eq2(p1: ArrayLike, p2: ArrayLike, cot_b: ArrayLike, cot_g: ArrayLike) -> F64:
    """Seed 001's eq. (2) **as printed** (with the sign error), for the record.

    Returns (N, 2). Used by the tests and the study to show the inconsistency;
    the corrected formula is what :class:`CotangentFourPoint` uses.
    """
    x1, y1 = np.asarray(p1, dtype=float)
    x2, y2 = np.asarray(p2, dtype=float)
    cb, cg = np.asarray(cot_b, dtype=float), np.asarray(cot_g, dtype=float)
    s = cb + cg
    return np.column_stack([x1 + ((x2 - x1) * cb - (y2 - y1)) / s, y1 + ((y2 - y1) * cb - (x2 - x1)) / s])


def corrected_eq2(p1: ArrayLike, p2: ArrayLike, cot_b: ArrayLike, cot_g: ArrayLike) -> F64:
    """Seed 001's eq. (2) with the corrected sign in the y-line, (N, 2)."""
    x1, y1 = np.asarray(p1, dtype=float)
    x2, y2 = np.asarray(p2, dtype=float)
    cb, cg = np.asarray(cot_b, dtype=float), np.asarray(cot_g, dtype=float)
    s = cb + cg
    return np.column_stack([x1 + ((x2 - x1) * cb - (y2 - y1)) / s, y1 + ((y2 - y1) * cb + (x2 - x1)) / s])


def base_cotangents(p1: ArrayLike, p2: ArrayLike, points: ArrayLike) -> tuple[F64, F64]:
    """Signed cotangents (cot B, cot G) of the base angles at p1 and p2, (N,) each."""
    a, b = np.asarray(p1, dtype=float), np.asarray(p2, dtype=float)
    p = as_points(points, "points")
    d = b - a
    cr = d[0] * (p[:, 1] - a[1]) - d[1] * (p[:, 0] - a[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        cb = (d[0] * (p[:, 0] - a[0]) + d[1] * (p[:, 1] - a[1])) / cr
        cg = (-d[0] * (p[:, 0] - b[0]) - d[1] * (p[:, 1] - b[1])) / cr
    return cb, cg
