"""Where Monte Carlo chunks run: in this process, in local worker processes, on Dask.

A *kernel* (anything picklable with a ``run_chunk(chunk)`` method) reaches every worker
once - inherited with the memory by local workers started with ``fork`` (with whatever it
has cached, nothing pickled), pickled through the pool's initializer with ``spawn``, or
``Client.scatter(..., broadcast=True)`` on Dask - and every task refers to it; nothing
large travels per chunk.  Workers run single-threaded BLAS (see
:mod:`volcal.base.threads`): faster here, and the same arithmetic in every process, so a
chunk gives bit-identical results wherever it runs.

:func:`run_chunks` yields ``(chunk, result)`` as chunks finish, in completion order.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from volcal.base.processes import signals_held_while_forking as _signals_held_while_forking
from volcal.base.processes import watch_parent as _watch_parent

__all__ = ["run_chunks", "default_workers"]

_KERNEL: Any = None
_CLAIMED: Any = None


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


def _init_worker(kernel: Any, parent: int | None = None, claimed: Any = None) -> None:
    """In a worker: the kernel, pickled (``spawn``) or the parent's object itself (``fork``:
    inherited with the parent's memory, its cached arrays included, nothing to unpickle),
    and the shared flags of the chunks taken."""
    global _KERNEL, _CLAIMED
    if parent is not None:
        _watch_parent(parent)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from volcal.base.threads import set_blas_threads

    set_blas_threads(1)
    _KERNEL = pickle.loads(kernel) if isinstance(kernel, bytes) else kernel
    _CLAIMED = claimed


def _claim(claimed: Any, i: int) -> bool:
    """Take chunk i (shared flags, with their lock): False if another process has."""
    with claimed.get_lock():
        if claimed[i]:
            return False
        claimed[i] = 1
        return True


def _run_local(i: int, chunk):
    # the workers take the chunks from the front, the parent from the back
    if _CLAIMED is not None and not _claim(_CLAIMED, i):
        return None
    return chunk, _KERNEL.run_chunk(chunk)


def _run_remote(kernel, chunk):
    # on a Dask worker: the scattered kernel arrives as the object itself
    from volcal.base.threads import set_blas_threads

    set_blas_threads(1)
    return chunk, kernel.run_chunk(chunk)


def run_chunks(
    kernel,
    chunks: Iterable,
    *,
    workers: int | None = None,
    scheduler: Any = None,
    on_start: Callable[[], None] | None = None,
) -> Iterator[tuple[Any, Any]]:
    """Run ``kernel.run_chunk`` on every chunk.

    scheduler: None (local), a Dask scheduler address (``"tcp://host:8786"``) or a
    ``distributed.Client``; workers: local worker processes (None: every core, this
    process's included - it computes chunks too; 1: this process only, no pool);
    on_start: called once the work is under way and this process will not fork again
    (local worker processes started), e.g. to start a thread of other work (a fork while
    another thread is inside a library can leave the child deadlocked)."""
    chunks = list(chunks)
    started = False

    def start() -> None:
        nonlocal started
        if on_start is not None and not started:
            started = True
            on_start()

    if not chunks:
        start()
        return
    if scheduler is not None:
        start()
        yield from _run_dask(kernel, chunks, scheduler)
        return
    # the default uses every core, this process's included; W workers are W processes
    # besides this one, which then only collects
    helps = workers is None
    n = default_workers() if workers is None else int(workers)
    if n <= 1 or len(chunks) == 1:
        from volcal.base.threads import blas_threads

        start()
        with blas_threads(1):
            for c in chunks:
                yield c, kernel.run_chunk(c)
        return
    yield from _run_pool(kernel, chunks, n - 1 if helps else n, helps, start)


def _run_pool(kernel, chunks: list, n: int, helps: bool, start: Callable[[], None]):
    """The chunks on ``n`` worker processes and, with ``helps``, this one.  Every chunk is
    queued for the workers, which take them from the front; this process takes them from
    the back between collecting results, and a chunk already taken is skipped.  So this
    process does not idle while the workers start (their first chunk pays for mapping the
    parent's memory), nothing it computes travels through a pipe, and the work balances
    itself whatever the load of the cores."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    from volcal.base.threads import blas_threads

    method = _start_method()
    ctx = mp.get_context(method)
    # fork: the children inherit the kernel (and what it has cached) with the memory
    shipped = kernel if method == "fork" else pickle.dumps(kernel, pickle.HIGHEST_PROTOCOL)
    claimed = ctx.Array("b", len(chunks), lock=True)
    # the children inherit the environment at spawn: single-threaded BLAS from the start
    old = os.environ.get("OPENBLAS_NUM_THREADS")
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    try:
        pool = ProcessPoolExecutor(
            max_workers=max(1, min(n, len(chunks) - 1 if helps else len(chunks))),
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(shipped, os.getpid(), claimed),
        )
    finally:
        if old is None:
            os.environ.pop("OPENBLAS_NUM_THREADS", None)
        else:
            os.environ["OPENBLAS_NUM_THREADS"] = old
    done = False
    try:
        # fork: the workers start with the first submit; an error or Ctrl-C stops them at
        # once (below), so they take the signals only once their handlers are set
        with _signals_held_while_forking():
            pending = {pool.submit(_run_local, i, c) for i, c in enumerate(chunks)}
        # fork: every worker started with the first submit; spawn: exec'd children
        start()

        def collect(block: bool):
            nonlocal pending
            if not pending:
                return
            finished, pending = wait(pending, 0 if not block else None, FIRST_COMPLETED)
            for f in finished:
                res = f.result()
                if res is not None:
                    yield res

        with blas_threads(1):
            for i in reversed(range(len(chunks)) if helps else ()):
                yield from collect(False)
                if not _claim(claimed, i):
                    break  # the workers have reached this one: they hold the rest
                yield chunks[i], kernel.run_chunk(chunks[i])
        while pending:
            yield from collect(True)
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
            # let the pool's manager thread finish closing its wake-up pipe now: at
            # interpreter exit concurrent.futures wakes every manager without its lock
            # (CPython 3.11) and, racing a manager that is closing, wrote to the closed
            # pipe ("OSError: Bad file descriptor" after "interrupted", seen in CI)
            manager = getattr(pool, "_executor_manager_thread", None)
            if manager is not None:
                manager.join(timeout=5)
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
