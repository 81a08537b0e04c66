"""Fixtures shared by several test modules."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``volcal demo`` run once as a user runs it (the installed program, a separate
    process with its plotting processes): the completed process and the folder it wrote.
    tests/test_cli_demo.py checks the run; tests/test_html_report.py reports on its
    identification (reading, never writing, inside it)."""
    exe = Path(sys.executable).parent / "volcal"
    out = tmp_path_factory.mktemp("demo") / "demo"
    run = subprocess.run(
        [str(exe), "demo", "--out", str(out)], capture_output=True, text=True, timeout=600
    )
    return run, out


@pytest.fixture(scope="session")
def dask_client():
    """One Dask LocalCluster (2 worker processes, 1 thread each) for every test that checks
    a run on Dask against the same run here: starting a cluster costs seconds, the results
    do not depend on which cluster computes them (each task carries its own seed). Skips
    the test when distributed is not installed."""
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client
