"""Fixtures shared by several test modules."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

# Under pytest-xdist every core runs a test process: each gets one BLAS / OpenMP thread
# (set before any test module imports numpy; the volcal programs the tests start inherit
# it), or two processes each asking for every core make the dense algebra thrash.  A
# test that checks thread handling sets its own variables.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")


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
