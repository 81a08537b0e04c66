"""``volcal models`` (list the bundled machine models) and ``volcal show MODEL`` (one model's
axes, error quantities and first-order volumetric error, written out).

Only the ``show`` path touches SymPy, through :mod:`volcal.model.symbolic`, and it imports it
inside the handler: ``volcal --help`` and ``volcal models`` never load it.
"""

from __future__ import annotations

import csv
import io
import sys
from dataclasses import dataclass

from volcal.model.spec import AXIS_LETTERS, AxisSpec, ErrorSymbol, MachineSpec, error_symbols

_SECTIONS = ("axes", "errors", "volumetric")
# the written-out first-order formula doubles in size with every rotary axis
MAX_WRITTEN_ROTARY = 4
_COMPONENTS = ("dx", "dy", "dz")
_COMPONENT_TEXT = {"dx": "Δx", "dy": "Δy", "dz": "Δz"}


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "models",
        help="list the bundled machine models",
        description="List the machine models shipped with volcal: name, number of axes, "
        "number of error quantities and description. Use the name with --model "
        "or with 'volcal show'.",
    )
    p.add_argument(
        "--format", choices=("text", "csv"), default="text", help="output format (default: text)"
    )
    p.set_defaults(func=run_models)

    s = subparsers.add_parser(
        "show",
        help="show a model: axes, error quantities, first-order volumetric error",
        description="Show one machine model: its axes (travel in mm or deg), its error "
        "quantities (ISO 230-1 / 230-7 names; mm and rad inside volcal, printed "
        "as um and urad in reports) and the first-order volumetric error "
        "dx, dy, dz (actual minus nominal tool point, mm, in the workpiece frame) "
        "as a sum of coefficient * error, one term per error quantity. "
        "See docs/conventions.md.",
    )
    s.add_argument(
        "model",
        metavar="MODEL",
        help="name of a bundled model (see 'volcal models') or path of a model file",
    )
    s.add_argument(
        "--format",
        choices=("text", "csv"),
        default="text",
        help="output format (default: text); csv prints the tables one after "
        "the other, each after a '# axes' / '# errors' / '# volumetric' line",
    )
    s.add_argument(
        "--section",
        choices=("all", *_SECTIONS),
        default="all",
        help="print only one table (with --format csv: one plain CSV table)",
    )
    s.set_defaults(func=run_show)


# --------------------------------------------------------------------------------------
# volcal models


def run_models(args) -> int:
    from volcal.model.spec import bundled_models, load_model_file

    rows = []
    for name, path in bundled_models().items():
        spec = load_model_file(path)
        rows.append(
            [name, len(spec.axes), len(error_symbols(spec)), chain_string(spec), spec.description]
        )
    header = ["name", "n_axes", "n_errors", "chain", "description"]
    if args.format == "csv":
        _write_csv(header, rows)
    else:
        print(_text_table(header, rows))
    return 0


# --------------------------------------------------------------------------------------
# volcal show


def chain_string(spec: MachineSpec) -> str:
    """The kinematic chain as the papers write it: W (workpiece), F (frame), T (tool)."""
    wp = [a.name for a in spec.axes if a.branch == "workpiece"]
    tl = [a.name for a in spec.axes if a.branch == "tool"]
    return "-".join(["W", *wp, "F", *tl, "T"])


def _fmt(v: float) -> str:
    return f"{v:g}"


def axis_rows(spec: MachineSpec) -> list[list[str]]:
    rows = []
    for a in spec.axes:
        unit = "deg" if a.is_rotary else "mm"
        centre = [_fmt(c) for c in a.center] if a.is_rotary else ["", "", ""]
        rows.append(
            [
                a.name,
                a.kind,
                a.branch,
                a.direction,
                _fmt(a.travel[0]),
                _fmt(a.travel[1]),
                _fmt(a.reference),
                unit,
                *centre,
            ]
        )
    return rows


def _linear_axis_along(spec: MachineSpec, k: int) -> str:
    for a in spec.axes:
        if a.kind == "linear" and a.dir_index == k:
            return a.name
    return AXIS_LETTERS[k]


def describe_error(spec: MachineSpec, s: ErrorSymbol) -> str:
    """What an error quantity is, in ISO 230-1 / 230-7 words."""
    if s.kind == "tool":
        d = "xyz"[s.component]
        return (
            f"tool zero position in {d}"
            if s.quantity == "translation"
            else f"tool zero orientation about {d}"
        )
    a: AxisSpec = spec.axis(s.axis)
    d = "xyz"[s.component]
    own = s.component == a.dir_index
    if s.kind == "component":
        if s.quantity == "translation":
            if a.kind == "linear":
                return "positioning error motion" if own else f"straightness error motion in {d}"
            return "axial error motion" if own else f"radial error motion in {d}"
        if a.kind == "linear":
            return "roll" if own else f"angular error motion about {d} (pitch/yaw)"
        return "angular positioning error motion" if own else f"tilt error motion about {d}"
    if a.kind == "linear":
        other = _linear_axis_along(spec, 3 - a.dir_index - s.component)
        return f"squareness of {a.name} to {other} (about {d})"
    if s.quantity == "translation":
        return f"position of the axis line in {d}"
    return f"orientation of the axis line about {d}"


def error_rows(spec: MachineSpec) -> list[list[str]]:
    rows = []
    for s in error_symbols(spec):
        report = "um" if s.quantity == "translation" else "urad"
        rows.append([s.name, s.axis, s.kind, s.quantity, s.unit, report, describe_error(spec, s)])
    return rows


@dataclass(frozen=True)
class Term:
    """One term coefficient * error of a first-order volumetric error component.

    coefficient: SymPy-syntax text in the axis positions (named as the axes; mm for linear,
    rad for rotary axes) and the tool offset ``tool_x, tool_y, tool_z`` (mm); it is
    dimensionless for a translational error and mm/rad for a rotational one."""

    component: str
    error: str
    unit: str
    coefficient: str
    display: str  # "+ coefficient*error" as the text format prints it


def volumetric_terms(spec: MachineSpec) -> tuple[list[Term], list[str]]:
    """The first-order volumetric error of ``spec`` as terms collected by error symbol, in
    canonical error order per component; and the errors with no first-order effect."""
    import sympy as sp

    from volcal.model.symbolic import build_chain

    ch = build_chain(spec)
    # readable names: axis positions as the axes (measurement-table columns), tool offset
    rename = {q: sp.Symbol(a.name, real=True) for q, a in zip(ch.q, spec.axes)}
    rename.update({t: sp.Symbol(f"tool_{c}", real=True) for t, c in zip(ch.t, "xyz")})

    # sin^n -> sin^(n-2) (1 - cos^2) until every sine is of power one: a canonical form in
    # which sin^2 + cos^2 cancels (cheap, unlike trigsimp)
    def is_sin_power(x):
        return x.is_Pow and x.base.func == sp.sin and x.exp.is_Integer and x.exp >= 2

    def lower_sin_power(x):
        return sp.sin(x.base.args[0]) ** (x.exp - 2) * (1 - sp.cos(x.base.args[0]) ** 2)

    def canonical(x):
        x = sp.expand(x)
        while x.has(sp.sin) and x.find(is_sin_power):
            x = sp.expand(x.replace(is_sin_power, lower_sin_power))
        return x

    units = {s.name: s.unit for s in error_symbols(spec)}
    terms: list[Term] = []
    seen: set[str] = set()
    for comp, expr in zip(_COMPONENTS, ch.first_order):
        expanded = canonical(expr)
        coeffs = sp.collect(expanded, ch.e, evaluate=False) if expanded != 0 else {}
        stray = set(coeffs) - set(ch.e)
        if stray:  # a term free of errors would mean the expression is not first order
            raise RuntimeError(f"first-order {comp} has terms without an error symbol: {stray}")
        for e in ch.e:
            c = coeffs.get(e, 0)
            if c == 0:
                continue
            c = sp.factor_terms(c).xreplace(rename)
            if c.is_Add:  # pull out a minus only when most terms are negative
                negative = 2 * sum(a.could_extract_minus_sign() for a in c.args) > len(c.args)
            else:
                negative = c.could_extract_minus_sign()
            sign, mag = ("-", -c) if negative else ("+", c)
            mag_text = f"({sp.sstr(mag)})" if mag.is_Add else sp.sstr(mag)
            body = e.name if mag == 1 else f"{mag_text}*{e.name}"
            terms.append(Term(comp, e.name, units[e.name], sp.sstr(c), f"{sign} {body}"))
            seen.add(e.name)
    silent = [e.name for e in ch.e if e.name not in seen]
    return terms, silent


def volumetric_text(terms: list[Term], silent: list[str]) -> str:
    lines = []
    for comp in _COMPONENTS:
        mine = [t for t in terms if t.component == comp]
        head = f"{_COMPONENT_TEXT[comp]} = "
        if not mine:
            lines.append(head + "0")
            continue
        for k, t in enumerate(mine):
            lines.append(f"{head if k == 0 else ' ' * len(head)}{t.display}")
        lines.append("")
    if silent:
        lines.append("no first-order effect on the tool point: " + ", ".join(silent))
    return "\n".join(lines).rstrip()


def run_show(args) -> int:
    from volcal.model.spec import resolve_model

    spec = resolve_model(args.model)
    sections: tuple[str, ...] = _SECTIONS if args.section == "all" else (args.section,)
    axes_header = [
        "axis",
        "kind",
        "branch",
        "direction",
        "travel_min",
        "travel_max",
        "reference",
        "unit",
        "center_x_mm",
        "center_y_mm",
        "center_z_mm",
    ]
    err_header = ["name", "axis", "kind", "quantity", "unit", "report_unit", "meaning"]
    vol_header = ["component", "error", "error_unit", "coefficient"]
    terms: list = []
    silent: list[str] = []
    n_rot = sum(a.is_rotary for a in spec.axes)
    too_big = None
    if "volumetric" in sections and n_rot > MAX_WRITTEN_ROTARY:
        # each rotary axis doubles the terms of the expanded formula: 4 rotary axes take
        # seconds, 6 a quarter of a minute, 12 hours; the model itself builds in linear time
        too_big = (
            f"the first-order volumetric error is not written out: written out in "
            f"full it has about 2^{n_rot} terms per error quantity ({n_rot} rotary "
            f"axes; at most {MAX_WRITTEN_ROTARY} are written out); volcal builds and "
            "uses the model without it"
        )
        if args.section == "volumetric":
            from volcal.base.exceptions import InputError

            raise InputError(too_big, source=str(args.model))
        sections = tuple(x for x in sections if x != "volumetric")
    if "volumetric" in sections:
        terms, silent = volumetric_terms(spec)

    if args.format == "csv":
        for k, sec in enumerate(sections):
            if len(sections) > 1:
                if k:
                    print()
                print(f"# {sec}")
            if sec == "axes":
                _write_csv(axes_header, axis_rows(spec))
            elif sec == "errors":
                _write_csv(err_header, error_rows(spec))
            else:
                _write_csv(
                    vol_header, [[t.component, t.error, t.unit, t.coefficient] for t in terms]
                )
        if too_big:
            print(f"\n# volumetric: {too_big}")
        return 0

    out = []
    if len(sections) > 1:
        out += [
            f"model {spec.name}: {spec.description}".rstrip(": "),
            f"chain {chain_string(spec)} (W workpiece, F machine frame, T tool); "
            f"{len(spec.axes)} axes, {len(error_symbols(spec))} error quantities (each a "
            "function of its axis or a constant; an identification fits the parameters of "
            "their bases)",
            "",
        ]
    if "axes" in sections:
        rows = []
        for r in axis_rows(spec):
            name, kind, branch, direction, lo, hi, ref, unit, cx, cy, cz = r
            centre = f"({cx}, {cy}, {cz})" if cx else "-"
            rows.append(
                [name, kind, branch, direction, f"{lo} .. {hi} {unit}", f"{ref} {unit}", centre]
            )
        out += [
            "axes (chain order: workpiece -> frame -> tool)",
            _text_table(
                ["axis", "kind", "branch", "direction", "travel", "reference", "centre (mm)"], rows
            ),
            "",
        ]
    if "errors" in sections:
        rows = [
            [n, ax, kind, f"{unit} ({rep.replace('u', 'µ')} in reports)", meaning]
            for n, ax, kind, _q, unit, rep, meaning in error_rows(spec)
        ]
        out += [
            "error quantities (error = actual - nominal; mm and rad inside volcal, "
            "µm and µrad in reports)",
            _text_table(["name", "axis", "kind", "unit", "meaning"], rows),
            "",
        ]
    if "volumetric" in sections:
        axes_legend = ", ".join(f"{a.name} ({'rad' if a.is_rotary else 'mm'})" for a in spec.axes)
        out += [
            "first-order volumetric error (actual - nominal tool point, mm, workpiece frame)",
            f"positions: {axes_legend}; tool offset tool_x, tool_y, tool_z (mm, tool frame)",
            "",
            volumetric_text(terms, silent),
            "",
        ]
    if too_big:
        out += [too_big, ""]
    print("\n".join(out).rstrip())
    return 0


# --------------------------------------------------------------------------------------
# output helpers


def _write_csv(header: list[str], rows: list[list]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    sys.stdout.write(buf.getvalue())


def _text_table(header: list[str], rows: list[list]) -> str:
    cells = [[str(c) for c in header]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[k]) for r in cells) for k in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
