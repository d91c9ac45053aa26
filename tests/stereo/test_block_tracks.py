"""Block tie points: union-find tracks, conflicts, even spread, pair selection, a rendered 2 x 3 block."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError, RasterIOError
from rectify.features.match import MatcherConfig
from rectify.geometry.camera import Camera
from stereo.block.tracks_graph import (
    PairMatches,
    build_tracks,
    connected_labels,
    grid_coverage,
    rays_histogram,
    spread_tracks,
)
from stereo.block.tracks_pairs import footprints, select_pairs
from stereo.block.types import Pose, Tracks, project_pixel
from stereo.features.tracks import BlockMatchOptions, block_components, block_tie_points
from tests.support.block_render import BlockTerrain, make_terrain, render_block, render_image, strip_poses

CAM = Camera(focal_length_mm=20.0, pixel_size_mm=0.05, width=400, height=300)
H_FLY = 100.0          # flying height above the mean terrain, m
Z0 = 50.0              # mean terrain height, m
GSD = H_FLY * CAM.pixel_size_mm / CAM.focal_length_mm      # 0.25 m


# --------------------------------------------------------------------------- union-find, hand-made answers
def _track_sets(build) -> set[frozenset[tuple[int, int]]]:
    t = build.tracks
    out: dict[int, set[tuple[int, int]]] = {}
    for p, i, k in zip(t.obs_point, t.obs_image, build.obs_keypoint, strict=True):
        out.setdefault(int(p), set()).add((int(i), int(k)))
    return {frozenset(s) for s in out.values()}


def _pm(i: int, j: int, kp_i, kp_j, score=None) -> PairMatches:
    """PairMatches from plain lists."""
    s = np.zeros(0) if score is None else np.asarray(score, dtype=np.float64)
    return PairMatches(i, j, np.asarray(kp_i, dtype=np.int64), np.asarray(kp_j, dtype=np.int64), s)


def _kps(counts: list[int]) -> list[np.ndarray]:
    """Distinct positions: keypoint k of image i at (10 k, 7 i)."""
    return [np.column_stack([10.0 * np.arange(n), np.full(n, 7.0 * i)]) for i, n in enumerate(counts)]


def test_connected_labels_known_answer():
    lab = connected_labels(7, [0, 2, 5, 3], [1, 3, 6, 1])
    assert lab.tolist() == [0, 0, 0, 0, 4, 5, 5]
    assert connected_labels(3, [], []).tolist() == [0, 1, 2]
    with pytest.raises(InvalidInputError, match=r"0\.\.2"):
        connected_labels(3, [0], [3])


def test_tracks_known_answer_and_conflicts():
    # image 0 keypoints 0..2, image 1 keypoints 0..2, image 2 keypoints 0..2
    kp = _kps([3, 3, 3])
    m = [_pm(0, 1, [0, 1, 2], [0, 1, 2]),
         _pm(1, 2, [0, 1], [0, 1]),
         _pm(0, 2, [2], [0])]          # joins (0,0)-(1,0)-(2,0) with (0,2)-(1,2): a conflict
    drop = build_tracks(kp, m, images=["a", "b", "c"], conflicts="drop")
    assert _track_sets(drop) == {frozenset({(0, 1), (1, 1), (2, 1)})}
    assert (drop.n_components, drop.n_conflicting, drop.n_split, drop.n_obs_dropped) == (2, 1, 0, 5)
    assert drop.tracks.images == ("a", "b", "c") and drop.tracks.point_ids == ("t1",)
    assert_allclose(drop.tracks.obs_pixel, [[10, 0], [10, 7], [10, 14]])
    split = build_tracks(kp, m, conflicts="split")
    # image 0 keeps keypoint 2 (2 matches), image 1 keeps keypoint 0 (2 matches)
    assert _track_sets(split) == {frozenset({(0, 1), (1, 1), (2, 1)}), frozenset({(0, 2), (1, 0), (2, 0)})}
    assert (split.n_conflicting, split.n_split, split.n_obs_dropped) == (1, 1, 2)
    assert rays_histogram(split.tracks) == {3: 2}


def test_tracks_min_rays_ranking_and_merge():
    kp = _kps([2, 2, 2])
    m = [_pm(0, 1, [0, 1], [0, 1], [0.5, 0.2]), _pm(1, 2, [0], [0], [0.3])]
    b = build_tracks(kp, m)
    assert b.tracks.rays_per_point().tolist() == [3, 2]          # more rays first
    assert_allclose(b.track_score, [0.4, 0.2])
    b3 = build_tracks(kp, m, min_rays=3)
    assert b3.tracks.n_points == 1 and b3.n_short == 1
    # two keypoints of image 0 at one position (two SIFT orientations) are one node: no conflict
    kp2 = [np.array([[5.0, 5.0], [5.0, 5.0]]), np.array([[1.0, 1.0]]), np.array([[2.0, 2.0]])]
    mm = [_pm(0, 1, [0], [0]), _pm(0, 2, [1], [0])]
    b = build_tracks(kp2, mm)
    assert b.n_conflicting == 0 and b.n_merged == 1 and b.tracks.rays_per_point().tolist() == [3]


def test_tracks_bad_inputs():
    kp = _kps([2, 2])
    with pytest.raises(InvalidInputError, match="conflict policy 'merge'"):
        build_tracks(kp, [], conflicts="merge")
    with pytest.raises(InvalidInputError, match="min_rays must be >= 2; got 1"):
        build_tracks(kp, [], min_rays=1)
    with pytest.raises(InvalidInputError, match=r"keypoint index out of range 0\.\.1 for image '1'"):
        build_tracks(kp, [_pm(0, 1, [0], [5])])
    with pytest.raises(InvalidInputError, match="names image 4"):
        build_tracks(kp, [_pm(0, 4, [0], [0])])
    with pytest.raises(InvalidInputError, match=r"two different images; got \(1, 1\)"):
        _pm(1, 1, [0], [0])
    with pytest.raises(InvalidInputError, match="one value per match"):
        _pm(0, 1, [0, 1], [0])


def _reference_components(counts, edges):
    """Plain BFS components of the (image, keypoint) graph: the slow, obvious answer."""
    adj: dict[tuple[int, int], set[tuple[int, int]]] = {}
    for a, b in edges:
        adj.setdefault(a, set()).add(b)
        adj.setdefault(b, set()).add(a)
    seen: set[tuple[int, int]] = set()
    comps = []
    for s in adj:
        if s in seen:
            continue
        stack, comp = [s], set()
        while stack:
            x = stack.pop()
            if x in comp:
                continue
            comp.add(x)
            stack.extend(adj[x] - comp)
        seen |= comp
        comps.append(frozenset(comp))
    return comps


@st.composite
def _match_lists(draw):
    counts = draw(st.lists(st.integers(1, 5), min_size=2, max_size=5))
    n = len(counts)
    node = st.tuples(st.integers(0, n - 1), st.integers(0, 4)).map(lambda t: (t[0], t[1] % counts[t[0]]))
    edges = draw(st.lists(st.tuples(node, node).filter(lambda e: e[0][0] != e[1][0]), max_size=25))
    return counts, edges


def _pair_matches(edges, reverse=False):
    by_pair: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for (i, a), (j, b) in edges:
        if reverse:
            (i, a), (j, b) = (j, b), (i, a)
        by_pair.setdefault((i, j), []).append((a, b))
    return [_pm(i, j, [x[0] for x in v], [x[1] for x in v]) for (i, j), v in by_pair.items()]


@settings(max_examples=80, deadline=None)
@given(_match_lists(), st.randoms(use_true_random=False))
def test_union_find_property(data, rnd):
    counts, edges = data
    kp = _kps(counts)
    comps = _reference_components(counts, edges)
    ok = [c for c in comps if len({i for i, _ in c}) == len(c) and len(c) >= 2]
    for policy in ("drop", "split"):
        b = build_tracks(kp, _pair_matches(edges), conflicts=policy)
        sets = _track_sets(b)
        nodes = [x for s in sets for x in s]
        assert len(nodes) == len(set(nodes))                      # the tracks partition their observations
        assert all(len({i for i, _ in s}) == len(s) >= 2 for s in sets)   # one observation per image, >= 2 rays
        assert all(any(s <= c for c in comps) for s in sets)     # each track lies in one component
        if policy == "drop":
            assert sets == set(ok)                                # exactly the conflict-free components
        else:
            assert set(ok) <= sets
        shuffled = list(edges)
        rnd.shuffle(shuffled)
        b2 = build_tracks(kp, _pair_matches(shuffled, reverse=True), conflicts=policy)
        assert _track_sets(b2) == sets                            # independent of match order and direction
        assert b2.tracks.point_ids == b.tracks.point_ids


def test_spread_keeps_best_per_cell_and_coverage():
    # two images 80 x 80, grid 2 x 2; tracks 0..2 all in the top-left cell of both images
    t = Tracks(("a", "b"), ("p", "q", "r", "s"),
               np.array([0, 0, 1, 1, 2, 2, 3, 3]), np.array([0, 1, 0, 1, 0, 1, 0, 1]),
               np.array([[5, 5], [5, 5], [6, 6], [6, 6], [7, 7], [7, 7], [60, 60], [60, 10]], dtype=float))
    res = spread_tracks(t, [[80, 80], [80, 80]], grid=(2, 2), per_cell=1, track_score=[0.5, 0.1, 0.9, 0.5])
    assert res.keep.tolist() == [False, True, False, True]
    assert res.points_per_image.tolist() == [2, 2]
    assert_allclose(res.coverage, [0.5, 0.5])
    assert_allclose(grid_coverage([[0, 0], [79, 79]], [0, 0], [[80, 80]], grid=(2, 2)), [0.5])
    with pytest.raises(InvalidInputError, match="per_cell"):
        spread_tracks(t, [[80, 80], [80, 80]], per_cell=0)


# --------------------------------------------------------------------------- pair selection
def _layout(alternate: bool = False, angle_sigma_rad: float = 0.0, seed: int = 0) -> list[Pose]:
    return strip_poses(CAM, n_strips=2, n_per_strip=3, flying_height_m=H_FLY, ground_z=Z0,
                       forward_overlap=0.6, side_overlap=0.3, alternate=alternate, angle_sigma_rad=angle_sigma_rad,
                       seed=seed)


def test_footprint_pairs_of_two_strips():
    # vertical images, 60 % forward and 30 % side overlap: images 0 1 2 over 3 4 5
    poses = _layout()
    fp = footprints(poses, CAM, Z0)
    assert_allclose(fp[0], [[-50, 37.5], [50, 37.5], [50, -37.5], [-50, -37.5]], atol=1e-9)
    expected = {(0, 1): 0.6, (0, 2): 0.2, (0, 3): 0.3, (0, 4): 0.18,
                (1, 2): 0.6, (1, 3): 0.18, (1, 4): 0.3, (1, 5): 0.18,
                (2, 4): 0.18, (2, 5): 0.3,
                (3, 4): 0.6, (3, 5): 0.2, (4, 5): 0.6}       # (0, 5) and (2, 3) overlap 0.06 < 0.1
    pairs = select_pairs(6, cameras=CAM, poses=poses, ground_z=Z0)
    assert {(p.i, p.j): round(p.overlap, 4) for p in pairs} == expected
    assert {p.reason for p in pairs} == {"footprints"}
    strong = select_pairs(6, cameras={"cam": CAM}, poses=poses, ground_z=Z0, min_overlap=0.25)
    assert [(p.i, p.j) for p in strong] == [(0, 1), (0, 3), (1, 2), (1, 4), (2, 5), (3, 4), (4, 5)]


def test_pair_strategies_and_errors():
    assert len(select_pairs(["a", "b", "c", "d"])) == 6
    assert {p.reason for p in select_pairs(5)} == {"all"}
    with pytest.raises(InvalidInputError, match="at least 2 images; got 1"):
        select_pairs(1)
    with pytest.raises(InvalidInputError, match="unknown pair strategy 'nearest'"):
        select_pairs(3, strategy="nearest")
    with pytest.raises(InvalidInputError, match=r"missing \['ground_z'\]"):
        select_pairs(6, cameras=CAM, poses=_layout(), strategy="footprints")
    with pytest.raises(InvalidInputError, match="needs the image paths"):
        select_pairs(3, strategy="overview")
    with pytest.raises(InvalidInputError, match="min_overlap must be in"):
        select_pairs(3, min_overlap=0.0)
    with pytest.raises(InvalidInputError, match="5 poses for 6 images"):
        select_pairs(6, cameras=CAM, poses=_layout()[:5], ground_z=Z0)
    with pytest.raises(InvalidInputError, match="names camera 'cam'"):
        select_pairs(6, cameras={"other": CAM}, poses=_layout(), ground_z=Z0)


# --------------------------------------------------------------------------- a rendered block
def _terrain(seed: int = 3) -> BlockTerrain:
    w, h = CAM.width * GSD, CAM.height * GSD
    ext = (-w / 2 - 20, -(1 - 0.3) * h - h / 2 - 20, 2 * 0.4 * w + w / 2 + 20, h / 2 + 20)
    return make_terrain(ext, cell_m=GSD, base_height_m=Z0 - 3.0, relief_m=8.0, seed=seed)


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    out = tmp_path_factory.mktemp("block")
    terrain = _terrain()
    poses = _layout(alternate=True, angle_sigma_rad=0.01, seed=1)
    paths = render_block(CAM, poses, terrain, out)
    opts = BlockMatchOptions(matcher=MatcherConfig(verify="fundamental", max_keypoints=3000))
    res = block_tie_points(paths, cameras=CAM, poses=poses, ground_z=terrain.mean_height, options=opts)
    return terrain, poses, paths, res


def test_render_block_files_and_truth(block, tmp_path):
    terrain, poses, paths, _ = block
    assert [p.name for p in paths] == [f"{q.image}.png" for q in poses]
    img = cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE)
    assert img is not None and img.shape == (300, 400) and img.min() > 0 and img.std() > 20
    # a ray-cast ground point projects back to its pixel
    px = np.array([[10.0, 20.0], [200.0, 150.0], [390.0, 290.0]])
    g = terrain.ground_from_pixel(CAM, poses[0], px)
    assert_allclose(g[:, 2], terrain.height(g[:, :2]), atol=1e-4)
    assert_allclose(project_pixel(CAM, poses[0], g), px, atol=1e-3)
    tif = render_block(CAM, poses[:1], terrain, tmp_path, suffix=".tif")
    assert tif[0].suffix == ".tif" and tif[0].stat().st_size > 0
    with pytest.raises(InvalidInputError, match="suffix must be"):
        render_block(CAM, poses[:1], terrain, tmp_path, suffix=".jpg")
    with pytest.raises(InvalidInputError, match="supersample must be >= 1; got 0"):
        render_image(terrain, CAM, poses[0], supersample=0)


def _true_errors(terrain, poses, tracks: Tracks) -> tuple[np.ndarray, np.ndarray]:
    """Each track's first observation ray-cast onto the DEM, projected into its other images: the
    distance to the measured pixels (px), and the mask of those other observations."""
    first = np.r_[True, tracks.obs_point[1:] != tracks.obs_point[:-1]]
    fi = np.flatnonzero(first)
    G = np.full((tracks.n_points, 3), np.nan)
    for k, pose in enumerate(poses):
        s = fi[tracks.obs_image[fi] == k]
        G[tracks.obs_point[s]] = terrain.ground_from_pixel(CAM, pose, tracks.obs_pixel[s])
    proj = np.full((tracks.n_obs, 2), np.nan)
    for k, pose in enumerate(poses):
        s = tracks.obs_image == k
        proj[s] = project_pixel(CAM, pose, G[tracks.obs_point[s]])
    return np.linalg.norm(proj - tracks.obs_pixel, axis=1)[~first], ~first


def test_block_tracks_agree_with_truth(block):
    terrain, poses, _, res = block
    t = res.tracks
    assert t.images == tuple(p.image for p in poses)
    assert t.n_points > 300
    err, _ = _true_errors(terrain, poses, t)
    assert np.isfinite(err).all()
    assert np.median(err) < 0.5
    assert np.mean(err < 1.0) > 0.97
    assert res.n_refined > 0 and set(np.unique(t.obs_sigma_px)) <= {0.25, 0.5}
    assert all(p.status == "ok" for p in res.pairs) and len(res.pairs) == 13


def test_block_multi_ray_tracks_across_strips(block):
    _, _, _, res = block
    t = res.tracks
    rays = t.rays_per_point()
    strip = np.array([0, 0, 0, 1, 1, 1])[t.obs_image]
    both = np.zeros(t.n_points, dtype=bool)
    for p in range(t.n_points):
        both[p] = len(np.unique(strip[t.obs_point == p])) == 2
    assert np.sum(both & (rays >= 3)) >= 20
    assert max(res.rays_histogram) >= 4
    assert sum(res.rays_histogram.values()) == t.n_points
    assert block_components(t) == [[0, 1, 2, 3, 4, 5]]


def test_block_every_image_covered(block):
    terrain, poses, _, res = block
    gx, gy = res.grid
    # coverable cells: the cell centre is seen by at least one other image
    cx = (np.arange(gx) + 0.5) * CAM.width / gx - 0.5
    cy = (np.arange(gy) + 0.5) * CAM.height / gy - 0.5
    centres = np.array([[x, y] for y in cy for x in cx])
    for k, pose in enumerate(poses):
        g = terrain.ground_from_pixel(CAM, pose, centres)
        seen = np.zeros(len(centres), dtype=bool)
        for j, other in enumerate(poses):
            if j != k:
                q = project_pixel(CAM, other, g)
                seen |= (q[:, 0] > 8) & (q[:, 1] > 8) & (q[:, 0] < CAM.width - 9) & (q[:, 1] < CAM.height - 9)
        assert res.coverage[k] >= 0.9 * seen.mean(), (pose.image, res.coverage[k], seen.mean())
        assert res.coverage[k] >= 0.6
    assert (res.points_per_image >= 100).all()
    assert res.points_per_image.tolist() == res.tracks.points_per_image().tolist()
    lines = res.summary_lines()
    assert lines[0].startswith(f"block tie points: {res.tracks.n_points} tracks")
    assert any(line.strip().startswith(f"{poses[0].image}: ") and "coverage" in line for line in lines)


def test_overview_pair_selection_finds_neighbours(block):
    _, _, paths, _ = block
    pairs = select_pairs(6, images=paths, strategy="overview", neighbours=2, overview_px=256)
    got = {(p.i, p.j) for p in pairs}
    # along each strip the neighbours overlap 60 % (strip 2 is flown back: 3 4 5 lie over 2 1 0)
    assert {(0, 1), (1, 2), (3, 4), (4, 5)} <= got
    assert all(p.overview_matches >= 12 for p in pairs)


# --------------------------------------------------------------------------- bad inputs
def test_block_bad_inputs(block, tmp_path):
    terrain, poses, paths, _ = block
    with pytest.raises(InvalidInputError, match="at least 2 images; got 1"):
        block_tie_points(paths[:1])
    (tmp_path / "x").mkdir()
    dup = tmp_path / "x" / paths[0].name
    dup.write_bytes(paths[0].read_bytes())
    with pytest.raises(InvalidInputError, match=r"duplicate image names \['img_1_1'\].*names="):
        block_tie_points([paths[0], dup])
    with pytest.raises(InvalidInputError, match="3 names for 2 images"):
        block_tie_points(paths[:2], names=["a", "b", "c"])
    bad = tmp_path / "broken.png"
    bad.write_text("not an image")
    with pytest.raises(RasterIOError, match="broken.png"):
        block_tie_points([paths[0], bad])
    with pytest.raises(RasterIOError, match="missing.png"):
        block_tie_points([paths[0], tmp_path / "missing.png"])
    with pytest.raises(InvalidInputError, match=r"no pose for image\(s\) \['img_1_2'\]"):
        block_tie_points(paths[:2], cameras=CAM, poses=poses[:1], ground_z=Z0)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((300, 400), 128, np.uint8))
    with pytest.raises(EstimationError, match=r"only 0 keypoints found in image .*blank.png"):
        block_tie_points([paths[0], blank])


def test_block_option_errors():
    with pytest.raises(InvalidInputError, match="unknown conflict policy 'keep'"):
        BlockMatchOptions(conflicts="keep")
    with pytest.raises(InvalidInputError, match="unknown pair strategy 'x'"):
        BlockMatchOptions(pair_strategy="x")
    with pytest.raises(InvalidInputError, match=r"grid must be two integers >= 1.*\(8, 0\)"):
        BlockMatchOptions(grid=(8, 0))
    with pytest.raises(InvalidInputError, match="per_cell must be an integer >= 1; got 0"):
        BlockMatchOptions(per_cell=0)
    with pytest.raises(InvalidInputError, match="sigma_px must be a positive number; got -1"):
        BlockMatchOptions(sigma_px=-1)


def test_block_unconnected_image_and_disconnected_block(block, tmp_path):
    _, poses, paths, _ = block
    other = _terrain(seed=11)
    foreign = render_block(CAM, [Pose("far_1", "cam", poses[0].position, poses[0].rotation),
                                 Pose("far_2", "cam", poses[1].position, poses[1].rotation)], other, tmp_path)
    opts = BlockMatchOptions(matcher=MatcherConfig(verify="fundamental", max_keypoints=1500, refine=False))
    with pytest.raises(EstimationError, match=r"image\(s\) \['far_1'\] have no tie points to any other image"):
        block_tie_points([paths[0], paths[1], foreign[0]], options=opts)
    with pytest.raises(EstimationError, match=r"disconnected: 2 groups.*\[img_1_1, img_1_2\] \| \[far_1, far_2\]"):
        block_tie_points([paths[0], paths[1], *foreign], options=opts)


def test_block_split_policy_and_sizes(block):
    # the split policy keeps at least as many tracks as dropping; the pieces are counted
    _, poses, paths, res = block
    opts = BlockMatchOptions(matcher=MatcherConfig(verify="fundamental", max_keypoints=3000, refine=False),
                             conflicts="split", per_cell=2, grid=(4, 4))
    r = block_tie_points(paths, names=[p.image for p in poses], options=opts)
    assert r.tracks.n_points > 0 and r.n_refined == 0
    assert set(np.unique(r.tracks.obs_sigma_px)) == {0.5}
    assert r.n_split <= r.n_conflicting * 3
    assert {p.reason for p in r.pairs} == {"all"} and len(r.pairs) == 15
    # every image keeps at most per_cell tracks per cell that it alone chose; spread caps the total
    assert r.tracks.n_points <= 6 * 16 * 2
    assert math.isclose(sum(r.rays_histogram.values()), r.tracks.n_points)
    assert Path(paths[0]).exists()


def test_block_large_images_detected_on_overviews(block):
    # images above detect_max_px are detected on an overview: positions scaled back, sigma scaled,
    # no refinement; the progress callback ends at (total, total)
    terrain, poses, paths, _ = block
    calls: list[tuple[int, int]] = []
    opts = BlockMatchOptions(matcher=MatcherConfig(verify="fundamental", max_keypoints=2000, min_inliers=10),
                             detect_max_px=200)
    r = block_tie_points(paths[:3], cameras=CAM, poses=poses[:3], ground_z=terrain.mean_height, options=opts,
                         progress=lambda d, t: calls.append((d, t)))
    assert calls[-1][0] == calls[-1][1] and len(calls) >= 3 + len(r.pairs)
    assert r.n_refined == 0 and set(np.unique(r.tracks.obs_sigma_px)) == {1.0}
    err, _ = _true_errors(terrain, poses[:3], r.tracks)
    assert np.median(err) < 1.5
