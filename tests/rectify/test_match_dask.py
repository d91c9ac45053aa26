"""Tie-point matching of large scenes by tiles on Dask (issue 17): the same matches as the thread path.

A module-scoped 2-worker LocalCluster (processes, one thread each) is reached by its address. Tiling
is forced on small images (``tiled_above_px``, ``tile_px``). Each tile seeds OpenCV's RNG (FLANN's
randomised kd-trees) from the configuration's seed and its origin, so the matches are the same to
the last bit whichever worker computes the tile.
"""

from __future__ import annotations

import affine
import cv2
import numpy as np
import pytest
from click.testing import CliRunner

import rectify.actions.common
import rectify.actions.match
from rectify.cli.main import cli
from rectify.features import MatcherConfig, match_images
from rectify.raster import io as rio
from tests.rectify.test_features import _texture_image
from tests.support.dask_support import DASK_WARNING_FILTERS, local_cluster

distributed = pytest.importorskip("distributed")

pytestmark = [*DASK_WARNING_FILTERS,
              pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")]

H = np.array([[0.97, 0.05, 25.0], [-0.04, 1.01, -12.0], [1e-5, -2e-5, 1.0]])
BASE = dict(tiled_above_px=400, tile_px=256, overlap_px=24, overview_px=320)


cluster = pytest.fixture(scope="module")(local_cluster)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """768 x 512 px: 3 x 2 tiles of 256 px; the right image through a homography, with its nodata."""
    d = tmp_path_factory.mktemp("match_dask")
    h, w = 512, 768
    img = _texture_image(h, w, seed=1)
    warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_CUBIC)
    valid_r = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST) > 0
    rio.write_raster(d / "l.tif", img, affine.Affine.identity(), None)
    rio.write_raster(d / "r.tif", warped, affine.Affine.identity(), None, nodata=0, valid=valid_r)
    return d / "l.tif", d / "r.tif"


def _counts(res):
    return {k: v for k, v in res.summary().items() if not k.startswith("time")}


@pytest.mark.parametrize("extra", [dict(max_matches=600), dict(max_tiles=3, max_matches=300),
                                   dict(max_candidates=150, max_matches=100)],
                         ids=["all-tiles", "sparse-tiles", "thinned"])
def test_tiled_matching_on_dask_equals_threads(pair, cluster, tmp_path, extra):
    cfg = MatcherConfig(**BASE, **extra)
    ticks_t, ticks_d = [], []
    local = match_images(*pair, config=cfg, scheduler="threads", progress=lambda d, t: ticks_t.append((d, t)))
    dask = match_images(*pair, config=cfg, scheduler=cluster.scheduler_address, workdir=tmp_path,
                        progress=lambda d, t: ticks_d.append((d, t)))
    assert local.tiled and dask.tiled and len(local.matches) >= 50
    # the same matches, in the same order, to the last bit (the issue asks 1e-9 px)
    for a, b in ((local.matches.left, dask.matches.left), (local.matches.right, dask.matches.right),
                 (local.candidates_left, dask.candidates_left), (local.candidates_right, dask.candidates_right),
                 (local.candidate_inlier, dask.candidate_inlier)):
        assert a.shape == b.shape and np.array_equal(a, b)
    assert np.array_equal(local.matches.score, dask.matches.score, equal_nan=True)
    assert local.rmse_raw_px == dask.rmse_raw_px          # the raw (unrefined) positions too
    assert _counts(local) == _counts(dask)   # detected (both sides), matched, refined, verified, kept
    assert ticks_t[-1] == ticks_d[-1] and ticks_d[-1][0] == ticks_d[-1][1]
    assert not list(tmp_path.glob(".match-blocks.*"))
    # and the known geometry is found (the matches are good, not just equal)
    e = np.linalg.norm(cv2.perspectiveTransform(local.matches.left[None], H)[0] - local.matches.right, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.3


def test_rectify_match_scheduler_cli(pair, cluster, tmp_path, monkeypatch):
    """``rectify match --scheduler tcp://...`` writes the CSV the local run writes (tiling forced)."""
    config = rectify.actions.match.MatchOptions.config
    monkeypatch.setattr(rectify.actions.match.MatchOptions, "config",
                        lambda self: MatcherConfig(**{**config(self).__dict__, **BASE}))
    outs = {}
    for label, extra in (("threads", []), ("dask", ["--scheduler", cluster.scheduler_address])):
        out = tmp_path / f"{label}.csv"
        r = CliRunner().invoke(cli, ["match", str(pair[0]), str(pair[1]), "-o", str(out), "--max-matches", "300",
                                     *extra])
        assert r.exit_code == 0, r.output
        assert "tiled" in r.output
        # (the cluster's scheduler runs in this process: its INFO log lines reach the command's output)
        outs[label] = (out.read_text(), [s for s in r.output.splitlines() if not s.startswith(("wrote", "INFO "))])
    assert outs["threads"] == outs["dask"]
    assert not list(tmp_path.glob(".match-blocks.*"))


def test_bad_scheduler_values(pair, tmp_path, monkeypatch):
    r = CliRunner().invoke(cli, ["match", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "m.csv"),
                                 "--scheduler", "processes:x"])
    assert r.exit_code == 2
    assert [s for s in r.output.splitlines() if s.startswith("Error")] == [
        "Error: Invalid value for '--scheduler': bad scheduler 'processes:x': the worker count must be an integer "
        "in 1..1024"]
    monkeypatch.setenv("RECTIFY_SCHEDULER", "gpus")
    r = CliRunner().invoke(cli, ["match", str(pair[0]), str(pair[1]), "-o", str(tmp_path / "m.csv")])
    assert r.exit_code == 1
    assert r.output.strip().splitlines()[-1] == (
        "Error: InvalidInputError: unknown scheduler in $RECTIFY_SCHEDULER 'gpus'; expected 'threads', "
        "'processes', 'processes:N' or 'tcp://HOST:PORT'")
    assert not (tmp_path / "m.csv").exists()
