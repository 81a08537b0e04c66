"""HEIDENHAIN nonlinear axis error compensation: ``*.COM`` tables and the ``*.CMA``
assignment.

Written files:

* ``<AXIS>.COM`` for each axis that carries compensation: TNC table with the columns
  ``NR``, ``AXISPOS`` (positions of that axis from the machine datum, mm or deg, uniform
  spacing) and one column per compensated axis (the linear axes, and a rotary axis' own
  column for its angular positioning error): the value added to that axis at the position
  AXISPOS of the table's axis (``[column axis] = F(table axis)``);
* ``CONFIG.CMA``: one line assigning each ``*.COM`` to the column of its axis, marked
  active (``*`` in ``ACTIVE``).

**Sign.**  The values are the **errors** of the column's axis (actual - nominal, = -the
correction the control applies) in mm on linear axes and deg on rotary axes, linear
between the AXISPOS points: HEIDENHAIN's technical manuals enter the measured axis error
("The axis-error is entered, with the correct sign ... The error is positive if the table
travel is too long", TNC 407 technical manual, 1.6.3; the nonlinear compensation example
of 1.6.4 tabulates the "Error in Z [mm]" over Y).  A full-turn rotary axis' table spans
one turn and repeats.  **AXISPOS** is "given with respect to the machine datum
(MP_refPosition)" (MANUALplus 620 technical manual, 6.10.3): model positions plus
``machine_datum`` (stated after ``[END]``).  TNC tables have no comment syntax: the statement
of what the file holds (sign, tool offset, residual) follows the ``[END]`` line, which the
control does not read.

The correction is split as in :mod:`volcal.outputs.compensation.siemens` (a rotary axis' own
angular positioning error on that axis, the rest on the linear axes at the tables' tool
offset) and fitted by least squares as a **sum of functions of one axis each**: the
nonlinear axis error compensation has no products, so the lever-arm terms (an angular
error times the position of another axis, ``z EBY(y)``) are carried only by their best
additive approximation, and the
tool-length-dependent part of the angular errors only at the tables' tool offset.  Both
residuals are reported.

Limits: ``max_points`` compensation points per table (default 256), ``max_tables`` tables
(default 8).
"""

from __future__ import annotations

import numpy as np

from . import (
    Built,
    Context,
    check_axis_names,
    control_path,
    one_axis_built,
    render_template,
    table_residuals,
    tool_offset_not_carried,
)
from .grid import (
    AxisTable,
    check_limit,
    fit_tables,
    one_axis_tables,
    table_fit_poses,
)

MAX_POINTS = 256
MAX_TABLES = 8
DECIMALS = 6


def build(ctx: Context) -> Built:
    fld = ctx.field
    max_points = int(ctx.options.get("max_points") or MAX_POINTS)
    max_tables = int(ctx.options.get("max_tables") or MAX_TABLES)
    targets, sp, nodes, tables = one_axis_tables(fld, ctx.table_tool, ctx.tolerance_um)
    inputs = [a.name for a in fld.axes]
    per = {a.name: a.full_turn for a in fld.axes}
    lin = targets.linear
    for J in inputs:
        for o in lin:
            tables.append(AxisTable(J, o, nodes[J], np.zeros(len(nodes[J])), per[J]))
    Q = table_fit_poses(fld, nodes)
    fit_tables(
        fld,
        tables,
        Q,
        targets.linear_values(fld, Q),
        lin,
        [i for i, t in enumerate(tables) if t.kind == "own"],
    )
    for t in tables:
        t.values = np.round(t.values, DECIMALS)
    by_input = {J: [t for t in tables if t.input == J] for J in inputs}
    by_input = {J: ts for J, ts in by_input.items() if ts}
    check_limit(
        len(by_input),
        max_tables,
        "compensation value tables (*.COM)",
        f"{max_tables} tables (--max-tables)",
        "raise --max-tables",
    )
    for J in by_input:
        check_limit(
            len(nodes[J]),
            max_points,
            f"compensation points of {J}.COM",
            f"{max_points} points per table (--max-points)",
            "raise --tolerance or --max-points",
        )
    keys = dict(ctx.options.get("axis_names") or {})
    check_axis_names(fld, keys)
    key = {a: str(keys.get(a, a)) for a in inputs}
    # the manuals enter the axis error: the negative of the fitted correction
    sgn = -1.0
    datum = ctx.options.get("machine_datum") or {a: 0.0 for a in inputs}
    cdir = ctx.options.get("control_dir")
    notes = [
        "AXISPOS from the machine datum: model positions plus the model-to-machine datum "
        + ", ".join(f"{a} {datum[a]:g}" for a in inputs)
        + " (mm / deg; --machine-datum)",
        (
            f"CONFIG.CMA names the tables in {cdir}"
            if cdir
            else "CONFIG.CMA names the tables without a folder; give --control-dir (e.g. "
            "TNC:\\table) if the control expects their path"
        ),
    ]

    at_table, others = table_residuals(fld, tables, ctx)
    not_carried = [
        "products of an axis position and a function of another axis (an angular error "
        "times its lever arm) and couplings of rotary axes: the tables add functions of one "
        "axis each; with the interpolation this leaves "
        f"{at_table:.3g} um RMS at the tables' tool offset"
    ] + tool_offset_not_carried(others)
    values = (
        "errors of the column's axis (actual - nominal, as the HEIDENHAIN technical manuals "
        "enter the axis error; the control applies their negative), mm on linear axes, deg "
        "on rotary axes, at AXISPOS of the table's axis (mm / deg from the machine datum)"
    )

    def render(comp) -> dict[str, str]:
        head = comp.header() + notes
        out: dict[str, str] = {}
        for J, ts in by_input.items():
            a = fld.axis(J)
            cols = [key[t.output] for t in ts]
            vals = [t.file_values(fld, sgn) for t in ts]
            rows = []
            for n, x in enumerate(nodes[J]):
                cells = [f"{v[n] + 0.0:+.{DECIMALS}f}" for v in vals]
                rows.append((n, f"{a.to_file(x) + datum[J] + 0.0:+.4f}", cells))
            out[f"{J}.COM"] = render_template(
                "heidenhain.com.j2",
                name=f"{J}.COM",
                unit="MM",
                columns=cols,
                rows=rows,
                header=head
                + [
                    f"table {J}.COM: {', '.join(cols)} = F({key[J]}); AXISPOS in "
                    f"{a.unit}" + ("; one full turn, repeats modulo 360 deg" if a.full_turn else "")
                ],
            )
        out["CONFIG.CMA"] = render_template(
            "heidenhain.cma.j2",
            header=head,
            columns=[key[J] for J in by_input],
            files=[control_path(cdir, f"{J}.COM") for J in by_input],
        )
        return out

    summary = [
        {
            "table": f"{J}.COM",
            "input": J,
            "columns": " ".join(t.output for t in ts),
            "points": len(nodes[J]),
        }
        for J, ts in by_input.items()
    ]
    limits = {
        "tables": f"{len(by_input)} of {max_tables}",
        "points per table": f"{max(len(nodes[J]) for J in by_input)} of {max_points}",
    }
    return one_axis_built(ctx, tables, sp, render, values, not_carried, summary, limits, notes)
