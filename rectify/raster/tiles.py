"""Local tiled computation on threads, with locality: the engine of ``threads`` (the default scheduler).

:func:`run_tiles` computes output windows on ``threads`` worker threads and hands every result to a
``write`` callback on the calling thread (so writers need no lock). Each worker starts with its own
contiguous run of the windows (a band of output rows when the windows are in row-major order) and, when
its run is done, takes windows from the far end of the longest remaining run. A worker keeps its own
source reader (one GDAL dataset per thread), and GDAL's block cache is per dataset: neighbouring windows
on one thread reuse the source blocks that thread decoded, where a shared first-come queue made both
threads decode most blocks (a 10 000 x 10 000 x 3 warp decoded 15 % less with runs).

Memory is bounded: at most ``2 * threads + 1`` results are computed and not yet written. The first
error of a window stops the workers (each finishes the window it holds) and is re-raised; so is an
interruption of the calling thread (SIGTERM turned into SystemExit by the command line).
"""

from __future__ import annotations

import collections
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any

from rectify.atomic import raise_if_terminated

__all__ = ["run_tiles"]

Window = tuple[int, int, int, int]


def run_tiles(tile: Callable[..., Any], write: Callable[[Any, int, int], bool], windows: Sequence[Window],
              threads: int, progress: Callable[[int, int], None] | None, *, name: str = "tile") -> int:
    """Compute ``windows`` with ``tile`` on ``threads`` threads; write each result; return the empty count.

    Parameters
    ----------
    tile : callable(col, row, width, height) -> result
        Computes one output window (output pixels); called on a worker thread.
    write : callable(result, col, row) -> bool
        Writes one result on the calling thread and returns whether the window was empty.
    windows : sequence of (col, row, width, height)
        In the order that keeps neighbours together (row-major for a grid of tiles).
    threads : int
        Worker threads (at least 1; never more than there are windows).
    progress : callable(done, total), optional
        Called with the number of windows written.
    name : str
        Prefix of the worker threads' names.

    Returns
    -------
    int
        Windows whose ``write`` returned True (empty).
    """
    wins = list(windows)
    total, done, n_empty = len(wins), 0, 0
    if progress:
        progress(0, total)
    if not wins:
        return 0
    n = max(1, min(int(threads), total))
    bounds = [round(i * total / n) for i in range(n + 1)]
    runs = [collections.deque(wins[bounds[i]:bounds[i + 1]]) for i in range(n)]
    lock = threading.Lock()
    results: queue.Queue[tuple[str, Window | None, Any]] = queue.Queue()
    room = threading.Semaphore(2 * n + 1)
    stop = threading.Event()

    def take(i: int) -> Window | None:
        with lock:
            if runs[i]:
                return runs[i].popleft()
            j = max(range(n), key=lambda k: len(runs[k]))
            return runs[j].pop() if runs[j] else None

    def work(i: int) -> None:
        try:
            while not stop.is_set():
                win = take(i)
                if win is None:
                    return
                room.acquire()
                if stop.is_set():
                    return
                try:
                    res = tile(*win)
                except BaseException as err:  # noqa: BLE001 - handed to the calling thread, re-raised there
                    results.put(("error", win, err))
                    return
                results.put(("done", win, res))
        finally:
            results.put(("end", None, None))

    workers = [threading.Thread(target=work, args=(i,), name=f"{name}-{i}", daemon=True) for i in range(n)]
    for t in workers:
        t.start()
    ended = 0
    try:
        while ended < n:
            kind, win, res = results.get()
            raise_if_terminated()
            if kind == "end":
                ended += 1
            elif kind == "error":
                raise res
            else:
                assert win is not None
                n_empty += int(write(res, win[0], win[1]))
                room.release()
                done += 1
                if progress:
                    progress(done, total)
    finally:
        stop.set()
        for _ in range(n):      # wake workers waiting for room
            room.release()
        for t in workers:
            t.join()
    return n_empty
