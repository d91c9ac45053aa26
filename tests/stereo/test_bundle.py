"""Bundle adjustment of a block (stereo.block.bundle.adjust) on synthetic blocks with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.bundle import solve as bs
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.model import interior_from_camera, project, rotation_axes, rotations
from stereo.block.types import BlockControl, GnssObservations, Pose, Tracks, project_pixel
from tests.support.block_synthetic import default_camera, make_block

DIST = Camera(focal_length_mm=100.0, pixel_size_mm=0.01, width=2000, height=1500, principal_point_mm=(0.03, -0.02),
              distortion={"k1": -0.08, "k2": 0.02, "k3": -0.01, "p1": 2e-4, "p2": -1e-4})


def _model(camera: Camera, pose: Pose, X: np.ndarray, jacobian: bool = True):
    m = len(X)
    ang = pose.angles[None, :]
    R = np.repeat(rotations(ang), m, axis=0)
    ax = np.repeat(rotation_axes(ang), m, axis=0)
    intr = np.repeat(interior_from_camera(camera)[None], m, axis=0)
    return project(R, np.repeat(pose.position[None], m, axis=0), ax, intr, np.full(m, camera.pixel_size_mm),
                   np.repeat([[(camera.width - 1) / 2, (camera.height - 1) / 2]], m, axis=0), X, jacobian=jacobian)


def _pose(angles, position, name="a") -> Pose:
    return Pose(name, "cam", np.asarray(position, float), matrix_from_angles(*angles))


# ------------------------------------------------------------------ the model
def test_model_equals_project_pixel_with_distortion():
    rng = np.random.default_rng(1)
    pose = _pose((0.02, -0.03, 2.9), (10.0, 20.0, 1000.0))
    X = np.column_stack([rng.uniform(-60, 80, 50), rng.uniform(-40, 80, 50), rng.uniform(-30, 30, 50)])
    pix = _model(DIST, pose, X, jacobian=False)[0]
    np.testing.assert_allclose(pix, project_pixel(DIST, pose, X), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(om=st.floats(-0.3, 0.3), ph=st.floats(-0.3, 0.3), ka=st.floats(-np.pi, np.pi),
       cx=st.floats(-100, 100), cy=st.floats(-100, 100), h=st.floats(300, 3000))
def test_model_equals_project_pixel_property(om, ph, ka, cx, cy, h):
    pose = _pose((om, ph, ka), (cx, cy, h))
    rng = np.random.default_rng(2)
    # points near the optical axis, in front of the camera
    rays = np.column_stack([rng.uniform(-6, 6, 20), rng.uniform(-5, 5, 20), np.full(20, -100.0)])
    X = pose.position + (rays @ pose.rotation.T) * (h / 100.0)
    pix = _model(DIST, pose, X, jacobian=False)[0]
    np.testing.assert_allclose(pix, project_pixel(DIST, pose, X), atol=1e-7)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    pose = _pose((0.05, -0.04, 0.3), (5.0, -3.0, 900.0))
    X = np.column_stack([rng.uniform(-60, 60, 8), rng.uniform(-50, 50, 8), rng.uniform(-20, 20, 8)])
    pix, _, Jpose, Jpt, Jint = _model(DIST, pose, X)
    ang0, C0, intr0 = pose.angles, pose.position, interior_from_camera(DIST)
    m = len(X)

    def f(ang, C, intr, Xp):
        R = np.repeat(rotations(ang[None]), m, axis=0)
        return project(R, np.repeat(C[None], m, 0), np.repeat(rotation_axes(ang[None]), m, 0),
                       np.repeat(intr[None], m, 0), np.full(m, DIST.pixel_size_mm),
                       np.repeat([[(DIST.width - 1) / 2, (DIST.height - 1) / 2]], m, 0), Xp, jacobian=False)[0]

    def num(k, which, eps):
        a, c, i, x = ang0.copy(), C0.copy(), intr0.copy(), X.copy()
        vec = {"a": a, "c": c, "i": i}
        if which == "x":
            xp, xm = X.copy(), X.copy()
            xp[:, k] += eps
            xm[:, k] -= eps
            return (f(a, c, i, xp) - f(a, c, i, xm)) / (2 * eps)
        v = vec[which]
        v[k] += eps
        up = f(a, c, i, x)
        v[k] -= 2 * eps
        return (up - f(a, c, i, x)) / (2 * eps)

    for k in range(3):
        np.testing.assert_allclose(Jpose[:, :, k], num(k, "a", 1e-7), rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(Jpose[:, :, 3 + k], num(k, "c", 1e-4), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(Jpt[:, :, k], num(k, "x", 1e-4), rtol=1e-5, atol=1e-6)
    for k, eps in enumerate((1e-5, 1e-6, 1e-6, 1e-7, 1e-7, 1e-7, 1e-8, 1e-8)):
        np.testing.assert_allclose(Jint[:, :, k], num(k, "i", eps), rtol=1e-4, atol=1e-3)


# ------------------------------------------------------------------ exact data
def _exact_block(**kw):
    return make_block(0, image_noise_px=0.0, gnss_noise_m=0.0, control_noise_m=0.0, **kw)


def test_exact_data_recovers_truth_from_perturbed_start():
    b = _exact_block(camera=DIST)
    ctrl = BlockControl(b.control.ids, b.control.xyz, b.control.kind, np.full_like(b.control.xyz, 0.05),
                        b.control.check)
    gn = GnssObservations(b.gnss.images, b.gnss.position, np.full((len(b.gnss.images), 3), 0.1))
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=ctrl, gnss=gn)
    assert r.converged
    ext = np.ptp(b.true_points, axis=0).max()
    assert np.abs(r.points - b.true_points).max() < 1e-6 * ext
    for p, q in zip(r.poses, b.true_poses, strict=True):
        assert np.abs(p.position - q.position).max() < 1e-6 * ext
        np.testing.assert_allclose(p.rotation, q.rotation, atol=1e-8)
    assert r.rms_px < 1e-6
    assert not r.flagged.any()
    np.testing.assert_allclose(r.check_errors, 0.0, atol=1e-6 * ext)


# ------------------------------------------------------------------ noisy block, robust
def _norm_rms(err, std):
    return float(np.sqrt(np.mean((err / std) ** 2)))


def _pose_errors(r, truth):
    e = np.array([np.r_[p.angles - q.angles, p.position - q.position] for p, q in zip(r.poses, truth, strict=True)])
    e[:, :3] = (e[:, :3] + np.pi) % (2 * np.pi) - np.pi
    return e


def test_noisy_block_with_blunders_robust():
    b = make_block(0, blunder_fraction=0.05)
    assert len(b.blunder_obs) >= 0.04 * b.tracks.n_obs
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                      options=BundleOptions(robust="tukey", image_sigma_px=0.5))
    assert r.converged
    flagged = set(r.flagged_obs.tolist())
    assert set(b.blunder_obs.tolist()) <= flagged           # every planted blunder flagged
    assert len(flagged - set(b.blunder_obs.tolist())) <= 5  # seed 0: 0 false flags
    assert _norm_rms(r.check_errors, r.check_std) < 1.5
    assert _norm_rms(_pose_errors(r, b.true_poses), r.pose_std) < 1.5
    assert 0.9 < r.sigma0 < 1.1
    assert 0.3 < r.rms_px < 0.5
    lines = r.summary_lines()
    assert any("flagged as blunders" in s for s in lines) and any("sigma0" in s for s in lines)
    assert r.pose_covariance.shape == (18, 6, 6) and r.correlation.shape == (108, 108)
    np.testing.assert_allclose(np.diag(r.correlation), 1.0)


def test_predicted_std_agrees_with_monte_carlo():
    trials = 30
    errs, pred_pose, perrs, pred_pts = [], [], [], []
    for k in range(trials):
        b = make_block(0, noise_seed=k)
        r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                          options=BundleOptions(image_sigma_px=0.5))
        errs.append(_pose_errors(r, b.true_poses))
        pred_pose.append(r.pose_std / r.sigma0)  # a-priori (sigma0 = 1) prediction
        perrs.append(r.points - b.true_points)
        pred_pts.append(r.point_std / r.sigma0)
    emp = np.sqrt(np.mean(np.array(errs) ** 2, axis=0))
    pred = np.mean(pred_pose, axis=0)
    ratio = np.mean(emp / pred)
    assert 0.9 < ratio < 1.1, ratio
    emp_p = np.sqrt(np.mean(np.array(perrs) ** 2, axis=0))
    ratio_p = np.mean(emp_p / np.mean(pred_pts, axis=0))
    assert 0.9 < ratio_p < 1.1, ratio_p


# ------------------------------------------------------------------ datum
def test_datum_corner_control_without_gnss():
    b = make_block(0, control_layout="corners")
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control,
                      options=BundleOptions(image_sigma_px=0.5))
    text = "\n".join(r.datum)
    assert r.datum_groups == ("control",)
    assert "no GNSS, control at 4 points" in text
    assert "control only at the block edge" in text and "heights in the block interior rest on" in text
    ctrl_pts = [b.tracks.point_ids.index(i) for i in r.control_ids]
    sz_ctrl = np.median(r.point_std[ctrl_pts, 2])
    others = np.setdiff1d(np.arange(len(r.points)), ctrl_pts)
    q95 = np.percentile(r.point_std[others, 2], 95)
    assert q95 > 3 * sz_ctrl
    assert f"95th percentile {q95:.3f} m" in text and f"{sz_ctrl:.3f} m at the control points" in text
    assert np.isfinite(r.condition_number) and r.condition_number > 1
    assert _norm_rms(r.check_errors, r.check_std) < 1.5


def test_datum_gnss_without_control():
    b = make_block(0)
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, gnss=b.gnss,
                      options=BundleOptions(image_sigma_px=0.5))
    assert r.datum_groups == ("gnss",)
    assert any("the datum rests on GNSS alone; a GNSS bias would shift the whole block undetected" in s
               for s in r.datum)
    assert r.control_ids == () and len(r.check_ids) == 0
    assert r.pose_std[:, 5].max() < 0.1


def test_datum_defect_without_control_and_gnss():
    b = make_block(0)
    with pytest.raises(EstimationError, match="datum defect.*give control points"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points)
    ctrl = BlockControl(b.control.ids[:2], b.control.xyz[:2])
    with pytest.raises(EstimationError, match="datum defect: 0 GNSS positions, 2 plan and 2 height"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=ctrl)
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points,
                      options=BundleOptions(image_sigma_px=0.5, free_network=True))
    assert "free network" in r.datum_groups and r.datum[0].startswith("datum: free network")


# ------------------------------------------------------------------ self-calibration, VCE
def test_self_calibration_recovers_interior():
    true = default_camera(distortion=True)
    b = make_block(1, camera=true, relief_m=250.0, n_points=900, gnss_noise_m=0.02)
    start = Camera(focal_length_mm=100.08, pixel_size_mm=0.01, width=2000, height=1500,
                   principal_point_mm=(0.0, 0.0), distortion={**true.distortion, "k1": true.distortion["k1"] + 0.02})
    r = adjust_bundle({"cam": start}, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                      options=BundleOptions(image_sigma_px=0.5, self_calibrate=("f", "x0", "y0", "k1")))
    cam = r.cameras["cam"]
    std = r.interior_std["cam"]
    assert set(std) == {"f", "x0", "y0", "k1"} and cam.std_errors["f"] == std["f"]
    assert abs(cam.focal_length_mm - true.focal_length_mm) < 3 * std["f"]
    assert abs(cam.principal_point_mm[0] - true.principal_point_mm[0]) < 3 * std["x0"]
    assert abs(cam.principal_point_mm[1] - true.principal_point_mm[1]) < 3 * std["y0"]
    assert abs(cam.distortion["k1"] - true.distortion["k1"]) < 3 * std["k1"]
    assert std["f"] < 0.05


def test_variance_components_find_a_wrong_group_sigma():
    b = make_block(0)
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                      options=BundleOptions(image_sigma_px=0.5 / 3, variance_components=True))
    assert abs(r.variance_factors["image"] - 3.0) < 0.3
    assert abs(r.sigma0_groups["image"] - 1.0) < 0.05
    assert 0.9 < r.sigma0 < 1.1


# ------------------------------------------------------------------ convergence and bad input
def test_no_convergence_names_the_worst_observations():
    b = make_block(0)
    with pytest.raises(ConvergenceError, match="did not converge in 1 iterations.*largest residuals: point"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, gnss=b.gnss,
                      options=BundleOptions(max_iterations=1))


@pytest.mark.parametrize("kw, match", [
    ({"image_sigma_px": 0.0}, "image_sigma_px must be a finite number > 0; got 0.0"),
    ({"tolerance": -1.0}, "tolerance must be a finite number > 0; got -1.0"),
    ({"blunder_threshold": float("nan")}, "blunder_threshold must be a finite number > 0; got nan"),
    ({"robust": "cauchy"}, "robust must be one of .*got 'cauchy'"),
    ({"robust_groups": ("ins",)}, "unknown group 'ins'"),
    ({"self_calibrate": ("zoom",)}, "unknown parameter 'zoom'"),
    ({"self_calibrate": ("f", "f")}, "duplicates"),
    ({"max_iterations": 0}, "max_iterations must be an integer >= 1; got 0"),
    ({"dense_limit": 1.5}, "dense_limit must be an integer >= 1; got 1.5"),
    ({"covariance": "some"}, "covariance must be one of .*got 'some'"),
    ({"threads": 0}, "threads must be None or an integer >= 1; got 0"),
])
def test_bad_options(kw, match):
    with pytest.raises(InvalidInputError, match=match):
        BundleOptions(**kw)


def test_bad_control_and_gnss():
    with pytest.raises(InvalidInputError, match="duplicate ids"):
        BlockControl(("a", "a"), np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match=r"`xyz` must be \(2, 3\) finite; got shape \(2, 2\)"):
        BlockControl(("a", "b"), np.zeros((2, 2)))
    with pytest.raises(InvalidInputError, match="`kind` must have 2 entries; got 1"):
        BlockControl(("a", "b"), np.zeros((2, 3)), ("full",))
    with pytest.raises(InvalidInputError, match="unknown kind 'xy'"):
        BlockControl(("a",), np.zeros((1, 3)), ("xy",))
    with pytest.raises(InvalidInputError, match=r"`sigma_m` must be .* got \[\[0.0"):
        BlockControl(("a",), np.zeros((1, 3)), ("full",), np.zeros((1, 3)))
    with pytest.raises(InvalidInputError, match="`check` must have 1 entries"):
        BlockControl(("a",), np.zeros((1, 3)), ("full",), np.ones((1, 3)), np.zeros(2, bool))
    with pytest.raises(InvalidInputError, match="gnss: duplicate images"):
        GnssObservations(("a", "a"), np.zeros((2, 3)), np.ones((2, 3)))
    with pytest.raises(InvalidInputError, match=r"`position` must be \(1, 3\) finite"):
        GnssObservations(("a",), np.zeros((1, 2)), np.ones((1, 3)))
    with pytest.raises(InvalidInputError, match=r"`sigma_m` must be .* got \[\[-1.0"):
        GnssObservations(("a",), np.zeros((1, 3)), -np.ones((1, 3)))
    with pytest.raises(InvalidInputError, match="`lever_arm_m` must be 3 finite numbers; got"):
        GnssObservations(("a",), np.zeros((1, 3)), np.ones((1, 3)), lever_arm_m=np.array([1.0, 2.0]))
    with pytest.raises(InvalidInputError, match=r"`angles` must be \(1, 3\) finite"):
        GnssObservations(("a",), np.zeros((1, 3)), np.ones((1, 3)), angles=np.zeros((1, 2)))
    with pytest.raises(InvalidInputError, match="`angles` need `sigma_rad`; got None"):
        GnssObservations(("a",), np.zeros((1, 3)), np.ones((1, 3)), angles=np.zeros((1, 3)))
    with pytest.raises(InvalidInputError, match=r"`sigma_rad` must be .* got \[\[0.0"):
        GnssObservations(("a",), np.zeros((1, 3)), np.ones((1, 3)), angles=np.zeros((1, 3)),
                         sigma_rad=np.zeros((1, 3)))
    with pytest.raises(InvalidInputError, match="`sigma_rad` given without `angles`"):
        GnssObservations(("a",), np.zeros((1, 3)), np.ones((1, 3)), sigma_rad=np.ones((1, 3)))


@pytest.fixture(scope="module")
def block():
    return make_block(0)


def test_bad_adjust_inputs(block):
    b = block
    ok = {"control": b.control, "gnss": b.gnss}
    with pytest.raises(InvalidInputError, match="`tracks` must be a Tracks; got list"):
        adjust_bundle(b.cameras, b.initial_poses, [], b.initial_points)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="`options` must be a BundleOptions; got dict"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, options={})  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="`poses` must be a sequence of Pose"):
        adjust_bundle(b.cameras, [1, 2], b.tracks, b.initial_points)  # type: ignore[list-item]
    with pytest.raises(InvalidInputError, match="poses: duplicate image names"):
        adjust_bundle(b.cameras, [*b.initial_poses, b.initial_poses[0]], b.tracks, b.initial_points, **ok)
    with pytest.raises(InvalidInputError, match=f"tracks name image.* without a pose: \\['{b.tracks.images[0]}'\\]"):
        adjust_bundle(b.cameras, b.initial_poses[1:], b.tracks, b.initial_points, **ok)
    extra = Pose("zz", "cam", b.initial_poses[0].position, b.initial_poses[0].rotation)
    with pytest.raises(InvalidInputError, match=r"not in the tracks: \['zz'\]"):
        adjust_bundle(b.cameras, [*b.initial_poses, extra], b.tracks, b.initial_points, **ok)
    with pytest.raises(InvalidInputError, match="names camera 'cam', which is not given"):
        adjust_bundle({"other": b.camera}, b.initial_poses, b.tracks, b.initial_points, **ok)
    with pytest.raises(InvalidInputError, match="camera 'cam' must be a rectify.geometry.camera.Camera; got str"):
        adjust_bundle({"cam": "x"}, b.initial_poses, b.tracks, b.initial_points, **ok)  # type: ignore[dict-item]
    with pytest.raises(InvalidInputError, match=r"`points` must have shape \(\d+, 3\).*got \(3, 3\)"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points[:3], **ok)
    bad = b.initial_points.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InvalidInputError, match="`points` must be finite; row 4 is not"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, bad, **ok)
    behind = b.initial_points.copy()
    behind[7, 2] = 5000.0
    with pytest.raises(InvalidInputError, match="point behind the camera at the start, e.g. point 'p7'"):
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, behind, **ok)
    t = b.tracks
    one = Tracks(t.images, (*t.point_ids, "lonely"), np.r_[t.obs_point, t.n_points], np.r_[t.obs_image, 0],
                 np.vstack([t.obs_pixel, [[5.0, 5.0]]]))
    with pytest.raises(InvalidInputError, match=r"fewer than 2 observations, e.g. \['lonely'\] with \[1\]"):
        adjust_bundle(b.cameras, b.initial_poses, one, np.vstack([b.initial_points, [[0, 0, 0]]]), **ok)
    few = t.subset(~((t.obs_image == 0) & (np.arange(t.n_obs) % 50 != 0)))
    with pytest.raises(InvalidInputError, match=f"fewer than 3 observations: \\[\\('{t.images[0]}'"):
        adjust_bundle(b.cameras, b.initial_poses, few, np.zeros((few.n_points, 3)), **ok)
    with pytest.raises(InvalidInputError, match="`control` must be a BlockControl; got dict"):
        adjust_bundle(b.cameras, b.initial_poses, t, b.initial_points, control={})  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match=r"control point id\(s\) not in the tracks: \['nope'\]"):
        adjust_bundle(b.cameras, b.initial_poses, t, b.initial_points,
                      control=BlockControl(("nope",), np.zeros((1, 3))))
    with pytest.raises(InvalidInputError, match="`gnss` must be a GnssObservations; got int"):
        adjust_bundle(b.cameras, b.initial_poses, t, b.initial_points, gnss=3)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match=r"GNSS image\(s\) not in the tracks: \['q'\]"):
        adjust_bundle(b.cameras, b.initial_poses, t, b.initial_points,
                      gnss=GnssObservations(("q",), np.zeros((1, 3)), np.ones((1, 3))))


# ------------------------------------------------------------------ GNSS lever arm, INS, invariance
def test_lever_arm_and_ins_angles():
    b = make_block(2, lever_arm_m=(0.1, -0.2, 1.5), ins_noise_rad=1e-7, image_noise_px=0.0, gnss_noise_m=0.0,
                   control_noise_m=0.0)
    gn = GnssObservations(b.gnss.images, b.gnss.position, np.full((18, 3), 0.05), b.gnss.lever_arm_m,
                          b.gnss.angles, np.full((18, 3), 1e-3))
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, gnss=gn,
                      options=BundleOptions(covariance="poses"))
    assert "ins" in r.datum_groups
    assert np.abs(r.points - b.true_points).max() < 1e-3  # INS noise 1e-7 rad at 1000 m
    assert np.abs(r.gnss_residuals).max() < 1e-4
    assert r.point_covariance is None and np.isnan(r.point_std).all()


def test_solution_invariant_to_a_shift_of_the_ground_frame(block):
    b = block
    shift = np.array([4.5e5, 5.2e6, 300.0])
    r0 = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                       options=BundleOptions(image_sigma_px=0.5, covariance="none"))
    moved = [Pose(p.image, p.camera, p.position + shift, p.rotation) for p in b.initial_poses]
    ctrl = BlockControl(b.control.ids, b.control.xyz + shift, b.control.kind, b.control.sigma_m, b.control.check)
    gn = GnssObservations(b.gnss.images, b.gnss.position + shift, b.gnss.sigma_m)
    r1 = adjust_bundle(b.cameras, moved, b.tracks, b.initial_points + shift, control=ctrl, gnss=gn,
                       options=BundleOptions(image_sigma_px=0.5, covariance="none"))
    np.testing.assert_allclose(r1.points - shift, r0.points, atol=1e-5)
    np.testing.assert_allclose(r1.residuals_px, r0.residuals_px, atol=1e-6)
    assert "conditioning not computed" in " ".join(r0.datum)


def test_sparse_reduced_system_matches_dense(block):
    b = block
    o = {"control": b.control, "gnss": b.gnss}
    r0 = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, **o,
                       options=BundleOptions(covariance="none"))
    r1 = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, **o,
                       options=BundleOptions(covariance="none", dense_limit=10))
    np.testing.assert_allclose(r1.points, r0.points, atol=1e-6)


def test_reduced_system_equals_the_schur_complement_of_the_full_normal_matrix(block):
    """The per-image-pair assembly of S (and its right-hand side) against N_cc - N_cp N_pp^-1 N_pc of the
    full normal matrix, formed densely, with self-calibration (interior unknowns shared by all images)."""
    from stereo.block.bundle.adjust import GROUPS, _base_weights, _setup

    b = block
    opts = BundleOptions(self_calibrate=("f", "k1"))
    prob, st, _ = _setup(b.cameras, b.initial_poses, b.tracks, b.initial_points, b.control, b.gnss, opts)
    w = _base_weights(prob, {g: 1.0 for g in GROUPS})
    lin = bs.evaluate(prob, st, jacobian=True)
    ne = bs.normal(prob, lin, w, 0.0, dense=True)
    nc, P, M = prob.n_c, prob.n_points, len(prob.obs_pt)
    A = np.zeros((2 * M, nc + 3 * P))
    rows = np.arange(2 * M).reshape(M, 2)
    cidx = prob.cidx()
    A[rows[:, :, None], cidx[:, None, :]] = lin.Jc
    A[rows[:, :, None], (nc + 3 * prob.obs_pt[:, None] + np.arange(3))[:, None, :]] = lin.Jp
    Wd = w.image.ravel()
    N = A.T @ (A * Wd[:, None])
    bvec = A.T @ (Wd * lin.res.image.ravel())
    gi = prob.g_img
    for k, i in enumerate(gi):
        J = lin.Jg[k]
        N[6 * i:6 * i + 6, 6 * i:6 * i + 6] += J.T @ (J * w.gnss[k][:, None])
        bvec[6 * i:6 * i + 6] += J.T @ (w.gnss[k] * lin.res.gnss[k])
    for k, j in enumerate(prob.c_pt):
        sl = slice(nc + 3 * j, nc + 3 * j + 3)
        N[sl, sl] += np.diag(w.control[k])
        bvec[sl] += w.control[k] * lin.res.control[k]
    Ncc, Ncp, Npp = N[:nc, :nc], N[:nc, nc:], N[nc:, nc:]
    S = Ncc - Ncp @ np.linalg.solve(Npp, Ncp.T)
    rhs = bvec[:nc] - Ncp @ np.linalg.solve(Npp, bvec[nc:])
    scale = np.sqrt(np.outer(np.diag(Ncc), np.diag(Ncc)))
    assert np.abs((ne.S - S) / scale).max() < 1e-9
    np.testing.assert_allclose(ne.diag_c, np.diag(Ncc), rtol=1e-12)
    assert np.abs(ne.rhs_c - rhs).max() < 1e-8 * np.abs(rhs).max()


def test_banded_reduced_system_matches_dense(block, monkeypatch):
    b = block
    o = {"control": b.control, "gnss": b.gnss}
    r0 = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, **o,
                       options=BundleOptions(covariance="none"))
    used = []
    real = bs.use_banded
    monkeypatch.setattr(bs, "BANDED_MIN_GAIN", 0.0)
    monkeypatch.setattr(bs, "use_banded", lambda prob: used.append(real(prob)) or used[-1])
    r1 = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, **o,
                       options=BundleOptions(covariance="none"))
    assert used == [True]
    np.testing.assert_allclose(r1.points, r0.points, atol=1e-6)
    np.testing.assert_allclose(r1.residuals_px, r0.residuals_px, atol=1e-6)


def test_threads_and_pieces_give_the_same_solution(block, monkeypatch):
    b = block
    o = {"control": b.control, "gnss": b.gnss}
    r0 = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, **o,
                       options=BundleOptions(covariance="none"))
    monkeypatch.setattr(bs, "CHUNK", 250)  # several pieces, several track-length groups each
    monkeypatch.setattr(bs, "EVAL_CHUNK", 300)
    monkeypatch.setattr(bs, "THREADS_MIN_OBSERVATIONS", 0)
    for threads in (1, 3):
        r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, **o,
                          options=BundleOptions(covariance="none", threads=threads))
        np.testing.assert_allclose(r.points, r0.points, atol=1e-7)
        assert r.iterations == r0.iterations


def test_progress_callback(block):
    calls = []
    adjust_bundle(block.cameras, block.initial_poses, block.tracks, block.initial_points, gnss=block.gnss,
                  options=BundleOptions(covariance="none"), progress=lambda i, n: calls.append((i, n)))
    assert calls and calls[0] == (1, 50)


def test_solve_helpers_inv3():
    A = np.array([[[2.0, 0, 0], [0, 3, 0], [0, 0, 4]], [[1.0, 2, 3], [2, 4, 6], [0, 0, 1]]])
    inv = bs.inv3(A)
    np.testing.assert_allclose(inv[0], np.diag([0.5, 1 / 3, 0.25]))
    assert np.isnan(inv[1]).all()
