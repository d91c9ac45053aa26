"""rectify.raster.distributed: the tiled steps on a Dask cluster write what the local thread pool writes.

A module-scoped 2-worker LocalCluster (processes, one thread each) is reached by its address, as a
user's cluster would be (``tcp://HOST:PORT``); the ``processes:N`` path (a cluster started for the
run) is driven end to end by ``tests/cli/test_scheduler.py``.
"""

from __future__ import annotations

import os
import signal
import time
from typing import Any

import numpy as np
import pytest
import rasterio
from affine import Affine

from rectify.errors import InvalidInputError
from rectify.raster import daskpeer
from rectify.raster.daskpeer import split_address
from rectify.raster.dem import Dem
from rectify.raster.distributed import (
    ENV_VAR,
    STALL_TIMEOUT_ENV_VAR,
    TIMEOUT_ENV_VAR,
    WORKER_TIMEOUT_ENV_VAR,
    Scheduler,
    SchedulerError,
    check_scheduler,
    resolve_scheduler,
)
from rectify.raster.georef import Grid
from rectify.raster.io import TiledWriter, mask_policy, verify_geotiff, write_raster
from rectify.raster.mosaic import MosaicOptions, mosaic
from rectify.raster.ortho import OrthoOptions, orthorectify
from rectify.raster.warp import WarpOptions, warp_raster
from tests.rectify.test_ortho import _flat_ortho, frame_scene
from tests.support.dask_support import DASK_WARNING_FILTERS, FakeServer, closed_port, local_cluster
from tests.support.rectify_support import cog_problems

distributed = pytest.importorskip("distributed")

# distributed may warn while workers shut down (a killed worker, closing comms): only here, narrowly
pytestmark = [*DASK_WARNING_FILTERS]

CRS = "EPSG:32618"
H = np.array([[1.02, 0.05, 3.0], [-0.04, 0.98, -5.0], [1e-5, 2e-5, 1.0]])  # output world -> source pixel


class Homography:
    """World (x, y) -> source pixel through ``H`` (has a matrix: the analytic warpPerspective path)."""

    matrix = H

    def __call__(self, p):
        h = np.c_[np.asarray(p, dtype=np.float64), np.ones(len(p))] @ H.T
        return h[:, :2] / h[:, 2:]


class Curved:
    """A non-matrix mapping (the sparse grid + remap path): the homography plus a smooth bend."""

    def __call__(self, p):
        q = Homography()(p)
        return q + np.column_stack([3 * np.sin(q[:, 1] / 90.0), 2 * np.cos(q[:, 0] / 70.0)])


GRID = Grid(640, 520, Affine(1, 0, -20, 0, -1, 510), CRS)


cluster = pytest.fixture(scope="module")(local_cluster)


@pytest.fixture()
def writes(monkeypatch):
    """Count the windows the calling process writes as pixels (``TiledWriter.write``) and as compressed tiles
    (``write_encoded``): on Dask every window arrives compressed."""
    counts = {"pixels": 0, "encoded": 0}
    write, write_encoded = TiledWriter.write, TiledWriter.write_encoded

    def pixels(self, *a, **k):
        counts["pixels"] += 1
        return write(self, *a, **k)

    def encoded(self, *a, **k):
        counts["encoded"] += 1
        return write_encoded(self, *a, **k)

    monkeypatch.setattr(TiledWriter, "write", pixels)
    monkeypatch.setattr(TiledWriter, "write_encoded", encoded)
    return counts


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """600 x 500 x 3 sources: uint8 with a nodata hole, uint8 without nodata (the output gets an internal mask),
    float32 (NaN nodata)."""
    d = tmp_path_factory.mktemp("dask_src")
    rng = np.random.default_rng(17)
    rr, cc = np.mgrid[0:500, 0:600]
    smooth = np.stack([cc * 0.3 + rr * 0.1, 120 + 80 * np.sin(cc / 17.0) * np.cos(rr / 23.0), rr * 0.4], axis=-1)
    img = np.clip(smooth + rng.normal(0, 6, smooth.shape), 1, 255).astype(np.uint8)
    img[200:240, 300:380] = 0  # nodata hole: renormalised kernels next to it
    write_raster(d / "u8.tif", img, Affine(1, 0, 0, 0, -1, 500), CRS, nodata=0)
    write_raster(d / "u8m.tif", img, Affine(1, 0, 0, 0, -1, 500), CRS)
    f32 = (smooth * 10.0 + rng.normal(0, 3, smooth.shape)).astype(np.float32)
    f32[100:130, 50:90] = np.nan
    write_raster(d / "f32.tif", f32, Affine(1, 0, 0, 0, -1, 500), CRS, nodata=float("nan"))
    return d


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(), ds.read_masks(1), ds.profile, ds.dataset_mask()


def _assert_same(a_path, b_path, *, rtol=0.0):
    for p in (a_path, b_path):
        verify_geotiff(p)
    a, ma, pa, da = _read(a_path)
    b, mb, pb, db = _read(b_path)
    assert a.shape == b.shape and a.dtype == b.dtype
    assert (ma == mb).all() and (da == db).all()
    for k in ("crs", "transform", "nodata", "blockxsize", "blockysize", "compress", "count"):
        assert pa.get(k) == pb.get(k) or (k == "nodata" and np.isnan(pa[k]) and np.isnan(pb[k])), k
    if rtol == 0.0:
        np.testing.assert_array_equal(a, b)
    else:
        np.testing.assert_allclose(a, b, rtol=rtol, atol=0, equal_nan=True)


# ----------------------------------------------------------------- scheduler choice
def test_parse_scheduler_values():
    assert Scheduler.parse("threads") == Scheduler()
    assert Scheduler.parse(" Processes ") == Scheduler("processes")
    assert Scheduler.parse("processes:3") == Scheduler("processes", workers=3)
    s = Scheduler.parse("tcp://127.0.0.1:8786")
    assert s.kind == "cluster" and s.address == "tcp://127.0.0.1:8786" and str(s) == "tcp://127.0.0.1:8786"
    assert str(Scheduler.parse("processes:2")) == "processes:2"


@pytest.mark.parametrize(("spec", "message"), [
    ("gpu", "unknown scheduler 'gpu'; expected 'threads', 'processes', 'processes:N' or 'tcp://HOST:PORT'"),
    ("processes:0", "bad scheduler 'processes:0': the worker count must be an integer in 1..1024"),
    ("processes:two", "bad scheduler 'processes:two': the worker count must be an integer in 1..1024"),
    ("tcp://", "bad scheduler address 'tcp://'; expected tcp://HOST:PORT"),
    ("tcp://host:port", "bad scheduler address 'tcp://host:port'; expected tcp://HOST:PORT"),
])
def test_bad_scheduler_values_are_refused_in_one_line(spec, message):
    with pytest.raises(InvalidInputError) as err:
        Scheduler.parse(spec)
    assert str(err.value) == message and "\n" not in str(err.value)
    with pytest.raises(InvalidInputError):  # the options refuse it before any work
        WarpOptions(scheduler=spec)
    with pytest.raises(InvalidInputError):
        OrthoOptions(scheduler=spec)
    with pytest.raises(InvalidInputError):
        MosaicOptions(scheduler=spec)


def test_environment_variable(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert resolve_scheduler(None) == Scheduler()
    monkeypatch.setenv(ENV_VAR, "processes:2")
    assert resolve_scheduler(None) == Scheduler("processes", workers=2)
    assert resolve_scheduler("threads") == Scheduler()  # an explicit choice wins
    monkeypatch.setenv("RECTIFY_SCHEDULER_TIMEOUT", "3.5")
    assert resolve_scheduler("tcp://10.1.2.3:8786").timeout_s == 3.5
    monkeypatch.setenv("RECTIFY_SCHEDULER_TIMEOUT", "soon")
    with pytest.raises(InvalidInputError, match=r"\$RECTIFY_SCHEDULER_TIMEOUT must be a number of seconds > 0; "
                                                r"got 'soon'"):
        resolve_scheduler("tcp://10.1.2.3:8786")
    monkeypatch.delenv("RECTIFY_SCHEDULER_TIMEOUT")
    monkeypatch.setenv(ENV_VAR, "cluster-please")
    with pytest.raises(InvalidInputError, match=r"unknown scheduler in \$RECTIFY_SCHEDULER 'cluster-please'"):
        resolve_scheduler(None)


def test_scheduler_error_lives_in_rectify_errors():
    """``SchedulerError`` is in ``rectify.errors`` (a project error), re-exported by ``rectify.raster.distributed``."""
    from rectify import errors

    assert SchedulerError is errors.SchedulerError and "SchedulerError" in errors.__all__
    assert issubclass(SchedulerError, errors.RectifyError) and issubclass(SchedulerError, OSError)


@pytest.mark.parametrize(("spec", "message"), [
    ("tcp://127.0.0.1", "bad scheduler address 'tcp://127.0.0.1': no port; expected tcp://HOST:PORT"),
    ("tcp://[::1]", "bad scheduler address 'tcp://[::1]': no port; expected tcp://HOST:PORT"),
    ("tcp://127.0.0.1:0", "bad scheduler address 'tcp://127.0.0.1:0': port 0 is outside 1..65535"),
    ("tcp://127.0.0.1:70000", "bad scheduler address 'tcp://127.0.0.1:70000': port 70000 is outside 1..65535"),
    ("tls://10.0.0.5:8786", "bad scheduler address 'tls://10.0.0.5:8786': only tcp:// schedulers are supported; "
                            "expected tcp://HOST:PORT"),
    ("tcp://user@host:8786", "bad scheduler address 'tcp://user@host:8786'; expected tcp://HOST:PORT"),
])
def test_addresses_dask_cannot_use_are_refused_by_name(spec, message):
    """``tcp://127.0.0.1`` (no port) made Dask raise a ValueError traceback; other schemes cannot be checked."""
    with pytest.raises(InvalidInputError) as err:
        Scheduler.parse(spec)
    assert str(err.value) == message
    with pytest.raises(InvalidInputError):
        Scheduler("cluster", address=spec)


def test_ipv6_and_trailing_slash_addresses():
    assert Scheduler.parse("tcp://[::1]:8786").address == "tcp://[::1]:8786"
    assert Scheduler.parse("tcp://node-3.cluster.local:8786/").address == "tcp://node-3.cluster.local:8786"
    assert split_address("tcp://[fe80::1]:1") == ("fe80::1", 1)


def test_bounds_from_the_environment(monkeypatch):
    for var in (TIMEOUT_ENV_VAR, WORKER_TIMEOUT_ENV_VAR, STALL_TIMEOUT_ENV_VAR):
        monkeypatch.delenv(var, raising=False)
    s = Scheduler.parse("tcp://10.1.2.3:8786")
    assert (s.timeout_s, s.worker_timeout_s, s.stall_timeout_s) == (10.0, 60.0, 600.0)
    monkeypatch.setenv(TIMEOUT_ENV_VAR, "2.5")
    monkeypatch.setenv(WORKER_TIMEOUT_ENV_VAR, "7")
    monkeypatch.setenv(STALL_TIMEOUT_ENV_VAR, "90")
    s = Scheduler.parse("tcp://10.1.2.3:8786")
    assert (s.timeout_s, s.worker_timeout_s, s.stall_timeout_s) == (2.5, 7.0, 90.0)
    p = Scheduler.parse("processes:2")
    assert (p.worker_timeout_s, p.stall_timeout_s) == (7.0, 90.0)
    for var, bad in ((WORKER_TIMEOUT_ENV_VAR, "0"), (STALL_TIMEOUT_ENV_VAR, "inf"), (WORKER_TIMEOUT_ENV_VAR, "-1"),
                     (STALL_TIMEOUT_ENV_VAR, "a while")):
        monkeypatch.setenv(var, bad)
        with pytest.raises(InvalidInputError) as err:
            Scheduler.parse("tcp://10.1.2.3:8786")
        assert str(err.value) == f"${var} must be a number of seconds > 0; got {bad!r}"
        monkeypatch.setenv(var, "5")
    with pytest.raises(InvalidInputError, match="scheduler stall_timeout_s must be a number of seconds > 0; got 0"):
        Scheduler("cluster", address="tcp://h:1", stall_timeout_s=0)
    with pytest.raises(InvalidInputError, match="scheduler worker_timeout_s must be"):
        Scheduler("processes", worker_timeout_s=float("nan"))


def test_check_scheduler_needs_no_network_for_local_schedulers(monkeypatch):
    def no_network(*a, **k):
        raise AssertionError("a local scheduler was checked over the network")

    monkeypatch.setattr(daskpeer.socket, "create_connection", no_network)
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert check_scheduler(None) == Scheduler()
    assert check_scheduler("threads") == Scheduler()
    assert check_scheduler("processes:2").workers == 2


# ----------------------------------------------------------------- peers that are not a Dask scheduler
@pytest.mark.parametrize(("mode", "expect", "waits"), [
    ("silent", "the peer at {a!r} sent no Dask handshake within 1 s ($T); is it a Dask scheduler?", True),
    ("http", "{a!r} is not a Dask scheduler: where a Dask handshake was expected it sent b'HTTP/1.1' (read as a "
             "Dask message length: 3543824036068086856 bytes, outside 16..1048576)", False),
    ("huge", "{a!r} is not a Dask scheduler: where a Dask handshake was expected it sent "
             "b'\\x00\\x00\\x00\\x00\\x00\\x00\\x00\\x80' (read as a Dask message length: "
             "9223372036854775808 bytes, outside 16..1048576)", False),
    ("not-handshake", "{a!r} is not a Dask scheduler: its first message is not a Dask handshake (list [1, 2, 3])",
     False),
])
def test_identify_refuses_peers_that_are_not_dask_within_the_timeout(mode, expect, waits):
    """The check never waits past its timeout and never sizes a buffer from the peer's bytes: a length of
    2**63 (or 'HTTP/1.1', 3.5e18) is refused from the first 8 bytes (Dask allocated it: 3.07 EiB)."""
    with FakeServer(mode) as srv:
        t0 = time.monotonic()
        with pytest.raises(SchedulerError) as err:
            daskpeer.identify(srv.address, 1.0, env_var="$T")
        dt = time.monotonic() - t0
    assert str(err.value) == expect.format(a=srv.address, T="$T")
    assert (1.0 <= dt < 3.0) if waits else dt < 0.9, dt


def test_identify_a_closed_port_retries_until_the_timeout():
    port = closed_port()
    t0 = time.monotonic()
    with pytest.raises(SchedulerError) as err:
        daskpeer.identify(f"tcp://127.0.0.1:{port}", 1.0, env_var="$T")
    dt = time.monotonic() - t0
    assert str(err.value) == f"cannot reach the Dask scheduler 'tcp://127.0.0.1:{port}' within 1 s ($T): " \
                             "connection refused"
    assert 1.0 <= dt < 3.0


def test_identify_a_real_scheduler_and_its_workers(cluster):
    ident = daskpeer.identify(cluster.scheduler_address, 5.0)
    assert (ident.n_workers, ident.total_threads) == (2, 2)
    with distributed.Client(cluster, set_as_default=False) as client:
        worker = next(iter(client.scheduler_info()["workers"]))
    with pytest.raises(SchedulerError, match=r"is not a Dask scheduler: it answers as a Dask Worker$"):
        daskpeer.identify(worker, 5.0)
    assert check_scheduler(cluster.scheduler_address).address == cluster.scheduler_address


def test_wait_for_workers_is_bounded():
    lc = distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None)
    try:
        t0 = time.monotonic()
        with pytest.raises(SchedulerError) as err:
            check_scheduler(Scheduler("cluster", address=lc.scheduler_address, timeout_s=2.0, worker_timeout_s=1.5))
        dt = time.monotonic() - t0
    finally:
        lc.close()
    assert str(err.value) == f"the Dask scheduler {lc.scheduler_address!r} has no workers: none joined within " \
                             "1.5 s ($RECTIFY_SCHEDULER_WORKER_TIMEOUT)"
    assert 1.5 <= dt < 4.0


def test_a_silent_peer_fails_a_warp_within_the_timeout_and_leaves_nothing(sources, tmp_path):
    with FakeServer("silent") as srv:
        t0 = time.monotonic()
        with pytest.raises(SchedulerError, match="sent no Dask handshake within 1 s"):
            warp_raster(sources / "u8.tif", tmp_path / "out.tif", Homography(), GRID,
                        options=WarpOptions(scheduler=Scheduler("cluster", address=srv.address, timeout_s=1.0)))
        assert time.monotonic() - t0 < 3.0
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------- bounds during a run
class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _watch(monkeypatch, workers, **bounds):
    """A run's watch on a fake clock, the scheduler answering with ``workers()`` workers (or raising)."""
    from rectify.raster import distributed as dist

    def ident(address, timeout_s, env_var=""):
        n = workers()
        if isinstance(n, Exception):
            raise n
        return daskpeer.SchedulerIdentity(address, n, n)

    monkeypatch.setattr(dist, "identify_scheduler", ident)
    clock = _Clock()
    sched = Scheduler("cluster", address="tcp://10.9.8.7:8786", **bounds)
    return dist._Watch(sched, sched.address, "warp", clock=clock), clock


def test_watch_stops_a_run_left_without_workers(monkeypatch):
    n = {"workers": 1}
    watch, clock = _watch(monkeypatch, lambda: n["workers"], worker_timeout_s=10.0, stall_timeout_s=1000.0)
    assert watch.wait_s() == 2.0
    clock.t = 5.0
    watch.check(4)                         # workers present: fine
    n["workers"] = 0
    clock.t = 6.0
    watch.check(4)                         # none since t=6
    clock.t = 15.9
    watch.check(4)
    n["workers"] = 2                       # a worker came back: the wait restarts
    clock.t = 16.5
    watch.check(4)
    n["workers"] = 0
    clock.t = 17.0
    watch.check(4)
    clock.t = 27.0
    with pytest.raises(SchedulerError) as err:
        watch.check(3)
    assert str(err.value) == "warp: the Dask scheduler 'tcp://10.9.8.7:8786' has had no workers for 10 s " \
                             "($RECTIFY_SCHEDULER_WORKER_TIMEOUT); 3 task(s) unfinished"


def test_watch_stops_a_run_without_progress(monkeypatch):
    watch, clock = _watch(monkeypatch, lambda: 2, worker_timeout_s=10.0, stall_timeout_s=100.0)
    clock.t = 99.0
    watch.check(5)
    watch.progressed()                     # a task finished at t=99: the stall clock restarts
    clock.t = 198.0
    watch.check(5)
    clock.t = 199.0
    with pytest.raises(SchedulerError) as err:
        watch.check(5)
    assert str(err.value) == "warp: no Dask task finished for 100 s ($RECTIFY_SCHEDULER_STALL_TIMEOUT) on the " \
                             "scheduler 'tcp://10.9.8.7:8786' (2 worker(s)); 5 task(s) unfinished"


def test_watch_stops_a_run_whose_scheduler_is_gone(monkeypatch):
    watch, clock = _watch(monkeypatch, lambda: SchedulerError("cannot reach X"), worker_timeout_s=1.0)
    assert watch.wait_s() == 0.25          # polls faster under a short bound
    with pytest.raises(SchedulerError, match=r"^warp: lost the Dask scheduler 'tcp://10.9.8.7:8786' during the "
                                             r"run: cannot reach X$"):
        watch.check(1)


def test_unreachable_cluster_fails_quickly_and_leaves_nothing(sources, tmp_path):
    import socket

    with socket.socket() as s:  # a port with nothing listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    sched = Scheduler("cluster", address=f"tcp://127.0.0.1:{port}", timeout_s=2.0)
    with pytest.raises(SchedulerError) as err:
        warp_raster(sources / "u8.tif", tmp_path / "out.tif", Homography(), GRID,
                    options=WarpOptions(scheduler=sched))
    assert time.perf_counter() - t0 < 20
    msg = str(err.value)
    assert msg.startswith(f"cannot reach the Dask scheduler 'tcp://127.0.0.1:{port}' within 2 s") and "\n" not in msg
    assert list(tmp_path.iterdir()) == []  # no output, no temporary file, no block folder


# ----------------------------------------------------------------- tiled equals whole
@pytest.mark.parametrize(("source", "resampling", "mapping", "rtol", "policy"), [
    ("u8.tif", "nearest", Homography, 0.0, "nodata"),
    ("u8.tif", "bilinear", Curved, 0.0, "nodata"),
    ("u8m.tif", "bilinear", Homography, 0.0, "mask"),
    ("u8m.tif", "cubic", Curved, 0.0, "mask"),
    ("f32.tif", "bilinear", Homography, 1e-6, "nodata"),
    ("f32.tif", "cubic", Curved, 1e-6, "nodata"),
])
def test_warp_on_the_cluster_equals_the_local_path(cluster, sources, tmp_path, writes, source, resampling, mapping,
                                                   rtol, policy):
    kw = dict(resampling=resampling, tile_px=64)
    local = warp_raster(sources / source, tmp_path / "local.tif", mapping(), GRID, options=WarpOptions(**kw))
    assert writes == {"pixels": 90, "encoded": 0}  # the local path writes pixels, as before
    assert local.policy == policy == mask_policy(tmp_path / "local.tif").kind
    seen: list[tuple[int, int]] = []
    remote = warp_raster(sources / source, tmp_path / "dask.tif", mapping(), GRID,
                         options=WarpOptions(scheduler=cluster.scheduler_address, **kw),
                         progress=lambda d, t: seen.append((d, t)))
    assert writes == {"pixels": 90, "encoded": 90}  # the Dask path: compressed tiles only
    _assert_same(tmp_path / "local.tif", tmp_path / "dask.tif", rtol=rtol)
    assert (remote.n_tiles, remote.n_empty_tiles, remote.policy) == (local.n_tiles, local.n_empty_tiles, local.policy)
    assert seen[0] == (0, 90) and seen[-1] == (90, 90) and len(seen) == 91
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dask.tif", "local.tif"]  # no block files left


@pytest.mark.parametrize("source", ["u8.tif", "u8m.tif"])
def test_cog_on_the_cluster(cluster, sources, tmp_path, writes, source):
    kw: dict[str, Any] = dict(resampling="bilinear", tile_px=128, cog=True)
    warp_raster(sources / source, tmp_path / "local.tif", Homography(), GRID, options=WarpOptions(**kw))
    warp_raster(sources / source, tmp_path / "dask.tif", Homography(), GRID,
                options=WarpOptions(scheduler=cluster.scheduler_address, **kw))
    assert writes == {"pixels": 25, "encoded": 25}  # the COG body (uncompressed) from the workers' tiles
    assert cog_problems(tmp_path / "dask.tif") == []
    _assert_same(tmp_path / "local.tif", tmp_path / "dask.tif")


@pytest.mark.parametrize(("resampling", "true_ortho"), [("nearest", True), ("bilinear", False), ("cubic", False)])
def test_ortho_on_the_cluster_equals_the_local_path(cluster, tmp_path, writes, resampling, true_ortho):
    model = frame_scene(tmp_path)
    dem = Dem.from_path(tmp_path / "dem.tif")
    kw = dict(tile_px=64, resampling=resampling, true_ortho=true_ortho)
    a = orthorectify(tmp_path / "frame.tif", tmp_path / "local.tif", model, dem, resolution=1.0,
                     options=OrthoOptions(**kw))
    b = orthorectify(tmp_path / "frame.tif", tmp_path / "dask.tif", model, dem, resolution=1.0,
                     options=OrthoOptions(scheduler=cluster.scheduler_address, **kw))
    assert writes["encoded"] == writes["pixels"] == a.n_tiles
    _assert_same(tmp_path / "local.tif", tmp_path / "dask.tif", rtol=0.0 if resampling == "nearest" else 1e-6)
    # the statistics gathered in the workers' tiles add up to the local run's
    assert (b.dem_range, b.max_relief_shift, b.n_occluded, b.n_tiles, b.n_empty_tiles) == \
        (a.dem_range, a.max_relief_shift, a.n_occluded, a.n_tiles, a.n_empty_tiles)
    with rasterio.open(tmp_path / "dask.tif") as ds:
        assert ds.tags()["ORTHO_MODEL"] == "FrameModel"


@pytest.mark.parametrize("cog", [False, True])
def test_mosaic_on_the_cluster_equals_the_local_path(cluster, tmp_path, writes, cog):
    _flat_ortho(tmp_path / "a.tif", 0, 100, 100.0, 30.0)
    _flat_ortho(tmp_path / "b.tif", 40, 140, 200.0, 110.0)
    ins = [tmp_path / "a.tif", tmp_path / "b.tif"]
    a = mosaic(ins, tmp_path / "local.tif", options=MosaicOptions(feather_px=20, tile_px=16, cog=cog))
    b = mosaic(ins, tmp_path / "dask.tif", options=MosaicOptions(feather_px=20, tile_px=16, cog=cog,
                                                                   scheduler=cluster.scheduler_address))
    assert writes["encoded"] == writes["pixels"] > 0
    _assert_same(tmp_path / "local.tif", tmp_path / "dask.tif")
    if cog:
        assert cog_problems(tmp_path / "dask.tif") == []
    assert a.share == b.share


def test_a_failing_task_raises_its_error_and_leaves_nothing(cluster, sources, tmp_path):
    """A task that raises (here: the source vanished between planning and computing) fails the run with
    the task's own project error; no output and no block files remain."""
    import shutil

    src = tmp_path / "in" / "u8.tif"
    src.parent.mkdir()
    shutil.copy(sources / "u8.tif", src)

    out = tmp_path / "out"
    out.mkdir()
    from rectify.errors import RasterIOError

    def remove_source(done, total):
        if done == 0:
            src.unlink()

    with pytest.raises(RasterIOError, match="raster not found"):
        warp_raster(src, out / "dask.tif", Homography(), GRID,
                    options=WarpOptions(tile_px=64, scheduler=Scheduler("cluster", address=cluster.scheduler_address,
                                                                        retries=0)),
                    progress=remove_source)
    assert list(out.iterdir()) == []


def _opencv_threads_in_a_task() -> int:
    import cv2

    from rectify.raster.distributed import _bound_opencv_threads

    _bound_opencv_threads()
    return cv2.getNumThreads()


def test_opencv_uses_the_worker_threads_only(cluster):
    """A worker of one thread runs OpenCV on one thread (not on every core, on top of the other workers);
    outside a worker the setting is left alone."""
    import cv2
    import distributed

    with distributed.Client(cluster) as client:
        assert client.submit(_opencv_threads_in_a_task, pure=False).result() == 1
    before = cv2.getNumThreads()
    assert _opencv_threads_in_a_task() == before


# ----------------------------------------------------------------- a worker lost mid-run
class KillableCurved(Curved):
    """:class:`Curved`, whose first call in one of ``worker_pids`` claims that worker as the victim (an
    exclusive file, then ``victim.pid`` written atomically) and blocks there until the test kills it: the
    kill always lands inside a running task, which the run cannot finish without. The replacement worker
    (a new pid) and the other worker compute normally."""

    def __init__(self, flag_dir, worker_pids):
        self.claim = str(flag_dir / "victim.claim")
        self.pid_file = str(flag_dir / "victim.pid")
        self.worker_pids = frozenset(worker_pids)

    def __call__(self, p):
        if os.getpid() in self.worker_pids:
            try:
                os.close(os.open(self.claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                pass
            else:
                tmp = f"{self.pid_file}.tmp"
                with open(tmp, "w") as f:
                    f.write(str(os.getpid()))
                os.replace(tmp, self.pid_file)
                deadline = time.monotonic() + 600
                while time.monotonic() < deadline:  # wait for SIGKILL
                    time.sleep(0.02)
                raise RuntimeError("the claimed worker was not killed within 600 s")
        return super().__call__(p)


def _wait_for(what, ok, timeout_s):
    """Poll ``ok()`` until true; fail naming ``what`` after ``timeout_s`` (generous: the machine may be busy)."""
    deadline = time.monotonic() + timeout_s
    while not ok():
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        time.sleep(0.1)


def _gone(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_a_killed_worker_is_replaced_and_the_output_is_complete(sources, tmp_path, caplog):
    """A worker killed (SIGKILL) inside a running task: the scheduler removes it, its task runs elsewhere, the
    nanny starts a replacement, and the output is complete and equal to the threads path's.

    Deterministic under load: the kill waits for the task's own signal (``KillableCurved``) and every later
    check polls for its event with a generous deadline; nothing depends on how long a step takes."""
    import logging
    import threading

    caplog.set_level(logging.INFO, logger="distributed.scheduler")
    kw: dict[str, Any] = dict(resampling="cubic", tile_px=32)
    out = tmp_path / "out"
    out.mkdir()
    flags = tmp_path / "flags"
    flags.mkdir()
    warp_raster(sources / "f32.tif", out / "local.tif", Curved(), GRID, options=WarpOptions(**kw))
    lc = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    try:
        with distributed.Client(lc) as client:
            pids = client.run(os.getpid)  # worker address -> pid
            state = {"done": 0, "total": None, "killed": None, "done_at_kill": None}

            def progress(done, total):
                state["done"], state["total"] = done, total

            def kill_the_claimed_worker():
                pid_file = flags / "victim.pid"
                deadline = time.monotonic() + 600
                while not pid_file.exists():
                    if time.monotonic() > deadline:
                        return
                    time.sleep(0.02)
                pid = int(pid_file.read_text())
                state["done_at_kill"] = state["done"]
                os.kill(pid, signal.SIGKILL)
                state["killed"] = pid

            killer = threading.Thread(target=kill_the_claimed_worker, daemon=True)
            killer.start()
            r = warp_raster(sources / "f32.tif", out / "dask.tif", KillableCurved(flags, pids.values()), GRID,
                            options=WarpOptions(scheduler=lc.scheduler_address, **kw), progress=progress)
            killer.join(timeout=60)
            victim = state["killed"]
            assert victim in pids.values(), "no worker claimed a task and was killed"
            victim_address = next(a for a, p in pids.items() if p == victim)
            # the kill happened inside a task of this run, before its end
            assert state["done_at_kill"] is not None and state["done_at_kill"] < r.n_tiles == state["total"]
            _wait_for(f"worker process {victim} to be gone", lambda: _gone(victim), 120)
            # the scheduler saw the worker go (its task is recomputed elsewhere: the run completed)
            _wait_for(f"the scheduler to log 'Remove worker' for {victim_address}",
                      lambda: any("Remove worker" in m.getMessage() and victim_address in m.getMessage()
                                  for m in caplog.records), 120)
            # the nanny started a new worker process in its place
            def replaced():
                workers = set(client.scheduler_info()["workers"])
                return victim_address not in workers and len(workers) == 2

            _wait_for("a replacement worker", replaced, 300)
            now = client.run(os.getpid)
            assert len(now) == 2 and victim not in now.values()
    finally:
        lc.close()
    _assert_same(out / "local.tif", out / "dask.tif")
    assert sorted(p.name for p in out.iterdir()) == ["dask.tif", "local.tif"]


def test_guided_task_sizes_cover_every_window_once_and_shrink():
    from rectify.raster.distributed import GUIDED_MAX, GUIDED_MIN, _guided_groups

    for n in (0, 1, 5, 169, 484, 5000):
        for slots in (1, 2, 8):
            wins = [(i, 0, 1, 1) for i in range(n)]
            groups = _guided_groups(wins, slots)
            assert [w for g in groups for w in g] == wins
            sizes = [len(g) for g in groups]
            assert all(1 <= s <= GUIDED_MAX for s in sizes)
            assert sizes == sorted(sizes, reverse=True)          # big tasks first, small ones at the end
            assert all(s >= GUIDED_MIN for s in sizes[:-1])
    assert len(_guided_groups([(i, 0, 1, 1) for i in range(484)], 2)) < 484 // 8   # fewer tasks than 8 per task
