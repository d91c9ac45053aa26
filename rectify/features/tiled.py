"""Coarse-to-fine matching of large rasters by tiles, with bounded memory.

Both images are read as area-averaged overviews, matched and verified with a
homography; then the left image is processed tile by tile and, for each
tile, only the right window where the coarse homography predicts the partner
is read and searched (see :mod:`rectify.features` for the memory bound).

Which left tiles: all of them; or, for a scene much larger than ``max_matches`` needs (issue 17), a
regular sub-grid of disjoint half-size tiles spread over the whole extent, enough for the requested
matches with a margin (:func:`_budget_tiles`: at 8000 x 8000 px and 20 000 matches, 64 tiles of
512 px, 30 % of the left image with their pads); or, above ``max_tiles`` tiles, an even sub-grid
of half-size tiles (:func:`_pick_tiles`). The two sub-grids detect each tile's right window directly.
"""

from __future__ import annotations

import copy
import logging
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from rectify.features.detect import Features, detect, grid_select
from rectify.features.lsm import refine_matches
from rectify.features.match import (
    MatcherConfig,
    MatchResult,
    _check_blank,
    _grey_float,
    _no_overlap,
    _result,
    _reverify_and_cap,
    _shift_limits,
    _verify_checked,
    match_descriptors,
)
from rectify.features.verify import _apply_h, _h_jacobian
from rectify.raster import io as rio
from rectify.raster.distributed import Scheduler, resolve_scheduler, run_windows

logger = logging.getLogger(__name__)


def _overview(path, info, cfg: MatcherConfig):
    data, valid, _ = rio.read_overview_average(path, cfg.overview_px)
    scale = (info.width / data.shape[1], info.height / data.shape[0])
    g = data.astype(np.float32).mean(axis=2) if data.ndim == 3 else data.astype(np.float32)
    ok = valid & np.isfinite(g)
    if ok.any():
        sample = g[ok]
        lo, hi = np.percentile(sample, cfg.percentiles)
    else:
        lo, hi = 0.0, 1.0
    return g, valid, scale, (float(lo), float(hi))


def _scale_mat(s: tuple[float, float]) -> NDArray[np.float64]:
    """Full-resolution pixel -> overview pixel, u = (x + 0.5) / sx - 0.5 (rows alike)."""
    sx, sy = s
    return np.array([[1 / sx, 0, 0.5 / sx - 0.5], [0, 1 / sy, 0.5 / sy - 0.5], [0, 0, 1]])


def _coarse(left_path, right_path, il, ir, cfg: MatcherConfig):
    gl, vl, sl, lim_l = _overview(left_path, il, cfg)
    gr, vr, sr, lim_r = _overview(right_path, ir, cfg)
    kw: dict[str, Any] = dict(detector="sift", max_keypoints=cfg.max_keypoints, cell_cap=cfg.cell_cap,
                              percentiles=cfg.percentiles)
    fl = detect(gl, valid=vl, **kw)
    _check_blank(fl, "left", left_path)
    fr = detect(gr, valid=vr, **kw)
    _check_blank(fr, "right", right_path)
    pairs = match_descriptors(fl, fr, ratio=cfg.ratio, mutual=True)
    pl, pr = fl.xy[pairs.left], fr.xy[pairs.right]
    ver = _verify_checked(pl, pr, replace(cfg, threshold_px=max(cfg.threshold_px, 2.0)), "homography")
    Hc = cast(NDArray[np.float64], ver.matrix)   # a verified homography always has its matrix
    H = np.linalg.inv(_scale_mat(sr)) @ Hc @ _scale_mat(sl)
    H /= H[2, 2]
    err_full = ver.rmse_px * max(sr)
    logger.info("coarse match: %d of %d verified, RMSE %.2f overview px (scales %.2f, %.2f)",
                int(ver.inliers.sum()), len(pl), ver.rmse_px, sl[0], sr[0])
    return H, err_full, lim_l, lim_r, vl, sl


def _match_tiled(left_path, right_path, il, ir, cfg: MatcherConfig, progress, *,
                 scheduler: Scheduler | str | None = None, workdir: str | Path | None = None) -> MatchResult:
    sched = resolve_scheduler(scheduler)  # a bad value fails before any work
    t0 = time.perf_counter()
    H, err_full, lim_l, lim_r, ov_valid_l, sl = _coarse(left_path, right_path, il, ir, cfg)
    t1 = time.perf_counter()
    margin = cfg.search_margin_px + 4.0 * err_full
    n_all = math.ceil(il.width / cfg.tile_px) * math.ceil(il.height / cfg.tile_px)
    sparse = n_all > cfg.max_tiles
    budget = None if sparse else _budget_tiles(il, cfg)
    if sparse:
        # search a sparse, even sub-grid of smaller tiles (3x as many, half the side: less area,
        # denser coverage); right windows are detected directly (little reuse between sparse tiles)
        cfg = replace(cfg, tile_px=max(128, cfg.tile_px // 2), max_tiles=3 * cfg.max_tiles)
        tiles = _pick_tiles(il, cfg)
    elif budget is not None:
        # the scene is much larger than the requested matches need: search only a regular sub-grid of
        # disjoint half-size tiles spread over the whole extent (right windows detected directly)
        tiles, cfg = budget
        sparse = True
        logger.info("match budget: %d tiles of %d px searched (%.0f %% of the left image)", len(tiles),
                    cfg.tile_px, 100.0 * sum(w * h for _c, _r, w, h in tiles) / (il.width * il.height))
    else:
        tiles = _pick_tiles(il, cfg)
    n_tiles = len(tiles)
    quota = max(50, int(math.ceil(2.0 * cfg.max_matches / max(n_tiles, 1))))
    per_tile_kp = max(1500, min(cfg.max_keypoints, 4 * quota, int(4 * cfg.max_candidates / max(n_tiles, 1))))
    # tiles with no valid overview pixel are skipped here (they would be skipped by the tile function)
    windows = [t for t in tiles if _tile_has_data(ov_valid_l, sl, *t)]
    n_skipped = n_tiles - len(windows)
    engine = _TilePairs(str(Path(left_path).resolve()), str(Path(right_path).resolve()), il, ir, cfg, H, margin,
                        sparse, quota, per_tile_kp, lim_l, lim_r)
    store = _Store(il, cfg, {(c, r): i for i, (c, r, _w, _h) in enumerate(windows)})

    def prog(done: int, total: int) -> None:
        if progress is not None:
            progress(n_skipped + done, n_tiles)

    if progress is not None:
        progress(0, n_tiles)
    try:
        # the local path computes the tiles one after the other (one right-tile cache), as before; on Dask
        # each task computes a few consecutive tiles with its own cache, and the driver takes the tiles'
        # matches in tile order (the candidate thinning depends on it), so the result is the same
        run_windows(engine, store.write, windows, threads=1, progress=prog, scheduler=sched,
                    workdir=Path(workdir) if workdir is not None else Path(tempfile.gettempdir()), name="match")
    finally:
        engine.close()
    if progress is not None:
        progress(n_tiles, n_tiles)
    n_det_l, n_matched, n_ref, n_fail = store.n_det_l, store.n_matched, store.n_ref, store.n_fail
    n_det_r = engine.n_detected_right()
    n_stored = store.n_stored
    store_l, store_r, store_raw, store_s = store.l, store.r, store.raw, store.s
    t2 = time.perf_counter()
    if n_stored > cfg.max_candidates:
        store_l, store_r, store_raw, store_s = _thin(store_l, store_r, store_raw, store_s, il, cfg)
    pl = np.concatenate(store_l) if store_l else np.zeros((0, 2))
    pr = np.concatenate(store_r) if store_r else np.zeros((0, 2))
    raw = np.concatenate(store_raw) if store_raw else np.zeros((0, 2))
    sc = np.concatenate(store_s) if store_s else np.zeros(0)
    if cfg.verify == "none":
        if len(pl) < cfg.min_inliers:
            raise _no_overlap(len(pl), len(pl), cfg)
        inl = np.ones(len(pl), bool)
    else:
        ver0 = _verify_checked(pl, pr, cfg, cfg.verify)
        inl = ver0.inliers
    cand = _cap_candidates(pl, pr, inl, 200000)
    n_verified = int(inl.sum())
    # tiled: no unrefined match is kept (failures are dropped in their tile), so the screened ones are dropped too
    out_l, out_r, out_raw, out_s, ver, n_dup, n_scr = _reverify_and_cap(pl[inl], pr[inl], raw[inl], sc[inl], cfg,
                                                                 (il.height, il.width), keep_unrefined=False)
    t3 = time.perf_counter()
    timings = {"coarse": t1 - t0, "tiles": t2 - t1, "verify": t3 - t2, "total": t3 - t0}
    return _result(out_l, out_r, out_s, ver, cfg, (n_det_l, n_det_r), n_matched, n_verified, n_ref, n_fail,
                   out_raw, *cand, True, ((il.height, il.width), (ir.height, ir.width)), timings, n_dup,
                   n_screened=n_scr)


class _Store:
    """The driver's side: the tiles' matches taken in tile order (results arriving out of order wait),
    with the candidate thinning of the sequential loop."""

    def __init__(self, il, cfg: MatcherConfig, index: dict[tuple[int, int], int]):
        self.il, self.cfg, self.index = il, cfg, index
        self.pending: dict[int, Any] = {}
        self.next = 0
        self.l: list[NDArray] = []
        self.r: list[NDArray] = []
        self.raw: list[NDArray] = []
        self.s: list[NDArray] = []
        self.n_stored = 0
        self.n_det_l = self.n_matched = self.n_ref = self.n_fail = 0

    def write(self, res: Any, c0: int, r0: int) -> bool:
        self.pending[self.index[(c0, r0)]] = res
        while self.next in self.pending:
            self._take(self.pending.pop(self.next))
            self.next += 1
        return res[1] is None

    def _take(self, res: Any) -> None:
        counts, pl, pr, raw, score = res
        d_l, matched, ref, fail = (int(v) for v in counts)
        self.n_det_l += d_l
        self.n_matched += matched
        self.n_ref += ref
        self.n_fail += fail
        if pl is None:
            return
        self.l.append(pl)
        self.r.append(pr)
        self.raw.append(raw)
        self.s.append(score)
        self.n_stored += len(pl)
        if self.n_stored > 2 * self.cfg.max_candidates:
            self.l, self.r, self.raw, self.s = _thin(self.l, self.r, self.raw, self.s, self.il, self.cfg)
            self.n_stored = len(self.l[0])


class _TilePairs:
    """The search of one left tile in its predicted right window, for :func:`rectify.raster.distributed.run_windows`.

    ``tile(c0, r0, w, h)`` returns ``(counts, left, right, raw, score)``: the counts (left keypoints,
    matches kept in the core, refined, failed refinements) and the tile's matches in full-resolution
    pixels (None when the tile stores none). It holds the images' absolute paths, the coarse
    homography and the configuration, never pixels; the right image's features come from a cache of
    right tiles (each detected once per copy of the engine: once per Dask task).
    """

    def __init__(self, left_path: str, right_path: str, il, ir, cfg: MatcherConfig, H: NDArray[np.float64],
                 margin: float, sparse: bool, quota: int, per_tile_kp: int, lim_l, lim_r):
        self.left_path, self.right_path, self.il, self.ir, self.cfg = left_path, right_path, il, ir, cfg
        self.H, self.margin, self.sparse, self.quota, self.per_tile_kp = H, margin, sparse, quota, per_tile_kp
        self.lim_l, self.lim_r = lim_l, lim_r
        self.right: _RightTiles | None = None
        self.n_sparse_right = 0                      # right keypoints of the sparse windows
        self.merged_right: dict[int, int] = {}       # right tile -> keypoints, from the Dask tasks

    def portable(self) -> _TilePairs:
        out = copy.copy(self)
        out.right, out.n_sparse_right, out.merged_right = None, 0, {}
        return out

    def close(self) -> None:
        pass

    def stats(self) -> tuple[dict[int, int], int]:
        return (dict(self.right.counts) if self.right is not None else {}), self.n_sparse_right

    def merge_stats(self, stats: tuple[dict[int, int], int]) -> None:
        counts, n_sparse = stats
        self.merged_right.update(counts)   # a right tile detected by several tasks counts once
        self.n_sparse_right += int(n_sparse)

    def n_detected_right(self) -> int:
        local = self.right.n_detected if self.right is not None else 0
        return local + sum(self.merged_right.values()) + self.n_sparse_right

    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray[np.int64], Any, Any, Any, Any]:
        cfg, il, ir, H = self.cfg, self.il, self.ir, self.H
        left_path, right_path = self.left_path, self.right_path
        per_tile_kp, margin, gate = self.per_tile_kp, self.margin, self.margin
        n_det_l = n_matched = n_ref = n_fail = 0

        def out(pl=None, pr=None, raw=None, score=None):
            return np.array([n_det_l, n_matched, n_ref, n_fail], np.int64), pl, pr, raw, score

        if self.right is None:
            self.right = _RightTiles(right_path, ir, cfg, per_tile_kp, self.lim_r)
        # OpenCV's per-thread RNG seeded per tile (FLANN's index builds seed it themselves): a tile matches
        # the same on any thread, process or machine (and whatever ran before it there)
        cv2.setRNGSeed(_tile_seed(cfg.seed, c0, r0))
        kw: dict[str, Any] = dict(detector=cfg.detector, cell_cap=cfg.cell_cap, percentiles=cfg.percentiles)
        core = _core(c0, r0, w, h, il, cfg)
        corners = np.array([[c0, r0], [c0 + w - 1, r0], [c0, r0 + h - 1], [c0 + w - 1, r0 + h - 1]], float)
        pc = _apply_h(H, corners)
        if not np.isfinite(pc).all():
            return out()
        x0, y0 = np.floor(pc.min(axis=0) - margin).astype(int)
        x1, y1 = np.ceil(pc.max(axis=0) + margin).astype(int)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, ir.width - 1), min(y1, ir.height - 1)
        if x1 - x0 < 32 or y1 - y0 < 32:
            return out()
        if self.sparse:
            Rd, Rv = rio.read_window(right_path, x0, y0, x1 - x0 + 1, y1 - y0 + 1)
            if Rv.mean() < 0.02:
                return out()
            fr = detect(Rd, valid=Rv, max_keypoints=3 * per_tile_kp, limits=self.lim_r,
                        **kw).transformed(1.0, (x0, y0))
            self.n_sparse_right += len(fr)
        else:
            fr = self.right.features(x0, y0, x1, y1)
        if len(fr) < 4:
            return out()
        Ld, Lv = rio.read_window(left_path, c0, r0, w, h)
        if Lv.mean() < 0.02:
            return out()
        fl = detect(Ld, valid=Lv, max_keypoints=per_tile_kp, limits=self.lim_l, **kw)
        n_det_l += len(fl)
        if len(fl) < 4:
            return out()
        pairs = match_descriptors(fl, fr, ratio=cfg.ratio, mutual=cfg.mutual)
        pl = fl.xy[pairs.left] + [c0, r0]
        pr = fr.xy[pairs.right]
        ratio = pairs.ratio
        size_r = fr.size[pairs.right]
        inside = (pl[:, 0] >= core[0]) & (pl[:, 0] < core[2]) & (pl[:, 1] >= core[1]) & (pl[:, 1] < core[3])
        ok = inside & (np.linalg.norm(_apply_h(H, pl) - pr, axis=1) < gate)
        pl, pr, ratio, size_r = pl[ok], pr[ok], ratio[ok], size_r[ok]
        n_matched += len(pl)
        if not len(pl):
            return out()
        if len(pl) > self.quota:     # keep what the output can use, evenly over the tile core
            keep = grid_select(pl - [c0, r0], -ratio, (h, w), self.quota, cell_cap=cfg.cell_cap)
            pl, pr, ratio, size_r = pl[keep], pr[keep], ratio[keep], size_r[keep]
        raw = pr.copy()
        score = ratio
        if cfg.refine:
            A = _h_jacobian(H, pl)
            # the right windows' reach: the template's radius times the affine's largest row sum
            reach = float(np.abs(A).sum(axis=2).max()) if len(A) else 1.0
            m = int(math.ceil(cfg.lsm.radius_px * max(1.0, reach))) + 4
            bx0, by0 = np.floor(pr.min(axis=0)).astype(int) - m
            bx1, by1 = np.ceil(pr.max(axis=0)).astype(int) + m
            Rd, Rv = rio.read_window(right_path, bx0, by0, bx1 - bx0 + 1, by1 - by0 + 1)
            Lg = _grey_float(Ld, Lv)
            Rg = _grey_float(Rd, Rv)
            lr = refine_matches(Lg, Rg, pl - [c0, r0], pr - [bx0, by0], affine=A, config=cfg.lsm,
                                shift_limit_px=_shift_limits(size_r))
            okr = lr.converged
            n_ref += int(okr.sum())
            n_fail += int((~okr).sum())
            pl, raw = pl[okr], raw[okr]
            pr = lr.right[okr] + [bx0, by0]
            score = lr.std_px[okr]
        return out(np.asarray(pl, np.float64), np.asarray(pr, np.float64), np.asarray(raw, np.float64),
                   np.asarray(score))


class _RightTiles:
    """Right-image features by tiles, each tile detected once (keypoints of its core only) and kept in
    a least-recently-used cache bounded to ``cache_mb`` of descriptors."""

    def __init__(self, path, info, cfg: MatcherConfig, per_tile_kp: int, limits, cache_mb: float = 256.0):
        self.path, self.info, self.cfg = path, info, cfg
        self.kp = per_tile_kp
        self.limits = limits
        self.tiles = list(rio.iter_windows(info.width, info.height, cfg.tile_px, cfg.overlap_px))
        self.nx = math.ceil(info.width / cfg.tile_px)
        self.cache: dict[int, Features] = {}
        self.bytes = 0
        self.max_bytes = cache_mb * 2 ** 20
        self.n_detected = 0
        self.counts: dict[int, int] = {}   # right tile -> keypoints kept (for the Dask tasks' statistics)

    def _tile(self, idx: int) -> Features:
        f = self.cache.pop(idx, None)
        if f is None:
            c0, r0, w, h = self.tiles[idx]
            data, valid = rio.read_window(self.path, c0, r0, w, h)
            cfg = self.cfg
            if valid.mean() < 0.02:
                f = Features.concat([], 128 if cfg.detector == "sift" else 32,
                                    np.float32 if cfg.detector == "sift" else np.uint8)
            else:
                f = detect(data, valid=valid, detector=cfg.detector, max_keypoints=self.kp, cell_cap=cfg.cell_cap,
                           percentiles=cfg.percentiles, limits=self.limits).transformed(1.0, (c0, r0))
                x0, y0, x1, y1 = _core(c0, r0, w, h, self.info, cfg)
                inside = (f.xy[:, 0] >= x0) & (f.xy[:, 0] < x1) & (f.xy[:, 1] >= y0) & (f.xy[:, 1] < y1)
                f = f.subset(np.flatnonzero(inside))
            self.n_detected += len(f)
            self.counts[idx] = len(f)
            self.bytes += f.descriptors.nbytes
            while self.cache and self.bytes > self.max_bytes:
                old = next(iter(self.cache))
                self.bytes -= self.cache.pop(old).descriptors.nbytes
        self.cache[idx] = f           # most recently used last
        return f

    def features(self, x0: int, y0: int, x1: int, y1: int) -> Features:
        """Keypoints inside [x0, x1] x [y0, y1] (full-resolution right pixels)."""
        t = self.cfg.tile_px
        items = []
        for ty in range(max(y0, 0) // t, min(y1, self.info.height - 1) // t + 1):
            for tx in range(max(x0, 0) // t, min(x1, self.info.width - 1) // t + 1):
                f = self._tile(ty * self.nx + tx)
                m = (f.xy[:, 0] >= x0) & (f.xy[:, 0] <= x1) & (f.xy[:, 1] >= y0) & (f.xy[:, 1] <= y1)
                items.append(f.subset(np.flatnonzero(m)))
        return Features.concat(items, 128 if self.cfg.detector == "sift" else 32,
                               np.float32 if self.cfg.detector == "sift" else np.uint8)


def _tile_seed(seed: int, c0: int, r0: int) -> int:
    """The RNG seed of the tile at (c0, r0): the configuration's seed and the tile's origin."""
    return (int(seed) * 1_000_003 + int(r0) * 65_537 + int(c0)) % 2_147_483_647


def _pick_tiles(info, cfg: MatcherConfig) -> list[tuple[int, int, int, int]]:
    """Tile windows to search: all of them, or an even sub-grid of at most ``max_tiles``."""
    tiles = list(rio.iter_windows(info.width, info.height, cfg.tile_px, cfg.overlap_px))
    if len(tiles) <= cfg.max_tiles:
        return tiles
    nx = math.ceil(info.width / cfg.tile_px)
    ny = math.ceil(info.height / cfg.tile_px)
    k = math.ceil(math.sqrt(len(tiles) / cfg.max_tiles))
    while math.ceil(nx / k) * math.ceil(ny / k) > cfg.max_tiles:
        k += 1
    ox, oy = (nx - 1) % k // 2, (ny - 1) % k // 2
    return [t for i, t in enumerate(tiles) if (i // nx - oy) % k == 0 and (i % nx - ox) % k == 0]


BUDGET_TILE_MATCHES = 500
"""Candidate matches a budget tile (half of ``tile_px`` on a side) is counted on to supply."""
BUDGET_MARGIN = 1.5
"""The budget sub-grid has tiles for this many times ``max_matches`` candidates."""
BUDGET_MAX_SHARE = 0.4
"""The budget sub-grid is used only when its tiles cover at most this share of the left image."""
BUDGET_MIN_TILES = 16
"""The budget sub-grid has at least this many tiles (4 x 4 on a square image), for the spread."""


def _budget_tiles(info, cfg: MatcherConfig) -> tuple[list[tuple[int, int, int, int]], MatcherConfig] | None:
    """The budget sub-grid of a scene much larger than ``max_matches`` needs, or None.

    ``nx`` x ``ny`` disjoint tiles of ``tile_px // 2`` (at least 128) on a side, enough for
    ``BUDGET_MARGIN * max_matches`` candidates at ``BUDGET_TILE_MATCHES`` each (and at least
    ``BUDGET_MIN_TILES``), with ``nx / ny`` close to the image's aspect ratio; tile ``i`` of a row
    is centred at ``(i + 0.5) * width / nx`` (rows alike), so the tiles span the whole extent with
    equal gaps. Each window is the tile plus a pad of ``lsm.radius_px + 6`` pixels (the
    refinement's template support); the returned configuration has ``tile_px`` = the tile side and
    ``overlap_px`` = the pad, so that :func:`_core` gives each window's tile back. None when the
    grid would cover more than ``BUDGET_MAX_SHARE`` of the image or its padded windows would touch
    (the scene is not large enough to be worth skipping pixels). Depends only on the image size and
    the configuration.
    """
    side = max(128, cfg.tile_px // 2)
    pad = int(cfg.lsm.radius_px) + 6
    W, H = int(info.width), int(info.height)
    need = max(BUDGET_MIN_TILES, math.ceil(BUDGET_MARGIN * cfg.max_matches / BUDGET_TILE_MATCHES))
    nx = max(1, min(round(math.sqrt(need * W / H)), need))
    ny = max(1, math.ceil(need / nx))
    if nx * ny * side * side > BUDGET_MAX_SHARE * W * H:
        return None
    if W / nx < side + 2 * pad or H / ny < side + 2 * pad:
        return None

    def starts(n: int, extent: int) -> list[int]:
        return [min(max(int(round((i + 0.5) * extent / n - side / 2)), 0), extent - side) for i in range(n)]

    tiles = []
    for y in starts(ny, H):
        for x in starts(nx, W):
            c0, r0 = max(x - pad, 0), max(y - pad, 0)
            tiles.append((c0, r0, min(x + side + pad, W) - c0, min(y + side + pad, H) - r0))
    return tiles, replace(cfg, tile_px=side, overlap_px=pad)


def _core(c0, r0, w, h, info, cfg):
    """Core (no-overlap) rectangle [x0, y0, x1, y1) of a window from :func:`rectify.raster.io.iter_windows`."""
    cx = 0 if c0 == 0 else c0 + cfg.overlap_px
    cy = 0 if r0 == 0 else r0 + cfg.overlap_px
    return cx - 0.5, cy - 0.5, min(cx + cfg.tile_px, info.width) - 0.5, min(cy + cfg.tile_px, info.height) - 0.5


def _tile_has_data(ov_valid, s, c0, r0, w, h) -> bool:
    a0, b0 = int(c0 / s[0]), int(r0 / s[1])
    a1, b1 = int(math.ceil((c0 + w) / s[0])), int(math.ceil((r0 + h) / s[1]))
    sub = ov_valid[b0:max(b1, b0 + 1), a0:max(a1, a0 + 1)]
    return bool(sub.size and sub.any())


def _thin(sl, sr, sraw, ss, info, cfg: MatcherConfig):
    pl, pr, raw, sc = (np.concatenate(x) for x in (sl, sr, sraw, ss))
    keep = grid_select(pl, -sc, (info.height, info.width), cfg.max_candidates, cell_cap=max(cfg.cell_cap, 8))
    return [pl[keep]], [pr[keep]], [raw[keep]], [sc[keep]]


def _cap_candidates(pl, pr, inl, cap) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    if len(pl) <= cap:
        return pl, pr, inl
    idx = np.random.default_rng(0).choice(len(pl), cap, replace=False)
    return pl[idx], pr[idx], inl[idx]
