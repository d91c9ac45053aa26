"""Dense matching tiles on Dask (issue 17): the disparity a 2-worker cluster computes is the thread path's.

A module-scoped 2-worker LocalCluster (processes, one thread each) is reached by its address, as a
user's cluster would be (``tcp://HOST:PORT``). The issue asks the disparity identical to 0.1 px on at
least 99.9 % of the pixels; the tests assert that (and the same valid pixels within 0.1 %).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.errors import InvalidInputError
from stereo.actions.dense import DenseOptions
from stereo.actions.scene import make_scene, write_scene_inputs
from stereo.cli.main import cli
from stereo.dense.matching import NODATA, MatchOptions, match_rasters
from tests.support.dask_support import DASK_WARNING_FILTERS, local_cluster

distributed = pytest.importorskip("distributed")

pytestmark = [*DASK_WARNING_FILTERS,
              pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")]


cluster = pytest.fixture(scope="module")(local_cluster)


def _texture(h, w, seed):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 1.2)
    return np.clip(128 + 60 * t / t.std(), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A 420 x 300 normal-case pair: a smooth disparity 10..22 px, a raised box at 30 px, a nodata strip."""
    d = tmp_path_factory.mktemp("dense_dask")
    H, W = 300, 420
    src = _texture(H, W + 80, 5)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    disp = 10 + 12 * (xs / W) + 2 * np.sin(ys / 40.0)
    disp[110:190, 150:260] = 30.0
    left = src[:, 40:W + 40]
    # right(x - d) = left(x), by inverse mapping at the right pixel (disparity taken at the same column)
    right = cv2.remap(src, xs + 40 + disp, ys, cv2.INTER_CUBIC)
    right[:, :6] = 0
    for name, img in (("left.tif", left), ("right.tif", right)):
        with rasterio.open(d / name, "w", driver="GTiff", width=W, height=H, count=1, dtype="uint8", nodata=0,
                           tiled=True, blockxsize=128, blockysize=128, transform=Affine.identity()) as ds:
            ds.write(img, 1)
    return d


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read()


def _assert_close(a_path, b_path):
    """Disparity identical to 0.1 px on >= 99.9 % of the pixels (NaN/nodata against a value counts as a miss)."""
    a, b = _read(a_path)[0], _read(b_path)[0]
    va, vb = a != NODATA, b != NODATA
    same = (va == vb) & (~va | (np.abs(a - b) <= 0.1))
    assert same.mean() >= 0.999, same.mean()
    assert va.mean() > 0.5
    return a, b


def test_match_rasters_on_dask_equals_threads(pair, cluster, tmp_path):
    opts = MatchOptions(tile=128, overlap=16, fill_max_px=50)  # 4 x 3 = 12 tiles
    out = {}
    for label, sched in (("threads", "threads"), ("dask", cluster.scheduler_address)):
        seen = []
        stats = match_rasters(pair / "left.tif", pair / "right.tif", tmp_path / f"d_{label}.tif",
                              tmp_path / f"c_{label}.tif", disparity_range=(5, 35), options=opts,
                              scheduler=sched, progress=lambda d, t, seen=seen: seen.append((d, t)))
        out[label] = (stats, seen)
    (st, seen_t), (sd, seen_d) = out["threads"], out["dask"]
    assert st.n_tiles == sd.n_tiles == 12 and seen_t[-1] == seen_d[-1] == (12, 12)
    assert abs(st.n_valid - sd.n_valid) <= 1e-3 * st.width * st.height
    assert abs(st.disparity_min - sd.disparity_min) < 0.1 and abs(st.disparity_max - sd.disparity_max) < 0.1
    a, _ = _assert_close(tmp_path / "d_threads.tif", tmp_path / "d_dask.tif")
    ca, cb = _read(tmp_path / "c_threads.tif"), _read(tmp_path / "c_dask.tif")
    assert (np.abs(ca - cb) <= 1e-3).mean() >= 0.999  # confidence and filled flags
    # the thread path is today's: the matched disparity is right where it should be (box at 30 px)
    box = a[130:170, 190:240]
    assert np.nanmedian(np.where(box == NODATA, np.nan, box)) == pytest.approx(30, abs=0.3)
    assert not list(tmp_path.glob(".dense-blocks.*"))  # block files are removed


def test_stereo_run_and_dense_scheduler_cli(cluster, tmp_path):
    """``stereo run --dense --scheduler tcp://...`` and ``stereo dense --scheduler`` write the local disparity."""
    scene = make_scene(0, size_px=320)
    inp = write_scene_inputs(scene, tmp_path / "input")
    run = tmp_path / "run"
    r = CliRunner().invoke(cli, ["run", str(inp["left"]), str(inp["right"]), "--camera", str(inp["camera"]),
                                 "-o", str(run), "--dense", "--scheduler", cluster.scheduler_address])
    assert r.exit_code == 0, r.output
    run_line = next(s for s in r.output.splitlines() if s.startswith("dense: disparity:"))
    assert not list((run / "dense").glob(".dense-blocks.*"))
    outputs = {}
    # the same dense chain on the run's orientation and matches, locally (the run's dense step is this call);
    # then in 128 px tiles (6 tiles: 6 Dask tasks), locally and on the cluster
    for label, extra in (("threads", []), ("t128", ["--tile", "128"]),
                         ("d128", ["--tile", "128", "--scheduler", cluster.scheduler_address])):
        r = CliRunner().invoke(cli, ["dense", str(run / "relative.json"), str(inp["left"]), str(inp["right"]),
                                     "--matches", str(run / "matches.csv"), "-o", str(tmp_path / label),
                                     "--cloud", "none", *extra])
        assert r.exit_code == 0, r.output
        outputs[label] = next(s for s in r.output.splitlines() if s.startswith("disparity:"))
    assert run_line == "dense: " + outputs["threads"]
    assert outputs["t128"] == outputs["d128"] and outputs["d128"].endswith(" 6 tiles")
    _assert_close(tmp_path / "threads" / "disparity.tif", run / "dense" / "disparity.tif")
    _assert_close(tmp_path / "t128" / "disparity.tif", tmp_path / "d128" / "disparity.tif")


def test_bad_scheduler_values(tmp_path, monkeypatch):
    with pytest.raises(InvalidInputError, match="unknown scheduler 'gpus:4'"):
        DenseOptions(scheduler="gpus:4")
    with pytest.raises(InvalidInputError, match="worker count"):
        dataclasses.replace(DenseOptions(), scheduler="processes:0")
    f = tmp_path / "x.json"
    f.write_text("{}")
    r = CliRunner().invoke(cli, ["dense", str(f), str(f), str(f), "-o", str(tmp_path / "o"), "--scheduler", "gpus:4"])
    assert r.exit_code == 2
    err = [s for s in r.output.splitlines() if s.startswith("Error")]
    assert err == ["Error: Invalid value for '--scheduler': unknown scheduler 'gpus:4'; expected 'threads', "
                   "'processes', 'processes:N' or 'tcp://HOST:PORT'"]
    r = CliRunner().invoke(cli, ["run", str(f), str(f), "--camera", str(f), "-o", str(tmp_path / "o"),
                                 "--scheduler", "processes:2"])
    assert r.exit_code == 2 and "goes with --dense" in r.output
    # $RECTIFY_SCHEDULER is read by the library, and a bad value fails before any output is made
    monkeypatch.setenv("RECTIFY_SCHEDULER", "processes:0")
    scene = make_scene(0, size_px=320)
    inp = write_scene_inputs(scene, tmp_path / "input")
    r = CliRunner().invoke(cli, ["run", str(inp["left"]), str(inp["right"]), "--camera", str(inp["camera"]),
                                 "-o", str(tmp_path / "o"), "--dense"])
    assert r.exit_code == 1
    assert r.output.strip().splitlines()[-1] == ("Error: InvalidInputError: bad scheduler in $RECTIFY_SCHEDULER "
                                                 "'processes:0': the worker count must be an integer in 1..1024")
    assert not (tmp_path / "o" / "relative.json").exists()
