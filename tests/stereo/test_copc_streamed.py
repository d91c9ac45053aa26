"""The COPC octree of a cloud larger than ``COPC_BATCH``, built by batches in bounded memory (issue 27)."""

from __future__ import annotations

import os
import time

import laspy
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stereo.formats.cloud as cloud
from rectify.errors import RasterIOError
from stereo.formats.cloud import CloudChunk, write_cloud


def _check_nodes(P, centre, half, nodes):
    """Each point in exactly one node, inside the node's cube; every node's parent has points."""
    seen = np.concatenate([sel for _, sel in nodes])
    np.testing.assert_array_equal(np.sort(seen), np.arange(len(P)))
    keys = {k for k, _ in nodes}
    assert len(keys) == len(nodes)
    for (d, x, y, z), sel in nodes:
        assert len(sel)
        size = 2 * half / (1 << d)
        lo = centre - half + size * np.array([x, y, z])
        assert ((P[sel] >= lo - 1e-9) & (P[sel] <= lo + size + 1e-9)).all()
        if d:
            assert (d - 1, x // 2, y // 2, z // 2) in keys


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 3000), dup=st.integers(0, 2), batch=st.sampled_from([1, 7, 100, 1000]),
       seed=st.integers(0, 10**6))
def test_streamed_octree_properties(n, dup, batch, seed, tmp_path_factory):
    """Batches of every size (one point to the whole cloud), repeated points: a valid octree (the cube and
    the bounds of the build in one piece), the index file removed."""
    rng = np.random.default_rng(seed)
    P = rng.integers(-50_000, 50_000, (n, 3)).astype(np.int32)
    if dup:
        P[: n // 2] = P[0]
    old = cloud.COPC_BATCH, cloud.COPC_MAX_NODE, cloud.OCTREE_CHUNK
    cloud.COPC_BATCH, cloud.COPC_MAX_NODE, cloud.OCTREE_CHUNK = batch, 20, 64
    scratch = tmp_path_factory.mktemp("octree") / "stage.las"
    try:
        centre, half, lo, hi, it = cloud._octree_streamed(P[:, 0], P[:, 1], P[:, 2], scratch)
        nodes = list(it)
        c1, h1, one = cloud._octree(P[:, 0], P[:, 1], P[:, 2])
    finally:
        cloud.COPC_BATCH, cloud.COPC_MAX_NODE, cloud.OCTREE_CHUNK = old
    assert list(scratch.parent.iterdir()) == []
    np.testing.assert_array_equal(lo, P.min(axis=0))
    np.testing.assert_array_equal(hi, P.max(axis=0))
    assert np.array_equal(c1, centre) and h1 == half
    _check_nodes(P, centre, half, nodes)
    _check_nodes(P, c1, h1, one)


def test_streamed_copc_equals_the_points_and_answers_queries(tmp_path, monkeypatch):
    """A 40 000-point cloud written as COPC with batches of 3000 points (so about 14 batches): every point
    and extra value once, box queries exact, copclib reads it, no file left but the output."""
    if not cloud.copc_available():
        pytest.skip("copclib not installed")
    monkeypatch.setattr(cloud, "COPC_BATCH", 3000)
    monkeypatch.setattr(cloud, "COPC_MAX_NODE", 500)
    rng = np.random.default_rng(4)
    g = np.mgrid[0:200, 0:200].reshape(2, -1).T * 0.5
    xyz = np.column_stack([350_000 + g[:, 0], 5_800_000 + g[:, 1], 100 + 5 * np.sin(g[:, 0] / 7)])
    ids = np.arange(len(xyz), dtype=np.uint32)
    chunks = (CloudChunk(xyz[i:i + 7000], None, {"sigma_z": rng.random(len(xyz[i:i + 7000])),
                                                  "id": ids[i:i + 7000]})
              for i in range(0, len(xyz), 7000))
    out = write_cloud(tmp_path / "c.copc.laz", chunks, extra_dims=["sigma_z", cloud.ExtraDim("id", "uint32", "id")],
                      crs_wkt="EPSG:32633")
    assert [p.name for p in tmp_path.iterdir()] == ["c.copc.laz"]
    with laspy.CopcReader.open(out) as cr:
        allp = cr.query()
        np.testing.assert_array_equal(np.sort(np.asarray(allp["id"])), ids)
        assert 0 < len(cr.query(level=0)) < len(xyz)
        gx = np.round(xyz, 3)
        for lo, hi in [((350_010, 5_800_020), (350_030, 5_800_060)), ((350_000, 5_800_000), (350_099.5, 5_800_001))]:
            q = cr.query(laspy.copc.Bounds(np.array(lo, float), np.array(hi, float)))
            inside = (gx[:, 0] >= lo[0]) & (gx[:, 0] <= hi[0]) & (gx[:, 1] >= lo[1]) & (gx[:, 1] <= hi[1])
            np.testing.assert_array_equal(np.sort(np.asarray(q["id"])), np.flatnonzero(inside))
    r = cloud.copclib.FileReader(str(out))
    assert len(r.GetAllPoints()) == len(xyz)


def test_streamed_copc_index_file_on_a_full_disk(small_disk, monkeypatch):
    """The batch index file (8 bytes per point) does not fit: one line, nothing left on the disk."""
    if not cloud.copc_available():
        pytest.skip("copclib not installed")
    monkeypatch.setattr(cloud, "COPC_BATCH", 500)
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 100, (3000, 3))               # staging 3000 x 36 B = 108 KB; the index 24 KB more
    pad = small_disk / "pad"
    pad.write_bytes(b"\0" * (76 * 1024))    # 200 KiB: room for the staging file (27 pages), 4 pages left, not 6
    with pytest.raises(RasterIOError, match="no space left on device") as info:
        write_cloud(small_disk / "c.copc.laz", xyz)
    assert "\n" not in str(info.value)
    assert [p.name for p in small_disk.iterdir()] == ["pad"]


def test_interrupted_while_copclib_runs_leaves_nothing(tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM's SystemExit) while the parent waits for the copclib child: the child is stopped
    before the files are removed, so it cannot write the output or the batch index file afterwards."""
    if not cloud.copc_available():
        pytest.skip("copclib not installed")
    monkeypatch.setattr(cloud, "COPC_BATCH", 2000)
    real_fdopen = os.fdopen

    class Interrupted:
        def __init__(self, fd, *a, **k):
            self.fh = real_fdopen(fd, *a, **k)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

        def read(self):
            raise KeyboardInterrupt

    monkeypatch.setattr(cloud.os, "fdopen", Interrupted)
    xyz = np.random.default_rng(2).uniform(0, 500, (60_000, 3))
    with pytest.raises(KeyboardInterrupt):
        write_cloud(tmp_path / "c.copc.laz", xyz)
    time.sleep(1.0)   # a child left running would have written its files by now
    assert list(tmp_path.iterdir()) == []
