"""rectify.raster.tiles.run_tiles: every window written once on the calling thread, runs of neighbours per
thread, bounded results in flight, the first error stops the work and is re-raised."""

from __future__ import annotations

import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.raster.tiles import run_tiles


def _grid(nx: int, ny: int, t: int = 16):
    return [(c * t, r * t, t, t) for r in range(ny) for c in range(nx)]


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 60), threads=st.integers(1, 5))
def test_every_window_is_written_once_on_the_calling_thread(n, threads):
    wins = [(i, 2 * i, 1, 1) for i in range(n)]
    main = threading.current_thread()
    written, ticks = [], []

    def tile(c, r, w, h):
        return (c, r, c % 3 == 0)

    def write(res, c, r):
        assert threading.current_thread() is main
        assert res[:2] == (c, r)
        written.append((c, r))
        return res[2]

    empty = run_tiles(tile, write, wins, threads, lambda d, t: ticks.append((d, t)))
    assert sorted(written) == sorted((c, r) for c, r, _, _ in wins)
    assert empty == sum(1 for c, *_ in wins if c % 3 == 0)
    assert ticks[0] == (0, n) and ticks[-1] == (n, n) and len(ticks) == n + 1


def test_each_thread_starts_on_its_own_run_of_neighbours():
    wins = _grid(8, 8)
    seen: dict[str, list[int]] = {}
    lock = threading.Lock()

    def tile(c, r, w, h):
        time.sleep(0.001)
        with lock:
            seen.setdefault(threading.current_thread().name, []).append(r // 16)
        return False

    run_tiles(tile, lambda res, c, r: res, wins, 2, None, name="t")
    assert sorted(seen) == ["t-0", "t-1"]
    # thread 0 begins at the top rows, thread 1 at the bottom half (rows 4..7), not interleaved
    assert seen["t-0"][:8] == [0] * 8
    assert seen["t-1"][:8] == [4] * 8


def test_results_in_flight_are_bounded():
    gate = threading.Event()
    computed = []

    def tile(c, r, w, h):
        computed.append(c)
        return False

    def write(res, c, r):
        if not gate.is_set():
            time.sleep(0.2)           # a slow writer: the workers must wait for room
            assert len(computed) <= 2 * 2 + 1 + 1
            gate.set()
        return res

    run_tiles(tile, write, [(i, 0, 1, 1) for i in range(50)], 2, None)
    assert len(computed) == 50


def test_first_error_is_reraised_and_stops_the_workers():
    calls = []

    def tile(c, r, w, h):
        calls.append(c)
        if c == 5:
            raise ValueError("bad window 5")
        time.sleep(0.002)
        return False

    with pytest.raises(ValueError, match="bad window 5"):
        run_tiles(tile, lambda res, c, r: res, [(i, 0, 1, 1) for i in range(400)], 2, None)
    assert len(calls) < 400
    assert not [t for t in threading.enumerate() if t.name.startswith("tile-")]   # workers joined


def test_error_in_write_stops_the_workers():
    def write(res, c, r):
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        run_tiles(lambda c, r, w, h: False, write, [(i, 0, 1, 1) for i in range(100)], 3, None)
    assert not [t for t in threading.enumerate() if t.name.startswith("tile-")]
