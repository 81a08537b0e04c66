"""Thread count of the BLAS under numpy and scipy.

The dense problems of volcal are small (a QR of 20,000 x 130, SVDs of a few hundred
columns).  On the project's 2-core machine a multi-threaded OpenBLAS spent 2 s on a QR
that takes 0.065 s on one thread when the other core was busy, and Monte Carlo workers in
separate processes would fight over the cores anyway.  volcal therefore runs its numerics
with one BLAS thread: the command line for the whole process, the library inside
:func:`blas_threads` blocks around its heavy work.  Implemented with ``threadpoolctl``.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

_global_limiter = None
_casadi_blas: bool | None = None


def _casadi_openblas() -> None:
    """Bring CasADi's own OpenBLAS under the limits (once per process).

    CasADi's wheels bundle an OpenBLAS (``libcasadi-tp-openblas``, used by IPOPT's MUMPS)
    whose file name threadpoolctl does not recognise, and which is loaded only with the
    IPOPT plugin: left alone it runs on every core.  It is registered with threadpoolctl
    and loaded now, so that the limits below hold for IPOPT as well.  Besides the speed,
    this makes a ``fork`` safe while IPOPT runs in another thread: OpenBLAS stops its
    worker threads at a fork, which leaves a threaded call waiting for them forever."""
    global _casadi_blas
    if _casadi_blas is not None:
        return
    _casadi_blas = False
    try:
        import ctypes
        import importlib.util
        from pathlib import Path

        from threadpoolctl import OpenBLASController, register

        spec = importlib.util.find_spec("casadi")
        if spec is None or not spec.submodule_search_locations:
            return
        libs = sorted(Path(spec.submodule_search_locations[0]).glob("libcasadi-tp-openblas.so*"))
        if not libs:
            return

        class CasadiOpenBLASController(OpenBLASController):
            filename_prefixes = ("libcasadi-tp-openblas",)

        register(CasadiOpenBLASController)
        ctypes.CDLL(str(libs[0]))
        _casadi_blas = True
    except Exception:  # pragma: no cover - another CasADi build or an old threadpoolctl
        return


def set_blas_threads(n: int | None = 1) -> None:
    """Limit BLAS to ``n`` threads for the rest of the process (None: leave as is): the
    libraries loaded already (threadpoolctl limits those; CasADi's is loaded here) and
    those loaded later through the environment they read when they load: numpy's and
    SciPy's OpenBLAS, which come with their first import, after this call (numpy is not
    imported here: a bad input is reported before it, 0.1 s sooner).  Left alone SciPy's
    ran on every core, and the row-block QRs of a plan's null-space check took 4-5 s
    instead of 0.1 s on a busy 2-core machine."""
    global _global_limiter
    if n is not None:
        import os

        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(int(n))
        _casadi_openblas()
        _global_limiter = threadpool_limits(limits=int(n), user_api="blas")


@contextmanager
def blas_threads(n: int | None = 1) -> Iterator[None]:
    """Run a block with BLAS limited to ``n`` threads (None: unchanged), then restore."""
    if n is None:
        yield
        return
    _casadi_openblas()
    with threadpool_limits(limits=int(n), user_api="blas"):
        yield
