"""Tracks from pairwise matches: union-find over (image, keypoint) nodes, conflicts, even spread.

A block's keypoints are detected once per image, so keypoint ``k`` of image ``i`` is one node of a
graph whatever pair it is matched in; every verified match of a pair is an edge. The connected
components of that graph (union-find) are the tracks.

Conflicts
---------
A component that holds two different keypoints of one image is a *conflict*: some match in it is
wrong (or two keypoints sit on one feature). With ``conflicts="drop"`` the whole track is dropped.
With ``conflicts="split"`` each conflicting image keeps only its best-supported keypoint (most
matches inside the component, then the best mean match score, then the lowest index), the other
keypoints of that image are removed, and the components are recomputed on the remaining nodes; the
pieces are kept when they still reach ``min_rays`` images. Both ways are counted
(:class:`TrackBuild`).

Keypoints of one image at the same position (within 0.05 px; SIFT gives one keypoint per dominant
orientation) are merged into one node before the components are formed, so that they do not make
false conflicts.

Even spread
-----------
:func:`spread_tracks` keeps, in every image, at most ``per_cell`` tracks per grid cell, preferring
tracks with more rays, then better scores; a track is kept when any of its images selects it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError
from stereo.block.types import Tracks

__all__ = ["CONFLICT_POLICIES", "PairMatches", "SpreadResult", "TrackBuild", "build_tracks", "connected_labels",
           "grid_coverage", "rays_histogram", "spread_tracks"]

CONFLICT_POLICIES = ("drop", "split")

#: keypoints of one image closer than this (px, each axis) are one node
SAME_POSITION_PX = 0.05


@dataclass(frozen=True, eq=False)
class PairMatches:
    """Verified matches of one image pair, as keypoint indices.

    Attributes
    ----------
    i, j : int
        Image indices (block order), i != j.
    kp_i, kp_j : (M,) int64
        Keypoint indices in image i and image j.
    score : (M,) float64
        Match quality, lower is better (the descriptor distance ratio); ones by default.
    """

    i: int
    j: int
    kp_i: NDArray[np.int64]
    kp_j: NDArray[np.int64]
    score: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        a = np.array(self.kp_i, dtype=np.int64, copy=True).reshape(-1)
        b = np.array(self.kp_j, dtype=np.int64, copy=True).reshape(-1)
        s = np.array(self.score, dtype=np.float64, copy=True).reshape(-1)
        if s.size == 0:
            s = np.ones(len(a))
        if len(b) != len(a) or len(s) != len(a):
            raise ShapeError(f"pair ({self.i}, {self.j}): kp_i, kp_j and score must have one value per match; "
                             f"got {len(a)}, {len(b)} and {len(s)}")
        if int(self.i) == int(self.j):
            raise InvalidInputError(f"a pair needs two different images; got ({self.i}, {self.j})")
        for arr in (a, b, s):
            arr.flags.writeable = False
        object.__setattr__(self, "i", int(self.i))
        object.__setattr__(self, "j", int(self.j))
        object.__setattr__(self, "kp_i", a)
        object.__setattr__(self, "kp_j", b)
        object.__setattr__(self, "score", s)

    def __len__(self) -> int:
        return len(self.kp_i)


@dataclass(frozen=True, eq=False)
class TrackBuild:
    """Tracks built from pairwise matches (:func:`build_tracks`).

    Attributes
    ----------
    tracks : Tracks
        Sorted by track, then image; ``obs_sigma_px`` is 1 (the caller sets the real ones).
    obs_keypoint : (M,) int64
        Keypoint index of each observation in its image (same order as ``tracks``).
    track_score : (P,) float64
        Mean match score of the edges inside each track (lower is better).
    n_components : int
        Connected components with two or more images, before conflicts.
    n_conflicting : int
        Components holding two different keypoints of one image.
    n_split : int
        Tracks made from the pieces of conflicting components (``conflicts="split"``).
    n_obs_dropped : int
        Observations lost to conflicts (the dropped components, or the removed keypoints).
    n_short : int
        Components (or pieces) seen in fewer than ``min_rays`` images, dropped.
    n_merged : int
        Keypoints merged into another one at the same position of the same image.
    """

    tracks: Tracks
    obs_keypoint: NDArray[np.int64]
    track_score: NDArray[np.float64]
    n_components: int
    n_conflicting: int
    n_split: int
    n_obs_dropped: int
    n_short: int
    n_merged: int = 0


def connected_labels(n_nodes: int, u: ArrayLike, v: ArrayLike) -> NDArray[np.int64]:
    """Union-find: the component label of each node, given edges (u, v).

    The label of a component is its smallest node index, so the labels do not depend on the order
    of the edges. Vectorised: roots are hooked onto the smaller root of each edge and paths are
    compressed by pointer jumping, until no edge joins two roots.

    Parameters
    ----------
    n_nodes : int
    u, v : (E,) int
        Edge end points, 0 <= u, v < n_nodes.

    Returns
    -------
    (n_nodes,) int64
    """
    a = np.asarray(u, dtype=np.int64).reshape(-1)
    b = np.asarray(v, dtype=np.int64).reshape(-1)
    if a.shape != b.shape:
        raise ShapeError(f"edge arrays must have one shape; got {a.shape} and {b.shape}")
    if a.size and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n_nodes):
        raise InvalidInputError(f"edge end points must lie in 0..{n_nodes - 1}")
    parent = np.arange(n_nodes, dtype=np.int64)
    while True:
        while True:
            pp = parent[parent]
            if np.array_equal(pp, parent):
                break
            parent = pp
        ra, rb = parent[a], parent[b]
        d = ra != rb
        if not d.any():
            return parent
        np.minimum.at(parent, np.maximum(ra[d], rb[d]), np.minimum(ra[d], rb[d]))


def _merge_same_position(keypoints: Sequence[NDArray[np.float64]]) -> tuple[NDArray[np.int64], int]:
    """Global node of every global keypoint: keypoints of one image at one position share a node."""
    node = []
    offset = 0
    n_merged = 0
    for xy in keypoints:
        n = len(xy)
        if n:
            q = np.round(xy / SAME_POSITION_PX).astype(np.int64)
            _, first, inv = np.unique(q, axis=0, return_index=True, return_inverse=True)
            canon = first[inv.reshape(-1)] + offset
            n_merged += n - len(first)
        else:
            canon = np.zeros(0, np.int64)
        node.append(canon)
        offset += n
    return (np.concatenate(node) if node else np.zeros(0, np.int64)), n_merged


def build_tracks(keypoints: Sequence[ArrayLike], matches: Sequence[PairMatches], *,
                 images: Sequence[str] | None = None, conflicts: str = "drop", min_rays: int = 2,
                 id_prefix: str = "t") -> TrackBuild:
    """Tracks from pairwise keypoint matches by union-find, with conflict handling.

    Parameters
    ----------
    keypoints : sequence of (N_i, 2) array_like
        Keypoint positions of each image, pixels (x = column, y = row).
    matches : sequence of PairMatches
        Verified matches; pairs may come in any order and direction.
    images : sequence of str, optional
        Image names (default ``"0"``, ``"1"``, ...).
    conflicts : {"drop", "split"}
        What to do with a component holding two keypoints of one image (module docstring).
    min_rays : int
        Tracks seen in fewer images are dropped (>= 2).
    id_prefix : str
        Track ids are ``f"{id_prefix}{k}"``, k = 1, 2, ... in track order.

    Returns
    -------
    TrackBuild
        Tracks sorted by rays (most first), then score (best first), then smallest node, so the
        result does not depend on the order of the matches.
    """
    if conflicts not in CONFLICT_POLICIES:
        raise InvalidInputError(f"unknown conflict policy {conflicts!r}; choose from {CONFLICT_POLICIES}")
    if int(min_rays) < 2:
        raise InvalidInputError(f"min_rays must be >= 2; got {min_rays!r}")
    kps = [np.asarray(k, dtype=np.float64).reshape(-1, 2) for k in keypoints]
    n_img = len(kps)
    names = tuple(str(i) for i in range(n_img)) if images is None else tuple(images)
    if len(names) != n_img:
        raise InvalidInputError(f"{len(names)} image names for {n_img} keypoint sets")
    counts = np.array([len(k) for k in kps], dtype=np.int64)
    offset = np.r_[0, np.cumsum(counts)].astype(np.int64)
    n_nodes = int(offset[-1])
    img_of = np.repeat(np.arange(n_img, dtype=np.int64), counts)
    us, vs, ss = [], [], []
    for m in matches:
        for side, idx in ((m.i, m.kp_i), (m.j, m.kp_j)):
            if not 0 <= side < n_img:
                raise InvalidInputError(f"pair ({m.i}, {m.j}) names image {side}, outside 0..{n_img - 1}")
            if idx.size and (idx.min() < 0 or idx.max() >= counts[side]):
                raise InvalidInputError(f"pair ({m.i}, {m.j}): keypoint index out of range 0..{counts[side] - 1} "
                                        f"for image {names[side]!r}")
        us.append(m.kp_i + offset[m.i])
        vs.append(m.kp_j + offset[m.j])
        ss.append(m.score)
    canon, n_merged = _merge_same_position(kps)
    u = canon[np.concatenate(us)] if us else np.zeros(0, np.int64)
    v = canon[np.concatenate(vs)] if vs else np.zeros(0, np.int64)
    s = np.concatenate(ss) if ss else np.zeros(0)
    keep_e = u != v
    u, v, s = u[keep_e], v[keep_e], s[keep_e]
    active = np.zeros(n_nodes, dtype=bool)
    active[u] = True
    active[v] = True
    label = connected_labels(n_nodes, u, v)
    n_components = _count_multi_image(label, active, img_of)

    # conflicts: a component with more nodes than images
    conflict_comp = _conflicting(label, active, img_of)
    n_conflicting = len(conflict_comp)
    n_obs_dropped = 0
    n_split = 0
    if n_conflicting:
        bad_node = active & np.isin(label, conflict_comp)
        if conflicts == "drop":
            n_obs_dropped = int(bad_node.sum())
            active &= ~bad_node
        else:
            removed = _losers(label, bad_node, img_of, u, v, s, n_nodes)
            n_obs_dropped = int(removed.sum())
            active &= ~removed
            keep = active[u] & active[v]
            u, v, s = u[keep], v[keep], s[keep]
            active = np.zeros(n_nodes, dtype=bool)
            active[u] = True
            active[v] = True
            label = connected_labels(n_nodes, u, v)
            pieces = np.unique(label[active & bad_node])
            n_split = int(sum(len(np.unique(img_of[active & (label == p)])) >= min_rays for p in pieces))
    # tracks: components of active nodes
    nodes = np.flatnonzero(active)
    lab = label[nodes]
    uniq, comp = np.unique(lab, return_inverse=True)
    comp = comp.reshape(-1)
    rays = np.bincount(comp, minlength=len(uniq))
    ok_comp = rays >= int(min_rays)
    n_short = int((~ok_comp).sum())
    # mean edge score per component
    e_ok = active[u] & active[v]
    e_comp = np.searchsorted(uniq, label[u[e_ok]])
    ssum = np.bincount(e_comp, weights=s[e_ok], minlength=len(uniq))
    scount = np.bincount(e_comp, minlength=len(uniq))
    score = ssum / np.maximum(scount, 1)
    # order tracks: more rays, better score, smallest node (= label)
    order = np.lexsort((uniq, score, -rays))
    order = order[ok_comp[order]]
    rank = np.full(len(uniq), -1, dtype=np.int64)
    rank[order] = np.arange(len(order))
    sel = ok_comp[comp]
    obs_point = rank[comp[sel]]
    obs_node = nodes[sel]
    obs_image = img_of[obs_node]
    obs_kp = obs_node - offset[obs_image]
    srt = np.lexsort((obs_image, obs_point))
    obs_point, obs_image, obs_kp = obs_point[srt], obs_image[srt], obs_kp[srt]
    pix = np.concatenate(kps)[obs_node[srt]] if len(srt) else np.zeros((0, 2))
    ids = tuple(f"{id_prefix}{k + 1}" for k in range(len(order)))
    tracks = Tracks(names, ids, obs_point, obs_image, pix, np.ones(len(obs_point)))
    return TrackBuild(tracks, obs_kp, score[order], n_components, n_conflicting, n_split, n_obs_dropped,
                      n_short, n_merged)


def _count_multi_image(label, active, img_of) -> int:
    nodes = np.flatnonzero(active)
    if not len(nodes):
        return 0
    pairs = np.unique(np.c_[label[nodes], img_of[nodes]], axis=0)
    _, n_img = np.unique(pairs[:, 0], return_counts=True)
    return int((n_img >= 2).sum())


def _conflicting(label, active, img_of) -> NDArray[np.int64]:
    """Labels of the components holding two nodes of one image."""
    nodes = np.flatnonzero(active)
    if not len(nodes):
        return np.zeros(0, np.int64)
    key = np.c_[label[nodes], img_of[nodes]]
    uk, cnt = np.unique(key, axis=0, return_counts=True)
    return np.unique(uk[cnt > 1, 0])


def _losers(label, bad_node, img_of, u, v, s, n_nodes) -> NDArray[np.bool_]:
    """Nodes to remove so that each (conflicting component, image) keeps its best-supported keypoint."""
    deg = np.bincount(np.r_[u, v], minlength=n_nodes).astype(np.float64)
    ssum = np.bincount(np.r_[u, v], weights=np.r_[s, s], minlength=n_nodes)
    mean_s = ssum / np.maximum(deg, 1)
    nodes = np.flatnonzero(bad_node)
    order = np.lexsort((nodes, mean_s[nodes], -deg[nodes], img_of[nodes], label[nodes]))
    ordered = nodes[order]
    key = np.c_[label[ordered], img_of[ordered]]
    first = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
    removed = np.zeros(n_nodes, dtype=bool)
    removed[ordered[~first]] = True
    return removed


# --------------------------------------------------------------------------- even spread
@dataclass(frozen=True, eq=False)
class SpreadResult:
    """Which tracks :func:`spread_tracks` keeps.

    Attributes
    ----------
    keep : (P,) bool
        Tracks kept.
    coverage : (n_images,) float64
        Fraction of each image's grid cells holding at least one kept observation.
    points_per_image : (n_images,) int64
        Kept observations per image.
    """

    keep: NDArray[np.bool_]
    coverage: NDArray[np.float64]
    points_per_image: NDArray[np.int64]


def _cells(pixel: NDArray[np.float64], image: NDArray[np.int64], sizes: NDArray[np.int64],
           grid: tuple[int, int]) -> NDArray[np.int64]:
    """Cell index (0 .. gx*gy-1) of each observation in its image's gx x gy grid."""
    gx, gy = grid
    w = sizes[image, 0].astype(np.float64)
    h = sizes[image, 1].astype(np.float64)
    cx = np.clip(np.floor((pixel[:, 0] + 0.5) / w * gx), 0, gx - 1).astype(np.int64)
    cy = np.clip(np.floor((pixel[:, 1] + 0.5) / h * gy), 0, gy - 1).astype(np.int64)
    return cy * gx + cx


def spread_tracks(tracks: Tracks, image_sizes: ArrayLike, *, grid: tuple[int, int] = (8, 8), per_cell: int = 6,
                  track_score: ArrayLike | None = None) -> SpreadResult:
    """Keep an even spread of tracks: at most ``per_cell`` per grid cell of every image.

    Tracks are ranked by rays (most first), then ``track_score`` (lowest first), then index. In
    every image, each cell of a ``grid`` (columns, rows) selects its best-ranked ``per_cell``
    tracks; a track is kept when any image selects it (so a crowded cell can hold more than
    ``per_cell`` observations of tracks that other images needed).

    Parameters
    ----------
    tracks : Tracks
    image_sizes : (n_images, 2) int
        (width, height) of every image, px.
    grid : (int, int)
        Cells across and down.
    per_cell : int
    track_score : (P,) float, optional

    Returns
    -------
    SpreadResult
    """
    sizes = np.asarray(image_sizes, dtype=np.int64).reshape(-1, 2)
    if len(sizes) != len(tracks.images):
        raise ShapeError(f"image_sizes must have shape ({len(tracks.images)}, 2); got {sizes.shape}")
    gx, gy = (int(g) for g in grid)
    if gx < 1 or gy < 1 or int(per_cell) < 1:
        raise InvalidInputError(f"grid cells and per_cell must be >= 1; got grid={grid!r}, per_cell={per_cell!r}")
    P = tracks.n_points
    score = np.zeros(P) if track_score is None else np.asarray(track_score, dtype=np.float64).reshape(-1)
    if len(score) != P:
        raise ShapeError(f"track_score must have shape ({P},); got {score.shape}")
    rays = tracks.rays_per_point()
    trank = np.empty(P, dtype=np.int64)
    trank[np.lexsort((np.arange(P), score, -rays))] = np.arange(P)
    cell = _cells(tracks.obs_pixel, tracks.obs_image, sizes, (gx, gy))
    key = tracks.obs_image * (gx * gy) + cell
    m = tracks.n_obs
    order = np.lexsort((trank[tracks.obs_point], key))
    ks = key[order]
    start = np.r_[0, np.flatnonzero(np.diff(ks)) + 1] if m else np.zeros(0, np.int64)
    rank_in_cell = np.empty(m, dtype=np.int64)
    rank_in_cell[order] = np.arange(m) - np.repeat(start, np.diff(np.r_[start, m]).astype(np.int64))
    keep = np.zeros(P, dtype=bool)
    keep[tracks.obs_point[rank_in_cell < int(per_cell)]] = True
    kept_obs = keep[tracks.obs_point]
    cov = grid_coverage(tracks.obs_pixel[kept_obs], tracks.obs_image[kept_obs], sizes, grid=(gx, gy))
    ppi = np.bincount(tracks.obs_image[kept_obs], minlength=len(sizes)).astype(np.int64)
    return SpreadResult(keep, cov, ppi)


def grid_coverage(pixel: ArrayLike, image: ArrayLike, image_sizes: ArrayLike, *, grid: tuple[int, int] = (8, 8)
                  ) -> NDArray[np.float64]:
    """Fraction of each image's ``grid`` cells (columns, rows) holding at least one observation.

    Parameters
    ----------
    pixel : (M, 2) float
        Observations, px.
    image : (M,) int
        Image index of each observation.
    image_sizes : (n_images, 2) int
        (width, height), px.

    Returns
    -------
    (n_images,) float64
    """
    sizes = np.asarray(image_sizes, dtype=np.int64).reshape(-1, 2)
    px = np.asarray(pixel, dtype=np.float64).reshape(-1, 2)
    im = np.asarray(image, dtype=np.int64).reshape(-1)
    gx, gy = (int(g) for g in grid)
    n = len(sizes)
    if not len(px):
        return np.zeros(n)
    cell = _cells(px, im, sizes, (gx, gy))
    used = np.unique(im * (gx * gy) + cell)
    return np.bincount(used // (gx * gy), minlength=n).astype(np.float64) / (gx * gy)


def rays_histogram(tracks: Tracks) -> dict[int, int]:
    """{number of rays: number of tracks}, ascending."""
    r = tracks.rays_per_point()
    vals, cnt = np.unique(r, return_counts=True)
    return {int(a): int(b) for a, b in zip(vals, cnt, strict=True)}
