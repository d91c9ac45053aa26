"""The result of a relative orientation: :class:`RelativeOrientation` and :class:`RelativeGeometry`.

:class:`RelativeOrientation` holds the estimate, its precision and per-point residuals, converts
it to other systems and to Wolf & Dewitt's omega-phi-kappa form, and gives its dict form (the
content of the relative orientation JSON, :mod:`stereo.formats.orientation`). :class:`RelativeGeometry` is what
intersection needs of it, built one way: from that dict form.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError
from rectify.geometry import lsq
from rectify.geometry.camera import Camera
from rectify.geometry.points import as_pair
from rectify.geometry.residuals import ResidualTable, rms
from rectify.geometry.rotation import angles_from_matrix
from stereo.relative.solver import RelativeOptions, choose_frame, precision, solve, validate
from stereo.relative.systems import _evaluate, _rays, get_system

logger = logging.getLogger(__name__)

__all__ = ["RelativeGeometry", "RelativeOrientation", "WesternForm"]


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
    method_figures : dict or None
        System ``projective``: the fundamental matrix of the photo coordinates (in pixels) and its
        Sampson fit (written as ``"fundamental"`` in the dict form).
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
    method_figures: dict[str, Any] | None = None

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
            at the principal point (see :meth:`rectify.geometry.camera.Camera.photo_from_pixel`).
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
        prob = validate(left_mm, right_mm, focal_length_mm=focal_length_mm, system=system, robust=robust,
                        initial=initial, ids=ids, weights=weights, pixel_size_mm=pixel_size_mm)
        prob = choose_frame(prob, opts)  # dobrynin-pimshina: photo frames turned to put the base along x
        sol = solve(prob, opts)
        pr = precision(prob, sol, opts)
        sys_ = prob.system
        out = cls(
            system=sys_.name, names=sys_.names, elements=sol.elements, covariance=pr.covariance,
            sigma0_mm=pr.sigma0_mm, iterations=sol.iterations, irls_iterations=sol.irls_iterations, converged=True,
            condition_number=pr.condition_number, condition_number_raw=pr.condition_number_raw,
            focal_length_mm=prob.focal_length_mm, ids=prob.ids, left_mm=prob.left_mm, right_mm=prob.right_mm,
            parallax_mm=pr.parallax_mm, residual_mm=pr.residual_mm, weights=sol.weights, outlier=pr.outlier,
            pixel_size_mm=pixel_size_mm, robust=prob.robust, scale_mm=sol.scale, initial_method=sol.initial,
            elapsed_s=time.perf_counter() - t0, method_figures=sol.extra,
        )
        logger.info("relative orientation (%s): %d iterations, sigma0 %s mm", sys_.name, sol.iterations,
                    pr.sigma0_mm)
        return out

    @classmethod
    def from_pixels(cls, left_px: ArrayLike, right_px: ArrayLike, camera: Camera, *,
                    camera_right: Camera | None = None, **kwargs: Any) -> RelativeOrientation:
        """Like :meth:`from_points` for pixel coordinates (N, 2) and :class:`rectify.geometry.camera.Camera` objects.

        Pixels go to photo mm through the camera (principal point, fx, fy, skew, distortion), as the
        ideal camera of principal distance ``camera.focal_length_mm``; the pixel size of the left
        camera is used for pixel figures (column pixels: with fy != fx, figures along the rows
        differ from row pixels by the factor fy/fx).
        """
        cam_r = camera_right or camera
        lm = camera.photo_from_pixel(left_px)
        r = cam_r.photo_from_pixel(right_px)
        kwargs.setdefault("pixel_size_mm", camera.pixel_size_mm)
        ro = cls.from_points(lm, r, focal_length_mm=(camera.focal_length_mm, cam_r.focal_length_mm), **kwargs)
        return dataclasses.replace(ro, left_px=np.asarray(left_px, dtype=np.float64))

    # --------------------------------------------------------------- geometry
    @property
    def std_errors(self) -> NDArray[np.float64] | None:
        """(5,) standard errors of the elements, radians (``None`` without redundancy)."""
        return None if self.covariance is None else lsq.standard_errors(self.covariance)

    @property
    def correlation(self) -> NDArray[np.float64] | None:
        """(5, 5) correlation matrix of the elements."""
        return None if self.covariance is None else lsq.correlation(self.covariance)

    @property
    def element_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.names, self.elements, strict=True)}

    @property
    def rotation_left(self) -> NDArray[np.float64]:
        """(3, 3) left photo vector (x, y, -f) -> model frame."""
        return get_system(self.system).geometry(self.elements)[0]

    @property
    def rotation_right(self) -> NDArray[np.float64]:
        """(3, 3) right photo vector (x, y, -f) -> model frame."""
        return get_system(self.system).geometry(self.elements)[1]

    @property
    def base(self) -> NDArray[np.float64]:
        """(3,) unit base, right projection centre minus left, model frame."""
        return get_system(self.system).geometry(self.elements)[2]

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
        lm, r = as_pair(left_mm, right_mm, names=("left_mm", "right_mm"))
        f1, f2 = self.focal_length_mm
        return _evaluate(get_system(self.system), self.elements, _rays(lm, f1), _rays(r, f2), jac=False).parallax

    def to_system(self, system: str) -> NDArray[np.float64]:
        """Elements (5,) of the same relative geometry in another system (no re-adjustment)."""
        return get_system(system).elements_from_relative(self.relative_rotation, self.base_left)

    def western(self, bx: float = 1.0) -> WesternForm:
        """Omega-phi-kappa of the right image in the left photo frame and (bx, by, bz), with std errors.

        Standard errors are propagated from the covariance of the elements
        with the (central-difference) Jacobian of the conversion; the
        propagation is exact to first order since both forms parametrise the
        same five degrees of freedom.
        """
        sys_ = get_system(self.system)

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
            std: list[float | None] = [float(s[0]), float(s[1]), float(s[2]), float(abs(bx) * s[3]),
                                       float(abs(bx) * s[4])]
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
        out: dict[str, Any] = {
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
        """The dict form of the relative orientation JSON (:mod:`stereo.formats.orientation`, ``docs/formats.md``)."""
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
            "std_errors": None if std is None else {k: float(v) for k, v in zip(self.names, std, strict=True)},
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
            **({"fundamental": self.method_figures} if self.method_figures else {}),
        }


@dataclass(frozen=True, eq=False)
class RelativeGeometry:
    """What intersection needs from a relative orientation: the two rotations, the base, the focal lengths.

    Built one way, from the relative orientation's dict form (:meth:`RelativeOrientation.to_dict`, which
    is also the content of the relative orientation JSON read by :func:`stereo.formats.orientation.read_relative`).

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
