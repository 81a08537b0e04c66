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
rasterised scatters, images instead of patches; and a plotting child builds the frames
(figure, axes, styling, ticks) of the figures it will draw while it waits for their data
(:func:`prepare_frame`, :func:`frame_plan`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np

__all__ = [
    "draw_component_errors",
    "draw_volumetric_slices",
    "draw_residuals",
    "draw_residuals_vs_axes",
    "draw_correlations",
    "draw_plan",
    "prepare_frame",
    "frame_plan",
    "hold",
    "write_held",
    "plan_frame_ahead",
    "COSTS",
]

DPI = 100
#: widest figure (inches): the HTML report shows a figure up to about 1040 px wide at its
#: own size (DPI 100), so its fonts keep their point size there
MAX_WIDTH = 10.4
#: units as the figures print them (the data carry the ASCII names of the CSV columns)
_DISPLAY = {"um": "µm", "urad": "µrad"}
#: ticks per axis at most: tick labels are most of a figure's drawing time
_NBINS = 5
#: FreeType's hinting of the text in the written figures: its autohinter, matplotlib's
#: default up to 3.10.  Matplotlib 3.11's default (the font's own hinting program, run
#: for every glyph of every text drawn) made drawing the figures 5-20 % slower (text is
#: most of it), for the same layout and glyphs as crisp (sub-pixel differences)
HINTING = "force_autohint"

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
    level 6 (the default) for files 6 % larger.  Text hinted by :data:`HINTING`."""
    if path is not None:
        from matplotlib import rc_context

        _settle_titles(fig)
        png = not isinstance(path, (str, Path)) or Path(path).suffix.lower() in ("", ".png")
        with rc_context({"text.hinting": HINTING}):
            fig.savefig(path, dpi=dpi, **({"pil_kwargs": {"compress_level": 3}} if png else {}))
    return fig


def _settle_titles(fig) -> None:
    """Place each axes' title at the top of its axes for good where nothing is drawn
    there: matplotlib otherwise lays out the y axis' tick labels once more while drawing,
    to see whether the title must move above the axis' offset text (``1e-8``, ``+1e3``;
    a twentieth of the drawing time).  Only where the x axis' ticks and label are at the
    bottom, the limits are not changed by the drawing (an aspect kept by the data
    limits) and the y axis' formatter, given the ticks it will draw, shows no offset
    text; the picture is the same.  Titles are set with a text and a font size only
    (set again here with those)."""
    for ax in fig.axes:
        t = ax.title
        if not t.get_text() or ax.get_title("left") or ax.get_title("right"):
            continue
        if ax.xaxis.get_ticks_position() != "bottom" or ax.xaxis.get_label_position() != "bottom":
            continue
        if ax.get_aspect() != "auto" and ax.get_adjustable() == "datalim":
            continue  # the limits, so the ticks, change as it is drawn
        fmt = ax.yaxis.get_major_formatter()
        fmt.set_locs(ax.yaxis.get_majorticklocs())  # as the drawing will
        if fmt.get_offset():
            continue
        ax.set_title(t.get_text(), fontsize=t.get_fontsize(), y=1.0)


def _few_ticks(ax) -> None:
    ax.locator_params(nbins=_NBINS)


#: frames built ahead (:func:`prepare_frame`), by layout key: a figure and its axes,
#: styled, with their ticks made
_FRAMES: dict[tuple, Any] = {}
#: ticks made per axis in a frame built ahead: every axis of these figures shows at most
#: seven (five bins), a few more are made as needed
_TICKS_AHEAD = 8


#: the result folder's figures in the order ``volcal identify`` sends them to the plotting
#: children (the two that need no covariance first: they are sent as soon as the solve
#: has ended, :func:`volcal.outputs.plots.hold_solved_plots`), with their relative
#: drawing time (processor seconds at 10^4 readings of the benchmarks' mcv754_wxyzt, as
#: a plotting child draws them: warm matplotlib, frames built ahead), by which
#: :class:`volcal.outputs.plot_process.PlotProcess` shares them between its children
#: (two: volumetric map and component errors to one, the other three to the other)
COSTS = {
    "volumetric_map.png": 0.12,
    "residuals.png": 0.12,
    "component_errors.png": 0.25,
    "correlations.png": 0.15,
    "residuals_vs_axes.png": 0.10,
}


def frame_plan(
    n_axes: int, workers: int, volumetric: tuple | None = None
) -> list[list[tuple[Callable[..., Any], tuple]]]:
    """The frames (:func:`prepare_frame`) each of ``workers`` plotting children builds
    while it waits for its first request: those of the figures it will be sent, a result
    of ``n_axes`` machine axes drawn in the order of :data:`COSTS`, each sent to the
    child with the least drawing queued (as :meth:`PlotProcess.draw` does); the
    volumetric map's when its key is given (:func:`volumetric_frame_key`).  A frame that
    does not match its figure (another layout, another child) is not used."""
    keys = {
        "volumetric_map.png": volumetric,
        "component_errors.png": ("component_errors", n_axes),
        "correlations.png": ("correlations",),
        "residuals.png": ("residuals",),
        "residuals_vs_axes.png": ("residuals_vs_axes", max(n_axes, 1)),
    }
    queued = [0.0] * workers
    plan: list[list[tuple[Callable[..., Any], tuple]]] = [[] for _ in range(workers)]
    for name, cost in COSTS.items():
        i = min(range(workers), key=lambda k: queued[k])
        queued[i] += cost
        if keys.get(name) is not None:
            plan[i].append((prepare_frame, (keys[name],)))
    return plan


def plan_frame_ahead(workers: int) -> list[list[tuple[Callable[..., Any], tuple]]]:
    """The frame ``volcal plan``'s plotting child builds while it waits (``workers ->
    plan``, as :func:`frame_plan`): plan.png's, a fifth of its drawing time, in the
    first child (the one :meth:`~volcal.outputs.plot_process.PlotProcess.draw` sends
    the only figure to)."""
    return [[(prepare_frame, (("plan",),))]] + [[] for _ in range(workers - 1)]


def _frame(key: tuple, build: Callable[[], Any]) -> Any:
    """The frame of layout ``key`` built ahead (:func:`prepare_frame`), else ``build()``."""
    frame = _FRAMES.pop(key, None)
    return frame if frame is not None else build()


def prepare_frame(key: tuple) -> None:
    """Build the frame of a figure ahead (``key``: ``("component_errors", rows)``,
    ``("residuals",)``, ``("residuals_vs_axes", panels)``, ``("correlations",)`` or
    ``("plan",)``): its
    figure, axes and styling, the same calls the drawing function makes, and the ticks of
    every axis.  A plotting child does this while it waits for its first request: a tick
    costs about half a millisecond to make, a figure's ticks and axes a fifth of its
    drawing time.  The drawing function takes it when the layout matches (else it builds
    its own); ticks made and not needed are not drawn, so the picture is the same."""
    fig, axes = _BUILDERS[key[0]](*key[1:])
    for ax in fig.axes:
        ax.xaxis.get_major_ticks(_TICKS_AHEAD)
        ax.yaxis.get_major_ticks(_TICKS_AHEAD)
    _FRAMES[key] = (fig, axes)


#: figures drawn before their result folder exists (:func:`hold`): PNG bytes by name
_HELD: dict[str, bytes] = {}


def hold(draw: Callable[..., Any], data: dict[str, Any], name: str) -> None:
    """Draw ``draw(data)`` into PNG bytes kept in this process under ``name`` until
    :func:`write_held` writes them: a plotting child draws a figure whose data are known
    before the folder it goes to is made (the same bytes as drawn to the file)."""
    import io

    buf = io.BytesIO()
    draw(data, buf)
    _HELD[name] = buf.getvalue()


def write_held(name: str, path: str | Path) -> None:
    """Write the figure held under ``name`` (:func:`hold`) to ``path``."""
    Path(path).write_bytes(_HELD.pop(name))


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
    fig, grid = _frame(("component_errors", len(axes)), lambda: _component_frame(len(axes)))
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
            ax.set_ylabel(f"error ({_DISPLAY.get(panel['unit'], panel['unit'])})")
            ax.axhline(0.0, color="0.6", linewidth=0.6)
            if panel["series"]:
                ax.legend(fontsize=8, loc="upper left", ncol=3)
            else:
                ax.text(0.5, 0.5, "none in this model", transform=ax.transAxes, ha="center")
    h = fig.get_figheight()
    fig.suptitle(
        "Component error motions (error = actual − nominal), band = ±2u (k = 2)",
        y=1 - 0.15 / h,
        va="top",
    )
    fig.subplots_adjust(
        left=0.08, right=0.98, bottom=0.5 / h, top=1 - 0.8 / h, hspace=0.6, wspace=0.22
    )
    return save(fig, path)


def _component_frame(rows: int):
    fig = figure(MAX_WIDTH, 2.6 * rows + 0.7)
    grid = fig.subplots(rows, 2, squeeze=False)
    for ax in grid.ravel():
        ax.tick_params(labelsize=9)
        ax.grid(True, alpha=0.3)
        _few_ticks(ax)
    return fig, grid


def _nice(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``x`` (for a scale key)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    e = 10.0 ** np.floor(np.log10(x))
    return float(max(m for m in (1.0, 2.0, 5.0, 10.0) if m * e <= x * (1 + 1e-9)) * e)


def draw_volumetric_slices(data: dict[str, Any], path: Target = None):
    """data: ``{"g1", "g2"`` (grid positions, mm), ``"labels"`` (x, y), ``"slices"``:
    ``[{"title", "norm" (n1, n2) µm, "d1", "d2" (in-plane components, µm)}]``, ``"vmax"``,
    ``"title"}``; or ``{"message": text}``.  Panels to scale (equal mm on both axes), one
    arrow scale for all, with its key."""
    if "message" in data:
        return _message(data["message"], path)
    slices = data["slices"]
    g1, g2 = data["g1"], data["g2"]
    G1, G2 = np.meshgrid(g1, g2, indexing="ij")
    span1 = float(g1.max() - g1.min()) or 1.0
    span2 = float(g2.max() - g2.min()) or 1.0
    L = _volumetric_layout(len(slices), span1, span2)
    ncol, pw, left, gap_w = L["ncol"], L["pw"], L["left"], L["gap_w"]
    width, height = L["width"], L["height"]
    # the figure, its panels and the colour bar's axes: built ahead when the plotting
    # child knew the machine (volumetric_frame_key)
    fig, (axes, cax) = _frame(
        ("volumetric", len(slices), span1, span2),
        lambda: _volumetric_frame(len(slices), span1, span2),
    )
    ext = [g1.min(), g1.max(), g2.min(), g2.max()]
    step = max(1, len(g1) // 9)
    spacing = span1 / max(1, (len(g1) - 1) / step)
    vmax = float(data["vmax"]) or 1.0
    # one scale for every panel: the largest error is drawn 1.6 arrow spacings long
    scale = vmax / (1.6 * spacing)
    im = quiv = None
    for ax, s in zip(axes, slices):
        im = ax.imshow(
            s["norm"].T,
            origin="lower",
            extent=ext,
            cmap="viridis",
            vmin=0,
            vmax=vmax,
            aspect="equal",
        )
        quiv = ax.quiver(
            G1[::step, ::step],
            G2[::step, ::step],
            s["d1"][::step, ::step],
            s["d2"][::step, ::step],
            color="white",
            angles="xy",
            scale_units="xy",
            scale=scale,
            pivot="mid",
        )
        ax.set_title(s["title"], fontsize=9)
        ax.set_xlabel(data["labels"][0], fontsize=9)
        ax.set_ylabel(data["labels"][1], fontsize=9)
    fig.colorbar(im, cax=cax, label="|volumetric error| (µm)")
    cax.tick_params(labelsize=8)
    if quiv is not None:
        key = _nice(vmax)
        fig.text(
            (left + ncol * pw + (ncol - 1) * gap_w) / width,
            0.2 / height,
            "arrow scale:",
            ha="right",
            va="center",
            fontsize=9,
        )
        axes[0].quiverkey(
            quiv,
            (left + ncol * pw + (ncol - 1) * gap_w + 0.15 + key / scale * pw / span1) / width,
            0.2 / height,
            key,
            f"{key:g} µm",
            labelpos="E",
            coordinates="figure",
            color="black",
            fontproperties={"size": 9},
        )
    fig.suptitle(data["title"], fontsize=10, y=1 - 0.3 / height)
    return save(fig, path)


def _volumetric_layout(n: int, span1: float, span2: float) -> dict[str, Any]:
    """Where the ``n`` panels of the volumetric map go (inches): three to a row, each to
    scale with the travel of its two axes (``span1`` x ``span2`` mm)."""
    # panel sizes (inches) follow the travel: 800 x 500 mm is drawn 800 x 500
    ncol = min(n, 3)
    nrow = int(np.ceil(n / ncol))
    gap_w, gap_h = 0.85, 1.0  # y labels; two-line titles and x labels
    left, right, top, bottom = 0.75, 1.3, 0.9, 0.55
    # at most MAX_WIDTH wide: the report shows it at its own size
    pw = min(2.7, (MAX_WIDTH - left - right - (ncol - 1) * gap_w) / ncol)
    # to scale within [0.8, 4] in of height; a travel too long for that (3000 x 100 mm)
    # keeps the width and gives up the scale rather than grow past MAX_WIDTH
    ph = float(np.clip(pw * span2 / span1, 0.8, 4.0))
    pw = min(pw, ph * span1 / span2)
    width = left + ncol * pw + (ncol - 1) * gap_w + right
    height = top + nrow * ph + (nrow - 1) * gap_h + bottom + 0.25
    return {
        "ncol": ncol,
        "nrow": nrow,
        "pw": pw,
        "ph": ph,
        "left": left,
        "right": right,
        "bottom": bottom,
        "gap_w": gap_w,
        "gap_h": gap_h,
        "width": width,
        "height": height,
    }


def _volumetric_frame(n: int, span1: float, span2: float):
    """The volumetric map's figure, its ``n`` panels (styled) and its colour bar's axes:
    what depends on the machine's travel and number of slices only, so it is built ahead
    (:func:`volumetric_frame_key`)."""
    L = _volumetric_layout(n, span1, span2)
    ncol, nrow, pw, ph = L["ncol"], L["nrow"], L["pw"], L["ph"]
    left, bottom, gap_w, gap_h = L["left"], L["bottom"], L["gap_w"], L["gap_h"]
    width, height = L["width"], L["height"]
    fig = figure(width, height)
    axes = []
    for k in range(n):
        r, c = divmod(k, ncol)
        x0 = left + c * (pw + gap_w)
        y0 = bottom + 0.25 + (nrow - 1 - r) * (ph + gap_h)
        ax = fig.add_axes((x0 / width, y0 / height, pw / width, ph / height))
        ax.tick_params(labelsize=8)
        _few_ticks(ax)
        axes.append(ax)
    cb_x = (width - L["right"] + 0.3) / width
    cb_h = min(nrow * ph + (nrow - 1) * gap_h, 4.0)
    cb_top = bottom + 0.25 + nrow * ph + (nrow - 1) * gap_h  # level with the first row
    cax = fig.add_axes((cb_x, (cb_top - cb_h) / height, 0.15 / width, cb_h / height))
    return fig, (axes, cax)


def volumetric_frame_key(
    axes: Sequence[tuple[float, float, bool]], heights: int = 3, angles: int = 4
) -> tuple | None:
    """The frame key (:func:`prepare_frame`) of the volumetric map of a machine whose
    axes are ``(travel low, travel high, rotary?)`` (mm or deg), drawn with ``heights``
    slices along the third linear axis and ``angles`` per rotary axis, as
    :func:`volcal.outputs.plots.volumetric_slices_data` makes them; None without two
    linear axes (no map).  Known before the solve: the frame is built while the
    plotting child waits."""
    lin = [(lo, hi) for lo, hi, rotary in axes if not rotary]
    if len(lin) < 2:
        return None
    n = (heights if len(lin) > 2 else 1) + angles * sum(1 for *_, rotary in axes if rotary)
    # the map's grid runs from end to end of the travel (linspace: the ends exact)
    (lo1, hi1), (lo2, hi2) = lin[:2]
    return ("volumetric", n, float(hi1 - lo1) or 1.0, float(hi2 - lo2) or 1.0)


def draw_residuals(data: dict[str, Any], path: Target = None):
    """data: ``{"kept", "rejected"`` (residuals, um), ``"bins"``, ``"rms"``, ``"qq"``:
    (normal quantiles, sorted standardised residuals) or None, ``"lim"``, ``"by_station"``:
    ``[(station, reading numbers, residuals um)]``, ``"rejected_at"``: reading numbers}``."""
    fig, (ax1, ax2, ax3) = _frame(("residuals",), _residuals_frame)
    kept, rej = data["kept"], data["rejected"]
    # histograms as one filled outline each (one artist instead of one per bar)
    if len(kept):
        counts, edges = np.histogram(kept, bins=data["bins"])
        ax1.stairs(counts, edges, fill=True, color="tab:blue")
    if len(rej):
        counts, edges = np.histogram(rej, bins=10)
        ax1.stairs(counts, edges, fill=True, color="tab:red", alpha=0.8, label="rejected")
        ax1.legend(fontsize=8)
    ax1.set_title(f"residuals (RMS {data['rms']:.3g} µm,\n{len(kept)} readings)", fontsize=10)
    ax1.set_xlabel("residual (µm)")
    ax1.set_ylabel("readings")
    if data["qq"] is not None:
        theo, zs = data["qq"]
        ax2.plot(theo, zs, ".", markersize=2, rasterized=True)
        lim = data["lim"]
        ax2.plot([-lim, lim], [-lim, lim], color="0.4", linewidth=0.8)
    ax2.set_title("normal QQ plot of the\nstandardised residuals", fontsize=10)
    ax2.set_xlabel("normal quantile")
    ax2.set_ylabel("standardised residual")
    for sid, idx, r in data["by_station"]:
        ax3.plot(idx, r, ".", markersize=2, label=str(sid), rasterized=True)
    if len(data["rejected_at"]):
        ax3.plot(data["rejected_at"], rej, "x", color="tab:red", label="rejected")
    ax3.axhline(0.0, color="0.5", linewidth=0.6)
    ax3.set_xlabel("reading (order in the data file)")
    ax3.set_ylabel("residual (µm)")
    ax3.set_title("residual (model − measured) per reading,\nby station", fontsize=10)
    ax3.legend(fontsize=8, ncol=2, markerscale=4, loc="upper right")
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.13, top=0.85, wspace=0.3)
    return save(fig, path)


def _residuals_frame():
    fig = figure(MAX_WIDTH, 4.0)
    axes = fig.subplots(1, 3, width_ratios=[1, 1, 2])
    for ax in axes:
        _few_ticks(ax)
        ax.tick_params(labelsize=9)
    for ax in axes[1:]:
        ax.grid(True, alpha=0.3)
    return fig, axes


def draw_residuals_vs_axes(data: dict[str, Any], path: Target = None):
    """data: ``{"panels": [{"xlabel", "title", "x", "z"`` (the drawn readings),
    ``"means": [(centres, binned means)]`` per station, ``"rms": (centres, binned RMS)}],
    ``"title"}``; residuals normalised (residual / sigma)."""
    panels = data["panels"]
    n = max(len(panels), 1)
    ncol, nrow = _panel_grid(n)
    fig, axes = _frame(("residuals_vs_axes", n), lambda: _residuals_vs_axes_frame(n))
    for ax, p in zip(axes, panels):
        ax.plot(p["x"], p["z"], ".", color="0.65", markersize=2, rasterized=True)
        for centres, mean in p["means"]:
            ax.plot(centres, mean, "-", linewidth=1.0, alpha=0.9)
        ax.plot(*p["rms"], "k--", linewidth=1.2, label="binned RMS")
        ax.axhline(0.0, color="0.3", linewidth=0.6)
        ax.set_xlabel(p["xlabel"])
        ax.set_ylabel("normalised residual")
        ax.set_title(p["title"], fontsize=9)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    if panels:
        axes[0].legend(fontsize=8, loc="upper right")
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


def _panel_grid(n: int) -> tuple[int, int]:
    """(columns, rows) of ``n`` panels, three to a row."""
    ncol = min(n, 3)
    return ncol, -(-n // ncol)


def _residuals_vs_axes_frame(n: int):
    ncol, nrow = _panel_grid(n)
    fig = figure(min(MAX_WIDTH, 3.5 * ncol), 2.9 * nrow + 0.8)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    for ax in axes:
        ax.tick_params(labelsize=8)
        ax.grid(True, alpha=0.3)
        _few_ticks(ax)
    return fig, axes


def strongest_pairs(R: np.ndarray, names: list[str], n: int = 12) -> list[tuple[str, str, float]]:
    """The ``n`` off-diagonal pairs of the correlation matrix ``R`` with the largest |r|,
    strongest first, as ``(name, name, r)``."""
    if len(R) < 2:
        return []
    i, j = np.triu_indices(len(R), k=1)
    r = R[i, j]
    order = np.argsort(-np.abs(r), kind="stable")[:n]
    return [(names[i[k]], names[j[k]], float(r[k])) for k in order]


def _blocks(groups: list[str]) -> list[tuple[int, int, str]]:
    """Runs of equal labels as ``(first, last + 1, label)``."""
    out: list[tuple[int, int, str]] = []
    for k, g in enumerate(groups):
        if out and out[-1][2] == g:
            out[-1] = (out[-1][0], k + 1, g)
        else:
            out.append((k, k + 1, g))
    return out


def _correlations_frame():
    """The matrix, its colour bar and the strongest pairs' axes."""
    fig = figure(10.4, 6.2)
    ax = fig.add_axes((0.08, 0.1, 0.5, 0.5 * 10.4 / 6.2 * 0.95))
    cax = fig.add_axes((0.595, 0.1, 0.012, 0.5 * 10.4 / 6.2 * 0.95))
    pax = fig.add_axes((0.79, 0.1, 0.19, 0.79))
    return fig, (ax, cax, pax)


def draw_correlations(data: dict[str, Any], path: Target = None, max_labels: int = 30):
    """data: ``{"R"`` (correlation matrix), ``"names"``, ``"groups"`` (optional: the axis
    of each parameter's error quantity)}``.  Left: the matrix, each parameter named when
    there are at most ``max_labels``, else labelled by blocks of its axis; right: the
    strongest pairs by name."""
    R, names = data["R"], data["names"]
    groups = data.get("groups") or [""] * len(names)
    fig, (ax, cax, pax) = _frame(("correlations",), _correlations_frame)
    im = ax.imshow(R, cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
    if len(names) <= max_labels:
        ax.set_xticks(range(len(names)), names, rotation=90, fontsize=8)
        ax.set_yticks(range(len(names)), names, fontsize=8)
    else:
        blocks = _blocks(groups)
        centres = [0.5 * (a + b - 1) for a, b, _ in blocks]
        labels = [("tool" if g == "T" else f"axis {g}") if g else "" for *_, g in blocks]
        ax.set_xticks(centres, labels, fontsize=9)
        ax.set_yticks(centres, labels, fontsize=9, rotation=90, va="center")
        for a, *_ in blocks[1:]:
            ax.axhline(a - 0.5, color="0.2", linewidth=0.6)
            ax.axvline(a - 0.5, color="0.2", linewidth=0.6)
        ax.tick_params(length=0)
    ax.set_xlabel("parameter (basis coefficient)", fontsize=9)
    fig.colorbar(im, cax=cax)
    cax.tick_params(labelsize=8)
    pairs = strongest_pairs(R, names)
    if pairs:
        y = np.arange(len(pairs))
        r = np.array([p[2] for p in pairs])
        pax.barh(y, r, color=np.where(r > 0, "#b2182b", "#2166ac"), height=0.6)
        pax.set_yticks(y, [f"{a} ~ {b}" for a, b, _ in pairs], fontsize=8)
        pax.invert_yaxis()
        pax.set_xlim(-1, 1)
        pax.axvline(0, color="0.3", linewidth=0.6)
        for k, v in enumerate(r):
            inside = abs(v) > 0.35  # the value on its bar, or beyond a short one
            pax.text(
                v - np.sign(v) * 0.04 if inside else v + np.copysign(0.04, v),
                k,
                f"{v:+.3f}",
                va="center",
                ha=("left" if v < 0 else "right") if inside else ("right" if v < 0 else "left"),
                fontsize=8,
                color="white" if inside else "black",
            )
    pax.set_xticks([-1, 0, 1])
    pax.tick_params(labelsize=8)
    pax.set_xlabel("correlation r", fontsize=9)
    pax.set_title("strongest pairs", fontsize=10)
    off = np.abs(R[~np.eye(len(R), dtype=bool)]) if len(R) > 1 else np.zeros(0)
    worst = float(off.max()) if len(off) else 0.0
    fig.suptitle(
        f"Correlations of the {len(names)} identifiable parameters (basis coefficients; "
        f"largest |r| {worst:.3f}" + (f": {pairs[0][0]} ~ {pairs[0][1]})" if pairs else ")"),
        fontsize=11,
    )
    return save(fig, path)


def draw_plan(data: dict[str, Any], path: Target = None):
    """A measurement plan's ``plan.png`` (:mod:`volcal.outputs.plan_files`): data
    ``{"stations_mm" (K, 3), "points_mm" (n, 3), "u_um" (n,), "centre_mm" (3,) or None}``;
    the stations and the evaluation points from above (x, y) and from the side (x, z),
    the points coloured by the predicted volumetric uncertainty u (µm), the point the
    re-aimed reflector is aimed from when there is one.  Fixed margins: pyplot's import
    and the constrained layout were two thirds of the figure's time."""
    S, P, u, c = data["stations_mm"], data["points_mm"], data["u_um"], data["centre_mm"]
    fig, (axes, cax) = _frame(("plan",), _plan_frame)
    for ax, (i, j) in zip(axes, _PLAN_VIEWS):
        sc = ax.scatter(P[:, i], P[:, j], c=u, s=10, cmap="viridis", rasterized=True)
        ax.plot(S[:, i], S[:, j], "r^", markersize=9, label="stations")
        if c is not None:
            ax.plot(c[i], c[j], "kx", markersize=9, label="reflector aimed from")
        for k, s in enumerate(S):
            ax.annotate(f"S{k + 1}", (s[i], s[j]), textcoords="offset points", xytext=(4, 4))
    fig.colorbar(sc, cax=cax, label="predicted u of the volumetric error (µm)")
    axes[0].legend(loc="best", fontsize=8)
    return save(fig, path, dpi=110)


#: the two views of plan.png: (horizontal, vertical) coordinate (0 x, 1 y, 2 z)
_PLAN_VIEWS = ((0, 1), (0, 2))


def _plan_frame():
    """plan.png's figure, its two views (labels, titles, equal scales) and the colour
    bar's axes: what does not depend on the plan."""
    fig = figure(10, 4.2)
    fig.subplots_adjust(left=0.07, right=0.88, bottom=0.12, top=0.92, wspace=0.25)
    axes = fig.subplots(1, 2)
    titles = ("from above (x, y)", "from the side (x, z)")
    for ax, (i, j), lab in zip(axes, _PLAN_VIEWS, titles):
        ax.set_xlabel("xyz"[i] + " / mm")
        ax.set_ylabel("xyz"[j] + " / mm")
        ax.set_title(lab)
        ax.set_aspect("equal", adjustable="datalim")
    cax = fig.add_axes((0.9, 0.12, 0.015, 0.8))
    return fig, (axes, cax)


#: the frame builders of :func:`prepare_frame`, by the first item of its key
_BUILDERS: dict[str, Callable[..., Any]] = {
    "volumetric": _volumetric_frame,
    "component_errors": _component_frame,
    "residuals": _residuals_frame,
    "residuals_vs_axes": _residuals_vs_axes_frame,
    "correlations": _correlations_frame,
    "plan": _plan_frame,
}
