"""Dask test support: one local 2-worker process cluster and the warning filters its shutdown needs."""

from __future__ import annotations

from collections.abc import Iterator
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
