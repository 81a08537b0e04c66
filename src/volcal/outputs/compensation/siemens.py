"""SINUMERIK 840D sl / 828D interpolatory compensation: CEC and LEC tables.

Written files:

* ``NC_CEC.INI``: init program ``%_N_NC_CEC_INI`` with the CEC tables (sag / angularity
  compensation, "inter-axis"): per table t ``$AN_CEC[t,N]`` (values at the nodes),
  ``$AN_CEC_INPUT_AXIS[t]``, ``$AN_CEC_OUTPUT_AXIS[t]``, ``$AN_CEC_STEP[t]``,
  ``$AN_CEC_MIN[t]``, ``$AN_CEC_MAX[t]``, ``$AN_CEC_DIRECTION[t]`` (0: both directions),
  ``$AN_CEC_IS_MODULO[t]`` (1 for a full-turn rotary input);
* ``AX_EEC.INI``: init program ``%_N_AX_EEC_INI`` with the LEC tables (leadscrew /
  encoder error compensation of each axis over its own position): ``$AA_ENC_COMP[0,N,AX]``,
  ``$AA_ENC_COMP_STEP``, ``_MIN``, ``_MAX``, ``_IS_MODULO``.

**Sign.**  Siemens' function manual (K3, interpolatory compensation) says for LEC / MSEC
that "a positive compensation value causes the corresponding machine axis to move in the
negative direction"; the CEC values add to the same total compensation value of the
output axis.  So every value written is the *error* of the output axis (= -the correction
the control applies), mm on linear axes, deg on rotary axes.

**Every value is small.**  K3 says LEC values are "not limited and not monitored ... small
compensation values must be selected".  Table multiplication (``$AN_CEC_MULT_BY_TABLE``)
adds the product of two tables *in addition to* their own values, so carrying a lever-arm
product ``z EBY(y)`` needs a factor table that holds the position ``z`` and a second table
that cancels it: values of hundreds of mm that move the axis by that much whenever the
two are not active together.  volcal therefore writes no products: every table is a
function of one axis, fitted by least squares, and the lever-arm products are listed under
NOT CARRIED with the residual they leave.

How the correction is split (:mod:`volcal.outputs.compensation.grid`): a rotary axis' own
angular positioning error (``ECC`` for C) is corrected on that axis by its LEC table
(exact to first order); what remains of the volumetric error at the tables' tool offset
is turned into corrections of the three linear axes and fitted by the LEC table of each
linear axis and one CEC table per other input axis and output axis (straightness,
squareness, sag).  Tables whose contribution is negligible (together at most half the
tolerance) are left out.

What it cannot carry: the lever-arm products and couplings of several axes (their best
additive approximation is carried), and the tool-length-dependent part of the angular
errors away from the tables' tool offset (``table_tool``).  Both residuals are reported.

Axis names: ``X1``, ``Y1``, ... or general names ``AX1`` ... (``general_axis_names``; for
multi-channel controls), ``axis_names`` for any other.  Table positions are from the
machine datum: model positions plus ``machine_datum``.

Limits (``target``): ``840d`` 62 CEC tables of at most 2000 points (MD18342
$MN_MM_CEC_MAX_POINTS), LEC 5000 points per axis (MD38000 $MA_MM_ENC_COMP_MAX_POINTS);
``828d`` 8 CEC tables of 200 points ("sag compensation, multi-dimensional").
``max_tables`` / ``max_points`` override them.
"""

from __future__ import annotations

import numpy as np

from volcal.base.exceptions import InputError

from . import (
    Built,
    Context,
    check_axis_names,
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

TARGETS = {
    "840d": {
        "max_tables": 62,
        "max_points": 2000,
        "max_lec_points": 5000,
        "name": "SINUMERIK 840D sl",
    },
    "828d": {"max_tables": 8, "max_points": 200, "max_lec_points": 5000, "name": "SINUMERIK 828D"},
}
DECIMALS = 10
#: ridge of the scaled normal equations (splits constants shared by several tables)
RIDGE = 1e-9


def _limits(ctx: Context) -> dict:
    target = (ctx.options.get("target") or "840d").lower()
    if target not in TARGETS:
        raise InputError(
            f"unknown target {target!r}; expected one of {sorted(TARGETS)}", source="--target"
        )
    lim = dict(TARGETS[target])
    if ctx.options.get("max_tables") is not None:
        lim["max_tables"] = int(ctx.options["max_tables"])
    if ctx.options.get("max_points") is not None:
        lim["max_points"] = int(ctx.options["max_points"])
    lim["target"] = target
    return lim


def _prune(
    fld,
    tables: list[AxisTable],
    Q: np.ndarray,
    target: np.ndarray,
    lin: list[str],
    budget_um: float,
) -> list[AxisTable]:
    """Backward elimination, per output axis: leave out a CEC table (least significant
    first) when the refit without it moves the largest residual at the fit sample by no
    more than what is left of ``budget_um`` (split over the outputs).  Returns the pruned,
    refitted tables."""
    from scipy import sparse

    from .grid import hat_matrix

    fixed = [i for i, t in enumerate(tables) if t.kind == "own"]
    fixed_vals = {i: tables[i](Q[:, fld.axis(tables[i].input).index]) for i in fixed}
    per_out = budget_um / np.sqrt(len(lin)) * 1e-3  # mm
    drop: set[int] = set()
    for o in lin:
        y = target[:, lin.index(o)].copy()
        for i in fixed:
            if tables[i].output == o:
                y -= fixed_vals[i]
        idx = [i for i, t in enumerate(tables) if t.output == o and i not in fixed]
        blocks, cols, k = {}, [], 0
        for i in idx:
            t = tables[i]
            H = hat_matrix(t.nodes, Q[:, fld.axis(t.input).index], periodic=t.periodic)
            cols.append(H)
            blocks[i] = np.arange(k, k + H.shape[1])
            k += H.shape[1]
        A = sparse.hstack(cols).tocsr()
        N = (A.T @ A).toarray()
        b = A.T @ y
        # columns scaled to unit norm, a tiny ridge for the constants several tables share;
        # the inverse normal matrix is downdated as blocks leave: removing block B from the
        # fit gives x_K - P_KB P_BB^-1 x_B without a new factorisation
        d = np.diag(N).copy()
        D = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        A = A @ sparse.diags(D)
        P = np.linalg.inv(D[:, None] * N * D[None, :] + RIDGE * np.eye(len(N)))
        x = P @ (D * b)
        act = np.arange(len(N))
        base = float(np.max(np.abs(y - A @ x)))
        sig = []
        for i in idx:
            t = tables[i]
            if t.kind != "base":
                continue
            g = hat_matrix(t.nodes, Q[:, fld.axis(t.input).index], periodic=t.periodic) @ (
                D[blocks[i]] * x[blocks[i]]
            )
            sig.append((float(np.max(np.abs(g - 0.5 * (g.max() + g.min())))), i))
        for _, i in sorted(sig):
            B = np.flatnonzero(np.isin(act, blocks[i]))
            K = np.flatnonzero(~np.isin(act, blocks[i]))
            PKB = P[np.ix_(K, B)]
            W = np.linalg.solve(P[np.ix_(B, B)], np.c_[x[B], PKB.T])
            x_new = x[K] - PKB @ W[:, 0]
            r = float(np.max(np.abs(y - A[:, act[K]] @ x_new)))
            if r <= base + per_out:
                P = P[np.ix_(K, K)] - PKB @ W[:, 1:]
                x, act = x_new, act[K]
                drop.add(i)
    out = [
        AxisTable(t.input, t.output, t.nodes, t.values.copy(), t.periodic, t.kind)
        for i, t in enumerate(tables)
        if i not in drop
    ]
    fit_tables(fld, out, Q, target, lin, [i for i, t in enumerate(out) if t.kind == "own"])
    return out


def machine_axis_names(ctx: Context) -> dict[str, str]:
    """SINUMERIK machine axis name of every model axis: ``--axis`` first, else ``AX<n>``
    (general names: linear axes X, Y, Z as AX1 to AX3 by direction, then the rotary axes in
    model order) with ``general_axis_names``, else ``<axis>1``."""
    fld = ctx.field
    inputs = [a.name for a in fld.axes]
    names = dict(ctx.options.get("axis_names") or {})
    check_axis_names(fld, names)
    if ctx.options.get("general_axis_names"):
        order = sorted((a for a in fld.axes if not a.rotary), key=lambda a: a.dir_index) + [
            a for a in fld.axes if a.rotary
        ]
        default = {a.name: f"AX{k + 1}" for k, a in enumerate(order)}
    else:
        default = {a: f"{a}1" for a in inputs}
    return {a: str(names.get(a, default[a])) for a in inputs}


def build(ctx: Context) -> Built:
    fld = ctx.field
    lim = _limits(ctx)
    targets, sp, nodes, own = one_axis_tables(fld, ctx.table_tool, ctx.tolerance_um)
    inputs = [a.name for a in fld.axes]
    per = {a.name: a.full_turn for a in fld.axes}
    lin = targets.linear
    # LEC: own position, then the rotary axes' own tables
    tables = [AxisTable(o, o, nodes[o], np.zeros(len(nodes[o])), False, "lec") for o in lin]
    tables += own
    # CEC: one table per other input axis and output axis; no table multiplication (a
    # factor table would hold a position, see the module docstring)
    for o in lin:
        for J in inputs:
            if J != o:
                tables.append(AxisTable(J, o, nodes[J], np.zeros(len(nodes[J])), per[J]))
    Q = table_fit_poses(fld, nodes)
    target = targets.linear_values(fld, Q)

    def fixed(tabs):
        return [i for i, t in enumerate(tabs) if t.kind == "own"]

    fit_tables(fld, tables, Q, target, lin, fixed(tables))
    tables = _prune(fld, tables, Q, target, lin, 0.5 * ctx.tolerance_um)
    for t in tables:
        t.values = np.round(t.values, DECIMALS)
    cec = [t for t in tables if t.kind not in ("lec", "own")]
    lec = [t for t in tables if t.kind in ("lec", "own")]
    check_limit(
        len(cec),
        lim["max_tables"],
        "CEC tables needed",
        f"{TARGETS[lim['target']]['name']}: {lim['max_tables']} tables (--max-tables; "
        "MD18342 $MN_MM_CEC_MAX_POINTS[t] per table)",
        "raise --tolerance, choose --target 840d or raise --max-tables",
    )
    for t in cec:
        check_limit(
            len(t.nodes),
            lim["max_points"],
            f"points of the CEC table {t.input} -> {t.output}",
            f"{lim['max_points']} points per table (--max-points; MD18342 $MN_MM_CEC_MAX_POINTS)",
            "raise --tolerance or --max-points",
        )
    for t in lec:
        check_limit(
            len(t.nodes),
            lim["max_lec_points"],
            f"points of the LEC table of {t.input}",
            f"{lim['max_lec_points']} (MD38000 $MA_MM_ENC_COMP_MAX_POINTS)",
            "raise --tolerance",
        )
    mach = machine_axis_names(ctx)
    datum = ctx.options.get("machine_datum") or {a: 0.0 for a in inputs}
    # K3: "a positive compensation value causes the corresponding machine axis to move in
    # the negative direction": the value is the negative of the axis motion wanted
    sgn = -1.0

    at_table, others = table_residuals(fld, tables, ctx)
    not_carried = [
        "the lever-arm products (an angular error of one axis times the position of "
        "another, z EBY(y)), couplings of more than one axis and the interpolation: the "
        "tables add functions of one axis each (table multiplication is not used: its "
        "factor table would hold a position, not a small correction); this leaves "
        f"{at_table:.3g} um RMS at the tables' tool offset"
    ] + tool_offset_not_carried(others)
    values = (
        "compensation values as SINUMERIK documents them (K3: a positive compensation "
        "value causes the machine axis to move in the negative direction; the same sign "
        "for the CEC tables, whose values add to the axis' total compensation value): each "
        "value is the error of the output axis (actual - nominal, = -the correction the "
        "control applies), mm on linear axes, deg on rotary axes (input positions mm / deg "
        "from the machine datum)"
    )
    notes = [
        "machine axes: "
        + ", ".join(f"{a} = {mach[a]}" for a in inputs)
        + "; table positions are model positions plus the model-to-machine datum "
        + ", ".join(f"{a} {datum[a]:g}" for a in inputs)
        + " (mm / deg; --machine-datum)"
    ]

    def axis_val(name, x):
        return fld.axis(name).to_file(x) + datum[name]

    def render(comp) -> dict[str, str]:
        head = comp.header() + notes
        ctab = []
        for k, t in enumerate(cec):
            vals = t.file_values(fld, sgn)
            xs = axis_val(t.input, t.nodes)
            ctab.append(
                dict(
                    index=k,
                    desc=f"{t.output} = F({t.input})",
                    values=[f"{v:.{DECIMALS}f}" for v in vals + 0.0],
                    input=mach[t.input],
                    output=mach[t.output],
                    step=f"{(xs[-1] - xs[0]) / (len(xs) - 1):.9f}",
                    min=f"{xs[0]:.6f}",
                    max=f"{xs[-1]:.6f}",
                    modulo=int(t.periodic),
                )
            )
        ltab = []
        for t in lec:
            a = fld.axis(t.input)
            vals = t.file_values(fld, sgn)  # input = output: the axis' own table
            xs = axis_val(t.input, t.nodes)
            ltab.append(
                dict(
                    axis=mach[t.input],
                    values=[f"{v:.{DECIMALS}f}" for v in vals + 0.0],
                    step=f"{(xs[-1] - xs[0]) / (len(xs) - 1):.9f}",
                    min=f"{xs[0]:.6f}",
                    max=f"{xs[-1]:.6f}",
                    modulo=int(t.periodic),
                    unit=a.unit,
                    what=("own angular positioning error" if t.kind == "own" else "own position"),
                )
            )
        return {
            "NC_CEC.INI": render_template(
                "siemens_cec.ini.j2",
                header=head,
                tables=ctab,
                target=TARGETS[lim["target"]]["name"],
            ),
            "AX_EEC.INI": render_template("siemens_lec.ini.j2", header=head, tables=ltab),
        }

    summary = [
        {
            "table": f"CEC {k + 1}",
            "kind": t.kind,
            "input": t.input,
            "output": t.output,
            "points": len(t.nodes),
        }
        for k, t in enumerate(cec)
    ] + [
        {
            "table": f"LEC {t.input}",
            "kind": t.kind,
            "input": t.input,
            "output": t.output,
            "points": len(t.nodes),
        }
        for t in lec
    ]
    limits = {
        "target": TARGETS[lim["target"]]["name"],
        "CEC tables": f"{len(cec)} of {lim['max_tables']}",
        "CEC points per table": f"{max((len(t.nodes) for t in cec), default=0)} of "
        f"{lim['max_points']}",
        "LEC points per axis": f"{max((len(t.nodes) for t in lec), default=0)} of "
        f"{lim['max_lec_points']}",
    }
    return one_axis_built(ctx, tables, sp, render, values, not_carried, summary, limits, notes)
