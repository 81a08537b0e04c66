"""Generic compensation files: ISO 230-1 error tables per axis and a volumetric
correction grid.

Written files:

* ``errors_<AXIS>.csv``: the component error motions of one axis under their ISO 230-1
  names on the axis' uniform grid: ``position_mm`` or ``position_deg``, then
  ``EXX_um ... ECX_urad`` (the identified **errors**, actual - nominal);
* ``constants.csv``: ``name, value, unit, kind, meaning``: location errors (squareness,
  rotary axis lines) and the tool's zero position and orientation (``EX0T ... EC0T``);
* ``volumetric_grid.csv``: the volumetric **correction** (-error; ``sign="error"`` writes
  the error) of the tool point in the workpiece frame, um, on a grid over every axis of
  the model (a 3-D grid on a 3-axis machine) for each tool offset: columns ``tool_x_mm,
  tool_y_mm, tool_z_mm``, the axes (mm / deg), ``corr_x_um, corr_y_um, corr_z_um`` (or
  ``err_*``);
* ``volumetric_grid.npz``: the same grid in binary (NumPy ``.npz``, read with
  ``numpy.load(..., allow_pickle=False)``): ``nodes_<AXIS>`` (mm / deg), ``tools`` (K, 3)
  mm, ``values`` (K, n_1, ..., n_d, 3) um, and ``metadata`` (a JSON string: units, sign
  convention, frame, axis order, tool offsets, reference position, model fingerprint,
  spacing, interpolation, residual figures).

A consumer interpolates multilinearly between the grid nodes (modulo 360 deg on a
full-turn rotary axis) at the tool offset it needs; the node spacing per axis comes from
the curvature of the volumetric error along that axis so that the interpolation error
stays within the tolerance.  The grid carries the whole model at its tool offsets; at
other tool offsets the per-axis tables (with the kinematic chain) do.  ``max_points``
bounds the number of grid nodes times tool offsets (default 2,000,000).
"""

from __future__ import annotations

import io
import json

import numpy as np

from . import Built, Context
from .grid import (
    LimitError,
    check_limit,
    choose_spacing,
    component_tables,
    curvature_nd,
    multilinear,
    uniform_nodes,
    workspace_sample,
)

MAX_GRID_POINTS = 2_000_000
#: tolerances (um) tried in turn for the grid when none is given
AUTO_TOLERANCES = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)

_MEANING = {
    "location": "location error (constant)",
    "tool": "tool zero position / orientation error (constant, tool frame)",
}


def _unit(unit: str) -> tuple[float, str]:
    return (1e3, "um") if unit == "mm" else (1e6, "urad")


def _csv(header: list[str], df) -> str:
    buf = io.StringIO()
    for h in header:
        buf.write(f"# {h}\n")
    # rounded, then written with the shortest representation (fast, C-level)
    num = df.select_dtypes("number").columns
    df = df.copy()
    df[num] = df[num].round(6) + 0.0
    df.to_csv(buf, index=False, lineterminator="\n")
    return buf.getvalue()


def build(ctx: Context) -> Built:
    import pandas as pd

    fld = ctx.field
    tools = np.asarray(ctx.tools, float)
    max_points = int(ctx.options.get("max_points") or MAX_GRID_POINTS)
    tabs = component_tables(fld, np.vstack([np.zeros(3), tools]), ctx.tolerance_um, fold_tool=False)
    # ---- the volumetric grid over every axis, one per tool offset
    lo, hi = fld.lower, fld.upper
    axes = fld.axes

    def dp_all(q):
        a, B = fld.affine(q)
        return np.hstack([a + np.einsum("nij,j->ni", B, t) for t in tools])

    S = curvature_nd(dp_all, lo, hi) * 1e3
    qv = workspace_sample(lo, hi, 1500, skip=5000)
    exact = [fld.volumetric(qv, t) for t in tools]
    per = [a.full_turn for a in axes]
    mins = [8 if a.full_turn else 1 for a in axes]

    def n_nodes(tol: float, scale: float = 1.0) -> int:
        """Grid nodes at ``tol`` from the curvature estimate times ``scale`` (the factor
        the refinement in ``grid`` found the estimate short by)."""
        sp = choose_spacing([a.length for a in axes], S * scale, tol, min_intervals=mins)
        return int(np.prod([len(uniform_nodes(a.lo, a.hi, sp.h[j])) for j, a in enumerate(axes)]))

    # the factor the curvature estimate was found short by (interpolation error ~ S h^2,
    # so a grid at scale s that measured m > tol needed at least s m / tol): the node
    # counts of the hints use it, not the bare estimate
    learnt = [1.0]

    def grid(tol: float, scale: float = 1.0):
        measured = np.inf
        for _ in range(5):
            sp = choose_spacing([a.length for a in axes], S * scale, tol, min_intervals=mins)
            nodes = [uniform_nodes(a.lo, a.hi, sp.h[j]) for j, a in enumerate(axes)]
            shape = tuple(len(n) for n in nodes)
            check_limit(
                int(np.prod(shape)) * len(tools),
                max_points,
                f"volumetric grid points ({' x '.join(map(str, shape))} nodes x "
                f"{len(tools)} tool offset(s))",
                "--max-points (default 2,000,000)",
                "raise --tolerance, give fewer --tool offsets or raise --max-points",
            )
            Q = np.stack(np.meshgrid(*nodes, indexing="ij"), axis=-1).reshape(-1, len(axes))
            a0, B0 = fld.affine(Q)
            vals = np.stack(
                [(a0 + np.einsum("nij,j->ni", B0, t)).reshape(*shape, 3) for t in tools]
            )  # error, mm
            err = 0.0
            for k in range(len(tools)):
                d = multilinear(nodes, vals[k], qv, per) - exact[k]
                err = max(err, float(np.max(np.linalg.norm(d, axis=1))) * 1e3)
            measured, used = err, scale
            if measured <= tol:
                break
            learnt[0] = max(learnt[0], scale * measured / tol)
            scale *= max(1.2, 1.1 * measured / tol)
        return sp, nodes, vals, measured, used

    grid_tol = ctx.tolerance_um
    chosen_note = None
    if not ctx.options.get("auto_tolerance"):
        try:
            sp, nodes, vals, measured, _ = grid(grid_tol)
        except LimitError as exc:
            fits = [t for t in AUTO_TOLERANCES if n_nodes(t, learnt[0]) * len(tools) <= max_points]
            if fits and fits[0] > grid_tol:
                raise LimitError(f"{exc}; --tolerance {fits[0]:g} fits") from None
            raise
    else:
        # no tolerance given: the smallest of the ladder whose grid fits the limit
        built = None
        for tol in AUTO_TOLERANCES:
            if n_nodes(tol, learnt[0]) * len(tools) > max_points:
                continue
            try:
                built = grid(tol, learnt[0])
            except LimitError:
                continue
            grid_tol = tol
            break
        if built is None:
            one = next(
                (t for t in AUTO_TOLERANCES if n_nodes(t) <= max_points), AUTO_TOLERANCES[-1]
            )
            raise LimitError(
                f"volumetric grid: {n_nodes(AUTO_TOLERANCES[-1]) * len(tools)} points at "
                f"{AUTO_TOLERANCES[-1]:g} um for {len(tools)} tool offset(s), more than the "
                f"limit of {max_points} (--max-points); propose --tolerance {one:g} with "
                "one --tool offset (e.g. --tool "
                + ",".join(f"{v:g}" for v in tools[0])
                + "), or raise --max-points"
            )
        sp, nodes, vals, measured, scale = built
        if grid_tol != ctx.tolerance_um:
            # the count at the default with the curvature scale the refinement found
            need = n_nodes(ctx.tolerance_um, max(scale, learnt[0]))
            chosen_note = (
                f"volumetric grid tolerance chosen automatically: {grid_tol:g} um (the "
                f"default {ctx.tolerance_um:g} um would need {need:,} "
                f"nodes x {len(tools)} tool offset(s), more than the limit of "
                f"{max_points:,}); give --tolerance to choose another"
            )
    grid_bound = sp.bound_um
    sgn = -1.0 if ctx.sign == "correction" else 1.0
    tag = "corr" if ctx.sign == "correction" else "err"

    def residual(q, t):
        k = np.flatnonzero(np.abs(tools - t).max(axis=1) < 1e-9)
        if not len(k):
            return np.full((len(q), 3), np.nan)
        return fld.volumetric(q, t) - multilinear(nodes, vals[k[0]], q, per)

    values = (
        "errors in the per-axis tables and constants (actual - nominal, ISO 230-1, um / "
        "urad); in the volumetric grid "
        + (
            "corrections (= -error) to add to the commanded tool point"
            if ctx.sign == "correction"
            else "errors (actual - nominal tool point; the correction is their negative)"
        )
        + ", um, workspace frame"
    )
    names = {s.name: s for s in fld.errors_list}

    def render(comp) -> dict[str, str | bytes]:
        head = comp.header()
        out: dict[str, str | bytes] = {}
        for ax in tabs.axes:
            a = fld.axis(ax)
            df = pd.DataFrame({f"position_{a.unit}": a.to_file(tabs.nodes[ax])})
            for j, n in enumerate(tabs.columns[ax]):
                f, u = _unit(names[n].unit)
                df[f"{n}_{u}"] = tabs.values[ax][:, j] * f + 0.0
            out[f"errors_{ax}.csv"] = _csv(
                head
                + [
                    f"component error motions of axis {ax} (ISO 230-1 names): errors, "
                    "actual - nominal; linear interpolation between the rows"
                    + ("; one full turn, repeats modulo 360 deg" if a.full_turn else "")
                ],
                df,
            )
        rows = []
        for n, v in tabs.constants.items():
            f, u = _unit(names[n].unit)
            rows.append(
                {
                    "name": n,
                    "value": v * f + 0.0,
                    "unit": u,
                    "kind": names[n].kind,
                    "meaning": _MEANING[names[n].kind],
                }
            )
        out["constants.csv"] = _csv(
            head + ["constant errors (actual - nominal)"],
            pd.DataFrame(rows, columns=["name", "value", "unit", "kind", "meaning"]),
        )
        Q = np.stack(np.meshgrid(*nodes, indexing="ij"), axis=-1).reshape(-1, len(axes))
        frames = []
        for k, t in enumerate(tools):
            df = pd.DataFrame(
                {"tool_x_mm": t[0], "tool_y_mm": t[1], "tool_z_mm": t[2]}, index=range(len(Q))
            )
            for j, a in enumerate(axes):
                df[f"{a.name}_{a.unit}"] = a.to_file(Q[:, j])
            v = vals[k].reshape(-1, 3) * sgn * 1e3 + 0.0
            for j, c in enumerate("xyz"):
                df[f"{tag}_{c}_um"] = v[:, j]
            frames.append(df)
        grid_head = head + [
            f"volumetric grid: {' x '.join(str(len(n)) for n in nodes)} nodes over "
            f"{', '.join(a.name for a in axes)} per tool offset; "
            + ("corrections (= -error)" if ctx.sign == "correction" else "errors")
            + " of the tool point in um, workpiece frame; multilinear interpolation"
            + (
                ", modulo 360 deg on " + ", ".join(a.name for a in axes if a.full_turn)
                if any(per)
                else ""
            )
            + f"; measured interpolation error {measured:.3g} um"
        ]
        out["volumetric_grid.csv"] = _csv(grid_head, pd.concat(frames, ignore_index=True))
        meta = {
            "format": "volcal-volumetric-grid",
            "format_version": 1,
            "values": "correction" if ctx.sign == "correction" else "error",
            "sign": (
                "correction = -error (error = actual - nominal tool point)"
                if ctx.sign == "correction"
                else "error = actual - nominal tool point"
            ),
            "units": {"values": "um", "linear axes": "mm", "rotary axes": "deg", "tools": "mm"},
            "frame": "workpiece frame (the machine frame with every axis at zero)",
            "axes": [a.name for a in axes],
            "axis_units": [a.unit for a in axes],
            "periodic": [bool(p) for p in per],
            "interpolation": "multilinear between nodes, held at the ends; periodic axes "
            "modulo 360 deg",
            "tool_offsets_mm": tools.tolist(),
            "tool_frame": "tool offsets in the tool frame (reflector / tool point relative to "
            "the spindle reference point)",
            "reference_position": {a.name: float(a.to_file(a.reference)) for a in axes},
            "model": fld.spec.name,
            "model_fingerprint": fld.spec.fingerprint(),
            "tolerance_um": grid_tol,
            "spacing": {a.name: float(a.to_file(sp.h[j])) for j, a in enumerate(axes)},
            "interpolation_bound_um": grid_bound,
            "interpolation_max_um": measured,
            "header": head,
        }
        buf = io.BytesIO()
        arrays = {f"nodes_{a.name}": a.to_file(nodes[j]) for j, a in enumerate(axes)}
        np.savez(
            buf,
            tools=tools,
            values=vals * sgn * 1e3 + 0.0,
            metadata=np.array(json.dumps(meta)),
            **arrays,
        )
        out["volumetric_grid.npz"] = buf.getvalue()
        return out

    tables = [
        {
            "table": f"errors_{ax}.csv",
            "input": ax,
            "columns": " ".join(tabs.columns[ax]),
            "points": len(tabs.nodes[ax]),
        }
        for ax in tabs.axes
    ]
    tables.append(
        {
            "table": "volumetric_grid",
            "input": " ".join(a.name for a in axes),
            "columns": f"{tag}_x/y/z x {len(tools)} tool offset(s)",
            "points": int(np.prod([len(n) for n in nodes])),
        }
    )
    not_carried: list[str] = []
    spacing = ", ".join(
        f"{ax} {fld.axis(ax).to_file(tabs.spacing.h[i]):.4g} {fld.axis(ax).unit}"
        for i, ax in enumerate(tabs.axes)
    )
    notes = [
        f"per-axis tables: spacing {spacing}, "
        f"interpolation error {tabs.interp_max_um:.3g} um (bound "
        f"{tabs.spacing.bound_um:.3g} um); the grid spacing is the one reported",
        "the volumetric grid exists at its tool offsets only; at others use the per-axis "
        "tables with the kinematic chain",
    ]
    if chosen_note:
        notes.insert(0, chosen_note)
    limits = {
        "grid points": f"{int(np.prod([len(n) for n in nodes])) * len(tools)} of {max_points}"
    }
    return Built(
        residual,
        render,
        values,
        {a.name: sp.h[j] for j, a in enumerate(axes)},
        grid_bound,
        measured,
        not_carried,
        tables,
        limits,
        notes,
        tolerance_um=grid_tol,
        file_names=[f"errors_{ax}.csv" for ax in tabs.axes]
        + ["constants.csv", "volumetric_grid.csv", "volumetric_grid.npz"],
    )
