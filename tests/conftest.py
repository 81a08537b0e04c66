"""Fixtures shared by several test modules."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def dask_client():
    """One Dask LocalCluster (2 worker processes, 1 thread each) for every test that checks
    a run on Dask against the same run here: starting a cluster costs seconds, the results
    do not depend on which cluster computes them (each task carries its own seed). Skips
    the test when distributed is not installed."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        yield client
