"""Signs of life for long stages, on stderr.

A library stays quiet unless asked: progress is off until :func:`enable` is called (the
command line does, unless ``-q``; a notebook user can too).  Two forms:

* :func:`stage` wraps a stage ("building the model", "solving", "plotting"): once it has
  run for a second, ``name ...`` (on a terminal completed in place with the duration at
  the end; when stderr is not a terminal, e.g. a log file or CI, a second plain line
  ``name: done in 1.2 s``).  Stages shorter than a second print nothing.
* :func:`update` reports a step inside a stage (a solver iteration with its cost, a search
  generation): on a terminal it rewrites the current line; otherwise at most one line per
  second.  Long loops with a known count use tqdm (Monte Carlo trials).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

__all__ = ["enable", "enabled", "stage", "update", "timings", "reset_timings", "record"]

#: seconds per stage name of this process (kept whether or not reports are on), for the
#: result's record and the benchmarks; a name's parenthesised detail is left out
_TIMINGS: dict[str, float] = {}


def timings() -> dict[str, float]:
    """Seconds spent in each stage of this process so far, in the order first entered."""
    return dict(_TIMINGS)


def reset_timings() -> None:
    _TIMINGS.clear()


def _record(name: str, seconds: float) -> None:
    key = name.split(" (")[0]
    _TIMINGS[key] = _TIMINGS.get(key, 0.0) + seconds


def record(name: str, seconds: float) -> None:
    """Add ``seconds`` (s) to the stage ``name`` of this process's record: a stage a
    command ran before the computation that starts a new record (:func:`reset_timings`)."""
    _record(name, seconds)


_STATE: dict = {"on": False, "stream": None, "tty": False, "last": 0.0, "stage": None}


def enable(on: bool = True, stream: TextIO | None = None) -> None:
    """Turn progress reports on (or off) for this process; ``stream`` default stderr."""
    s = stream or sys.stderr
    _STATE.update(on=bool(on), stream=s, tty=bool(getattr(s, "isatty", lambda: False)()))


def enabled() -> bool:
    return bool(_STATE["on"])


def _write(text: str) -> None:
    s = _STATE["stream"] or sys.stderr
    try:
        s.write(text)
        s.flush()
    except (OSError, ValueError):  # a closed pipe must not stop the computation
        pass


@contextmanager
def stage(name: str, after: float = 1.0) -> Iterator[None]:
    """Report the stage ``name`` when it lasts longer than ``after`` seconds: its name once
    that time has passed, then its duration when it ends (see the module docstring).
    Shorter stages print nothing, so quick runs stay quiet."""
    t0 = time.perf_counter()
    if not _STATE["on"]:
        try:
            yield
        finally:
            _record(name, time.perf_counter() - t0)
        return
    outer = _STATE["stage"]
    _STATE["stage"] = name
    shown = threading.Event()

    def announce() -> None:
        shown.set()
        _STATE["shown"] = name
        _write(f"{name} ...\r" if _STATE["tty"] else f"{name} ...\n")

    timer = threading.Timer(after, announce)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        _record(name, time.perf_counter() - t0)
        _STATE["stage"] = outer
        _STATE["shown"] = None
        if shown.is_set():
            dt = time.perf_counter() - t0
            _write(("\x1b[2K" if _STATE["tty"] else "") + f"{name}: done in {dt:.1f} s\n")


def update(message: str) -> None:
    """A step inside the current stage (see the module docstring)."""
    if not _STATE["on"]:
        return
    name = _STATE["stage"] or "volcal"
    now = time.monotonic()
    if _STATE["tty"] and _STATE.get("shown") == name:
        _write(f"\x1b[2K{name}: {message}\r")
    elif _STATE.get("shown") == name and now - _STATE["last"] >= 1.0:
        _STATE["last"] = now
        _write(f"{name}: {message}\n")
