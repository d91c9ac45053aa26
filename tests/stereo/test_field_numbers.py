"""The numbers users rely on, computed independently (issue 32): standard errors against Monte Carlo,
redundancies counted by hand, residual signs against docs/formats.md, covariances in rotated frames,
the half-cell origin of the DSM and the tile-size independence of dense matching.

Each test recomputes its figure without the code under test (its own collinearity, its own count of
observations and unknowns, rasterio's geotransform), so that a plausible one-line mistake in the code
changes the figure and fails the test. The Monte Carlo bands follow tests/stereo/test_precision.py:
sigma0 from ``sqrt(mean(sigma0^2))`` (unbiased), standard errors from the RMS of the standardised
errors; the trial counts and the measured values are given with each test.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from rectify.geometry.points import ControlTable
from rectify.geometry.rotation import matrix_from_angles, rodrigues
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.types import BlockControl, GnssObservations, project_pixel
from stereo.calibration.result import Calibration
from stereo.calibration.views import TargetView
from stereo.dense.dsm import DSM_NODATA, DsmGrid
from stereo.pair.absolute import AbsoluteOrientation
from stereo.pair.intersection import intersect
from stereo.pair.model import ModelOptions, build_model
from stereo.pair.resection import resect
from stereo.relative.result import RelativeGeometry
from tests.support.block_synthetic import make_block
from tests.support.calibration_synthetic import board_scene, field_scene
from tests.support.stereo_support import write_known_pair

DOCS = Path(__file__).resolve().parents[2] / "docs"


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def _collinearity(R: np.ndarray, C: np.ndarray, f: float, X: np.ndarray) -> np.ndarray:
    """Photo coordinates (mm) of ground points X through a camera at C with rotation R (photo -> ground)."""
    p = (X - C) @ R  # = R^T (X - C), the photo-frame vector
    return np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]])


def test_docs_state_the_residual_convention():
    """The convention the residual tests below compare with, as docs/formats.md states it."""
    text = (DOCS / "formats.md").read_text()
    assert "residual = adjusted - observed" in text
    assert "adjusted - observed (the adjusted point projected into the image minus the measurement)" in text


# ====================================================================== bundle adjustment
def _bundle(b, k: float = 1.0, **kw):
    """Adjust ``b`` with every a-priori sigma (image, GNSS, control) multiplied by ``k``."""
    ctrl = BlockControl(b.control.ids, b.control.xyz, b.control.kind, b.control.sigma_m * k, b.control.check)
    gn = GnssObservations(b.gnss.images, b.gnss.position, b.gnss.sigma_m * k)
    return adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=ctrl, gnss=gn,
                         options=BundleOptions(image_sigma_px=0.5 * k, **kw))


def _pose_errors(r, truth) -> np.ndarray:
    e = np.array([np.r_[p.angles - q.angles, p.position - q.position] for p, q in zip(r.poses, truth, strict=True)])
    e[:, :3] = (e[:, :3] + np.pi) % (2 * np.pi) - np.pi
    return e


def test_bundle_standard_errors_do_not_depend_on_the_a_priori_scale():
    """The a-posteriori covariance sigma0^2 Q is invariant when every a-priori sigma is multiplied by k
    (Q grows by k^2, sigma0 shrinks by 1/k): std errors scaled by sigma0 (not its square) grow by
    sqrt(k) instead."""
    b = make_block(0, strips=2, images_per_strip=4, n_points=150)
    r1 = _bundle(b, 1.0)
    r3 = _bundle(b, 3.0)
    assert r3.sigma0 == pytest.approx(r1.sigma0 / 3.0, rel=1e-6)
    np.testing.assert_allclose(r3.pose_std, r1.pose_std, rtol=1e-5)
    np.testing.assert_allclose(r3.point_std, r1.point_std, rtol=1e-5)
    # a check point's error std adds its own a-priori coordinate sigma (scaled with the others here)
    rows = [list(b.control.ids).index(i) for i in r1.check_ids]
    for r, k in ((r1, 1.0), (r3, 3.0)):
        own = (b.control.sigma_m[rows] * k) ** 2
        np.testing.assert_allclose(r.check_std ** 2 - own, r1.point_std[[r1.point_ids.index(i) for i in r1.check_ids]]
                                   ** 2, rtol=1e-5)


def test_bundle_redundancy_and_sigma0_by_hand():
    """r = 2 x image observations + 3 x GNSS positions + 3 x full control points - (6 x images + 3 x points);
    the group redundancies add up to it, and sigma0^2 r = v'Pv summed by hand from the residuals and the
    a-priori sigmas (image 0.5 px, GNSS 0.05 m, control 0.01 m)."""
    b = make_block(0, strips=2, images_per_strip=4, n_points=150, noise_seed=1)
    r = _bundle(b)
    n_img, n_pts = len(b.true_poses), len(b.true_points)
    n_ctrl = int((~b.control.check).sum())
    r_hand = 2 * b.tracks.n_obs + 3 * n_img + 3 * n_ctrl - (6 * n_img + 3 * n_pts)
    assert r_hand == 225
    assert sum(r.redundancy_groups.values()) == pytest.approx(r_hand, abs=1e-6)
    assert float(np.sum(r.redundancy_numbers)) < 2 * b.tracks.n_obs
    vtpv = (float(np.sum((r.residuals_px / 0.5) ** 2)) + float(np.sum((r.gnss_residuals / 0.05) ** 2))
            + float(np.sum((r.control_residuals / 0.01) ** 2)))
    assert r.sigma0 ** 2 * r_hand == pytest.approx(vtpv, rel=1e-6)


def test_bundle_standard_errors_against_monte_carlo_with_pessimistic_priors():
    """Every a-priori sigma twice the simulated noise (sigma0 about 0.5): the reported a-posteriori
    standard errors of poses and points must still equal the spread of the estimates over 60 noise
    draws of one geometry (measured ratios 1.01 poses, 1.01 points, sigma0 0.50); scaling by sigma0
    instead of sigma0^2 gives about 1/sqrt(0.5) = 1.41 too large errors: ratios 0.72 and 0.71 measured."""
    errs, std, perr, pstd, s0 = [], [], [], [], []
    for k in range(60):
        b = make_block(0, strips=2, images_per_strip=4, n_points=150, noise_seed=100 + k)
        r = _bundle(b, 2.0)
        s0.append(r.sigma0)
        errs.append(_pose_errors(r, b.true_poses))
        std.append(r.pose_std)
        perr.append(r.points - b.true_points)
        pstd.append(r.point_std)
    assert 0.45 < math.sqrt(np.mean(np.square(s0))) < 0.55
    ratio_pose = float(np.mean(np.sqrt(np.mean(np.square(errs), axis=0)) / np.mean(std, axis=0)))
    ratio_pts = float(np.mean(np.sqrt(np.mean(np.square(perr), axis=0)) / np.mean(pstd, axis=0)))
    assert 0.88 < ratio_pose < 1.12, ratio_pose
    assert 0.9 < ratio_pts < 1.1, ratio_pts


def test_bundle_residual_signs_as_documented():
    """BundleResult: image residuals observed - computed, control residuals given - adjusted (its docstring;
    observations.csv and the report tables turn them into adjusted - observed, tested in test_seams_block)."""
    b = make_block(0, strips=2, images_per_strip=4, n_points=150, noise_seed=3)
    r = _bundle(b)
    poses = {p.image: p for p in r.poses}
    tr = b.tracks
    proj = np.empty((tr.n_obs, 2))
    for i, name in enumerate(tr.images):
        sel = tr.obs_image == i
        proj[sel] = project_pixel(b.camera, poses[name], r.points[tr.obs_point[sel]])
    np.testing.assert_allclose(r.residuals_px, tr.obs_pixel - proj, atol=1e-6)
    rows = [list(b.control.ids).index(i) for i in r.control_ids]
    adj = r.points[[r.point_ids.index(i) for i in r.control_ids]]
    np.testing.assert_allclose(r.control_residuals, b.control.xyz[rows] - adj, atol=1e-9)


# ====================================================================== calibration
def test_calibration_redundancy_counted_by_hand():
    """2 x points - (interior elements + 6 x views), also in the printed summary."""
    sc = board_scene(np.random.default_rng(4), n_views=6)
    cal = Calibration.from_views(sc.views, 640, 480, distortion=("k1", "k2", "p1", "p2"))
    n = sum(v.n for v in sc.views)
    assert cal.names == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
    hand = 2 * n - (8 + 6 * len(sc.views))
    assert cal.adjustment.redundancy == hand
    assert any(f"(redundancy {hand})" in line for line in cal.summary_lines())
    s0 = math.sqrt(float(np.sum(cal.adjustment.residuals ** 2)) / hand)
    assert cal.sigma0_px == pytest.approx(s0, rel=1e-9)


def test_calibration_sigma0_and_standard_errors_against_monte_carlo():
    """3 views of 15 field points (90 coordinates, 26 unknowns, dof 64), 0.3 px, 30 noise draws of one
    geometry: sum(dof) = 1920. sigma0 within +-6 % (measured 1.02; n instead of n - u gives 0.86), the
    standard errors rescaled to the true sigma predict the errors (RMS z measured 0.99)."""
    noise = 0.3
    sc = field_scene(np.random.default_rng(11), n_views=3, n_points=15, noise_px=noise)
    dist = ("k1", "k2", "p1", "p2")
    first = Calibration.from_views(sc.views, 640, 480, distortion=dist)
    start = (first.adjustment.interiors[0], first.adjustment.poses)
    rng = np.random.default_rng(12)
    s0sq, z = [], []
    for _ in range(30):
        views = [TargetView(v.name, v.object_xyz, e + rng.normal(0, noise, e.shape), v.ids)
                 for v, e in zip(sc.views, sc.exact, strict=True)]
        cal = Calibration.from_views(views, 640, 480, distortion=dist, start=start)
        assert cal.adjustment.redundancy == 64
        s0sq.append(cal.sigma0_px ** 2)
        se = np.array([cal.std_errors[n] for n in cal.names]) / cal.sigma0_px * noise
        z.append([(cal.value(n) - float(getattr(sc.camera, n))) / s for n, s in zip(cal.names, se, strict=True)])
    ratio = math.sqrt(float(np.mean(s0sq))) / noise
    assert 0.94 < ratio < 1.06, ratio
    rz = _rms(z)
    assert 0.8 < rz < 1.25, rz


def test_calibration_residual_sign_is_adjusted_minus_observed():
    sc = board_scene(np.random.default_rng(5), n_views=5)
    cal = Calibration.from_views(sc.views, 640, 480, distortion=("k1", "k2", "p1", "p2"))
    a = cal.adjustment
    k = 0
    for s, v in enumerate(sc.views):
        R = rodrigues(a.poses[s, :3])[0]
        proj = cal.intrinsics.project(v.object_xyz @ R.T + a.poses[s, 3:])
        np.testing.assert_allclose(a.residuals[k:k + v.n], proj - v.pixel, atol=1e-6)
        k += v.n


# ====================================================================== intersection
def _convergent_pair(rng, n=400, sigma=0.004):
    R1 = matrix_from_angles(0.02, 0.25, 0.1)
    R2 = matrix_from_angles(-0.03, -0.2, -0.05)
    C1, B = np.array([10.0, -5.0, 1000.0]), np.array([420.0, 30.0, -25.0])
    f1, f2 = 100.0, 150.0
    P = np.column_stack([rng.uniform(-200, 600, n), rng.uniform(-300, 300, n), rng.uniform(-50, 50, n)])
    x1 = _collinearity(R1, C1, f1, P) + rng.normal(0, sigma, (n, 2))
    x2 = _collinearity(R2, C1 + B, f2, P) + rng.normal(0, sigma, (n, 2))
    return R1, R2, C1, B, (f1, f2), P, x1, x2


def test_intersection_residuals_are_reprojected_minus_measured():
    rng = np.random.default_rng(31)
    R1, R2, C1, B, f, P, x1, x2 = _convergent_pair(rng)
    for method in ("least-squares", "midpoint"):
        it = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=f, centre_left=C1,
                       method=method)
        proj = np.hstack([_collinearity(R1, C1, f[0], it.points), _collinearity(R2, C1 + B, f[1], it.points)])
        np.testing.assert_allclose(it.residuals_mm, proj - np.hstack([x1, x2]), atol=1e-9)


def test_intersection_vertical_parallax_sign_in_the_normal_case():
    """docs/model.md: the signed residual vertical parallax is y2 - y1 in the normal case."""
    I3 = np.eye(3)
    x1 = np.array([[10.0, 5.0], [-3.0, -8.0]])
    x2 = np.array([[-10.0, 5.02], [-21.0, -8.03]])
    it = intersect(x1, x2, rotation_left=I3, rotation_right=I3, base=[200.0, 0, 0], focal_length_mm=100.0)
    # (at the left photo scale: y2 - y1 to within the scale ratio of the two rays, 0.2 % here)
    np.testing.assert_allclose(it.vertical_parallax_mm, x2[:, 1] - x1[:, 1], rtol=5e-3)


def test_intersection_covariance_in_a_rotated_frame_is_R_C_RT():
    """The same pair in a ground frame turned by a large rotation Q (and shifted): points Q p + t and
    covariances Q C Q^T, to rounding."""
    rng = np.random.default_rng(32)
    R1, R2, C1, B, f, P, x1, x2 = _convergent_pair(rng, n=50)
    Q = matrix_from_angles(0.7, -0.5, 1.2)
    t = np.array([1000.0, -2000.0, 300.0])
    a = intersect(x1, x2, rotation_left=R1, rotation_right=R2, base=B, focal_length_mm=f, centre_left=C1,
                  sigma_mm=0.004)
    b = intersect(x1, x2, rotation_left=Q @ R1, rotation_right=Q @ R2, base=Q @ B, focal_length_mm=f,
                  centre_left=Q @ C1 + t, sigma_mm=0.004)
    np.testing.assert_allclose(b.points, a.points @ Q.T + t, atol=1e-6)
    expect = np.einsum("ij,njk,lk->nil", Q, a.covariance, Q)
    np.testing.assert_allclose(b.covariance, expect, rtol=1e-6, atol=1e-9 * np.abs(a.covariance).max())
    # and not the other way round (the test can tell the two apart)
    wrong = np.einsum("ji,njk,kl->nil", Q, a.covariance, Q)
    assert np.abs(b.covariance - wrong).max() > 0.1 * np.abs(a.covariance).max()


# ====================================================================== absolute orientation
def _similarity_case(rng, n=12):
    R = matrix_from_angles(0.8, -0.6, 1.3)
    s, T = 7.5, np.array([5000.0, -3000.0, 250.0])
    m = rng.uniform(-50, 50, (n, 3)) * [1, 1, 0.3]
    return m, s, R, T


def test_absolute_orientation_residuals_and_point_covariance():
    """Residuals adjusted - observed = G(model) - ground (docs/formats.md); the model points' covariance
    enters the ground covariance as s^2 R C_m R^T."""
    rng = np.random.default_rng(41)
    m, s, R, T = _similarity_case(rng)
    g = s * m @ R.T + T + rng.normal(0, 0.05, m.shape)
    ao = AbsoluteOrientation.from_points(m, g)
    rows = ao.residuals
    np.testing.assert_allclose(rows.observed, g, atol=1e-9)
    np.testing.assert_allclose(rows.adjusted, ao(m), atol=1e-9)
    np.testing.assert_allclose(rows.adjusted, ao.scale * m @ ao.rotation.T + ao.translation, atol=1e-6)
    doc = ao.to_dict()
    np.testing.assert_allclose([p["residual"] for p in doc["points"]], ao(m) - g, atol=1e-6)
    # anisotropic model covariances (depth 3x noisier), turned by the similarity
    A = matrix_from_angles(0.3, 0.2, -0.4)
    Cm = np.repeat((A @ np.diag([0.01, 0.02, 0.09]) @ A.T)[None], len(m), axis=0)
    extra = ao.point_covariance(m, Cm) - ao.point_covariance(m)
    sR = ao.scale * ao.rotation
    np.testing.assert_allclose(extra, np.einsum("ij,njk,lk->nil", sR, Cm, sR), rtol=1e-9, atol=1e-12)


def test_model_ground_std_against_monte_carlo_in_a_rotated_frame():
    """A stereo model oriented to control in a ground frame turned by large angles: the ground standard
    deviations of the tie points (intersection covariance rotated to ground plus the absolute orientation's
    parameters) equal the spread over 150 noise draws (per axis, measured 0.98 .. 0.99), and the weighted
    least-squares absolute orientation's sigma0 is about 1 (measured 0.99). A covariance rotated R^T C R
    instead of R C R^T puts the model's depth noise on the wrong ground axes: control weighted that way
    gives sigma0 2.8 and ratios 0.79 .. 0.85."""
    rng = np.random.default_rng(51)
    f, sigma = 150.0, 0.005
    R1 = matrix_from_angles(0.01, -0.02, 0.0)
    R2 = matrix_from_angles(-0.01, 0.03, 0.02)
    B = np.array([1.0, 0.02, -0.01])
    n_tie, n_ctrl = 60, 8
    xy = rng.uniform([-0.6, -0.8], [1.6, 0.8], (n_tie + n_ctrl, 2))
    model = np.column_stack([xy, -2.5 + rng.uniform(-0.2, 0.2, len(xy))])
    Q = matrix_from_angles(0.9, -0.7, 2.0)
    s, T = 800.0, np.array([350_000.0, 5_600_000.0, 400.0])
    ground = s * model @ Q.T + T
    x1 = _collinearity(R1, np.zeros(3), f, model)
    x2 = _collinearity(R2, B, f, model)
    geo = RelativeGeometry(R1, R2, B, (f, f), sigma0_mm=sigma, pixel_size_mm=0.01)
    ids = [f"t{i}" for i in range(n_tie)]
    cids = tuple(f"c{i}" for i in range(n_ctrl))
    errs, stds, s0 = [], [], []
    for _ in range(150):
        n1 = x1 + rng.normal(0, sigma, x1.shape)
        n2 = x2 + rng.normal(0, sigma, x2.shape)
        ctrl = ControlTable(cids, np.zeros((n_ctrl, 2)), np.zeros((n_ctrl, 2)), ground[n_tie:], crs=None)
        mdl = build_model(n1[:n_tie], n2[:n_tie], geo, ids=ids, control=ctrl,
                          control_mm=(n1[n_tie:], n2[n_tie:]),
                          options=ModelOptions(frame="map", control_sigma_px=sigma / 0.01, robust="none"),
                          pixel_size_mm=0.01)
        k = [mdl.ids.index(i) for i in ids]
        errs.append(mdl.ground[k] - ground[:n_tie])
        stds.append(mdl.ground_std[k])
        s0.append(mdl.absolute.sigma0)
    ratio = np.sqrt(np.mean(np.square(errs), axis=0)) / np.sqrt(np.mean(np.square(stds), axis=0))
    per_axis = ratio.mean(axis=0)
    assert np.all((per_axis > 0.9) & (per_axis < 1.1)), per_axis
    # each point and axis: a 150-trial ratio has a sampling sd of 6 % (measured 0.88 .. 1.16; the wrong
    # rotation of the model covariance gives 0.35 .. 2.1)
    assert 0.75 < ratio.min() and ratio.max() < 1.3, (ratio.min(), ratio.max())
    s0r = math.sqrt(float(np.mean(np.square(s0))))
    assert 0.9 < s0r < 1.1, s0r


# ====================================================================== resection
def test_resection_residuals_are_adjusted_minus_observed():
    rng = np.random.default_rng(61)
    R = matrix_from_angles(0.05, -0.04, 0.7)
    C = np.array([500.0, 800.0, 1500.0])
    G = np.column_stack([rng.uniform(-400, 1400, 12), rng.uniform(-200, 1800, 12), rng.uniform(0, 80, 12)])
    x = _collinearity(R, C, 150.0, G) + rng.normal(0, 0.005, (12, 2))
    eo = resect(x, G, focal_length_mm=150.0)
    proj = _collinearity(eo.rotation, eo.position, 150.0, G)
    tab = eo.residuals
    np.testing.assert_allclose(tab.observed, x, atol=1e-12)
    np.testing.assert_allclose(tab.adjusted, proj, atol=1e-9)
    doc = eo.to_dict()
    np.testing.assert_allclose([p["residual_mm"] for p in doc["points"]], proj - x, atol=1e-6)


# ====================================================================== DSM: half-cell origin
def test_dsm_geotiff_cells_are_centred_where_the_geotransform_says(tmp_path):
    """Points on a steep plane z = 2 x - y: every interior cell of the written GeoTIFF holds the plane's
    height at its centre as rasterio computes it from the file's geotransform (tolerance 2 % of a cell's
    rise); half a cell off is 0.5 x 2 x cell = 1 cell side of height."""
    cell = 0.5
    rng = np.random.default_rng(71)
    xy = rng.uniform([1000.3, 2000.1], [1030.3, 2020.1], (40_000, 2))
    z = 2.0 * xy[:, 0] - xy[:, 1]
    for radius in (1.0, 0.0):
        g = DsmGrid((1000.3, 2000.1, 1030.3, 2020.1), cell, crs="EPSG:32633", radius=radius, max_spread=0)
        g.add(np.column_stack([xy, z]))
        p = g.result().write(tmp_path / f"dsm{radius}.tif", overwrite=True)
        with rasterio.open(p) as ds:
            h = ds.read(1)
            T = ds.transform
        rr, cc = np.nonzero(h != DSM_NODATA)
        inner = (rr > 2) & (cc > 2) & (rr < h.shape[0] - 3) & (cc < h.shape[1] - 3)
        rr, cc = rr[inner], cc[inner]
        x, y = rasterio.transform.xy(T, rr, cc, offset="center")
        err = h[rr, cc] - (2.0 * np.asarray(x) - np.asarray(y))
        assert len(err) > 1500
        # radius 0: the mean of the points inside the cell, at most about cell/sqrt(n) from its centre's height
        assert abs(float(np.median(err))) < 0.02 * cell, (radius, float(np.median(err)))
        assert float(np.percentile(np.abs(err), 95)) < (0.6 if radius == 0 else 0.3) * cell, radius


# ====================================================================== dense: DSM origin, tiles, rasters
@pytest.fixture(scope="module")
def dense_pair(tmp_path_factory):
    """A 320 px synthetic pair with exact exterior orientations and 40 exact tie points."""
    d = tmp_path_factory.mktemp("field_dense")
    return d, write_known_pair(d, n_ties=40, margin_px=10.0, with_crs=True)


def _run_dense(d: Path, out: Path, **options):
    from stereo.actions.dense import DenseOptions, run_dense

    return run_dense(d / "l.json", d / "l.png", d / "r.png", out, right_orientation=d / "r.json",
                     matches=d / "m.csv", options=DenseOptions(**options))


def test_dense_dsm_cells_hold_the_points_that_fall_in_them(dense_pair, tmp_path):
    """``stereo dense`` with a radius of 0 and no spread test: each DSM cell is the mean height and the
    count of the point cloud's points that fall in it, the cell found from the DSM GeoTIFF's own
    geotransform by rasterio (the same run's PLY). Half a cell off moves points into neighbour cells:
    about half the counts change."""
    d, _ = dense_pair
    out = tmp_path / "out"
    _run_dense(d, out, cloud_format="ply", dsm_radius=0.0, dsm_max_spread=0.0)
    from stereo.formats.points import read_ply_xyz

    P = read_ply_xyz(out / "points.ply")
    with rasterio.open(out / "dsm.tif") as ds:
        h, cnt = ds.read(1), ds.read(2)
        rows, cols = rasterio.transform.rowcol(ds.transform, P[:, 0], P[:, 1], op=math.floor)
    rows, cols = np.asarray(rows), np.asarray(cols)
    inside = (rows >= 0) & (cols >= 0) & (rows < h.shape[0]) & (cols < h.shape[1])
    assert inside.mean() > 0.999
    k = rows[inside] * h.shape[1] + cols[inside]
    n = np.bincount(k, minlength=h.size).reshape(h.shape)
    s = np.bincount(k, weights=P[inside, 2], minlength=h.size).reshape(h.shape)
    has = n > 0
    assert np.array_equal(h != DSM_NODATA, has)
    assert np.array_equal(cnt[has].astype(int), np.minimum(n[has], 65535))
    np.testing.assert_allclose(h[has], s[has] / n[has], atol=0.02)


def test_dense_matching_does_not_depend_on_the_tile_size(dense_pair, tmp_path):
    """Matching tiles of 64 px (20 tiles) and of 1024 px (one tile): the disparity rasters agree (measured:
    0.02 % of the pixels valid in one only, 0.1 % differing by more than 0.5 px). Tiles matched without
    their overlap give seams: 23 % and 4.7 %."""
    from stereo.dense.matching import MatchOptions

    d, _ = dense_pair
    disp = {}
    for tile in (64, 1024):
        out = tmp_path / f"t{tile}"
        r = _run_dense(d, out, cloud_format="none", matching=MatchOptions(fill_max_px=200, tile=tile))
        assert r.matching.n_tiles == (20 if tile == 64 else 1)
        with rasterio.open(out / "disparity.tif") as ds:
            disp[tile] = ds.read(1)
    a, b = disp[64], disp[1024]
    va, vb = a != -9999, b != -9999
    assert va.mean() > 0.7
    xor = float((va ^ vb).sum() / (va | vb).sum())
    both = va & vb
    off = float((np.abs(a - b)[both] > 0.5).mean())
    assert xor < 0.005 and off < 0.005, (xor, off)


def test_dense_rasters_lie_on_the_left_normal_photo(dense_pair, tmp_path):
    """disparity.tif and confidence.tif are on the left normal photo's pixel grid: same size, same
    (pixel-frame) geotransform; the DSM's geotransform is on whole multiples of its cell and covers the points."""
    d, _ = dense_pair
    out = tmp_path / "out"
    res = _run_dense(d, out, cloud_format="ply")
    from stereo.formats.points import read_ply_xyz

    with rasterio.open(out / "left_normal.tif") as ln:
        shape, T = (ln.height, ln.width), ln.transform
    for name in ("disparity.tif", "confidence.tif"):
        with rasterio.open(out / name) as ds:
            assert (ds.height, ds.width) == shape and ds.transform == T, name
    with rasterio.open(out / "dsm.tif") as ds:
        t, cell = ds.transform, res.dsm_cell
        assert t.a == pytest.approx(cell) and t.e == pytest.approx(-cell) and t.b == 0 and t.d == 0
        assert abs(t.c / cell - round(t.c / cell)) < 1e-6 and abs(t.f / cell - round(t.f / cell)) < 1e-6
        left, bottom, right, top = ds.bounds
    P = read_ply_xyz(out / "points.ply")
    # the grid covers the bounding box of a sample of the disparities (every 8th), on whole cells
    lo, hi = np.percentile(P[:, :2], 0.1, axis=0), np.percentile(P[:, :2], 99.9, axis=0)
    assert left <= lo[0] and hi[0] <= right and bottom <= lo[1] and hi[1] <= top, (lo, hi, (left, bottom, right, top))


def test_disparity_raster_has_the_left_images_georeference(tmp_path):
    """``stereo disparity`` of a georeferenced pair: the disparity raster has the left image's geotransform
    and CRS (not the right's, not shifted by half a pixel), and its values are the known shift."""
    from stereo.actions.disparity import disparity

    rng = np.random.default_rng(81)
    h, w, shift = 120, 200, 9
    big = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + shift)).astype(np.float32), (0, 0), 1.2)
    big = np.round(255 * (big - big.min()) / np.ptp(big)).astype(np.uint8)
    left, right = big[:, :w], big[:, shift:shift + w]  # col_left - col_right = shift
    TL = rasterio.Affine(0.5, 0, 300_000.25, 0, -0.5, 5_000_000.75)
    TR = rasterio.Affine(0.5, 0, 400_000.0, 0, -0.5, 6_000_000.0)
    for name, img, T in (("l.tif", left, TL), ("r.tif", right, TR)):
        with rasterio.open(tmp_path / name, "w", driver="GTiff", width=w, height=h, count=1, dtype="uint8",
                           crs="EPSG:32633", transform=T) as ds:
            ds.write(img, 1)
    disparity(tmp_path / "l.tif", tmp_path / "r.tif", tmp_path / "d.tif")
    with rasterio.open(tmp_path / "d.tif") as ds:
        assert ds.transform == TL and ds.crs == rasterio.crs.CRS.from_epsg(32633)
        dd = ds.read(1)
    ok = dd != -9999
    assert ok.mean() > 0.5 and abs(float(np.median(dd[ok])) - shift) < 0.1
