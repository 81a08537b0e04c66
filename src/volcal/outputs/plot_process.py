"""Processes that draw PNG plots while the parent computes (``volcal identify``, ``volcal mc``).

Matplotlib costs a third of a second to import and its drawing is pure Python: on the
critical path of a short run it is most of the time.  :class:`PlotProcess` forks a child
at the start of a command, before the parent imports the numerics; it imports matplotlib
and writes a throw-away line of text (the font, the PNG writer) on the other core
while the parent reads, solves and writes, then forks the other plotting children from its
warmed-up self (one import of matplotlib, not one per child).  The parent then sends
``(function, args)`` requests: the function is a module-level drawing function (pickled by
its name) and the arguments are plain data (numpy arrays, numbers, strings, paths), so a
child never imports pandas, scipy or the solver.  With two children the figures of one
result are drawn two at a time.  Until its first request, a child makes the calls it is
given ``ahead`` (:func:`volcal.outputs.figures.frame_plan`: the frames of the figures it
will draw, a fifth of their drawing time, built while it would otherwise wait).

The parent waits for every figure before it renames its result folder into place, so the
folder stays all-or-nothing.  Fork only (Linux); :meth:`PlotProcess.start` returns None
elsewhere and the caller draws in its own process.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

__all__ = ["PlotProcess", "plotting", "warm_up"]

#: a call a plotting child makes: a module-level function and plain-data arguments
Request = tuple[Callable[..., Any], tuple]


def warm_up() -> None:
    """Import matplotlib's Agg canvas and write one line of text into a tiny PNG in
    memory (:func:`volcal.outputs.figures.save`): the font file, the text layout and the
    PNG writer (Pillow) are loaded once, in the first plotting child, for all of them.  A
    warm-up figure with every kind of artist the plots use cost 0.1 s of the plotting
    children's time and saved no more than that in the figures drawn after it."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from volcal.outputs.figures import save

    fig = Figure(figsize=(1.0, 0.5))
    FigureCanvasAgg(fig)
    fig.text(0.5, 0.5, "error (µm) −1.5", fontsize=9, ha="center")
    save(fig, io.BytesIO(), dpi=20)  # as the figures are written (hinting, PNG level)


def _without_setter_docs() -> None:  # pragma: no cover - runs in a child
    """Before matplotlib's import in a plotting child: its artists' ``set`` docstrings are
    not written.  Matplotlib builds them as it defines each artist class (every setter's
    docstring parsed for its accepted values, :func:`matplotlib.artist.kwdoc`): a
    quarter of its import (0.1 of 0.4 s of processor here), for text that a child that
    only draws never reads.  Only ``Artist``'s own is built; the drawing is the same (PNGs
    byte for byte).  Nothing is done where matplotlib is imported already (inherited
    from the parent), and in the parent never: its docstrings stay whole."""
    import sys

    if "matplotlib.artist" in sys.modules:
        return
    try:
        import matplotlib.artist
    except Exception:  # reported with the first figure
        return
    matplotlib.artist.kwdoc = lambda artist: ""


class _FontTables:
    """An FT2Font whose SFNT tables (:meth:`get_sfnt_table`) are read once: the rest is
    the font's own."""

    def __init__(self, font) -> None:
        self._font = font
        self._tables: dict = {}

    def get_sfnt_table(self, name):
        try:
            return self._tables[name]
        except KeyError:
            table = self._tables[name] = self._font.get_sfnt_table(name)
            return table

    def __getattr__(self, name):
        return getattr(self._font, name)


def _font_lookups_cached() -> None:  # pragma: no cover - runs in a child
    """In a plotting child: the font's line metrics that matplotlib 3.11 reads for every
    text it lays out, two tables of the font file (``OS/2``, ``head``) made into new
    dicts each time (30 µs; 1,400 times for the five figures of a result at 10^4
    readings, 0.04 s of the children's processor time), are read once per font, and
    the font files of a text's properties are looked up once per properties.  The
    values, so the layout and the picture, are the same (PNGs byte for byte).  Other
    versions of matplotlib are left as they are."""
    try:
        import matplotlib
        import matplotlib.font_manager
        import matplotlib.text as mtext
    except Exception:  # reported with the first figure
        return
    # the version whose text layout this was checked against (the font it gets is used
    # for its tables only); another keeps matplotlib's own
    get_font = getattr(mtext, "get_font", None)
    if get_font is None or not matplotlib.__version__.startswith("3.11."):
        return
    wrapped: dict[int, _FontTables] = {}

    def font_with_tables_read_once(*args, **kwargs):
        font = get_font(*args, **kwargs)
        w = wrapped.get(id(font))
        if w is None or w._font is not font:
            w = wrapped[id(font)] = _FontTables(font)
        return w

    # the name text.py's layout gets the font by (for its tables only)
    mtext.get_font = font_with_tables_read_once  # type: ignore[attr-defined]
    # the font files of a text's properties: looked up once per properties (matplotlib
    # builds a key of six rcParams lists for its own cache at every look-up, 25 µs, for
    # every text laid out and drawn: 0.03 s); the child changes no font setting
    manager = matplotlib.font_manager.fontManager
    find = manager._find_fonts_by_props
    found: dict = {}

    def font_files(prop, *args, **kwargs):
        if args or kwargs:
            return find(prop, *args, **kwargs)
        try:
            return found[prop]
        except KeyError:
            files = found[prop.copy()] = find(prop)
            return files

    manager._find_fonts_by_props = font_files  # type: ignore[method-assign]  # this instance


def _serve_requests(conn, ahead: Sequence[Request] = ()) -> None:  # pragma: no cover - child
    """Draw on request, ``(function, args)`` -> ``("ok" | "error", text)``, until None;
    after each answer, the figure's garbage is collected (the collector is off while
    drawing: 6 ms here instead of a quarter of the drawing time, and 15-20 MB less).
    Until the first request comes, the calls ``ahead`` are made one at a time (frames of
    the figures this child is expected to draw; a failure there is ignored: the drawing
    function then builds its own)."""
    import gc
    import traceback

    def idle() -> bool:  # no request waiting (a closed pipe ends the loop below)
        try:
            return not conn.poll()
        except (EOFError, OSError):
            return False

    todo = list(ahead)
    while todo and idle():
        func, args = todo.pop(0)
        try:
            func(*args)
        except Exception:
            pass
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        func, args = msg
        try:
            func(*args)
            conn.send(("ok", ""))
        except Exception:
            conn.send(("error", traceback.format_exc()))
        gc.collect()


def _zygote(  # pragma: no cover - runs in a child
    conns: list,
    parent: int,
    warm: tuple[Callable[[], None], ...],
    ahead: Sequence[Sequence[Request]] = (),
) -> None:
    """The first plotting child: warm up (while the parent computes), then fork the other
    plotting children from its warmed-up self (matplotlib imported once, its pages
    shared copy-on-write), and serve ``conns[0]`` while they serve the others; child ``i``
    makes the calls ``ahead[i]`` while it waits for its first request."""
    ahead = list(ahead) + [()] * (len(conns) - len(ahead))
    from volcal.base.processes import watch_parent

    watch_parent(parent)  # its handlers, then the signals held while forking (start)
    # below the parent while both compute: the parent's reading and solving is the
    # critical path, the warm-up only has to end before the first figure is asked for (the
    # same time within 1 % as at the parent's priority, whole runs paired under a load of
    # 3; volcal plan's and volcal mc's workers keep both cores busy meanwhile)
    try:
        os.nice(10)
    except OSError:  # pragma: no cover
        pass
    _without_setter_docs()
    _font_lookups_cached()
    for w in warm:
        try:
            w()
        except Exception:  # a real failure is reported with the first request
            pass
    # no cyclic garbage collection while drawing: matplotlib allocates tens of thousands
    # of objects per figure and the collector's passes cost a quarter of the drawing
    # time; a child draws a handful of figures and exits.  Everything alive now is frozen
    # (the collections after each figure walk that figure's objects only), without a
    # collection first: it walked every object inherited from the parent and matplotlib's
    # (0.1 s, with the first figure often already waiting) to free the warm-up figure's
    # few cycles
    import gc

    gc.freeze()
    gc.disable()
    kids = []
    for i in range(1, len(conns)):
        pid = os.fork()
        if pid == 0:  # another plotting child, ending with this one (PR_SET_PDEATHSIG)
            code = 0
            try:
                watch_parent(os.getppid())
                for k, c in enumerate(conns):
                    if k != i:
                        c.close()
                _serve_requests(conns[i], ahead[i])
            except BaseException:
                code = 1
            finally:
                os._exit(code)
        kids.append(pid)
        conns[i].close()
    try:
        _serve_requests(conns[0], ahead[0])
    finally:
        for pid in kids:
            try:
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass


class _Sender:
    """Sends requests to one plotting child from a thread: a request larger than the pipe's
    buffer would otherwise block this process until the child, maybe still importing
    matplotlib, reads it."""

    def __init__(self, conn) -> None:
        import queue
        import threading

        self.conn = conn
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self.error: BaseException | None = None
        self._t = threading.Thread(target=self._run, name="volcal-plot-sender", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while True:
            msg = self._q.get()
            try:
                self.conn.send(msg)
            except BaseException as exc:  # reported by PlotProcess.wait
                self.error = exc
            if msg is None:
                return

    def send(self, msg) -> None:
        self._q.put(msg)

    def close(self, timeout: float) -> None:
        self._q.put(None)
        self._t.join(timeout)


class PlotProcess:
    """Children (``fork``) that import matplotlib now and draw figures later.

    ``draw(func, *args)`` sends a request to the child with the least work queued
    (``cost``: the caller's estimate, any unit); :meth:`wait` returns when every figure
    asked for is written.  Use :meth:`start`, which returns None where fork is not safe.
    """

    def __init__(self, proc, conns: list) -> None:
        self._proc, self._conns = proc, conns
        # the sending threads start with the first request: a command that forks worker
        # processes meanwhile (volcal mc) then forks while this process has one thread
        self._senders: list[_Sender] = []
        self._pending = [0] * len(conns)
        self._queued = [0.0] * len(conns)

    @classmethod
    def start(
        cls,
        workers: int = 1,
        warm: tuple[Callable[[], None], ...] = (warm_up,),
        ahead: Callable[[int], Sequence[Sequence[Request]]] | None = None,
    ) -> PlotProcess | None:
        """Start ``workers`` plotting children (at least one; at most one per core): the
        first forks now and runs ``warm``, then forks the others.  ``ahead``: given the
        number of children, the calls each makes while it waits for its first request
        (:func:`volcal.outputs.figures.frame_plan`: the frames of the figures
        :meth:`draw` will send it).  None but on Linux."""
        import multiprocessing as mp
        import sys

        # fork is safe on Linux only (macOS frameworks are not fork-safe)
        if not sys.platform.startswith("linux") or "fork" not in mp.get_all_start_methods():
            return None
        workers = max(1, min(int(workers), os.cpu_count() or 1))
        ctx = mp.get_context("fork")
        pairs = [ctx.Pipe() for _ in range(workers)]
        plan = [list(a) for a in ahead(workers)] if ahead is not None else []
        proc = ctx.Process(
            target=_zygote,
            args=([there for _, there in pairs], os.getpid(), tuple(warm), plan),
            name="volcal-plots",
            daemon=True,
        )
        # a failing command ends its plotting children right after the fork: the child
        # takes Ctrl-C and SIGTERM only once _zygote has set its own handlers
        from volcal.base.processes import signals_held_while_forking

        with signals_held_while_forking():
            proc.start()
        for _, there in pairs:
            there.close()
        return cls(proc, [here for here, _ in pairs])

    @property
    def workers(self) -> int:
        return len(self._conns)

    def draw(
        self, func: Callable[..., Any], *args: Any, cost: float = 1.0, child: int | None = None
    ) -> int:
        """Ask for ``func(*args)`` (a module-level function; plain-data arguments) from
        the child with the least drawing queued, or from ``child``; returns which child
        (a figure it keeps in memory is written by a later request to it)."""
        if not self._senders:
            self._senders = [_Sender(c) for c in self._conns]
        i = min(range(len(self._conns)), key=lambda k: self._queued[k]) if child is None else child
        self._senders[i].send((func, args))
        self._pending[i] += 1
        self._queued[i] += cost
        return i

    def wait(self, timeout: float = 600.0) -> None:
        """Wait for every figure asked for; a failed figure, or none for ``timeout``
        seconds, raises RuntimeError."""
        from multiprocessing.connection import wait as wait_any

        errors: list[str] = []
        while any(self._pending):
            for snd in self._senders:
                error = snd.error  # read once: the sending thread may set it meanwhile
                if isinstance(error, (BrokenPipeError, ConnectionResetError, EOFError)):
                    # the child is gone (a figure sent to it after it died)
                    raise RuntimeError(
                        f"the plotting process ended unexpectedly (a plot request could "
                        f"not be sent: {error})"
                    )
                if error is not None:
                    raise RuntimeError(f"could not send a plot request: {error}")
            busy = [c for c, n in zip(self._conns, self._pending) if n]
            ready = wait_any(busy, timeout)
            if not ready:
                raise RuntimeError(f"no plot from the plotting process in {timeout:g} s")
            for c in ready:
                i = self._conns.index(c)  # one of ours: a Connection
                try:
                    status, text = self._conns[i].recv()
                except (EOFError, OSError):
                    raise RuntimeError("the plotting process ended unexpectedly") from None
                self._pending[i] -= 1
                if status != "ok":
                    errors.append(text)
        self._queued = [0.0] * len(self._conns)
        if errors:
            raise RuntimeError("plotting failed:\n" + "\n".join(errors))

    def close(self, abort: bool = False) -> None:
        """End the plotting children: after their figures, or at once on an error or when
        ``abort`` (the command failed: a child still importing matplotlib is not waited
        for)."""
        for snd in self._senders:
            snd.close(timeout=0.0 if abort else 2.0)
        for c in self._conns:
            c.close()
        busy = abort or any(self._pending)
        self._proc.join(timeout=2.0 if not busy else 0.0)
        if self._proc.is_alive():  # the others end with it (PR_SET_PDEATHSIG)
            self._proc.terminate()
            self._proc.join(timeout=2.0)


@contextmanager
def plotting(
    enabled: bool = True,
    workers: int = 2,
    warm: tuple[Callable[[], None], ...] = (warm_up,),
    ahead: Callable[[int], Sequence[Sequence[Request]]] | None = None,
) -> Iterator[PlotProcess | None]:
    """``with plotting(not args.no_plots) as plotter:`` the plotting children of a command
    (:meth:`PlotProcess.start`; None when not ``enabled`` or not on Linux), closed at the
    end whatever happens.  Enter it first, before the numerics are imported: numpy is
    imported here (the command needs it anyway) so that the children inherit it, and they
    import matplotlib on the other core meanwhile."""
    plotter = None
    if enabled:
        import numpy  # noqa: F401

        plotter = PlotProcess.start(workers=workers, warm=warm, ahead=ahead)
    try:
        yield plotter
    except BaseException:
        if plotter is not None:  # the command failed: its error is not kept waiting
            plotter.close(abort=True)
            plotter = None
        raise
    finally:
        if plotter is not None:
            plotter.close()
