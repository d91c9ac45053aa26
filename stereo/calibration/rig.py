"""Two-camera rigs: both interior orientations and the fixed relative orientation (the stereo base).

Both cameras see the target at the same instants (stations). Unknowns: both
interior orientations, the pose of the left camera at every station, and one
relative orientation ``Xc_right = R_rel Xc_left + t_rel`` (OpenCV camera
frames), adjusted together (:func:`.adjust.adjust` with two cameras). Start:
each camera calibrated alone, the relative orientation averaged over stations.

The rig JSON (``"format": "rectify-stereo/rig"``) holds both camera JSONs and
the relative orientation in the project's photo frame (x right, y up, z back):
``rotation_right`` takes a right photo vector into the left photo frame and
``base`` is the right projection centre in the left photo frame, target units.
These are the elements of the left-image system of relative orientation, so
``stereo run`` / ``stereo dense`` can take each camera file and the relative
orientation from it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.camera import intrinsics_document
from rectify.geometry.rotation import angles_from_matrix, rodrigues, rotvec_from_matrix
from stereo.calibration.adjust import Adjustment, Observations, adjust, free_parameters
from stereo.calibration.model import CV_FROM_PHOTO, Intrinsics
from stereo.calibration.result import Calibration
from stereo.calibration.views import TargetView

logger = logging.getLogger(__name__)

__all__ = ["RigCalibration"]

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """A calibrated two-camera rig.

    Attributes
    ----------
    left, right : Intrinsics
    std_left, std_right : dict name -> float
        Standard errors of the interior elements.
    rotation_right : (3, 3) float64
        Right photo frame -> left photo frame.
    base : (3,) float64
        Right projection centre in the left photo frame, target units.
    std_angles : (3,) float64
        Standard errors of omega, phi, kappa of ``rotation_right``, rad.
    std_base : (3,) float64
    sigma0_px : float
    rms_px : float
    adjustment : Adjustment
    """

    left: Intrinsics
    right: Intrinsics
    std_left: dict[str, float]
    std_right: dict[str, float]
    rotation_right: F64
    base: F64
    std_angles: F64
    std_base: F64
    std_base_length: float
    sigma0_px: float
    rms_px: float
    n_stations: int
    adjustment: Adjustment

    @classmethod
    def from_views(cls, left_views: Sequence[TargetView], right_views: Sequence[TargetView], width: int, height: int,
                   *, right_size: tuple[int, int] | None = None, **model: Any) -> RigCalibration:
        """Calibrate a rig from synchronous views (``left_views[i]`` and ``right_views[i]`` at one instant).

        Keywords as :meth:`Calibration.from_views` (``equal_focal``, ``distortion``, ``symmetry``).

        Raises
        ------
        InvalidInputError
            Different numbers of left and right views, or target points that differ within a pair.
        CalibrationError
            As :meth:`Calibration.from_views`, for either camera.
        """
        if len(left_views) != len(right_views):
            raise InvalidInputError(f"{len(left_views)} left views but {len(right_views)} right views")
        for lv, rv in zip(left_views, right_views, strict=True):
            common = set(lv.ids) & set(rv.ids)
            if len(common) < 4:
                raise InvalidInputError(f"views {lv.name!r} / {rv.name!r} share {len(common)} target points")
        rw, rh = right_size or (width, height)
        kw = {k: v for k, v in model.items() if k != "robust"}
        cl = Calibration.from_views(left_views, width, height, **kw)
        cr = Calibration.from_views(right_views, rw, rh, **kw)
        pl, pr = cl.adjustment.poses, cr.adjustment.poses
        rels = []
        for a, b in zip(pl, pr, strict=True):
            Ra, Rb = rodrigues(a[:3])[0], rodrigues(b[:3])[0]
            Rr = Rb @ Ra.T
            rels.append(np.concatenate([rotvec_from_matrix(Rr), b[3:] - Rr @ a[3:]]))
        rel0 = np.median(np.array(rels), axis=0)
        X = np.concatenate([v.object_xyz for v in left_views] + [v.object_xyz for v in right_views])
        px = np.concatenate([v.pixel for v in left_views] + [v.pixel for v in right_views])
        cam = np.concatenate([np.zeros(sum(v.n for v in left_views), int), np.ones(sum(v.n for v in right_views), int)])
        sta = np.concatenate([np.repeat(np.arange(len(left_views)), [v.n for v in left_views]),
                              np.repeat(np.arange(len(right_views)), [v.n for v in right_views])])
        obs = Observations(X, px, cam.astype(np.intp), sta.astype(np.intp))
        free = free_parameters(equal_focal=kw.get("equal_focal", False), distortion=kw.get("distortion",
                               ("k1", "k2", "k3", "p1", "p2")), symmetry=kw.get("symmetry", False))
        a = adjust(obs, [cl.intrinsics.vector, cr.intrinsics.vector], [free, free], pl, rel0[None],
                   camera_labels=["left", "right"], station_labels=[v.name for v in left_views])
        sym = kw.get("symmetry", False)
        li = Intrinsics.from_vector(a.interiors[0], width, height, symmetry=sym)
        ri = Intrinsics.from_vector(a.interiors[1], rw, rh, symmetry=sym)
        m = len(free)
        se = a.std_errors
        labels = [n.rstrip("*") for n in free]
        sl = dict(zip(labels, (float(s) for s in se[:m]), strict=True))
        sr = dict(zip(labels, (float(s) for s in se[m:2 * m]), strict=True))
        rel = a.relative[0]
        o = len(a.names) - 6
        cov = a.covariance[o:, o:]

        def elements(p: F64) -> F64:
            Rcv = rodrigues(p[:3])[0]
            Rp = CV_FROM_PHOTO @ Rcv.T @ CV_FROM_PHOTO
            C = CV_FROM_PHOTO @ (-Rcv.T @ p[3:])
            return np.concatenate([angles_from_matrix(Rp), C, [np.linalg.norm(C)]])

        J = np.zeros((7, 6))
        for j in range(6):
            h = 1e-7 * (1.0 if j < 3 else max(1.0, float(np.linalg.norm(rel[3:]))))
            pp, pm = rel.copy(), rel.copy()
            pp[j] += h
            pm[j] -= h
            J[:, j] = (elements(pp) - elements(pm)) / (2 * h)
        s_el = np.sqrt(np.clip(np.diag(J @ cov @ J.T), 0, None))
        el = elements(rel)
        Rcv = rodrigues(rel[:3])[0]
        r = a.residuals
        if s_el[6] > 0.5 * el[6]:
            raise CalibrationError(f"the stereo base is unobservable: {el[6]:.3g} +- {s_el[6]:.3g}")
        return cls(li, ri, sl, sr, CV_FROM_PHOTO @ Rcv.T @ CV_FROM_PHOTO, el[3:6], s_el[:3], s_el[3:6],
                   float(s_el[6]), a.sigma0, float(np.sqrt(np.sum(r * r) / len(r))), len(left_views), a)

    @property
    def base_length(self) -> float:
        return float(np.linalg.norm(self.base))

    @property
    def angles(self) -> F64:
        """omega, phi, kappa of :attr:`rotation_right`, rad."""
        return angles_from_matrix(self.rotation_right)

    def to_dict(self, *, pixel_size_mm: float | None = None) -> dict[str, Any]:
        """Rig JSON: both cameras (version-2 camera JSON) and the relative orientation."""
        om, ph, ka = (float(x) for x in self.angles)
        return {"format": "rectify-stereo/rig", "version": 1,
                "left": intrinsics_document(self.left, std_errors=self.std_left, sigma0_px=self.sigma0_px,
                                            pixel_size_mm=pixel_size_mm),
                "right": intrinsics_document(self.right, std_errors=self.std_right, sigma0_px=self.sigma0_px,
                                             pixel_size_mm=pixel_size_mm),
                "rotation_right": self.rotation_right.tolist(), "base": self.base.tolist(),
                "relative": {"order": "omega-phi-kappa", "omega": om, "phi": ph, "kappa": ka,
                             "std_omega": float(self.std_angles[0]), "std_phi": float(self.std_angles[1]),
                             "std_kappa": float(self.std_angles[2]), "std_base": self.std_base.tolist(),
                             "base_length": self.base_length, "std_base_length": self.std_base_length},
                "sigma0_px": self.sigma0_px, "rms_px": self.rms_px, "stations": self.n_stations}

    def summary_lines(self) -> list[str]:
        om, ph, ka = (math.degrees(float(x)) for x in self.angles)
        so, sp, sk = (math.degrees(float(x)) for x in self.std_angles)
        return [f"rig: {self.n_stations} stations; RMS {self.rms_px:.4f} px, sigma0 {self.sigma0_px:.4f} px",
                f"  left  fx {self.left.fx:.3f} +- {self.std_left.get('fx', self.std_left.get('f', 0)):.3f} px, "
                f"right fx {self.right.fx:.3f} +- {self.std_right.get('fx', self.std_right.get('f', 0)):.3f} px",
                f"  relative omega, phi, kappa = {om:.4f} +- {so:.4f}, {ph:.4f} +- {sp:.4f}, {ka:.4f} +- {sk:.4f} deg",
                f"  base ({self.base[0]:.4f}, {self.base[1]:.4f}, {self.base[2]:.4f}), length {self.base_length:.4f} "
                f"+- {self.std_base_length:.4f} (target units)"]
