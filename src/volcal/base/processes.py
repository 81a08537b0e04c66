"""Processes: children that must not outlive their parent; returning freed memory."""

from __future__ import annotations

import os

__all__ = ["watch_parent", "return_freed_memory"]


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

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="volcal-parent-watch", daemon=True).start()


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
