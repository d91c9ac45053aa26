"""The result of a bundle adjustment (:func:`stereo.block.bundle.adjust.adjust_bundle`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from stereo.block.types import Pose

__all__ = ["BundleResult"]

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
        components).
    flagged_control : tuple of str
        Control points whose standardised residual exceeds the threshold.
    check_ids, check_errors, check_std
        Check points, adjusted minus given coordinates (C, 3), m, and the predicted standard
        error of that difference (C, 3), m.
    gnss_residuals : (g, 3) float64
        GNSS observed minus adjusted antenna positions, m.
    iterations : int
    converged : bool
    datum : tuple of str
        The datum analysis: which groups define the datum and its expected weakness.
    datum_groups : tuple of str
    condition_number : float
        Of the Jacobi-scaled reduced camera system (NaN when not computed).
    warnings : tuple of str
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
        out = [f"bundle: {len(self.poses)} images, {len(self.points)} points, {m} image observations, "
               f"{self.iterations} iterations{'' if self.converged else ' (NOT converged)'}",
               f"image residuals: RMS {self.rms_px:.3f} px ({int(self.flagged.sum())} flagged as blunders)",
               f"sigma0 {self.sigma0:.3f}"]
        for g, s in self.sigma0_groups.items():
            out.append(f"group {g}: sigma0 {s:.3f}, redundancy {self.redundancy_groups.get(g, float('nan')):.1f}, "
                       f"variance factor {self.variance_factors.get(g, 1.0):.3f}")
        if len(self.gnss_residuals):
            out.append(f"GNSS residuals: RMS {np.sqrt(np.mean(self.gnss_residuals ** 2)):.3f} m")
        if len(self.control_ids):
            r = self.control_residuals[np.isfinite(self.control_residuals)]
            out.append(f"control: {len(self.control_ids)} points, RMS residual {np.sqrt(np.mean(r ** 2)):.3f} m"
                       + (f", flagged {list(self.flagged_control)}" if self.flagged_control else ""))
        if len(self.check_ids):
            e = self.check_errors
            out.append(f"check: {len(self.check_ids)} points, RMS error x {np.sqrt(np.mean(e[:, 0] ** 2)):.3f} "
                       f"y {np.sqrt(np.mean(e[:, 1] ** 2)):.3f} z {np.sqrt(np.mean(e[:, 2] ** 2)):.3f} m")
        out.extend(self.datum)
        out.extend(f"WARNING: {w}" for w in self.warnings)
        return out
