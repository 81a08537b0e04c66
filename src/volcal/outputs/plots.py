"""Plots of an identification, public (``volcal.plots``) and used by the result folder.

Every function returns a matplotlib ``Figure`` (shown inline in Jupyter) and writes it when
given a ``path``.  Each is two steps: a ``*_data`` function turns the result into plain data
(numpy arrays, numbers, strings; it needs the model, pandas and scipy) and
:mod:`volcal.outputs.figures` draws it (numpy and matplotlib only), so that the result
folder's plots can be drawn in a plotting child process (:func:`plot_requests`).

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

from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.distributions import norm_ppf
from volcal.outputs import figures as F

__all__ = [
    "component_errors",
    "volumetric_slices",
    "residuals",
    "residuals_vs_axes",
    "correlations",
    "component_errors_data",
    "volumetric_slices_data",
    "residuals_data",
    "residuals_vs_axes_data",
    "correlations_data",
    "plot_requests",
    "iter_plot_requests",
    "solved_plot_requests",
    "hold_solved_plots",
    "saved_plot_requests",
]

_VOL = ["dx_um", "dy_um", "dz_um"]

Target = F.Target


def _unit(spec, name: str) -> str:
    return "deg" if spec.axis(name).is_rotary else "mm"


# --------------------------------------------------------------------------------------
# component error motions


def component_errors_data(table: pd.DataFrame, error_model: Any) -> dict[str, Any]:
    """The data of :func:`component_errors` (see :func:`figures.draw_component_errors`)."""
    spec = error_model.spec
    out = []
    for a in spec.axes:
        sub = table[table["axis"] == a.name]
        if sub.empty:
            continue
        unit = _unit(spec, a.name)
        panels = []
        for quantity, u_name in (("translation", "um"), ("rotation", "urad")):
            series = []
            for s in error_model.errors:
                if s.axis != a.name or s.kind != "component" or s.quantity != quantity:
                    continue
                y = sub[f"{s.name}_{u_name}"].to_numpy(float)
                ucol = f"u_{s.name}_{u_name}"
                u = sub[ucol].to_numpy(float) if ucol in sub else None
                ok = u is None or bool(np.isfinite(u).all())
                series.append({"name": s.name, "y": y, "u": u if ok else None, "identifiable": ok})
            kind = "translational" if quantity == "translation" else "angular"
            panels.append(
                {"title": f"axis {a.name}: {kind} error motions", "unit": u_name, "series": series}
            )
        out.append(
            {
                "name": a.name,
                "unit": unit,
                "x": sub[f"position_{unit}"].to_numpy(float),
                "panels": panels,
            }
        )
    return {"axes": out}


def component_errors(table: pd.DataFrame, error_model: Any, path: Target = None):
    """The component error motions of ``table`` (:func:`volcal.outputs.results.
    component_error_table`: position per axis, value in um / urad, u_ columns) with +-2 u
    bands (a dashed line where not identifiable)."""
    return F.draw_component_errors(component_errors_data(table, error_model), path)


# --------------------------------------------------------------------------------------
# volumetric error maps


def volumetric_slices_data(
    machine: Any,
    error_model: Any,
    theta: np.ndarray,
    *,
    n: int = 25,
    heights: int = 3,
    angles: int = 4,
    tool: np.ndarray | None = None,
) -> dict[str, Any]:
    """The data of :func:`volumetric_slices` (see :func:`figures.draw_volumetric_slices`)."""
    from volcal.analysis.identify import predict_volumetric

    spec = machine.spec
    lin = [a for a in spec.axes if not a.is_rotary]
    rot = [a for a in spec.axes if a.is_rotary]
    if len(lin) < 2:
        return {"message": "volumetric slices need two linear axes"}
    ax1, ax2 = lin[0], lin[1]
    ax3 = lin[2] if len(lin) > 2 else None
    ref = {a.name: a.reference for a in spec.axes}
    slices: list[tuple[str, dict[str, float]]] = []

    def where(fixed: dict[str, float], first: str) -> str:
        # the slice's own axis first, then where every other axis not in the plane stands
        # (a reader must not have to guess the rotary axes' or the height's position)
        others = [
            f"{a.name} = {fixed.get(a.name, ref[a.name]):g} {_unit(spec, a.name)}"
            for a in spec.axes
            if a.name not in (ax1.name, ax2.name, first)
        ]
        head = f"{first} = {fixed.get(first, ref[first]):g} {_unit(spec, first)}"
        return head + (f"\n({', '.join(others)})" if others else "")

    if ax3 is not None:
        for h in np.linspace(ax3.travel[0], ax3.travel[1], heights):
            fixed = {ax3.name: float(h)}
            slices.append((where(fixed, ax3.name), fixed))
    else:
        slices.append((f"{ax1.name}{ax2.name} plane", {}))
    for r in rot:
        mid = {ax3.name: 0.5 * sum(ax3.travel)} if ax3 is not None else {}
        full = r.travel[1] - r.travel[0] >= 360 - 1e-9
        vals = np.linspace(r.travel[0], r.travel[1], angles + (1 if full else 0))
        vals = vals[:-1] if full else vals
        for v in vals:
            fixed = {r.name: float(v), **mid}
            slices.append((where(fixed, r.name), fixed))
    g1 = np.linspace(ax1.travel[0], ax1.travel[1], n)
    g2 = np.linspace(ax2.travel[0], ax2.travel[1], n)
    G1, G2 = np.meshgrid(g1, g2, indexing="ij")
    # one slice at a time: the field Jacobian of a slice is (n * n, 3, parameters)
    d_all = []
    for _, fixed in slices:
        q = np.tile([fixed.get(a.name, ref[a.name]) for a in spec.axes], (n * n, 1)).astype(float)
        q[:, spec.axis_names.index(ax1.name)] = G1.ravel()
        q[:, spec.axis_names.index(ax2.name)] = G2.ravel()
        t = np.zeros((n * n, 3)) if tool is None else np.tile(tool, (n * n, 1))
        pred = predict_volumetric(machine, error_model, theta, None, machine.axis_to_internal(q), t)
        d_all.append(pred[_VOL].to_numpy().reshape(n, n, 3))
    c1, c2 = "xyz".index(ax1.direction[-1]), "xyz".index(ax2.direction[-1])
    out = []
    for (title, _), d in zip(slices, d_all):
        out.append(
            {"title": title, "norm": np.linalg.norm(d, axis=2), "d1": d[..., c1], "d2": d[..., c2]}
        )
    vmax = max(float(np.max(s["norm"])) for s in out) or 1.0
    t = np.zeros(3) if tool is None else np.asarray(tool, float)
    what = "tool offset (" + ", ".join(f"{v:g}" for v in np.round(t, 1) + 0.0) + ") mm"
    return {
        "g1": g1,
        "g2": g2,
        "labels": (f"{ax1.name} (mm)", f"{ax2.name} (mm)"),
        "slices": out,
        "vmax": vmax,
        "title": f"Volumetric error (actual − nominal), {what}; arrows: in-plane components",
    }


def volumetric_slices(
    machine: Any,
    error_model: Any,
    theta: np.ndarray,
    path: Target = None,
    *,
    n: int = 25,
    heights: int = 3,
    angles: int = 4,
    tool: np.ndarray | None = None,
):
    """2-D maps of the volumetric error (tool offset ``tool`` mm, default 0): XY slices at
    ``heights`` positions of the third linear axis (rotary axes at their reference), and
    for each rotary axis XY slices at ``angles`` angles over its travel (the third linear
    axis mid-travel).  Colour: |d| (µm); arrows: the in-plane components, one scale for
    every panel (the key gives it); panels drawn to scale (equal mm on both axes)."""
    data = volumetric_slices_data(
        machine, error_model, theta, n=n, heights=heights, angles=angles, tool=tool
    )
    return F.draw_volumetric_slices(data, path)


# --------------------------------------------------------------------------------------
# residuals


def residuals_data(table: pd.DataFrame, max_points: int = 4000) -> dict[str, Any]:
    """The data of :func:`residuals` (see :func:`figures.draw_residuals`)."""
    r = table["residual_um"].to_numpy(float)
    rej = np.asarray(table["rejected"], bool) if "rejected" in table else np.zeros(len(r), bool)
    z = (
        table["normalised_residual"].to_numpy(float)
        if "normalised_residual" in table
        else r / np.nanstd(r)
    )
    keep = ~rej & np.isfinite(r)
    kept = r[keep]
    zs = np.sort(z[keep & np.isfinite(z)])
    qq, lim = None, 1.0
    if len(zs):
        sub = np.unique(np.linspace(0, len(zs) - 1, min(len(zs), max_points)).astype(int))
        # the normal quantiles of the points drawn only (sub holds the first and the last)
        theo = norm_ppf((sub + 0.5) / len(zs))
        qq = (theo, zs[sub])
        lim = float(max(abs(theo[0]), abs(theo[-1]), 1.0))
    idx = np.arange(1, len(r) + 1)
    step = max(1, len(r) // max_points)
    st = table["station"].astype(str).to_numpy() if "station" in table else np.full(len(r), "")
    by_station = []
    for sid in dict.fromkeys(st):
        m = (st == sid) & keep
        m[np.arange(len(m)) % step != 0] = False
        by_station.append((str(sid), idx[m], r[m]))
    return {
        "kept": kept,
        "rejected": r[rej],
        "rejected_at": idx[rej],
        "bins": max(10, min(60, int(np.sqrt(max(len(kept), 1))))),
        "rms": float(np.sqrt(np.mean(kept**2))) if len(kept) else float("nan"),
        "qq": qq,
        "lim": lim,
        "by_station": by_station,
    }


def residuals(table: pd.DataFrame, path: Target = None, max_points: int = 4000):
    """Histogram of the residuals (um), normal QQ plot of the standardised residuals and the
    residuals per reading by station (at most ``max_points`` drawn, rasterised)."""
    return F.draw_residuals(residuals_data(table, max_points), path)


def residuals_vs_axes_data(
    residuals: pd.DataFrame,
    axis_names: list[str],
    units: list[str],
    adequacy: Any = None,
    max_points: int = 4000,
) -> dict[str, Any]:
    """The data of :func:`residuals_vs_axes` from a residual table (normalised residuals,
    axis positions, station), its axes and their units, and the model adequacy
    (:func:`volcal.analysis.adequacy.assess`, for the F test per axis; optional)."""
    from volcal.analysis.adequacy import format_p, position_bins

    z = residuals["normalised_residual"].to_numpy(float)
    rej = (
        np.asarray(residuals["rejected"], bool)
        if "rejected" in residuals
        else np.zeros(len(z), bool)
    )
    keep = np.isfinite(z) & ~rej
    unit_of = dict(zip(axis_names, units))
    st = (
        residuals["station"].astype(str).to_numpy()
        if "station" in residuals
        else np.full(len(z), "all")
    )
    by_axis = {s.axis: s for s in (adequacy.structure if adequacy else ()) if s.kind == "axis"}
    idx = np.flatnonzero(keep)
    sub = idx[:: max(1, int(np.ceil(len(idx) / max_points)))]
    zk, sk = z[keep], st[keep]
    panels = []
    for name in (a for a in axis_names if a in residuals.columns):
        x = residuals[name].to_numpy(float)
        code, centres = position_bins(x[keep])
        means = []
        for sid in dict.fromkeys(sk):
            m = sk == sid
            cnt = np.bincount(code[m], minlength=len(centres))
            mean = np.bincount(code[m], weights=zk[m], minlength=len(centres))
            ok = cnt > 0
            means.append((centres[ok], mean[ok] / cnt[ok]))
        cnt = np.bincount(code, minlength=len(centres))
        rms = np.sqrt(np.bincount(code, weights=zk**2, minlength=len(centres)) / np.maximum(cnt, 1))
        ok = cnt > 0
        u = unit_of.get(name, "")
        s = by_axis.get(name)
        panels.append(
            {
                "xlabel": f"{name} position ({u})" if u else name,
                "title": f"axis {name}"
                + (
                    f": F = {s.f:.3g}, {format_p(s)}" + (" (significant)" if s.significant else "")
                    if s
                    else ""
                ),
                "x": x[sub],
                "z": z[sub],
                "means": means,
                "rms": (centres[ok], rms[ok]),
            }
        )
    head = (
        "Normalised residuals (residual / sigma) against axis position; lines: binned "
        "means per station"
    )
    if adequacy is not None:
        head += (
            f"\nchi2/dof {adequacy.chi2_per_dof:.4g}, 99.9 % interval "
            f"[{adequacy.interval[0]:.4g}, {adequacy.interval[1]:.4g}]: "
            + {
                "fits": "the model fits",
                "budget_pessimistic": "the model fits, the budget is pessimistic",
            }.get(adequacy.verdict, "the model does NOT fit")
        )
    return {"panels": panels, "title": head}


def residuals_vs_axes(result: Any, path: Target = None):
    """Normalised residuals against each axis position (one panel per axis), with the
    binned means per station (lines) and the binned RMS over all stations (black dashed);
    the title gives the model adequacy test (:func:`volcal.analysis.adequacy.assess`)."""
    from volcal.analysis.adequacy import assess

    spec = result.machine.spec
    data = residuals_vs_axes_data(
        result.residuals,
        spec.axis_names,
        [_unit(spec, a) for a in spec.axis_names],
        adequacy=assess(result),
    )
    return F.draw_residuals_vs_axes(data, path)


# --------------------------------------------------------------------------------------
# correlations


def _datum_determined(result: Any, keep: np.ndarray) -> np.ndarray:
    """Mask of the parameters (among ``keep``) that the datum conditions in force determine
    from the others: one pivot column of C per independent condition."""
    from volcal.base.linalg import pivot_order
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
    # QR with column pivoting (no scipy import in a plotting run): the pivoted R's
    # diagonal is the unpivoted QR's of the columns in pivot order
    piv = pivot_order(Ck)
    d = np.abs(np.diag(np.asarray(np.linalg.qr(Ck[:, piv], mode="r"))))
    rank = int(np.sum(d > 1e-10 * (d[0] if len(d) else 1.0)))
    out[cols[piv[:rank]]] = True
    return out


def correlations_data(result: Any) -> dict[str, Any]:
    """The data of :func:`correlations`: the correlation matrix ``R`` of the identifiable
    error parameters and their ``names``."""
    cov = np.asarray(result.cov_theta, float)
    var = np.diag(cov)
    keep = np.asarray(result.identifiable, bool) & np.isfinite(var) & (var > 0)
    # the datum conditions in force tie some parameters exactly to others: leave out one
    # parameter per condition (QR with column pivoting picks them), so the picture shows
    # the correlations the data leave, not the datum's
    keep &= ~_datum_determined(result, keep)
    em = result.error_model
    names = [n for n, k in zip(em.param_names, keep) if k]
    # the axis each parameter's error quantity belongs to ("T": the tool), to label the
    # matrix by blocks when there are too many parameters to name each
    groups = [em.errors[e].axis for e, k in zip(em.param_error, keep) if k]
    C = cov[np.ix_(keep, keep)]
    d = np.sqrt(np.diag(C))
    R = C / np.outer(d, d) if len(d) else np.zeros((0, 0))
    return {"R": R, "names": names, "groups": groups}


def correlations(result: Any, path: Target = None, max_labels: int = 30):
    """Correlation matrix of the identifiable error parameters, beside the strongest
    pairs by name: parameters that are held, unidentifiable, fixed by the datum alone
    (zero variance) or determined from the others by a datum condition are left out, so
    the picture shows what the data determine, not the datum's ties.  Up to
    ``max_labels`` parameters are named on the matrix; more are labelled by the axis their
    error quantity belongs to."""
    return F.draw_correlations(correlations_data(result), path, max_labels)


# --------------------------------------------------------------------------------------
# the result folder


def iter_plot_requests(
    result: Any,
    component_table: pd.DataFrame,
    *,
    residuals: pd.DataFrame | None = None,
    adequacy: Any = "assess",
    skip: Collection[str] = (),
) -> Iterator[tuple[str, Any, dict, float]]:
    """:func:`plot_requests` one figure at a time, each as soon as its data are ready: a
    plotting child starts drawing the first while this process prepares the next, and
    the model adequacy test (for the title of ``residuals_vs_axes.png`` only) is computed
    last, after the other figures are on their way.  ``skip``: the names of figures
    asked for already (:func:`hold_solved_plots`)."""
    spec = result.machine.spec
    if residuals is None:
        residuals = result.residuals
    # in the order of F.COSTS (the children's frames built ahead expect it); the first
    # two are those of solved_plot_requests
    cost = F.COSTS
    yield from _no_covariance_requests(
        result.machine, result.error_model, result.theta, residuals, skip
    )
    yield (
        "component_errors.png",
        F.draw_component_errors,
        component_errors_data(component_table, result.error_model),
        cost["component_errors.png"],
    )
    yield (
        "correlations.png",
        F.draw_correlations,
        correlations_data(result),
        cost["correlations.png"],
    )
    if isinstance(adequacy, str) and adequacy == "assess":
        from volcal.analysis.adequacy import assess

        adequacy = assess(result)
    yield (
        "residuals_vs_axes.png",
        F.draw_residuals_vs_axes,
        residuals_vs_axes_data(
            residuals,
            spec.axis_names,
            [_unit(spec, a) for a in spec.axis_names],
            adequacy=adequacy,
        ),
        cost["residuals_vs_axes.png"],
    )


def solved_plot_requests(solved: Any) -> Iterator[tuple[str, Any, dict, float]]:
    """The result folder's figures that need no covariance, ``volumetric_map.png`` and
    ``residuals.png``, as :func:`iter_plot_requests` yields them, from what a fit knows
    once its solve has ended (:class:`volcal.analysis.identify.Solved`): the same data,
    so the same figures, as from the finished result."""
    return _no_covariance_requests(
        solved.machine, solved.error_model, solved.theta, solved.residuals
    )


def _no_covariance_requests(
    machine: Any,
    error_model: Any,
    theta: np.ndarray,
    residuals: pd.DataFrame,
    skip: Collection[str] = (),
) -> Iterator[tuple[str, Any, dict, float]]:
    """The requests of ``volumetric_map.png`` and ``residuals.png`` (no covariance
    needed), each but those in ``skip``, its data made only when it is yielded: the one
    definition of both for a finished result (:func:`iter_plot_requests`) and for a
    fit whose solve has just ended (:func:`solved_plot_requests`)."""
    if "volumetric_map.png" not in skip:
        yield (
            "volumetric_map.png",
            F.draw_volumetric_slices,
            volumetric_slices_data(machine, error_model, theta),
            F.COSTS["volumetric_map.png"],
        )
    if "residuals.png" not in skip:
        yield (
            "residuals.png",
            F.draw_residuals,
            residuals_data(residuals),
            F.COSTS["residuals.png"],
        )


def hold_solved_plots(plotter: Any, solved: Any) -> dict[str, int]:
    """Send :func:`solved_plot_requests` to ``plotter``'s children
    (:class:`volcal.outputs.plot_process.PlotProcess`) as soon as the solve has ended,
    to be drawn while the uncertainty is computed and kept in memory until the result
    folder exists (:func:`figures.hold`); returns ``{file name: child}`` for
    :func:`volcal.outputs.results.save_result` (``held``), which has them written."""
    held: dict[str, int] = {}
    for name, draw, data, cost in solved_plot_requests(solved):
        held[name] = plotter.draw(F.hold, draw, data, name, cost=cost)
    return held


def plot_requests(
    result: Any,
    component_table: pd.DataFrame,
    *,
    residuals: pd.DataFrame | None = None,
    adequacy: Any = "assess",
) -> list[tuple[str, Any, dict, float]]:
    """The result folder's plots as ``(file name, drawing function, data, cost)`` in the
    order of :data:`figures.COSTS`: those that need no covariance first (sent before the
    uncertainty stage by ``volcal identify``), ``residuals_vs_axes.png``, which needs
    the adequacy test, last (see :func:`iter_plot_requests`); cost: the relative drawing
    time (measured on the example), by which :class:`volcal.outputs.plot_process.
    PlotProcess` shares them between its children.

    result: an identification result, or a saved one (:func:`saved_plot_requests`);
    component_table: :func:`volcal.outputs.results.component_error_table`; residuals and
    adequacy: the residual table and model adequacy (default ``result.residuals`` and
    :func:`volcal.analysis.adequacy.assess` of the result; None: no adequacy test in the
    residual plot's title)."""
    return list(iter_plot_requests(result, component_table, residuals=residuals, adequacy=adequacy))


def saved_plot_requests(saved: Any) -> list[tuple[str, Any, dict, float]]:
    """:func:`plot_requests` of a saved result (:func:`volcal.outputs.results.
    load_result`), from its folder's tables (``component_errors.csv``,
    ``residuals.csv``) and saved adequacy test: the same data, so the same figures, as
    ``volcal identify`` draws (a result written with ``--no-plots`` can get its plots
    later, e.g. in ``volcal report``)."""
    from volcal.analysis.adequacy import Adequacy

    folder = Path(saved.path)
    ad = saved.meta.get("adequacy")
    return plot_requests(
        saved,
        pd.read_csv(folder / "component_errors.csv"),
        residuals=pd.read_csv(folder / "residuals.csv"),
        adequacy=Adequacy.from_dict(ad) if ad else None,
    )
