"""Files and plots of a Monte Carlo run (``volcal mc``, the studies).

:func:`write_mc_outputs` writes, next to the resumable ``samples/`` folder:

=======================  ================================================================
``parameters.csv``       per error parameter and station coordinate: value, GUM S1 mean,
                         u, U (k = 2), 95 % coverage interval, linearised u and the ratio
``error_motions.csv``    every error motion at the ends of its travel (and location errors)
                         with u, U, interval (the paper 002 Table 3 form)
``volumetric.csv``       per evaluation pose: dx, dy, dz and |d| with u, U, interval
``contributions.csv``    u per quantity per input source, one source at a time (+ linear)
``comparison.csv``       E_n against a reference table (when one is given)
``summary.json``         run figures: trials, seed, timing, agreement, largest errors
``report.md``            the human-readable summary
``*.png``                contributions (paper 002 Fig. 5 form), volumetric U map,
                         distribution of the largest volumetric error
=======================  ================================================================
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.analysis.uncertainty.montecarlo import MCResult, quantity_table
from volcal.outputs.figures import figure
from volcal.outputs.mc_plots import _plot_max_hist, _plot_volumetric_U
from volcal.outputs.plot_process import PlotProcess

__all__ = ["write_mc_outputs", "default_quantities", "plot_contributions"]


def default_quantities(error_model) -> list[str]:
    """Every component error motion at the end of its travel farther from its reference
    (where the datum does not hold it at zero), and every location error."""
    out = []
    spec = error_model.spec
    for s in error_model.errors:
        if s.kind != "component":
            out.append(s.name)
            continue
        a = spec.axis(s.axis)
        lo, hi = a.travel
        far = hi if abs(hi - a.reference) >= abs(lo - a.reference) else lo
        if error_model.forms[error_model.errors.index(s)].kind == "constant":
            out.append(f"{s.name}({far:g})")
            continue
        # a straightness held at both ends: its middle
        straight = (
            error_model.datum == "iso230"
            and not a.is_rotary
            and s.quantity == "translation"
            and s.component != a.dir_index
        )
        out.append(f"{s.name}({(lo + hi) / 2:g})" if straight else f"{s.name}({far:g})")
    return out


def _atomic_csv(df: pd.DataFrame, path: Path, **kw) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(fd)
    df.to_csv(tmp, **kw)
    os.replace(tmp, path)


def _atomic_text(text: str, path: Path) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def plot_contributions(
    table: pd.DataFrame, total: pd.DataFrame, path: Path, title: str = "", label: str = "{} only"
) -> None:
    """Expanded uncertainty (k = 2) per quantity: all sources, and each source alone
    (paper 002 Fig. 5 form).  table: quantity, unit, source, u; total: name, unit, U."""
    units = [u for u in ("um", "urad") if (total["unit"] == u).any()]
    fig = figure(13, 4.2 * max(1, len(units)), layout="constrained")
    axes = fig.subplots(max(1, len(units)), 1, squeeze=False)[:, 0]
    sources = list(dict.fromkeys(table["source"]))
    for ax, unit in zip(axes, units):
        tot = total[total["unit"] == unit]
        x = np.arange(len(tot))
        ax.plot(x, tot["U"].to_numpy(), "s", color="k", label="all sources")
        for s in sources:
            sub = table[table["source"] == s].set_index("quantity")
            y = [2 * sub["u"].get(n, np.nan) for n in tot["name"]]
            ax.plot(x, y, "o", markersize=4, alpha=0.8, label=label.format(s))
        ax.set_xticks(x, tot["name"], rotation=60, fontsize=8, ha="right")
        ax.set_ylabel(f"expanded uncertainty U, k = 2 ({unit})")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)


def write_mc_outputs(
    out_dir: str | Path,
    mc: MCResult,
    error_model,
    *,
    contributions: pd.DataFrame | None = None,
    reference: pd.DataFrame | None = None,
    quantities: list[str] | None = None,
    plots: bool = True,
    extra: dict[str, Any] | None = None,
    stages=None,
    plotter: PlotProcess | None = None,
) -> dict[str, Any]:
    """Write the run's tables, plots and summary into ``out_dir`` (created; the
    ``samples/`` folder of the run is kept).  Returns the summary dict.  stages: a
    :class:`volcal.base.timing.Stages` that receives the seconds of tables and plots;
    plotter: a :class:`PlotProcess` that draws the volumetric plots meanwhile (else they
    are drawn here)."""
    from volcal.analysis.uncertainty.evaluation import compare_with_reference
    from volcal.base.timing import Stages

    st = stages if stages is not None else Stages()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if plots:
        # the plots first (from the few figures they need): a plotting process draws them
        # while the tables are computed and written
        with st("plots"):
            args_u = (
                2 * mc.norm_u_um(),
                float(np.linalg.norm(mc.estimate_um(), axis=1).max()),
                mc.kernel.volmap.points,
                out / "volumetric_U.png",
            )
            args_h = (mc.norm_um().max(axis=1), out / "max_volumetric.png")
            if plotter is not None:
                plotter.draw(_plot_volumetric_U, *args_u)
                plotter.draw(_plot_max_hist, *args_h)
            else:
                _plot_volumetric_U(*args_u)
                _plot_max_hist(*args_h)
    with st("tables"):
        par = mc.parameters()
        _atomic_csv(par, out / "parameters.csv", index=False)
        qs = quantities or default_quantities(error_model)
        qt = quantity_table(mc, error_model, qs)
        _atomic_csv(qt, out / "error_motions.csv", index=False)
        vol = mc.volumetric()
        _atomic_csv(vol, out / "volumetric.csv", index=False)
        mv = mc.max_volumetric()
        agree = mc.agreement()
        s = mc.samples
        summary: dict[str, Any] = {
            "trials": s.n,
            "seed": s.seed,
            "mode": s.mode,
            "sources": mc.kernel.source_names,
            "enabled": list(s.enabled) if s.enabled else None,
            "seconds": s.seconds,
            "resumed_chunks": s.resumed_chunks,
            "not_converged": int((~s.converged).sum()),
            "iterations": {
                str(k): int(v) for k, v in zip(*np.unique(s.iterations, return_counts=True))
            },
            "agreement_with_linearised": agree,
            "max_volumetric": mv,
            "notes": mc.kernel.sampler.notes,
        }
        summary.update(extra or {})
        comp = None
        if reference is not None:
            both = pd.concat([qt, par[["name", "unit", "value", "U"]]], ignore_index=True)
            both = both.drop_duplicates("name")
            comp = compare_with_reference(both, reference)
            _atomic_csv(comp, out / "comparison.csv", index=False)
            summary["comparison"] = {
                "n": int(len(comp)),
                "agree": int(comp["agrees"].sum()),
                "max_E_n": float(np.nanmax(comp["E_n"])),
            }
        if contributions is not None:
            wide = contributions.pivot_table(
                index=["quantity", "unit"], columns="source", values="u", sort=False
            ).reset_index()
            _atomic_csv(wide, out / "contributions.csv", index=False)
    if plots:
        with st("plots"):
            if contributions is not None:
                tot = par[par["name"].isin(contributions["quantity"])][["name", "unit", "U"]]
                tot = tot[tot["unit"].isin(["um", "urad"])]
                # error parameters only (stations are instrument set-up, not machine errors)
                tot = tot[~tot["name"].str.contains(r"\.")]
                plot_contributions(
                    contributions,
                    tot,
                    out / "contributions.png",
                    "Expanded uncertainty of the error parameters by input source",
                )
    with st("summary and report"):
        _atomic_text(json.dumps(summary, indent=2, default=float) + "\n", out / "summary.json")
        _atomic_text(
            _markdown(summary, qt, comp, contributions is not None, plots), out / "report.md"
        )
    if plots and plotter is not None:
        with st("plots"):
            plotter.wait()
    return summary


def _markdown(summary, qt: pd.DataFrame, comp, has_contrib: bool, plots: bool) -> str:
    mv = summary["max_volumetric"]
    ag = summary["agreement_with_linearised"]
    lines = [
        "# Monte Carlo uncertainty (GUM Supplement 1)",
        "",
        f"{summary['trials']} trials ({summary['mode']}), seed {summary['seed']}, "
        f"{summary['seconds']:.1f} s; input sources: {', '.join(summary['sources'])}; "
        f"not converged: {summary['not_converged']}.",
        "",
        f"Largest volumetric error over the evaluation poses: {mv['max_norm_um']:.2f} um, "
        f"expanded uncertainty of |d| there U = {mv['U_norm_at_max_um']:.2f} um (k = 2); "
        f"largest U(|d|) over the poses {mv['U_norm_largest_um']:.2f} um; 95 % interval "
        f"of the largest error [{mv['max_ci95_low_um']:.2f}, "
        f"{mv['max_ci95_high_um']:.2f}] um.",
        "",
        f"Linearised vs Monte Carlo standard uncertainties: parameters max relative "
        f"difference {100 * ag['parameters_max_rel_diff']:.1f} % (median ratio "
        f"{ag['parameters_median_ratio']:.3f}); volumetric components "
        f"{100 * ag['volumetric_max_rel_diff']:.1f} % (median ratio "
        f"{ag['volumetric_median_ratio']:.3f}).",
        "",
        "## Error motions (value at the identification, U with k = 2)",
        "",
        "| quantity | value | U (k = 2) | 95 % interval | unit |",
        "|---|---|---|---|---|",
    ]
    for r in qt.itertuples():
        lines.append(
            f"| {r.name} | {r.value:.3f} | {r.U:.3f} | [{r.ci95_low:.3f}, "
            f"{r.ci95_high:.3f}] | {r.unit} |"
        )
    lines.append("")
    if comp is not None:
        lines += [
            "## Comparison with the reference (E_n, paper 002 eq. 25)",
            "",
            "| quantity | value | U | reference | U ref | E_n |",
            "|---|---|---|---|---|---|",
        ]
        for r in comp.itertuples():
            lines.append(
                f"| {r.name} | {r.value:.3f} | {r.U:.3f} | {r.reference:.3f} | "
                f"{r.U_reference:.3f} | {r.E_n:.2f} |"
            )
        lines.append("")
    if plots:
        lines += [
            "![volumetric U](volumetric_U.png)",
            "",
            "![largest error](max_volumetric.png)",
            "",
        ]
        if has_contrib:
            lines += ["![contributions](contributions.png)", ""]
    for n in summary.get("notes", []):
        lines.append(f"Note: {n}")
    return "\n".join(lines) + "\n"
