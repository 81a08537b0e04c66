"""Measurement plans (commanded poses) and default station layouts.

A *plan* is a :class:`pandas.DataFrame` with one column per axis of the model, named as
the axis (``X``, ``Y``, ``Z``, ``B``, ``C`` ...), in model order, one row per commanded
pose, in file units: linear axes in mm, rotary axes in degrees.  Tool offsets are not part
of a plan: the simulator measures every pose with every tool offset it is given.

* :func:`default_plan`: the plan ``simulate`` and ``analyze`` use when none is given: the
  grid below for a model without rotary axes; with rotary axes a linear-axis grid plus
  rotary sweeps over the whole travel at several linear and rotary positions;
* :func:`summary_grid`: the poses over which the "largest volumetric error" is stated
  (linear axes and, on a coarse grid, the rotary axes over their travel);
* :func:`grid_plan`: a full grid over the travel (rotary axes on a coarser grid);
* :func:`line_plan`: lines along each axis through the reference pose;
* :func:`diagonal_plan`: the four body diagonals of the linear-axis box (ISO 230-6);
* :func:`plan_from_csv`: poses from a CSV file (validated);
* :func:`measurement_plan_from_csv`: the poses, tool offsets and stations of a
  measurement plan (one row per reading: ``station, point, <axes>, tool_x_mm, tool_y_mm,
  tool_z_mm[, length_mm]``, as ``volcal plan`` writes it), for the simulator;
* :func:`check_plan`: validation of a plan DataFrame (used by all of the above's callers).

:func:`default_stations` places tracker stations around the workspace for models that have
no stations table of their own.

Every function takes the model as a :class:`~volcal.model.spec.MachineSpec`, a
:class:`~volcal.model.machine.Machine` (its ``spec`` is used), a bundled model name or a model
file path.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError
from volcal.model.spec import AxisSpec, MachineSpec, resolve_model

__all__ = [
    "default_plan",
    "summary_grid",
    "grid_plan",
    "line_plan",
    "diagonal_plan",
    "plan_from_csv",
    "measurement_plan_from_csv",
    "is_measurement_plan",
    "check_plan",
    "default_stations",
    "ROTARY_GRID_FULL_TURN",
    "ROTARY_GRID_PARTIAL",
    "STATION_MIN_CLEARANCE_MM",
    "SUMMARY_ROTARY_FULL_TURN",
    "SUMMARY_ROTARY_PARTIAL",
]

#: Default number of angles of a full-turn rotary axis (travel >= 360 deg) in a grid plan:
#: every 90 deg.
ROTARY_GRID_FULL_TURN = 4
#: Default number of angles of a rotary axis with a partial travel in a grid plan
#: (both ends and the middle).
ROTARY_GRID_PARTIAL = 3
#: Angles of a full-turn rotary axis in :func:`summary_grid` (every 45 deg).
SUMMARY_ROTARY_FULL_TURN = 8
#: Angles of a partial-travel rotary axis in :func:`summary_grid` (both ends included; the
#: reference position is added when it is not among them).
SUMMARY_ROTARY_PARTIAL = 5
#: :func:`default_stations` keeps every station at least this far (mm) from every nominal
#: tool point of the default grid.
STATION_MIN_CLEARANCE_MM = 50.0


def _as_spec(spec: Any) -> MachineSpec:
    """A MachineSpec from a spec, a Machine (duck-typed: ``.spec``), a name or a path."""
    inner = getattr(spec, "spec", None)
    if isinstance(inner, MachineSpec):
        return inner
    return resolve_model(spec)


def _unit(a: AxisSpec) -> str:
    return "deg" if a.is_rotary else "mm"


def _full_turn(a: AxisSpec) -> bool:
    return a.is_rotary and (a.travel[1] - a.travel[0]) >= 360.0 - 1e-9


def _axis_positions(
    a: AxisSpec, n: int, margin: float = 0.0, *, through_reference: bool = False
) -> np.ndarray:
    """``n`` positions (file units) along the travel of one axis.

    Linear axes and partial-travel rotary axes: evenly spaced from ``min + margin`` to
    ``max - margin`` (margin applies to linear axes only, mm).  A full-turn rotary axis:
    ``n`` angles 360/n apart from the start of travel (the end of travel, the same angle
    as the start, is not repeated); with ``through_reference`` one of them is the
    reference position instead (wrapped into ``[min, min + 360)``, sorted).
    ``n = 1``: the reference position.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"axis {a.name}: expected a number of positions >= 1, got {n!r}")
    if n == 1:
        return np.array([a.reference], dtype=float)
    lo, hi = a.travel
    if _full_turn(a):
        start = (a.reference - lo) if through_reference else 0.0
        ang = np.mod(start + 360.0 * np.arange(n) / n, 360.0) + lo
        return np.sort(np.round(ang, 12))
    if not a.is_rotary and margin:
        lo, hi = lo + margin, hi - margin
    return np.linspace(lo, hi, int(n))


def _counts(spec: MachineSpec, n: int | dict[str, int]) -> dict[str, int]:
    out: dict[str, int] = {}
    if isinstance(n, dict):
        unknown = sorted(set(n) - set(spec.axis_names))
        if unknown:
            raise InputError(
                f"grid counts given for unknown axes {unknown}; the model "
                f"'{spec.name}' has axes {spec.axis_names}"
            )
        default = None
    else:
        default = n
    for a in spec.axes:
        if isinstance(n, dict) and a.name in n:
            out[a.name] = n[a.name]
            continue
        base = 5 if default is None else default
        if isinstance(base, bool) or not isinstance(base, (int, np.integer)) or base < 1:
            raise InputError(f"expected a number of grid positions >= 1, got {base!r}")
        if a.is_rotary:
            coarse = ROTARY_GRID_FULL_TURN if _full_turn(a) else ROTARY_GRID_PARTIAL
            out[a.name] = int(min(base, coarse))
        else:
            out[a.name] = int(base)
    return out


def _frame(spec: MachineSpec, rows: np.ndarray) -> pd.DataFrame:
    df = pd.DataFrame(
        np.asarray(rows, dtype=float).reshape(-1, len(spec.axes)), columns=spec.axis_names
    )
    # exact duplicates (e.g. the reference pose on several lines) are measured once
    return df.drop_duplicates(ignore_index=True)


def grid_plan(spec: Any, n: int | dict[str, int] = 5, margin: float = 0.0) -> pd.DataFrame:
    """A full grid of poses over the travel of every axis.

    spec: the model (see the module docstring).
    n: positions per axis: an int for every linear axis, or ``{axis name: count}``
        (axes not named get 5 or the rotary default).  Rotary axes get a coarser grid:
        ``min(n, 4)`` angles 360/min(n, 4) deg apart from the start of travel for a
        full-turn axis (-180, -90, 0, 90 for a C axis from -180 to 180), ``min(n, 3)``
        evenly spaced angles (both ends and the middle) for a partial travel, unless
        given in the dict.
        A count of 1 puts the axis at its reference position.
    margin: distance (mm) kept clear of both ends of travel of every linear axis.

    Returns the plan (columns = axis names, mm / deg), the last axis varying fastest.
    """
    spec = _as_spec(spec)
    margin = float(margin)
    for a in spec.axes:
        if not a.is_rotary and not 0.0 <= 2 * margin < (a.travel[1] - a.travel[0]):
            raise InputError(
                f"margin {margin:g} mm leaves no travel on axis {a.name} "
                f"(travel {a.travel[0]:g} .. {a.travel[1]:g} mm)"
            )
    counts = _counts(spec, n)
    grids = [_axis_positions(a, counts[a.name], margin) for a in spec.axes]
    return _frame(spec, np.array(list(itertools.product(*grids))))


def _reference(spec: MachineSpec) -> np.ndarray:
    return np.array([a.reference for a in spec.axes], dtype=float)


def summary_grid(spec: Any, n: int = 5) -> pd.DataFrame:
    """The poses over which volcal states a model's largest volumetric error.

    ``n`` positions per linear axis over its travel, and every rotary axis over its
    travel too on a coarse grid that holds its reference position:
    :data:`SUMMARY_ROTARY_FULL_TURN` angles 45 deg apart for a full turn,
    :data:`SUMMARY_ROTARY_PARTIAL` evenly spaced angles (both ends) plus the reference
    for a partial travel.  Without rotary axes this is ``grid_plan(spec, n)``.  Returns
    the poses (columns = axis names, mm / deg), the last axis varying fastest."""
    spec = _as_spec(spec)
    grids = []
    for a in spec.axes:
        if not a.is_rotary:
            grids.append(_axis_positions(a, n))
        elif _full_turn(a):
            grids.append(_axis_positions(a, SUMMARY_ROTARY_FULL_TURN, through_reference=True))
        else:
            grids.append(
                np.unique(
                    np.round(np.append(_axis_positions(a, SUMMARY_ROTARY_PARTIAL), a.reference), 9)
                )
            )
    return _frame(spec, np.array(list(itertools.product(*grids))))


def _other_rotary_positions(a: AxisSpec) -> np.ndarray:
    """Where a rotary axis stands while another one sweeps: its reference and two more
    (a full turn: 120 deg apart; a partial travel: both ends, or an end and the middle
    when the reference is an end)."""
    if _full_turn(a):
        return _axis_positions(a, 3, through_reference=True)
    lo, hi = a.travel
    pos = {round(lo, 9), round(a.reference, 9), round(hi, 9)}
    if len(pos) < 3:
        pos.add(round((lo + hi) / 2, 9))
    return np.array(sorted(pos))


def _linear_anchors(spec: MachineSpec, frac: float = 0.75) -> np.ndarray:
    """Linear-axis positions (one row per anchor, columns = linear axes in model order)
    where the rotary sweeps of :func:`default_plan` are measured: corners of the box
    spanned by the linear axes shrunk to ``frac`` of its size about its centre; all
    corners for up to two linear axes, the half with an odd number of upper ends for
    three or more (for X Y Z the four corners of a tetrahedron: lever arms in every
    direction at four heights and radii)."""
    lin = [a for a in spec.axes if not a.is_rotary]
    if not lin:
        return np.zeros((1, 0))
    c = np.array([(a.travel[0] + a.travel[1]) / 2 for a in lin])
    h = np.array([(a.travel[1] - a.travel[0]) / 2 for a in lin]) * frac
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=len(lin))))
    if len(lin) >= 3:
        signs = signs[(signs > 0).sum(axis=1) % 2 == 1]
    return c + signs * h


def default_plan(spec: Any, degree: int = 3) -> pd.DataFrame:
    """The plan ``volcal simulate`` and ``volcal analyze`` measure when none is given.

    Without rotary axes: :func:`grid_plan` with ``max(5, degree + 2)`` positions per
    axis (5 x 5 x 5 for the default Legendre degree 3).

    With rotary axes, a plan that lets the data see every error the volumetric error
    depends on (checked by the plan analysis, ``volcal analyze``), at a size that keeps
    simulate + identify to seconds:

    1. the linear axes on a ``max(5, degree + 2)`` grid with the rotary axes at their
       reference (the linear axes' error motions);
    2. for every rotary axis a sweep over its whole travel: ``2 degree + 6`` angles for a
       full turn (12, 30 deg apart, for degree 3: more than the ``2 degree + 1``
       functions of its Fourier series, and no aliasing of the harmonics it has),
       ``degree + 4`` evenly spaced angles (both ends) for a partial travel; each sweep
       with the other rotary axes at three positions (see below) and the linear axes at
       the corners of a tetrahedron inside their box (at 75 % of the travel about its
       centre): the rotary axes' error motions and location errors, through lever arms
       of different lengths and directions.  A rotary axis that stands still during
       another's sweep is at its reference and two more positions (a full turn: 120 deg
       apart; a partial travel: both ends).

    Tool offsets are not part of a plan: measure every pose with several of them,
    including offsets off the spindle axis (the default of ``volcal simulate``), so that
    the angular errors of the last axes and the tool's orientation are seen.

    degree: the polynomial degree of the error model (default 3).  Returns the plan
    (columns = axis names, mm / deg), duplicates removed.
    """
    spec = _as_spec(spec)
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or degree < 0:
        raise InputError(f"expected a degree >= 0, got {degree!r}")
    n_lin = max(5, int(degree) + 2)
    rot = [j for j, a in enumerate(spec.axes) if a.is_rotary]
    if not rot:
        return grid_plan(spec, n_lin)
    lin = [j for j, a in enumerate(spec.axes) if not a.is_rotary]
    ref = _reference(spec)
    parts = [
        grid_plan(spec, {a.name: (1 if a.is_rotary else n_lin) for a in spec.axes}).to_numpy(float)
    ]
    anchors = _linear_anchors(spec)
    for j in rot:
        a = spec.axes[j]
        sweep = _axis_positions(
            a, 2 * int(degree) + 6 if _full_turn(a) else int(degree) + 4, through_reference=True
        )
        others = [k for k in rot if k != j]
        other_pos = [_other_rotary_positions(spec.axes[k]) for k in others]
        rows = []
        for combo in itertools.product(*other_pos):
            for anchor in anchors:
                for v in sweep:
                    r = ref.copy()
                    r[j] = v
                    r[others] = combo
                    r[lin] = anchor
                    rows.append(r)
        parts.append(np.array(rows))
    return _frame(spec, np.concatenate(parts))


def line_plan(spec: Any, n: int = 11) -> pd.DataFrame:
    """Lines along each axis through the reference pose (ISO 230-1 style single-axis runs).

    For each axis in model order, ``n`` positions over its travel (a full-turn rotary axis:
    ``n`` angles 360/n apart, one at the reference) with every other axis at its reference
    position.  Poses that
    occur on several lines (the reference pose) are kept once.  Returns the plan
    (columns = axis names, mm / deg).
    """
    spec = _as_spec(spec)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise InputError(f"expected n >= 2 positions per line, got {n!r}")
    ref = _reference(spec)
    rows = []
    for j, a in enumerate(spec.axes):
        for v in _axis_positions(a, int(n), through_reference=True):
            r = ref.copy()
            r[j] = v
            rows.append(r)
    return _frame(spec, np.array(rows))


def diagonal_plan(spec: Any, n: int = 11, margin: float = 0.0) -> pd.DataFrame:
    """The body diagonals of the box spanned by the linear axes (ISO 230-6).

    With three linear axes: the four diagonals from each corner of the box where the first
    linear axis is at its minimum to the opposite corner, ``n`` evenly spaced poses each,
    in the order (min, min, min) -> (max, max, max), (min, max, min) -> (max, min, max),
    (min, min, max) -> (max, max, min), (min, max, max) -> (max, min, min).  With k linear
    axes there are 2^(k-1) such diagonals.  Rotary axes stay at their reference positions.
    ``margin`` (mm) shrinks the box from every side.  Poses shared by several diagonals
    (the centre for odd n) are kept once.  Returns the plan (columns = axis names).
    """
    spec = _as_spec(spec)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise InputError(f"expected n >= 2 positions per diagonal, got {n!r}")
    lin = [j for j, a in enumerate(spec.axes) if not a.is_rotary]
    if not lin:
        raise InputError(f"model '{spec.name}' has no linear axis: no body diagonals")
    lo = np.array([spec.axes[j].travel[0] + margin for j in lin])
    hi = np.array([spec.axes[j].travel[1] - margin for j in lin])
    if np.any(hi <= lo):
        raise InputError(f"margin {margin:g} mm leaves no travel on a linear axis")
    ref = _reference(spec)
    s = np.linspace(0.0, 1.0, int(n))
    rows = []
    k = len(lin)
    for code in range(2 ** (k - 1)):
        # start corner: bit b of code set -> axis lin[b] starts at its max; the first
        # linear axis always starts at its min so that each diagonal is listed once
        bits = np.array([(code >> b) & 1 for b in range(k)], dtype=float)
        bits = np.concatenate([[0.0], bits[:-1]]) if k > 1 else np.zeros(1)
        start = np.where(bits > 0, hi, lo)
        end = np.where(bits > 0, lo, hi)
        for v in s:
            r = ref.copy()
            r[lin] = start + v * (end - start)
            rows.append(r)
    return _frame(spec, np.array(rows))


# --------------------------------------------------------------------------------------
# validation


def check_plan(plan: pd.DataFrame, spec: Any, *, source: str = "<plan>") -> pd.DataFrame:
    """Validate a plan DataFrame: one column per model axis (``X`` or ``X_mm``, ``B`` or
    ``B_deg``), finite numbers inside the travel (tolerance
    :data:`volcal.measurement.tables.TRAVEL_TOLERANCE` x travel range), at least one row.  Other
    columns are an error.  Returns a new DataFrame with exactly the axis columns in model
    order (float, mm / deg).  Raises :class:`InputError` naming source, row (spreadsheet
    numbering: header = row 1) and column."""
    from volcal.measurement import tables as _data

    spec = _as_spec(spec)
    if not isinstance(plan, pd.DataFrame):
        raise InputError(f"expected a DataFrame of poses, got {type(plan).__name__}", source=source)
    raw = _data.read_raw(plan, source, "plan")
    return _validate_raw(raw, spec)


def _validate_raw(raw: Any, spec: MachineSpec) -> pd.DataFrame:
    from volcal.measurement import tables as _data

    problems = _data.Problems(raw.name)
    schema = [
        _data.Column(a.name, (f"{a.name}_{_unit(a)}",), True, "float", _unit(a)) for a in spec.axes
    ]
    pos = _data.resolve_columns(
        raw, schema, problems, axis_names=spec.axis_names, model_name=spec.name
    )
    out = {}
    for a in spec.axes:
        label = raw.header[pos[a.name]]
        v = _data.parse_float(raw.body[pos[a.name]], raw.rows, label, _unit(a), False, problems)
        lo, hi = a.travel
        tol = _data.TRAVEL_TOLERANCE * (hi - lo)
        _data.report_rows(
            problems,
            raw.rows,
            (v < lo - tol) | (v > hi + tol),
            label,
            lambda k, v=v, a=a, lo=lo, hi=hi: (
                f"{a.name} = {v[k]:g} {_unit(a)} is "
                f"outside the travel [{lo:g}, {hi:g}] {_unit(a)} of axis {a.name}"
            ),
        )
        out[a.name] = v
    problems.raise_if_any()
    return pd.DataFrame(out, columns=spec.axis_names)


def plan_from_csv(path: str | Path, spec: Any) -> pd.DataFrame:
    """Poses from a CSV file: a header row with one column per model axis (``X`` or
    ``X_mm``, ``B`` or ``B_deg``; linear axes in mm, rotary axes in degrees) and one row
    per pose.  Unknown columns, missing or non-numeric values and positions outside the
    travel raise :class:`InputError` naming the file, row and column.  Returns the plan
    (columns = axis names in model order)."""
    from volcal.measurement import tables as _data

    spec = _as_spec(spec)
    raw = _data.read_raw(Path(path), None, "plan")
    return _validate_raw(raw, spec)


_TOOL_COLUMNS = (("tool_x_mm", "tool_x"), ("tool_y_mm", "tool_y"), ("tool_z_mm", "tool_z"))


def is_measurement_plan(path: str | Path) -> bool:
    """Whether the CSV file's header names a ``station`` column (a measurement plan, one
    row per reading) rather than poses only."""
    try:
        header = pd.read_csv(Path(path), nrows=0).columns
    except (OSError, ValueError, pd.errors.ParserError):
        return False
    return "station" in [str(c).strip() for c in header]


def measurement_plan_from_csv(
    path: str | Path, spec: Any
) -> tuple[pd.DataFrame, np.ndarray, list[str]]:
    """The poses (axis columns, mm / deg, in measuring order), tool offsets (T, 3) mm and
    station ids (in measuring order) of a measurement plan file: one row per reading with
    ``station``, optionally ``point``, one column per axis (``X`` or ``X_mm``), the tool
    offset (``tool_x_mm, tool_y_mm, tool_z_mm``, or without ``_mm``; absent: (0, 0, 0))
    and optionally ``length_mm`` / ``length`` (ignored here).  The simulator measures every
    pose with every tool offset from every station, station after station, at each
    station tool after tool: the file must have that layout (``volcal plan`` writes it);
    :class:`InputError` names the file, row (header = row 1) and what differs."""
    spec = _as_spec(spec)
    src = str(path)
    try:
        df = pd.read_csv(Path(path), dtype=str, keep_default_na=False)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise InputError(f"cannot read the measurement plan: {exc}", source=src) from None
    df.columns = [str(c).strip() for c in df.columns]
    if "station" not in df.columns or not len(df):
        raise InputError("a measurement plan needs a 'station' column and rows", source=src)
    tool_cols = []
    for names in _TOOL_COLUMNS:
        have = [n for n in names if n in df.columns]
        if len(have) > 1:
            raise InputError(f"both {names[0]!r} and {names[1]!r} given", source=src)
        tool_cols.append(have[0] if have else None)
    if any(tool_cols) and not all(tool_cols):
        raise InputError(
            "give all three tool offset columns tool_x_mm, tool_y_mm, tool_z_mm or none",
            source=src,
        )
    axis_cols = [
        c
        for c in df.columns
        if c not in ("station", "point", "length_mm", "length", "sigma", "time", *tool_cols)
    ]
    poses = check_plan(df[axis_cols], spec, source=src)
    tools = np.zeros((len(df), 3))
    for j, c in enumerate(tool_cols):
        if c is None:
            continue
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise InputError(
                f"row {bad[0] + 2}: expected a finite tool offset in mm, got "
                f"{df[c].iloc[bad[0]]!r}",
                source=src,
                column=c,
            )
        tools[:, j] = v
    stations = [str(s).strip() for s in df["station"]]
    if any(not s for s in stations):
        i = stations.index("")
        raise InputError(f"row {i + 2}: no station", source=src, column="station")
    order = list(dict.fromkeys(stations))
    tool_list = np.unique(tools, axis=0, return_index=True)[1]
    T = tools[np.sort(tool_list)]
    first = np.array([s == order[0] for s in stations])
    q0 = poses.to_numpy(float)[first]
    n_t = len(T)
    n_p = len(q0) // n_t if n_t else 0
    Q = q0[:n_p]
    want_q = np.tile(Q, (n_t * len(order), 1))
    want_t = np.tile(np.repeat(T, n_p, axis=0), (len(order), 1))
    want_s = np.repeat(order, n_t * n_p)
    got_q, got_s = poses.to_numpy(float), np.array(stations)
    if n_p * n_t != len(q0) or len(want_s) != len(df):
        raise InputError(
            f"{len(df)} readings for {len(order)} stations x {n_t} tool offset(s): the "
            "simulator measures every pose with every tool offset from every station; "
            "every station needs the same readings",
            source=src,
        )
    diff = (
        (got_s != want_s)
        | ~np.all(np.isclose(tools, want_t, atol=1e-9), axis=1)
        | ~np.all(np.isclose(got_q, want_q, atol=1e-9), axis=1)
    )
    if diff.any():
        i = int(np.flatnonzero(diff)[0])
        raise InputError(
            f"row {i + 2}: expected station {want_s[i]}, tool offset "
            f"{', '.join(f'{v:g}' for v in want_t[i])} mm and the pose of row "
            f"{i % n_p + 2}: the simulator measures station after station, at each station "
            "tool offset after tool offset, the same poses in the same order",
            source=src,
        )
    return poses.iloc[:n_p].reset_index(drop=True), T, order


# --------------------------------------------------------------------------------------
# stations


def nominal_points(spec: Any, plan: pd.DataFrame, tools: np.ndarray | None = None) -> np.ndarray:
    """Nominal tool points (mm, workpiece frame) of every (tool, pose) of a plan,
    shape (K * N, 3), tool-major (all poses with the first tool, then the second ...)."""
    from volcal.measurement.tables import nominal_tool_points as _nominal_tool_points

    spec = _as_spec(spec)
    q = plan[spec.axis_names].to_numpy(dtype=float).copy()
    for j, a in enumerate(spec.axes):
        if a.is_rotary:
            q[:, j] = np.deg2rad(q[:, j])
    tools = np.zeros((1, 3)) if tools is None else np.atleast_2d(np.asarray(tools, float))
    return np.concatenate(
        [_nominal_tool_points(spec, q, np.broadcast_to(t, q.shape[:1] + (3,))) for t in tools]
    )


def default_stations(
    spec: Any,
    n: int = 6,
    seed: int = 0,
    *,
    tools: np.ndarray | None = None,
    plan: pd.DataFrame | None = None,
) -> pd.DataFrame:
    """A plausible layout of ``n`` tracker stations around the workspace.

    The nominal tool points of ``plan`` (default :func:`default_plan`: the default grid
    for a model without rotary axes) with ``tools`` (default zero offset) span a box.
    Stations sit on an ellipse around that box in the xy-plane (the ellipse through the
    corners of the box grown by ``150 mm + 10 %`` of its largest side), at angles
    ``360/n`` apart with a seeded jitter of up to +-15 % of the spacing, and alternate
    between two heights, at 25 % and 75 % of the box's z range (+-5 % jitter).
    They are therefore outside the point cloud (at least :data:`STATION_MIN_CLEARANCE_MM`
    from every point, checked) and never coplanar (checked).  Dead lengths are drawn
    uniformly in [0.05, 0.5] mm.

    n: number of stations (>= 4: fewer cannot be non-coplanar).
    seed: seed of the numpy Generator for the jitter and the dead lengths.
    plan: the poses the stations must keep clear of (mm / deg; default the default plan).

    Returns a stations table in :func:`volcal.measurement.tables.load_stations` form (``station``
    ``S1``..``Sn``, ``x_mm, y_mm, z_mm, dead_length_mm`` in mm, ``dead_length_given``
    True, ``fixed`` False).
    """
    spec = _as_spec(spec)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 4:
        raise InputError(
            f"expected at least 4 stations (3 or fewer are always coplanar), got {n!r}"
        )
    rng = np.random.default_rng(seed)
    pts = nominal_points(spec, default_plan(spec) if plan is None else plan, tools)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, half = (lo + hi) / 2, (hi - lo) / 2
    grow = 150.0 + 0.1 * float((hi - lo).max())
    a_ax, b_ax = half[0] * np.sqrt(2) + grow, half[1] * np.sqrt(2) + grow
    dz = hi[2] - lo[2]
    spacing = 2 * np.pi / n
    for _ in range(100):
        phi = np.pi / n + spacing * np.arange(n) + rng.uniform(-0.15, 0.15, n) * spacing
        level = np.where(np.arange(n) % 2 == 0, 0.25, 0.75) + rng.uniform(-0.05, 0.05, n)
        xyz = np.column_stack(
            [
                c[0] + a_ax * np.cos(phi),
                c[1] + b_ax * np.sin(phi),
                lo[2] + level * dz if dz > 0 else c[2] + (level - 0.5) * 2 * grow,
            ]
        )
        sv = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
        dmin = np.sqrt(((pts[:, None, :] - xyz[None, :, :]) ** 2).sum(-1)).min()
        if sv[2] > 1e-3 * sv[0] and dmin >= STATION_MIN_CLEARANCE_MM:
            break
    else:  # pragma: no cover - the construction above always succeeds
        raise RuntimeError("could not place non-coplanar stations clear of the workspace")
    dead = rng.uniform(0.05, 0.5, n)
    return pd.DataFrame(
        {
            "station": np.array([f"S{k + 1}" for k in range(n)], dtype=object),
            "x_mm": xyz[:, 0],
            "y_mm": xyz[:, 1],
            "z_mm": xyz[:, 2],
            "dead_length_mm": dead,
            "dead_length_given": np.ones(n, dtype=bool),
            "fixed": np.zeros(n, dtype=bool),
        }
    )
