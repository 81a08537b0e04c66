"""SINUMERIK 840D sl / 828D interpolatory compensation: CEC and LEC tables.

Written files:

* ``NC_CEC.INI``: init program ``%_N_NC_CEC_INI`` with the CEC tables (sag / angularity
  compensation, "inter-axis"): per table t ``$AN_CEC[t,N]`` (values at the nodes),
  ``$AN_CEC_INPUT_AXIS[t]``, ``$AN_CEC_OUTPUT_AXIS[t]``, ``$AN_CEC_STEP[t]``,
  ``$AN_CEC_MIN[t]``, ``$AN_CEC_MAX[t]``, ``$AN_CEC_DIRECTION[t]`` (0: both directions),
  ``$AN_CEC_IS_MODULO[t]`` (1 for a full-turn rotary input) and, where a product is
  needed, ``$AN_CEC_MULT_BY_TABLE[t]``;
* ``AX_EEC.INI``: init program ``%_N_AX_EEC_INI`` with the LEC tables (leadscrew /
  encoder error compensation of each axis over its own position): ``$AA_ENC_COMP[0,N,AX]``,
  ``$AA_ENC_COMP_STEP``, ``_MIN``, ``_MAX``, ``_IS_MODULO``.

The values are **corrections** (= -error; ``sign="error"`` writes the errors instead)
added to the output axis' position: mm on linear axes, deg on rotary axes.

How the correction is split (:mod:`volcal.outputs.compensation.grid`):

* a rotary axis' own angular positioning error (``ECC`` for C) is corrected on that axis
  by its LEC table (exact to first order);
* what remains of the volumetric error at the tables' tool offset is turned into
  corrections of the three linear axes, ``c(q)``, and fitted (least squares over a sample
  of the travel) by: the LEC table of each linear axis (its own position), one CEC table
  per other input axis and output axis (straightness, squareness, sag) and, for each
  product of an axis position and a function of another axis (an angular error times its
  lever arm: ``z EBY(y)``; on a 5-axis machine also a function of one rotary axis times
  the cosine or sine of another), a CEC table multiplied
  (``$AN_CEC_MULT_BY_TABLE``) by a table holding the lever axis' position (or the cosine
  or sine).  SINUMERIK adds the product *in addition* to the multiplied table's own value,
  so the multiplier table holds ``h - 1`` (the sum is then ``g * h``) and its own
  contribution, ``h - 1`` on its output axis, is taken out by that axis' LEC table (or
  the table of that output over the multiplier's input axis).  Tables whose
  contribution is negligible (together at most half the tolerance) are left out.

What it cannot carry: the tables know no tool offset, so the tool-length-dependent part
of the angular errors is corrected only at the tables' tool offset (``table_tool``); and
an error that depends on more than two axes, or on two axes other than through a lever
arm (the motions of rotary axes seen through other rotary axes on a 5-axis machine), is
carried only as far as the sum of 1-D tables and lever-arm products reaches.  Both
residuals are reported.

Limits (``target``): ``840d`` 62 CEC tables of at most 2000 points (MD18342
$MN_MM_CEC_MAX_POINTS), LEC 5000 points per axis (MD38000 $MA_MM_ENC_COMP_MAX_POINTS);
``828d`` 8 CEC tables of 200 points ("sag compensation, multi-dimensional").
``max_tables`` / ``max_points`` override them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from volcal.base.exceptions import InputError

from . import Built, Context, render_template, table_residuals
from .grid import (
    AxisTable,
    check_limit,
    correction_residual,
    correction_spacing,
    correction_targets,
    fit_tables,
    uniform_nodes,
    workspace_sample,
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


def _output_values(fld, tables: list[AxisTable], Q: np.ndarray, out: str) -> np.ndarray:
    """What the tables add to the command of axis ``out`` at poses Q."""
    v = np.zeros(len(Q))
    for t in tables:
        if t.output != out:
            continue
        x = t(Q[:, fld.axis(t.input).index])
        v += x
        if t.multiplier is not None:
            m = tables[t.multiplier]
            v += x * m(Q[:, fld.axis(m.input).index])
    return v


def _reindex(tables: list[AxisTable], keep: list[int]) -> list[AxisTable]:
    new = {old: k for k, old in enumerate(keep)}
    out = []
    for i in keep:
        t = tables[i]
        out.append(
            AxisTable(
                t.input,
                t.output,
                t.nodes,
                t.values.copy(),
                t.periodic,
                t.kind,
                None if t.multiplier is None else new[t.multiplier],
                t.label,
            )
        )
    return out


def _prune(
    fld,
    tables: list[AxisTable],
    Q: np.ndarray,
    target: np.ndarray,
    lin: list[str],
    budget_um: float,
) -> list[AxisTable]:
    """Backward elimination, per output axis: leave out a CEC table (base or carrier,
    least significant first) when the refit without it moves the largest residual at the
    fit sample by no more than what is left of ``budget_um`` (split over the outputs);
    multipliers nobody uses go too.  Returns the pruned, refitted tables."""
    from scipy import sparse

    from .grid import hat_matrix

    fixed = [i for i, t in enumerate(tables) if t.kind in ("own", "multiplier")]
    fixed_vals = {i: tables[i](Q[:, fld.axis(tables[i].input).index]) for i in fixed}
    per_out = budget_um / np.sqrt(len(lin)) * 1e-3  # mm
    drop: set[int] = set()
    for o_i, o in enumerate(lin):
        y = target[:, o_i].copy()
        for i in fixed:
            if tables[i].output == o:
                y -= fixed_vals[i]
        idx = [i for i, t in enumerate(tables) if t.output == o and i not in fixed]
        blocks, cols, k = {}, [], 0
        for i in idx:
            t = tables[i]
            H = hat_matrix(t.nodes, Q[:, fld.axis(t.input).index], periodic=t.periodic)
            if t.multiplier is not None:
                H = sparse.diags(1.0 + fixed_vals[t.multiplier]) @ H
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
            if t.kind not in ("base", "carrier"):
                continue
            g = hat_matrix(t.nodes, Q[:, fld.axis(t.input).index], periodic=t.periodic) @ (
                D[blocks[i]] * x[blocks[i]]
            )
            if t.kind == "carrier":
                assert t.multiplier is not None  # a carrier always names its multiplier
                a = fld.axis(tables[t.multiplier].input)
                # a lever arm about the middle of the travel; a rotary factor as it is
                v = g * (
                    Q[:, a.index] - 0.5 * (a.lo + a.hi)
                    if not a.rotary
                    else 1.0 + fixed_vals[t.multiplier]
                )
            else:
                v = g - 0.5 * (g.max() + g.min())
            sig.append((float(np.max(np.abs(v))), i))
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
    used = {t.multiplier for i, t in enumerate(tables) if t.kind == "carrier" and i not in drop}
    out = _reindex(
        tables,
        [
            i
            for i, t in enumerate(tables)
            if i not in drop and (t.kind != "multiplier" or i in used)
        ],
    )
    fit_tables(
        fld, out, Q, target, lin, [i for i, t in enumerate(out) if t.kind in ("own", "multiplier")]
    )
    return out


def build(ctx: Context) -> Built:
    fld = ctx.field
    lim = _limits(ctx)
    targets = correction_targets(fld, ctx.table_tool)
    inputs = [a.name for a in fld.axes]
    sp, _ = correction_spacing(fld, targets, ctx.tolerance_um, inputs)
    nodes = {a.name: uniform_nodes(a.lo, a.hi, sp.h[i]) for i, a in enumerate(fld.axes)}
    per = {a.name: a.full_turn for a in fld.axes}
    lin = targets.linear
    tables: list[AxisTable] = []
    for o in lin:  # LEC: own position
        tables.append(AxisTable(o, o, nodes[o], np.zeros(len(nodes[o])), False, "lec"))
    for r in targets.own:
        tables.append(AxisTable(r, r, nodes[r], targets.own_value(fld, r, nodes[r]), per[r], "own"))
    mult: dict[Any, int] = {}
    for L in lin:
        mult[L] = len(tables)
        tables.append(
            AxisTable(L, L, nodes[L], nodes[L] - 1.0, False, "multiplier", label=f"position of {L}")
        )
    for r in [a.name for a in fld.axes if a.rotary]:
        for fn, h in (("cos", np.cos), ("sin", np.sin)):
            mult[(r, fn)] = len(tables)
            tables.append(
                AxisTable(
                    r, lin[0], nodes[r], h(nodes[r]) - 1.0, per[r], "multiplier", label=f"{fn}({r})"
                )
            )
    for o in lin:
        for J in inputs:
            if J != o:
                tables.append(AxisTable(J, o, nodes[J], np.zeros(len(nodes[J])), per[J]))
            for L in mult:
                if (L if isinstance(L, str) else L[0]) != J and (
                    isinstance(L, str) or fld.axis(J).rotary
                ):
                    tables.append(
                        AxisTable(
                            J, o, nodes[J], np.zeros(len(nodes[J])), per[J], "carrier", mult[L]
                        )
                    )
    n_fit = int(min(40000, max(6000, 40 * max(len(v) for v in nodes.values()))))
    Q = workspace_sample(fld.lower, fld.upper, n_fit, skip=3)
    target = targets.linear_values(fld, Q)

    def fixed(tabs):
        return [i for i, t in enumerate(tabs) if t.kind in ("own", "multiplier")]

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
    names = dict(ctx.options.get("axis_names") or {})
    unknown = sorted(set(names) - set(inputs))
    if unknown:
        raise InputError(f"unknown axis name(s) {unknown}; the model has {inputs}", source="--axis")
    mach = {a: str(names.get(a, f"{a}1")) for a in inputs}
    sgn = -1.0 if ctx.sign == "error" else 1.0

    def residual(q, t):
        return correction_residual(fld, tables, q, t)

    at_table, others = table_residuals(fld, tables, ctx)
    not_carried = [
        f"what 1-D tables and products of two tables cannot represent (errors coupling more "
        f"than two axes, or two axes other than through a lever arm) and the interpolation: "
        f"{at_table:.3g} um RMS left at the tables' tool offset"
    ]
    if others:
        worst, wt = max(others, key=lambda x: x[0])
        not_carried.append(
            "the tool-length-dependent part of the angular errors (the tables know no tool "
            "offset): up to "
            f"{worst:.3g} um RMS at tool offset (" + ", ".join(f"{v:g}" for v in wt) + ") mm"
        )
    values = (
        "corrections (= -error) added to the output axis position, mm on linear axes, "
        "deg on rotary axes (input positions mm / deg)"
        if ctx.sign == "correction"
        else "errors (actual - nominal; the correction is their negative), mm on linear "
        "axes, deg on rotary axes (input positions mm / deg)"
    )

    def axis_val(name, x):
        return fld.axis(name).to_file(x)

    def render(comp) -> dict[str, str]:
        head = comp.header()
        ctab = []
        idx = {id(t): k for k, t in enumerate(cec)}
        for k, t in enumerate(cec):
            a = fld.axis(t.input)
            out_rot = fld.axis(t.output).rotary
            vals = t.values if t.kind == "multiplier" else sgn * t.values
            if out_rot:
                vals = np.rad2deg(vals)
            xs = axis_val(t.input, t.nodes)
            if t.kind == "carrier":
                assert t.multiplier is not None
                m = tables[t.multiplier]
                desc = (
                    f"{t.output} = F({t.input}) x (table {idx[id(m)] + 1}: {m.label} minus "
                    "1, the product added to this table's own value)"
                )
            elif t.kind == "multiplier":
                where = (
                    f"the LEC table of {t.output}"
                    if t.input == t.output
                    else f"the table {t.output} = F({t.input})"
                )
                desc = (
                    f"{t.label} minus 1 (factor of products; its own value on {t.output} "
                    f"is taken out by {where})"
                )
            else:
                desc = f"{t.output} = F({t.input})"
            ctab.append(
                dict(
                    index=k,
                    desc=desc,
                    values=[f"{v:.{DECIMALS}f}" for v in vals + 0.0],
                    input=mach[t.input],
                    output=mach[t.output],
                    step=f"{(xs[-1] - xs[0]) / (len(xs) - 1):.9f}",
                    min=f"{xs[0]:.6f}",
                    max=f"{xs[-1]:.6f}",
                    modulo=int(t.periodic),
                    mult=(idx[id(tables[t.multiplier])] + 1 if t.multiplier is not None else None),
                )
            )
        ltab = []
        mult_of = {m.input: m for m in cec if m.kind == "multiplier"}
        for t in lec:
            a = fld.axis(t.input)
            vals = sgn * t.values
            if ctx.sign == "error" and t.input in mult_of:
                # the multiplier table keeps its sign (it is a factor): its own value, taken
                # out here, must flip with everything else
                vals = vals - 2 * mult_of[t.input].values
            if a.rotary:
                vals = np.rad2deg(vals)
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
    return Built(
        residual,
        render,
        values,
        {a: sp.h[i] for i, a in enumerate(inputs)},
        sp.bound_um,
        None,
        not_carried,
        summary,
        limits,
        table_tool=np.asarray(ctx.table_tool, float),
    )
