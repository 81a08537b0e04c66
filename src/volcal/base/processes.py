"""Child processes that must not outlive their parent."""

from __future__ import annotations

import os

__all__ = ["watch_parent"]


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
