"""Relative orientation of a stereo pair by the coplanarity condition.

Three systems of elements share one model frame (``docs/relative.md``, "one
frame, three systems"); each fixes three of the eight angular elements of the
pair and estimates the other five:

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
generators, see :func:`stereo.relative.systems._chain`); with respect to the photo coordinates they
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
(:func:`rectify.geometry.robust.irls`).

Modules
-------
- :mod:`stereo.relative.systems`: the three systems of elements, the coplanarity
  misclosure and its analytic derivatives, the a-priori precision structure;
- :mod:`stereo.relative.solver`: the estimation in stages (validate, start values
  and Gauss-Newton/IRLS solution, precision), the essential-matrix start;
- :mod:`stereo.relative.result`: :class:`RelativeOrientation` (the result and its
  dict form) and :class:`RelativeGeometry` (what intersection needs of it);
- :mod:`stereo.relative.universal`, :mod:`stereo.relative.projective`: the method systems of
  :data:`METHOD_SYSTEMS` (seed 003, 3.2.1 and 3.2.2; ``docs/universal.md``): ``universal`` (linear
  iterations with the p, q, r matrices and Gram-Schmidt, reported in the ``basis`` elements) and
  ``projective`` (the fundamental matrix, reported in the ``left-image`` elements).
"""

from stereo.relative.result import RelativeGeometry, RelativeOrientation, WesternForm
from stereo.relative.solver import INITIAL_METHODS, RelativeOptions, relative_from_essential
from stereo.relative.systems import (
    METHOD_SYSTEMS,
    SYSTEMS,
    PrecisionStructure,
    System,
    coplanarity,
    precision_structure,
)

__all__ = [
    "INITIAL_METHODS",
    "METHOD_SYSTEMS",
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
