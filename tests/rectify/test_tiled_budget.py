"""The budget sub-grid of the tiled matcher (issue 17): a scene much larger than ``max_matches`` needs is
searched only in a regular sub-grid of disjoint tiles spread over the whole extent.

Unit tests of the tile selection (coverage of the extent, number of tiles for a budget, determinism,
when it is not used), then a 1024 x 1024 pair matched in budget mode: the known homography, matches
spread over the whole image, and the same matches on a 2-worker Dask cluster as on the thread path.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import affine
import cv2
import numpy as np
import pytest

from rectify.features import MatcherConfig, match_images
from rectify.features.tiled import (
    BUDGET_MARGIN,
    BUDGET_MAX_SHARE,
    BUDGET_MIN_TILES,
    BUDGET_TILE_MATCHES,
    _budget_tiles,
    _core,
)
from rectify.raster import io as rio
from tests.rectify.test_features import _texture_image
from tests.support.dask_support import DASK_WARNING_FILTERS, local_cluster

pytestmark = [*DASK_WARNING_FILTERS,
              pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")]


def _info(w: int, h: int) -> SimpleNamespace:
    return SimpleNamespace(width=w, height=h)


def _budget(info: Any, cfg: MatcherConfig) -> tuple[list[tuple[int, int, int, int]], MatcherConfig]:
    out = _budget_tiles(info, cfg)
    assert out is not None
    return out


def _core_of(t: tuple[int, int, int, int], info: Any, cfg: MatcherConfig) -> tuple[float, float, float, float]:
    c0, r0, w, h = t
    return _core(c0, r0, w, h, info, cfg)


def _grid(tiles, info, cfg):
    cores = [_core_of(t, info, cfg) for t in tiles]
    xs = sorted({c[0] for c in cores})
    ys = sorted({c[1] for c in cores})
    return cores, xs, ys


@pytest.mark.parametrize("size", [(8000, 8000), (12000, 12000), (20000, 6000), (6000, 20000), (33000, 33000)])
def test_budget_grid_covers_the_extent(size):
    info = _info(*size)
    cfg0 = MatcherConfig()
    tiles, cfg = _budget(info, cfg0)
    assert cfg.tile_px == cfg0.tile_px // 2 and cfg.overlap_px == cfg0.lsm.radius_px + 6
    cores, xs, ys = _grid(tiles, info, cfg)
    assert len(tiles) == len(xs) * len(ys)                    # a full regular grid
    s = cfg.tile_px
    for c0, r0, w, h in tiles:                                 # windows inside the image, core inside window
        assert c0 >= 0 and r0 >= 0 and c0 + w <= info.width and r0 + h <= info.height
    for (x0, y0, x1, y1), (c0, r0, w, h) in zip(cores, tiles, strict=True):
        assert x1 - x0 == s and y1 - y0 == s
        assert c0 - 0.5 <= x0 and x1 <= c0 + w - 0.5 and r0 - 0.5 <= y0 and y1 <= r0 + h - 0.5
    # windows are disjoint (no keypoint counted twice, no shared work)
    wx = sorted({(t[0], t[0] + t[2]) for t in tiles})
    assert all(a[1] <= b[0] for a, b in zip(wx, wx[1:], strict=False))
    # spread over the whole extent with equal gaps: the tile centres are at (i + 0.5) * extent / n
    for starts, extent in ((xs, info.width), (ys, info.height)):
        n = len(starts)
        pitch = extent / n
        centres = np.array(starts) + 0.5 + s / 2
        assert np.allclose(centres, (np.arange(n) + 0.5) * pitch, atol=1.0)
        assert centres[0] - s / 2 <= pitch / 2 and centres[-1] + s / 2 >= extent - pitch / 2
    # the aspect ratio is followed (cells of the grid are near square)
    px, py = info.width / len(xs), info.height / len(ys)
    assert 0.5 < px / py < 2.0
    # it searches a minority of the pixels
    assert len(tiles) * s * s <= BUDGET_MAX_SHARE * info.width * info.height


@pytest.mark.parametrize("max_matches", [1000, 5000, 20000, 40000])
def test_budget_tile_count_follows_the_requested_matches(max_matches):
    info = _info(20000, 20000)
    tiles, cfg = _budget(info, MatcherConfig(max_matches=max_matches))
    need = max(BUDGET_MIN_TILES, math.ceil(BUDGET_MARGIN * max_matches / BUDGET_TILE_MATCHES))
    assert need <= len(tiles) <= need + math.isqrt(need) + 2    # enough, and a grid's rounding at most
    assert len(tiles) * BUDGET_TILE_MATCHES >= BUDGET_MARGIN * max_matches


def test_budget_grid_8000_default():
    tiles, cfg = _budget(_info(8000, 8000), MatcherConfig())
    assert len(tiles) == 64 and cfg.tile_px == 512                    # 8 x 8 tiles, pitch 1000 px
    assert tiles[0] == (228, 228, 544, 544) and tiles[1] == (1228, 228, 544, 544)


def test_budget_grid_is_deterministic():
    a = _budget(_info(12345, 9876), MatcherConfig())
    b = _budget(_info(12345, 9876), MatcherConfig(seed=7))   # the seed does not choose tiles
    c = _budget(_info(12345, 9876), MatcherConfig())
    assert a[0] == b[0] == c[0] and len(a[0]) >= BUDGET_MIN_TILES


@pytest.mark.parametrize("size,kw", [((4000, 4000), {}),            # the tiles would cover > 40 %
                                     ((8000, 2000), {}),
                                     ((768, 512), dict(tile_px=256, max_matches=100)),
                                     ((8000, 8000), dict(max_matches=60000))])
def test_no_budget_grid_when_the_scene_is_not_much_larger(size, kw):
    assert _budget_tiles(_info(*size), MatcherConfig(**kw)) is None


# --- matching in budget mode ------------------------------------------------------------------------

H = np.array([[0.97, 0.05, 25.0], [-0.04, 1.01, -12.0], [1e-5, -2e-5, 1.0]])
BASE: dict[str, Any] = dict(tiled_above_px=400, tile_px=256, overlap_px=24, overview_px=320, max_matches=300)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """1024 x 1024 px; with 256-px tiles and 300 matches: 16 budget tiles of 128 px (25 % of the image)."""
    d = tmp_path_factory.mktemp("budget")
    h = w = 1024
    img = _texture_image(h, w, seed=3)
    warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_CUBIC)
    valid_r = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST) > 0
    rio.write_raster(d / "l.tif", img, affine.Affine.identity(), None)
    rio.write_raster(d / "r.tif", warped, affine.Affine.identity(), None, nodata=0, valid=valid_r)
    return d / "l.tif", d / "r.tif"


def test_budget_matching_finds_the_geometry_over_the_whole_extent(pair):
    cfg = MatcherConfig(**BASE)
    tiles, bcfg = _budget(_info(1024, 1024), cfg)
    assert len(tiles) == 16
    r = match_images(*pair, config=cfg)
    assert r.tiled and len(r.matches) == 300
    e = np.linalg.norm(cv2.perspectiveTransform(r.matches.left[None], H)[0] - r.matches.right, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.3
    # every match lies in a budget tile, and every tile whose partner is inside the right image has some
    cores = [_core_of(t, _info(1024, 1024), bcfg) for t in tiles]
    left = r.matches.left
    inside = np.zeros(len(left), bool)
    per_tile = []
    for x0, y0, x1, y1 in cores:
        m = (left[:, 0] >= x0) & (left[:, 0] < x1) & (left[:, 1] >= y0) & (left[:, 1] < y1)
        inside |= m
        per_tile.append(int(m.sum()))
    assert inside.all()
    assert sum(c > 0 for c in per_tile) >= 14
    # half the left image was never detected: the detected count is far below the whole-image one
    assert r.n_detected[0] < 16 * r.n_detected[1]


def test_budget_matching_is_repeatable(pair):
    cfg = MatcherConfig(**BASE)
    a = match_images(*pair, config=cfg)
    b = match_images(*pair, config=cfg)
    assert np.array_equal(a.matches.left, b.matches.left) and np.array_equal(a.matches.right, b.matches.right)


cluster = pytest.fixture(scope="module")(local_cluster)


def test_budget_matching_on_dask_equals_threads(pair, cluster, tmp_path):
    cfg = MatcherConfig(**BASE)
    local = match_images(*pair, config=cfg, scheduler="threads")
    dask = match_images(*pair, config=cfg, scheduler=cluster.scheduler_address, workdir=tmp_path)
    for a, b in ((local.matches.left, dask.matches.left), (local.matches.right, dask.matches.right),
                 (local.candidates_left, dask.candidates_left), (local.candidates_right, dask.candidates_right),
                 (local.candidate_inlier, dask.candidate_inlier)):
        assert a.shape == b.shape and np.array_equal(a, b)
    sa, sb = local.matches.score, dask.matches.score
    assert sa is not None and sb is not None and np.array_equal(sa, sb, equal_nan=True)
    s_l = {k: v for k, v in local.summary().items() if not k.startswith("time")}
    s_d = {k: v for k, v in dask.summary().items() if not k.startswith("time")}
    assert s_l == s_d
