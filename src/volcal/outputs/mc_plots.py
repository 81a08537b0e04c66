"""The plots of a Monte Carlo run (``volcal mc``).

Light on purpose (numpy and, when drawing, matplotlib): they take arrays only, so that
:class:`volcal.outputs.plot_process.PlotProcess` can draw them in a child that never imports
pandas or the solver.  Figures use the Agg canvas directly (no pyplot).
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

from volcal.outputs.figures import figure, save

__all__ = ["warm_up"]


def _plot_volumetric_U(
    u_norm: np.ndarray, max_norm: float, points: np.ndarray, path: Path | BinaryIO
) -> None:
    """U(|d|) (M,) at the evaluation poses' nominal points (M, 3), |d| up to max_norm
    (arrays only: drawn here or in :class:`PlotProcess`)."""
    fig = figure(8, 6.5)
    # axes placed by hand where the constrained layout put them
    ax = fig.add_axes((0.0, 0.0, 0.86, 0.93), projection="3d")
    sc = ax.scatter(*np.asarray(points).T, c=u_norm, cmap="viridis", s=25)
    fig.colorbar(sc, cax=fig.add_axes((0.895, 0.2, 0.022, 0.55)), label="U(|d|), k = 2 (µm)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(
        f"Monte Carlo expanded uncertainty of the volumetric error |d|\n"
        f"(|d| up to {max_norm:.1f} µm; U up to "
        f"{np.max(u_norm):.2f} µm)",
        fontsize=10,
    )
    save(fig, path, dpi=110)


def _plot_max_hist(mx: np.ndarray, path: Path | BinaryIO) -> None:
    fig = figure(6, 4)
    fig.subplots_adjust(left=0.12, right=0.97, bottom=0.13, top=0.92)
    ax = fig.subplots()
    # one filled outline (the same picture as 60 bars, one artist instead of 60)
    counts, edges = np.histogram(mx, bins=60)
    ax.stairs(counts, edges, fill=True, color="tab:blue", alpha=0.85)
    lo, hi = np.quantile(mx, [0.025, 0.975])
    for v in (lo, hi):
        ax.axvline(v, color="tab:red", linestyle="--", linewidth=0.8)
    ax.set_xlabel("largest volumetric error over the evaluation poses (µm)")
    ax.set_ylabel("trials")
    ax.set_title(f"{len(mx)} trials; 95 % interval [{lo:.2f}, {hi:.2f}] µm")
    save(fig, path, dpi=110)


def warm_up() -> None:
    """The plotting child's warm-up for a Monte Carlo run: the 3-D axes too."""
    import io

    _plot_volumetric_U(np.ones(2), 1.0, np.zeros((2, 3)), io.BytesIO())
