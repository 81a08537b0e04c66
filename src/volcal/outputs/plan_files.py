"""The files of a measurement plan (``volcal plan --out DIR``).

Written into a temporary folder and renamed into place (:func:`volcal.base.folders.write_folder`):

* ``stations.csv``: station, x_mm, y_mm, z_mm, the tracker set-ups (the stations table
  ``identify`` reads; dead lengths are found by the identification);
* ``poses.csv``: the selected poses, one column per axis (mm / deg), the plan format of
  ``volcal simulate --plan`` and ``volcal analyze --plan``;
* ``measurement_plan.csv``: every reading in measuring order with the columns ``identify``
  reads (station, point, axes, tool_x_mm, tool_y_mm, tool_z_mm) and an empty length_mm;
* ``program_<dialect>.nc``: the NC program that runs the plan (one per dialect asked for);
* ``prediction_parameters.csv`` (parameter, unit, u), ``prediction_error_motions.csv``
  (error, axis, position, u_value, unit) and ``prediction_volumetric.csv`` (axes, tool,
  nominal point, u_dx_um, u_dy_um, u_dz_um, u_total_um, modulo the rigid motion no
  multilateration sees): the predicted standard uncertainties;
* ``search_history.csv`` (search, step, best, seconds), ``summary.json`` (the figures,
  the effective settings, the margins and the slack left on every declared limit, the
  set-up sheet, what stays unidentifiable) and ``report.md`` (the same, with the set-up
  sheet per station: where the tracker stands, where the reflector points and how it is
  mounted, the tool offsets by value in mm, the order of the readings, the expected
  time; the NC programs carry the same sheet as comments before each station's first
  program stop);
* ``plan.png`` (stations and workspace from above and from the side, the points coloured
  by the predicted volumetric uncertainty) unless plots are off;
* with instruments added within a time budget (``volcal plan --add-minutes``,
  :mod:`volcal.analysis.planning.additions`): ``added_interferometer.csv`` and
  ``added_ballbar.csv`` (the chosen lines and circles in measuring order, in the columns
  the instruments read, ``volcal identify --data interferometer=FILE``, with the reading
  column ``displacement_um`` / ``deviation_um`` empty to fill, or to simulate with
  ``volcal simulate --instruments interferometer=FILE``), ``prediction_instruments.csv``
  (the criterion and the predicted uncertainties of the field and of the positioning
  errors without the additions and after each one, with units) and the report's
  "Added instruments" section (what to set up where, in what order, the time per
  instrument).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.folders import write_folder
from volcal.outputs.nc_program import NC_DIALECTS, nc_program

__all__ = ["write_plan", "PLAN_FILES", "setup_lines"]

PLAN_FILES = (
    "stations.csv",
    "poses.csv",
    "measurement_plan.csv",
    *(f"program_{d}.nc" for d in NC_DIALECTS),
    "prediction_parameters.csv",
    "prediction_error_motions.csv",
    "prediction_volumetric.csv",
    "search_history.csv",
    "summary.json",
    "report.md",
    "plan.png",
    "added_interferometer.csv",
    "added_ballbar.csv",
    "prediction_instruments.csv",
)


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def _num(v: float, d: int = 1) -> str:
    """``v`` with ``d`` decimals, no ``-0``."""
    return f"{round(float(v), d) + 0.0:.{d}f}"


def _xyz(v: Sequence[float], d: int = 1, sep: str = ", ") -> str:
    return sep.join(_num(x, d) for x in v)


def _tool(v: Sequence[float]) -> str:
    return f"tool offset {_xyz(v, 3).replace('.000', '')} mm"


def setup_lines(entry: dict[str, Any], n_stations: int, half_angle_deg: float) -> list[str]:
    """The set-up sheet of one station (an entry of
    :meth:`volcal.analysis.planning.PlanResult.setup_sheet`) as short plain lines, for the
    NC program's comments and the report: where the tracker stands, where the reflector
    points, the readings and their expected time."""
    p, a = entry["position_mm"], entry["aim"]
    where = f", in region {entry['region']}" if entry["region"] else ""
    lines = [
        f"station {entry['station']} of {n_stations}: tracker at x {_num(p[0])} "
        f"y {_num(p[1])} z {_num(p[2])} mm{where}"
    ]
    if a["mode"] == "re-aimed":
        f = (a["from_x_mm"], a["from_y_mm"], a["from_z_mm"])
        lines += [
            f"reflector axis aimed from the workspace centre x {_num(f[0])} y {_num(f[1])} "
            f"z {_num(f[2])} mm at the tracker",
            f"aim direction {_xyz((a['dir_x'], a['dir_y'], a['dir_z']), 3)}: azimuth "
            f"{_num(a['azimuth_deg'])} deg from +x, elevation {_num(a['elevation_deg'])} deg",
            f"keep this aim for the whole station; largest beam angle "
            f"{_num(a['max_beam_angle_deg'])} deg of {half_angle_deg:g} deg accepted",
        ]
    elif a["mode"] == "tool frame":
        lines += [
            f"reflector axis along {_xyz((a['dir_x'], a['dir_y'], a['dir_z']), 3)} in the "
            "tool frame, turning with the rotary axes",
            f"largest beam angle {_num(a['max_beam_angle_deg'])} deg of "
            f"{half_angle_deg:g} deg accepted",
        ]
    else:
        lines.append("reflector: any orientation, no acceptance limit declared")
    lines.append(
        f"{entry['readings']} readings with {len(entry['blocks'])} tool offset(s), about "
        f"{_num(entry['minutes'])} min of readings"
    )
    return lines


def _setup_section(summary: dict[str, Any]) -> list[str]:
    sheet, n = summary["setup_sheet"], len(summary["setup_sheet"])
    half = summary["settings"].get("half_angle_deg", 180.0)
    spr = summary["settings"].get("seconds_per_reading", 4.0)
    total = sum(e["minutes"] for e in sheet)
    out = [
        "",
        "## Set-up sheet",
        "",
        f"Stations in measuring order; at each, the tool offsets in the order given, the "
        f"poses in the order of `measurement_plan.csv` (rows below). Times count "
        f"{spr:g} s per reading (`seconds_per_reading`), {_num(total)} min in all; setting "
        "up the tracker and changing the reflector come on top. Tool offsets are in the "
        "tool frame, mm. Coordinates are in the machine frame, mm; the NC programs carry "
        "the same sheet as comments.",
    ]
    for e in sheet:
        out += ["", f"### Station {e['station']}", ""]
        out += [f"- {line}" for line in setup_lines(e, n, half)]
        out += ["", "| order | mount the reflector at | rows | points | readings | minutes |"]
        out.append("|---|---|---|---|---|---|")
        for k, b in enumerate(e["blocks"]):
            pts = b["points"]
            out.append(
                f"| {k + 1} | {_tool(b['tool_offset_mm'])} | {b['first_row']}-{b['last_row']} "
                f"| {pts[0]}-{pts[-1]} | {b['readings']} | {_num(b['readings'] * spr / 60.0)} |"
            )
    return out


def _slack_section(summary: dict[str, Any]) -> list[str]:
    mg = summary["margins"]
    out = [
        "",
        "## Margins and slack",
        "",
        f"The search kept {mg['deg']:g} deg off the reflector's acceptance half-angle and "
        f"{mg['mm']:g} mm inside the regions, on the minimum distance, the range and around "
        "the obstacles (`--margin-deg`, `--margin-mm`, or `margin_deg`, `margin_mm` in the "
        "setting). Room left on each declared limit, worst case over the planned readings:",
        "",
        "| limit | worst value | declared limit | slack | at |",
        "|---|---|---|---|---|",
    ]
    names = {
        "angle": "beam angle to the reflector axis",
        "distance": "minimum station-to-point distance",
        "range": "tracker range",
        "region": "station inside its region (distance to the nearest face)",
        "sight": "beam clearance to cylinder obstacles",
    }
    for r in summary["slack"]:
        at = r["station"] + (f", row {r['reading'] + 1}" if r["reading"] >= 0 else "")
        u = r["unit"]
        out.append(
            f"| {names.get(r['constraint'], r['constraint'])} | {_num(r['worst'], 2)} {u} | "
            f"{r['limit']:g} {u} | {_num(r['slack'], 2)} {u} | {at} |"
        )
    return out


def _additions_section(add: dict[str, Any], pred: pd.DataFrame) -> list[str]:
    """The report's section on the interferometer lines and ballbar circles added."""
    c = add["costs"]
    out = [
        "",
        "## Added instruments",
        "",
        f"Budget {add['budget_minutes']:g} min for {', '.join(add['instruments'])} on top "
        f"of the tracker plan ({_num(add['tracker_minutes'])} min of readings); spent "
        f"{_num(add['spent_minutes'])} min on {len(add['setups'])} set-up(s), chosen from "
        f"{add['candidates']} candidates by the plan's criterion ({add['method']}). Costs: "
        f"an interferometer line {c['interferometer_setup_min']:g} min to set up + "
        f"{c['interferometer_targets']} targets x {c['interferometer_seconds_per_target']:g} s "
        f"({c['interferometer_sigma_um']:g} um per reading); a ballbar circle "
        f"{c['ballbar_setup_min']:g} min to set up + {c['ballbar_seconds_per_rev']:g} s per "
        f"revolution ({c['ballbar_angles']} readings, {c['ballbar_sigma_um']:g} um each). "
        "Optics on the table, the reflector (or the spindle ball) at the tool offset of the "
        "files; axis positions in mm / deg.",
        "",
        "| instrument | set-ups | minutes |",
        "|---|---|---|",
    ]
    for name, v in add["per_instrument"].items():
        out.append(f"| {name} | {v['setups']} | {_num(v['minutes'])} |")
    if add["setups"]:
        out += [
            "",
            "In measuring order (`added_interferometer.csv`, `added_ballbar.csv`; fill "
            "`displacement_um` / `deviation_um` with the readings and identify with "
            "`volcal identify --data measurements.csv --data interferometer=... --data "
            "ballbar=...`):",
            "",
            "| order | picked | set-up | instrument | what to set up where | readings | minutes |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in add["setups"]:
            out.append(
                f"| {r['order']} | {r['picked']} | {r['setup']} | {r['instrument']} | "
                f"{r['what']} | {r['readings']} | {_num(r['minutes'])} |"
            )
    pos = [col for col in pred.columns if col.startswith("positioning_u_")]
    out += [
        "",
        "Predicted (`prediction_instruments.csv`): the criterion, the field's standard "
        "uncertainty over the workspace (RMS and max, modulo the rigid motion no "
        "multilateration sees) and the positioning error's (along each linear axis "
        "through the middle of the travel, relative to its start, RMS over the targets), "
        "without the additions and after each:",
        "",
        "| step | added | minutes | criterion | field u RMS (um) | field u max (um) | "
        + " | ".join(f"positioning u {p.split('_')[2]} (um)" for p in pos)
        + " |",
        "|---|---|---|---|---|---|" + "---|" * len(pos),
    ]
    for _, r in pred.iterrows():
        out.append(
            f"| {r['step']} | {r['added'] or 'tracker plan'} | {_num(r['minutes_added'])} | "
            f"{r['criterion']} {_fmt(r['criterion_value'])} {r['criterion_unit']} | "
            f"{_fmt(r['field_u_rms_um'])} | {_fmt(r['field_u_max_um'])} | "
            + " | ".join(_fmt(r[p]) for p in pos)
            + " |"
        )
    if add["notes"]:
        out += [""] + [f"- {n}" for n in add["notes"]]
    return out


def _report(
    summary: dict[str, Any],
    vol: pd.DataFrame,
    motions: pd.DataFrame,
    pred: pd.DataFrame | None = None,
) -> str:
    lines = [
        f"# Measurement plan: {summary['model']}",
        "",
        f"- {summary['stations']} stations, {summary['poses']} poses x "
        f"{summary['tool_offsets']} tool offset(s) = {summary['readings']} readings",
        f"- criterion {summary['criterion']}: {_fmt(summary['criterion_value'])} "
        f"(start {_fmt(summary['start_value'])})",
        f"- predicted volumetric standard uncertainty over the workspace (modulo the rigid "
        f"motion no multilateration sees): RMS {_fmt(summary['volumetric_u_rms_um'])} um, "
        f"max {_fmt(summary['volumetric_u_max_um'])} um",
        f"- evaluation poses whose volumetric error the data do not determine: "
        f"{summary['field_not_determined']}",
        "- unidentifiable error parameters: "
        + (", ".join(summary["unidentifiable_error_parameters"]) or "none"),
        f"- every reading checked against the constraints: {summary['violations']} violations",
        "- tool offsets (tool frame, mm), each measured from every station: "
        + "; ".join(_xyz(t, 3).replace(".000", "") for t in summary["settings"]["tools_mm"]),
        *_slack_section(summary),
        *_setup_section(summary),
        *(_additions_section(summary["additions"], pred) if pred is not None else []),
        "",
        "## Searches",
        "",
        "| search | criterion reached | evaluations | seconds |",
        "|---|---|---|---|",
    ]
    for s in summary["searches"]:
        lines.append(
            f"| {s['method']} | {_fmt(s['value'])} | {s['evaluations']} | {s['seconds']:.1f} |"
        )
    worst = motions.groupby(["error", "unit"])["u_value"].max().sort_values(ascending=False).head(8)
    lines += ["", "## Largest predicted error-motion uncertainties", "", "| error | max u |"]
    lines.append("|---|---|")
    for (err, unit), v in worst.items():
        lines.append(f"| {err} | {_fmt(v)} {unit} |")
    if summary["notes"]:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in summary["notes"]]
    return "\n".join(lines) + "\n"


def _plot_data(result: Any, vol: pd.DataFrame) -> dict[str, Any]:
    """What ``plan.png`` shows, as plain arrays (:func:`draw_plan`)."""
    aimed = result.constraints.reflector.limited and result.constraints.reflector.axis is None
    return {
        "stations_mm": np.asarray(result.stations_mm, float),
        "points_mm": vol[["x_mm", "y_mm", "z_mm"]].to_numpy(float),
        "u_um": vol["u_total_um"].to_numpy(float),
        # the point the re-aimed reflector's axis is aimed from (the set-up sheet's)
        "centre_mm": np.asarray(result.centre_mm, float) if aimed else None,
    }


def write_plan(
    result: Any,
    out_dir: str | Path,
    *,
    dialects: Sequence[str] = ("iso",),
    dwell_s: float = 2.0,
    feed_mm_min: float = 2000.0,
    plots: bool = True,
    force: bool | None = None,
    plotter: Any = None,
) -> Path:
    """Write the files of a :class:`volcal.analysis.planning.PlanResult` (see the module
    docstring) atomically into ``out_dir``; returns its path.  ``plotter``: a
    :class:`volcal.outputs.plot_process.PlotProcess` started early (the command line's),
    which draws ``plan.png`` while this process writes the tables; None: drawn here."""
    from volcal.outputs.figures import draw_plan

    def writer(d: Path) -> None:
        # the volumetric prediction first and plan.png asked for at once: the plotting
        # child draws it (about 0.3 s) while this process computes the other predictions,
        # the NC programs and the set-up sheet, instead of after them
        vol = result.volumetric_uncertainty()
        if plots and plotter is not None:
            plotter.draw(draw_plan, _plot_data(result, vol), d / "plan.png")
        files = _plan_contents(result, vol, dialects, dwell_s, feed_mm_min)
        for name, table in files["tables"].items():
            table.to_csv(d / name, index=False)
        for name, text in files["texts"].items():
            (d / name).write_text(text)
        if plots and plotter is not None:
            plotter.wait()  # the folder is renamed into place with its figure
        elif plots:
            draw_plan(_plot_data(result, vol), d / "plan.png")

    return write_folder(out_dir, PLAN_FILES, "a measurement plan", writer, force=force)


def _plan_contents(
    result: Any,
    vol: pd.DataFrame,
    dialects: Sequence[str],
    dwell_s: float,
    feed_mm_min: float,
) -> dict[str, dict[str, Any]]:
    """The files of a plan but plan.png: ``{"tables": {file name: DataFrame}, "texts":
    {file name: text}}``, in the order they are written; ``vol``: the plan's
    :meth:`volumetric_uncertainty`."""
    m = result.machine
    mp = result.measurement_plan()
    mp_nc = result.measurement_plan(with_tool_index=True)
    axes = [(a.name, "rotary" if a.is_rotary else "linear") for a in m.spec.axes]
    sheet = result.setup_sheet()
    half = float(result.constraints.reflector.half_angle_deg)
    notes = {e["station"]: setup_lines(e, len(sheet), half) for e in sheet}
    programs = {
        d: nc_program(
            mp_nc,
            axes,
            dialect=d,
            dwell_s=dwell_s,
            feed_mm_min=feed_mm_min,
            header_lines=[
                f"volcal measurement plan for {m.spec.name}: {len(result.stations_mm)} "
                f"stations, {int(result.selected.sum())} poses, {len(result.tools)} tool "
                "offset(s)",
                f"margins kept from the declared limits {result.margins[0]:g} deg, "
                f"{result.margins[1]:g} mm",
            ],
            setup_notes=notes,
        )
        for d in dialects
    }
    motions = result.error_motion_uncertainty()
    params = result.parameter_uncertainty()
    summary = result.summary(vol=vol)
    summary["field_not_determined"] = int((~result.field_determined()).sum())
    summary["violations"] = int(len(result.violations()))
    summary["settings"] = dict(result.settings, half_angle_deg=half)
    summary["setup_sheet"] = sheet
    summary["stations_mm"] = np.round(result.stations_mm, 4).tolist()
    add = getattr(result, "additions", None)
    pred = add.prediction() if add is not None else None
    if add is not None:
        summary["additions"] = add.summary()
    hist = pd.DataFrame(
        [
            {"search": f"{k + 1}:{s.method}", **h}
            for k, s in enumerate(result.searches)
            for h in s.history
        ],
        columns=["search", "step", "best", "seconds"],
    )
    tables = {
        "stations.csv": result.stations,
        "poses.csv": result.poses,
        "measurement_plan.csv": mp,
    }
    texts = {f"program_{name}.nc": text for name, text in programs.items()}
    tables.update(
        {
            "prediction_parameters.csv": params,
            "prediction_error_motions.csv": motions,
            "prediction_volumetric.csv": vol,
            "search_history.csv": hist,
        }
    )
    texts["summary.json"] = json.dumps(summary, indent=2) + "\n"
    texts["report.md"] = _report(summary, vol, motions, pred)
    if add is not None and pred is not None:
        tables["prediction_instruments.csv"] = pred
        for name in add.instruments:
            table = add.table(name)
            if len(table):
                tables[f"added_{name}.csv"] = table
    return {"tables": tables, "texts": texts}
