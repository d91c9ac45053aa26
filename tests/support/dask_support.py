"""Dask test support: one local 2-worker process cluster and the warning filters its shutdown needs."""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

#: warnings dask.distributed may emit while workers start, stop or are killed
DASK_WARNING_FILTERS = [pytest.mark.filterwarnings("ignore::ResourceWarning"),
                        pytest.mark.filterwarnings("ignore:.*[Cc]lient.*:UserWarning"),
                        pytest.mark.filterwarnings("ignore:.*[Ww]orker.*:UserWarning"),
                        pytest.mark.filterwarnings("ignore:.*[Cc]omm.*:UserWarning")]


def local_cluster() -> Iterator[Any]:
    """A LocalCluster of 2 worker processes, 1 thread each; closed at the end (use as a module fixture:
    ``cluster = pytest.fixture(scope="module")(local_cluster)``)."""
    import distributed

    lc = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    try:
        yield lc
    finally:
        lc.close()


class FakeServer:
    """A TCP server on 127.0.0.1 that is not a Dask scheduler (a thread accepting connections).

    ``mode``: ``"silent"`` accepts and never reads or answers (a black hole); ``"http"`` reads the
    request and answers ``HTTP/1.1 400 Bad Request`` (any web server); ``"huge"`` sends 8 bytes that,
    read as a Dask message length, claim 2**63 bytes, then nothing; ``"not-handshake"`` sends a
    well-framed Dask message whose msgpack body is not a handshake (a list). Use as a context manager.
    """

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self._sock = socket.socket()
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(16)
        self._sock.settimeout(0.2)
        self.port = self._sock.getsockname()[1]
        self._conns: list[Any] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"fake-{mode}", daemon=True)
        self._thread.start()

    @property
    def address(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:  # the accept timeout (to see the stop event), or the socket closed
                continue
            self._conns.append(conn)
            try:
                if self.mode == "http":
                    conn.settimeout(2.0)
                    conn.recv(65536)
                    conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                elif self.mode == "huge":
                    conn.sendall(struct.pack("<Q", 2 ** 63))
                elif self.mode == "not-handshake":
                    body = b"\x93\x01\x02\x03"  # msgpack [1, 2, 3]
                    conn.sendall(struct.pack("<QQQ", 16 + len(body), 1, len(body)) + body)
            except OSError:
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for c in [*self._conns, self._sock]:
            try:
                c.close()
            except OSError:
                pass

    def __enter__(self) -> FakeServer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def closed_port() -> int:
    """A port of 127.0.0.1 with nothing listening (bound for a moment, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


REPO = Path(__file__).resolve().parents[2]


def start_worker(scheduler_address: str, *, timeout_s: float = 120.0) -> subprocess.Popen:
    """A ``dask worker`` process of one thread and no nanny (killed, it is not replaced), registered with
    the scheduler at ``scheduler_address`` before this returns; the repository is on its ``PYTHONPATH`` so
    that tasks can unpickle the project's (and the tests') classes. Stop it with :func:`stop_worker`."""
    import distributed

    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "PYTHONPATH": path, "DASK_LOGGING__DISTRIBUTED": "error"}
    proc = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", scheduler_address, "--no-nanny",
                             "--nthreads", "1", "--no-dashboard", "--death-timeout", "120"], env=env, cwd=str(REPO),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with distributed.Client(scheduler_address, timeout="30s", set_as_default=False) as client:
        deadline = time.monotonic() + timeout_s
        while proc.pid not in client.run(os.getpid).values():
            if proc.poll() is not None or time.monotonic() > deadline:
                stop_worker(proc)
                raise RuntimeError(f"the dask worker process {proc.pid} did not register within {timeout_s:g} s")
            time.sleep(0.1)
    return proc


def stop_worker(proc: subprocess.Popen) -> None:
    """Kill a worker of :func:`start_worker` (continued first if it was stopped) and reap it."""
    if proc.poll() is None:
        try:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
        except ProcessLookupError:
            pass
    proc.wait(timeout=30)
