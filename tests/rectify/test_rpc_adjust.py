"""RPC block adjustment (issue 28): a synthetic RPC triplet with known image-space biases (2 px along the
track on one image) is recovered within 0.05 px; the refitted RPCs reproduce the compensated model within
0.01 px and GDAL's RPC transformer (rasterio) reads them back within 0.01 px; tracks from pairwise
matches; bad input. Synthetic truth: tests/support/rpc_synthetic.py (RPCs fitted to pushbroom-like
models to 1e-11 px)."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import rasterio
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import EstimationError, InvalidInputError
from rectify.formats.rpc import read_rpc, rpb_text, rpc_txt_text
from rectify.geometry.rpc import RPC, RPCRefinement
from rectify.geometry.rpc_adjust import RPCBlockAdjustment, TieTracks, chain_matches, check_overlap, refit_rpc
from rectify.raster.rpcfiles import gdal_rpc_project, rpc_vrt_text
from tests.support.rpc_synthetic import SIZE, VIEWS, camera, ground_points, measure, triplet

BIAS = np.array([[0.0, 0.0], [0.0, 2.0], [0.0, 0.0]])  # (dc, dr): 2 px along the track (rows) on image 2
TOL_BIAS = 0.05  # px, the figure


@pytest.fixture(scope="module")
def rpcs() -> list[RPC]:
    return triplet()


def _block(rpcs, bias=BIAS, n_ties=150, n_gcp=8, noise=0.05, seed=0):
    ties = ground_points(n_ties, seed=seed)
    gcp = ground_points(n_gcp, seed=seed + 100)
    im, tr, px = measure(rpcs, np.vstack([ties, gcp]), bias, noise=noise, seed=seed + 1)
    ids = [f"t{i}" for i in range(n_ties)] + [f"G{i}" for i in range(n_gcp)]
    tracks = TieTracks.from_arrays(ids, im, tr, px, max(noise, 0.01))
    control = {f"G{i}": (tuple(gcp[i]), (0.01, 0.01)) for i in range(n_gcp)}
    return tracks, control


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_shift_biases_recovered_with_gcps(rpcs, robust):
    tracks, control = _block(rpcs)
    a = RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, tracks, control=control, check=["G0", "G1"],
                                             model="shift", robust=robust)
    assert np.abs(a.params[:, :, 0] - BIAS).max() < TOL_BIAS
    assert (a.std > 0).all() and (a.std < 0.05).all()
    assert 0.6 < a.sigma0 < 1.4  # sigma 0.05 px given, noise 0.05 px
    assert a.check_ids == ("G0", "G1") and a.accuracy is not None and a.accuracy.n == 2
    assert np.abs(a.check_errors).max() < 0.1  # m: 0.05 px noise, 0.5 m pixels
    assert set(a.control_ids) == {f"G{i}" for i in range(2, 8)}


def test_affine_biases_recovered(rpcs):
    bias_fn = np.array([[0.3, 4e-4, -2e-4], [-0.5, 1e-4, 5e-4]])  # plain frame: dc = a0 + a1 col + a2 row
    tracks, control = _block(rpcs, bias=np.zeros((3, 2)), noise=0.0)
    # apply an affine bias on image 3 on top of the 2 px row shift of image 2
    px = tracks.pixels.copy()
    proj = tracks.pixels  # noise-free, unbiased: the RPC projections
    s3 = tracks.image == 2
    px[s3] += np.column_stack([np.ones(s3.sum()), proj[s3]]) @ bias_fn.T
    px[tracks.image == 1] += BIAS[1]
    t2 = TieTracks.from_arrays(tracks.ids, tracks.image, tracks.track, px, 0.01)
    a = RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, t2, control=control, model="affine")
    grid = np.array([[c, r] for c in (0, 1000, 1999) for r in (0, 1000, 1999)], float)
    truth = [np.zeros((9, 2)), np.tile(BIAS[1], (9, 1)), np.column_stack([np.ones(9), grid]) @ bias_fn.T]
    for j in range(3):
        got = a.refinement(j).correction(grid)
        assert np.abs(got - truth[j]).max() < TOL_BIAS, j


def test_without_gcps_the_relative_biases_are_recovered(rpcs):
    """No GCP: the prior takes the least-norm biases; what remains of the truth is a common ground shift."""
    tracks, _control = _block(rpcs, n_gcp=0)
    a = RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, tracks, model="shift")
    assert abs(a.params[:, :, 0].mean()) < 0.05  # the datum: about zero mean bias
    diff = (a.params[:, :, 0] - BIAS).reshape(-1)
    # image shifts of a ground shift (east, north, up) at the scene centre, per image: (6, 3)
    c = ground_points(1, seed=7)
    J = []
    for rpc in rpcs:
        cols = []
        for d in (np.array([1e-5, 0, 0]), np.array([0, 1e-5, 0]), np.array([0, 0, 1.0])):
            cols.append((rpc.project(c + d) - rpc.project(c - d))[0] / 2)
        J.append(np.column_stack(cols))
    A = np.vstack(J)
    x, *_ = np.linalg.lstsq(A, diff, rcond=None)
    assert np.abs(A @ x - diff).max() < TOL_BIAS
    assert np.abs(diff).max() > 0.3  # the truth is not reachable without control: the test can fail


@pytest.mark.parametrize("robust", ["huber", "tukey"])
def test_robust_weights_down_weight_a_blunder(rpcs, robust):
    tracks, control = _block(rpcs)
    px = tracks.pixels.copy()
    px[5] += (6.0, -4.0)  # one wrong measurement
    t2 = TieTracks.from_arrays(tracks.ids, tracks.image, tracks.track, px, 0.05)
    a = RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, t2, control=control, robust=robust)
    assert a.weights[5] < 0.1
    assert np.abs(a.params[:, :, 0] - BIAS).max() < TOL_BIAS


# ----------------------------------------------------------------- refit and GDAL
def test_shift_refit_is_exact_and_affine_refit_within_tolerance(rpcs):
    shift = RPCRefinement(rpcs[1], "shift", np.array([[0.7], [-2.0]]))
    r = refit_rpc(shift)
    assert r.method == "offsets" and r.max_px < 1e-9
    aff = RPCRefinement(rpcs[2], "affine", np.array([[0.3, 4e-4, -2e-4], [-0.5, 1e-4, 5e-4]]))
    r = refit_rpc(aff)
    assert r.method == "numerators" and r.max_px <= 0.01 and r.rms_px <= r.max_px
    g = ground_points(50, seed=3)
    assert np.abs(r.rpc.project(g) - aff.project(g)).max() <= 0.01


def test_refit_refuses_an_unreachable_tolerance(rpcs):
    # the synthetic RPCs have different line and sample denominators: an affine is not exact
    assert not np.allclose(rpcs[2].line_den_coeff, rpcs[2].samp_den_coeff)
    aff = RPCRefinement(rpcs[2], "affine", np.array([[0.3, 4e-3, -2e-3], [-0.5, 1e-3, 5e-3]]))
    with pytest.raises(EstimationError, match="cannot reach the tolerance"):
        refit_rpc(aff, tolerance_px=1e-15)
    with pytest.raises(InvalidInputError, match="tolerance"):
        refit_rpc(aff, tolerance_px=0.0)


@functools.lru_cache(maxsize=1)
def _first_rpc() -> RPC:
    return triplet()[0]


@settings(max_examples=10, deadline=None)
@given(st.floats(-20, 20), st.floats(-20, 20))
def test_shift_fold_is_exact(dc, dr):
    rpc = _first_rpc()
    ref = RPCRefinement(rpc, "shift", np.array([[dc], [dr]]))
    g = ground_points(20, seed=1)
    assert np.abs(refit_rpc(ref, n_xy=5, n_h=3).rpc.project(g) - rpc.project(g) - (dc, dr)).max() < 1e-9


def test_gdal_reads_the_written_rpcs(rpcs, tmp_path):
    """The refitted RPC as a VRT's RPC domain, an .RPB and an _RPC.TXT beside a plain GeoTIFF: GDAL's RPC
    transformer reproduces our projection of check points within 0.01 px."""
    aff = RPCRefinement(rpcs[2], "affine", np.array([[0.3, 4e-4, -2e-4], [-0.5, 1e-4, 5e-4]]))
    new = refit_rpc(aff).rpc
    g = ground_points(40, seed=9)
    ours = aff.project(g)
    img = tmp_path / "img.tif"
    with rasterio.open(img, "w", driver="GTiff", width=64, height=32, count=1, dtype="uint16") as ds:
        ds.write(np.arange(64 * 32, dtype=np.uint16).reshape(1, 32, 64))
    (tmp_path / "img.vrt").write_text(rpc_vrt_text(img, new.to_rasterio()))
    assert np.abs(gdal_rpc_project(tmp_path / "img.vrt", g) - ours).max() < 0.01
    with rasterio.open(tmp_path / "img.vrt") as ds:  # the VRT shows the image's pixels
        assert ds.read(1)[5, 7] == 5 * 64 + 7
    for name, text in (("a.RPB", rpb_text(new)), ("b_RPC.TXT", rpc_txt_text(new))):
        stem = name.split(".")[0].split("_")[0]
        tif = tmp_path / f"{stem}.tif"
        tif.write_bytes(img.read_bytes())
        (tmp_path / name).write_text(text)
        assert np.abs(gdal_rpc_project(tif, g) - ours).max() < 0.01, name
        assert np.abs(read_rpc(tmp_path / name).project(g) - new.project(g)).max() < 1e-9


# ----------------------------------------------------------------- tracks
def test_chain_matches_builds_three_image_tracks():
    rng = np.random.default_rng(0)
    p0 = rng.uniform(0, 500, (30, 2))
    p1, p2 = p0 + (10, 3), p0 + (-7, 12)
    jit = rng.uniform(-0.1, 0.1, (30, 2))
    pairs = [(0, 1, p0, p1 + jit), (0, 2, p0, p2), (1, 2, p1, p2 - jit)]
    # a wrong chain: point 0 of image 0 also matched to a far point of image 2 through image 1
    pairs.append((1, 2, p1[:1] + 0.05, p2[5:6]))
    ids, image, track, px = chain_matches(pairs, radius_px=0.5)
    n_img = np.bincount(track)
    # the wrong match joins tracks 0 and 5 into one with two far-apart points of image 2: both dropped
    assert len(ids) == 28 and (n_img == 3).all()
    for t in range(len(ids)):
        s = track == t
        i0 = px[s & (image == 0)][0]
        k = int(np.argmin(np.hypot(*(p0 - i0).T)))
        assert np.abs(px[s & (image == 2)][0] - p2[k]).max() < 0.11


# ----------------------------------------------------------------- bad input
def test_non_overlapping_images_are_refused(rpcs):
    d = rpcs[2].to_dict()
    d["long_off"] += 0.5
    far = RPC.from_dict(d, source="far")
    with pytest.raises(InvalidInputError, match="'c.tif' does not overlap any other image"):
        check_overlap([rpcs[0], rpcs[1], far], [SIZE] * 3, ["a.tif", "b.tif", "c.tif"])
    assert check_overlap(rpcs, [SIZE] * 3, ["a", "b", "c"]) == [(0, 1), (0, 2), (1, 2)]
    with pytest.raises(InvalidInputError, match="at least 2 images"):
        check_overlap(rpcs[:1], [SIZE], ["a"])


def test_adjustment_bad_input(rpcs):
    tracks, control = _block(rpcs)
    with pytest.raises(InvalidInputError, match="unknown bias model"):
        RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, tracks, model="poly")
    with pytest.raises(InvalidInputError, match="'X' is not a GCP"):
        RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, tracks, control=control, check=["X"])
    with pytest.raises(InvalidInputError, match="prior_px"):
        RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, tracks, prior_px=0.0)
    only01 = tracks.select(tracks.image != 2)
    with pytest.raises(InvalidInputError, match="'image 2' has 0 tie measurements"):
        RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, only01)
    with pytest.raises(InvalidInputError, match="sigmas"):
        TieTracks.from_arrays(["a"], [0], [0], [[1.0, 2.0]], 0.0)
    # two groups of images that share no tie point
    n = len(tracks)
    im = np.concatenate([tracks.image, tracks.image + 3])
    tr = np.concatenate([tracks.track, tracks.track + len(tracks.ids)])
    split = TieTracks.from_arrays(list(tracks.ids) + [i + "b" for i in tracks.ids], im, tr,
                                  np.vstack([tracks.pixels] * 2), np.full(2 * n, 0.05))
    with pytest.raises(InvalidInputError, match="do not form one block"):
        RPCBlockAdjustment.from_observations(rpcs * 2, [SIZE] * 6, split)


def test_camera_helper_is_the_rpc_truth(rpcs):
    """The synthetic RPCs reproduce their physical models (the truth of every test above)."""
    g = ground_points(100, seed=4)
    for i, rpc in enumerate(rpcs):
        assert np.abs(rpc.project(g) - camera(VIEWS[i], rot=0.01 * i)(g)).max() < 1e-6


def test_plain_params_are_the_normalised_correction(rpcs):
    """params (normalised frame, a0 at the image centre) and params_plain (RPCRefinement's frame) are one
    correction: evaluated at the corners and the centre they agree."""
    tracks, control = _block(rpcs, n_ties=60)
    a = RPCBlockAdjustment.from_observations(rpcs, [SIZE] * 3, tracks, control=control, model="affine",
                                             prior_px=0.5)
    w, h = SIZE
    c0, r0, s = (w - 1) / 2, (h - 1) / 2, max(w, h) / 2
    px = np.array([[0.0, 0.0], [w - 1.0, 0.0], [c0, r0], [w - 1.0, h - 1.0]])
    for j in range(3):
        design = np.column_stack([np.ones(4), (px[:, 0] - c0) / s, (px[:, 1] - r0) / s])
        assert np.allclose(a.refinement(j).correction(px), design @ a.params[j].T, atol=1e-9)
    assert np.allclose(a.refinement(1).correction(px[2:3])[0], a.params[1][:, 0], atol=1e-9)


@settings(max_examples=15, deadline=None)
@given(st.permutations([0, 1, 2]), st.booleans())
def test_chain_matches_does_not_depend_on_the_pair_order(order, swap):
    rng = np.random.default_rng(1)
    p0 = rng.uniform(0, 300, (20, 2))
    pts = [p0, p0 + (4.0, 1.0), p0 + (-3.0, 6.0)]
    pairs = [(0, 1), (0, 2), (1, 2)]
    given_pairs = []
    for k in order:
        i, j = pairs[k]
        given_pairs.append((j, i, pts[j], pts[i]) if swap else (i, j, pts[i], pts[j]))
    ids, image, track, px = chain_matches(given_pairs)
    assert len(ids) == 20 and len(image) == 60
    # every track holds one point of each image, all of the same ground point
    for t in range(20):
        s = track == t
        k = int(np.argmin(np.hypot(*(p0 - px[s & (image == 0)][0]).T)))
        for j in range(3):
            assert np.allclose(px[s & (image == j)][0], pts[j][k])
