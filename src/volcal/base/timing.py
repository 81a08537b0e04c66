"""Wall-clock time per stage of a command (``volcal mc -v`` prints them).

:class:`Stages` accumulates the seconds of named stages in the order they first ran;
:func:`process_seconds` is the age of this process (interpreter start-up included), so
that a command can report what ran before its own code.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Stages", "process_seconds"]


class Stages:
    """Seconds per named stage (a stage entered twice adds up)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)

    def table(self, total: float | None = None) -> str:
        """The stages as aligned text lines (and the total, when given)."""
        width = max([len(k) for k in self.seconds] + [5])
        lines = [f"  {k:<{width}}  {v:7.3f} s" for k, v in self.seconds.items()]
        if total is not None:
            lines.append(f"  {'total':<{width}}  {total:7.3f} s")
        return "\n".join(lines)


def process_seconds() -> float | None:
    """Seconds since this process started (Linux: from /proc, 10 ms resolution), or None
    where unknown."""
    try:
        with open("/proc/self/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        with open("/proc/uptime") as fh:
            uptime = float(fh.read().split()[0])
        return max(0.0, uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):  # pragma: no cover - not Linux
        return None
