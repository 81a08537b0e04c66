"""Simulated multilateration data: true error motions -> length readings.

Inputs: a machine model, its error parameterisation (:class:`~volcal.model.errors.ErrorModel`)
with true parameter values, the true stations, a measurement plan (commanded poses, see
:mod:`volcal.measurement.plans`), the tool (reflector) offsets, an uncertainty budget and a seed.
Output: a :class:`Simulation` holding the measurement table in DESIGN.md's format, the
true parameters and the true volumetric errors.

Reading model (sequential multilateration, paper 002 eq. 5-6)::

    length = || P_actual(q_cmd + dq, t) - Q_s || - d_s + n_length + n_drift

* ``P_actual`` is the actual tool point of the **exact** model
  (``Machine.evaluate(..., exact=True)``; never the first-order one) with the error
  motions evaluated at the actual axis positions ``q_cmd + dq``;
* ``dq`` is the positioning repeatability of the axes (budget sources ``axis:<NAME>``),
  drawn anew for every reading: sequential multilateration visits every (pose, tool)
  once per station, and every visit repositions the axes;
* ``Q_s, d_s`` are the position (mm) and dead length (mm) of the reading's station;
* ``n_length`` is the sum of the budget's length sources at the true distance
  ``||P_actual - Q_s||`` (:meth:`~volcal.measurement.budget.Budget.sample_length_errors`);
* ``n_drift`` (only with ``drift=True``) is one realisation of the budget's drift per
  station (:meth:`~volcal.measurement.budget.Budget.sample_drift` over that station's
  time stamps: the instrument is re-referenced at each station).

Randomness: ``numpy.random.SeedSequence(seed)`` spawns three child streams, used for the
axis repeatability, the length noise and the drift respectively, each drawn in reading
order.  Switching one source off therefore leaves the draws of the others unchanged, and
a given seed always gives the same table.

Reading order and time stamps: station after station (in stations-table order); at each
station tool after tool; for each tool every pose of the plan in plan order.  One reading
every :data:`READING_INTERVAL_S` s, :data:`TOOL_CHANGE_S` s for a tool change and
:data:`STATION_SETUP_S` s to move and set up the tracker at the next station; the first
reading is at t = 0 s.  Point ids are unique per (pose, tool): ``p0001`` ... numbered
tool-major (all poses with the first tool, then with the second ...).

Units: lengths mm, angles rad inside the code; files carry rotary axes in degrees and
the true parameters in um / urad (their ``unit`` column says which).
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal import __version__
from volcal.base.exceptions import InputError
from volcal.base.units import REPORT
from volcal.measurement.budget import ANGLE_UNITS, LENGTH_UNITS, Budget, load_budget
from volcal.measurement.instruments import SequentialMultilateration
from volcal.model.errors import ErrorModel, legendre
from volcal.model.machine import Machine

log = logging.getLogger(__name__)

__all__ = [
    "Simulation",
    "Example",
    "draw_true_parameters",
    "simulate",
    "save_simulation",
    "load_true_parameters",
    "parameters_table",
    "example",
    "examples",
    "parse_tools",
    "NOISE_SOURCES",
    "READING_INTERVAL_S",
    "TOOL_CHANGE_S",
    "STATION_SETUP_S",
    "MAGNITUDES",
    "SIMULATION_FILES",
]

#: Noise sources that ``simulate(noise=...)`` can switch on independently.
NOISE_SOURCES = ("length", "axes")
#: Time between two readings (s).
READING_INTERVAL_S = 5.0
#: Extra time for a tool (reflector) change at a station (s).
TOOL_CHANGE_S = 120.0
#: Extra time to move and set up the tracker at the next station (s).
STATION_SETUP_S = 900.0
#: Readings closer than this to their station (mm) draw a warning.
MIN_STATION_DISTANCE_MM = 50.0
#: Files written by :func:`save_simulation`.
SIMULATION_FILES = (
    "measurements.csv",
    "stations.csv",
    "true_parameters.csv",
    "true_volumetric.csv",
    "simulation.json",
)
#: Files :func:`save_simulation` writes only when asked (other instruments' readings).
OPTIONAL_SIMULATION_FILES = ("interferometer.csv", "ballbar.csv")

#: Headline sizes (low, high) of drawn error motions, internal units (mm, rad); see
#: :func:`draw_true_parameters`.
MAGNITUDES: dict[str, tuple[float, float]] = {
    "linear_positioning": (10e-3, 30e-3),  # EXX: +-10..30 um over travel
    "linear_straightness": (2e-3, 6e-3),  # EYX, EZX
    "linear_angular": (10e-6, 30e-6),  # EAX, EBX, ECX
    "rotary_translation": (2e-3, 8e-3),  # EXC, EYC, EZC
    "rotary_angular": (10e-6, 30e-6),  # EAC, EBC, ECC
    "squareness": (20e-6, 50e-6),  # EC0Y, EB0Z, EA0Z
    "rotary_location_translation": (10e-3, 50e-3),  # EX0C, EY0C
    "rotary_location_rotation": (20e-6, 50e-6),  # EA0C, EB0C
    "tool_position": (5e-3, 20e-3),  # EX0T, EY0T, EZ0T
    "tool_orientation": (10e-6, 40e-6),  # EA0T, EB0T, EC0T
}
#: Ratio of the scale of successive Legendre coefficients of a drawn error motion.
COEFFICIENT_DECAY = 0.4
#: Datum projection: the k-th Legendre coefficient of an error motion changes with weight
#: ``DATUM_ORDER_FACTOR ** -k`` (see :func:`draw_true_parameters`).
DATUM_ORDER_FACTOR = 30.0
#: Degree of the random smooth function drawn for a table-form error motion.
TABLE_FUNCTION_DEGREE = 4

_TO_FILE = REPORT


# --------------------------------------------------------------------------------------
# helpers


def _machine(machine: Machine | str | Path) -> Machine:
    return machine if isinstance(machine, Machine) else Machine.from_model(machine)


def _error_model(machine: Machine, error_model: ErrorModel | None) -> ErrorModel:
    if error_model is None:
        return ErrorModel(machine.spec)
    if error_model.spec.fingerprint() != machine.spec.fingerprint():
        raise InputError(
            f"the error model is for model '{error_model.spec.name}', the "
            f"machine is '{machine.spec.name}'"
        )
    return error_model


def _rng(rng: np.random.Generator | int) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise TypeError(f"expected a numpy Generator or an integer seed, got {type(rng).__name__}")


def _error_values(error_model: ErrorModel, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """e (N, n_errors) at internal poses q (N, n_axes); CasADi map (no dense basis)."""
    if error_model.n_errors == 0:
        return np.zeros((q.shape[0], 0))
    f = error_model.values_function().map(q.shape[0])
    return np.asarray(f(q.T, np.asarray(theta, float))).T.reshape(q.shape[0], -1)


def _plan_internal(machine: Machine, plan: pd.DataFrame) -> np.ndarray:
    return machine.axis_to_internal(plan[machine.axis_names].to_numpy(dtype=float))


def max_volumetric_error_um(
    machine: Machine,
    error_model: ErrorModel,
    theta: np.ndarray,
    plan: pd.DataFrame | None = None,
    tool: np.ndarray | None = None,
) -> float:
    """Largest ``||actual - nominal||`` (um, exact model) over the poses of ``plan``
    (default :func:`volcal.measurement.plans.summary_grid` of the model: 5 positions per linear axis
    and the rotary axes over their whole travel on a coarse grid) with tool offset
    ``tool`` (mm, default zero)."""
    from volcal.measurement.plans import summary_grid

    plan = summary_grid(machine.spec) if plan is None else plan
    q = _plan_internal(machine, plan)
    t = np.zeros(3) if tool is None else np.asarray(tool, float)
    _, dp, _ = machine.evaluate(q, t, _error_values(error_model, q, theta), exact=True)
    return float(np.linalg.norm(dp, axis=1).max() * 1e3)


# --------------------------------------------------------------------------------------
# true parameters


def _category(error_model: ErrorModel, k: int) -> str:
    s = error_model.errors[k]
    if s.kind == "tool":
        return "tool_position" if s.quantity == "translation" else "tool_orientation"
    axis = error_model.spec.axis(s.axis)
    if s.kind == "location":
        if not axis.is_rotary:
            return "squareness"
        return (
            "rotary_location_translation"
            if s.quantity == "translation"
            else "rotary_location_rotation"
        )
    if axis.is_rotary:
        return "rotary_translation" if s.quantity == "translation" else "rotary_angular"
    if s.quantity == "rotation":
        return "linear_angular"
    return "linear_positioning" if s.component == axis.dir_index else "linear_straightness"


def draw_true_parameters(
    machine: Machine,
    error_model: ErrorModel | None,
    rng: np.random.Generator | int,
    max_volumetric_um: float | None = 60.0,
    *,
    grid: pd.DataFrame | None = None,
) -> np.ndarray:
    """A realistic random set of true error parameters (internal units: mm, rad).

    Each error quantity gets a headline size drawn uniformly from its range in
    :data:`MAGNITUDES` (positioning errors 10-30 um, straightness 2-6 um, angular errors
    10-30 urad, squareness 20-50 urad, rotary-axis location offsets 10-50 um and tilts
    20-50 urad, rotary-axis component motions 2-8 um / 10-30 urad) with a random sign.
    A component error motion is a Legendre series in the normalised axis position
    s in [-1, 1] up to the form's degree (degree 4 for a table form, then fitted to the
    table knots): ``sign * size`` times the headline polynomial (P_1; P_2, the bow, for a
    straightness, whose P_0 and P_1 the datum removes), ``size * 0.4^(j - lead) N(0,1)``
    for the higher orders j and ``size * N(0,1)`` for the lower ones (mostly removed by
    the datum); a location error is the constant ``sign * size``.

    The parameters are then projected onto the datum constraints of ``error_model`` so
    that ``C theta = 0`` holds to rounding (an oblique projection that adjusts the low
    Legendre orders first, so that the drawn shapes keep their decay; then
    ``theta -= pinv(C) C theta``; see :func:`_project_datum`), and scaled so
    that the largest volumetric error ``||actual - nominal||`` of the exact model over
    ``grid`` (default :func:`volcal.measurement.plans.summary_grid` of the model, which spans the
    rotary axes' travel too) with zero tool offset equals ``max_volumetric_um`` (um;
    ``None``: no scaling).  The exact model is not linear in the parameters, so the scale
    is refined until the maximum matches to a relative 1e-10.

    machine: the Machine; error_model: its parameterisation (None: the default
    :class:`ErrorModel`); rng: numpy Generator or integer seed.
    Returns theta, shape (error_model.n_params,), mm / rad.
    """
    from volcal.measurement.plans import summary_grid

    machine = _machine(machine)
    em = _error_model(machine, error_model)
    g = _rng(rng)
    funcs = {}
    for k, s in enumerate(em.errors):
        lo_hi = MAGNITUDES[_category(em, k)]
        size = g.uniform(*lo_hi) * (1.0 if g.random() < 0.5 else -1.0)
        form = em.forms[k]
        if form.kind == "constant":
            if _category(em, k) == "tool_position":
                # left at zero: without rotary axes on the tool branch the tool's zero
                # position is a translation of the whole field, which nothing sees
                size = 0.0
            funcs[s.name] = lambda x, v=size: np.full(np.shape(x), v)
            continue
        if form.kind == "fourier":
            # periodic: harmonic k with amplitude |size| decaying by COEFFICIENT_DECAY,
            # the first harmonic's cosine carrying the drawn size
            amp = np.array(
                [
                    abs(size) * COEFFICIENT_DECAY ** max(j - 1, 0) * g.normal()
                    for j in range(2 * form.degree + 1)
                ]
            )
            if form.degree:
                amp[1] = size

            def f(x, amp=amp, n=form.degree):
                x = np.asarray(x, float)
                return amp[0] + sum(
                    amp[2 * j - 1] * np.cos(j * x) + amp[2 * j] * np.sin(j * x)
                    for j in range(1, n + 1)
                )

            funcs[s.name] = f
            continue
        deg = form.degree if form.kind == "poly" else TABLE_FUNCTION_DEGREE
        # the headline order: the slope P_1, or for a straightness (zero at both ends of
        # travel, which removes P_0 and P_1) the bow P_2
        lead = min(deg, 2 if _category(em, k) == "linear_straightness" else 1)
        coef = np.zeros(deg + 1)
        for j in range(deg + 1):
            coef[j] = (
                size
                if j == lead
                else abs(size) * COEFFICIENT_DECAY ** max(j - lead, 0) * g.normal()
            )
        lo, hi, _ = em._axis_range(s)

        def poly(x, coef=coef, lo=lo, hi=hi, deg=deg):
            sx = 2 * (np.asarray(x, float) - lo) / (hi - lo) - 1
            return sum(c * p for c, p in zip(coef, legendre(sx, deg)))

        funcs[s.name] = poly
    theta = _project_datum(em, em.fit_functions(funcs))
    if max_volumetric_um is None:
        return theta
    target = float(max_volumetric_um)
    if not target > 0:
        raise InputError(f"expected max_volumetric_um > 0, got {max_volumetric_um!r}")
    grid = summary_grid(machine.spec) if grid is None else grid
    for _ in range(20):
        current = max_volumetric_error_um(machine, em, theta, grid)
        if current == 0.0:
            raise InputError(
                f"model '{machine.spec.name}' has no error that moves the tool "
                "point: cannot scale to a volumetric error"
            )
        if abs(current / target - 1.0) < 1e-10:
            break
        theta = theta * (target / current)
    return theta


def _project_datum(em: ErrorModel, theta: np.ndarray) -> np.ndarray:
    """Project theta onto ``C theta = 0`` (the datum constraints of ``em``).

    An oblique projection that changes low Legendre orders first (the k-th coefficient is
    weighted ``DATUM_ORDER_FACTOR ** -k``): zero-at-reference constraints then shift the
    constant term and zero-at-both-ends constraints remove the line through the ends,
    as a measured error curve is referenced, instead of spreading the correction over all
    coefficients as the plain minimum-norm projection would.  A final minimum-norm step
    ``theta -= pinv(C) C theta`` removes what rounding leaves.
    """
    C, _ = em.constraints()
    if not C.shape[0]:
        return theta
    # per parameter: its Legendre degree or harmonic number (0 for the other kinds)
    scale = DATUM_ORDER_FACTOR ** -np.asarray(em.param_order, float)
    W = scale**2
    A = (C * W) @ C.T
    theta = theta - W * (C.T @ np.linalg.lstsq(A, C @ theta, rcond=None)[0])
    return theta - np.linalg.pinv(C) @ (C @ theta)


def parameters_table(error_model: ErrorModel, theta: np.ndarray) -> pd.DataFrame:
    """Parameters as a table ``name, value, unit`` with translations in um and rotations
    in urad (the file form of true_parameters.csv)."""
    theta = np.asarray(theta, float)
    units = error_model.param_units
    return pd.DataFrame(
        {
            "name": list(error_model.param_names),
            "value": [v * _TO_FILE[u][0] for v, u in zip(theta, units)],
            "unit": [_TO_FILE[u][1] for u in units],
        }
    )


def load_true_parameters(path: str | Path, error_model: ErrorModel) -> np.ndarray:
    """Read a parameter file (``name, value, unit``; e.g. true_parameters.csv) into theta
    (internal units mm / rad) for ``error_model``.

    Units: ``mm, um, nm`` for translational parameters, ``rad, mrad, urad, deg, arcsec``
    for rotational ones (a unit of the wrong kind is an error).  Parameters not listed are
    zero.  Unknown or repeated names, non-numeric values and unknown units raise
    :class:`InputError` naming the file, row and column.
    """
    from volcal.measurement import tables as _data

    raw = _data.read_raw(Path(path), None, "parameter table")
    problems = _data.Problems(raw.name)
    schema = [
        _data.Column("name", (), True, "id"),
        _data.Column("value", (), True, "float"),
        _data.Column("unit", (), True, "id"),
    ]
    pos = _data.resolve_columns(raw, schema, problems)
    names = _data.parse_ids(raw.body[pos["name"]], raw.rows, "name", problems)
    values = _data.parse_float(
        raw.body[pos["value"]], raw.rows, "value", "in the row's unit", False, problems
    )
    units = _data.parse_ids(raw.body[pos["unit"]], raw.rows, "unit", problems)
    problems.raise_if_any()
    index = {n: i for i, n in enumerate(error_model.param_names)}
    kinds = error_model.param_units
    theta = np.zeros(error_model.n_params)
    seen: dict[str, int] = {}
    for k, (n, v, u) in enumerate(zip(names, values, units)):
        row = int(raw.rows[k])
        if n not in index:
            import difflib

            m = difflib.get_close_matches(n, error_model.param_names, n=1)
            problems.add(
                row,
                "name",
                f"unknown parameter '{n}' for model "
                f"'{error_model.spec.name}'" + (f" (did you mean '{m[0]}'?)" if m else ""),
            )
            continue
        if n in seen:
            problems.add(row, "name", f"parameter '{n}' is listed twice (rows {seen[n]} and {row})")
            continue
        seen[n] = row
        table = LENGTH_UNITS if kinds[index[n]] == "mm" else ANGLE_UNITS
        if u not in table:
            what = "translational" if kinds[index[n]] == "mm" else "rotational"
            problems.add(
                row,
                "unit",
                f"parameter '{n}' is {what}; expected a unit in {list(table)}, got '{u}'",
            )
            continue
        theta[index[n]] = v * table[u]
    problems.raise_if_any()
    return theta


# --------------------------------------------------------------------------------------
# simulation


@dataclass
class Simulation:
    """A simulated measurement with its ground truth.

    measurements: the measurement table (DESIGN.md format): ``station, point, <axes>``
        (commanded, mm / deg), ``tool_x, tool_y, tool_z`` (mm), ``length`` (mm), ``time``
        (s), ``sigma`` (mm: the budget's standard uncertainty of the reading, length
        sources combined with the axis repeatabilities projected on the beam direction).
    theta: true parameter vector (mm / rad, ``error_model.param_names`` order).
    parameters: ``name, value, unit`` with values in um / urad.
    volumetric: per (pose, tool): ``point, <axes>, tool_x, tool_y, tool_z, dx_um, dy_um,
        dz_um``, the true volumetric error (actual - nominal, exact model, commanded pose).
    stations: the true stations table (:func:`volcal.measurement.tables.load_stations` form, mm).
    seed: the seed; model: the model name; budget: the budget name;
    noise: the noise sources that were on; drift: whether drift was on.
    """

    measurements: pd.DataFrame
    theta: np.ndarray
    parameters: pd.DataFrame
    volumetric: pd.DataFrame
    stations: pd.DataFrame
    seed: int
    model: str = ""
    budget: str = ""
    noise: tuple[str, ...] = NOISE_SOURCES
    drift: bool = False

    @property
    def max_volumetric_um(self) -> float:
        """Largest true volumetric error over the plan and tools (um)."""
        v = self.volumetric[["dx_um", "dy_um", "dz_um"]].to_numpy()
        return float(np.linalg.norm(v, axis=1).max())


def _noise_sources(noise: bool | str | Iterable[str] | None) -> tuple[str, ...]:
    if noise is True:
        return NOISE_SOURCES
    if noise is False or noise is None:
        return ()
    items = (noise,) if isinstance(noise, str) else tuple(noise)
    bad = [s for s in items if s not in NOISE_SOURCES]
    if bad:
        raise InputError(
            f"unknown noise source(s) {bad}; expected a subset of "
            f"{list(NOISE_SOURCES)} (or True / False)"
        )
    return tuple(s for s in NOISE_SOURCES if s in items)


def _check_tools(tools: Any) -> np.ndarray:
    t = np.asarray(tools, dtype=float)
    if t.ndim == 1 and t.shape == (3,):
        t = t[None, :]
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] == 0:
        raise InputError(f"expected tool offsets of shape (K, 3) in mm, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError("tool offsets must be finite numbers (mm)")
    if len(np.unique(t, axis=0)) != len(t):
        raise InputError("the same tool offset is listed twice")
    return t


def _position_jacobian(machine: Machine, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """d(nominal tool point)/dq, shape (N, 3, n_axes), mm per mm or mm per rad."""
    n = q.shape[0]
    f = machine["nominal"].factory("nominal_jac_q", ["q", "t"], ["jac:p:q"]).map(n)
    J = np.asarray(f(q.T, t.T))
    return J.reshape(3, n, machine.n_axes).transpose(1, 0, 2)


def simulate(
    machine: Machine | str,
    error_model: ErrorModel | None,
    theta_true: np.ndarray,
    stations: pd.DataFrame | str | Path,
    plan: pd.DataFrame,
    tools: np.ndarray,
    budget: Budget | str | Path,
    seed: int,
    *,
    noise: bool | str | Iterable[str] = True,
    drift: bool = False,
) -> Simulation:
    """Simulate a sequential multilateration measurement (see the module docstring).

    machine: Machine (or model name/file); error_model: its parameterisation (None:
        default ErrorModel); theta_true: true parameters (mm / rad).
    stations: stations table (DataFrame or CSV, :func:`volcal.measurement.tables.load_stations`
        format:
        ``station, x_mm, y_mm, z_mm, dead_length_mm``), the true positions (mm) and dead
        lengths (mm; 0 where not given).
    plan: commanded poses (one column per axis, mm / deg; see :mod:`volcal.measurement.plans`).
    tools: (K, 3) tool (reflector) offsets in the tool frame, mm; every station measures
        every (pose, tool).
    budget: Budget, bundled budget name or budget file.
    seed: integer seed (see the module docstring for the streams).
    noise: True (all of :data:`NOISE_SOURCES`), False (none), or a subset such as
        ``("length",)`` or ``("axes",)``.
    drift: add the budget's drift (one realisation per station).

    The ``sigma`` column is the budget's standard uncertainty whatever sources are
    switched on: ``sqrt(u_L(L)^2 + sum_j (u_j g_j)^2)`` with ``u_L`` the length sources
    at the nominal distance, ``u_j`` the repeatability of axis j (mm or rad) and ``g_j``
    the derivative of the nominal distance with respect to axis j (the axis' motion
    projected on the beam).  Drift is not part of ``sigma``.

    Raises :class:`InputError` for inconsistent inputs and for a reading that would not
    be positive (a point within the dead length of its station).
    """
    from volcal.measurement.plans import check_plan
    from volcal.measurement.tables import DataWarning, load_stations

    machine = _machine(machine)
    em = _error_model(machine, error_model)
    spec = machine.spec
    theta = np.asarray(theta_true, dtype=float)
    if theta.shape != (em.n_params,):
        raise InputError(
            f"expected {em.n_params} true parameters for model '{spec.name}', "
            f"got shape {theta.shape}"
        )
    if not np.all(np.isfinite(theta)):
        raise InputError("true parameters must be finite")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"expected a non-negative integer seed, got {seed!r}")
    seed = int(seed)
    st = load_stations(stations, name=None if isinstance(stations, (str, Path)) else "<stations>")
    plan = check_plan(plan, spec)
    tools = _check_tools(tools)
    budget = load_budget(budget)
    budget.check_axes(spec)
    budget.warn_uncovered(spec)
    sources = _noise_sources(noise)

    S, N, K = len(st), len(plan), len(tools)
    M = S * K * N
    names = spec.axis_names
    q_file = plan[names].to_numpy(dtype=float)
    q_cmd = machine.axis_to_internal(q_file)
    # reading r = ((s * K) + k) * N + i
    idx_s = np.repeat(np.arange(S), K * N)
    idx_k = np.tile(np.repeat(np.arange(K), N), S)
    idx_i = np.tile(np.arange(N), S * K)
    idx_pt = idx_k * N + idx_i  # (pose, tool) index, tool-major
    width = max(4, len(str(N * K)))
    point_ids = np.array([f"p{j + 1:0{width}d}" for j in range(N * K)], dtype=object)

    # time stamps
    time = np.empty(M)
    t0 = 0.0
    for s in range(S):
        if s:
            t0 += STATION_SETUP_S - READING_INTERVAL_S
        for k in range(K):
            if k:
                t0 += TOOL_CHANGE_S - READING_INTERVAL_S
            r0 = (s * K + k) * N
            time[r0 : r0 + N] = t0 + READING_INTERVAL_S * np.arange(N)
            t0 += READING_INTERVAL_S * N

    g_axes, g_len, g_drift = (
        np.random.default_rng(c) for c in np.random.SeedSequence(seed).spawn(3)
    )

    # actual tool points: exact model at the actual axis positions
    dq = (
        budget.sample_axis_errors(names, M, g_axes)
        if "axes" in sources
        else np.zeros((M, len(names)))
    )
    q_act = q_cmd[idx_i] + dq
    e_act = _error_values(em, q_act, theta)
    P, _, _ = machine.evaluate(q_act, tools[idx_k], e_act, exact=True)
    # the readings from the instrument's one reading function (the model identify fits)
    tracker = SequentialMultilateration()
    Q = st[["x_mm", "y_mm", "z_mm"]].to_numpy(dtype=float)
    dead = st["dead_length_mm"].to_numpy(dtype=float)
    st_params = np.column_stack([Q, dead])
    length, _ = tracker.evaluate(P, st_params[idx_s])
    dist = length + dead[idx_s]
    if "length" in sources:
        length = length + budget.sample_length_errors(dist, g_len)
    if drift:
        for s in range(S):
            rows = slice(s * K * N, (s + 1) * K * N)
            length[rows] += budget.sample_drift(time[rows], g_drift)

    if np.any(length <= 0):
        r = int(np.flatnonzero(length <= 0)[0])
        raise InputError(
            f"station '{st['station'].iloc[idx_s[r]]}' is {dist[r]:.3g} mm from "
            f"point {point_ids[idx_pt[r]]} (dead length "
            f"{dead[idx_s[r]]:g} mm): the reading would not be positive; move the "
            "station or drop the pose"
        )
    if dist.min() < MIN_STATION_DISTANCE_MM:
        r = int(np.argmin(dist))
        warnings.warn(
            f"station '{st['station'].iloc[idx_s[r]]}' is only {dist[r]:.1f} mm from "
            f"point {point_ids[idx_pt[r]]}",
            DataWarning,
            stacklevel=2,
        )

    # standard uncertainty of each reading (nominal geometry of the commanded pose)
    q_pt = np.tile(q_cmd, (K, 1))
    t_pt = np.repeat(tools, N, axis=0)
    P0 = np.asarray(machine["nominal"].map(N * K)(q_pt.T, t_pt.T)).T
    Jq = _position_jacobian(machine, q_pt, t_pt)
    L0, u = tracker.evaluate(P0[idx_pt], st_params[idx_s])  # u: d reading / d point
    L0 = L0 + dead[idx_s]
    g = np.einsum("ri,rij->rj", u, Jq[idx_pt])
    u_axes = np.array([budget.axis_sigma(a) for a in names])
    sigma = np.sqrt(budget.length_sigma(L0) ** 2 + ((g * u_axes) ** 2).sum(axis=1))

    meas = pd.DataFrame(
        {"station": st["station"].to_numpy(dtype=object)[idx_s], "point": point_ids[idx_pt]}
    )
    for j, a in enumerate(names):
        meas[a] = q_file[idx_i, j]
    for j, c in enumerate(("tool_x", "tool_y", "tool_z")):
        meas[c] = tools[idx_k, j]
    meas["length"] = length
    meas["time"] = time
    meas["sigma"] = sigma

    # true volumetric errors at the commanded poses
    e_cmd = _error_values(em, q_pt, theta)
    _, dp, _ = machine.evaluate(q_pt, t_pt, e_cmd, exact=True)
    vol = pd.DataFrame({"point": point_ids})
    for j, a in enumerate(names):
        vol[a] = np.tile(q_file[:, j], K)
    for j, c in enumerate(("tool_x", "tool_y", "tool_z")):
        vol[c] = t_pt[:, j]
    for j, c in enumerate(("dx_um", "dy_um", "dz_um")):
        vol[c] = dp[:, j] * 1e3

    return Simulation(
        measurements=meas,
        theta=theta.copy(),
        parameters=parameters_table(em, theta),
        volumetric=vol,
        stations=st,
        seed=seed,
        model=spec.name,
        budget=budget.name,
        noise=sources,
        drift=bool(drift),
    )


# --------------------------------------------------------------------------------------
# files


def save_simulation(
    sim: Simulation,
    out_dir: str | Path,
    *,
    force: bool | None = None,
    tables: dict[str, pd.DataFrame] | None = None,
) -> Path:
    """Write a simulation to ``out_dir``: ``measurements.csv`` (the measurement table),
    ``stations.csv`` (true stations: ``station, x_mm, y_mm, z_mm, dead_length_mm``),
    ``true_parameters.csv`` (``name, value, unit`` in um / urad), ``true_volumetric.csv``
    and ``simulation.json`` (seed, model, budget, noise settings, volcal version); and
    ``tables`` ({file name in OPTIONAL_SIMULATION_FILES: table}, other instruments' readings of the
    same machine, :mod:`volcal.measurement.simulate_instruments`).

    Everything is written into a temporary folder next to ``out_dir`` and renamed into
    place, so ``out_dir`` is never half-written.  An existing ``out_dir`` is replaced only
    when it is empty or holds nothing but these files (a previous simulation); otherwise
    :class:`InputError`.  Returns the output folder.
    """
    from volcal.base.folders import write_folder

    def writer(tmp: Path) -> None:
        sim.measurements.to_csv(tmp / "measurements.csv", index=False)
        sim.stations[["station", "x_mm", "y_mm", "z_mm", "dead_length_mm"]].to_csv(
            tmp / "stations.csv", index=False
        )
        sim.parameters.to_csv(tmp / "true_parameters.csv", index=False)
        sim.volumetric.to_csv(tmp / "true_volumetric.csv", index=False)
        for name, table in (tables or {}).items():
            table.to_csv(tmp / name, index=False)
        meta = {
            "volcal_version": __version__,
            "model": sim.model,
            "budget": sim.budget,
            "seed": sim.seed,
            "noise": list(sim.noise),
            "drift": sim.drift,
            "n_readings": int(len(sim.measurements)),
            "n_stations": int(len(sim.stations)),
            "max_volumetric_um": sim.max_volumetric_um,
            "reading_interval_s": READING_INTERVAL_S,
            "tool_change_s": TOOL_CHANGE_S,
            "station_setup_s": STATION_SETUP_S,
        }
        (tmp / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")

    return write_folder(
        out_dir,
        SIMULATION_FILES + OPTIONAL_SIMULATION_FILES,
        "a simulation",
        writer,
        force=force,
    )


# --------------------------------------------------------------------------------------
# tools from text


def parse_tools(text: str) -> np.ndarray:
    """Tool offsets from text ``"x,y,z;x,y,z;..."`` (mm) -> array (K, 3).  Raises
    :class:`InputError` naming the offending entry."""
    if not isinstance(text, str) or not text.strip():
        raise InputError(
            'expected tool offsets as "x,y,z;x,y,z" in mm, got an empty string', source="--tools"
        )
    out = []
    for k, item in enumerate(text.split(";")):
        if not item.strip():
            raise InputError(
                f'tool offset #{k + 1} is empty; expected "x,y,z" in mm '
                f"(offsets separated by ';'), got {text!r}",
                source="--tools",
            )
        parts = item.split(",")
        if len(parts) != 3:
            raise InputError(
                f"tool offset #{k + 1} {item.strip()!r} has {len(parts)} "
                f'value(s); expected three numbers "x,y,z" in mm',
                source="--tools",
            )
        try:
            v = [float(p) for p in parts]
        except ValueError:
            raise InputError(
                f"tool offset #{k + 1} {item.strip()!r} is not three numbers; "
                'expected "x,y,z" in mm',
                source="--tools",
            ) from None
        if not all(math.isfinite(x) for x in v):
            raise InputError(
                f"tool offset #{k + 1} {item.strip()!r} is not finite", source="--tools"
            )
        out.append(v)
    return _check_tools(np.array(out))


# --------------------------------------------------------------------------------------
# the bundled example


@dataclass(frozen=True)
class _ExampleDef:
    model: str
    parameters_file: str
    stations_file: str
    grid: dict[str, int]
    tools: tuple[tuple[float, float, float], ...]
    budget: str
    seed: int
    clearance_mm: float
    description: str


_EXAMPLES: dict[str, _ExampleDef] = {
    "mcv754": _ExampleDef(
        model="mcv754_wxyzt",
        parameters_file="mcv754_true_parameters.csv",
        stations_file="mcv754_stations.csv",
        grid={"X": 6, "Y": 5, "Z": 5},
        # the reflector below the spindle nose (z up), and two lateral offsets so that the
        # angular error motions of Z (the last axis) are identifiable
        tools=((0.0, 0.0, 0.0), (0.0, 0.0, -100.0), (80.0, 0.0, -100.0), (0.0, 80.0, -100.0)),
        budget="paper002",
        seed=754,
        clearance_mm=50.0,
        description="KOVOSVIT MCV 754 (paper 000): stations of its Table 5, a drawn error "
        "set scaled to 64 um maximum volumetric error, paper 002's budget",
    ),
}


@dataclass(frozen=True, eq=False)
class Example:
    """Everything needed to simulate a bundled example.

    name: example name; model: model name; machine, error_model: the model and its
    parameterisation (Legendre degree 3, datum ``iso230``); theta_true: the shipped true
    parameters (mm / rad); stations: true stations (load_stations form); plan: commanded
    poses (mm / deg); tools: (K, 3) tool offsets (mm); budget: the Budget; seed: the
    default simulation seed; description: one line.
    """

    name: str
    model: str
    machine: Machine = field(repr=False)
    error_model: ErrorModel = field(repr=False)
    theta_true: np.ndarray = field(repr=False)
    stations: pd.DataFrame = field(repr=False)
    plan: pd.DataFrame = field(repr=False)
    tools: np.ndarray = field(repr=False)
    budget: Budget = field(repr=False)
    seed: int = 0
    description: str = ""

    def simulate(
        self, seed: int | None = None, *, noise: bool | Iterable[str] = True, drift: bool = False
    ) -> Simulation:
        """Simulate the example (``seed`` None: the example's default seed)."""
        return simulate(
            self.machine,
            self.error_model,
            self.theta_true,
            self.stations,
            self.plan,
            self.tools,
            self.budget,
            self.seed if seed is None else seed,
            noise=noise,
            drift=drift,
        )


def examples() -> list[str]:
    """Names of the bundled examples."""
    return sorted(_EXAMPLES)


def _data_file(name: str) -> Path:
    return Path(str(resources.files("volcal").joinpath("data", name)))


def _clear_plan(
    machine: Machine,
    plan: pd.DataFrame,
    tools: np.ndarray,
    stations: pd.DataFrame,
    clearance: float,
) -> pd.DataFrame:
    """The poses whose nominal tool points (every tool) keep ``clearance`` mm from every
    station."""
    from volcal.measurement.plans import nominal_points

    pts = nominal_points(machine.spec, plan, tools).reshape(len(tools), len(plan), 3)
    Q = stations[["x_mm", "y_mm", "z_mm"]].to_numpy(dtype=float)
    d = np.linalg.norm(pts[:, :, None, :] - Q[None, None, :, :], axis=-1)
    keep = (d >= clearance).all(axis=(0, 2))
    return plan.loc[keep].reset_index(drop=True)


def example(name: str = "mcv754") -> Example:
    """The bundled example ``name`` (see :func:`examples`).

    ``mcv754``: model ``mcv754_wxyzt`` (paper 000's MCV 754, travels 754 x 500 x 550 mm);
    stations LT1..LT6 at the positions of paper 000's Table 5 (calculated values, mm) with
    small dead lengths (``volcal/data/mcv754_stations.csv``); the shipped true parameters
    (``volcal/data/mcv754_true_parameters.csv``, um / urad: drawn once with
    :func:`draw_true_parameters`, seed 754, scaled to 64 um maximum volumetric error over
    the default grid with zero tool offset); a 6 x 5 x 5 grid over the whole travel
    (poses whose tool points come within 50 mm of a station dropped); tool offsets
    (0, 0, 0), (0, 0, -100), (80, 0, -100), (0, 80, -100) mm; budget ``paper002``.
    """
    from volcal.measurement.plans import grid_plan
    from volcal.measurement.tables import load_stations

    if name not in _EXAMPLES:
        raise InputError(f"no bundled example named {name!r}; examples: {examples()}")
    d = _EXAMPLES[name]
    machine = Machine.from_model(d.model)
    em = ErrorModel(machine.spec)
    theta = load_true_parameters(_data_file(d.parameters_file), em)
    stations = load_stations(_data_file(d.stations_file))
    tools = np.array(d.tools, dtype=float)
    plan = _clear_plan(machine, grid_plan(machine.spec, d.grid), tools, stations, d.clearance_mm)
    return Example(
        name=name,
        model=d.model,
        machine=machine,
        error_model=em,
        theta_true=theta,
        stations=stations,
        plan=plan,
        tools=tools,
        budget=load_budget(d.budget),
        seed=d.seed,
        description=d.description,
    )


def _write_example_parameters(
    name: str = "mcv754", *, max_volumetric_um: float = 64.0, path: str | Path | None = None
) -> Path:
    """Regenerate the shipped true parameters of an example (maintainers only): draw with
    the example's seed, scale to ``max_volumetric_um`` and write ``name, value, unit``."""
    d = _EXAMPLES[name]
    machine = Machine.from_model(d.model)
    em = ErrorModel(machine.spec)
    theta = draw_true_parameters(machine, em, np.random.default_rng(d.seed), max_volumetric_um)
    path = Path(path) if path is not None else _data_file(d.parameters_file)
    # full precision (repr): the datum constraints hold to rounding in the file too
    parameters_table(em, theta).to_csv(path, index=False)
    return path
