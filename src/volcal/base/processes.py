"""Processes: children that must not outlive their parent; returning freed memory; the
garbage collector paused while a command line program imports its libraries."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = [
    "watch_parent",
    "signals_held_while_forking",
    "return_freed_memory",
    "pause_gc",
    "resume_gc",
]


def watch_parent(parent: int) -> None:
    """In a child process (a Monte Carlo worker, the plotting process): end this process
    when its parent is gone (killed, even by SIGKILL); Ctrl-C is left to the parent."""
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
    # the signals the parent held while forking (signals_held_while_forking) are taken
    # now, with this process's own handlers
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="volcal-parent-watch", daemon=True).start()


@contextmanager
def signals_held_while_forking() -> Iterator[None]:
    """In the parent, around the start of children that call :func:`watch_parent`: Ctrl-C
    and SIGTERM held back (blocked in this thread; the children inherit the mask) until
    the block ends here and, in each child, until :func:`watch_parent` has set its
    handlers.  A forked child runs the parent's handlers until then: the command line's
    raises KeyboardInterrupt, which, raised inside multiprocessing's start-up code,
    escaped the child's bootstrap, and the child went on as a copy of the parent (a
    command that fails ends its plotting children right after forking them)."""
    import signal

    held = {signal.SIGINT, signal.SIGTERM}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def return_freed_memory() -> None:
    """Give the heap's freed pages back to the operating system (glibc's ``malloc_trim``;
    nothing elsewhere).  After a large computation the allocator keeps what was freed
    (the solver's work arrays, the tall Jacobian's copies: 25 MB at 10^4 readings) as
    resident memory; a command calls this before its next stage (``volcal identify``
    before writing and plotting, while the plotting processes draw) and takes 2 ms."""
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        pass


#: whether :func:`pause_gc` stopped the collector (and :func:`resume_gc` has not restarted it)
_GC_PAUSED = False


def pause_gc() -> bool:
    """Stop Python's cyclic garbage collector while a program starts: importing numpy,
    pandas, SciPy and CasADi allocates about a million objects, and the collections they
    trigger (about 200 for `volcal identify`, each walking the objects allocated since the
    last one, one walking them all) were 0.05 s of a 1.1 s run.  Only for the program
    itself (the command line run as ``volcal``), never inside a caller's process: resume
    with :func:`resume_gc` once the imports are done.  Returns whether it paused it (False
    when the collector was already off)."""
    import gc

    global _GC_PAUSED
    if not gc.isenabled():
        return False
    gc.disable()
    _GC_PAUSED = True
    return True


def resume_gc() -> None:
    """Restart the collector paused by :func:`pause_gc` (no-op otherwise), after moving the
    objects alive now (modules, classes, functions: they live as long as the program) to
    the permanent generation (``gc.freeze``), which later collections do not walk.  The
    few cycles that became garbage while paused (argparse's, the imports' own: about 1,500
    small objects for `volcal identify`, no arrays or tables) stay until exit: collecting
    them first would walk every object once more (0.08 s), the cost the pause avoids."""
    import gc

    global _GC_PAUSED
    if not _GC_PAUSED:
        return
    _GC_PAUSED = False
    gc.freeze()
    gc.enable()
