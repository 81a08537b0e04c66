"""Drawing the identification plots from plain data (numpy arrays, numbers, strings).

:mod:`volcal.outputs.plots` turns a result into the data of each figure (that needs the
model, pandas and scipy); this module only draws, with matplotlib's object API on the Agg
canvas (no pyplot, no global state), so that a plotting child process
(:class:`volcal.outputs.plot_process.PlotProcess`) can draw a figure without importing
anything but numpy and matplotlib.  Each ``draw_*`` function takes the dict its
``*_data`` counterpart in :mod:`volcal.outputs.plots` returns, writes the PNG when given a
path, and returns the ``Figure``.

Speed matters here (the default plots are on the critical path of every ``volcal
identify``): fixed margins instead of a layout engine, at most five ticks per axis,
rasterised scatters, images instead of patches.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np

__all__ = [
    "draw_component_errors",
    "draw_volumetric_slices",
    "draw_residuals",
    "draw_residuals_vs_axes",
    "draw_correlations",
]

DPI = 100
#: ticks per axis at most: tick labels are most of a figure's drawing time
_NBINS = 5

Target = str | Path | BinaryIO | None


def figure(w: float, h: float, layout: Literal["constrained"] | None = None):
    """A figure (inches) on the Agg canvas (no pyplot, no GUI backend).  ``layout``:
    None for figures that place their axes themselves (the plots of a result: the
    constrained layout costs a third of a small figure's drawing time), ``"constrained"``
    where placing them by hand is not worth it."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def save(fig, path: Target, dpi: int = DPI):
    """Write ``fig`` to ``path`` (a file name or a binary stream; PNG unless the name says
    otherwise) and return it.  PNGs use zlib level 3: a fifth of the drawing time at
    level 6 (the default) for files 6 % larger."""
    if path is not None:
        png = not isinstance(path, (str, Path)) or Path(path).suffix.lower() in ("", ".png")
        fig.savefig(path, dpi=dpi, **({"pil_kwargs": {"compress_level": 3}} if png else {}))
    return fig


def _few_ticks(ax) -> None:
    ax.locator_params(nbins=_NBINS)


def _message(text: str, path: Target):
    fig = figure(6, 2)
    fig.text(0.5, 0.5, text, ha="center")
    return save(fig, path)


def draw_component_errors(data: dict[str, Any], path: Target = None):
    """data: ``{"axes": [{"name", "unit", "x", "panels": [{"title", "unit", "series":
    [{"name", "y", "u" (or None: no band), "identifiable"}]}] (translation, rotation)}]}``;
    values in um / urad, bands +-2 u."""
    axes = data["axes"]
    if not axes:
        return _message("no component error motions in this model", path)
    fig = figure(11, 2.6 * len(axes) + 0.6)
    grid = fig.subplots(len(axes), 2, squeeze=False)
    for row, a in zip(grid, axes):
        x = a["x"]
        for ax, panel in zip(row, a["panels"]):
            for s in panel["series"]:
                (line,) = ax.plot(x, s["y"], label=s["name"])
                if not s["identifiable"]:
                    line.set_label(f"{s['name']} (not identifiable)")
                    line.set_linestyle("--")
                elif s["u"] is not None:
                    ax.fill_between(
                        x,
                        s["y"] - 2 * s["u"],
                        s["y"] + 2 * s["u"],
                        color=line.get_color(),
                        alpha=0.2,
                        linewidth=0,
                    )
            ax.set_title(panel["title"], fontsize=10)
            ax.set_xlabel(f"{a['name']} position ({a['unit']})")
            ax.set_ylabel(f"error ({panel['unit']})")
            ax.axhline(0.0, color="0.6", linewidth=0.6)
            ax.grid(True, alpha=0.3)
            _few_ticks(ax)
            if panel["series"]:
                ax.legend(fontsize=7, loc="upper left", ncol=3)
            else:
                ax.text(0.5, 0.5, "none in this model", transform=ax.transAxes, ha="center")
    fig.suptitle("Component error motions (error = actual - nominal), band = +-2 u")
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.06, top=0.93, hspace=0.55, wspace=0.2)
    return save(fig, path)


def draw_volumetric_slices(data: dict[str, Any], path: Target = None):
    """data: ``{"g1", "g2"`` (grid positions, mm), ``"labels"`` (x, y), ``"slices"``:
    ``[{"title", "norm" (n1, n2) um, "d1", "d2" (in-plane components, um)}]``, ``"vmax"``,
    ``"title"}``; or ``{"message": text}``."""
    if "message" in data:
        return _message(data["message"], path)
    slices = data["slices"]
    g1, g2 = data["g1"], data["g2"]
    G1, G2 = np.meshgrid(g1, g2, indexing="ij")
    ncol = min(len(slices), 4)
    nrow = int(np.ceil(len(slices) / ncol))
    height = 2.9 * nrow + 1.1
    fig = figure(3.2 * ncol + 1.0, height)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    ext = [g1.min(), g1.max(), g2.min(), g2.max()]
    step = max(1, len(g1) // 9)
    im = None
    for ax, s in zip(axes, slices):
        im = ax.imshow(
            s["norm"].T,
            origin="lower",
            extent=ext,
            cmap="viridis",
            vmin=0,
            vmax=data["vmax"],
            aspect="auto",
        )
        ax.quiver(
            G1[::step, ::step],
            G2[::step, ::step],
            s["d1"][::step, ::step],
            s["d2"][::step, ::step],
            color="white",
            angles="xy",
            pivot="mid",
        )
        ax.set_title(s["title"], fontsize=9)
        ax.set_xlabel(data["labels"][0], fontsize=8)
        ax.set_ylabel(data["labels"][1], fontsize=8)
        ax.tick_params(labelsize=7)
        _few_ticks(ax)
    for ax in axes[len(slices) :]:
        ax.set_visible(False)
    # margins in inches: room for the suptitle and the x labels whatever the row count
    top, bottom = 1 - 0.8 / height, 0.5 / height
    fig.subplots_adjust(left=0.07, right=0.88, bottom=bottom, top=top, hspace=0.55, wspace=0.3)
    cax = fig.add_axes((0.9, bottom + 0.02, 0.015, top - bottom - 0.04))
    fig.colorbar(im, cax=cax, label="|volumetric error| (um)")
    fig.suptitle(data["title"], fontsize=10)
    return save(fig, path)


def draw_residuals(data: dict[str, Any], path: Target = None):
    """data: ``{"kept", "rejected"`` (residuals, um), ``"bins"``, ``"rms"``, ``"qq"``:
    (normal quantiles, sorted standardised residuals) or None, ``"lim"``, ``"by_station"``:
    ``[(station, reading numbers, residuals um)]``, ``"rejected_at"``: reading numbers}``."""
    fig = figure(14, 4.2)
    ax1, ax2, ax3 = fig.subplots(1, 3, width_ratios=[1, 1, 2])
    kept, rej = data["kept"], data["rejected"]
    # histograms as one filled outline each (one artist instead of one per bar)
    if len(kept):
        counts, edges = np.histogram(kept, bins=data["bins"])
        ax1.stairs(counts, edges, fill=True, color="tab:blue")
    if len(rej):
        counts, edges = np.histogram(rej, bins=10)
        ax1.stairs(counts, edges, fill=True, color="tab:red", alpha=0.8, label="rejected")
        ax1.legend(fontsize=8)
    ax1.set_title(f"residuals (RMS {data['rms']:.3g} um, {len(kept)} readings)", fontsize=10)
    ax1.set_xlabel("residual (um)")
    _few_ticks(ax1)
    if data["qq"] is not None:
        theo, zs = data["qq"]
        ax2.plot(theo, zs, ".", markersize=2, rasterized=True)
        lim = data["lim"]
        ax2.plot([-lim, lim], [-lim, lim], color="0.4", linewidth=0.8)
    ax2.set_title("normal QQ plot of the standardised residuals", fontsize=10)
    ax2.set_xlabel("normal quantile")
    ax2.set_ylabel("standardised residual")
    ax2.grid(True, alpha=0.3)
    _few_ticks(ax2)
    for sid, idx, r in data["by_station"]:
        ax3.plot(idx, r, ".", markersize=2, label=str(sid), rasterized=True)
    if len(data["rejected_at"]):
        ax3.plot(data["rejected_at"], rej, "x", color="tab:red", label="rejected")
    ax3.axhline(0.0, color="0.5", linewidth=0.6)
    ax3.set_xlabel("reading (order in the data file)")
    ax3.set_ylabel("residual (um)")
    ax3.set_title("residual (model - measured) per reading, by station", fontsize=10)
    ax3.grid(True, alpha=0.3)
    _few_ticks(ax3)
    ax3.legend(fontsize=7, ncol=2, markerscale=4, loc="upper right")
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.13, top=0.9, wspace=0.28)
    return save(fig, path)


def draw_residuals_vs_axes(data: dict[str, Any], path: Target = None):
    """data: ``{"panels": [{"xlabel", "title", "x", "z"`` (the drawn readings),
    ``"means": [(centres, binned means)]`` per station, ``"rms": (centres, binned RMS)}],
    ``"title"}``; residuals normalised (residual / sigma)."""
    import math

    panels = data["panels"]
    n = max(len(panels), 1)
    ncol = min(n, 3)
    nrow = int(math.ceil(n / ncol))
    fig = figure(4.2 * ncol, 3.0 * nrow + 0.6)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    for ax, p in zip(axes, panels):
        ax.plot(p["x"], p["z"], ".", color="0.65", markersize=2, rasterized=True)
        for centres, mean in p["means"]:
            ax.plot(centres, mean, "-", linewidth=1.0, alpha=0.9)
        ax.plot(*p["rms"], "k--", linewidth=1.2, label="binned RMS")
        ax.axhline(0.0, color="0.3", linewidth=0.6)
        ax.set_xlabel(p["xlabel"])
        ax.set_ylabel("normalised residual")
        ax.set_title(p["title"], fontsize=9)
        ax.grid(True, alpha=0.3)
        _few_ticks(ax)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    if panels:
        axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(data["title"], fontsize=10)
    top = 1.0 - 0.6 / fig.get_figheight()
    fig.subplots_adjust(
        left=0.07 if ncol > 1 else 0.15,
        right=0.98,
        bottom=0.1 / nrow + 0.05,
        top=top - 0.05 / nrow,
        wspace=0.3,
        hspace=0.45,
    )
    return save(fig, path)


def draw_correlations(data: dict[str, Any], path: Target = None, max_labels: int = 60):
    """data: ``{"R"`` (correlation matrix), ``"names"}``."""
    R, names = data["R"], data["names"]
    size = 7.5 if len(names) <= max_labels else 6.5
    fig = figure(size + 1.2, size)
    ax = fig.add_subplot()
    im = ax.imshow(R, cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
    if len(names) <= max_labels:
        ax.set_xticks(range(len(names)), names, rotation=90, fontsize=5)
        ax.set_yticks(range(len(names)), names, fontsize=5)
    cax = fig.add_axes((0.86, 0.2, 0.02, 0.6))
    fig.colorbar(im, cax=cax, label="correlation")
    off = np.abs(R[~np.eye(len(R), dtype=bool)]) if len(R) > 1 else np.zeros(0)
    worst = float(off.max()) if len(off) else 0.0
    ax.set_title(
        f"correlations of the {len(names)} identifiable error parameters (largest |r| {worst:.3f})",
        fontsize=10,
    )
    fig.subplots_adjust(left=0.12, right=0.84, bottom=0.12, top=0.94)
    return save(fig, path)
