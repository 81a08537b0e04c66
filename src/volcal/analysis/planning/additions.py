"""Interferometer lines and ballbar circles added to a tracker plan within a time budget.

A tracker plan (:func:`volcal.analysis.planning.plan.plan`) sees every error motion, some
less sharply than a laser interferometer or a ballbar would (paper 002's tracker reads
lengths to a micrometre; an interferometer reads a displacement along a line to a tenth of
one).  :func:`add_instruments` chooses, from a set of candidate set-ups, what to add to the
(fixed) tracker plan so that the plan's own criterion improves most within a budget of
measuring minutes:

* candidates (:func:`candidates`): interferometer lines along every linear axis at
  ``levels`` positions of each other linear axis across the travel (a ``levels`` x
  ``levels`` grid of offsets for a 3-axis machine; optics on the table, the reflector at
  the plan's first tool offset, ``interferometer_targets`` targets over the axis' travel);
  ballbar circles in every plane of two linear axes (XY, YZ, ZX), centred in the plane's
  travel at ``levels`` positions of the normal axis, with every radius of
  ``ballbar_radii_mm`` the travel allows (``ballbar_angles`` readings over one
  revolution).  Rotary axes stay at their reference position: the ballbar reader takes
  circles in planes of two linear axes (:mod:`volcal.measurement.instruments.ballbar`),
  so on a 5-axis machine those are the circles it supports;
* the information a set-up adds: its readings' whitened Jacobian from the instrument's
  own reading expression (:meth:`Instrument.reading`, differentiated by CasADi) times the
  model's d(point)/d(error parameters), in the plan's frozen parameterisation (the datum
  and pivots of :meth:`PlanEvaluator.freeze`), with the set-up's own free parameters
  (the interferometer's dead-path offset; the ballbar's centre in its plane and its bar
  length) eliminated (Schur complement): exactly the information the joint identification
  (:func:`volcal.analysis.fusion.identify_datasets`) has about the error parameters,
  since every set-up's parameters are its own.  Information adds over readings, so the
  plan with additions has M = M_tracker + sum of the chosen set-ups' M_c, judged by the
  plan's criterion (I, A, D or E of :class:`volcal.analysis.planning.evaluator.Scorer`);
* the choice (:func:`choose`): greedy by criterion gain per minute, then an exchange pass
  (swap a chosen set-up for an unchosen one while the criterion improves and the budget
  holds), then the greedy fill again, and at the end the best single affordable set-up if
  it alone beats the whole choice (the classic safeguard of cost-benefit greedy).  Not a
  knapsack: a knapsack needs a value per item that adds up, and these gains do not (a
  second line along X adds less than the first, a circle in XY less after the X and Y
  lines); greedy on the true criterion, re-evaluated after every pick, follows the
  diminishing returns, and the exchange pass repairs the greedy's early picks.  Each
  evaluation is one Cholesky factor of an r x r matrix (r free parameters), so the whole
  choice over a few dozen candidates takes well under a second.

Time costs (:class:`InstrumentCosts`; defaults documented there, overridable in the
planning setting's ``[instruments]`` table and on the command line): a set-up time per
line or circle and a time per target (interferometer) or per revolution (ballbar).

What cannot be added: a direction the tracker plan leaves undetermined stays pivoted in
the frozen parameterisation (the criterion is judged in the tracker plan's unknowns), so
the additions sharpen what the tracker plan determines; they do not rescue a parameter
it cannot see at all.

Units: mm and degrees in the tables (file units), minutes for times, um for predicted
uncertainties.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
import pandas as pd
import scipy.linalg as sla

from volcal.analysis.identify import field_jacobian
from volcal.base.exceptions import InputError
from volcal.base.threads import blas_threads
from volcal.measurement.instruments import Ballbar, Instrument, LaserInterferometer
from volcal.measurement.simulate_instruments import BALLBAR_SIGMA_UM, INTERFEROMETER_SIGMA_UM

__all__ = [
    "ADDABLE",
    "COST_KEYS",
    "InstrumentCosts",
    "Candidate",
    "Additions",
    "candidates",
    "choose",
    "add_instruments",
    "instruments_from_dict",
    "check_instruments",
    "check_minutes",
]

#: instruments the planner can add to a tracker plan
ADDABLE = ("interferometer", "ballbar")


@dataclass(frozen=True)
class InstrumentCosts:
    """Time costs and reading uncertainties of the instruments the planner adds.

    interferometer_setup_min: setting up one line (laser, optics on the table, alignment
    along the axis), minutes (default 15); interferometer_seconds_per_target: moving to
    and dwelling at one target, s (default 10); interferometer_targets: targets per line
    over the axis' travel (default 11); interferometer_sigma_um: standard uncertainty of
    one displacement reading, um (default 0.1, as ``volcal simulate --instruments``);
    ballbar_setup_min: setting up one circle (table ball, centring, the bar), minutes
    (default 5); ballbar_seconds_per_rev: one revolution of the circle, s (default 60);
    ballbar_angles: readings per revolution (default 36); ballbar_sigma_um: standard
    uncertainty of one deviation reading, um (default 0.5); ballbar_radii_mm: the bar
    lengths available, mm (default 50, 100, 150); levels: candidate positions per other
    axis across the travel (default 3: at 1/6, 1/2 and 5/6 of it)."""

    interferometer_setup_min: float = 15.0
    interferometer_seconds_per_target: float = 10.0
    interferometer_targets: int = 11
    interferometer_sigma_um: float = INTERFEROMETER_SIGMA_UM
    ballbar_setup_min: float = 5.0
    ballbar_seconds_per_rev: float = 60.0
    ballbar_angles: int = 36
    ballbar_sigma_um: float = BALLBAR_SIGMA_UM
    ballbar_radii_mm: tuple[float, ...] = (50.0, 100.0, 150.0)
    levels: int = 3

    def line_minutes(self) -> float:
        """Minutes one interferometer line takes: set-up plus every target."""
        return (
            self.interferometer_setup_min
            + self.interferometer_targets * self.interferometer_seconds_per_target / 60.0
        )

    def circle_minutes(self) -> float:
        """Minutes one ballbar circle takes: set-up plus one revolution."""
        return self.ballbar_setup_min + self.ballbar_seconds_per_rev / 60.0

    @classmethod
    def from_mapping(
        cls, values: Mapping[str, Any], source: str = "instruments"
    ) -> InstrumentCosts:
        """Costs from a mapping of :data:`COST_KEYS` (the setting's ``[instruments]`` keys
        or ``--instrument-cost`` items), every value checked; raises :class:`InputError`
        naming ``source`` and the key."""
        out: dict[str, Any] = {}
        for k, v in values.items():
            if k not in COST_KEYS:
                raise InputError(
                    f"unknown instrument cost {k!r}; expected some of {', '.join(COST_KEYS)}",
                    source=source,
                )
            if k == "ballbar_radii_mm":
                ok = (
                    isinstance(v, (list, tuple))
                    and len(v) > 0
                    and all(
                        isinstance(r, (int, float))
                        and not isinstance(r, bool)
                        and math.isfinite(r)
                        and r > 0
                        for r in v
                    )
                )
                if not ok:
                    raise InputError(
                        f"'{k}' must be a non-empty list of positive radii (mm), got {v!r}",
                        source=source,
                    )
                out[k] = tuple(float(r) for r in v)
                continue
            integer = k in ("interferometer_targets", "ballbar_angles", "levels")
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError(f"'{k}' must be a number, got {v!r}", source=source)
            if integer and (float(v) != int(v) or v < (1 if k == "levels" else 3)):
                least = 1 if k == "levels" else 3
                raise InputError(f"'{k}' must be an integer >= {least}, got {v!r}", source=source)
            zero_ok = k.endswith(("_min", "_target", "_rev"))
            if not math.isfinite(v) or v < 0 or (v == 0 and not zero_ok):
                raise InputError(
                    f"'{k}' must be a finite number {'>= 0' if zero_ok else '> 0'}, got {v!r}",
                    source=source,
                )
            out[k] = int(v) if integer else float(v)
        return dataclasses.replace(cls(), **out)

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["ballbar_radii_mm"] = list(self.ballbar_radii_mm)
        return d


#: the cost keys (setting ``[instruments]`` table, ``--instrument-cost KEY=VALUE``)
COST_KEYS = tuple(f.name for f in dataclasses.fields(InstrumentCosts))


def check_minutes(minutes: Any, source: str = "minutes") -> float:
    """The time budget for the added instruments, checked: a finite number >= 0."""
    ok = isinstance(minutes, (int, float)) and not isinstance(minutes, bool)
    if not ok or not (math.isfinite(float(minutes)) and float(minutes) >= 0):
        raise InputError(
            "the time budget for the added instruments must be a finite number of minutes "
            f">= 0, got {minutes!r}",
            source=source,
        )
    return float(minutes)


def check_instruments(names: Any, source: str = "instruments") -> tuple[str, ...]:
    """The instruments to add, checked against :data:`ADDABLE`."""
    if isinstance(names, str) or not isinstance(names, (list, tuple)):
        raise InputError(
            f"expected a list of instruments to add (some of {', '.join(ADDABLE)}), got {names!r}",
            source=source,
        )
    bad = [n for n in names if n not in ADDABLE]
    if bad or not names:
        raise InputError(
            f"unknown instrument(s) to add {', '.join(map(repr, bad)) or '(none)'}; "
            f"expected some of {', '.join(ADDABLE)}",
            source=source,
        )
    return tuple(dict.fromkeys(names))


def instruments_from_dict(doc: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The planning setting's ``[instruments]`` table checked: ``add`` (list of
    instruments, default both), ``minutes`` (the time budget for them) and the cost keys
    (:class:`InstrumentCosts`).  Returns {"add": tuple, "minutes": float or None,
    "costs": {key: value}}; raises :class:`InputError` naming ``source`` and the key."""
    where = f"{source}: [instruments]"
    out: dict[str, Any] = {"add": ADDABLE, "minutes": None, "costs": {}}
    costs = {k: v for k, v in doc.items() if k not in ("add", "minutes")}
    if "add" in doc:
        out["add"] = check_instruments(doc["add"], f"{where} 'add'")
    if "minutes" in doc:
        out["minutes"] = check_minutes(doc["minutes"], f"{where} 'minutes'")
    InstrumentCosts.from_mapping(costs, where)  # checks every key and value
    out["costs"] = dict(costs)
    return out


@dataclass(repr=False)
class Candidate:
    """One set-up the planner may add: its instrument, id, what it is (``what``: e.g.
    ``line along X at Y 83.3 mm, Z -441.7 mm``), the axis positions of its readings
    (file units, (n, n_axes)), the tool offset (mm), its minutes, its table in the
    instrument's CSV format (the reading column empty) and its information (r, r) in
    the plan's frozen parameterisation."""

    instrument: str
    setup: str
    what: str
    q_file: np.ndarray
    tool_mm: np.ndarray
    minutes: float
    table: pd.DataFrame
    info: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: when the planner picked it (1 = first; 0 = not chosen)
    picked: int = 0


def _levels(lo: float, hi: float, n: int) -> np.ndarray:
    """``n`` positions spread over [lo, hi]: the middles of n equal parts."""
    return lo + (np.arange(n) + 0.5) / n * (hi - lo)


def _reference(machine) -> np.ndarray:
    """Axis positions (file units) every candidate starts from: linear axes in the middle
    of their travel, rotary axes at their reference."""
    return np.array(
        [
            a.reference if a.is_rotary else 0.5 * (a.travel[0] + a.travel[1])
            for a in machine.spec.axes
        ],
        float,
    )


def _travel(
    machine, travel: Mapping[str, Sequence[float]] | None
) -> dict[str, tuple[float, float]]:
    out = {}
    for a in machine.spec.axes:
        lo, hi = (travel or {}).get(a.name, a.travel)
        out[a.name] = (float(lo), float(hi))
    return out


def _axis_columns(machine, prefix: str = "") -> list[str]:
    return [f"{prefix}{a.name}_{'deg' if a.is_rotary else 'mm'}" for a in machine.spec.axes]


def candidates(
    machine,
    instruments: Sequence[str],
    costs: InstrumentCosts,
    tool_mm: Sequence[float] | np.ndarray,
    travel: Mapping[str, Sequence[float]] | None = None,
) -> list[Candidate]:
    """The candidate set-ups (module docstring) for the given instruments, without their
    information (ids: ``I<axis><k>`` for lines, ``B<plane><k>`` for circles); tool_mm:
    the reflector's (or the spindle ball's) tool offset, mm;
    travel: {axis: (lo, hi)} mm / deg to cover (default the whole travel)."""
    spec = machine.spec
    lin = [a for a in spec.axes if not a.is_rotary]
    tr = _travel(machine, travel)
    ref = _reference(machine)
    for a in lin:
        ref[spec.axis_names.index(a.name)] = 0.5 * sum(tr[a.name])
    names = spec.axis_names
    tool = np.asarray(tool_mm, float)
    cols = _axis_columns(machine)
    out: list[Candidate] = []
    if "interferometer" in instruments:
        n = costs.interferometer_targets
        for a in lin:
            others = [b for b in lin if b.name != a.name]
            grids = [_levels(*tr[b.name], costs.levels) for b in others]
            for k, pos in enumerate(itertools.product(*grids)):
                q = np.tile(ref, (n, 1))
                q[:, names.index(a.name)] = np.linspace(*tr[a.name], n)
                for b, v in zip(others, pos):
                    q[:, names.index(b.name)] = v
                sid = f"I{a.name}{k + 1}"
                at = ", ".join(f"{b.name} {v:.1f} mm" for b, v in zip(others, pos))
                df = pd.DataFrame({"setup": sid, "point": [f"t{i + 1}" for i in range(n)]})
                for c, v in zip(cols, q.T):
                    df[c] = v
                for c, v in zip("xyz", tool):
                    df[f"tool_{c}_mm"] = v
                df["displacement_um"] = np.nan
                df["sigma_um"] = costs.interferometer_sigma_um
                out.append(
                    Candidate(
                        "interferometer",
                        sid,
                        f"line along {a.name}" + (f" at {at}" if at else ""),
                        q,
                        tool,
                        costs.line_minutes(),
                        df,
                    )
                )
    if "ballbar" in instruments and len(lin) >= 2:
        n = costs.ballbar_angles
        ang = np.arange(n) * 360.0 / n
        if len(lin) == 2:
            pairs = [(lin[0], lin[1])]
        else:
            pairs = [(lin[i], lin[(i + 1) % len(lin)]) for i in range(len(lin))]
        for a1, a2 in pairs:
            normal = [b for b in lin if b.name not in (a1.name, a2.name)]
            grids = [_levels(*tr[b.name], costs.levels) for b in normal]
            half = min(np.ptp(tr[a1.name]), np.ptp(tr[a2.name])) / 2.0
            k = 0
            for pos in itertools.product(*grids):
                for radius in costs.ballbar_radii_mm:
                    if radius > half + 1e-9:
                        continue  # the circle would leave the travel
                    k += 1
                    qc = ref.copy()
                    for b, v in zip(normal, pos):
                        qc[names.index(b.name)] = v
                    q = np.tile(qc, (n, 1))
                    q[:, names.index(a1.name)] += radius * np.cos(np.deg2rad(ang))
                    q[:, names.index(a2.name)] += radius * np.sin(np.deg2rad(ang))
                    plane = a1.name + a2.name
                    sid = f"B{plane}{k}"
                    at = ", ".join(f"{b.name} {v:.1f} mm" for b, v in zip(normal, pos))
                    df = pd.DataFrame(
                        {"setup": sid, "point": [f"a{i + 1}" for i in range(n)], "plane": plane}
                    )
                    for c, v in zip(_axis_columns(machine, "centre_"), qc):
                        df[c] = v
                    df["radius_mm"] = radius
                    df["angle_deg"] = ang
                    for c, v in zip("xyz", tool):
                        df[f"tool_{c}_mm"] = v
                    df["deviation_um"] = np.nan
                    df["sigma_um"] = costs.ballbar_sigma_um
                    out.append(
                        Candidate(
                            "ballbar",
                            sid,
                            f"circle in {plane}, radius {radius:g} mm, centre "
                            + ", ".join(
                                f"{names[j]} {qc[j]:.1f} mm"
                                for j in (names.index(a1.name), names.index(a2.name))
                            )
                            + (f", {at}" if at else ""),
                            q,
                            tool,
                            costs.circle_minutes(),
                            df,
                        )
                    )
    return out


def _nominal_readings(instrument: str, P0: np.ndarray) -> np.ndarray:
    """What the instrument reads on the nominal machine, for its start values: an
    interferometer zeroed at the first target reads the distance travelled along the
    line; a ballbar's deviation is zero."""
    if instrument == "interferometer":
        return np.linalg.norm(P0 - P0[0], axis=1)
    return np.zeros(len(P0))


@functools.lru_cache(maxsize=8)
def _derivatives(ins: Instrument) -> ca.Function:
    """(point, station) -> (d reading / d point, d reading / d station), from the
    instrument's one reading expression."""
    p = ca.SX.sym("p", 3)
    s = ca.SX.sym("s", ins.n_station_params)
    g = ca.SX.sym("g", ins.n_global_params)
    v = ins.reading(p, s, g)
    return ca.Function(f"{ins.name}_d", [p, s, g], [ca.jacobian(v, p), ca.jacobian(v, s)])


def candidate_information(plan_result: Any, cand: Candidate, sigma_um: float) -> np.ndarray:
    """The information (r, r) a candidate adds about the plan's unknowns, its own free
    set-up parameters eliminated (module docstring)."""
    ev = plan_result.evaluator
    fz = ev.frozen
    if fz is None:
        raise RuntimeError("the plan's evaluator is not frozen")
    pr = ev.problem
    nt = pr.n_theta
    m = plan_result.machine
    ins: Instrument = {"interferometer": LaserInterferometer(), "ballbar": Ballbar()}[
        cand.instrument
    ]
    q = m.axis_to_internal(cand.q_file)
    t = np.tile(cand.tool_mm, (len(q), 1))
    P0, _, G = field_jacobian(m, plan_result.error_model, np.zeros(nt), q, t)
    idx = np.zeros(len(q), int)
    st0 = ins.start_values([cand.setup], idx, P0, _nominal_readings(cand.instrument, P0))[0]
    held = set(ins.held_station_params(cand.setup))
    held |= set(ins.held_from_points([cand.setup], idx, P0).get(cand.setup, ()))
    free_s = [j for j, n in enumerate(ins.station_param_names) if n not in held]
    f = _derivatives(ins).map(len(q))
    dp, ds = f(P0.T, np.tile(st0[:, None], (1, len(q))), np.zeros((ins.n_global_params, len(q))))
    dp = np.asarray(dp).reshape(len(q), 3)
    ds = np.asarray(ds).reshape(len(q), ins.n_station_params)
    w = 1.0 / (sigma_um * 1e-3)
    ZZ = np.zeros((pr.n_x, fz.Z.shape[1]))
    ZZ[fz.free] = fz.Z
    # whitened rows in the plan's scaled, frozen coordinates
    A = w * np.einsum("nc,nck->nk", dp, G) * pr.scale[None, :nt] @ ZZ[:nt]
    S = w * ds[:, free_s]
    if S.size:
        Q = sla.qr(S, mode="economic")[0]
        A = A - Q @ (Q.T @ A)
    return A.T @ A


@dataclass(repr=False)
class Additions:
    """What :func:`add_instruments` added to a plan: the chosen candidates in measuring
    order, every candidate considered, the budget and costs, and the prediction with and
    without the additions (:meth:`prediction`)."""

    plan: Any
    chosen: list[Candidate]
    considered: list[Candidate]
    minutes: float
    costs: InstrumentCosts
    instruments: tuple[str, ...]
    tracker_minutes: float
    method: str
    notes: list[str] = field(default_factory=list)
    #: {axis: (lo, hi)} the candidates used (None: the whole travel)
    travel: Mapping[str, Sequence[float]] | None = None

    @property
    def spent_minutes(self) -> float:
        return float(sum(c.minutes for c in self.chosen))

    def information(self, upto: int | None = None) -> np.ndarray:
        """M of the tracker plan plus the first ``upto`` chosen set-ups (all by default)."""
        p = self.plan
        M = p.evaluator.information(p.stations_mm, p.selected)
        for c in self.chosen[: len(self.chosen) if upto is None else upto]:
            M = M + c.info
        return M

    def table(self, instrument: str) -> pd.DataFrame:
        """The chosen set-ups of one instrument in its CSV format, measuring order, the
        reading column empty (to fill with the readings, or with ``volcal simulate
        --instruments NAME=FILE``)."""
        frames = [c.table for c in self.chosen if c.instrument == instrument]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()

    def setups(self) -> pd.DataFrame:
        """One row per chosen set-up in measuring order: order, picked (when the planner
        chose it, 1 = first), instrument, setup, what, readings, minutes,
        cumulative_minutes."""
        rows, total = [], 0.0
        for k, c in enumerate(self.chosen):
            total += c.minutes
            rows.append(
                {
                    "order": k + 1,
                    "picked": c.picked,
                    "instrument": c.instrument,
                    "setup": c.setup,
                    "what": c.what,
                    "readings": len(c.table),
                    "minutes": c.minutes,
                    "cumulative_minutes": total,
                }
            )
        return pd.DataFrame(
            rows,
            columns=[
                "order",
                "picked",
                "instrument",
                "setup",
                "what",
                "readings",
                "minutes",
                "cumulative_minutes",
            ],
        )

    def positioning_lines(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The reference lines the positioning uncertainty is predicted on: per linear
        axis, (axis name, poses (n, n_axes) internal units, tool offsets (n, 3) mm): the
        axis' travel in ``interferometer_targets`` steps, the other axes in the middle
        (rotary at their reference), at the plan's first tool offset."""
        m = self.plan.machine
        tr = _travel(m, self.travel)
        ref = _reference(m)
        for a in m.spec.axes:
            if not a.is_rotary:
                ref[m.axis_names.index(a.name)] = 0.5 * sum(tr[a.name])
        n = self.costs.interferometer_targets
        out = []
        for j, a in enumerate(m.spec.axes):
            if a.is_rotary:
                continue
            q = np.tile(ref, (n, 1))
            q[:, j] = np.linspace(*tr[a.name], n)
            out.append((a.name, m.axis_to_internal(q), np.tile(self.plan.tools[0], (n, 1))))
        return out

    @functools.cached_property
    def _positioning_rows(self) -> dict[str, np.ndarray]:
        """{axis: (n - 1, r)} the displacement along each reference line relative to its
        first target, per reduced coordinate (mm per scaled unit)."""
        p = self.plan
        ev, pr = p.evaluator, p.evaluator.problem
        nt = pr.n_theta
        fz = ev.frozen
        ZZ = np.zeros((pr.n_x, fz.Z.shape[1]))
        ZZ[fz.free] = fz.Z
        out = {}
        for name, q, t in self.positioning_lines():
            P0, _, G = field_jacobian(p.machine, p.error_model, np.zeros(nt), q, t)
            u = P0[-1] - P0[0]
            u = u / np.linalg.norm(u)
            out[name] = np.einsum("c,nck->nk", u, G[1:] - G[0]) * pr.scale[None, :nt] @ ZZ[:nt]
        return out

    def positioning_u_um(self, M: np.ndarray) -> dict[str, float]:
        """{axis: RMS over the targets of its reference line (:meth:`positioning_lines`)
        of the standard uncertainty (um) of the displacement along the axis relative to
        the line's first target} for information M."""
        L = np.linalg.cholesky(M)
        out = {}
        for name, g in self._positioning_rows.items():
            X = sla.solve_triangular(L, g.T, lower=True)
            out[name] = float(np.sqrt(np.mean(np.sum(X * X, axis=0)))) * 1e3
        return out

    def prediction(self) -> pd.DataFrame:
        """See :meth:`_prediction` (computed once: the choice does not change)."""
        if getattr(self, "_pred", None) is None:
            with blas_threads(1):
                self._pred = self._prediction()
        return self._pred.copy()

    def _prediction(self) -> pd.DataFrame:
        """The criterion and the predicted uncertainties of the tracker plan, then after
        each chosen set-up in measuring order (the last row: the plan with every
        addition): step, added (set-up id, empty for the tracker plan), instrument,
        minutes_added (cumulative), criterion, criterion_value, criterion_unit,
        field_u_rms_um and field_u_max_um (the volumetric error's standard uncertainty
        over the evaluation poses, modulo the rigid motion no multilateration sees) and
        positioning_u_<AXIS>_um (:meth:`positioning_u_um`)."""
        p = self.plan
        ev = p.evaluator
        crit = p.criterion if p.criterion in ("I", "A", "D", "E") else "I"
        unit = "um" if crit == "I" else "scaled"
        rows = []
        for k in range(len(self.chosen) + 1):
            M = self.information(k)
            L = np.linalg.cholesky(M)
            X = sla.solve_triangular(L, ev.scorer.B.T, lower=True)
            u = np.sqrt(np.sum(X * X, axis=0)).reshape(-1, 3)
            tot = np.linalg.norm(u, axis=1)
            c = self.chosen[k - 1] if k else None
            row = {
                "step": k,
                "added": c.setup if c else "",
                "instrument": c.instrument if c else "tracker",
                "minutes_added": float(sum(x.minutes for x in self.chosen[:k])),
                "criterion": crit,
                "criterion_value": ev.scorer.value(M, crit),
                "criterion_unit": unit,
                "field_u_rms_um": float(np.sqrt(np.mean(tot**2))),
                "field_u_max_um": float(tot.max()),
            }
            for name, v in self.positioning_u_um(M).items():
                row[f"positioning_u_{name}_um"] = v
            rows.append(row)
        return pd.DataFrame(rows)

    def summary(self) -> dict[str, Any]:
        pred = self.prediction()
        by = {
            ins: {
                "setups": sum(c.instrument == ins for c in self.chosen),
                "minutes": float(sum(c.minutes for c in self.chosen if c.instrument == ins)),
            }
            for ins in self.instruments
        }
        return {
            "instruments": list(self.instruments),
            "budget_minutes": self.minutes,
            "spent_minutes": self.spent_minutes,
            "tracker_minutes": self.tracker_minutes,
            "per_instrument": by,
            "method": self.method,
            "candidates": len(self.considered),
            "costs": self.costs.as_dict(),
            "setups": self.setups().to_dict(orient="records"),
            "without": pred.iloc[0].to_dict(),
            "with": pred.iloc[-1].to_dict(),
            "notes": self.notes,
        }


def choose(
    base: np.ndarray,
    infos: Sequence[np.ndarray],
    minutes: Sequence[float],
    budget_min: float,
    value: Any,
) -> tuple[list[int], str]:
    """Indices of the chosen candidates (in the order they were picked) and a note on the
    method: greedy by criterion gain per minute, an exchange pass, the greedy fill
    again, and the best single affordable candidate if it alone is better (module
    docstring).  base: the tracker plan's information (r, r); infos: each candidate's;
    minutes: each candidate's cost; value(M): the criterion (smaller is better)."""
    cost = np.asarray(minutes, float)
    n = len(infos)
    if not budget_min > 0:  # no time: nothing, even set-ups costed at zero
        return [], "nothing to choose: no time"

    def total(sel: list[int]) -> np.ndarray:
        M = base.copy()
        for i in sel:
            M = M + infos[i]
        return M

    def greedy(sel: list[int]) -> list[int]:
        sel = list(sel)
        cur = value(total(sel))
        while True:
            left = budget_min - cost[sel].sum()
            M = total(sel)
            best, best_rate, best_val = -1, 0.0, cur
            for i in range(n):
                if i in sel or cost[i] > left + 1e-9:
                    continue
                v = value(M + infos[i])
                rate = (cur - v) / max(cost[i], 1e-9)
                if rate > best_rate * (1 + 1e-12) and v < cur * (1 - 1e-9):
                    best, best_rate, best_val = i, rate, v
            if best < 0:
                return sel
            sel.append(best)
            cur = best_val

    sel = greedy([])
    swaps = 0
    improved = True
    while improved and swaps < 4 * n:
        improved = False
        cur = value(total(sel))
        for a in list(sel):
            rest = [i for i in sel if i != a]
            M = total(rest)
            for b in range(n):
                if b in sel or cost[rest].sum() + cost[b] > budget_min + 1e-9:
                    continue
                v = value(M + infos[b])
                if v < cur * (1 - 1e-9):
                    sel = [b if i == a else i for i in sel]
                    cur, swaps, improved = v, swaps + 1, True
                    break
            if improved:
                break
    sel = greedy(sel)
    single = [i for i in range(n) if cost[i] <= budget_min + 1e-9]
    note = f"greedy by gain per minute, {swaps} exchange(s)"
    if single:
        i = min(single, key=lambda i: value(base + infos[i]))
        if value(base + infos[i]) < value(total(sel)) * (1 - 1e-9):
            sel = greedy([i])
            note += "; started again from the best single set-up, which beat the greedy"
    return sel, note


def add_instruments(*args: Any, **kwargs: Any) -> Additions:
    """See :func:`_add_instruments`; run with one BLAS thread, as the planner runs (its
    r x r solves are small, and a pool of threads on a shared machine slowed them ten
    times)."""
    with blas_threads(1):
        return _add_instruments(*args, **kwargs)


def _add_instruments(
    plan_result: Any,
    instruments: Sequence[str] = ADDABLE,
    minutes: float = 60.0,
    costs: InstrumentCosts | Mapping[str, Any] | None = None,
    *,
    tool_mm: Sequence[float] | None = None,
    travel: Mapping[str, Sequence[float]] | None = None,
) -> Additions:
    """Add interferometer lines and / or ballbar circles to a tracker plan within
    ``minutes`` of measuring time (module docstring); the tracker plan stays as it is.

    plan_result: :func:`volcal.analysis.planning.plan.plan`'s result; instruments: any of
    :data:`ADDABLE`; minutes: the budget for the additions, on top of the tracker plan's
    time (0: nothing added); costs: :class:`InstrumentCosts` or a mapping of
    :data:`COST_KEYS`; tool_mm: the tool offset of the reflector / spindle ball, mm
    (default the plan's first); travel: {axis: (lo, hi)} mm / deg the lines and circles
    may use (default the whole travel: the plan's criterion is judged over it, whatever
    part the tracker plan covers).  Returns :class:`Additions` (also set as
    ``plan_result.additions``)."""
    ins = check_instruments(list(instruments))
    minutes = check_minutes(minutes)
    c = costs if isinstance(costs, InstrumentCosts) else InstrumentCosts.from_mapping(costs or {})
    tool = np.asarray(plan_result.tools[0] if tool_mm is None else tool_mm, float)
    cands = candidates(plan_result.machine, ins, c, tool, travel)
    sigma = {"interferometer": c.interferometer_sigma_um, "ballbar": c.ballbar_sigma_um}
    for cand in cands:
        cand.info = candidate_information(plan_result, cand, sigma[cand.instrument])
    ev = plan_result.evaluator
    base = ev.information(plan_result.stations_mm, plan_result.selected)
    crit = plan_result.criterion if plan_result.criterion in ("I", "A", "D", "E") else "I"

    def value(M: np.ndarray) -> float:
        return ev.scorer.value(M, crit)

    notes: list[str] = []
    if plan_result.criterion not in ("I", "A", "D", "E"):
        notes.append(f"criterion {plan_result.criterion}: the additions are chosen by I")
    picked, method = choose(
        base, [x.info for x in cands], [x.minutes for x in cands], minutes, value
    )
    # measuring order: one instrument after the other (one set-up of the laser or the
    # ballbar kit), in the order the planner picked them within each
    order = [i for name in ins for i in picked if cands[i].instrument == name]
    chosen = [cands[i] for i in order]
    for rank, i in enumerate(picked):
        cands[i].picked = rank + 1
    if minutes > 0 and not chosen:
        cheapest = min((x.minutes for x in cands), default=float("nan"))
        notes.append(
            f"nothing added: the cheapest set-up takes {cheapest:.3g} min of the "
            f"{minutes:g} min budget, or none improves the criterion"
        )
    spr = float(plan_result.settings.get("seconds_per_reading", 4.0))
    n_read = int(plan_result.selected.sum()) * len(plan_result.tools) * len(plan_result.stations_mm)
    out = Additions(
        plan_result,
        chosen,
        cands,
        float(minutes),
        c,
        ins,
        n_read * spr / 60.0,
        method,
        notes,
        None if travel is None else {k: tuple(map(float, v)) for k, v in travel.items()},
    )
    plan_result.additions = out
    return out
