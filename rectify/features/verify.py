"""Geometric verification of tie points and the screening of refined ones.

:func:`verify_matches` (OpenCV USAC MAGSAC++: homography, fundamental matrix or none) and the
:class:`Verification` it returns; :func:`screen_refined` re-fits the model to the refined matches alone and
moves back the refined matches whose residual is too large for their precision (issue 30); :func:`table_for`
builds the residual table of exactly the returned matches. Pixel frame: x = column, y = row, pixel centres
at integers.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import EstimationError, InvalidInputError
from rectify.geometry.points import as_pair
from rectify.geometry.residuals import ResidualTable, rms

__all__ = ["SCREEN_RATIO", "VERIFY_METHODS", "Verification", "Verify", "screen_refined", "table_for",
           "verify_matches"]

logger = logging.getLogger(__name__)


class Verify(str, enum.Enum):
    HOMOGRAPHY = "homography"
    FUNDAMENTAL = "fundamental"
    NONE = "none"


VERIFY_METHODS = tuple(v.value for v in Verify)


@dataclass(frozen=True, eq=False)
class Verification:
    """Result of geometric verification.

    Attributes
    ----------
    method : str
    matrix : (3, 3) float64 or None
        H_right_from_left (homography) or F with x_r^T F x_l = 0 (fundamental).
    inliers : (N,) bool
    errors_px : (N,) float64
        Transfer error |H x_l - x_r| (homography) or Sampson distance
        (fundamental), px; NaN for ``none``.
    table : ResidualTable or None
    """

    method: str
    matrix: NDArray[np.float64] | None
    inliers: NDArray[np.bool_]
    errors_px: NDArray[np.float64]
    table: ResidualTable | None

    @property
    def rmse_px(self) -> float:
        e = self.errors_px[self.inliers]
        return rms(e) if e.size and np.isfinite(e).all() else float("nan")


def _sampson_vectors(F: NDArray[np.float64], pl: NDArray[np.float64], pr: NDArray[np.float64]
                     ) -> NDArray[np.float64]:
    """First-order (Sampson) corrections (N, 4) to (xl, yl, xr, yr); their norm is the Sampson distance."""
    xl = np.c_[pl, np.ones(len(pl))]
    xr = np.c_[pr, np.ones(len(pr))]
    Fx = xl @ F.T          # F x_l
    Ftx = xr @ F           # F^T x_r
    e = np.sum(xr * Fx, axis=1)
    den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
    k = -e / np.where(den > 0, den, np.nan)
    return k[:, None] * np.c_[Ftx[:, 0], Ftx[:, 1], Fx[:, 0], Fx[:, 1]]


def _apply_h(H: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:]


def verify_matches(left_xy: ArrayLike, right_xy: ArrayLike, *, method: str = "homography",
                   threshold_px: float = 1.5, ids: list[str] | None = None, seed: int = 0,
                   max_iters: int = 10000, confidence: float = 0.9999) -> Verification:
    """Geometric verification with OpenCV USAC (MAGSAC++).

    Parameters
    ----------
    left_xy, right_xy : (N, 2) array_like
        Matched positions, px.
    method : {"homography", "fundamental", "none"}
    threshold_px : float
        USAC threshold, px.
    ids : list of str, optional
        Point ids for the residual table (default "1".."N").

    Returns
    -------
    Verification
        For ``homography`` the residual table holds the transfer error in the
        right image (observed x_r, adjusted H x_l); for ``fundamental`` the
        Sampson correction of (x_l, y_l, x_r, y_r), whose norm is the Sampson
        distance. Non-inliers are flagged as outliers.

    Raises
    ------
    EstimationError
        Fewer than the minimal number of matches, or USAC finds no model.
    """
    if method not in VERIFY_METHODS:
        raise InvalidInputError(f"unknown verification {method!r}; choose from {VERIFY_METHODS}")
    pl, pr = as_pair(left_xy, right_xy, names=("left_xy", "right_xy"))
    n = len(pl)
    ids = [str(i + 1) for i in range(n)] if ids is None else list(ids)
    if method == "none":
        return Verification("none", None, np.ones(n, dtype=bool), np.full(n, np.nan), None)
    need = 4 if method == "homography" else 8
    if n < need:
        raise EstimationError(f"{method} verification needs at least {need} matches; got {n}")
    cv2.setRNGSeed(int(seed))
    params_thr = float(threshold_px)
    try:
        if method == "homography":
            M, mask = cv2.findHomography(pl, pr, cv2.USAC_MAGSAC, params_thr, maxIters=max_iters,
                                         confidence=confidence)
        else:
            M, mask = cv2.findFundamentalMat(pl, pr, cv2.USAC_MAGSAC, params_thr, confidence, max_iters)
    except cv2.error as exc:
        raise EstimationError(f"USAC {method} estimation failed on {n} matches: {exc}") from exc
    if M is None or mask is None or M.shape != (3, 3):
        raise EstimationError(f"USAC found no {method} consistent with {n} matches")
    Mf: NDArray[np.float64] = np.asarray(M, dtype=np.float64)
    if method == "homography":
        pred = _apply_h(Mf, pl)
        err = np.linalg.norm(pred - pr, axis=1)
        inl = mask.ravel().astype(bool) & (err <= max(2.5 * threshold_px, threshold_px + 1))
        table = ResidualTable(f"match verification ({method})", ids, pr, pred, "px", ("dx", "dy"),
                              outlier=~inl, position_px=pl, n_params=8,
                              extra={"threshold_px": float(threshold_px)})
    else:
        d = _sampson_vectors(Mf, pl, pr)
        err = np.linalg.norm(d, axis=1)
        err = np.where(np.isfinite(err), err, np.inf)
        inl = mask.ravel().astype(bool) & (err <= max(2.5 * threshold_px, threshold_px + 1))
        obs = np.c_[pl, pr]
        table = ResidualTable(f"match verification ({method})", ids, obs, obs + np.nan_to_num(d), "px",
                              ("dx_left", "dy_left", "dx_right", "dy_right"), outlier=~inl,
                              position_px=pl, n_params=7, extra={"threshold_px": float(threshold_px)})
    return Verification(method, Mf, inl, err, table)


def _h_jacobian(H: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    q = np.c_[p, np.ones(len(p))] @ H.T
    w = q[:, 2]
    J = np.empty((len(p), 2, 2))
    for i in range(2):
        for j in range(2):
            J[:, i, j] = (H[i, j] * w - q[:, i] * H[2, j]) / (w * w)
    return J


#: Screening of refined matches (issue 30): a refined match whose verification residual exceeds this many times
#: the median of the refined matches' residuals, each divided by its LSM standard deviation, is a wrong
#: convergence (the 99.9 % point of the residual's distribution when it is Gaussian: the Sampson distance is the
#: size of one Gaussian component, |N(0, s)|, median 0.674 s, 99.9 % point 3.29 s; the transfer error of a
#: homography is the length of a 2D one, Rayleigh, median 1.177 s, 99.9 % point 3.72 s).
SCREEN_RATIO = {"fundamental": 3.29 / 0.674, "homography": 3.72 / 1.177}
#: floor of the LSM standard deviation in the screening (px): windows of strong texture report a few
#: thousandths of a pixel, below what the model and the images hold
SCREEN_STD_FLOOR_PX = 0.02
#: a refined match this close to the model (px) is never screened out, however small the others' residuals (an
#: image against a copy of itself: residuals of 1e-6 px)
SCREEN_MIN_PX = 0.05


def _errors(method: str, M: NDArray[np.float64], pl, pr) -> NDArray[np.float64]:
    """Verification residual of each match (px): transfer error (homography) or Sampson distance (fundamental)."""
    if method == "homography":
        e = np.linalg.norm(_apply_h(M, pl) - pr, axis=1)
    else:
        e = np.linalg.norm(_sampson_vectors(M, pl, pr), axis=1)
    return np.where(np.isfinite(e), e, np.inf)


def screen_refined(ver: Verification, pl, pr, raw_pr, score, *, threshold_px: float, min_inliers: int,
                   keep_unrefined: bool, seed: int = 0):
    """The model re-fitted to the refined matches alone, and the refined matches it shows to be wrong convergences.

    Refined matches (finite ``score``, the LSM standard deviation) whose residual exceeds
    :data:`SCREEN_RATIO` times the median normalised residual are kept as unrefined matches (``keep_unrefined``;
    NaN score) at whichever of their raw and refined positions agrees better with the model, when that one
    passes ``threshold_px``, or dropped; unrefined matches farther than ``threshold_px`` from the refined
    matches' model are dropped. Returns (verification, pl, pr, raw_pr, score, number screened out)."""
    ref = np.isfinite(score)
    need = 4 if ver.method == "homography" else 8
    if int(ref.sum()) < max(need, min_inliers):
        return ver, pl, pr, raw_pr, score, 0
    try:    # the model of the precise matches: the unrefined ones (0.3-0.5 px) no longer pull it
        vr = verify_matches(pl[ref], pr[ref], method=ver.method, threshold_px=threshold_px, seed=seed)
        M = vr.matrix if vr.matrix is not None and int(vr.inliers.sum()) >= need else ver.matrix
    except EstimationError:
        M = ver.matrix
    if M is None:
        return ver, pl, pr, raw_pr, score, 0
    e = _errors(ver.method, M, pl, pr)
    z = e / np.maximum(np.where(ref, score, 1.0), SCREEN_STD_FLOOR_PX)
    cut = SCREEN_RATIO.get(ver.method, 5.0) * float(np.median(z[ref]))
    bad = ref & ~(z <= cut) & ~(e <= SCREEN_MIN_PX)
    # a screened match stays, unrefined (NaN score), at whichever of its raw and refined positions agrees better
    # with the model, when that one passes the threshold
    e_raw = _errors(ver.method, M, pl, raw_pr)
    to_raw = bad & (e_raw < e)
    back = bad & (np.minimum(e, e_raw) <= threshold_px) & keep_unrefined
    pr = np.where((back & to_raw)[:, None], raw_pr, pr)
    score = np.where(back, np.nan, score)
    keep = ~(bad & ~back) & (ref | (e <= threshold_px))      # unrefined ones must fit the refined matches' model
    ver = Verification(ver.method, M, np.ones(int(keep.sum()), bool), e[keep], None)
    logger.debug("screening: %d of %d refined matches off the refined model (cut %.3g x std), %d kept unrefined",
                 int(bad.sum()), int(ref.sum()), cut, int(back.sum()))
    return ver, pl[keep], pr[keep], raw_pr[keep], score[keep], int(bad.sum())


def table_for(ver: Verification, pl, pr, *, threshold_px: float, refined: NDArray[np.bool_] | None = None
              ) -> Verification:
    """The verification of exactly the returned matches with ``ver``'s model: residual table and errors. With
    ``refined``, the unrefined matches are check points of the table (withheld from its RMSE and sigma0)."""
    ids = [str(i + 1) for i in range(len(pl))]
    M = ver.matrix
    if M is None:
        raise InvalidInputError(f"verification {ver.method!r} has no model matrix")
    check = None if refined is None else ~refined
    if ver.method == "homography":
        pred = _apply_h(M, pl)
        err = np.linalg.norm(pred - pr, axis=1)
        table = ResidualTable("match verification (homography)", ids, pr, pred, "px", ("dx", "dy"),
                              position_px=pl, n_params=8, extra={"threshold_px": threshold_px}, check=check)
    else:
        d = _sampson_vectors(M, pl, pr)
        err = np.linalg.norm(d, axis=1)
        obs = np.c_[pl, pr]
        table = ResidualTable("match verification (fundamental)", ids, obs, obs + d, "px",
                              ("dx_left", "dy_left", "dx_right", "dy_right"), position_px=pl, n_params=7,
                              extra={"threshold_px": threshold_px}, check=check)
    return Verification(ver.method, M, np.ones(len(pl), bool), err, table)
