"""Independent models (stereo.block.independent) on small synthetic blocks with known truth."""

from __future__ import annotations

import math
from functools import cache
from typing import NamedTuple

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import EstimationError, InvalidInputError, ShapeError, StereoError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.independent import GroundBlock, ModelBlock, independent_models, to_ground
from stereo.block.models import IndependentOptions
from stereo.block.types import Pose, Tracks, project_pixel
from stereo.relative import RelativeOrientation

H = 250.0         # flying height above the datum, m
CAM = Camera(focal_length_mm=50.0, pixel_size_mm=0.02, width=2000, height=1500)
CAMS = {"c": CAM}
CAM2 = Camera(focal_length_mm=48.0, pixel_size_mm=0.02, width=2000, height=1500, principal_point_mm=(0.1, -0.05),
              distortion={"k1": -0.05, "k2": 0.01, "p1": 1e-4})
ALL_CAMS = {"c": CAM, "d": CAM2}
BASE = 75.0       # forward overlap 62 % of the 200 m footprint
STRIP = 90.0      # side overlap 40 % of the 150 m footprint
# Tolerances for 0.3 px of image noise. Each relative orientation alone is good to about 0.04 deg
# (1 sigma of its weakest angle, as its covariance says and as measured here), so the joined block
# is good to about 0.06 deg and 1e-3 of the flying height on average; the bounds leave room.
POS_TOL = 2.5e-3  # of the flying height
ANG_TOL_DEG = 0.15


def terrain(xy: np.ndarray) -> np.ndarray:
    """Heights with relief (about +-30 m over a few hundred metres)."""
    x, y = xy[:, 0], xy[:, 1]
    return 20.0 * np.sin(x / 70.0) * np.cos(y / 90.0) + 0.04 * x - 0.03 * y


class Block(NamedTuple):
    poses: list[Pose]
    ground: np.ndarray       # (n_points, 3) true points, ground frame
    tracks: Tracks
    blunder: np.ndarray      # (M,) bool, observations moved by 15-60 px


def make_block(strips: int = 2, per_strip: int = 4, *, noise_px: float = 0.0, blunders: float = 0.0,
               seed: int = 0, n_points: int = 3000, kappa_flip: bool = False, two_cameras: bool = False):
    """True poses and points and the tracks of a small block of `strips` x `per_strip` images.

    Footprint 200 m x 150 m (on the datum), bases of BASE along x, strips STRIP apart along y;
    attitudes within 1 degree, positions within a few metres of the plan. With ``two_cameras`` the
    odd strips are taken with camera "d" (CAM2: another focal length, distortion).
    """
    rng = np.random.default_rng(seed)
    poses = []
    for s in range(strips):
        for k in range(per_strip):
            ang = np.radians(rng.uniform(-1.0, 1.0, 3))
            if kappa_flip and s % 2 == 1:
                ang[2] += math.pi
            pos = np.array([BASE * k, STRIP * s, H]) + rng.normal(0, 2.0, 3)
            cam = "d" if two_cameras and s % 2 == 1 else "c"
            poses.append(Pose(f"s{s}i{k}", cam, pos, matrix_from_angles(*ang)))
    xmin, xmax = -100.0, BASE * (per_strip - 1) + 100.0
    ymin, ymax = -75.0, STRIP * (strips - 1) + 75.0
    xy = np.column_stack([rng.uniform(xmin, xmax, n_points), rng.uniform(ymin, ymax, n_points)])
    ground = np.column_stack([xy, terrain(xy)])
    pt, im, px = [], [], []
    for i, p in enumerate(poses):
        uv = project_pixel(ALL_CAMS[p.camera], p, ground)
        inside = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= CAM.width - 1) \
            & (uv[:, 1] >= 0) & (uv[:, 1] <= CAM.height - 1)
        idx = np.flatnonzero(inside)
        pt.append(idx)
        im.append(np.full(len(idx), i))
        px.append(uv[idx])
    pt_a, im_a, px_a = np.concatenate(pt), np.concatenate(im), np.concatenate(px)
    keep = np.bincount(pt_a, minlength=n_points)[pt_a] >= 2
    pt_a, im_a, px_a = pt_a[keep], im_a[keep], px_a[keep]
    order = np.lexsort((im_a, pt_a))                      # the order Tracks keeps
    pt_a, im_a, px_a = pt_a[order], im_a[order], px_a[order]
    px_a = px_a + rng.normal(0, noise_px, px_a.shape) if noise_px else px_a
    bad = np.zeros(len(px_a), dtype=bool)
    if blunders:
        bad = rng.random(len(px_a)) < blunders
        ang = rng.uniform(0, 2 * math.pi, bad.sum())
        r = rng.uniform(15.0, 60.0, bad.sum())
        px_a[bad] += np.column_stack([r * np.cos(ang), r * np.sin(ang)])
    ids = tuple(f"p{i}" for i in range(n_points))
    tracks = Tracks(tuple(p.image for p in poses), ids, pt_a, im_a, px_a,
                    np.full(len(pt_a), max(noise_px, 0.3)))
    return Block(poses, ground, tracks, bad)


def gnss_of(poses):
    return [p.image for p in poses], np.array([p.position for p in poses])


def run(b: Block, **kw) -> tuple[ModelBlock, GroundBlock]:
    block = independent_models(CAMS, ["c"] * len(b.tracks.images), b.tracks, **kw)
    return block, to_ground(block, gnss=gnss_of(b.poses))


def pose_errors(truth, got) -> tuple[float, float]:
    """Largest position error (ground units) and rotation error (deg) over the images."""
    by = {p.image: p for p in got}
    dpos = max(float(np.linalg.norm(by[p.image].position - p.position)) for p in truth)
    # rotation angle of R_true^T R_got from its skew part (precise for small angles)
    dang = 0.0
    for p in truth:
        D = p.rotation.T @ by[p.image].rotation
        w = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2
        dang = max(dang, math.degrees(math.asin(min(1.0, float(np.linalg.norm(w))))))
    return dpos, dang


def point_errors(b: Block, gb: GroundBlock) -> tuple[np.ndarray, np.ndarray]:
    """Errors (K,) of the triangulated points and which tracks (P,) have one."""
    idx = np.array([int(i[1:]) for i in gb.point_ids])
    ok = np.asarray(np.isfinite(gb.points).all(axis=1))
    return np.linalg.norm(gb.points[ok] - b.ground[idx[ok]], axis=1), ok


@cache
def cached(**kw) -> Block:
    return make_block(**kw)


# --------------------------------------------------------------------------- known answers
def test_exact_block_is_recovered():
    b = cached()
    block, gb = run(b)
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < 1e-6 * H
    assert dang < 1e-6
    e, ok = point_errors(b, gb)
    assert e.max() < 1e-6 * H
    # every track seen twice or more is a point, every observation is used
    assert ok.sum() == int((b.tracks.rays_per_point() >= 2).sum())
    assert block.obs_used.all()
    assert np.nanmax(block.residual_px) < 1e-6
    assert len(block.tree) == len(b.poses) - 1 == len(block.joins)
    assert all(j.rms_base < 1e-9 for j in block.joins)
    adj = block.adjustment
    assert adj is not None and adj.converged and adj.sigma0 < 1e-6
    assert adj.rms_base.shape == (7,) and adj.rms_base.max() < 1e-9
    assert gb.gnss_residuals.shape == (8, 3) and np.abs(gb.gnss_residuals).max() < 1e-6 * H


def test_noisy_block_within_tolerance():
    """0.3 px of image noise: poses within POS_TOL of the flying height and ANG_TOL_DEG, points likewise."""
    b = cached(noise_px=0.3)
    block, gb = run(b)
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG
    e, ok = point_errors(b, gb)
    assert np.median(e) < 1e-3 * H
    assert np.percentile(e, 95) < 2.5e-3 * H
    res = block.residual_px[np.isfinite(block.residual_px)]
    assert 0.15 < float(np.sqrt(np.mean(res ** 2))) < 0.6
    assert block.obs_used.mean() > 0.99
    # the joins are precise to about 1e-3 of the base
    assert all(j.rms_base < 5e-3 for j in block.joins[1:])
    # the simultaneous adjustment's sigma0 reads as the image noise in pixels
    adj = block.adjustment
    assert adj is not None and adj.converged
    assert 0.15 < adj.sigma0 < 0.45
    assert adj.rms_base.max() < 5e-3


def test_sequential_joins_only():
    """Without the simultaneous adjustment the sequential joins alone give the block."""
    b = cached(noise_px=0.3)
    block, gb = run(b, options=IndependentOptions(adjust=False))
    assert block.adjustment is None
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG
    assert len(block.summary_lines()) == 2 + 7


def test_three_strips():
    b = cached(strips=3, noise_px=0.3)
    block, gb = run(b)
    assert len(block.poses) == 12
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG
    e, _ = point_errors(b, gb)
    assert np.median(e) < 1.5e-3 * H


def test_opposite_strips_kappa_180():
    """The second strip flown the other way (kappa + 180 deg): cross-strip models still orient."""
    b = cached(noise_px=0.3, kappa_flip=True)
    _, gb = run(b)
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG


def test_spanning_tree_uses_cross_strip_links():
    b = cached(strips=3)
    block = independent_models(CAMS, ["c"] * 12, b.tracks)
    names = b.tracks.images
    tree = block.tree
    assert len(tree) == 11
    seen = set(tree[0])
    for left, right in tree[1:]:
        assert left in seen and right not in seen        # each model adds one new image
        seen.add(right)
    assert seen == set(range(12))
    strip = [n[:2] for n in names]
    cross = [(a, c) for a, c in tree if strip[a] != strip[c]]
    assert len(cross) >= 2                               # 3 strips need at least 2 links
    # the first model is the pair with the most common points
    counts = np.zeros((12, 12), dtype=int)
    for t in range(b.tracks.n_points):
        ims = b.tracks.obs_image[b.tracks.obs_point == t]
        counts[np.ix_(ims, ims)] += 1
    np.fill_diagonal(counts, 0)
    assert counts[tree[0]] == counts.max()
    assert [(j.left, j.right) for j in block.joins] == [(names[a], names[c]) for a, c in tree]


def test_blunders_are_rejected():
    """10 % of the observations moved by 15-60 px: the block still comes out right."""
    b = cached(noise_px=0.3, blunders=0.1)
    block, gb = run(b)
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG
    used = block.obs_used
    assert used[~b.blunder].mean() > 0.9                # good observations kept
    assert used[b.blunder].mean() < 0.25                # most blunders rejected (not those along the epipolar line)
    e, ok = point_errors(b, gb)
    multi = block.n_rays[ok] >= 3
    assert np.median(e) < 1e-3 * H
    assert np.percentile(e[multi], 95) < 3e-3 * H
    assert sum(j.n_relative_outliers for j in block.joins) > 0
    assert block.adjustment is not None and block.adjustment.n_rejected > 0


def test_relative_orientation_fallback(monkeypatch):
    """When the robust (essential-matrix) start fails, least squares from turned photo frames takes over."""
    b = cached(noise_px=0.3, kappa_flip=True)
    original = RelativeOrientation.from_points.__func__  # type: ignore[attr-defined]

    def no_essential(cls, *args, robust="none", **kw):
        if robust != "none":
            raise EstimationError("no essential matrix (test)")
        return original(cls, *args, robust=robust, **kw)

    monkeypatch.setattr(RelativeOrientation, "from_points", classmethod(no_essential))
    _, gb = run(b)
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG

    def nothing(cls, *args, **kw):
        raise EstimationError("nothing works (test)")

    monkeypatch.setattr(RelativeOrientation, "from_points", classmethod(nothing))
    with pytest.raises(StereoError, match=r"relative orientation of pair 's0i0'-'s0i1' failed: nothing works "
                                          r"\(test\); least squares from the zero start failed too"):
        independent_models(CAMS, ["c"] * 8, b.tracks)


def test_plain_least_squares_option():
    b = cached(noise_px=0.3)
    block, gb = run(b, options=IndependentOptions(robust="none"))
    assert pose_errors(b.poses, gb.poses)[0] < POS_TOL * H
    assert all(j.n_join_outliers == 0 for j in block.joins)


def test_two_cameras_with_distortion():
    """One camera per strip, the second with another focal length, principal point and distortion."""
    b = cached(two_cameras=True)
    camera_of = [p.camera for p in b.poses]
    block = independent_models(ALL_CAMS, camera_of, b.tracks)
    assert [p.camera for p in block.poses] == camera_of
    gb = to_ground(block, gnss=gnss_of(b.poses))
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < 1e-6 * H
    assert dang < 1e-6
    e, _ = point_errors(b, gb)
    assert e.max() < 1e-6 * H


def test_height_control_points():
    """Control with X and Y unknown (height points) joins GNSS centres in the similarity."""
    b = cached(noise_px=0.3)
    block = independent_models(CAMS, ["c"] * 8, b.tracks)
    ids = [b.tracks.point_ids[t] for t in np.flatnonzero(b.tracks.rays_per_point() >= 3)[::40]]
    xyz = b.ground[[int(i[1:]) for i in ids]].copy()
    xyz[:, :2] = np.nan
    gb = to_ground(block, control=(ids, xyz), gnss=gnss_of(b.poses))
    assert gb.similarity.extra["height_points"] == ids
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG


def test_control_points_instead_of_gnss():
    b = cached(noise_px=0.3)
    block = independent_models(CAMS, ["c"] * 8, b.tracks)
    rays = b.tracks.rays_per_point()
    ids = [b.tracks.point_ids[t] for t in np.flatnonzero(rays >= 3)[::25]]
    xyz = b.ground[[int(i[1:]) for i in ids]]
    gb = to_ground(block, control=(ids, xyz))
    dpos, dang = pose_errors(b.poses, gb.poses)
    assert dpos < POS_TOL * H
    assert dang < ANG_TOL_DEG
    assert gb.control_ids == tuple(ids) and gb.control_residuals.shape == (len(ids), 3)
    assert gb.gnss_images == () and gb.gnss_residuals.shape == (0, 3)
    both = to_ground(block, control=(ids, xyz), gnss=gnss_of(b.poses[:2]))
    assert both.residuals.n == len(ids) + 2
    assert any(i.startswith("gnss:") for i in both.residuals.ids)
    assert "control" in "\n".join(both.summary_lines())


def test_given_pairs_and_progress():
    b = cached()
    pairs = [(0, 1), (1, 2), (2, 3), (1, 5), (4, 5), (5, 6), (6, 7), (0, 4)]   # (0, 4) closes a loop
    calls = []
    block = independent_models(CAMS, ["c"] * 8, b.tracks, pairs=pairs, progress=lambda i, n: calls.append((i, n)))
    assert block.tree == ((0, 1), (1, 2), (2, 3), (1, 5), (5, 4), (5, 6), (6, 7))
    assert calls[-1] == (8, 8) and len(calls) == 8
    gb = to_ground(block, gnss=gnss_of(b.poses))
    assert pose_errors(b.poses, gb.poses)[0] < 1e-6 * H


def test_results_are_frozen_and_summarised():
    b = cached()
    block, gb = run(b)
    with pytest.raises(ValueError):
        block.points[0, 0] = 1.0
    with pytest.raises(AttributeError):
        block.points = None  # type: ignore[misc, assignment]
    lines = block.summary_lines()
    assert lines[0].startswith("independent models: 8 images, 7 models")
    assert len(lines) == 3 + 7
    assert lines[2].startswith("model adjustment: ")
    assert gb.summary_lines()[0].startswith("block to ground: scale")
    assert block.images == b.tracks.images
    assert block.n_points == int(np.isfinite(block.points).all(axis=1).sum())


# --------------------------------------------------------------------------- invariance
def permuted(b: Block, perm: list[int]) -> Tracks:
    """The same tracks with the images in the order ``perm`` (new index k is old image perm[k])."""
    t = b.tracks
    new_of_old = np.argsort(perm)
    return Tracks(tuple(t.images[i] for i in perm), t.point_ids, t.obs_point, new_of_old[t.obs_image],
                  t.obs_pixel, t.obs_sigma_px)


@cache
def reference_noisy() -> GroundBlock:
    return run(cached(noise_px=0.3))[1]


@settings(max_examples=6, deadline=None)
@given(st.permutations(list(range(8))))
def test_result_does_not_depend_on_the_order_of_images(perm):
    b = cached(noise_px=0.3)
    ref = reference_noisy()
    tracks = permuted(b, perm)
    block = independent_models(CAMS, ["c"] * 8, tracks)
    gb = to_ground(block, gnss=gnss_of(b.poses))
    by = {p.image: p for p in gb.poses}
    for p in ref.poses:
        np.testing.assert_allclose(by[p.image].position, p.position, atol=1e-6 * H)
        np.testing.assert_allclose(by[p.image].rotation, p.rotation, atol=1e-8)
    assert gb.point_ids == ref.point_ids
    np.testing.assert_allclose(gb.points, ref.points, atol=1e-6 * H)


# --------------------------------------------------------------------------- bad input
def test_bad_camera_list():
    t = cached().tracks
    with pytest.raises(ShapeError, match="one camera per image"):
        independent_models(CAMS, ["c"] * 7, t)
    with pytest.raises(InvalidInputError, match="names camera 'x'"):
        independent_models(CAMS, ["c"] * 7 + ["x"], t)
    with pytest.raises(InvalidInputError, match="sequence of camera ids"):
        independent_models(CAMS, "c", t)


def test_one_image_is_not_a_block():
    t = Tracks(("a",), (), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    with pytest.raises(InvalidInputError, match="at least 2 images"):
        independent_models(CAMS, ["c"], t)


def test_disconnected_image_graph_names_components():
    b = cached()
    t = b.tracks
    strip = np.array([int(n[1]) for n in t.images])[t.obs_image]
    first_strip = np.bincount(t.obs_point[strip == 0], minlength=t.n_points) > 0
    keep = ~((strip == 1) & first_strip[t.obs_point])     # no track spans both strips
    cut = t.subset(keep)
    with pytest.raises(StereoError, match=r"disconnected .*2 components \['s0i0', 's0i1', 's0i2', 's0i3'\]; "
                                          r"\['s1i0', 's1i1', 's1i2', 's1i3'\]"):
        independent_models(CAMS, ["c"] * 8, cut)


def test_given_pairs_errors():
    t = cached().tracks
    with pytest.raises(StereoError, match=r"pair 's0i0'-'s1i3' has 0 common points; at least 12"):
        independent_models(CAMS, ["c"] * 8, t, pairs=[(0, 1), (0, 7)])
    with pytest.raises(StereoError, match="given pairs leave the image graph disconnected: 7 components"):
        independent_models(CAMS, ["c"] * 8, t, pairs=[(0, 1)])
    with pytest.raises(InvalidInputError, match=r"pair \(0, 8\): image indices"):
        independent_models(CAMS, ["c"] * 8, t, pairs=[(0, 8)])
    with pytest.raises(InvalidInputError, match=r"pair \(3, 3\)"):
        independent_models(CAMS, ["c"] * 8, t, pairs=[(3, 3)])
    with pytest.raises(InvalidInputError, match="two image indices"):
        independent_models(CAMS, ["c"] * 8, t, pairs=[(0, 1, 2)])  # type: ignore[list-item]
    with pytest.raises(InvalidInputError, match="`pairs` is empty"):
        independent_models(CAMS, ["c"] * 8, t, pairs=[])


def test_failed_relative_orientation_names_the_pair():
    """Two identical photos (no base): the relative orientation fails, the pair is named."""
    rng = np.random.default_rng(3)
    px = rng.uniform([0, 0], [1999, 1499], (40, 2))
    t = Tracks(("a", "b"), tuple(f"q{i}" for i in range(40)), np.repeat(np.arange(40), 2),
               np.tile([0, 1], 40), np.repeat(px, 2, axis=0))
    with pytest.raises(StereoError, match="relative orientation of pair 'a'-'b' failed: "):
        independent_models(CAMS, ["c", "c"], t)


def test_model_sharing_too_few_points():
    t = cached().tracks
    with pytest.raises(StereoError, match=r"model '.*'-'.*' shares \d+ tie points with the block so far; "
                                          "at least 100000"):
        independent_models(CAMS, ["c"] * 8, t, options=IndependentOptions(min_join_points=100000))


@pytest.mark.parametrize("kw, msg", [
    ({"min_common": 4}, "`min_common` must be >= 5"),
    ({"min_join_points": 1}, "`min_join_points` must be >= 2"),
    ({"robust": "bogus"}, "unknown robust option 'bogus'"),
    ({"system": "bogus"}, "unknown system 'bogus'"),
    ({"join_trim": 0.0}, "`join_trim` must be a finite number > 0"),
    ({"outlier_floor_px": float("nan")}, "`outlier_floor_px` must be"),
    ({"min_angle_rad": 2.0}, r"`min_angle_rad` must be in \[0, pi/2\)"),
    ({"max_rejection_rounds": -1}, "`max_rejection_rounds` must be >= 0"),
    ({"adjust_iterations": 0}, "`adjust_iterations` must be >= 1"),
])
def test_bad_options(kw, msg):
    with pytest.raises(InvalidInputError, match=msg):
        IndependentOptions(**kw)


def test_to_ground_errors():
    b = cached()
    block = independent_models(CAMS, ["c"] * 8, b.tracks)
    names, pos = gnss_of(b.poses)
    with pytest.raises(EstimationError, match=r"too few points .*0 control point\(s\) and 2 GNSS centre\(s\)"):
        to_ground(block, gnss=(names[:2], pos[:2]))
    with pytest.raises(EstimationError, match="too few points"):
        to_ground(block)
    line = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]])
    with pytest.raises(EstimationError, match="collinear or too few in the ground frame"):
        to_ground(block, gnss=(names[:3], line))
    with pytest.raises(InvalidInputError, match=r"GNSS image\(s\) \['nope'\] are not images of the block"):
        to_ground(block, gnss=(["nope", *names[1:]], pos))
    with pytest.raises(ShapeError, match=r"GNSS positions must be finite with shape \(8, 3\)"):
        to_ground(block, gnss=(names, pos[:7]))
    with pytest.raises(InvalidInputError, match="duplicate GNSS image names"):
        to_ground(block, gnss=([names[0]] * 8, pos))
    with pytest.raises(InvalidInputError, match=r"control point\(s\) \['zz'\] are not tracks of the block"):
        to_ground(block, control=(["zz"], [[0.0, 0, 0]]), gnss=(names, pos))
    with pytest.raises(ShapeError, match=r"control coordinates must have shape \(2, 3\)"):
        to_ground(block, control=(["p1", "p2"], [[0.0, 0, 0]]), gnss=(names, pos))
    with pytest.raises(InvalidInputError, match="duplicate control point ids"):
        to_ground(block, control=(["p1", "p1"], np.zeros((2, 3))), gnss=(names, pos))
    with pytest.raises(InvalidInputError, match="unknown robust option 'bogus'"):
        to_ground(block, gnss=(names, pos), robust="bogus")
