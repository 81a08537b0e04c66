"""Where Monte Carlo chunks run: in this process, in local worker processes, on Dask.

A *kernel* (anything picklable with a ``run_chunk(chunk)`` method) is shipped once per
worker - through the process pool's initializer, or ``Client.scatter(..., broadcast=True)``
on Dask - and every task refers to it; nothing large travels per chunk.  Workers run
single-threaded BLAS (see :mod:`volcal.base.threads`): faster here, and the same
arithmetic in every process, so a chunk gives bit-identical results wherever it runs.

:func:`run_chunks` yields ``(chunk, result)`` as chunks finish, in completion order.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Iterable, Iterator
from typing import Any

__all__ = ["run_chunks", "default_workers"]

_KERNEL: Any = None


def default_workers() -> int:
    """Number of local worker processes by default: the usable CPU cores."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def _start_method() -> str:
    """``fork`` where available (no re-import of the user's main script, fast start; the
    children run numpy code only), else ``spawn``; ``VOLCAL_MP_START`` overrides."""
    import multiprocessing as mp

    env = os.environ.get("VOLCAL_MP_START")
    if env:
        return env
    return "fork" if "fork" in mp.get_all_start_methods() else "spawn"


def _watch_parent(parent: int) -> None:
    """In a worker: end this process when its parent is gone (killed, even by SIGKILL)."""
    import signal
    import threading
    import time

    # Ctrl-C reaches the whole process group: the parent handles it and stops the pool
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:  # Linux: the kernel sends SIGTERM when the parent exits
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except Exception:  # pragma: no cover - not Linux
        pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="volcal-parent-watch", daemon=True).start()


def _init_worker(blob: bytes, parent: int | None = None) -> None:
    global _KERNEL
    if parent is not None:
        _watch_parent(parent)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from volcal.base.threads import set_blas_threads

    set_blas_threads(1)
    _KERNEL = pickle.loads(blob)


def _run_local(chunk):
    return chunk, _KERNEL.run_chunk(chunk)


def _run_remote(kernel, chunk):
    # on a Dask worker: the scattered kernel arrives as the object itself
    from volcal.base.threads import set_blas_threads

    set_blas_threads(1)
    return chunk, kernel.run_chunk(chunk)


def run_chunks(
    kernel, chunks: Iterable, *, workers: int | None = None, scheduler: Any = None
) -> Iterator[tuple[Any, Any]]:
    """Run ``kernel.run_chunk`` on every chunk.

    scheduler: None (local), a Dask scheduler address (``"tcp://host:8786"``) or a
    ``distributed.Client``; workers: local worker processes (None: all cores; 1: in this
    process, no pool)."""
    chunks = list(chunks)
    if not chunks:
        return
    if scheduler is not None:
        yield from _run_dask(kernel, chunks, scheduler)
        return
    n = default_workers() if workers is None else int(workers)
    if n <= 1 or len(chunks) == 1:
        from volcal.base.threads import blas_threads

        with blas_threads(1):
            for c in chunks:
                yield c, kernel.run_chunk(c)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    blob = pickle.dumps(kernel, protocol=pickle.HIGHEST_PROTOCOL)
    ctx = mp.get_context(_start_method())
    # the children inherit the environment at spawn: single-threaded BLAS from the start
    old = os.environ.get("OPENBLAS_NUM_THREADS")
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    try:
        pool = ProcessPoolExecutor(
            max_workers=min(n, len(chunks)),
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(blob, os.getpid()),
        )
    finally:
        if old is None:
            os.environ.pop("OPENBLAS_NUM_THREADS", None)
        else:
            os.environ["OPENBLAS_NUM_THREADS"] = old
    done = False
    try:
        futs = [pool.submit(_run_local, c) for c in chunks]
        for f in as_completed(futs):
            yield f.result()
        done = True
    finally:
        if not done:
            # Ctrl-C, SIGTERM (raised as KeyboardInterrupt by the command line), an error or
            # an abandoned generator: stop the workers now, not after their running chunks
            procs = list((getattr(pool, "_processes", None) or {}).values())
            for proc in procs:
                if proc.is_alive():
                    proc.terminate()
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.join(timeout=5)
        else:
            pool.shutdown(wait=True, cancel_futures=True)


def _run_dask(kernel, chunks, scheduler):
    from distributed import Client, as_completed

    own = not isinstance(scheduler, Client)
    client = Client(scheduler) if own else scheduler
    try:
        kfut = client.scatter(kernel, broadcast=True, hash=False)
        futs = [client.submit(_run_remote, kfut, c, pure=False) for c in chunks]
        try:
            for f in as_completed(futs):
                yield f.result()
        finally:
            for f in futs:
                f.cancel()
            client.cancel(kfut)
    finally:
        if own:
            client.close()
