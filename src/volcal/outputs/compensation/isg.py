"""Beckhoff TwinCAT CNC volumetric compensation (TF5280, ISG kernel).

Written files:

* ``component_<AXIS>.csv`` (ISG CSV): header ``<AXIS> E?<AXIS> ...`` (the argument axis,
  then the ISO 230 component errors of that axis), one row per node of the axis' uniform
  grid; positions in mm or deg, errors in mm and rad; ``//`` comments.
* ``position_errors.csv`` (ISG CSV): one row of constants: the position errors (ISO 230
  location errors without the leading ``E``: ``C0Y B0Z A0Z``, ``X0C Y0C A0C B0C`` ...),
  the centres of rotation of the rotary axes (``PXC PYC PZC`` ...), the tool's zero
  position ``P0X P0Y P0Z`` and zero orientation ``N0X N0Y N0Z`` (ISG parameters).
* ``volcomp.lis``: the compensation list: axis assignment (logical axis numbers), the
  kinematic chain from the workpiece to the tool and the number of workpiece axes,
  ``interpolation GRID`` (linear on the grid), the parameter files with
  ``file_format ISG_CSV`` (bare names, or in ``control_dir``).

The files hold **errors** (actual - nominal, ISO 230-1), as the ISG kernel expects: the
control evaluates its kinematic model with them and corrects the axis setpoints itself.
``negate`` is not written: the parameter takes a string of axis names whose values are
negated (default "-", none), and no value needs negating.

Rotary axes: the table of a full-turn axis whose errors are periodic spans [0, 360] deg,
the range the control reports its position in (ISG gives rotary arguments over e.g.
[0, 360)); the first and last rows are equal.  Other rotary axes span their travel.

Tool: ISG knows the tool by its length along the zero orientation N0; a reflector offset
across N0 (lateral) is not something the control can be told, so the effect of the
angular errors on the lateral part of a tool offset is not carried (NOT CARRIED, with the
residual it leaves at the lateral tool offsets of the measurement).  The tool's zero
position and orientation errors (volcal's ``EX0T ...
EC0T``), which ISG's parameter list has no name for, are folded into the component errors
of the last tool-side axis (:func:`volcal.outputs.compensation.grid.tool_fold`: exact to first
order), so the files carry the whole identified model: what remains is the interpolation
error, which the node spacing keeps within the tolerance.

Topology: three linear axes X, Y, Z along x, y, z and up to three rotary axes A, B, C
about x, y, z, all in the positive sense (ISG's axis roles); anything else raises
:class:`~volcal.base.exceptions.InputError`.  Limits: at most 10 parameter files per
compensation; ``max_points`` bounds the number of data records (``max_records``).
"""

from __future__ import annotations

import numpy as np

from volcal.base.exceptions import InputError

from . import Built, Context, check_axis_names, control_path, render_template
from .grid import check_limit, component_tables

#: parameter files per compensation (TF5280 documentation)
MAX_FILES = 10
LINEAR, ROTARY = "XYZ", "ABC"


def _check_topology(field) -> None:
    lin = [a for a in field.axes if not a.rotary]
    rot = [a for a in field.axes if a.rotary]
    bad = []
    for a in field.axes:
        letters = ROTARY if a.rotary else LINEAR
        if a.name not in letters or letters.index(a.name) != a.dir_index or a.dir_sign != 1:
            kind = "rotary" if a.rotary else "linear"
            bad.append(f"{a.name} ({kind}, direction {'+-'[a.dir_sign < 0]}{'xyz'[a.dir_index]})")
    if bad or len(lin) != 3 or len(rot) > 3:
        raise InputError(
            "the ISG volumetric compensation needs exactly three linear axes X, "
            "Y, Z along +x, +y, +z and at most three rotary axes A, B, C about "
            f"+x, +y, +z; model {field.spec.name} has "
            + (
                f"axes that do not fit: {', '.join(bad)}"
                if bad
                else f"{len(lin)} linear and {len(rot)} rotary axes"
            ),
            source="--format isg",
        )


def _direction(text: str) -> np.ndarray:
    t = str(text).strip().lower()
    table = {"+x": 0, "x": 0, "-x": 0, "+y": 1, "y": 1, "-y": 1, "+z": 2, "z": 2, "-z": 2}
    if t not in table:
        raise InputError(
            f"expected one of +x -x +y -y +z -z, got {text!r}", source="--tool-direction"
        )
    v = np.zeros(3)
    v[table[t]] = -1.0 if t.startswith("-") else 1.0
    return v


def _fmt(v: float, unit: str) -> str:
    s = f"{v:.12f}" if unit == "rad" else f"{v:.9f}"
    return s[1:] if s.startswith("-") and float(s) == 0 else s


def _csv(header: list[str], columns: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(c), *(len(r[j]) for r in rows)) for j, c in enumerate(columns)]
    out = [f"// {h}" for h in header]
    out.append("  ".join(c.rjust(w) for c, w in zip(columns, widths)))
    out += ["  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in rows]
    return "\n".join(out) + "\n"


def build(ctx: Context) -> Built:
    fld = ctx.field
    _check_topology(fld)
    n0 = _direction(ctx.options.get("tool_direction") or "-z")
    tools = np.vstack([np.zeros(3), ctx.tools])
    tabs = component_tables(fld, tools, ctx.tolerance_um, fold_tool=True, turn_start=0.0)
    names = {s.name: s for s in fld.errors_list}
    files = [f"component_{ax}.csv" for ax in tabs.axes] + ["position_errors.csv"]
    check_limit(
        len(files),
        MAX_FILES,
        "parameter files",
        "TF5280: at most 10 parameter files per compensation",
        "no option changes it",
    )
    records = sum(len(tabs.nodes[ax]) for ax in tabs.axes) + 1
    check_limit(
        records,
        ctx.options.get("max_points"),
        "data records",
        "--max-points, the control's vol_comp[].max_records",
        "raise --tolerance or the limit",
    )
    axis_ids = dict(ctx.options.get("axis_names") or {})
    check_axis_names(fld, axis_ids)
    numbers, k = {}, 4
    for a in fld.axes:
        if a.name in axis_ids:
            numbers[a.name] = str(axis_ids[a.name])
        elif not a.rotary:
            numbers[a.name] = str(LINEAR.index(a.name) + 1)
        else:
            numbers[a.name] = str(k)
            k += 1
    p0 = fld.machine["nominal"](np.zeros(fld.n_axes), np.zeros(3)).full().ravel()

    unit_n0 = n0 / np.linalg.norm(n0)

    def known_tool(t):
        # what the control knows of the tool: its length along N0
        return unit_n0 * float(np.dot(t, unit_n0))

    def residual(q, t):
        # a full-turn axis is looked up modulo its turn (tabs.errors_at -> interp1 with
        # periodic=True), as the control reporting it in [0, 360) does
        e = tabs.errors_at(fld, q)
        return fld.volumetric(q, t) - fld.volumetric_from_errors(q, known_tool(t), e)

    values = (
        "errors (actual - nominal, ISO 230-1; component errors in mm and rad at axis "
        "positions in mm or deg); the control computes the correction (-error) from its "
        "kinematic model"
    )
    not_carried = list(tabs.not_carried)
    lateral = [t for t in ctx.tools if np.linalg.norm(t - known_tool(t)) > 1e-9]
    if lateral:
        from . import check_poses, rms_um

        qc = check_poses(fld)
        worst = max((rms_um(residual(qc, np.asarray(t, float))), tuple(t)) for t in lateral)
        not_carried.append(
            "the effect of the angular errors on the part of a tool offset across the tool "
            f"direction N0 ({ctx.options.get('tool_direction') or '-z'}): ISG applies the "
            f"tool length along N0 only; up to {worst[0]:.3g} um RMS at tool offset ("
            + ", ".join(f"{v:g}" for v in worst[1])
            + ") mm"
        )
    notes = []
    turns = [a.name for a in fld.axes if a.full_turn]
    if turns:
        notes.append(
            f"rotary tables of {', '.join(turns)} span [0, 360] deg: the control must report "
            "those axes modulo 360 deg in [0, 360)"
        )
    cdir = ctx.options.get("control_dir")
    notes.append(
        f"the list names the parameter files in {cdir}"
        if cdir
        else "the list names the parameter files without a folder (relative to the list); "
        "give --control-dir with their absolute path on the control if it expects one, as "
        "the TF5280 examples do"
    )
    if tabs.folded:
        notes.append(
            f"the tool's zero position and orientation errors "
            f"({', '.join(tabs.folded)}) are folded into the component errors of "
            f"{tabs.fold_axis}, the last tool-side axis (exact to first order)"
        )

    def render(comp) -> dict[str, str]:
        head = comp.header() + notes
        out: dict[str, str] = {}
        for ax in tabs.axes:
            a = fld.axis(ax)
            cols = [ax] + tabs.columns[ax]
            units = [a.unit] + [names[c].unit for c in tabs.columns[ax]]
            rows = []
            for x, v in zip(tabs.nodes[ax], tabs.values[ax]):
                rows.append(
                    [f"{a.to_file(x):.6f}"] + [_fmt(val, u) for val, u in zip(v, units[1:])]
                )
            h = head + [
                f"component errors of axis {ax} (argument {ax} in {a.unit}; "
                "translations in mm, rotations in rad)"
                + ("; full turn: the table repeats modulo 360 deg" if a.full_turn else "")
            ]
            out[f"component_{ax}.csv"] = _csv(h, cols, rows)
        cols, row = [], []
        for n, v in tabs.constants.items():
            cols.append(n[1:])  # ISO 230 location error without the leading E (ISG names)
            row.append(_fmt(v, names[n].unit))
        for a in fld.axes:
            if a.rotary:
                for j, c in enumerate("XYZ"):
                    cols.append(f"P{c}{a.name}")
                    row.append(f"{a.center[j]:.6f}")
        for j, c in enumerate("XYZ"):
            cols.append(f"P0{c}")
            row.append(f"{p0[j]:.6f}")
        for j, c in enumerate("XYZ"):
            cols.append(f"N0{c}")
            row.append(f"{n0[j]:.6f}")
        out["position_errors.csv"] = _csv(
            head
            + [
                "position errors (mm, rad), centres of rotation P<c><axis> (mm), tool "
                "zero position P0 (mm) and orientation N0 (unit vector) at all axes zero"
            ],
            cols,
            [row],
        )
        out["volcomp.lis"] = render_template(
            "isg_volcomp.lis.j2",
            header=head,
            files=[control_path(cdir, f) for f in files],
            axes=[(a.name, numbers[a.name]) for a in fld.axes],
            chain="".join(a.name for a in fld.axes),
            workpiece_axes=sum(a.branch == "workpiece" for a in fld.axes),
            records=records,
        )
        return out

    tables = [
        {
            "table": f"component_{ax}.csv",
            "input": ax,
            "columns": " ".join(tabs.columns[ax]),
            "points": len(tabs.nodes[ax]),
        }
        for ax in tabs.axes
    ]
    return Built(
        residual,
        render,
        values,
        {ax: tabs.spacing.h[i] for i, ax in enumerate(tabs.axes)},
        tabs.spacing.bound_um,
        tabs.interp_max_um,
        not_carried,
        tables,
        {
            "parameter files": f"{len(files)} of {MAX_FILES}",
            "data records": f"{records}"
            + (
                f" of {ctx.options['max_points']}"
                if ctx.options.get("max_points")
                else " (no limit given)"
            ),
        },
        notes,
    )
