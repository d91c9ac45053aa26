"""Independent models adjusted together with control: the finished method (seed 002, 3.1.2).

The models of a :class:`~stereo.block.independent.ModelBlock` (each a pair's intersected points in
its own frame, :class:`~stereo.block.models.Model`) are brought into the ground frame in one
least-squares adjustment. Each model point gives the three observation equations of seed 002's
eq. (3.16),

    X_i = t_j A_j R_ij + R0_j,

in the ground frame (``X_i`` the ground point, ``t_j, A_j, R0_j`` the scale, rotation and
translation of model j, ``R_ij`` the point in the model), linearised as eqs. (3.17)-(3.22); the
unknowns are the 7 parameters of every model and the ground coordinates of every model point
and projection centre (a tie point and a centre are common to the models that contain them).
Control points add the observation ``X_s = G_s`` with the weights of their sigmas (only Z for a
height point, X and Y for a plan point: the structure of seed 002's vector s0, eq. 3.26); GNSS
projection centres add ``C_k = G_k``. The model points are weighted by the inverse of their
intersection covariance (for ``image_sigma_px`` of image noise) carried into the ground frame;
the two projection centres of a model, exact in it, get the median variance of its points.

Normal equations (3.23)-(3.28): the 3 x 3 blocks of the points are inverted and eliminated, the
reduced 7m x 7m system of the models is solved, the points are back-substituted; Gauss-Newton
until the corrections vanish. Model points whose normalised residual exceeds
``reject_threshold`` times max(1, the robust scale) are rejected after each iteration (seed
002: "the solution can be obtained with robust analysis"). Standard errors: the covariance of a
point is ``Q_i + Q_i M_i S^-1 M_i^T Q_i`` (``Q_i`` the inverse of its 3 x 3 block, ``M_i`` its
coupling to the models, ``S`` the reduced matrix), times sigma0^2.

Frames: ground = the frame of the control and GNSS positions (right-handed, metric); model = the
model's own frame (left centre at the origin, unit base); photo = mm, x right, y up, vector
(x, y, -f).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from rectify.errors import EstimationError, InvalidInputError, StereoError
from rectify.geometry.residuals import rms
from rectify.geometry.robust import robust_scale
from rectify.geometry.rotation import rodrigues
from stereo.block.independent import ModelBlock, to_ground
from stereo.block.models import Model, _orthonormal, _skew
from stereo.block.types import BlockControl, GnssObservations, Pose
from stereo.pair.absolute import similarity_from_points

logger = logging.getLogger(__name__)

__all__ = ["ModelAdjustOptions", "ModelsAdjusted", "adjust_models", "check_model_datum"]

F64 = NDArray[np.float64]

#: above this sigma0 the summary warns that the models do not fit each other
SIGMA0_WARN = 3.0


@dataclass(frozen=True)
class ModelAdjustOptions:
    """Options of :func:`adjust_models`.

    Attributes
    ----------
    image_sigma_px : float
        Image noise the model points' weights assume, pixels.
    robust : bool
        Reject model points beyond ``reject_threshold`` (normalised residual, times max(1, its
        robust scale)).
    reject_threshold : float
    min_tie_points : int
        Fewest points a model must share with other models or control (its projection centres not
        counted; seed 002, 3.1.1: more than three for redundancy, three at least).
    max_iterations : int
        Gauss-Newton iterations.
    """

    image_sigma_px: float = 1.0
    robust: bool = True
    reject_threshold: float = 5.0
    min_tie_points: int = 3
    max_iterations: int = 20

    def __post_init__(self) -> None:
        for name in ("image_sigma_px", "reject_threshold"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InvalidInputError(f"`{name}` must be a finite number > 0; got {v!r}")
        if int(self.min_tie_points) < 3:
            raise InvalidInputError(f"`min_tie_points` must be >= 3 (a similarity needs 3 points); got "
                                    f"{self.min_tie_points!r}")
        if int(self.max_iterations) < 1:
            raise InvalidInputError(f"`max_iterations` must be >= 1; got {self.max_iterations!r}")


@dataclass(frozen=True, eq=False)
class ModelsAdjusted:
    """The block adjusted by independent models with control (seed 002, 3.1.2).

    Attributes
    ----------
    poses : tuple of Pose
        Ground frame, one per image of the block (position = adjusted projection centre, rotation =
        the mean over its models of ``A_j`` times the image's rotation in the model).
    point_ids : tuple of str
        Track ids (P,).
    points : (P, 3) float64
        Adjusted ground coordinates; NaN for a track in no model.
    point_covariance : (P, 3, 3) float64
        A-posteriori covariance (sigma0^2 scaled), ground units^2; NaN where no point.
    position_std, angle_std : (n, 3) float64
        Standard errors of each projection centre (ground units) and of the rotation of its
        models about the ground axes (rad; the mean over the image's models).
    scale, rotation, translation : (m,), (m, 3, 3), (m, 3) float64
        Each model's similarity model -> ground (``t_j``, ``A_j``, ``R0_j``), in ``tree`` order.
    parameter_std : (m, 7) float64
        Standard errors of d ln t, the three small rotations (rad) and R0 (ground units).
    residual_model : (K,) int64
        Model (index into ``tree``) of each model point.
    residual_id : tuple of str
        Track id of each model point, ``"centre:<image>"`` for a projection centre.
    residuals : (K, 3) float64
        Adjusted ground point minus transformed model point, ground units.
    residual_used : (K,) bool
        False for rejected model points.
    sigma0 : float
        A-posteriori standard deviation of unit weight.
    redundancy : int
    iterations : int
    converged : bool
    control_ids : tuple of str
    control_residuals : (c, 3) float64
        Given minus adjusted, NaN for components not given (height or plan points).
    check_ids : tuple of str
    check_errors, check_std : (k, 3) float64
        Adjusted minus given, and its predicted standard error, ground units.
    gnss_images : tuple of str
    gnss_residuals : (g, 3) float64
        Observed minus adjusted antenna position.
    tree : tuple of (str, str)
        The models as image-name pairs.
    """

    poses: tuple[Pose, ...]
    point_ids: tuple[str, ...]
    points: F64
    point_covariance: F64
    position_std: F64
    angle_std: F64
    scale: F64
    rotation: F64
    translation: F64
    parameter_std: F64
    residual_model: NDArray[np.int64]
    residual_id: tuple[str, ...]
    residuals: F64
    residual_used: NDArray[np.bool_]
    sigma0: float
    redundancy: int
    iterations: int
    converged: bool
    control_ids: tuple[str, ...]
    control_residuals: F64
    check_ids: tuple[str, ...]
    check_errors: F64
    check_std: F64
    gnss_images: tuple[str, ...]
    gnss_residuals: F64
    tree: tuple[tuple[str, str], ...]

    def __post_init__(self) -> None:
        for name in ("points", "point_covariance", "position_std", "angle_std", "scale", "rotation", "translation",
                     "parameter_std", "residual_model", "residuals", "residual_used", "control_residuals",
                     "check_errors", "check_std", "gnss_residuals"):
            a = np.array(getattr(self, name), copy=True)
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    @property
    def point_std(self) -> F64:
        """(P, 3) standard errors of the points, ground units."""
        return np.sqrt(np.einsum("pii->pi", self.point_covariance))

    @property
    def model_rms(self) -> F64:
        """(m,) RMS 3D residual of each model's used points, ground units."""
        m = len(self.scale)
        d2 = np.sum(self.residuals ** 2, axis=1)
        u = self.residual_used
        n = np.bincount(self.residual_model[u], minlength=m)
        return np.sqrt(np.bincount(self.residual_model[u], weights=d2[u], minlength=m) / np.maximum(n, 1))

    def summary_lines(self) -> list[str]:
        """Counts, sigma0, control, check and GNSS figures."""
        used = self.residual_used
        lines = [f"independent models adjusted with control (seed 002, 3.1.2): {len(self.poses)} images, "
                 f"{len(self.scale)} models, {int(np.isfinite(self.points).all(axis=1).sum())} points, "
                 f"{self.iterations} iterations{'' if self.converged else ' (NOT converged)'}",
                 f"model points: {int(used.sum())} used, {int((~used).sum())} rejected; RMS residual "
                 f"{rms(np.linalg.norm(self.residuals[used], axis=1)):.4g}; sigma0 {self.sigma0:.3f} "
                 f"(redundancy {self.redundancy})"]
        if self.sigma0 > SIGMA0_WARN:
            lines.append(f"warning: sigma0 {self.sigma0:.3g}: the models disagree far beyond their image noise (weak "
                         "models, e.g. a narrow base / height, or wrong relative orientations); the bundle "
                         "adjustment (--method bundle) models the rays themselves")
        if len(self.control_ids):
            r = self.control_residuals[np.isfinite(self.control_residuals)]
            lines.append(f"control: {len(self.control_ids)} points, RMS residual per component {rms(r):.4g}")
        if len(self.gnss_images):
            lines.append(f"GNSS: {len(self.gnss_images)} centres, RMS residual per component "
                         f"{rms(self.gnss_residuals):.4g}")
        if len(self.check_ids):
            e = self.check_errors
            lines.append(f"check: {len(self.check_ids)} points, RMS error x {rms(e[:, 0]):.3f} y {rms(e[:, 1]):.3f} "
                         f"z {rms(e[:, 2]):.3f}")
        return lines


# --------------------------------------------------------------------------- checks
def _control_rows(block: ModelBlock, control: BlockControl | None, in_model: NDArray[np.bool_]
                  ) -> tuple[NDArray[np.int64], F64, F64, NDArray[np.int64], list[str]]:
    """(track rows, given xyz, weight diag (NaN-free, 0 for unobserved), check rows, check ids)."""
    if control is None:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), []
    index = {p: k for k, p in enumerate(block.point_ids)}
    unknown = [i for i in control.ids if i not in index]
    if unknown:
        raise InvalidInputError(f"control point(s) {unknown[:5]} are not tracks of the block")
    rows, xyz, w, chk, chk_ids = [], [], [], [], []
    for k, pid in enumerate(control.ids):
        r = index[pid]
        if not in_model[r]:
            continue
        if control.check[k]:
            chk.append(r)
            chk_ids.append(pid)
            continue
        mask = {"full": (1, 1, 1), "height": (0, 0, 1), "plan": (1, 1, 0)}[control.kind[k]]
        rows.append(r)
        xyz.append(control.xyz[k])
        w.append(np.asarray(mask, dtype=np.float64) / control.sigma_m[k] ** 2)
    return (np.asarray(rows, np.int64), np.asarray(xyz).reshape(-1, 3), np.asarray(w).reshape(-1, 3),
            np.asarray(chk, np.int64), chk_ids)


def check_model_datum(n_plan: int, n_height: int, height_xy: F64, what: str) -> None:
    """Raise unless the control defines the datum of a model block (seed 002, 3.1.1).

    At least two points with plan coordinates and three with heights, the height points not on
    one line (``height_xy``: their plan positions, (n, 2)); ``what`` names the control counted.
    """
    ok = n_plan >= 2 and n_height >= 3
    if ok and len(height_xy) >= 3:
        c = height_xy - height_xy.mean(axis=0)
        sv = np.linalg.svd(c, compute_uv=False)
        ok = bool(sv[0] > 0 and sv[1] > 1e-3 * sv[0])
        if not ok:
            raise EstimationError(f"the height control of the independent models is on one line ({what}): the "
                                  "tilt about that line is undetermined; add control off it")
    if not ok:
        raise EstimationError(f"too little control for independent models: at least 2 points with plan coordinates "
                              f"and 3 with heights are needed (seed 002, 3.1.1: two full control points and a third "
                              f"with a height); got {n_plan} plan and {n_height} height ({what})")


def _tie_check(models: tuple[Model, ...], names: list[tuple[str, str]], ctrl_rows: NDArray[np.int64],
               n_tracks: int, minimum: int) -> None:
    count = np.zeros(n_tracks, np.int64)
    for m in models:
        np.add.at(count, m.tracks, 1)
    is_ctrl = np.zeros(n_tracks, bool)
    is_ctrl[ctrl_rows] = True
    for m, (a, b) in zip(models, names, strict=True):
        k = int(((count[m.tracks] >= 2) | is_ctrl[m.tracks]).sum())
        if k < minimum:
            raise StereoError(f"model {a!r}-{b!r} shares {k} tie points with other models or control; at least "
                              f"{minimum} are needed (seed 002, 3.1.1): add tie points in its overlaps")


# --------------------------------------------------------------------------- adjustment
def adjust_models(block: ModelBlock, *, control: BlockControl | None = None, gnss: GnssObservations | None = None,
                  options: ModelAdjustOptions | None = None) -> ModelsAdjusted:
    """Adjust the independent models of ``block`` together with control and GNSS centres.

    Parameters
    ----------
    block : ModelBlock
        From :func:`stereo.block.independent.independent_models` (its ``models`` and ``tree``).
    control : BlockControl, optional
        Control (``check`` rows are check points only), ground frame; points in no model are left
        out.
    gnss : GnssObservations, optional
        Antenna positions with their sigmas (the lever arm applied with the models' rotations);
        INS angles are not used by this method.
    options : ModelAdjustOptions, optional

    Returns
    -------
    ModelsAdjusted

    Raises
    ------
    EstimationError
        Too little control (named minimum: 2 plan and 3 height points, GNSS centres counting as
        full points), height control on one line, a singular system.
    StereoError
        A model sharing too few tie points (named), a block without models.
    InvalidInputError
        Control ids that are not tracks, GNSS images that are not images of the block.
    """
    opts = options or ModelAdjustOptions()
    models = block.models
    if not models:
        raise StereoError("the model block holds no models (a block of independent models needs at least one pair)")
    names = [p.image for p in block.poses]
    tree_names = [(names[a], names[b]) for a, b in block.tree]
    n_img, P, m = len(names), len(block.point_ids), len(models)
    in_model = np.zeros(P, bool)
    for mdl in models:
        in_model[mdl.tracks] = True
    c_rows, c_xyz, c_w, k_rows, k_ids = _control_rows(block, control, in_model)
    g_img, g_pos, g_w = _gnss_rows(names, gnss)
    n_plan = int((c_w[:, 0] > 0).sum()) + len(g_img)
    n_height = int((c_w[:, 2] > 0).sum()) + len(g_img)
    what = f"{len(c_rows)} control points in the models, {len(g_img)} GNSS centres"
    # plan positions of the height points: given, else from the block brought to the ground below
    _tie_check(models, tree_names, c_rows, P, int(opts.min_tie_points))
    if n_plan < 2 or n_height < 3:
        check_model_datum(n_plan, n_height, np.zeros((0, 2)), what)
    ctrl_init = None
    if len(c_rows):
        full_or_h = c_w[:, 2] > 0
        xyz0 = np.where(c_w > 0, c_xyz, np.nan)[full_or_h]
        xyz0[~np.isfinite(xyz0[:, :2]).all(axis=1), :2] = np.nan
        if full_or_h.any():
            ctrl_init = ([block.point_ids[r] for r in c_rows[full_or_h]], xyz0)
    gb = to_ground(block, control=ctrl_init, gnss=(list(g_img), g_pos) if len(g_img) else None, robust="none")
    ground_pts = np.asarray(gb.points)
    ground_pos = np.array([p.position for p in gb.poses]).reshape(-1, 3)
    hxy = np.vstack([np.where(np.isfinite(c_xyz[:, :2]) & (c_w[:, :2] > 0), c_xyz[:, :2], ground_pts[c_rows, :2])
                     [c_w[:, 2] > 0], g_pos[:, :2]])
    hxy = hxy[np.isfinite(hxy).all(axis=1)]
    check_model_datum(n_plan, n_height, hxy, what)
    # observations: model j, unknown u (tracks 0..P-1, centres P + image), model coordinates, covariance
    oj_l, ou_l, om_l, oc_l = [], [], [], []
    for j, (mdl, (a, b)) in enumerate(zip(models, block.tree, strict=True)):
        oj_l.append(np.full(len(mdl.tracks) + 2, j))
        ou_l.append(np.concatenate([mdl.tracks, [P + a, P + b]]))
        om_l.append(np.vstack([mdl.points, np.zeros(3), mdl.base]))
        lam = np.trace(mdl.covariance, axis1=1, axis2=2) / 3 if len(mdl.covariance) else np.ones(1)
        c0 = np.eye(3) * max(float(np.median(lam)), 1e-300)
        oc_l.append(np.concatenate([mdl.covariance, c0[None], c0[None]]) * opts.image_sigma_px ** 2)
    oj, ou_full = np.concatenate(oj_l), np.concatenate(ou_l)
    om, oc = np.concatenate(om_l), np.concatenate(oc_l)
    uniq, ou = np.unique(ou_full, return_inverse=True)
    nu = len(uniq)
    where = np.full(P + n_img, -1, np.int64)
    where[uniq] = np.arange(nu)
    # starting values: each model's similarity to the block brought to the ground
    guess = np.vstack([ground_pts, ground_pos])
    s = np.empty(m)
    R = np.empty((m, 3, 3))
    T = np.empty((m, 3))
    for j in range(m):
        sel = oj == j
        g = guess[ou_full[sel]]
        ok = np.isfinite(g).all(axis=1)
        try:
            s[j], R[j], T[j] = similarity_from_points(om[sel][ok], g[ok])
        except EstimationError as err:
            raise StereoError(f"model {tree_names[j][0]!r}-{tree_names[j][1]!r} could not be brought to the ground: "
                              f"{err}") from err
    tr = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om) + T[oj]
    X = np.zeros((nu, 3))
    np.add.at(X, ou, tr)
    X /= np.bincount(ou, minlength=nu)[:, None]
    Cb = (s[oj] ** 2)[:, None, None] * np.einsum("nij,njk,nlk->nil", R[oj], oc, R[oj])
    W = np.linalg.inv(Cb)
    # control and GNSS observations on unknowns
    cu = where[c_rows]
    gu = where[P + np.array([names.index(i) for i in g_img], dtype=np.int64)] if len(g_img) else np.zeros(0, np.int64)
    lever = None if gnss is None or gnss.lever_arm_m is None else np.asarray(gnss.lever_arm_m, dtype=np.float64)
    rot_img = np.array([p.rotation for p in gb.poses]).reshape(-1, 3, 3)
    g_obs = g_pos.copy()
    if lever is not None and len(g_img):
        g_obs = g_pos - np.einsum("nij,j->ni", rot_img[[names.index(i) for i in g_img]], lever)
    ext_u = np.concatenate([cu, gu])
    ext_G = np.vstack([c_xyz, g_obs])
    ext_w = np.vstack([c_w, g_w])                     # diagonal weights, 0 where not observed
    ext_G = np.where(ext_w > 0, ext_G, 0.0)
    w = np.ones(len(oj))
    pa, pb = _pairs(ou, nu)
    converged = False
    it = 0
    cf: tuple[F64, bool] = (np.eye(7 * m), False)
    d = np.ones(7 * m)
    Q = np.zeros((nu, 3, 3))
    for it in range(1, int(opts.max_iterations) + 1):
        sRm = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om)
        r = sRm + T[oj] - X[ou]
        A = np.zeros((len(oj), 3, 7))
        A[:, :, 0] = sRm
        A[:, :, 1:4] = -_skew(sRm)
        A[:, :, 4:7] = np.eye(3)
        We = W * w[:, None, None]
        Y = np.einsum("nki,nkl->nil", A, We)                      # A^T W (n, 7, 3)
        Nuu = np.zeros((nu, 3, 3))
        gu_ = np.zeros((nu, 3))
        np.add.at(Nuu, ou, We)
        np.add.at(gu_, ou, np.einsum("nij,nj->ni", We, r))
        re = X[ext_u] - ext_G
        np.add.at(Nuu, ext_u, ext_w[:, :, None] * np.eye(3)[None])
        np.add.at(gu_, ext_u, -ext_w * re)
        ok_u = np.linalg.det(Nuu) > 0                          # a point whose observations were all rejected
        Q = np.zeros_like(Nuu)                                  # stays where it is (and is left out)
        Q[ok_u] = np.linalg.inv(Nuu[ok_u])
        Z = np.einsum("nij,njk->nik", Y, Q[ou])                    # (n, 7, 3)
        S4 = np.zeros((m, m, 7, 7))
        np.add.at(S4, (oj, oj), np.einsum("nij,njk->nik", Y, A))
        np.add.at(S4, (oj[pa], oj[pb]), -np.einsum("nij,nkj->nik", Z[pa], Y[pb]))
        rhs = np.zeros((m, 7))
        np.add.at(rhs, oj, -np.einsum("nij,nj->ni", Y, r) + np.einsum("nij,nj->ni", Z, gu_[ou]))
        S = S4.transpose(0, 2, 1, 3).reshape(7 * m, 7 * m)
        d = np.sqrt(np.maximum(np.diag(S), 1e-300))
        try:  # Cholesky of the Jacobi-scaled reduced matrix: fails on a datum defect or a loose model
            cf = cho_factor(S / d[:, None] / d[None, :])
        except np.linalg.LinAlgError as err:
            raise EstimationError(f"the independent-model adjustment of {m} models is singular (a model or the "
                                  f"datum is not determined): {err}") from err
        dp = (cho_solve(cf, rhs.reshape(-1) / d) / d).reshape(m, 7)
        back = gu_.copy()
        np.add.at(back, ou, np.einsum("nji,nj->ni", Y, dp[oj]))
        dX = np.einsum("nij,nj->ni", Q, back)
        s = s * np.exp(dp[:, 0])
        R = np.stack([rodrigues(dp[k, 1:4])[0] @ R[k] for k in range(m)])
        T = T + dp[:, 4:7]
        X = X + dX
        size = max(float(np.max(s)), 1e-300)
        step = max(float(np.abs(dp[:, :4]).max()), float(np.abs(dp[:, 4:]).max()) / size,
                   float(np.abs(dX).max()) / size)
        changed = False
        if opts.robust and (it >= 3 or step < 1e-6):            # reject only once the start's errors are gone
            r = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om) + T[oj] - X[ou]
            e = np.sqrt(np.einsum("ni,nij,nj->n", r, W, r) / 3)
            live = w > 0
            sc = robust_scale(e[live]) if live.any() else 0.0
            far = e > opts.reject_threshold * max(sc, 1.0)
            changed = bool(np.any(far != ~live))
            w = np.where(far, 0.0, 1.0)
        if step < 1e-10 and not changed:
            converged = True
            break
    # residuals, sigma0
    r = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om) + T[oj] - X[ou]
    live = w > 0
    vpv = float(np.einsum("ni,nij,nj->n", r, W, r)[live].sum())
    re = X[ext_u] - ext_G
    vpv += float(np.sum(ext_w * re ** 2))
    n_eq = 3 * int(live.sum()) + int((ext_w > 0).sum())
    dof = n_eq - 7 * m - 3 * nu
    sigma0 = math.sqrt(vpv / dof) if dof > 0 else float("nan")
    s02 = sigma0 ** 2 if dof > 0 else 1.0
    # covariances: parameters (S^-1) and unknowns (Q + Z^T S^-1 Z)
    Sinv = cho_solve(cf, np.eye(7 * m)) / d[:, None] / d[None, :]
    Y = np.einsum("nki,nkl->nil", _design(s, R, oj, om), W * w[:, None, None])
    Z = np.einsum("nij,njk->nik", Y, Q[ou])
    S4inv = Sinv.reshape(m, 7, m, 7).transpose(0, 2, 1, 3)
    Cu = Q.copy()
    np.add.at(Cu, ou[pa], np.einsum("nji,njk,nkl->nil", Z[pa], S4inv[oj[pa], oj[pb]], Z[pb]))
    Cu *= s02
    par_std = np.sqrt(np.maximum(np.diag(Sinv) * s02, 0.0)).reshape(m, 7)
    return _result(block, names, tree_names, uniq, X, Cu, s, R, T, par_std, oj, ou_full, r, live, sigma0, dof, it,
                   converged, c_rows, c_xyz, c_w, k_rows, k_ids, control, g_img, g_pos, gu, lever)


def _design(s: F64, R: F64, oj: NDArray[np.int64], om: F64) -> F64:
    sRm = s[oj, None] * np.einsum("nij,nj->ni", R[oj], om)
    A = np.zeros((len(oj), 3, 7))
    A[:, :, 0] = sRm
    A[:, :, 1:4] = -_skew(sRm)
    A[:, :, 4:7] = np.eye(3)
    return A


def _pairs(ou: NDArray[np.int64], nu: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """All ordered pairs (self pairs included) of observations of the same unknown."""
    order = np.argsort(ou, kind="stable")
    cnt = np.bincount(ou, minlength=nu)
    pa_l, pb_l = [order], [order]
    for off in range(1, int(cnt.max()) if len(cnt) else 1):
        same = ou[order[:-off]] == ou[order[off:]]
        pa_l += [order[:-off][same], order[off:][same]]
        pb_l += [order[off:][same], order[:-off][same]]
    return np.concatenate(pa_l), np.concatenate(pb_l)


def _gnss_rows(names: list[str], gnss: GnssObservations | None) -> tuple[tuple[str, ...], F64, F64]:
    if gnss is None:
        return (), np.zeros((0, 3)), np.zeros((0, 3))
    unknown = [i for i in gnss.images if i not in names]
    if unknown:
        raise InvalidInputError(f"GNSS image(s) {unknown[:5]} are not images of the block")
    return (tuple(gnss.images), np.asarray(gnss.position, dtype=np.float64).reshape(-1, 3),
            1.0 / np.asarray(gnss.sigma_m, dtype=np.float64).reshape(-1, 3) ** 2)


def _result(block: ModelBlock, names: list[str], tree_names: list[tuple[str, str]], uniq: NDArray[np.int64], X: F64,
            Cu: F64, s: F64, R: F64, T: F64, par_std: F64, oj: NDArray[np.int64], ou_full: NDArray[np.int64], r: F64,
            live: NDArray[np.bool_], sigma0: float, dof: int, it: int, converged: bool, c_rows: NDArray[np.int64],
            c_xyz: F64, c_w: F64, k_rows: NDArray[np.int64], k_ids: list[str], control: BlockControl | None,
            g_img: tuple[str, ...], g_pos: F64, gu: NDArray[np.int64], lever: F64 | None) -> ModelsAdjusted:
    P, n_img = len(block.point_ids), len(names)
    pts = np.full((P + n_img, 3), np.nan)
    cov = np.full((P + n_img, 3, 3), np.nan)
    pts[uniq] = X
    cov[uniq] = Cu
    # image rotations: mean over the models of A_j times the image's rotation in the model
    rot_sum = np.zeros((n_img, 3, 3))
    ang_var = np.zeros((n_img, 3))
    cnt = np.zeros(n_img)
    for j, (mdl, (a, b)) in enumerate(zip(block.models, block.tree, strict=True)):
        for img, Rm in ((a, mdl.rotation_left), (b, mdl.rotation_right)):
            rot_sum[img] += R[j] @ Rm
            ang_var[img] += par_std[j, 1:4] ** 2
            cnt[img] += 1
    poses = []
    for i, p in enumerate(block.poses):
        rot = _orthonormal(rot_sum[i]) if cnt[i] else p.rotation
        poses.append(Pose(p.image, p.camera, pts[P + i], rot))
    angle_std = np.sqrt(ang_var / np.maximum(cnt, 1)[:, None])
    rid = tuple(block.point_ids[u] if u < P else f"centre:{names[u - P]}" for u in ou_full.tolist())
    given = np.where(c_w > 0, c_xyz, np.nan)
    ctrl_res = given - pts[c_rows] if len(c_rows) else np.zeros((0, 3))
    chk_err = np.zeros((0, 3))
    chk_std = np.zeros((0, 3))
    if len(k_rows) and control is not None:
        where = {pid: k for k, pid in enumerate(control.ids)}
        chk_xyz = np.array([control.xyz[where[i]] for i in k_ids]).reshape(-1, 3)
        chk_err = pts[k_rows] - chk_xyz
        chk_std = np.sqrt(np.einsum("kii->ki", cov[k_rows]))
    gres = np.zeros((0, 3))
    if len(g_img):
        idx = [names.index(i) for i in g_img]
        ant = pts[P + np.array(idx)]
        if lever is not None:
            ant = ant + np.einsum("nij,j->ni", np.array([poses[i].rotation for i in idx]), lever)
        gres = g_pos - ant
    pos_std = np.sqrt(np.einsum("nii->ni", cov[P:]))
    return ModelsAdjusted(poses=tuple(poses), point_ids=block.point_ids, points=pts[:P], point_covariance=cov[:P],
                          position_std=pos_std, angle_std=angle_std, scale=s, rotation=R, translation=T,
                          parameter_std=par_std, residual_model=oj, residual_id=rid, residuals=-r, residual_used=live,
                          sigma0=sigma0, redundancy=int(dof), iterations=it, converged=converged,
                          control_ids=tuple(block.point_ids[i] for i in c_rows), control_residuals=ctrl_res,
                          check_ids=tuple(k_ids), check_errors=chk_err, check_std=chk_std, gnss_images=g_img,
                          gnss_residuals=gres, tree=tuple(tree_names))
