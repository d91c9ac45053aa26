"""The result of a bundle adjustment (:func:`stereo.block.bundle.adjust.adjust_bundle`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from stereo.block.bundle.systematic import summary_lines as systematic_lines
from stereo.block.bundle.variance import VCE_MIN_REDUNDANCY, VCE_WARN_REDUNDANCY
from stereo.block.types import Pose

__all__ = ["BundleResult"]


def _rms(v: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class BundleResult:
    """Result of :func:`adjust_bundle`.

    Attributes
    ----------
    cameras : dict str -> Camera
        Adjusted cameras; self-calibrated parameters carry ``std_errors`` (f, x0, y0 in mm).
    poses : tuple of Pose
        Adjusted poses, in the input order.
    point_ids : tuple of str
        Track ids (P,).
    points : (P, 3) float64
        Adjusted object points, ground frame, m.
    pose_std : (n, 6) float64
        Standard errors of omega, phi, kappa (rad), x, y, z (m); NaN when not computed.
    pose_covariance : (n, 6, 6) float64
        Covariance of the same elements.
    correlation : (u, u) float64
        Correlation matrix of all orientation elements (6 per image) and interior parameters,
        names in ``correlation_names``; (0, 0) when not computed.
    correlation_names : tuple of str
        ``"<image>.<element>"`` and ``"<camera>.<parameter>"``.
    interior_std : dict str -> dict str -> float
        Standard errors of the self-calibrated parameters per camera.
    point_std : (P, 3) float64
        Standard errors of the object points, m (NaN where not computed).
    point_covariance : (P, 3, 3) float64 or None
        Covariance of each point (``covariance="full"``).
    sigma0 : float
        A-posteriori standard deviation of unit weight (all groups).
    sigma0_groups : dict str -> float
        sqrt(v_k^T P_k v_k / r_k) of each group present.
    variance_factors : dict str -> float
        Final group sigma / given group sigma (1 without variance components).
    redundancy_groups : dict str -> float
        Redundancy r_k of each group.
    residuals_px : (M, 2) float64
        Image residuals, observed minus computed, px, in the order of ``Tracks``.
    weights : (M, 2) float64
        Robust weights (1 without robust estimation).
    standardized : (M, 2) float64
        Standardised residuals |v| / (sigma0 sigma sqrt(r)).
    redundancy_numbers : (M, 2) float64
        Redundancy numbers r_i (NaN when not computed).
    flagged : (M,) bool
        Observations flagged as blunders.
    control_ids, control_residuals
        Control points used and given minus adjusted coordinates (K, 3), m (NaN for unused
        components). A control point all of whose rays were flagged as blunders is not among
        them (``rejected_control``).
    flagged_control : tuple of str
        Control points whose standardised residual exceeds the threshold.
    check_ids, check_errors, check_std
        Check points, adjusted minus given coordinates (C, 3), m, and the predicted standard
        error of that difference (C, 3), m. A check point all of whose rays were flagged is not
        among them (``rejected_check``).
    gnss_residuals : (g, 3) float64
        GNSS observed minus adjusted antenna positions, m.
    iterations : int
        Gauss-Newton iterations in all, over every variance-component round (at most
        ``iteration_limit``).
    converged : bool
    datum : tuple of str
        The datum analysis: which groups define the datum and its expected weakness.
    datum_groups : tuple of str
    condition_number : float
        Of the Jacobi-scaled reduced camera system (NaN when not computed).
    warnings : tuple of str
    rejected_control, rejected_check : tuple of str
        Control and check points all of whose rays were flagged as blunders: not used, not
        counted, named in ``warnings``.
    points_determined : (P,) bool
        Points finite and seen by at least two rays not flagged as blunders (the points a block
        writes; the datum statement's figures are of these).
    iteration_limit : int
        The iteration limit the adjustment ran under (0: not recorded).
    variance_estimated : dict str -> float or None
        With variance components: the groups whose factor was estimated, with the redundancy of
        the latest estimate (a group with less than 2 keeps its factor); None without.
    systematic_names : tuple of str
        The systematic unknowns (GNSS shift/drift, boresight; :mod:`stereo.block.bundle.systematic`).
    systematic, systematic_std : (s,) float64
        Their estimates and standard deviations (m, m/s, rad).
    """

    cameras: dict[str, Camera]
    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: F64
    pose_std: F64
    pose_covariance: F64
    correlation: F64
    correlation_names: tuple[str, ...]
    interior_std: dict[str, dict[str, float]]
    point_std: F64
    point_covariance: F64 | None
    sigma0: float
    sigma0_groups: dict[str, float]
    variance_factors: dict[str, float]
    redundancy_groups: dict[str, float]
    residuals_px: F64
    weights: F64
    standardized: F64
    redundancy_numbers: F64
    flagged: NDArray[np.bool_]
    control_ids: tuple[str, ...]
    control_residuals: F64
    flagged_control: tuple[str, ...]
    check_ids: tuple[str, ...]
    check_errors: F64
    check_std: F64
    gnss_residuals: F64
    iterations: int
    converged: bool
    datum: tuple[str, ...]
    datum_groups: tuple[str, ...]
    condition_number: float
    warnings: tuple[str, ...] = ()
    rejected_control: tuple[str, ...] = ()
    rejected_check: tuple[str, ...] = ()
    points_determined: NDArray[np.bool_] | None = None
    iteration_limit: int = 0
    variance_estimated: dict[str, float] | None = None
    systematic_names: tuple[str, ...] = ()
    systematic: F64 = field(default_factory=lambda: np.zeros(0))
    systematic_std: F64 = field(default_factory=lambda: np.zeros(0))

    @property
    def determined(self) -> NDArray[np.bool_]:
        """(P,) points finite and seen by at least two rays not flagged (``points_determined`` when recorded)."""
        if self.points_determined is not None:
            return self.points_determined
        return np.asarray(np.isfinite(self.points).all(axis=1), dtype=bool)

    @property
    def flagged_obs(self) -> NDArray[np.int64]:
        """Indices of the flagged observations (into the tracks' observations)."""
        return np.flatnonzero(self.flagged).astype(np.int64)

    @property
    def rms_px(self) -> float:
        """RMS of the image residuals of unflagged observations, px (per coordinate)."""
        v = self.residuals_px[~self.flagged]
        return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")

    def summary_lines(self) -> list[str]:
        """Short report lines: counts, RMS residuals with units, sigma0, groups, datum."""
        m = len(self.residuals_px)
        lim = f" (limit {self.iteration_limit})" if self.iteration_limit else ""
        out = [f"bundle: {len(self.poses)} images, {len(self.points)} points, {m} image observations, "
               f"{self.iterations} iterations{lim}{'' if self.converged else ' (NOT converged)'}",
               f"image residuals: RMS {self.rms_px:.3f} px ({int(self.flagged.sum())} flagged as blunders)",
               f"sigma0 {self.sigma0:.3f}"]
        for grp, s in self.sigma0_groups.items():
            rg = self.redundancy_groups.get(grp, float("nan"))
            note = ""
            if self.variance_estimated is not None:
                r_est = self.variance_estimated.get(grp)
                if r_est is None:
                    note = f" (not estimated: redundancy below {VCE_MIN_REDUNDANCY:g})"
                elif min(r_est, rg) < VCE_WARN_REDUNDANCY:
                    note = (f" (estimated from a redundancy of {r_est:.1f}: uncertain by about "
                            f"{100 / np.sqrt(2 * max(min(r_est, rg), 0.5)):.0f} %)")
            out.append(f"group {grp}: sigma0 {s:.3f}, redundancy {rg:.1f}, variance factor "
                       f"{self.variance_factors.get(grp, 1.0):.3f}{note}")
        if len(self.gnss_residuals):
            g = np.asarray(self.gnss_residuals, dtype=np.float64)
            d3 = float(np.sqrt(np.mean(np.sum(g ** 2, axis=1))))
            out.append(f"GNSS residuals: RMS per component {_rms(g):.3f} m (x {_rms(g[:, 0]):.3f}, "
                       f"y {_rms(g[:, 1]):.3f}, z {_rms(g[:, 2]):.3f} m); RMS of the 3D residual {d3:.3f} m")
        if len(self.control_ids) or self.rejected_control:
            r = self.control_residuals[np.isfinite(self.control_residuals)]
            rm = f"RMS residual per component {np.sqrt(np.mean(r ** 2)):.3f} m" if r.size else "no residual"
            out.append(f"control: {len(self.control_ids)} points, {rm}"
                       + (f", flagged {list(self.flagged_control)}" if self.flagged_control else "")
                       + (f"; rejected (every ray flagged as a blunder): {list(self.rejected_control)}"
                          if self.rejected_control else ""))
        if self.rejected_check:
            out.append(f"check points rejected (every ray flagged as a blunder): {list(self.rejected_check)}")
        if len(self.check_ids):
            e = self.check_errors
            out.append(f"check: {len(self.check_ids)} points, RMS error x {np.sqrt(np.mean(e[:, 0] ** 2)):.3f} "
                       f"y {np.sqrt(np.mean(e[:, 1] ** 2)):.3f} z {np.sqrt(np.mean(e[:, 2] ** 2)):.3f} m")
        out.extend(systematic_lines(self.systematic_names, self.systematic, self.systematic_std))
        out.extend(self.datum)
        out.extend(f"WARNING: {w}" for w in self.warnings)
        return out
