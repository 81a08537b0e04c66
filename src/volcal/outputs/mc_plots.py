"""The plots of a Monte Carlo run (``volcal mc``) and the process that draws them.

Light on purpose (numpy and, when drawing, matplotlib): :class:`PlotProcess` forks a child
at the start of a run, which imports matplotlib on another core while the parent imports
the numerics, identifies and samples; the plots take arrays only, so the child never
imports pandas or the solver.  Figures use the Agg canvas directly (no pyplot).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO, Literal

import numpy as np

__all__ = ["PlotProcess"]


def _figure(w: float, h: float, layout: Literal["constrained"] | None = "constrained"):
    """A figure on the Agg canvas (no pyplot, no GUI backend); ``layout=None`` for figures
    that place their axes themselves (the constrained layout costs a third of a small
    figure's drawing time)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _plot_volumetric_U(
    u_norm: np.ndarray, max_norm: float, points: np.ndarray, path: Path | BinaryIO
) -> None:
    """U(|d|) (M,) at the evaluation poses' nominal points (M, 3), |d| up to max_norm
    (arrays only: drawn here or in :class:`PlotProcess`)."""
    fig = _figure(8, 6.5, layout=None)
    # axes placed by hand where the constrained layout put them
    ax = fig.add_axes((0.0, 0.0, 0.86, 0.93), projection="3d")
    sc = ax.scatter(*np.asarray(points).T, c=u_norm, cmap="viridis", s=25)
    fig.colorbar(sc, cax=fig.add_axes((0.895, 0.2, 0.022, 0.55)), label="U(|d|), k = 2 (um)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(
        f"Monte Carlo expanded uncertainty of the volumetric error |d|\n"
        f"(|d| up to {max_norm:.1f} um; U up to "
        f"{np.max(u_norm):.2f} um)",
        fontsize=10,
    )
    fig.savefig(path, dpi=110)


def _plot_max_hist(mx: np.ndarray, path: Path | BinaryIO) -> None:
    fig = _figure(6, 4, layout=None)
    fig.subplots_adjust(left=0.12, right=0.97, bottom=0.13, top=0.92)
    ax = fig.subplots()
    # one filled outline (the same picture as 60 bars, one artist instead of 60)
    counts, edges = np.histogram(mx, bins=60)
    ax.stairs(counts, edges, fill=True, color="tab:blue", alpha=0.85)
    lo, hi = np.quantile(mx, [0.025, 0.975])
    for v in (lo, hi):
        ax.axvline(v, color="tab:red", linestyle="--", linewidth=0.8)
    ax.set_xlabel("largest volumetric error over the evaluation poses (um)")
    ax.set_ylabel("trials")
    ax.set_title(f"{len(mx)} trials; 95 % interval [{lo:.2f}, {hi:.2f}] um")
    fig.savefig(path, dpi=110)


_PLOTS: dict[str, Callable[..., None]] = {
    "volumetric_U": _plot_volumetric_U,
    "max_hist": _plot_max_hist,
}


def _plot_server(conn, parent: int) -> None:  # pragma: no cover - runs in the child
    """The plotting process: matplotlib imported first (while the parent computes), then
    plots drawn on request, ``(name, args)`` -> ``("ok" | "error", text)``, until None."""
    import traceback

    from volcal.base.processes import watch_parent

    watch_parent(parent)
    try:
        import io

        import matplotlib.backends.backend_agg  # noqa: F401
        import matplotlib.figure  # noqa: F401
        import mpl_toolkits.mplot3d  # noqa: F401

        # and once through the drawing code (fonts, 3-D axes, PNG writer): the plots
        # asked for later are drawn at full speed
        _plot_volumetric_U(np.ones(2), 1.0, np.zeros((2, 3)), io.BytesIO())
    except Exception:  # reported with the first request
        pass
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        name, args = msg
        try:
            _PLOTS[name](*args)
            conn.send(("ok", ""))
        except Exception:
            conn.send(("error", traceback.format_exc()))


class PlotProcess:
    """Draws the PNG plots of a run in a child process started early (``fork``), whose
    import of matplotlib (a quarter of a second) and drawing run on another core while
    this process identifies, samples and writes the tables.  Plots take arrays only.
    :meth:`start` returns None but on Linux (then the plots are drawn in this process)."""

    def __init__(self, proc, conn) -> None:
        self._proc, self._conn, self._pending = proc, conn, 0

    @classmethod
    def start(cls) -> PlotProcess | None:
        import multiprocessing as mp
        import sys

        # fork is safe on Linux only (macOS frameworks are not fork-safe)
        if not sys.platform.startswith("linux") or "fork" not in mp.get_all_start_methods():
            return None
        ctx = mp.get_context("fork")
        here, there = ctx.Pipe()
        proc = ctx.Process(
            target=_plot_server, args=(there, os.getpid()), name="volcal-plots", daemon=True
        )
        proc.start()
        there.close()
        return cls(proc, here)

    def draw(self, name: str, *args) -> None:
        """Ask for plot ``name`` (see ``_PLOTS``) with ``args``."""
        self._conn.send((name, args))
        self._pending += 1

    def wait(self, timeout: float = 600.0) -> None:
        """Wait for every plot asked for; a failed plot, or none for ``timeout`` seconds,
        raises RuntimeError."""
        errors = []
        while self._pending:
            try:
                if not self._conn.poll(timeout):
                    raise RuntimeError(f"no plot from the plotting process in {timeout:g} s")
                status, text = self._conn.recv()
            except (EOFError, OSError):
                raise RuntimeError("the plotting process ended unexpectedly") from None
            self._pending -= 1
            if status != "ok":
                errors.append(text)
        if errors:
            raise RuntimeError("plotting failed:\n" + "\n".join(errors))

    def close(self) -> None:
        """End the plotting process (after its plots, or at once on an error)."""
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._conn.close()
        self._proc.join(timeout=2.0 if not self._pending else 0.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=2.0)
