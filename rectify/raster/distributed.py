"""Tiled steps on Dask: one scheduler choice for the warp, orthophoto and mosaic engines.

The tiled engines (:mod:`rectify.raster.warp`, :mod:`rectify.raster.ortho`, :mod:`rectify.raster.mosaic`) compute
output windows with one function per engine (``engine.tile(col, row, width, height)``) and write
them with one callback (``write(result, col, row)``). :func:`run_windows` runs those windows

- on local threads (``threads``, the default: :func:`rectify.raster.tiles.run_tiles`), or
- as a Dask graph (``processes[:N]``: a :class:`distributed.LocalCluster` of N worker processes
  with one thread each; ``tcp://HOST:PORT``: an existing cluster), one task per *block* (a few
  consecutive output windows). Each task receives the engine (its geometry and the source *paths*,
  never pixels), opens the sources itself, computes its windows with the very code the local path
  runs (same margins, same kernels) and writes them to a per-task block file (``.npz``, or the
  encoded windows' bytes end to end; written to a temporary name and renamed: a retried task
  simply rewrites it) in a hidden folder beside the output. The calling process reads each block
  as its task completes and writes its windows inside the usual atomic output. With a
  ``raw_writer`` (the GeoTIFF writers of the warp, orthophoto and mosaic steps, in raw mode) the
  task also compresses each window into the output's GeoTIFF tile on the worker
  (:class:`rectify.raster.tiffblocks.TileEncoder`), and the calling process only copies the compressed
  bytes into the file (:meth:`rectify.raster.io.TiledWriter.write_encoded`): it neither decodes nor compresses pixels,
  so it does not compete with the workers for CPU. Either way the pixels and masks of the output
  are those of the local path (the tiles are the very bytes GDAL writes there).

Scheduler choice: the ``scheduler`` argument (``rectify warp/ortho/mosaic --scheduler``), else the
environment variable :data:`ENV_VAR` (``RECTIFY_SCHEDULER``), else ``threads``.

Faults: every task is submitted with ``retries`` (default 2) and Dask reruns the tasks of a worker
that dies on another worker; tasks are idempotent (block files are renamed into place). Progress is
reported through the ``progress(done, total)`` callback (windows done) as the tasks complete; the
Dask dashboard link, when the dashboard runs, is logged at INFO level.

Bounds (each a one-line :class:`SchedulerError` naming the address and the bound): before Dask's
client connects to a cluster, :mod:`rectify.raster.daskpeer` checks on a plain socket, within
``timeout_s`` (``$RECTIFY_SCHEDULER_TIMEOUT``, default 10 s), that a Dask *scheduler* answers there
(Dask's own client waits for a handshake without limit and sizes its first buffer from the peer's
first 8 bytes), and waits at most ``worker_timeout_s`` (``$RECTIFY_SCHEDULER_WORKER_TIMEOUT``, default
60 s) for it to have a worker; during a run, a cluster left without workers for ``worker_timeout_s``,
or a run in which no task finishes for ``stall_timeout_s`` (``$RECTIFY_SCHEDULER_STALL_TIMEOUT``,
default 600 s), stops. :func:`check_scheduler` runs the check up front (the commands call it before
any work).
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import importlib.util
import logging
import math
import os
import queue
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from rectify.atomic import raise_if_terminated
from rectify.errors import InvalidInputError, SchedulerError
from rectify.raster import tiles as tilepool
from rectify.raster.daskpeer import SchedulerIdentity, split_address, wait_for_workers
from rectify.raster.daskpeer import identify as identify_scheduler
from rectify.raster.io import bound_gdal_cache

__all__ = ["ENV_VAR", "TIMEOUT_ENV_VAR", "WORKER_TIMEOUT_ENV_VAR", "STALL_TIMEOUT_ENV_VAR", "Scheduler",
           "SchedulerError", "BlockEngine", "resolve_scheduler", "check_scheduler", "run_windows", "DEFAULT_RETRIES",
           "DEFAULT_CONNECT_TIMEOUT_S", "DEFAULT_WORKER_TIMEOUT_S", "DEFAULT_STALL_TIMEOUT_S"]

logger = logging.getLogger(__name__)

#: environment variable holding the default scheduler (``threads``, ``processes[:N]``, ``tcp://HOST:PORT``)
ENV_VAR = "RECTIFY_SCHEDULER"
#: times Dask reruns a failed task (a task whose worker died is rerun by the scheduler as well)
DEFAULT_RETRIES = 2
#: seconds to connect to a cluster's scheduler and exchange the handshake (``$RECTIFY_SCHEDULER_TIMEOUT`` overrides)
DEFAULT_CONNECT_TIMEOUT_S = 10.0
#: environment variable: seconds to connect to a cluster's scheduler and exchange the handshake
TIMEOUT_ENV_VAR = "RECTIFY_SCHEDULER_TIMEOUT"
#: seconds a run waits for a cluster to have a worker, before it starts and whenever it has none left
DEFAULT_WORKER_TIMEOUT_S = 60.0
#: environment variable: seconds to wait for a worker
WORKER_TIMEOUT_ENV_VAR = "RECTIFY_SCHEDULER_WORKER_TIMEOUT"
#: seconds a run may go without any task finishing (a hung worker or scheduler)
DEFAULT_STALL_TIMEOUT_S = 600.0
#: environment variable: seconds without a finished task
STALL_TIMEOUT_ENV_VAR = "RECTIFY_SCHEDULER_STALL_TIMEOUT"
#: seconds between the checks of a cluster's workers while no task finishes (shorter when a bound is shorter)
POLL_S = 2.0

_SPEC_HELP = "expected 'threads', 'processes', 'processes:N' or 'tcp://HOST:PORT'"


@dataclass(frozen=True)
class Scheduler:
    """Where the tiles of a step run.

    Attributes
    ----------
    kind : str
        ``"threads"`` (a local thread pool, today's path), ``"processes"`` (a local Dask cluster of
        worker processes started for the run) or ``"cluster"`` (an existing Dask cluster).
    workers : int or None
        Worker processes of ``"processes"`` (None: one per core).
    address : str or None
        Scheduler address of ``"cluster"`` (``tcp://HOST:PORT``).
    timeout_s : float
        Seconds to connect to a cluster's scheduler and exchange the handshake (``"cluster"``).
    retries : int
        Reruns of a failed task (Dask ``retries``).
    worker_timeout_s : float
        Seconds to wait for the cluster to have a worker: before the run and whenever it has none left.
    stall_timeout_s : float
        Seconds a run may go without any task finishing.
    """

    kind: str = "threads"
    workers: int | None = None
    address: str | None = None
    timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S
    retries: int = DEFAULT_RETRIES
    worker_timeout_s: float = DEFAULT_WORKER_TIMEOUT_S
    stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S

    def __post_init__(self) -> None:
        if self.kind not in ("threads", "processes", "cluster"):
            raise InvalidInputError(f"unknown scheduler kind {self.kind!r}; expected threads, processes or cluster")
        if self.workers is not None and not 1 <= self.workers <= 1024:
            raise InvalidInputError(f"scheduler workers must be in 1..1024; got {self.workers!r}")
        if self.kind == "cluster" and not self.address:
            raise InvalidInputError("a cluster scheduler needs an address (tcp://HOST:PORT)")
        if self.kind == "cluster":
            split_address(str(self.address))
        for name in ("timeout_s", "worker_timeout_s", "stall_timeout_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidInputError(f"scheduler {name} must be a number of seconds > 0; got {value!r}")
        if self.retries < 0:
            raise InvalidInputError(f"scheduler retries must be >= 0; got {self.retries!r}")

    @classmethod
    def parse(cls, spec: str, *, source: str = "scheduler") -> Scheduler:
        """Parse ``threads``, ``processes``, ``processes:N`` or ``tcp://HOST:PORT``.

        ``source`` names where the value came from in the error message (the option or the
        environment variable).

        Raises
        ------
        InvalidInputError
            Anything else, named in a one-line message.

        Examples
        --------
        >>> Scheduler.parse("processes:2").workers
        2
        >>> Scheduler.parse("tcp://10.0.0.5:8786").address
        'tcp://10.0.0.5:8786'
        >>> Scheduler.parse("gpu")
        Traceback (most recent call last):
        ...
        rectify.errors.InvalidInputError: unknown scheduler 'gpu'; expected 'threads', 'processes', \
'processes:N' or 'tcp://HOST:PORT'

        The bounds of a Dask scheduler come from ``$RECTIFY_SCHEDULER_TIMEOUT``,
        ``$RECTIFY_SCHEDULER_WORKER_TIMEOUT`` and ``$RECTIFY_SCHEDULER_STALL_TIMEOUT`` when set.
        """
        s = str(spec).strip()
        low = s.lower()
        if low == "threads":
            return cls("threads")
        if low == "processes":
            wt, st = _env_bounds()
            return cls("processes", worker_timeout_s=wt, stall_timeout_s=st)
        if low.startswith("processes:"):
            n = low.split(":", 1)[1]
            if not n.isdigit() or not 1 <= int(n) <= 1024:
                raise InvalidInputError(f"bad {source} {s!r}: the worker count must be an integer in 1..1024")
            wt, st = _env_bounds()
            return cls("processes", workers=int(n), worker_timeout_s=wt, stall_timeout_s=st)
        if "://" in s:
            host, port = split_address(s, source=source)
            host = f"[{host}]" if ":" in host else host
            wt, st = _env_bounds()
            return cls("cluster", address=f"tcp://{host}:{port}",
                       timeout_s=_env_seconds(TIMEOUT_ENV_VAR, DEFAULT_CONNECT_TIMEOUT_S), worker_timeout_s=wt,
                       stall_timeout_s=st)
        raise InvalidInputError(f"unknown {source} {s!r}; {_SPEC_HELP}")

    @property
    def is_local_threads(self) -> bool:
        """True for today's local thread pool."""
        return self.kind == "threads"

    def __str__(self) -> str:
        if self.kind == "processes":
            return "processes" if self.workers is None else f"processes:{self.workers}"
        return self.address if self.kind == "cluster" else "threads"  # type: ignore[return-value]


def _env_seconds(var: str, default: float) -> float:
    """Seconds from the environment variable ``var`` (a number > 0), else ``default``."""
    raw = os.environ.get(var, "").strip()
    if not raw:
        return default
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise InvalidInputError(f"${var} must be a number of seconds > 0; got {raw!r}")
    return value


def _env_bounds() -> tuple[float, float]:
    """(worker timeout, stall timeout) from the environment, else the defaults."""
    return (_env_seconds(WORKER_TIMEOUT_ENV_VAR, DEFAULT_WORKER_TIMEOUT_S),
            _env_seconds(STALL_TIMEOUT_ENV_VAR, DEFAULT_STALL_TIMEOUT_S))


def resolve_scheduler(spec: Scheduler | str | None = None) -> Scheduler:
    """The scheduler to use: ``spec``, else ``$RECTIFY_SCHEDULER``, else ``threads``.

    Raises
    ------
    InvalidInputError
        A bad ``spec`` or a bad value of the environment variable (named).
    """
    if isinstance(spec, Scheduler):
        return spec
    if spec is not None and str(spec).strip():
        return Scheduler.parse(str(spec))
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        return Scheduler.parse(env, source=f"scheduler in ${ENV_VAR}")
    return Scheduler()


def check_scheduler(spec: Scheduler | str | None = None) -> Scheduler:
    """:func:`resolve_scheduler`, and for a cluster the check that a Dask scheduler with a worker answers.

    What the commands call before any work: a cluster that cannot be reached, is not a Dask
    scheduler, or has no worker within ``worker_timeout_s`` fails here, in one line, whether or not
    the run would have needed it (``rectify match`` of a small pair does not tile). Local schedulers
    need no check (a local cluster is started by the run).

    Raises
    ------
    InvalidInputError
        A bad ``spec`` or environment variable.
    SchedulerError
        See :func:`rectify.raster.daskpeer.identify` and :func:`rectify.raster.daskpeer.wait_for_workers`.
    """
    sched = resolve_scheduler(spec)
    if sched.kind == "cluster":
        _wait_for_workers(sched, str(sched.address))
    return sched


def _wait_for_workers(sched: Scheduler, address: str) -> SchedulerIdentity:
    return wait_for_workers(address, sched.timeout_s, sched.worker_timeout_s, timeout_var=f"${TIMEOUT_ENV_VAR}",
                            worker_var=f"${WORKER_TIMEOUT_ENV_VAR}")


class BlockEngine(Protocol):
    """What :func:`run_windows` needs of a tiled engine.

    ``tile(c, r, w, h)`` computes one output window (any picklable result of arrays, None and
    bools); ``close()`` releases the engine's open files. For Dask, ``portable()`` returns a copy
    that pickles (no open files, locks or thread-locals) and names its inputs by absolute path.
    Engines that gather statistics while computing tiles may also define ``stats()`` (a picklable
    summary of what this copy computed) and ``merge_stats(stats)`` (add a copy's summary to this
    engine); :func:`run_windows` merges every task's summary into the calling engine.
    """

    def tile(self, c0: int, r0: int, w: int, h: int) -> Any: ...

    def close(self) -> None: ...

    def portable(self) -> Any: ...


Window = tuple[int, int, int, int]


def run_windows(engine: BlockEngine, write: Callable[[Any, int, int], bool], windows: Sequence[Window], *,
                threads: int, progress: Callable[[int, int], None] | None, scheduler: Scheduler | str | None,
                workdir: str | Path, name: str = "tile", windows_per_task: int | None = None,
                raw_writer: Any = None) -> int:
    """Compute ``windows`` with ``engine.tile`` on the chosen scheduler; write each; return the empty count.

    Parameters
    ----------
    engine : BlockEngine
    write : callable(result, col, row) -> bool
        Writes one window's result (always on the calling thread) and returns whether it was empty.
    windows : sequence of (col, row, width, height)
        Output windows, output pixels.
    threads : int
        Threads of the local path.
    progress : callable(done, total), optional
        Called with the windows done.
    scheduler : Scheduler, str or None
        See :func:`resolve_scheduler`.
    workdir : path
        Folder for the per-task block files (beside the output: on a cluster it must be a folder
        every worker can write and the caller can read).
    name : str
        Label of the tasks and threads.
    windows_per_task : int, optional
        Windows per Dask task (default: up to 4; with a ``raw_writer``, tasks of decreasing size,
        :func:`_guided_groups`; fewer on small jobs so every worker gets tasks).
    raw_writer : rectify.raster.io.TiledWriter, optional
        A writer in raw mode. Dask only (the local path calls ``write``): each window's result
        (``(data, valid, empty)`` or ``(data, empty)``) is compressed on the worker by
        ``raw_writer.encoder.encode_window`` and its bytes copied into the file by
        ``raw_writer.write_encoded``.

    Raises
    ------
    SchedulerError
        The cluster cannot be started or reached.
    RectifyError
        Whatever a task raised (re-raised here, after ``retries``).
    """
    sched = resolve_scheduler(scheduler)
    if sched.is_local_threads:
        return tilepool.run_tiles(engine.tile, write, list(windows), threads, progress, name=name)
    encoder = None
    if raw_writer is not None:
        encoder = raw_writer.encoder.encode_window

        def write_raw(encoded: tuple, c: int, r: int) -> bool:   # (tile, mask tile or None, empty)
            raw_writer.write_encoded(c, r, encoded)
            return bool(encoded[2])

        write = write_raw
    with _client(sched) as (client, address, ident):
        return _run_on_client(client, sched, engine, write, list(windows), progress, Path(workdir), name,
                              windows_per_task, encoder, address=address, slots=max(ident.total_threads, 1))


# --------------------------------------------------------------------------- clients
#: Dask settings of the local clusters this module starts (``processes[:N]``; a cluster given by address
#: keeps its own):
#:
#: - Dask sets MALLOC_TRIM_THRESHOLD_ in its workers, which turns off glibc's adaptive mmap threshold:
#:   every MB-sized array of a tile is then a fresh mmap, zeroed page by page (the orthophoto tiles ran
#:   1.6x slower). Memory is bounded by the tasks in flight anyway.
#: - The workers' statistical profiler (a sample every 10 ms, sent to the scheduler every second) and the
#:   event-loop and system monitors (every 20 ms and 500 ms) are turned off or slowed: on a small machine
#:   the scheduler and the monitors share the workers' cores (a 10 000 px warp on 2 workers: the driver
#:   process, which holds the scheduler, used 0.33-0.40 CPU s instead of 0.41-0.52).
LOCAL_CLUSTER_CONFIG: dict[str, Any] = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
}


#: Dask's loggers (in this process) whose lines the command line hides without -v
DASK_LOGGERS = ("distributed", "tornado", "bokeh")
_cli_logging = {"follow": False}


def follow_cli_logging() -> None:
    """Let Dask's log lines follow the command line's verbosity (called by ``--scheduler``'s option).

    Dask logs at INFO level by default, with its own handler, and some of its lines carry tracebacks
    (a stream closed by SIGTERM); a run's failures reach the user as one :class:`SchedulerError` line.
    So when a Dask scheduler is used and the root logger is above INFO (no -v), Dask's loggers are
    silenced here and in the worker processes of a local cluster; with -v they keep Dask's levels.
    Library callers' logging is left alone."""
    _cli_logging["follow"] = True


def _quiet_dask() -> bool:
    return _cli_logging["follow"] and logging.getLogger().getEffectiveLevel() > logging.INFO


def _distributed() -> Any:
    """The ``dask.distributed`` package, imported when a Dask scheduler is first used."""
    import distributed  # local: importing Dask takes about a second; the default (threads) never needs it

    if _quiet_dask():  # after the import: importing distributed sets its loggers' levels
        for name in DASK_LOGGERS:
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)

    return distributed


@contextlib.contextmanager
def _client(sched: Scheduler) -> Iterator[tuple[Any, str, SchedulerIdentity]]:
    """A ``distributed.Client`` for ``sched``, its scheduler's address and what the scheduler said of itself
    (a local cluster is started and closed around the run; a cluster's scheduler is checked first)."""
    try:
        distributed = _distributed()
    except ImportError as err:  # pragma: no cover - a declared dependency
        raise SchedulerError(f"scheduler {str(sched)!r} needs dask.distributed: {err}") from err
    if sched.kind == "processes":
        n = sched.workers or (os.cpu_count() or 1)
        t0 = time.perf_counter()
        try:
            import dask  # local: start-up time, as in _distributed

            config = dict(LOCAL_CLUSTER_CONFIG)
            if _quiet_dask():  # the workers' own log lines (read by Dask from the environment at start-up)
                config["distributed.nanny.pre-spawn-environ.DASK_LOGGING__DISTRIBUTED"] = "critical"
            with dask.config.set(config):
                cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                   dashboard_address=":0")
        except Exception as err:  # noqa: BLE001 - any start-up failure, one line
            raise SchedulerError(f"cannot start a local Dask cluster of {n} worker process(es): {err}") from err
        try:
            with distributed.Client(cluster) as client:
                ident = _wait_for_workers(sched, cluster.scheduler_address)
                logger.info("local Dask cluster of %d worker processes started in %.1f s%s", n,
                            time.perf_counter() - t0, _dashboard_note(client))
                yield client, cluster.scheduler_address, ident
        finally:
            cluster.close()
        return
    address = str(sched.address)
    # Dask's client would wait for a silent peer's handshake without limit, and size its first buffer from
    # whatever 8 bytes a peer sends: a Dask scheduler with a worker must answer the check first
    ident = _wait_for_workers(sched, address)
    try:
        client = distributed.Client(address, timeout=f"{sched.timeout_s}s")
    except (OSError, TimeoutError) as err:
        raise SchedulerError(f"cannot reach the Dask scheduler {address!r} within {sched.timeout_s:g} s "
                             f"(${TIMEOUT_ENV_VAR}): {_one_line(err)}") from err
    try:
        logger.info("connected to the Dask scheduler %s (%d workers, %d threads)%s", address, ident.n_workers,
                    ident.total_threads, _dashboard_note(client))
        yield client, address, ident
    finally:
        with contextlib.suppress(Exception):  # a scheduler gone or hung: closing gives up after the timeout
            client.close(timeout=sched.timeout_s)


def _has_dashboard() -> bool:
    return importlib.util.find_spec("bokeh") is not None


def _dashboard_note(client: Any) -> str:
    with contextlib.suppress(Exception):
        link = client.dashboard_link
        if link and _has_dashboard():
            return f"; dashboard {link}"
    return ""


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__


# --------------------------------------------------------------------------- the graph
def _groups(windows: list[Window], per_task: int) -> list[list[Window]]:
    return [windows[i:i + per_task] for i in range(0, len(windows), per_task)]


#: windows per task at most (encoded windows) and at least (the last tasks) in guided task sizes
GUIDED_MAX, GUIDED_MIN = 32, 2


def _guided_groups(windows: list[Window], slots: int) -> list[list[Window]]:
    """Tasks of decreasing size (guided self-scheduling): each takes 1/(2 slots) of the windows still
    unassigned, between :data:`GUIDED_MIN` and :data:`GUIDED_MAX`. Few tasks (each costs the scheduler
    and the driver a few ms of CPU, taken from the workers on a small machine) and a short tail (the
    last tasks are small, so the workers finish together)."""
    out, i, n = [], 0, len(windows)
    while i < n:
        k = min(GUIDED_MAX, max(GUIDED_MIN, (n - i) // (2 * max(slots, 1))))
        out.append(windows[i:i + k])
        i += k
    return out


def _run_on_client(client: Any, sched: Scheduler, engine: BlockEngine, write: Callable[[Any, int, int], bool],
                   windows: list[Window], progress: Callable[[int, int], None] | None, workdir: Path, name: str,
                   windows_per_task: int | None, encoder: Callable[[Any], Any] | None = None, *,
                   address: str, slots: int = 1) -> int:
    """Run the windows as Dask tasks; ``write`` receives each window's result (encoded when ``encoder``).

    ``address`` is the scheduler's (checked by :class:`_Watch` while no task finishes); ``slots`` the
    cluster's worker threads when the run starts."""
    total, done, n_empty = len(windows), 0, 0
    if progress:
        progress(0, total)
    if not windows:
        return 0
    if windows_per_task:
        groups = _groups(windows, windows_per_task)
    elif encoder is not None:
        # encoded windows are small (one decoded window at a time in a task): longer tasks, fewer round trips
        groups = _guided_groups(windows, slots)
    else:
        groups = _groups(windows, max(1, min(4, total // (4 * slots))))
    per_task = max(len(g) for g in groups)
    portable = engine.portable()
    merge = getattr(engine, "merge_stats", None)
    workdir.mkdir(parents=True, exist_ok=True)
    blockdir = Path(tempfile.mkdtemp(prefix=f".{name}-blocks.", dir=workdir))
    run_id = uuid.uuid4().hex[:8]
    max_inflight = 2 * slots + 2
    logger.info("%s: %d windows in %d Dask tasks of up to %d windows on %d worker thread(s) (%s)", name, total,
                len(groups), per_task, slots, sched)
    futures: dict[Any, int] = {}
    finished: queue.SimpleQueue[Any] = queue.SimpleQueue()  # futures as they finish (Dask's callback thread)
    it = iter(enumerate(groups))
    watch = _Watch(sched, address, name)

    def submit_next() -> None:
        nxt = next(it, None)
        if nxt is None:
            return
        i, group = nxt
        path = str((blockdir / f"block-{i:06d}.npz").resolve())
        fut = client.submit(_compute_block, portable, group, path, encoder, key=f"{name}-block-{run_id}-{i}",
                            retries=sched.retries, pure=False)
        futures[fut] = i
        fut.add_done_callback(finished.put)

    try:
        for _ in range(max_inflight):
            submit_next()
        while futures:
            try:
                fut = finished.get(timeout=watch.wait_s())
            except queue.Empty:
                watch.check(len(futures))
                continue
            watch.progressed()
            raise_if_terminated()  # SIGTERM's SystemExit dropped inside a Dask callback: stop here all the same
            i = futures.pop(fut)
            path, stats, index = _result(fut, sched)
            if merge is not None and stats is not None:
                merge(stats)
            results = _load_block(Path(path)) if index is None else _load_raw_block(Path(path), index)
            for (c, r, _w, _h), res in zip(groups[i], results, strict=True):
                n_empty += int(write(res, c, r))
                done += 1
                if progress:
                    progress(done, total)
            Path(path).unlink(missing_ok=True)
            fut.release()
            submit_next()
    except BaseException:
        with contextlib.suppress(Exception):  # queued to the scheduler; no wait for its answer
            client.cancel(list(futures))
        raise
    finally:
        shutil.rmtree(blockdir, ignore_errors=True)
    return n_empty


class _Watch:
    """The bounds of a run while no task finishes: workers present (``worker_timeout_s``), some task
    finishing (``stall_timeout_s``), the scheduler answering (its check's ``timeout_s``)."""

    def __init__(self, sched: Scheduler, address: str, name: str, clock: Callable[[], float] = time.monotonic):
        self.sched, self.address, self.name, self.clock = sched, address, name, clock
        self.last = clock()            # when a task last finished (or the run started)
        self.no_workers_since: float | None = None
        self.poll_s = min(POLL_S, sched.worker_timeout_s / 4, sched.stall_timeout_s / 4)

    def wait_s(self) -> float:
        """How long to wait for the next finished task before checking the cluster."""
        return max(self.poll_s, 0.01)

    def progressed(self) -> None:
        self.last = self.clock()
        self.no_workers_since = None

    def check(self, in_flight: int) -> None:
        """No task finished for a while: raise :class:`SchedulerError` past a bound."""
        now = self.clock()
        try:
            ident = identify_scheduler(self.address, self.sched.timeout_s, env_var=f"${TIMEOUT_ENV_VAR}")
        except SchedulerError as err:
            raise SchedulerError(f"{self.name}: lost the Dask scheduler {self.address!r} during the run: {err}") \
                from err
        if ident.n_workers > 0:
            self.no_workers_since = None
        else:
            self.no_workers_since = self.no_workers_since if self.no_workers_since is not None else now
            if now - self.no_workers_since >= self.sched.worker_timeout_s:
                raise SchedulerError(f"{self.name}: the Dask scheduler {self.address!r} has had no workers for "
                                     f"{self.sched.worker_timeout_s:g} s (${WORKER_TIMEOUT_ENV_VAR}); {in_flight} "
                                     "task(s) unfinished")
        if now - self.last >= self.sched.stall_timeout_s:
            raise SchedulerError(f"{self.name}: no Dask task finished for {self.sched.stall_timeout_s:g} s "
                                 f"(${STALL_TIMEOUT_ENV_VAR}) on the scheduler {self.address!r} "
                                 f"({ident.n_workers} worker(s)); {in_flight} task(s) unfinished")


def _result(fut: Any, sched: Scheduler) -> tuple[str, Any, Any]:
    """A task's result; Dask's own failures (a task whose workers kept dying, a lost scheduler) become
    :class:`SchedulerError`, the task's errors are re-raised as they are."""
    distributed = _distributed()
    try:
        path, stats, index = fut.result()
        return str(path), stats, index
    except (distributed.KilledWorker, asyncio.CancelledError, distributed.comm.CommClosedError) as err:
        raise SchedulerError(f"Dask scheduler {str(sched)!r} lost task {fut.key!r}: {_one_line(err)}") from err


def _compute_block(engine: BlockEngine, windows: list[Window], path: str,
                   encoder: Callable[[Any], Any] | None = None) -> tuple[str, Any, Any]:
    """One Dask task: compute ``windows`` with a private copy of ``engine`` (each result passed through
    ``encoder`` when given); write them to ``path``.

    Runs on a worker. Idempotent: the block is written to a unique temporary name and renamed.
    Returns the path, the engine's statistics and, for a raw block (encoded windows of bytes), its index.
    """
    bound_gdal_cache()
    _bound_opencv_threads()
    eng = copy.deepcopy(engine)  # a private copy: no statistics or open files shared with other tasks
    results = []
    try:
        for w in windows:  # encoded window by window: the task holds one decoded window at a time
            res = eng.tile(*w)
            results.append(res if encoder is None else encoder(res))
            del res
    finally:
        eng.close()
    stats_fn = getattr(eng, "stats", None)
    stats = stats_fn() if stats_fn is not None else None
    target = Path(path)
    tmp = target.with_name(f"{target.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    index = None
    try:
        if encoder is not None:
            index = _save_raw_block(tmp, results)
        else:
            _save_block(tmp, results)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return path, stats, index


def _bound_opencv_threads() -> None:
    """On a Dask worker, let OpenCV use as many threads as the worker has task slots.

    A worker of N threads holds N cores' worth of tasks; OpenCV's own thread pool (remap, warpAffine,
    ...) would otherwise spread every task over all the machine's cores, on top of the other workers.
    Dask's nanny sets ``OMP_NUM_THREADS`` and the BLAS counts to the same end; OpenCV reads none of them.
    """
    try:
        n = int(_distributed().get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):  # not on a worker
        return
    if n >= 1 and cv2.getNumThreads() != n:
        cv2.setNumThreads(n)


# --------------------------------------------------------------------------- block files
def _save_block(path: Path, results: list[Any]) -> None:
    """Results of windows (tuples of arrays, None and bools, or arrays) -> one ``.npz`` (no pickle)."""
    arrays: dict[str, np.ndarray] = {}
    for i, res in enumerate(results):
        items = res if isinstance(res, tuple) else (res,)
        kinds = []
        for k, v in enumerate(items):
            if v is None:
                kinds.append("n")
            elif isinstance(v, (bool, np.bool_)):
                kinds.append("b")
                arrays[f"w{i}_{k}"] = np.asarray(bool(v))
            else:
                kinds.append("a")
                arrays[f"w{i}_{k}"] = np.asarray(v)
        arrays[f"w{i}_kinds"] = np.asarray("".join(kinds) + ("t" if isinstance(res, tuple) else "s"))
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]  # numpy's stub types allow_pickle as **kwds


def _save_raw_block(path: Path, results: list[tuple]) -> list[list[tuple[str, int]]]:
    """Encoded windows (tuples of bytes, uint8 arrays, None, bools) -> their bytes end to end in one file.

    Returns the index that :func:`_load_raw_block` needs: per window, per item, ``("a", nbytes)``,
    ``("n", 0)`` (None) or ``("b", 0 or 1)``. The calling process reads the bytes back in one read,
    without decoding anything (no ``.npz`` parsing or checksums).
    """
    index: list[list[tuple[str, int]]] = []
    with open(path, "wb") as fh:
        for res in results:
            items: list[tuple[str, int]] = []
            for v in res:
                if v is None:
                    items.append(("n", 0))
                elif isinstance(v, (bool, np.bool_)):
                    items.append(("b", int(bool(v))))
                elif isinstance(v, bytes) or (isinstance(v, np.ndarray) and v.dtype == np.uint8):
                    b = memoryview(v).cast("B") if isinstance(v, bytes) else np.ascontiguousarray(v).data.cast("B")
                    fh.write(b)
                    items.append(("a", b.nbytes))
                else:
                    raise InvalidInputError(f"an encoded window holds bytes, uint8 arrays, None and bools; got "
                                            f"{type(v).__name__}")
            index.append(items)
    return index


def _load_raw_block(path: Path, index: list[list[tuple[str, int]]]) -> list[tuple]:
    """The windows of a raw block: uint8 arrays viewing the bytes read, None and bools."""
    buf = np.fromfile(path, dtype=np.uint8)
    out: list[tuple] = []
    pos = 0
    for items in index:
        vals: list[Any] = []
        for kind, n in items:
            if kind == "a":
                vals.append(buf[pos:pos + n])
                pos += n
            else:
                vals.append(None if kind == "n" else bool(n))
        out.append(tuple(vals))
    if pos != buf.size:
        raise SchedulerError(f"block file {str(path)!r} holds {buf.size} bytes; its task wrote {pos}")
    return out


def _load_block(path: Path) -> list[Any]:
    out: list[Any] = []
    with np.load(path, allow_pickle=False) as z:
        i = 0
        while f"w{i}_kinds" in z:
            kinds = str(z[f"w{i}_kinds"])
            items: list[Any] = []
            for k, kind in enumerate(kinds[:-1]):
                if kind == "n":
                    items.append(None)
                elif kind == "b":
                    items.append(bool(z[f"w{i}_{k}"]))
                else:
                    items.append(z[f"w{i}_{k}"])
            out.append(tuple(items) if kinds[-1] == "t" else items[0])
            i += 1
    return out
