"""GNSS/INS observation model of the bundle: full covariances, GNSS shift/drift and boresight per strip
(stereo.block.bundle.systematic; seed 002, 3.64-3.69), on synthetic blocks with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.rotation import angles_from_matrix
from stereo.block.bundle import solve as bs
from stereo.block.bundle.adjust import BundleOptions, _setup, adjust_bundle
from stereo.block.bundle.model import rotations
from stereo.block.bundle.systematic import frame_covariance, summary_dict
from stereo.block.types import GnssObservations
from tests.support import gnss_scenes
from tests.support.block_synthetic import make_block
from tests.support.gnss_scenes import BORESIGHT, DRIFT, SHIFT


@pytest.fixture(scope="module")
def drift_block():
    return gnss_scenes.drift_block()


def _run(blk, gnss, **kw):
    return adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, control=blk.control,
                         gnss=gnss, options=BundleOptions(image_sigma_px=0.5, **kw))


def test_shift_drift_per_strip_recovered(drift_block):
    """GNSS shifts of 0.3-1.05 m and drifts of 1.2-3 cm/s per strip (4 strips of 8 images, 5 control points):
    every shift and drift within 2 predicted std; the check points within their predicted std; without the
    unknowns sigma0 and the check-point errors grow."""
    blk, gg = drift_block
    res = _run(blk, gg, gnss_drift="shift-drift")
    truth = np.concatenate([np.concatenate([SHIFT[k], DRIFT[k]]) for k in range(4)])
    assert res.systematic_names[:6] == tuple(f"gnss {w} s0 {a}" for w in ("shift", "drift") for a in "xyz")
    z = (res.systematic - truth) / res.systematic_std
    assert np.all(np.abs(z) < 2.0), z.round(2)
    zc = res.check_errors / res.check_std
    assert np.all(np.sqrt(np.mean(zc ** 2, axis=0)) < 1.5) and np.abs(zc).max() < 4.0
    assert 0.8 < res.sigma0 < 1.2
    plain = _run(blk, gg)
    assert plain.sigma0 > 1.15 * res.sigma0
    assert np.sqrt(np.mean(plain.check_errors ** 2)) > 1.2 * np.sqrt(np.mean(res.check_errors ** 2))
    assert any(line.startswith("gnss drift s3 z:") for line in res.summary_lines())
    # the report's summary entry (stereo block writes it into report.json)
    d = summary_dict(res.systematic_names, res.systematic, res.systematic_std)["systematic"]
    assert d["gnss drift s3 z"] == {"value": float(res.systematic[-1]), "std": float(res.systematic_std[-1])}
    assert summary_dict((), np.zeros(0), np.zeros(0)) == {}


def test_shift_only_absorbs_the_shift(drift_block):
    """A shift per strip is estimated (a drift left unmodelled spreads into the shift's residuals only)."""
    blk, gg = drift_block
    res = _run(blk, gg, gnss_drift="shift")
    assert len(res.systematic) == 12
    err = res.systematic.reshape(4, 3) - SHIFT
    assert np.all(np.abs(err) < 4 * res.systematic_std.reshape(4, 3))


def test_boresight_block_and_strip_recovered():
    """INS angles with a boresight error of (0.05, -0.08, 0.12) deg: recovered within 3 predicted std per angle
    (block and per strip); check points back within their std; without the unknowns they are not."""
    blk, gg = gnss_scenes.boresight_block()
    beta = BORESIGHT
    for mode, k in (("block", 1), ("strip", 3)):
        res = _run(blk, gg, boresight_unknown=mode)
        z = (res.systematic - np.tile(beta, k)) / res.systematic_std
        assert np.all(np.abs(z) < 3.0), (mode, z.round(2))
        zc = res.check_errors / res.check_std
        assert np.all(np.sqrt(np.mean(zc ** 2, axis=0)) < 1.5), (mode, zc)
    plain = _run(blk, gg)
    zc = plain.check_errors / plain.check_std
    assert np.sqrt(np.mean(zc ** 2, axis=0)).max() > 2.0
    assert plain.sigma0_groups["ins"] > 3.0


def test_full_covariance_beats_diagonal_weights():
    """Correlated GNSS errors: strip 0's errors lie along (1, 1, 0) (rho = +0.995), strip 1's along (1, -1, 0)
    (rho = -0.995), sigma 0.5 m. The block has no control (GNSS datum): with the full covariances each strip fixes
    the direction the other cannot, and the check points are within a few cm and their predicted std; with the
    diagonal sigmas alone the same observations leave them (and the block's translation) 3 times (or more) farther
    off. Tight INS angles (2e-5 rad) tie the cameras' plan positions to the block's rigid geometry."""
    blk, g_full, g_diag = gnss_scenes.correlated_gnss_block()
    full = adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, control=blk.control,
                         gnss=g_full,
                         options=BundleOptions(image_sigma_px=0.5))
    diag = adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, control=blk.control,
                         gnss=g_diag,
                         options=BundleOptions(image_sigma_px=0.5))
    e_full = np.sqrt(np.mean(full.check_errors[:, :2] ** 2))
    e_diag = np.sqrt(np.mean(diag.check_errors[:, :2] ** 2))
    assert e_full < 0.05 and e_diag > 3 * e_full, (e_full, e_diag)
    true_c = np.array([p.position for p in blk.true_poses])
    shift_full = np.abs(np.mean([p.position for p in full.poses] - true_c, axis=0)[:2]).max()
    shift_diag = np.abs(np.mean([p.position for p in diag.poses] - true_c, axis=0)[:2]).max()
    assert shift_full < 0.03 and shift_diag > 3 * shift_full, (shift_full, shift_diag)
    z = full.check_errors / full.check_std
    assert np.sqrt(np.mean(z ** 2, axis=0)).max() < 1.5
    # the GNSS residuals are reported in metres (not decorrelated units)
    assert np.abs(np.asarray(full.gnss_residuals)).max() > 0.2


def test_six_by_six_covariance_is_the_full_weight_matrix():
    """Seed 002 (3.67)-(3.69): the decorrelated GNSS and INS residuals' squares sum to v^T K^-1 v with the
    6 x 6 covariance K of position and angles, v = (observed - computed) of both."""
    blk = make_block(2, strips=2, images_per_strip=4, n_points=300, ins_noise_rad=3e-4)
    g = blk.gnss
    n = len(g.images)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(n, 6, 6)) * np.array([0.05, 0.05, 0.05, 3e-4, 3e-4, 3e-4])[None, :, None]
    cov = np.einsum("nij,nkj->nik", A, A) + np.diag([1e-4] * 3 + [1e-8] * 3)[None]
    gg = GnssObservations(g.images, g.position, g.sigma_m, None, g.angles, g.sigma_rad, covariance=cov)
    prob, st, _ = _setup(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, blk.control, gg,
                         BundleOptions())
    lin = bs.evaluate(prob, st, jacobian=True)
    q = np.sum(lin.res.gnss ** 2, axis=1) + np.sum(lin.res.ins ** 2, axis=1)
    v = np.concatenate([g.position - st.centres, bs.wrap(g.angles - st.angles)], axis=1)
    expect = np.einsum("ni,nij,nj->n", v, np.linalg.inv(cov), v)
    np.testing.assert_allclose(q, expect, rtol=1e-9)
    res = adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, control=blk.control,
                        gnss=gg, options=BundleOptions(image_sigma_px=0.5))
    assert res.converged and np.isfinite(res.sigma0)


def test_bad_inputs(drift_block):
    blk, gg = drift_block
    g = blk.gnss
    n = len(g.images)
    bad = np.tile(np.diag([0.01, 0.01, 0.01]), (n, 1, 1))
    bad[2, 0, 1] = bad[2, 1, 0] = 0.02                       # |rho| = 2: not positive definite
    with pytest.raises(InvalidInputError, match="image 2 is not positive definite"):
        GnssObservations(g.images, g.position, g.sigma_m, covariance=bad)
    nan = np.tile(np.eye(3) * 0.01, (n, 1, 1))
    nan[1, 2, 2] = np.nan
    with pytest.raises(InvalidInputError, match="image 1 is not finite"):
        GnssObservations(g.images, g.position, g.sigma_m, covariance=nan)
    with pytest.raises(ShapeError, match="covariance"):
        GnssObservations(g.images, g.position, g.sigma_m, covariance=np.zeros((n, 2, 2)))
    with pytest.raises(InvalidInputError, match="needs `angles`"):
        GnssObservations(g.images, g.position, g.sigma_m, covariance=np.tile(np.eye(6) * 0.01, (n, 1, 1)))
    with pytest.raises(InvalidInputError, match="unknown GNSS drift model 'linear'"):
        BundleOptions(gnss_drift="linear")
    with pytest.raises(InvalidInputError, match="unknown boresight model 'camera'"):
        BundleOptions(boresight_unknown="camera")
    no_strip = GnssObservations(g.images, gg.position, g.sigma_m, time=gg.time)
    with pytest.raises(InvalidInputError, match="needs the strip of every image"):
        _run(blk, no_strip, gnss_drift="shift")
    no_time = GnssObservations(g.images, gg.position, g.sigma_m, strip=gg.strip)
    with pytest.raises(InvalidInputError, match="needs the exposure time"):
        _run(blk, no_time, gnss_drift="shift-drift")
    with pytest.raises(InvalidInputError, match="needs INS angles"):
        _run(blk, no_time, boresight_unknown="block")
    with pytest.raises(EstimationError, match="need at least 1 of each"):
        adjust_bundle(blk.cameras, blk.initial_poses, blk.tracks, blk.initial_points, gnss=gg,
                      options=BundleOptions(gnss_drift="shift"))


def test_covariance_into_another_frame():
    """Positions rotated by T; angles by the Jacobian of a_out(a_in) under R -> M R: at zero angles and M = Rz(90
    deg) the omega and phi variances swap; elsewhere the Jacobian matches finite differences."""
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    cov = np.diag([1.0, 4.0, 9.0, 1e-6, 4e-6, 9e-6])[None]
    out = frame_covariance(cov, Rz[None], np.zeros((1, 3)), np.array([[0.0, 0.0, np.pi / 2]]))
    np.testing.assert_allclose(np.diag(out[0]), [4.0, 1.0, 9.0, 4e-6, 1e-6, 9e-6], atol=1e-15)
    rng = np.random.default_rng(3)
    a = rng.normal(0, 0.3, (1, 3))
    M = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    out_a = np.asarray(angles_from_matrix(M @ rotations(a)[0], "omega-phi-kappa")).reshape(1, 3)
    J = np.empty((3, 3))
    for k in range(3):
        d = np.zeros((1, 3))
        d[0, k] = 1e-7
        ap = np.asarray(angles_from_matrix(M @ rotations(a + d)[0], "omega-phi-kappa")).reshape(3)
        am = np.asarray(angles_from_matrix(M @ rotations(a - d)[0], "omega-phi-kappa")).reshape(3)
        J[:, k] = (ap - am) / 2e-7
    K = np.diag([0.0, 0.0, 0.0, 1.0, 2.0, 3.0])[None]
    got = frame_covariance(K, np.eye(3)[None], a, out_a)[0, 3:, 3:]
    np.testing.assert_allclose(got, J @ np.diag([1.0, 2.0, 3.0]) @ J.T, rtol=1e-6, atol=1e-9)
    assert frame_covariance(None, np.eye(3)[None]) is None


def test_redundancy_numbers_add_up_with_the_model(drift_block):
    """The groups' redundancies (exact redundancy numbers, the systematic unknowns' columns in the hat matrix of the
    GNSS and INS rows) sum to observations - unknowns, with a full 6 x 6 covariance and shift-drift unknowns."""
    blk, gg = drift_block
    n = len(gg.images)
    rng = np.random.default_rng(5)
    A = rng.normal(size=(n, 6, 6)) * np.array([0.03, 0.03, 0.03, 1e-4, 1e-4, 1e-4])[None, :, None]
    cov = np.einsum("nij,nkj->nik", A, A) + np.diag([25e-4] * 3 + [4e-8] * 3)[None]
    g6 = GnssObservations(gg.images, gg.position, gg.sigma_m, None, gg.angles, gg.sigma_rad, cov, gg.time, gg.strip)
    res = _run(blk, g6, gnss_drift="shift-drift")
    n_obs = 2 * blk.tracks.n_obs + 3 * n + 3 * n + 3 * int((~blk.control.check).sum())
    n_unk = 6 * n + 3 * len(res.points) + len(res.systematic)
    assert len(res.systematic) == 24
    assert abs(sum(res.redundancy_groups.values()) - (n_obs - n_unk)) < 1e-6 * n_obs
    assert 0.8 < res.sigma0 < 1.25
