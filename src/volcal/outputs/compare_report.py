"""The folder of ``volcal compare``: strategies side by side, as tables, text and a plot.

:func:`write_comparison` writes a :class:`volcal.workflow.comparison.Comparison` as one folder
(temporary folder renamed into place, ``manifest.json``; :func:`volcal.base.folders.write_folder`):

``comparison.csv``             one row per strategy (the columns of
                               :func:`volcal.workflow.comparison.compare`, units in the names);
``parameter_differences.csv``  per strategy and parameter both fits identify: values,
                               difference and the difference over the reference's u
                               (um / urad);
``workspace_points.csv``       the workspace sample (axes mm / deg, tool offsets, nominal
                               points mm), the reference's standard uncertainty modulo the
                               gauge and each strategy's field difference |d| (um; with a
                               truth also its field error);
``trials.csv``                 with trials: one row per trial and strategy;
``compare.md``                 the table and notes in Markdown;
``compare.html``               the same as an HTML section (``volcal report`` embeds it);
``field_differences.png``      the field differences (and errors against the truth or over
                               the trials) per strategy;
``compare.json``               the settings and the table, for readers (``volcal report``);
``reference/``                 the reference strategy's result folder (no plots), so that
                               ``volcal report --result DIR`` reports it with the comparison.
"""

from __future__ import annotations

import base64
import io
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from volcal import __version__
from volcal.base.exceptions import InputError

if TYPE_CHECKING:
    from volcal.workflow.comparison import Comparison

__all__ = [
    "COMPARE_FILES",
    "COMPARE_FORMAT",
    "format_table",
    "write_comparison",
    "load_comparison",
    "is_comparison",
    "comparison_section",
    "section_context",
    "REFERENCE_DIR",
]

COMPARE_FORMAT = "volcal-compare"
COMPARE_FILES = (
    "comparison.csv",
    "parameter_differences.csv",
    "workspace_points.csv",
    "trials.csv",
    "compare.md",
    "compare.html",
    "field_differences.png",
    "compare.json",
)
REFERENCE_DIR = "reference"
PLOT = "field_differences.png"
#: unidentifiable names shown per strategy in the printed table
_SHOWN_NAMES = 3


def _g(v: Any, digits: int = 3) -> str:
    """The report's number format (html_report), "-" where there is no number."""
    from volcal.outputs.report_env import number

    return number(v, digits, missing="-")


def _rows(table: pd.DataFrame, reference: str) -> tuple[list[str], list[list[str]]]:
    """Headers and text rows of the side-by-side table (terminal, Markdown and HTML)."""
    has_truth = "truth_error_rms_um" in table
    has_trials = "trials_error_rms_mean_um" in table
    head = [
        "strategy",
        "status",
        "chi2/dof",
        "verdict",
        "resid. RMS um",
        f"field diff to {reference} RMS/max um",
        "RMS/max in u",
        "largest param. diff (u)",
        "unidentifiable",
        "time s",
    ]
    if has_truth:
        head.append("error vs truth RMS/max um")
    if has_trials:
        head.append("trials: error RMS um, mean ± sd")
    rows = []
    for r in table.to_dict("records"):
        ok = bool(r["success"])
        names = str(r.get("unidentifiable") or "").split()
        n_un = r.get("n_unidentifiable")
        un = (
            "-"
            if not ok
            else (
                "none"
                if not names
                else f"{len(names)}: {' '.join(names[:_SHOWN_NAMES])}"
                + (" ..." if len(names) > _SHOWN_NAMES else "")
            )
        )
        if ok and n_un is not None and not names and float(n_un or 0) > 0:
            un = str(int(n_un))
        is_ref = r["strategy"] == reference
        row = [
            str(r["strategy"]),
            "solved" if ok else f"FAILED ({r['status']})",
            _g(r["chi2_per_dof"]),
            # the most likely cause beside the verdict (comparison.csv has them all)
            str(r["verdict"])
            + (f" ({str(r.get('causes')).split()[0]})" if r.get("causes") else ""),
            _g(r["residual_rms_um"]),
            "reference"
            if is_ref and ok
            else f"{_g(r['field_diff_rms_um'])} / {_g(r['field_diff_max_um'])}",
            ""
            if is_ref and ok
            else f"{_g(r['field_diff_rms_in_u'])} / {_g(r['field_diff_max_in_u'])}",
            str(r.get("largest_parameter_differences") or ("" if is_ref else "-")),
            un,
            _g(r["time_s"], 2),
        ]
        if has_truth:
            row.append(f"{_g(r['truth_error_rms_um'])} / {_g(r['truth_error_max_um'])}")
        if has_trials:
            row.append(
                f"{_g(r['trials_error_rms_mean_um'])} ± {_g(r['trials_error_rms_sd_um'], 2)}"
                + (f" ({int(r['trials_failed'])} failed)" if r.get("trials_failed") else "")
            )
        rows.append(row)
    return head, rows


def format_table(table: pd.DataFrame, reference: str, fmt: str = "simple") -> str:
    """The side-by-side table as text (``fmt``: a tabulate format: ``simple`` for the
    terminal, ``github`` for Markdown)."""
    from tabulate import tabulate

    head, rows = _rows(table, reference)
    return tabulate(rows, headers=head, tablefmt=fmt, disable_numparse=True)


def _explanation(doc: dict[str, Any]) -> list[str]:
    """What the columns mean, in sentences (Markdown and HTML)."""
    ref = doc["reference"]
    out = [
        f"Every strategy identified the same {doc['n_readings']} readings of model "
        f"`{doc['model']}` with the same error model, budget and start values.",
        f"Field difference to {ref}: the volumetric errors of the two fits at "
        f"{doc['n_points']} workspace points (the declared travel at every measured tool "
        "offset), their difference with the best-fitting rigid motion removed (the gauge "
        "no multilateration sees); RMS and max of its norm in um, and in units of the "
        f"{ref} fit's standard uncertainty of the volumetric error modulo the same rigid "
        "motion (per point, root sum of squares of the components). Points one of the two "
        "fits does not determine are left out.",
        f"Largest parameter differences: strategy minus {ref}, over {ref}'s standard "
        "uncertainty, for parameters both fits identify.",
        "Verdict: the model adequacy test of each fit (volcal.analysis.adequacy): fits, "
        "budget_pessimistic (fits; chi2/dof below its 99.9 % interval without residual "
        "structure) or does_not_fit (chi2/dof above the interval or residual structure at "
        "p < 1e-6), with the most likely cause in brackets (strategy: a biased strategy; "
        "basis, tool_offset, station, drift: where the structure is; outliers; budget; "
        "all of them in the causes column of comparison.csv).",
    ]
    if doc.get("truth_source"):
        out.append(
            f"Error vs truth: each fit's volumetric error minus the true one "
            f"({doc['truth_source']}; exact model), rigid motion removed, at the same points."
        )
    if doc.get("trials"):
        out.append(
            f"Trials: {doc['trials']} simulated data sets with the data's poses, tool offsets "
            f"and stations, true errors from {doc['trials_truth']}, the budget's noise "
            f"(seed {doc['seed']}); each strategy's field error against that truth, mean and "
            "standard deviation over the trials."
        )
    return out


def _markdown(doc: dict[str, Any], table: pd.DataFrame) -> str:
    lines = [
        f"# Strategies compared: {doc['model']}",
        "",
        format_table(table, doc["reference"], "github"),
        "",
        *[f"- {s}" for s in _explanation(doc)],
    ]
    if doc.get("notes"):
        lines += ["", "Notes:", *[f"- {n}" for n in doc["notes"]]]
    lines += ["", f"![field differences]({PLOT})", ""]
    return "\n".join(lines)


def section_context(doc: dict[str, Any], table: pd.DataFrame, png: bytes | None) -> dict:
    """What ``templates/report/compare_section.html.j2`` shows (the plot as a data URI)."""
    head, rows = _rows(table, doc["reference"])
    uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii") if png else ""
    return {
        "model": doc["model"],
        "reference": doc["reference"],
        "head": head,
        "rows": rows,
        "explanation": _explanation(doc),
        "notes": doc.get("notes") or [],
        "plot": uri,
    }


def comparison_section(doc: dict[str, Any], table: pd.DataFrame, png: bytes | None) -> str:
    """The comparison as an HTML ``<section>`` (Jinja2 template
    ``templates/report/compare_section.html.j2``, autoescaped), the plot embedded as a data
    URI; ``volcal report`` includes the same section."""
    from volcal.outputs.report_env import environment

    return (
        environment()
        .get_template("compare_section.html.j2")
        .render(cmp=section_context(doc, table, png))
    )


# --------------------------------------------------------------------------------------
# the plot


def _plot_data(cmp: Comparison) -> dict[str, Any]:
    """Plain data of the field-differences figure: per strategy the norm of its field
    difference to the reference at the compared points (um), the reference's u there, the
    errors against the truth and the trials' RMS errors."""
    series = []
    for s in cmp.strategies:
        d = cmp.differences.get(s)
        e = (cmp.truth_errors or {}).get(s)
        t = (
            cmp.trials.loc[
                (cmp.trials["strategy"] == s) & cmp.trials["success"], "field_error_rms_um"
            ].to_numpy(float)
            if cmp.trials is not None
            else None
        )
        series.append(
            {
                "name": s,
                "diff": None if d is None else _finite_norms(d),
                "truth": None if e is None else _finite_norms(e),
                "trials": t,
            }
        )
    u = cmp.points["u_reference_um"].to_numpy(float)
    return {
        "reference": cmp.reference,
        "series": series,
        "u_median": float(np.nanmedian(u)) if np.isfinite(u).any() else float("nan"),
    }


def _finite_norms(d: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(d, axis=1)
    return n[np.isfinite(n)]


def draw_field_differences(data: dict[str, Any], path=None):
    """Box plots of |field difference to the reference| per strategy (um), the reference's
    median standard uncertainty as a line; beside it the field errors against the truth
    and the trials' RMS errors when there are any."""
    from volcal.outputs.figures import figure, save

    series = data["series"]
    names = [s["name"] for s in series]
    panels = [("diff", f"|field difference to {data['reference']}| (um), gauge removed")]
    if any(s["truth"] is not None for s in series):
        panels.append(("truth", "|field error against the truth| (um), gauge removed"))
    if any(s["trials"] is not None for s in series):
        panels.append(("trials", "field error RMS over simulated trials (um)"))
    fig = figure(4.2 * len(panels) + 0.6, 3.8, layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (key, title) in zip(axes, panels):
        vals = [
            s[key] if s[key] is not None and len(s[key]) else np.array([np.nan]) for s in series
        ]
        ax.boxplot(vals, whis=(0, 100), widths=0.5)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=20)
        ax.set_title(title, fontsize=9)
        ax.set_ylabel("um")
        if key == "diff" and math.isfinite(data["u_median"]):
            ax.axhline(data["u_median"], color="tab:red", linestyle="--", linewidth=0.8)
            ax.text(
                0.02,
                0.97,
                f"-- median u of {data['reference']}: {data['u_median']:.3g} um",
                transform=ax.transAxes,
                va="top",
                fontsize=8,
                color="tab:red",
            )
        ax.locator_params(axis="y", nbins=5)
    return save(fig, path)


# --------------------------------------------------------------------------------------
# the folder


def _doc(cmp: Comparison) -> dict[str, Any]:
    return {
        "format": COMPARE_FORMAT,
        "format_version": 1,
        "volcal_version": __version__,
        "model": cmp.model,
        "reference": cmp.reference,
        "strategies": list(cmp.strategies),
        "n_readings": int(cmp.n_readings),
        "n_points": int(len(cmp.points)),
        "truth_source": cmp.truth_source,
        "trials": cmp.n_trials,
        "trials_truth": cmp.trials_truth,
        "seed": int(cmp.seed),
        "seconds": float(cmp.seconds),
        "notes": list(cmp.notes),
        "reference_result": REFERENCE_DIR if cmp.reference_result is not None else None,
    }


def write_comparison(
    cmp: Comparison,
    out_dir: str | Path,
    *,
    plots: bool = True,
    data_name: str = "",
    inputs: tuple = (),
    force: bool | None = None,
) -> Path:
    """Write the comparison folder (module docstring) atomically and return its path.
    data_name: the data file recorded in the reference's result; inputs: paths the run
    read (never inside the output); force: see :func:`volcal.base.folders.check_out_dir`."""
    from volcal.base.folders import write_folder
    from volcal.outputs.results import _json_safe, save_result

    doc = _doc(cmp)
    table = cmp.table
    png = None
    if plots:
        buf = io.BytesIO()
        draw_field_differences(_plot_data(cmp), buf)
        png = buf.getvalue()
    pts = cmp.points.copy()
    for s in cmp.strategies:
        if s in cmp.differences and s != cmp.reference:
            pts[f"diff_{s}_um"] = np.linalg.norm(cmp.differences[s], axis=1)
        if cmp.truth_errors and s in cmp.truth_errors:
            pts[f"truth_error_{s}_um"] = np.linalg.norm(cmp.truth_errors[s], axis=1)

    def writer(tmp: Path) -> None:
        table.to_csv(tmp / "comparison.csv", index=False)
        cmp.parameter_differences.to_csv(tmp / "parameter_differences.csv", index=False)
        pts.to_csv(tmp / "workspace_points.csv", index=False)
        if cmp.trials is not None:
            cmp.trials.to_csv(tmp / "trials.csv", index=False)
        (tmp / "compare.md").write_text(_markdown(doc, table), encoding="utf-8")
        (tmp / "compare.html").write_text(comparison_section(doc, table, png), encoding="utf-8")
        if png is not None:
            (tmp / PLOT).write_bytes(png)
        full = dict(doc, table=_json_safe(table.to_dict("records")))
        (tmp / "compare.json").write_text(json.dumps(full, indent=1) + "\n", encoding="utf-8")
        ref = cmp.reference_result
        if ref is not None:
            save_result(
                ref,
                tmp / REFERENCE_DIR,
                data_name=data_name,
                plots=False,
                options={"strategy": ref.strategy, "written_by": "volcal compare"},
                force=True,
            )

    return write_folder(
        out_dir,
        COMPARE_FILES,
        "volcal compare",
        writer,
        marker="compare.json",
        inputs=inputs,
        allowed_dirs=(REFERENCE_DIR,),
        force=force,
    )


def is_comparison(folder: str | Path) -> bool:
    """Is ``folder`` a folder written by ``volcal compare``?"""
    return (Path(folder) / "compare.json").is_file()


def load_comparison(folder: str | Path) -> tuple[dict[str, Any], pd.DataFrame, bytes | None]:
    """(compare.json, comparison.csv, the plot's PNG or None) of a ``volcal compare``
    folder, checked against its manifest; :class:`InputError` naming the folder when it is
    not one."""
    from volcal.base.folders import verify_manifest

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(
            "no such folder (expected a folder written by `volcal compare`)", source=str(folder)
        )
    if not is_comparison(folder):
        raise InputError(
            "no compare.json here; expected a folder written by `volcal compare`",
            source=str(folder),
        )
    verify_manifest(folder, required=True)
    try:
        doc = json.loads((folder / "compare.json").read_text(encoding="utf-8"))
        table = pd.read_csv(folder / "comparison.csv", keep_default_na=False, na_values=[""])
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the comparison ({exc})", source=str(folder)) from None
    if not isinstance(doc, dict) or doc.get("format") != COMPARE_FORMAT:
        raise InputError(
            f'not a volcal comparison (expected "format": "{COMPARE_FORMAT}")',
            source=str(folder / "compare.json"),
        )
    for col in ("unidentifiable", "largest_parameter_differences", "status", "verdict", "causes"):
        if col in table:
            table[col] = [("" if pd.isna(v) else str(v)) for v in table[col]]
    png = (folder / PLOT).read_bytes() if (folder / PLOT).is_file() else None
    return doc, table, png
