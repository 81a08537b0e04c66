"""Signs of life for long stages, on stderr.

A library stays quiet unless asked: progress is off until :func:`enable` is called (the
command line does, unless ``-q``; a notebook user can too).  Two forms:

* :func:`stage` wraps a stage ("building the model", "solving", "plotting"): once it has
  run for a second, ``name ...`` (on a terminal completed in place with the duration at
  the end; when stderr is not a terminal, e.g. a log file or CI, a second plain line
  ``name: done in 1.2 s``).  Stages shorter than a second print nothing.
* :func:`update` reports a step inside a stage (a solver iteration with its cost, a search
  generation): on a terminal it rewrites the current line; otherwise at most one line per
  second.
* :func:`counter` counts the steps of a long loop (Monte Carlo trials, coverage
  experiments, order-selection fits) with the total, the rate and the time left: a tqdm
  bar on a terminal (a widget in Jupyter); otherwise plain lines ``desc: 40 of 200 trials
  (20 %), 0:12 elapsed, ETA 0:48`` at most every ``interval`` seconds and a last line with
  the total time, never a carriage return, so logs and CI stay readable.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

__all__ = [
    "enable",
    "enabled",
    "stage",
    "update",
    "counter",
    "Counter",
    "eta",
    "clock",
    "timings",
    "reset_timings",
    "record",
]

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
    _STATE.update(on=bool(on), stream=s, tty=bool(getattr(s, "isatty", lambda: False)()), last=0.0)


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
    outer, outer_shown = _STATE["stage"], _STATE.get("shown")
    _STATE["stage"] = name
    shown = threading.Event()

    def announce() -> None:
        shown.set()
        _STATE["shown"] = name
        _write(f"{name} ...\r" if _STATE["tty"] else f"{name} ...\n")

    timer = threading.Timer(after, announce)
    timer.daemon = True
    timer.start()
    ended = "done in"
    try:
        yield
    except BaseException:
        ended = "stopped after"  # an error or a signal: the stage did not finish
        raise
    finally:
        timer.cancel()
        _record(name, time.perf_counter() - t0)
        # back to the enclosing stage, shown as it was (its steps keep reporting)
        _STATE["stage"] = outer
        _STATE["shown"] = outer_shown
        if shown.is_set():
            dt = time.perf_counter() - t0
            _write(("\x1b[2K" if _STATE["tty"] else "") + f"{name}: {ended} {dt:.1f} s\n")


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


def clock(seconds: float) -> str:
    """A duration as ``m:ss`` (``h:mm:ss`` from an hour on)."""
    s = max(0, int(round(seconds)))
    h, rest = divmod(s, 3600)
    m, sec = divmod(rest, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def eta(done: float, total: float, elapsed: float) -> str:
    """The time left (``m:ss``) at the rate so far, ``?`` before the first step."""
    if done <= 0 or total <= 0:
        return "?"
    return clock(elapsed / done * max(total - done, 0))


class Counter:
    """A running count of a loop's steps (see :func:`counter`); ``update(n, note)``."""

    def __init__(
        self,
        total: int | None,
        desc: str,
        unit: str,
        initial: int,
        stream: TextIO,
        interval: float,
        bar: object | None,
    ):
        self.total, self.desc, self.unit = total, desc, unit
        self.n, self.initial = int(initial), int(initial)
        self.stream, self.interval, self.bar = stream, float(interval), bar
        self.t0 = time.monotonic()
        self.last = self.t0
        self.note = ""

    def _units(self, n: int) -> str:
        return self.unit if n == 1 or self.unit.endswith("s") else self.unit + "s"

    def line(self) -> str:
        """The plain-text state: ``desc: n of total units (p %), elapsed, ETA`` ."""
        dt = time.monotonic() - self.t0
        if self.total:
            text = (
                f"{self.desc}: {self.n} of {self.total} {self._units(self.total)} "
                f"({100.0 * self.n / self.total:.0f} %), {clock(dt)} elapsed, ETA "
                f"{eta(self.n - self.initial, self.total - self.initial, dt)}"
            )
        else:
            text = f"{self.desc}: {self.n} {self._units(self.n)}, {clock(dt)} elapsed"
        return text + (f" ({self.note})" if self.note else "")

    def update(self, n: int = 1, note: str | None = None) -> None:
        """``n`` more steps done; ``note``: a short state shown after the count."""
        self.n += int(n)
        if note is not None:
            self.note = note
        if self.bar is not None:
            if note is not None:
                self.bar.set_postfix_str(note, refresh=False)  # type: ignore[attr-defined]
            self.bar.update(n)  # type: ignore[attr-defined]
            return
        now = time.monotonic()
        if now - self.last >= self.interval:
            self.last = now
            self._write(self.line() + "\n")

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):
            pass

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()  # type: ignore[attr-defined]
            return
        if self.n > self.initial:
            dt = time.monotonic() - self.t0
            done = f"{self.n} of {self.total}" if self.total else f"{self.n}"
            units = self._units(self.total or self.n)
            self._write(f"{self.desc}: {done} {units} done in {clock(dt)}\n")


class _Off:
    """A counter that says nothing (progress off)."""

    def update(self, n: int = 1, note: str | None = None) -> None:
        pass

    def close(self) -> None:
        pass


def _in_notebook() -> bool:
    """Whether this process is a Jupyter kernel (not merely a process that imported
    ipykernel, as a test runner executing a notebook does)."""
    ipy = sys.modules.get("IPython")
    if ipy is None:
        return False
    try:
        shell = ipy.get_ipython()
    except Exception:  # an IPython too old or half-imported: no widget
        return False
    return shell is not None and type(shell).__name__ == "ZMQInteractiveShell"


@contextmanager
def counter(
    total: int | None,
    desc: str,
    unit: str,
    *,
    initial: int = 0,
    on: bool | None = None,
    interval: float = 5.0,
) -> Iterator[Counter | _Off]:
    """Count the ``total`` steps (None: unknown) of a loop named ``desc``, each one
    ``unit`` (singular: "trial"); ``initial`` steps done before (a resumed run); ``on``:
    report (default: whether :func:`enable` turned reports on); ``interval``: seconds
    between plain lines when the stream is not a terminal.  Yields an object with
    ``update(n=1, note=None)``.  On a terminal a tqdm bar, in Jupyter its widget,
    otherwise plain lines (see the module docstring)."""
    show = enabled() if on is None else bool(on)
    if not show:
        yield _Off()
        return
    stream = _STATE["stream"] or sys.stderr
    if getattr(stream, "closed", False):  # the stream of an earlier caller, gone since
        stream = sys.stderr
    try:
        tty = bool(getattr(stream, "isatty", lambda: False)())
    except (OSError, ValueError):
        tty = False
    bar = None
    notebook = _in_notebook()
    if notebook or tty:
        if notebook:
            from tqdm.auto import tqdm
        else:  # the plain terminal bar, whose import skips tqdm.auto's asyncio machinery
            from tqdm.std import tqdm
        bar = tqdm(total=total, desc=desc, unit=unit, initial=initial, leave=False, file=stream)
    c = Counter(total, desc, unit, initial, stream, interval, bar)
    try:
        yield c
    finally:
        c.close()
