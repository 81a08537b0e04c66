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


def set_blas_threads(n: int | None = 1) -> None:
    """Limit BLAS to ``n`` threads for the rest of the process (None: leave as is)."""
    global _global_limiter
    if n is not None:
        _global_limiter = threadpool_limits(limits=int(n), user_api="blas")


@contextmanager
def blas_threads(n: int | None = 1) -> Iterator[None]:
    """Run a block with BLAS limited to ``n`` threads (None: unchanged), then restore."""
    if n is None:
        yield
        return
    with threadpool_limits(limits=int(n), user_api="blas"):
        yield
