"""Machine topology descriptions: the Python API and the TOML files that map onto it.

A topology is a serial chain from the workpiece through the machine frame to the tool.
Axes are listed in chain order: first the workpiece-branch axes, from the workpiece towards
the frame, then the tool-branch axes, from the frame towards the tool.  Every field of a
TOML ``[[axis]]`` table is a field of :class:`AxisSpec`, and the top-level keys are the
fields of :class:`MachineSpec`, one to one.

Error names are generated (ISO 230-1 / ISO 230-7), never typed by hand:

* component error motions of axis ``J`` (linear or rotary): ``EXJ, EYJ, EZJ`` (translational,
  mm) and ``EAJ, EBJ, ECJ`` (angular, rad);
* location errors of a linear axis (squareness of its direction of travel), one per pair of
  linear axes, carried by the later axis of the pair in x < y < z order: ``EC0Y`` (Y to X
  about z), ``EB0Z`` (Z to X about y), ``EA0Z`` (Z to Y about x);
* location errors of a rotary axis ``J`` (position and orientation of its average line):
  two offsets perpendicular to it (``EX0C, EY0C`` for a C axis) and two tilts (``EA0C, EB0C``);
* the tool's zero position ``EX0T, EY0T, EZ0T`` (mm) and zero orientation ``EA0T, EB0T, EC0T``
  (rad): where the spindle reference point and the spindle's axes really are relative to the
  last axis of the tool branch.  Controllers' volumetric compensation carries exactly these
  (zero position and orientation of the tool).  They matter as soon as the tool offset
  varies: angular errors that are not zero at the reference position act on the tool
  offset, and under an ISO 230 datum only these parameters can carry that part.

Error bases (how each component error motion depends on its axis position, see
:mod:`volcal.model.errors` and docs/error_bases.md) can be declared per axis and per error motion::

    [[axis]]
    name = "C"
    kind = "rotary"
    # ...
    basis = { kind = "fourier", degree = 3 }        # every component error motion of C
    error_basis = { EZC = { kind = "fourier", degree = 5 } }   # this one differs

A basis table holds ``kind`` (``poly``, ``fourier``, ``bspline``, ``table``, ``constant``)
and the one field that kind uses: ``degree`` (poly: Legendre degree; fourier: highest
harmonic), ``segments`` (bspline) or ``knots`` (table, axis positions in mm / deg); they are
the fields of :class:`ErrorForm`.  Without a declaration a rotary axis that turns a full
turn gets the Fourier series, every other axis the Legendre series.

Reading a model file never executes code: TOML is parsed with :mod:`tomllib` and every
value is type-checked; numbers must be TOML numbers, never strings or expressions.
"""

from __future__ import annotations

import hashlib
import json
import math
import numbers
import re
import tomllib
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from volcal.base.exceptions import InputError

AXIS_LETTERS = "XYZ"
ROT_LETTERS = "ABC"
_NAME_RE = re.compile(r"^[A-Z][A-Z0-9]{0,3}$")
# model names end up in file names (the build cache): no path separators, no spaces
_MODEL_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_DIRECTIONS = {
    "+x": (0, 1),
    "-x": (0, -1),
    "+y": (1, 1),
    "-y": (1, -1),
    "+z": (2, 1),
    "-z": (2, -1),
}

#: kinds of error bases (:class:`ErrorForm`)
BASIS_KINDS = ("poly", "fourier", "bspline", "table", "constant")
#: the field each basis kind uses besides ``kind``
_BASIS_FIELDS = {
    "poly": ("degree",),
    "fourier": ("degree",),
    "bspline": ("segments",),
    "table": ("knots",),
    "constant": (),
}
_FORM_DEFAULTS = {"degree": 3, "knots": (), "segments": 4}


@dataclass(frozen=True)
class ErrorForm:
    """The basis of one error motion: e(x) = sum_j theta_j b_j(x) (see :mod:`volcal.model.errors`).

    kind: ``"poly"``: Legendre series P_0 .. P_degree of the travel normalised to [-1, 1];
    ``"fourier"``: 1, cos(k x), sin(k x) for k = 1 .. degree, x the angle in rad (rotary
    axes: ISO 230-7 error motions of a full turn are periodic); ``"bspline"``: clamped
    uniform cubic B-spline of ``segments`` segments over the travel (segments + 3
    functions); ``"table"``: piecewise linear between values at ``knots`` (axis positions,
    mm or deg); ``"constant"``: one value.
    degree: poly and fourier; segments: bspline; knots: table.  A field the kind does not
    use is reset to its default, so equal bases compare equal.  In a model file the same
    fields form a table: ``basis = { kind = "bspline", segments = 6 }``.
    """

    kind: Literal["poly", "fourier", "bspline", "table", "constant"] = "poly"
    degree: int = 3
    knots: tuple[float, ...] = ()
    segments: int = 4

    def __post_init__(self) -> None:
        if self.kind not in BASIS_KINDS:
            raise InputError(
                f"unknown basis kind {self.kind!r}; expected one of {list(BASIS_KINDS)}"
            )
        used = _BASIS_FIELDS[self.kind]
        for f, v in _FORM_DEFAULTS.items():
            if f not in used:
                object.__setattr__(self, f, v)
        if "knots" in used:
            object.__setattr__(self, "knots", tuple(float(k) for k in self.knots))
        for f in ("degree", "segments"):  # numpy integers from the API become ints
            v = getattr(self, f)
            if isinstance(v, numbers.Integral) and not isinstance(v, bool):
                object.__setattr__(self, f, int(v))

    @property
    def n_params(self) -> int:
        """Number of basis functions (parameters) of this form."""
        return {
            "poly": self.degree + 1,
            "fourier": 2 * self.degree + 1,
            "bspline": self.segments + 3,
            "table": len(self.knots),
            "constant": 1,
        }[self.kind]

    def problem(self, rotary: bool | None = None) -> str | None:
        """What is wrong with this form (on a rotary axis when ``rotary``), or None."""
        if self.kind in ("poly", "fourier") and (
            isinstance(self.degree, bool) or not isinstance(self.degree, int) or self.degree < 0
        ):
            return f"{self.kind} degree must be an integer >= 0, got {self.degree!r}"
        if self.kind == "bspline" and (
            isinstance(self.segments, bool)
            or not isinstance(self.segments, int)
            or self.segments < 1
        ):
            return f"bspline segments must be an integer >= 1, got {self.segments!r}"
        if self.kind == "table" and (
            len(self.knots) < 2 or any(not b > a for a, b in zip(self.knots, self.knots[1:]))
        ):
            return f"table knots must be at least two increasing positions, got {self.knots}"
        if self.kind == "fourier" and rotary is False:
            return "a fourier basis applies to rotary axes only (x is the angle)"
        return None

    def to_dict(self) -> dict[str, Any]:
        """The model-file table of this form (``kind`` and the field it uses)."""
        d: dict[str, Any] = {"kind": self.kind}
        for f in _BASIS_FIELDS[self.kind]:
            v = getattr(self, f)
            d[f] = [float(k) for k in v] if f == "knots" else int(v)
        return d

    def describe(self) -> str:
        """A short readable label (``Fourier series, harmonics 1..3``)."""
        return {
            "poly": f"Legendre polynomial, degree {self.degree}",
            "fourier": f"Fourier series, harmonics 1..{self.degree}",
            "bspline": f"cubic B-spline, {self.segments} segments",
            "table": f"piecewise-linear table, {len(self.knots)} knots",
            "constant": "constant",
        }[self.kind]


@dataclass(frozen=True)
class AxisSpec:
    """One machine axis.

    name: axis name (``X``, ``Y``, ``Z``, ``A``, ``B``, ``C``, ``U`` ...).
    kind: ``"linear"`` (positions in mm) or ``"rotary"`` (positions in deg in files and
        reports, rad inside the code).
    direction: nominal direction of travel (linear) or of the rotation vector by the
        right-hand rule (rotary): one of ``+x -x +y -y +z -z`` in the machine frame.
    branch: ``"workpiece"`` (the axis moves the workpiece) or ``"tool"``.
    travel: (min, max) axis position, mm or deg.
    reference: reference position where datum conventions put errors to zero, mm or deg.
    center: a point on the nominal rotation axis line, mm (rotary axes only).
    errors: ``"all"`` or the list of component error names to include (e.g. ``["EXX"]``).
    location: ``"all"``/``"none"`` or the list of location error names to include.
    exclude: names to drop from the generated set (component or location).
    basis: the :class:`ErrorForm` of every component error motion of this axis (None: the
        default, Fourier for a full-turn rotary axis, else Legendre).
    error_basis: per component error motion ``(name, ErrorForm)`` pairs overriding ``basis``.
    """

    name: str
    kind: Literal["linear", "rotary"]
    direction: str
    branch: Literal["workpiece", "tool"]
    travel: tuple[float, float]
    reference: float = 0.0
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    errors: str | tuple[str, ...] = "all"
    location: str | tuple[str, ...] = "all"
    exclude: tuple[str, ...] = ()
    basis: ErrorForm | None = None
    error_basis: tuple[tuple[str, ErrorForm], ...] = ()

    @property
    def full_turn(self) -> bool:
        """A rotary axis whose travel spans at least a full turn."""
        return self.is_rotary and (self.travel[1] - self.travel[0]) >= 360.0 - 1e-9

    @property
    def dir_index(self) -> int:
        return _DIRECTIONS[self.direction][0]

    @property
    def dir_sign(self) -> int:
        return _DIRECTIONS[self.direction][1]

    @property
    def is_rotary(self) -> bool:
        return self.kind == "rotary"

    def component_error_names(self) -> list[str]:
        """All six ISO 230-1 component error motion names of this axis."""
        return [f"E{c}{self.name}" for c in AXIS_LETTERS + ROT_LETTERS]


@dataclass(frozen=True, repr=False)
class MachineSpec:
    """A machine topology: a name, a description and the axes in chain order.

    tool_errors: ``"all"``/``"none"`` or the list of tool zero position / orientation
    errors (``EX0T EY0T EZ0T EA0T EB0T EC0T``) to include.
    """

    name: str
    axes: tuple[AxisSpec, ...]
    description: str = ""
    tool_errors: str | tuple[str, ...] = "all"

    @property
    def axis_names(self) -> list[str]:
        return [a.name for a in self.axes]

    def axis(self, name: str) -> AxisSpec:
        for a in self.axes:
            if a.name == name:
                return a
        raise KeyError(name)

    def __repr__(self) -> str:
        axes = " ".join(f"{a.name}({a.kind[0]})" for a in self.axes)
        return f"MachineSpec({self.name!r}: {axes})"

    def _repr_html_(self) -> str:
        """A table of the axes for Jupyter."""
        from html import escape

        rows = "".join(
            f"<tr><td>{escape(a.name)}</td><td>{a.kind}</td><td>{escape(a.direction)}</td>"
            f"<td>{a.branch}</td><td>{a.travel[0]:g} .. {a.travel[1]:g} "
            f"{'deg' if a.is_rotary else 'mm'}</td></tr>"
            for a in self.axes
        )
        return (
            f"<b>{escape(self.name)}</b> {escape(self.description)}<table><tr><th>axis</th>"
            f"<th>kind</th><th>direction</th><th>branch</th><th>travel</th></tr>{rows}</table>"
        )

    def fingerprint(self) -> str:
        """Content hash of the topology (used as the build-cache key).  Error bases are
        not part of the topology: the machine's functions do not depend on them."""
        d = asdict(self)
        for a in d["axes"]:
            a.pop("basis", None)
            a.pop("error_basis", None)
        blob = json.dumps(d, sort_keys=True, default=list).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# --------------------------------------------------------------------------------------
# error names


@dataclass(frozen=True)
class ErrorSymbol:
    """One error quantity of the model.

    name: ISO name (``EXX``, ``EC0Y`` ...); axis: the axis it belongs to (``"T"`` for the
    tool's zero position and orientation, which belong to no axis);
    kind: ``"component"`` (function of the axis position), ``"location"`` (constant) or
    ``"tool"`` (constant: the tool's zero position and orientation);
    quantity: ``"translation"`` (mm) or ``"rotation"`` (rad);
    component: index 0..2 of the machine-frame direction it acts along / about.
    """

    name: str
    axis: str
    kind: Literal["component", "location", "tool"]
    quantity: Literal["translation", "rotation"]
    component: int

    @property
    def unit(self) -> str:
        return "mm" if self.quantity == "translation" else "rad"


def _location_candidates(axis: AxisSpec, linear_dirs: set[int]) -> list[ErrorSymbol]:
    i = axis.dir_index
    out: list[ErrorSymbol] = []
    if axis.kind == "linear":
        # A squareness belongs to a pair of linear axes; the later one in x<y<z order
        # carries it, so that each pair is counted once.
        for j in range(3):
            k = 3 - i - j
            if j == i or k == i:
                continue
            if k < i and k in linear_dirs:
                out.append(
                    ErrorSymbol(
                        f"E{ROT_LETTERS[j]}0{axis.name}", axis.name, "location", "rotation", j
                    )
                )
    else:
        for j in range(3):
            if j != i:
                out.append(
                    ErrorSymbol(
                        f"E{AXIS_LETTERS[j]}0{axis.name}", axis.name, "location", "translation", j
                    )
                )
        for j in range(3):
            if j != i:
                out.append(
                    ErrorSymbol(
                        f"E{ROT_LETTERS[j]}0{axis.name}", axis.name, "location", "rotation", j
                    )
                )
    return out


def error_symbols(spec: MachineSpec) -> list[ErrorSymbol]:
    """The error quantities of a topology in canonical order: per axis in chain order,
    its selected component errors (X, Y, Z, A, B, C order) then its location errors."""
    linear_dirs = {a.dir_index for a in spec.axes if a.kind == "linear"}
    out: list[ErrorSymbol] = []
    for a in spec.axes:
        comps = [
            ErrorSymbol(
                f"E{c}{a.name}", a.name, "component", "translation" if k < 3 else "rotation", k % 3
            )
            for k, c in enumerate(AXIS_LETTERS + ROT_LETTERS)
        ]
        if a.errors != "all":
            comps = [s for s in comps if s.name in a.errors]
        locs = _location_candidates(a, linear_dirs)
        if a.location == "none":
            locs = []
        elif a.location != "all":
            locs = [s for s in locs if s.name in a.location]
        out.extend(s for s in comps + locs if s.name not in a.exclude)
    tool = tool_symbols()
    if spec.tool_errors == "none":
        tool = []
    elif spec.tool_errors != "all":
        tool = [s for s in tool if s.name in spec.tool_errors]
    return out + tool


TOOL_AXIS = "T"


def tool_symbols() -> list[ErrorSymbol]:
    """The tool's zero position (``EX0T EY0T EZ0T``, mm) and zero orientation
    (``EA0T EB0T EC0T``, rad), in the tool frame."""
    return [
        ErrorSymbol(f"E{c}0{TOOL_AXIS}", TOOL_AXIS, "tool", "translation", j)
        for j, c in enumerate(AXIS_LETTERS)
    ] + [
        ErrorSymbol(f"E{c}0{TOOL_AXIS}", TOOL_AXIS, "tool", "rotation", j)
        for j, c in enumerate(ROT_LETTERS)
    ]


# --------------------------------------------------------------------------------------
# validation and TOML


def _check_number(value: Any, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(
            f"expected a number, got {type(value).__name__} {value!r}", source=where, column=key
        )
    if not math.isfinite(value):
        raise InputError(f"expected a finite number, got {value!r}", source=where, column=key)
    return float(value)


def _check_names(value: Any, where: str, key: str, allowed: list[str]) -> str | tuple[str, ...]:
    if isinstance(value, str) and value in ("all", "none"):
        return value
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise InputError(
            f'expected "all", "none" or a list of error names from {allowed}, got {value!r}',
            source=where,
            column=key,
        )
    bad = [v for v in value if v not in allowed]
    if bad:
        raise InputError(
            f"unknown error name(s) {bad}; this axis generates {allowed}", source=where, column=key
        )
    return tuple(value)


_AXIS_KEYS = {
    "name",
    "kind",
    "direction",
    "branch",
    "travel",
    "reference",
    "center",
    "errors",
    "location",
    "exclude",
    "basis",
    "error_basis",
}


def form_from_dict(d: Any, where: str, key: str, rotary: bool | None = None) -> ErrorForm:
    """Validate one basis table (``{kind = "fourier", degree = 3}``) into an
    :class:`ErrorForm`; ``key`` names it in errors (``basis``, ``error_basis.EZC``)."""
    if not isinstance(d, dict):
        raise InputError(
            f'expected a table such as {{ kind = "poly", degree = 3 }}, got {d!r}',
            source=where,
            column=key,
        )
    kind = d.get("kind")
    if kind not in BASIS_KINDS:
        raise InputError(
            f"expected a basis kind from {list(BASIS_KINDS)}, got {kind!r}",
            source=where,
            column=f"{key}.kind",
        )
    allowed = ("kind",) + _BASIS_FIELDS[kind]
    unknown = sorted(set(d) - set(allowed))
    if unknown:
        raise InputError(
            f"unknown key(s) {unknown} for a {kind} basis; allowed: {list(allowed)}",
            source=where,
            column=key,
        )
    args: dict[str, Any] = {}
    for f in _BASIS_FIELDS[kind]:
        if f not in d:
            continue
        v = d[f]
        if f == "knots":
            if not isinstance(v, list):
                raise InputError(
                    f"expected a list of axis positions, got {v!r}",
                    source=where,
                    column=f"{key}.knots",
                )
            args[f] = tuple(_check_number(x, where, f"{key}.knots") for x in v)
        elif isinstance(v, bool) or not isinstance(v, int):
            raise InputError(
                f"expected an integer, got {type(v).__name__} {v!r}",
                source=where,
                column=f"{key}.{f}",
            )
        else:
            args[f] = v
    form = ErrorForm(kind, **args)
    bad = form.problem(rotary)
    if bad:
        raise InputError(bad, source=where, column=key)
    return form


def axis_from_dict(d: dict[str, Any], where: str) -> AxisSpec:
    """Validate one ``[[axis]]`` table (``where`` names it in errors)."""
    unknown = set(d) - _AXIS_KEYS
    if unknown:
        raise InputError(
            f"unknown key(s) {sorted(unknown)}; allowed: {sorted(_AXIS_KEYS)}", source=where
        )
    for key in ("name", "kind", "direction", "branch", "travel"):
        if key not in d:
            raise InputError("missing required key", source=where, column=key)
    name = d["name"]
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise InputError(
            f"expected an axis name of 1-4 upper-case letters/digits starting with a "
            f"letter, got {name!r}",
            source=where,
            column="name",
        )
    where = f"{where} (axis {name})"
    kind = d["kind"]
    if kind not in ("linear", "rotary"):
        raise InputError(
            f'unknown axis kind {kind!r}; expected "linear" or "rotary"',
            source=where,
            column="kind",
        )
    if not isinstance(d["direction"], str) or d["direction"] not in _DIRECTIONS:
        raise InputError(
            f"expected one of {list(_DIRECTIONS)}, got {d['direction']!r}",
            source=where,
            column="direction",
        )
    if d["branch"] not in ("workpiece", "tool"):
        raise InputError(
            f'expected "workpiece" or "tool", got {d["branch"]!r}', source=where, column="branch"
        )
    travel = d["travel"]
    if not isinstance(travel, list) or len(travel) != 2:
        raise InputError(f"expected [min, max], got {travel!r}", source=where, column="travel")
    lo, hi = (_check_number(v, where, "travel") for v in travel)
    if not lo < hi:
        raise InputError(f"expected min < max, got [{lo}, {hi}]", source=where, column="travel")
    # default reference: zero when it lies in the travel, else the end nearest to zero
    default_ref = lo if lo > 0 else hi if hi < 0 else 0.0
    ref = _check_number(d.get("reference", default_ref), where, "reference")
    if not lo <= ref <= hi:
        raise InputError(
            f"reference {ref} outside travel [{lo}, {hi}]", source=where, column="reference"
        )
    if kind == "linear" and "center" in d:
        raise InputError("'center' applies to rotary axes only", source=where, column="center")
    center = d.get("center", [0.0, 0.0, 0.0])
    if not isinstance(center, list) or len(center) != 3:
        raise InputError(f"expected [x, y, z] in mm, got {center!r}", source=where, column="center")
    center = tuple(_check_number(v, where, "center") for v in center)
    probe = AxisSpec(name, kind, d["direction"], d["branch"], (lo, hi), ref, center)
    comp_names = probe.component_error_names()
    errors = _check_names(d.get("errors", "all"), where, "errors", comp_names)
    if errors == "none":
        errors = ()
    loc_names = [s.name for s in _location_candidates(probe, {0, 1, 2})]
    location = _check_names(d.get("location", "all"), where, "location", loc_names)
    exclude = d.get("exclude", [])
    if not isinstance(exclude, list):
        raise InputError(
            f"expected a list of error names from {comp_names + loc_names}, got {exclude!r}",
            source=where,
            column="exclude",
        )
    exclude_names = _check_names(exclude, where, "exclude", comp_names + loc_names)
    # a list was checked above: never "all" / "none" here
    exclude = exclude_names if isinstance(exclude_names, tuple) else ()
    rotary = kind == "rotary"
    basis = form_from_dict(d["basis"], where, "basis", rotary) if "basis" in d else None
    eb = d.get("error_basis", {})
    if not isinstance(eb, dict):
        raise InputError(
            f"expected a table of error names to basis tables, got {eb!r}",
            source=where,
            column="error_basis",
        )
    bad = [n for n in eb if n not in comp_names]
    if bad:
        raise InputError(
            f"unknown component error name(s) {bad}; this axis generates {comp_names}",
            source=where,
            column="error_basis",
        )
    error_basis = tuple(
        (n, form_from_dict(v, where, f"error_basis.{n}", rotary)) for n, v in eb.items()
    )
    return AxisSpec(
        name,
        kind,
        d["direction"],
        d["branch"],
        (lo, hi),
        ref,
        center,
        errors,
        location,
        exclude,
        basis,
        error_basis,
    )


# limits checked when a model is loaded: a model beyond them is refused with a clear
# InputError instead of exhausting the stack, the memory or the user's patience
MAX_MODEL_BYTES = 1_000_000  # size of a model file
MAX_NESTING = 8  # tables / arrays inside each other (a model needs 4)
MAX_AXES = 12  # axes in the chain
MAX_ERROR_SYMBOLS = 250  # error parameters of the chain (12 rotary axes: 133)


def _nesting(doc: Any) -> int:
    """Depth of nested tables and arrays (iterative: no recursion on hostile input)."""
    deepest, stack = 0, [(doc, 0)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, dict):
            v = list(v.values())
        elif not isinstance(v, list):
            continue
        depth += 1
        deepest = max(deepest, depth)
        if deepest > MAX_NESTING:
            return deepest
        stack.extend((x, depth) for x in v)
    return deepest


def machine_from_dict(d: dict[str, Any], where: str = "<model>") -> MachineSpec:
    """Validate a parsed model document and build its :class:`MachineSpec`."""
    if not isinstance(d, dict):
        raise InputError(
            f"expected a table (the model document), got {type(d).__name__}", source=where
        )
    if _nesting(d) > MAX_NESTING:
        raise InputError(
            f"tables or arrays are nested more than {MAX_NESTING} deep; a model "
            "needs [[axis]] tables with plain values",
            source=where,
        )
    allowed = {"name", "description", "axis", "tool_errors"}
    unknown = set(d) - allowed
    if unknown:
        raise InputError(
            f"unknown top-level key(s) {sorted(unknown)}; allowed: {sorted(allowed)}", source=where
        )
    if "name" not in d:
        raise InputError("missing required key (the model name)", source=where, column="name")
    if not isinstance(d["name"], str) or not _MODEL_NAME_RE.match(d["name"]):
        raise InputError(
            "expected a model name of 1-64 letters, digits, '_', '-' or '.' "
            f"starting with a letter or digit, got {d['name']!r}",
            source=where,
            column="name",
        )
    desc = d.get("description", "")
    if not isinstance(desc, str):
        raise InputError("expected a string", source=where, column="description")
    axes_raw = d.get("axis")
    if not isinstance(axes_raw, list) or not axes_raw:
        raise InputError("expected one or more [[axis]] tables", source=where, column="axis")
    if len(axes_raw) > MAX_AXES:
        raise InputError(
            f"{len(axes_raw)} axes; volcal models hold at most {MAX_AXES}",
            source=where,
            column="axis",
        )
    axes = []
    for k, a in enumerate(axes_raw):
        if not isinstance(a, dict):
            raise InputError("expected a table", source=where, column=f"axis[{k}]")
        axes.append(axis_from_dict(a, f"{where} [[axis]] #{k + 1}"))
    names = [a.name for a in axes]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"duplicate axis name(s) {dup}", source=where, column="axis.name")
    branches = [a.branch for a in axes]
    if "workpiece" in branches[branches.index("tool") :] if "tool" in branches else False:
        raise InputError(
            "axes must be listed in chain order: all workpiece-branch axes "
            "(workpiece -> frame) before all tool-branch axes (frame -> tool)",
            source=where,
            column="axis.branch",
        )
    lin_dirs = [a.dir_index for a in axes if a.kind == "linear"]
    if len(set(lin_dirs)) != len(lin_dirs):
        raise InputError(
            "two linear axes share a direction; volcal needs distinct directions "
            "for the ISO error names",
            source=where,
            column="axis.direction",
        )
    tool = _check_names(
        d.get("tool_errors", "all"), where, "tool_errors", [s.name for s in tool_symbols()]
    )
    if "T" in names:
        raise InputError(
            "axis name 'T' is reserved for the tool's zero position and "
            "orientation errors (EX0T ... EC0T)",
            source=where,
            column="axis.name",
        )
    spec = MachineSpec(d["name"], tuple(axes), desc, tool)
    n_err = len(error_symbols(spec))
    if n_err > MAX_ERROR_SYMBOLS:
        raise InputError(
            f"{n_err} error parameters; volcal models hold at most {MAX_ERROR_SYMBOLS}",
            source=where,
            column="axis",
        )
    return spec


def spec_to_dict(spec: MachineSpec) -> dict[str, Any]:
    """The model document (TOML form, as parsed by :mod:`tomllib`) of a spec:
    ``machine_from_dict(spec_to_dict(spec)) == spec``.  Plain lists, strings and floats
    only, so that it serialises to JSON or TOML as is."""

    def names(v: str | tuple[str, ...]) -> str | list[str]:
        return v if isinstance(v, str) else list(v)

    axes = []
    for a in spec.axes:
        d: dict[str, Any] = {
            "name": a.name,
            "kind": a.kind,
            "direction": a.direction,
            "branch": a.branch,
            "travel": [float(a.travel[0]), float(a.travel[1])],
            "reference": float(a.reference),
        }
        if a.is_rotary:
            d["center"] = [float(c) for c in a.center]
        d["errors"] = names(a.errors)
        d["location"] = names(a.location)
        if a.exclude:
            d["exclude"] = list(a.exclude)
        if a.basis is not None:
            d["basis"] = a.basis.to_dict()
        if a.error_basis:
            d["error_basis"] = {n: f.to_dict() for n, f in a.error_basis}
        axes.append(d)
    return {
        "name": spec.name,
        "description": spec.description,
        "tool_errors": names(spec.tool_errors),
        "axis": axes,
    }


def load_model_file(path: str | Path) -> MachineSpec:
    """Parse and validate a model TOML file (never executes any of its content)."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"cannot read model file: {exc.strerror}", source=str(path)) from None
    if size > MAX_MODEL_BYTES:
        raise InputError(
            f"the file has {size} bytes; a model file holds at most "
            f"{MAX_MODEL_BYTES} (is it a model?)",
            source=str(path),
        )
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read model file: {exc.strerror}", source=str(path)) from exc
    except UnicodeDecodeError as exc:
        raise InputError(
            f"not a UTF-8 text file (TOML expected): {exc.reason} at byte {exc.start}",
            source=str(path),
        ) from exc
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source=str(path)) from None
    except RecursionError:
        raise InputError(
            f"tables or arrays are nested too deeply (at most {MAX_NESTING})", source=str(path)
        ) from None
    return machine_from_dict(doc, str(path))


def bundled_models() -> dict[str, Path]:
    """Names and paths of the models shipped with volcal."""
    root = resources.files("volcal.models")
    return {
        Path(p.name).stem: Path(str(p))
        for p in sorted(root.iterdir(), key=lambda p: p.name)
        if p.name.endswith(".toml")
    }


def resolve_model(model: str | Path | MachineSpec) -> MachineSpec:
    """A bundled model name, a model file path, or a spec (returned as is)."""
    if isinstance(model, MachineSpec):
        return model
    models = bundled_models()
    if isinstance(model, str) and model in models:
        return load_model_file(models[model])
    p = Path(model)
    if p.exists():
        return load_model_file(p)
    raise InputError(
        f"no bundled model named {str(model)!r} and no such file; bundled models: {sorted(models)}",
        source=str(model),
    )
