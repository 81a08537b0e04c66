"""Plots of an identification, public (``volcal.plots``) and used by the result folder.

Every function returns a matplotlib ``Figure`` (shown inline in Jupyter) and writes it when
given a ``path``.  They use matplotlib's object API on the Agg canvas (no pyplot, no global
state) and keep the number of artists small (rasterised scatters, images instead of
thousands of patches), so that the default set takes well under a second.

* :func:`component_errors`: each axis' translational and angular error motions under their
  ISO 230-1 names, with +-2 u bands (a dashed line where not identifiable);
* :func:`volumetric_slices`: 2-D maps of the volumetric error: |d| in colour and the
  in-plane error vectors as arrows, in XY slices at several heights, and for each rotary
  axis in slices at several angles;
* :func:`residuals`: histogram, normal QQ plot of the standardised residuals, and the
  residuals per reading by station;
* :func:`residuals_vs_axes`: normalised residuals against each axis position;
* :func:`correlations`: correlations of the identifiable error parameters (held and
  unidentifiable directions, i.e. the gauge and what the data cannot see, left out).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "component_errors",
    "volumetric_slices",
    "residuals",
    "residuals_vs_axes",
    "correlations",
]

_DPI = 100
_VOL = ["dx_um", "dy_um", "dz_um"]


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h))
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | Path | None):
    if path is not None:
        fig.savefig(path, dpi=_DPI)
    return fig


def _unit(spec, name: str) -> str:
    return "deg" if spec.axis(name).is_rotary else "mm"


def component_errors(table: pd.DataFrame, error_model: Any, path: str | Path | None = None):
    """The component error motions of ``table`` (:func:`volcal.outputs.results.
    component_error_table`: position per axis, value in um / urad, u_ columns) with +-2 u
    bands."""
    spec = error_model.spec
    axes = [a for a in spec.axes if (table["axis"] == a.name).any()]
    if not axes:
        fig = _figure(6, 2)
        fig.text(0.5, 0.5, "no component error motions in this model", ha="center")
        return _save(fig, path)
    fig = _figure(11, 2.6 * len(axes) + 0.6)
    panels = fig.subplots(len(axes), 2, squeeze=False)
    for row, a in zip(panels, axes):
        sub = table[table["axis"] == a.name]
        unit = _unit(spec, a.name)
        x = sub[f"position_{unit}"].to_numpy()
        for ax, quantity, u_name in ((row[0], "translation", "um"), (row[1], "rotation", "urad")):
            errs = [
                s
                for s in error_model.errors
                if s.axis == a.name and s.kind == "component" and s.quantity == quantity
            ]
            for s in errs:
                y = sub[f"{s.name}_{u_name}"].to_numpy()
                (line,) = ax.plot(x, y, label=s.name)
                ucol = f"u_{s.name}_{u_name}"
                if ucol in sub:
                    u = sub[ucol].to_numpy()
                    if np.isfinite(u).all():
                        ax.fill_between(
                            x, y - 2 * u, y + 2 * u, color=line.get_color(), alpha=0.2, linewidth=0
                        )
                    else:
                        line.set_label(f"{s.name} (not identifiable)")
                        line.set_linestyle("--")
            kind = "translational" if quantity == "translation" else "angular"
            ax.set_title(f"axis {a.name}: {kind} error motions", fontsize=10)
            ax.set_xlabel(f"{a.name} position ({unit})")
            ax.set_ylabel(f"error ({u_name})")
            ax.axhline(0.0, color="0.6", linewidth=0.6)
            ax.grid(True, alpha=0.3)
            if errs:
                ax.legend(fontsize=7, loc="best", ncol=3)
            else:
                ax.text(0.5, 0.5, "none in this model", transform=ax.transAxes, ha="center")
    fig.suptitle("Component error motions (error = actual - nominal), band = +-2 u")
    # fixed margins instead of constrained layout: a third of the drawing time otherwise
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.06, top=0.93, hspace=0.55, wspace=0.2)
    return _save(fig, path)


def _slice_panel(ax, X, Y, d, norm, vmax, title, xlabel, ylabel):
    """|d| as an image, the in-plane components as arrows."""
    ext = [X.min(), X.max(), Y.min(), Y.max()]
    im = ax.imshow(
        norm.T, origin="lower", extent=ext, cmap="viridis", vmin=0, vmax=vmax, aspect="auto"
    )
    step = max(1, X.shape[0] // 9)
    ax.quiver(
        X[::step, ::step],
        Y[::step, ::step],
        d[0][::step, ::step],
        d[1][::step, ::step],
        color="white",
        angles="xy",
        pivot="mid",
    )
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)
    return im


def volumetric_slices(
    machine: Any,
    error_model: Any,
    theta: np.ndarray,
    path: str | Path | None = None,
    *,
    n: int = 25,
    heights: int = 3,
    angles: int = 4,
    tool: np.ndarray | None = None,
):
    """2-D maps of the volumetric error (tool offset ``tool`` mm, default 0): XY slices at
    ``heights`` positions of the third linear axis (rotary axes at their reference), and
    for each rotary axis XY slices at ``angles`` angles over its travel (the third linear
    axis mid-travel).  Colour: |d| (um); arrows: the in-plane components."""
    from volcal.analysis.identify import predict_volumetric

    spec = machine.spec
    lin = [a for a in spec.axes if not a.is_rotary]
    rot = [a for a in spec.axes if a.is_rotary]
    if len(lin) < 2:
        fig = _figure(6, 2)
        fig.text(0.5, 0.5, "volumetric slices need two linear axes", ha="center")
        return _save(fig, path)
    ax1, ax2 = lin[0], lin[1]
    ax3 = lin[2] if len(lin) > 2 else None
    ref = {a.name: a.reference for a in spec.axes}
    slices: list[tuple[str, dict[str, float]]] = []
    if ax3 is not None:
        for h in np.linspace(ax3.travel[0], ax3.travel[1], heights):
            slices.append((f"{ax3.name} = {h:g} mm", {ax3.name: float(h)}))
    else:
        slices.append(("", {}))
    for r in rot:
        mid = {ax3.name: 0.5 * sum(ax3.travel)} if ax3 is not None else {}
        full = r.travel[1] - r.travel[0] >= 360 - 1e-9
        vals = np.linspace(r.travel[0], r.travel[1], angles + (1 if full else 0))
        vals = vals[:-1] if full else vals
        for v in vals:
            slices.append((f"{r.name} = {v:g} deg", {r.name: float(v), **mid}))
    g1 = np.linspace(ax1.travel[0], ax1.travel[1], n)
    g2 = np.linspace(ax2.travel[0], ax2.travel[1], n)
    G1, G2 = np.meshgrid(g1, g2, indexing="ij")
    fields = []
    for _, fixed in slices:
        q = np.tile([fixed.get(a.name, ref[a.name]) for a in spec.axes], (n * n, 1)).astype(float)
        q[:, spec.axis_names.index(ax1.name)] = G1.ravel()
        q[:, spec.axis_names.index(ax2.name)] = G2.ravel()
        t = np.zeros((n * n, 3)) if tool is None else np.tile(tool, (n * n, 1))
        pred = predict_volumetric(machine, error_model, theta, None, machine.axis_to_internal(q), t)
        d = pred[_VOL].to_numpy().reshape(n, n, 3)
        fields.append(d)
    vmax = max(float(np.max(np.linalg.norm(d, axis=2))) for d in fields) or 1.0
    ncol = min(len(slices), 4)
    nrow = int(np.ceil(len(slices) / ncol))
    height = 2.9 * nrow + 1.1
    fig = _figure(3.2 * ncol + 1.0, height)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    im = None
    c1, c2 = "xyz".index(ax1.direction[-1]), "xyz".index(ax2.direction[-1])
    for ax, (title, _), d in zip(axes, slices, fields):
        im = _slice_panel(
            ax,
            G1,
            G2,
            (d[..., c1], d[..., c2]),
            np.linalg.norm(d, axis=2),
            vmax,
            title or f"{ax1.name}{ax2.name} plane",
            f"{ax1.name} (mm)",
            f"{ax2.name} (mm)",
        )
    for ax in axes[len(slices) :]:
        ax.set_visible(False)
    # margins in inches: room for the suptitle and the x labels whatever the row count
    top, bottom = 1 - 0.8 / height, 0.5 / height
    fig.subplots_adjust(left=0.07, right=0.88, bottom=bottom, top=top, hspace=0.55, wspace=0.3)
    cax = fig.add_axes((0.9, bottom + 0.02, 0.015, top - bottom - 0.04))
    fig.colorbar(im, cax=cax, label="|volumetric error| (um)")
    what = "tool offset 0" if tool is None else f"tool offset {tuple(np.round(tool, 1))} mm"
    fig.suptitle(
        f"Volumetric error (actual - nominal), {what}; arrows: in-plane components",
        fontsize=10,
    )
    return _save(fig, path)


def residuals(table: pd.DataFrame, path: str | Path | None = None, max_points: int = 4000):
    """Histogram of the residuals (um), normal QQ plot of the standardised residuals and the
    residuals per reading by station (at most ``max_points`` drawn, rasterised)."""
    from scipy.special import ndtri  # the normal quantile; scipy.stats costs 0.4 s to import

    r = table["residual_um"].to_numpy(float)
    rej = np.asarray(table["rejected"], bool) if "rejected" in table else np.zeros(len(r), bool)
    z = (
        table["normalised_residual"].to_numpy(float)
        if "normalised_residual" in table
        else r / np.nanstd(r)
    )
    keep = ~rej & np.isfinite(r)
    fig = _figure(14, 4.2)
    ax1, ax2, ax3 = fig.subplots(1, 3, width_ratios=[1, 1, 2])
    kept = r[keep]
    ax1.hist(kept, bins=max(10, min(60, int(np.sqrt(max(len(kept), 1))))), color="tab:blue")
    if rej.any():
        ax1.hist(r[rej], bins=10, color="tab:red", alpha=0.8, label="rejected")
        ax1.legend(fontsize=8)
    rms = float(np.sqrt(np.mean(kept**2))) if len(kept) else float("nan")
    ax1.set_title(f"residuals (RMS {rms:.3g} um, {len(kept)} readings)", fontsize=10)
    ax1.set_xlabel("residual (um)")
    zs = np.sort(z[keep & np.isfinite(z)])
    if len(zs):
        theo = ndtri((np.arange(1, len(zs) + 1) - 0.5) / len(zs))
        sub = np.unique(np.linspace(0, len(zs) - 1, min(len(zs), max_points)).astype(int))
        ax2.plot(theo[sub], zs[sub], ".", markersize=2, rasterized=True)
        lim = float(max(abs(theo[0]), abs(theo[-1]), 1.0))
        ax2.plot([-lim, lim], [-lim, lim], color="0.4", linewidth=0.8)
    ax2.set_title("normal QQ plot of the standardised residuals", fontsize=10)
    ax2.set_xlabel("normal quantile")
    ax2.set_ylabel("standardised residual")
    ax2.grid(True, alpha=0.3)
    idx = np.arange(1, len(r) + 1)
    step = max(1, len(r) // max_points)
    st = table["station"].astype(str).to_numpy() if "station" in table else np.full(len(r), "")
    for sid in dict.fromkeys(st):
        m = (st == sid) & keep
        m[np.arange(len(m)) % step != 0] = False
        ax3.plot(idx[m], r[m], ".", markersize=2, label=str(sid), rasterized=True)
    if rej.any():
        ax3.plot(idx[rej], r[rej], "x", color="tab:red", label="rejected")
    ax3.axhline(0.0, color="0.5", linewidth=0.6)
    ax3.set_xlabel("reading (order in the data file)")
    ax3.set_ylabel("residual (um)")
    ax3.set_title("residual (model - measured) per reading, by station", fontsize=10)
    ax3.grid(True, alpha=0.3)
    ax3.legend(fontsize=7, ncol=2, markerscale=4, loc="best")
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.13, top=0.9, wspace=0.28)
    return _save(fig, path)


def residuals_vs_axes(result: Any, path: str | Path | None = None):
    """Normalised residuals against each axis position (see
    :func:`volcal.analysis.adequacy.plot_residuals_vs_axes`)."""
    from volcal.analysis.adequacy import assess, plot_residuals_vs_axes

    spec = result.machine.spec
    return plot_residuals_vs_axes(
        result.residuals,
        spec.axis_names,
        [_unit(spec, a) for a in spec.axis_names],
        path,
        adequacy=assess(result),
    )


def _datum_determined(result: Any, keep: np.ndarray) -> np.ndarray:
    """Mask of the parameters (among ``keep``) that the datum conditions in force determine
    from the others: one pivot column of C per independent condition."""
    import scipy.linalg as sla

    from volcal.model.datum import candidate_conditions

    em = result.error_model
    conds = candidate_conditions(em, em.datum)
    out = np.zeros(em.n_params, bool)
    if not conds:
        return out
    C = np.array([c.row for c in conds], float)
    if result.state is not None and len(result.state.datum_active) == len(conds):
        C = C[np.asarray(result.state.datum_active, bool)]
    cols = np.flatnonzero(keep)
    Ck = C[:, cols]
    if not Ck.size:
        return out
    _, R, piv = sla.qr(Ck, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    rank = int(np.sum(d > 1e-10 * (d[0] if len(d) else 1.0)))
    out[cols[piv[:rank]]] = True
    return out


def correlations(result: Any, path: str | Path | None = None, max_labels: int = 60):
    """Correlation matrix of the identifiable error parameters: parameters that are held,
    unidentifiable, fixed by the datum alone (zero variance) or determined from the others
    by a datum condition are left out, so the picture shows what the data determine, not
    the datum's ties."""
    cov = np.asarray(result.cov_theta, float)
    var = np.diag(cov)
    keep = np.asarray(result.identifiable, bool) & np.isfinite(var) & (var > 0)
    # the datum conditions in force tie some parameters exactly to others: leave out one
    # parameter per condition (QR with column pivoting picks them), so the picture shows
    # the correlations the data leave, not the datum's
    keep &= ~_datum_determined(result, keep)
    names = [n for n, k in zip(result.error_model.param_names, keep) if k]
    C = cov[np.ix_(keep, keep)]
    d = np.sqrt(np.diag(C))
    R = C / np.outer(d, d) if len(d) else np.zeros((0, 0))
    size = 7.5 if len(names) <= max_labels else 6.5
    fig = _figure(size + 1.2, size)
    ax = fig.add_subplot()
    im = ax.imshow(R, cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
    if len(names) <= max_labels:
        ax.set_xticks(range(len(names)), names, rotation=90, fontsize=5)
        ax.set_yticks(range(len(names)), names, fontsize=5)
    fig.colorbar(im, ax=ax, shrink=0.8, label="correlation")
    off = np.abs(R[~np.eye(len(R), dtype=bool)]) if len(R) > 1 else np.zeros(0)
    worst = float(off.max()) if len(off) else 0.0
    ax.set_title(
        f"correlations of the {len(names)} identifiable error parameters (largest |r| {worst:.3f})",
        fontsize=10,
    )
    fig.subplots_adjust(left=0.12, right=0.95, bottom=0.12, top=0.94)
    return _save(fig, path)
