"""A synthetic aerial block with known truth, for tests and benchmarks.

:func:`make_block` flies ``strips`` parallel strips along the ground x axis, alternately east and
west (kappa 0 and pi), over a terrain of sines with the given relief, and measures every object
point in every image whose frame it falls into (fully vectorised: each point is tested only
against the images of the neighbouring strips and stations, so 100 000 points and 500 images take
a few seconds).

Frames: ground x east, y north, z up, metres; camera photo x along the ground x axis for kappa 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.types import BlockControl, GnssObservations, Pose, Tracks

__all__ = ["SyntheticBlock", "default_camera", "make_block", "terrain_height"]

F64 = NDArray[np.float64]


def default_camera(distortion: bool = False) -> Camera:
    """A 100 mm camera with 0.01 mm pixels, 2000 x 1500 (optionally with Brown distortion)."""
    dist = {"k1": -0.05, "k2": 0.01, "k3": 0.0, "p1": 1e-4, "p2": -5e-5} if distortion else {}
    return Camera(focal_length_mm=100.0, pixel_size_mm=0.01, width=2000, height=1500,
                  principal_point_mm=(0.02, -0.01), distortion=dist)


def terrain_height(x: F64, y: F64, relief_m: float) -> F64:
    """Terrain height (m) at ground x, y (m): sines with peak-to-peak about ``relief_m``."""
    return np.asarray(relief_m * (0.3 * np.sin(x / 170.0) * np.cos(y / 130.0) + 0.2 * np.sin((x + 2 * y) / 90.0)),
                      dtype=np.float64)


@dataclass(frozen=True, eq=False)
class SyntheticBlock:
    """A synthetic block and its truth.

    Attributes
    ----------
    camera : Camera
        The true camera (id ``"cam"``).
    cameras : dict str -> Camera
        ``{"cam": camera}``.
    true_poses, initial_poses : list of Pose
        True and perturbed (starting) exterior orientations.
    true_points, initial_points : (P, 3) float64
        True and perturbed object points, in the order of ``tracks.point_ids``.
    tracks : Tracks
        Noisy measured pixels (each point seen in >= 2 images).
    true_pixels : (M, 2) float64
        Noise-free pixels of the observations.
    blunder_obs : (B,) int64
        Observation indices with planted blunders.
    control : BlockControl
        Control and check points (``check`` flags), measured with noise.
    control_true : (K, 3) float64
        True coordinates of the control and check points.
    gnss : GnssObservations
        Noisy antenna positions (and INS angles when asked).
    flying_height_m, base_m, strip_spacing_m : float
    """

    camera: Camera
    cameras: dict[str, Camera]
    true_poses: list[Pose]
    initial_poses: list[Pose]
    true_points: F64
    initial_points: F64
    tracks: Tracks
    true_pixels: F64
    blunder_obs: NDArray[np.int64]
    control: BlockControl
    control_true: F64
    gnss: GnssObservations
    flying_height_m: float
    base_m: float
    strip_spacing_m: float


def make_block(seed: int = 0, *, strips: int = 3, images_per_strip: int = 6, forward_overlap: float = 0.6,
               side_overlap: float = 0.3, flying_height_m: float = 1000.0, relief_m: float = 60.0,
               n_points: int = 600, image_noise_px: float = 0.5, gnss_noise_m: float = 0.05,
               ins_noise_rad: float | None = None, lever_arm_m: tuple[float, float, float] | None = None,
               control_noise_m: float = 0.01, blunder_fraction: float = 0.0,
               blunder_px: tuple[float, float] = (15.0, 40.0), blunder_min_rays: int = 4,
               camera: Camera | None = None, n_check: int = 6, control_layout: str = "corners+centre",
               pose_perturbation: tuple[float, float] = (3.0, 0.01), point_perturbation_m: float = 2.0,
               margin_px: float = 10.0, noise_seed: int | None = None) -> SyntheticBlock:
    """Make a block with known truth.

    Parameters
    ----------
    seed : int
        Random seed (everything is reproducible).
    strips, images_per_strip : int
        Block layout; strips fly along ground x, alternately east (kappa 0) and west (kappa pi).
    forward_overlap, side_overlap : float
        Overlaps in [0, 1): the base is (1 - forward) times the along-track footprint (the frame
        width), the strip spacing (1 - side) times the across-track footprint (the frame height).
    flying_height_m, relief_m : float
        Flying height above the mean terrain and the terrain's relief, m.
    n_points : int
        Object points drawn uniformly over the block (only those seen twice are kept).
    image_noise_px, gnss_noise_m, control_noise_m : float
        Standard deviations of the measurement noise.
    ins_noise_rad : float, optional
        Give INS angles with this noise.
    lever_arm_m : (3,), optional
        GNSS lever arm in the camera frame, m.
    blunder_fraction : float
        Fraction of the observations given a blunder of ``blunder_px`` (uniform range) pixels in a
        random direction, at most one per point and only on points seen at least
        ``blunder_min_rays`` times (with three rays a blunder is detectable but not always
        identifiable: the other rays may be rejected instead).
    camera : Camera, optional
        The true camera (default :func:`default_camera`).
    n_check : int
        Check points drawn from the interior points.
    control_layout : str
        ``"corners+centre"``, ``"corners"`` or ``"none"``: full control points nearest to these places.
    pose_perturbation : (position m, angle rad)
        Standard deviations of the perturbation of the initial poses.
    point_perturbation_m : float
        Standard deviation of the perturbation of the initial points.
    margin_px : float
        Points closer than this to the frame edge are not measured.
    noise_seed : int, optional
        Draw the measurement noise (image, GNSS, INS, control) from this seed, so that the same
        geometry gets independent noise (Monte Carlo); default: from ``seed``.
    """
    if strips < 1 or images_per_strip < 2:
        raise InvalidInputError(f"make_block needs >= 1 strip of >= 2 images; got {strips} x {images_per_strip}")
    for name, v in (("forward_overlap", forward_overlap), ("side_overlap", side_overlap)):
        if not 0.0 <= v < 1.0:
            raise InvalidInputError(f"make_block: `{name}` must be in [0, 1); got {v!r}")
    if control_layout not in ("corners+centre", "corners", "none"):
        raise InvalidInputError(f"make_block: unknown control_layout {control_layout!r}")
    rng = np.random.default_rng(seed)
    cam = camera if camera is not None else default_camera()
    H = flying_height_m
    scale = H / cam.focal_length_mm  # ground m per photo mm
    along = cam.width * cam.pixel_size_mm * scale
    across = cam.height * cam.pixel_size_mm * scale
    base = (1.0 - forward_overlap) * along
    spacing = (1.0 - side_overlap) * across
    # poses
    n_img = strips * images_per_strip
    s_idx = np.repeat(np.arange(strips), images_per_strip)
    k_idx = np.tile(np.arange(images_per_strip), strips)
    east = s_idx % 2 == 0
    order = np.where(east, k_idx, images_per_strip - 1 - k_idx)  # flight order within a strip
    cx = k_idx * base
    cy = s_idx * spacing
    cz = H + rng.normal(0.0, 5.0, n_img)
    centres = np.column_stack([cx + rng.normal(0.0, 2.0, n_img), cy + rng.normal(0.0, 2.0, n_img), cz])
    angles = np.column_stack([rng.normal(0.0, 0.01, n_img), rng.normal(0.0, 0.01, n_img),
                              np.where(east, 0.0, np.pi) + rng.normal(0.0, 0.01, n_img)])
    Rs = np.asarray(matrix_from_angles(angles[:, 0], angles[:, 1], angles[:, 2])).reshape(n_img, 3, 3)
    names = [f"s{s}_{o:03d}" for s, o in zip(s_idx, order, strict=True)]
    poses = [Pose(names[i], "cam", centres[i], Rs[i]) for i in range(n_img)]
    # points
    lo = np.array([-along / 2 + 0.05 * along, -across / 2 + 0.05 * across])
    hi = np.array([cx.max() + along / 2 - 0.05 * along, cy.max() + across / 2 - 0.05 * across])
    xy = rng.uniform(lo, hi, (n_points, 2))
    X = np.column_stack([xy, terrain_height(xy[:, 0], xy[:, 1], relief_m)])
    # candidate images: neighbouring strips and stations
    ks = int(np.ceil(along / 2 / max(base, 1e-9))) + 1
    ss = int(np.ceil(across / 2 / max(spacing, 1e-9))) + 1
    k0 = np.rint(xy[:, 0] / max(base, 1e-9)).astype(np.int64)
    s0 = np.rint(xy[:, 1] / max(spacing, 1e-9)).astype(np.int64)
    dk, ds = np.meshgrid(np.arange(-ks, ks + 1), np.arange(-ss, ss + 1), indexing="ij")
    kk = k0[:, None] + dk.ravel()[None, :]
    sq = s0[:, None] + ds.ravel()[None, :]
    ok = (kk >= 0) & (kk < images_per_strip) & (sq >= 0) & (sq < strips)
    pt = np.broadcast_to(np.arange(n_points)[:, None], kk.shape)[ok]
    im = (sq * images_per_strip + kk)[ok]
    pix = _project(cam, Rs[im], centres[im], X[pt])
    inside = np.isfinite(pix).all(axis=1)
    inside &= (pix[:, 0] >= margin_px) & (pix[:, 0] <= cam.width - 1 - margin_px)
    inside &= (pix[:, 1] >= margin_px) & (pix[:, 1] <= cam.height - 1 - margin_px)
    pt, im, pix = pt[inside], im[inside], pix[inside]
    counts = np.bincount(pt, minlength=n_points)
    keep_pt = np.flatnonzero(counts >= 2)
    remap = np.full(n_points, -1, np.int64)
    remap[keep_pt] = np.arange(len(keep_pt))
    sel = remap[pt] >= 0
    pt, im, pix = remap[pt[sel]], im[sel], pix[sel]
    o = np.lexsort((im, pt))
    pt, im, pix = pt[o], im[o], pix[o]
    X = X[keep_pt]
    P = len(X)
    M = len(pt)
    nrng = rng if noise_seed is None else np.random.default_rng([seed, noise_seed])
    meas = pix + nrng.normal(0.0, image_noise_px, (M, 2))
    # blunders: at most one per point seen >= 3 times
    counts = np.bincount(pt, minlength=P)
    starts = np.cumsum(counts) - counts
    cand_pts = np.flatnonzero(counts >= blunder_min_rays)
    nb = int(round(blunder_fraction * M))
    nb = min(nb, len(cand_pts))
    bl_pts = rng.choice(cand_pts, nb, replace=False) if nb else np.zeros(0, np.int64)
    blunder_obs = np.sort(starts[bl_pts] + (rng.random(nb) * counts[bl_pts]).astype(np.int64)).astype(np.int64)
    if nb:
        mag = rng.uniform(blunder_px[0], blunder_px[1], nb)
        ang = rng.uniform(0, 2 * np.pi, nb)
        meas[blunder_obs] += np.column_stack([mag * np.cos(ang), mag * np.sin(ang)])
    ids = tuple(f"p{i}" for i in range(P))
    tracks = Tracks(tuple(names), ids, pt, im, meas, np.ones(M))
    # control and check points
    centre_xy = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2])
    targets = []
    if control_layout != "none":
        inset = np.array([0.12 * (hi[0] - lo[0]), 0.12 * (hi[1] - lo[1])])
        a, b = lo + inset, hi - inset
        targets = [[a[0], a[1]], [b[0], a[1]], [a[0], b[1]], [b[0], b[1]]]
        if control_layout == "corners+centre":
            targets.append(list(centre_xy))
    good = np.flatnonzero(counts >= 3)
    if len(good) == 0:
        good = np.arange(P)
    ctrl: list[int] = []
    for t in targets:
        d = np.linalg.norm(X[good, :2] - np.asarray(t), axis=1)
        for j in good[np.argsort(d)]:
            if int(j) not in ctrl:
                ctrl.append(int(j))
                break
    rest = np.setdiff1d(good, ctrl)
    inner = rest[np.all(np.abs(X[rest, :2] - centre_xy) < 0.4 * (hi - lo), axis=1)]
    pool = inner if len(inner) >= n_check else rest
    chk = [int(j) for j in rng.choice(pool, min(n_check, len(pool)), replace=False)] if n_check else []
    # no blunders on control and check points
    rows = np.array(ctrl + chk, dtype=np.int64)
    ctrl_true = X[rows]
    ctrl_meas = ctrl_true + nrng.normal(0.0, control_noise_m, ctrl_true.shape)
    control = BlockControl(tuple(ids[j] for j in rows), ctrl_meas, ("full",) * len(rows),
                           np.full((len(rows), 3), max(control_noise_m, 1e-6)),
                           np.array([False] * len(ctrl) + [True] * len(chk)))
    # GNSS
    lever = None if lever_arm_m is None else np.asarray(lever_arm_m, dtype=np.float64)
    ant = centres + (0.0 if lever is None else np.einsum("nij,j->ni", Rs, lever))
    g_pos = ant + nrng.normal(0.0, gnss_noise_m, ant.shape)
    g_ang = g_sig = None
    if ins_noise_rad is not None:
        g_ang = angles + nrng.normal(0.0, ins_noise_rad, angles.shape)
        g_sig = np.full((n_img, 3), ins_noise_rad)
    gnss = GnssObservations(tuple(names), g_pos, np.full((n_img, 3), max(gnss_noise_m, 1e-6)), lever, g_ang, g_sig)
    # perturbed start
    dp, da = pose_perturbation
    a0 = angles + rng.normal(0.0, da, angles.shape)
    R0 = np.asarray(matrix_from_angles(a0[:, 0], a0[:, 1], a0[:, 2])).reshape(n_img, 3, 3)
    c0 = centres + rng.normal(0.0, dp, centres.shape)
    init_poses = [Pose(names[i], "cam", c0[i], R0[i]) for i in range(n_img)]
    X0 = X + rng.normal(0.0, point_perturbation_m, X.shape)
    true_pix = pix
    return SyntheticBlock(cam, {"cam": cam}, poses, init_poses, X, X0, tracks, true_pix, blunder_obs, control,
                          ctrl_true, gnss, H, base, spacing)


def _project(cam: Camera, R: F64, C: F64, X: F64) -> F64:
    """Pixels (N, 2) of points X (N, 3) in images (R (N, 3, 3), C (N, 3)); NaN behind the camera."""
    p = np.einsum("nji,nj->ni", R, X - C)
    f = cam.focal_length_mm
    ok = p[:, 2] < 0
    out = np.full((len(X), 2), np.nan)
    if ok.any():
        mm = np.column_stack([-f * p[ok, 0] / p[ok, 2], -f * p[ok, 1] / p[ok, 2]])
        out[ok] = cam.pixel_from_photo(mm)
    return out


def strip_control(blk: SyntheticBlock, n_check: int, seed: int = 0) -> BlockControl:
    """Control for a one-strip block: 15 full control points nearest to a 5 x 3 lattice of stations (5 along
    the strip, 3 across) among the points seen in 3 or more images, then ``n_check`` check points drawn
    (``seed``) from the other such points; their true coordinates with std 0.01 m."""
    t, X = blk.tracks, blk.true_points
    cnt = np.bincount(t.obs_point, minlength=t.n_points)
    ctrl: list[int] = []
    for x in np.linspace(X[:, 0].min(), X[:, 0].max(), 5):
        for y in np.linspace(X[:, 1].min(), X[:, 1].max(), 3):
            d = np.where(cnt >= 3, np.hypot(X[:, 0] - x, X[:, 1] - y), np.inf)
            ctrl.append(next(int(j) for j in np.argsort(d) if int(j) not in ctrl))
    rest = np.setdiff1d(np.flatnonzero(cnt >= 3), ctrl)
    chk = [int(j) for j in np.random.default_rng(seed).choice(rest, n_check, replace=False)]
    rows = ctrl + chk
    return BlockControl(tuple(t.point_ids[j] for j in rows), X[rows], ("full",) * len(rows),
                        np.full((len(rows), 3), 0.01), np.array([False] * len(ctrl) + [True] * len(chk)))
