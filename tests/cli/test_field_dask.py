"""Hostile Dask schedulers, end to end (issue 32): every command that takes ``--scheduler`` answers a peer
that is not a working Dask scheduler with one line, within the bound it names, and leaves nothing behind.

Each command runs in a subprocess with a hard ``timeout=`` (a hang fails the test, it does not stall the
suite); the bounds are set short through the environment (``RECTIFY_SCHEDULER_TIMEOUT=1`` and the
others). The peers: a socket that accepts and never answers, a server answering HTTP, a closed port, a
worker's port, a real scheduler with no worker, one whose only worker is killed during the run, one
whose only worker hangs (SIGSTOP); and SIGTERM during a Dask run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli as rectify_cli
from rectify.formats.transform import write_transform
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.transforms.matrix import AffineTransform
from rectify.raster.io import write_raster
from stereo.actions.scene import make_scene, write_scene_inputs
from stereo.cli.main import cli as stereo_cli
from tests.support.dask_support import DASK_WARNING_FILTERS, REPO, FakeServer, closed_port, start_worker, stop_worker

distributed = pytest.importorskip("distributed")

pytestmark = [*DASK_WARNING_FILTERS]

#: the hard bound of one command (a hang fails here instead of stalling the suite)
HARD_BOUND_S = 120.0
#: what a command may take on top of its stated timeout: starting Python, importing the command (and Dask)
STARTUP_S = 25.0
#: the short bounds the commands run with (seconds, through the environment)
BOUNDS = {"RECTIFY_SCHEDULER_TIMEOUT": "1", "RECTIFY_SCHEDULER_WORKER_TIMEOUT": "2",
          "RECTIFY_SCHEDULER_STALL_TIMEOUT": "3"}
CRS = "EPSG:32632"
E0, N0 = 500_000.0, 5_000_000.0


# ----------------------------------------------------------------------------- inputs of every command
def _frame(path: Path, w: int = 600, h: int = 500) -> None:
    rng = np.random.default_rng(5)
    rr, cc = np.mgrid[0:h, 0:w]
    img = np.stack([cc * 0.3 + rr * 0.1, 120 + 80 * np.sin(cc / 17.0), rr * 0.4], axis=-1)
    img = np.clip(img + rng.normal(0, 5, img.shape), 1, 255).astype(np.uint8)
    write_raster(path, img, Affine(1, 0, 0, 0, 1.0000001, 0), None, nodata=0)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """The input files of warp, ortho, mosaic, match, dense and run, in one folder (never written to)."""
    d = tmp_path_factory.mktemp("field_dask_inputs")
    _frame(d / "frame.tif")
    m = np.array([[29.0, 6.0, 500100.0], [5.0, -31.0, 4399900.0], [0.0, 0.0, 1.0]])
    write_transform(d / "affine.json", AffineTransform(m), crs="EPSG:32618")
    # ortho: a DEM, a frame photo, its camera and exterior orientation
    yy, xx = np.mgrid[0:100, 0:100]
    z = (100 + 10 * np.sin(xx / 9.0) + 0.2 * yy).astype("float32")
    with rasterio.open(d / "dem.tif", "w", driver="GTiff", width=100, height=100, count=1, dtype="float32", crs=CRS,
                       transform=Affine(4.0, 0, E0 - 200, 0, -4.0, N0 + 200)) as ds:
        ds.write(z, 1)
    rr, cc = np.mgrid[0:60, 0:80]
    with rasterio.open(d / "img.tif", "w", driver="GTiff", width=80, height=60, count=1, dtype="uint8") as ds:
        ds.write((100 + 50 * np.sin(cc / 3.0) * np.cos(rr / 4.0)).astype(np.uint8)[None])
    (d / "cam.json").write_text(json.dumps({"focal_length_mm": 10.0, "pixel_size_mm": 0.02, "width": 80,
                                            "height": 60}))
    (d / "eo.json").write_text(json.dumps({"position": [E0, N0, 600.0],
                                           "rotation": matrix_from_angles(0.03, -0.02, 0.2).tolist(), "crs": CRS}))
    # mosaic: an orthophoto
    write_raster(d / "ortho.tif", np.full((64, 64), 7, np.uint8), Affine(2.0, 0, E0, 0, -2.0, N0), CRS, nodata=0)
    # stereo run / dense: a rendered pair and its camera; a relative orientation stand-in (dense checks the
    # scheduler before it reads it)
    scene = write_scene_inputs(make_scene(0, size_px=320), d / "pair")
    (d / "relative.json").write_text("{}")
    return {"dir": d, "frame": d / "frame.tif", "affine": d / "affine.json", "dem": d / "dem.tif",
            "img": d / "img.tif", "cam": d / "cam.json", "eo": d / "eo.json", "ortho": d / "ortho.tif",
            "left": scene["left"], "right": scene["right"], "camera": scene["camera"],
            "relative": d / "relative.json"}


def _command(name: str, i: dict, out: Path) -> tuple[str, list[str]]:
    """(program, arguments) of ``name`` writing into the folder ``out``."""
    return {
        "warp": ("rectify", ["warp", str(i["frame"]), str(out / "o.tif"), "--transform", str(i["affine"])]),
        "ortho": ("rectify", ["ortho", str(i["img"]), "--dem", str(i["dem"]), "--camera", str(i["cam"]),
                              "--exterior", str(i["eo"]), "-o", str(out / "o.tif"), "--resolution", "2"]),
        "mosaic": ("rectify", ["mosaic", str(i["ortho"]), "-o", str(out / "o.tif")]),
        "match": ("rectify", ["match", str(i["left"]), str(i["right"]), "-o", str(out / "m.csv")]),
        "dense": ("stereo", ["dense", str(i["relative"]), str(i["left"]), str(i["right"]), "-o", str(out / "d")]),
        "run": ("stereo", ["run", str(i["left"]), str(i["right"]), "--camera", str(i["camera"]), "-o",
                           str(out / "r"), "--dense"]),
    }[name]


COMMANDS = ["warp", "ortho", "mosaic", "match", "dense", "run"]


def _cli(prog: str, args: list[str], *, env: dict[str, str] | None = None,
         timeout: float = HARD_BOUND_S) -> tuple[subprocess.CompletedProcess, float]:
    """Run ``prog args`` in a fresh interpreter with the short bounds; (result, seconds)."""
    e = {k: v for k, v in os.environ.items() if not k.startswith("RECTIFY_SCHEDULER")}
    e.update(BOUNDS)
    e["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    e.update(env or {})
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", f"from {prog}.cli.main import cli; cli(prog_name={prog!r})", *args],
                       capture_output=True, text=True, timeout=timeout, env=e, cwd=str(REPO))
    return r, time.monotonic() - t0


def _one_line_error(r: subprocess.CompletedProcess, seconds: float, bound_s: float, *parts: str) -> str:
    """The run failed (exit 1) in one line holding every one of ``parts``, no traceback, within ``bound_s`` +
    start-up."""
    text = (r.stdout + r.stderr).strip()
    assert r.returncode == 1, text
    assert "Traceback" not in text and len(text.splitlines()) == 1, text
    assert text.startswith("Error: SchedulerError: "), text
    for p in parts:
        assert p in text, (p, text)
    assert seconds < bound_s + STARTUP_S, f"{seconds:.1f} s"
    return text


def _nothing_left(out: Path) -> None:
    assert list(out.iterdir()) == [], sorted(p.name for p in out.rglob("*"))


# ----------------------------------------------------------------------------- peers that are not Dask
@pytest.mark.parametrize("command", COMMANDS)
def test_a_silent_peer_is_refused_within_the_handshake_timeout(inputs, tmp_path, command):
    """A socket that accepts and never answers hung warp, ortho and dense (Dask waits for the handshake
    without limit): now every command gives up after $RECTIFY_SCHEDULER_TIMEOUT, before any work."""
    with FakeServer("silent") as srv:
        prog, args = _command(command, inputs, tmp_path)
        r, sec = _cli(prog, [*args, "--scheduler", srv.address])
    _one_line_error(r, sec, 1.0, f"the peer at {srv.address!r} sent no Dask handshake within 1 s "
                                 "($RECTIFY_SCHEDULER_TIMEOUT); is it a Dask scheduler?")
    _nothing_left(tmp_path)


@pytest.mark.parametrize("command", COMMANDS)
def test_a_silent_peer_from_the_environment(inputs, tmp_path, command):
    """The same peer named by $RECTIFY_SCHEDULER: checked by the command itself (match, dense and run before
    any work; warp, ortho and mosaic before the first tile, their outputs atomic)."""
    with FakeServer("silent") as srv:
        prog, args = _command(command, inputs, tmp_path)
        r, sec = _cli(prog, args, env={"RECTIFY_SCHEDULER": srv.address})
    _one_line_error(r, sec, 1.0, f"the peer at {srv.address!r} sent no Dask handshake within 1 s")
    _nothing_left(tmp_path)


@pytest.mark.parametrize("command", ["warp", "ortho", "dense", "match"])
def test_an_http_server_is_not_a_scheduler_and_nothing_is_allocated_from_its_bytes(inputs, tmp_path, command):
    """An HTTP server's answer made Dask allocate 3.07 EiB ('HTTP/1.1' read as a length): now refused by name,
    at once, from the first 8 bytes."""
    with FakeServer("http") as srv:
        prog, args = _command(command, inputs, tmp_path)
        r, sec = _cli(prog, [*args, "--scheduler", srv.address])
    text = _one_line_error(r, sec, 1.0, f"{srv.address!r} is not a Dask scheduler: where a Dask handshake was "
                                        "expected it sent b'HTTP/1.1'")
    assert "EiB" not in text and "MemoryError" not in text
    _nothing_left(tmp_path)


def test_an_http_server_from_the_environment_in_warp(inputs, tmp_path):
    with FakeServer("http") as srv:
        prog, args = _command("warp", inputs, tmp_path)
        r, sec = _cli(prog, args, env={"RECTIFY_SCHEDULER": srv.address})
    _one_line_error(r, sec, 1.0, "is not a Dask scheduler", "b'HTTP/1.1'")
    _nothing_left(tmp_path)


@pytest.mark.parametrize("command", ["match", "run", "warp"])
def test_a_closed_port_fails_even_where_the_run_would_not_use_it(inputs, tmp_path, command):
    """``rectify match --scheduler tcp://<closed>`` ignored the scheduler (a small pair does not tile) and
    exited 0; ``stereo run --dense`` left matches.csv, model_points.ply and orientation.json. Both now refuse
    the scheduler before any work (as warp does)."""
    port = closed_port()
    prog, args = _command(command, inputs, tmp_path)
    for env, extra in (({}, ["--scheduler", f"tcp://127.0.0.1:{port}"]),
                       ({"RECTIFY_SCHEDULER": f"tcp://127.0.0.1:{port}"}, [])):
        r, sec = _cli(prog, [*args, *extra], env=env)
        _one_line_error(r, sec, 1.0, f"cannot reach the Dask scheduler 'tcp://127.0.0.1:{port}' within 1 s "
                                     "($RECTIFY_SCHEDULER_TIMEOUT): connection refused")
        _nothing_left(tmp_path)


@pytest.mark.parametrize("command", COMMANDS)
def test_an_address_without_a_port_is_a_usage_error(inputs, tmp_path, monkeypatch, command):
    """``tcp://127.0.0.1`` made Dask raise a ValueError traceback: now refused by name before any network
    (in this process: nothing here can hang)."""
    prog, args = _command(command, inputs, tmp_path)
    main = rectify_cli if prog == "rectify" else stereo_cli
    for key in [k for k in os.environ if k.startswith("RECTIFY_SCHEDULER")]:
        monkeypatch.delenv(key)
    r = CliRunner().invoke(main, [*args, "--scheduler", "tcp://127.0.0.1"])
    assert r.exit_code == 2 and isinstance(r.exception, SystemExit), r.output
    assert [s for s in r.output.splitlines() if s.startswith("Error")] == [
        "Error: Invalid value for '--scheduler': bad scheduler address 'tcp://127.0.0.1': no port; expected "
        "tcp://HOST:PORT"]
    monkeypatch.setenv("RECTIFY_SCHEDULER", "tcp://127.0.0.1")
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.output
    assert r.output.strip().splitlines()[-1] == ("Error: InvalidInputError: bad scheduler in $RECTIFY_SCHEDULER "
                                                 "address 'tcp://127.0.0.1': no port; expected tcp://HOST:PORT")
    _nothing_left(tmp_path)


# ----------------------------------------------------------------------------- real schedulers in trouble
@pytest.fixture()
def bare_scheduler():
    """A Dask scheduler with no workers (a LocalCluster of 0 worker processes); its address."""
    lc = distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None)
    try:
        yield lc.scheduler_address
    finally:
        lc.close()


@pytest.mark.parametrize("command", ["warp", "dense"])
def test_a_scheduler_without_workers_is_refused_after_the_worker_timeout(inputs, tmp_path, bare_scheduler, command):
    """A cluster with no workers hung the run (its tasks waited for ever)."""
    prog, args = _command(command, inputs, tmp_path)
    r, sec = _cli(prog, [*args, "--scheduler", bare_scheduler])
    _one_line_error(r, sec, 2.0, f"the Dask scheduler {bare_scheduler!r} has no workers: none joined within 2 s "
                                 "($RECTIFY_SCHEDULER_WORKER_TIMEOUT)")
    _nothing_left(tmp_path)


def test_a_workers_port_is_not_a_scheduler(inputs, tmp_path, bare_scheduler):
    worker = start_worker(bare_scheduler)
    try:
        with distributed.Client(bare_scheduler, set_as_default=False) as client:
            (address,) = client.scheduler_info()["workers"]
        prog, args = _command("warp", inputs, tmp_path)
        r, sec = _cli(prog, [*args, "--scheduler", address])
    finally:
        stop_worker(worker)
    _one_line_error(r, sec, 1.0, f"{address!r} is not a Dask scheduler: it answers as a Dask Worker")
    _nothing_left(tmp_path)


def _wait_for_blocks(out: Path, proc: subprocess.Popen, timeout_s: float = 90.0) -> None:
    """Until the run's hidden block folder appears in ``out`` (its Dask tasks are submitted)."""
    deadline = time.monotonic() + timeout_s
    while not list(out.glob(".warp-blocks.*")):
        assert proc.poll() is None, "the run ended before it submitted its tasks: " + proc.communicate()[1]
        assert time.monotonic() < deadline, f"no Dask task submitted within {timeout_s:g} s"
        time.sleep(0.01)


def _start(prog: str, args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
    e = {k: v for k, v in os.environ.items() if not k.startswith("RECTIFY_SCHEDULER")}
    e.update(BOUNDS)
    e["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    e.update(env or {})
    return subprocess.Popen([sys.executable, "-c", f"from {prog}.cli.main import cli; cli(prog_name={prog!r})",
                             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=e, cwd=str(REPO))


#: a warp long enough to be interrupted (3600 x 3000 px, cubic, about 50 tasks on one worker thread)
LONG_WARP = ["--resolution", "5", "--resampling", "cubic"]


def test_the_only_worker_killed_during_the_run(inputs, tmp_path, bare_scheduler):
    """The cluster's only worker (no nanny) is killed once the run has submitted its tasks: the tasks wait
    for a worker that never comes; the run stops after $RECTIFY_SCHEDULER_WORKER_TIMEOUT."""
    worker = start_worker(bare_scheduler)
    prog, args = _command("warp", inputs, tmp_path)
    proc = _start(prog, [*args, *LONG_WARP, "--scheduler", bare_scheduler])
    try:
        _wait_for_blocks(tmp_path, proc)
        t_kill = time.monotonic()
        os.kill(worker.pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=HARD_BOUND_S)
        after_kill = time.monotonic() - t_kill
    finally:
        stop_worker(worker)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    r = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    _one_line_error(r, after_kill, 2.0, f"warp: the Dask scheduler {bare_scheduler!r} has had no workers for 2 s "
                                        "($RECTIFY_SCHEDULER_WORKER_TIMEOUT)", "task(s) unfinished")
    _nothing_left(tmp_path)


def test_a_hung_worker_stops_the_run_after_the_stall_timeout(inputs, tmp_path, bare_scheduler):
    """The only worker hangs (SIGSTOP: the scheduler still counts it): no task finishes, and the run stops
    after $RECTIFY_SCHEDULER_STALL_TIMEOUT."""
    worker = start_worker(bare_scheduler)
    prog, args = _command("warp", inputs, tmp_path)
    try:
        os.kill(worker.pid, signal.SIGSTOP)
        r, sec = _cli(prog, [*args, "--scheduler", bare_scheduler])
    finally:
        stop_worker(worker)
    _one_line_error(r, sec, 3.0, "warp: no Dask task finished for 3 s ($RECTIFY_SCHEDULER_STALL_TIMEOUT) on the "
                                 f"scheduler {bare_scheduler!r} (1 worker(s))")
    _nothing_left(tmp_path)


def test_sigterm_during_a_dask_run_exits_143_without_a_traceback(inputs, tmp_path):
    """SIGTERM while a local Dask cluster computes the tiles: exit 143, nothing printed (Dask's closing
    comms logged a traceback), the cluster closed, nothing left beside the output."""
    prog, args = _command("warp", inputs, tmp_path)
    proc = _start(prog, [*args, *LONG_WARP, "--scheduler", "processes:2"])
    try:
        _wait_for_blocks(tmp_path, proc)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=HARD_BOUND_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, out + err
    assert "Traceback" not in err and (out + err).strip() == "", out + err
    _nothing_left(tmp_path)
