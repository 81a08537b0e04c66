"""Strategies side by side: several identifications of the same data, one table.

``volcal compare`` / :func:`compare` runs every requested strategy (default: joint,
two-phase, points-only, classic; any name :func:`volcal.problem.strategies.strategies`
knows) through :func:`volcal.workflow.identify` on the same readings, with the
same error model, budget and start values, and compares each with a reference strategy
(default joint):

* status, chi2/dof, the adequacy verdict (:func:`adequacy_verdict`) and its likely causes
  (``causes``: the kinds of :attr:`volcal.analysis.adequacy.Adequacy.cause_kinds`), residual
  RMS, time;
* the **field difference** to the reference: both volumetric errors at the workspace
  points (a Halton sample of the declared travel plus the corners of the travel box,
  :func:`volcal.analysis.identify.declared_poses`, at every measured tool offset),
  their difference with the best-fitting small rigid motion removed (the gauge: the one
  motion between stations and machine no multilateration sees), RMS and max of its norm
  in um and in units of its standard uncertainty.  That uncertainty is the reference
  fit's standard uncertainty of the volumetric error taken modulo the same rigid motion
  (the covariance propagated through the field Jacobian with the rigid part projected
  out), per point the root sum of squares of its three components.  One gauge for both:
  the rigid motion is fitted over the points both fits determine, for the difference and
  for its uncertainty alike (``u_reference_um`` of the points table is the reference's
  over the points it determines, the same set for every strategy that determines at
  least as much).  Two fits of the same
  readings are not independent, so the difference is measured against the uncertainty of
  the reference result: a strategy whose field moves by several u from the reference
  moves it by more than the data's own uncertainty.  Points whose error one of the two
  fits does not determine (a combination the data cannot see) are left out and counted;
* the largest parameter differences, in units of the reference's standard uncertainty
  (parameters both fits identify);
* what each leaves unidentifiable;
* with ``truth`` (true parameters, the file ``volcal simulate --true-parameters`` reads,
  or a function giving the true field): each strategy's field error against the truth,
  modulo the same rigid motion;
* with ``trials``: the comparison repeated on simulated data (the data's poses, tool
  offsets and stations, the budget's noise, seeded per trial), mean and spread of each
  strategy's field error against the simulated truth.  Trials run serially, in local
  processes or on Dask (:func:`volcal.analysis.uncertainty.parallel.run_chunks`); trial
  ``i`` draws its noise from ``SeedSequence(seed, spawn_key=(i,))`` wherever it runs, so a
  seed gives the same numbers everywhere.

The folder ``volcal compare`` writes is :func:`volcal.outputs.compare_report.write_comparison`.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.analysis.identifiability import rigid_columns
from volcal.analysis.identify import (
    IdentificationResult,
    build_error_model,
    declared_poses,
    field_jacobian,
    rigid_fit,
)
from volcal.base.exceptions import InputError, SolverError
from volcal.base.progress import stage as report_stage
from volcal.measurement.budget import Budget, BudgetWarning, load_budget
from volcal.measurement.tables import Measurements, load_measurements, load_stations
from volcal.model.errors import Datum, ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.model.spec import MachineSpec
from volcal.problem.strategies import strategies as registered_strategies
from volcal.workflow.dispatch import identify

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_STRATEGIES",
    "Comparison",
    "StrategyRun",
    "TrialKernel",
    "adequacy_verdict",
    "compare",
    "modulo_gauge",
    "run_trials",
    "trial_seed",
]

#: the strategies compared by default, in this order
DEFAULT_STRATEGIES: tuple[str, ...] = ("joint", "two-phase", "points-only", "classic")
#: Halton poses of the workspace sample (plus the corners of the travel box)
EVAL_POSES = 256
#: parameter differences named per strategy in the table
TOP_PARAMETERS = 3

_STATION_COLUMNS = ("station", "x_mm", "y_mm", "z_mm", "dead_length_mm")
#: a true volumetric error field: (q internal (N, n_axes) mm / rad, tools (N, 3) mm) -> um
TruthField = Callable[[np.ndarray, np.ndarray], np.ndarray]


def adequacy_verdict(result: IdentificationResult) -> str:
    """The adequacy verdict of ``result`` as the machine-readable word the
    :class:`volcal.analysis.adequacy.Adequacy` object gives (the one place the comparison
    reads it)."""
    return str(result.adequacy.verdict)


@dataclass
class StrategyRun:
    """One strategy's identification: the result (None when its solver failed), status,
    success, wall-clock seconds and the error message of a failure."""

    strategy: str
    result: IdentificationResult | None
    status: str
    success: bool
    seconds: float
    error: str = ""


@dataclass(repr=False)
class Comparison:
    """What :func:`compare` found (um / urad unless a name says otherwise).

    table: one row per strategy (columns in the module docstring's order, units in the
    names); parameter_differences: one row per strategy and parameter both identify
    (``difference_in_u``: the difference over the reference's standard uncertainty);
    points: the workspace sample (axis columns mm / deg, ``tool_x, tool_y, tool_z``,
    nominal ``x_mm, y_mm, z_mm``, ``u_reference_um`` the reference's standard uncertainty
    modulo the gauge); differences: per strategy the field difference to the reference
    (N, 3) um with the gauge removed (NaN where not compared); truth_errors: the same
    against the truth (None without a truth); trials: one row per trial and strategy
    (None without trials); runs: the identifications by strategy.
    """

    model: str
    reference: str
    strategies: list[str]
    runs: dict[str, StrategyRun]
    table: pd.DataFrame
    parameter_differences: pd.DataFrame
    points: pd.DataFrame
    differences: dict[str, np.ndarray]
    truth_errors: dict[str, np.ndarray] | None = None
    truth_source: str = ""
    trials: pd.DataFrame | None = None
    trials_truth: str = ""
    #: the trials' kernel (run more with :func:`run_trials`); None without trials
    trial_kernel: TrialKernel | None = field(default=None, repr=False)
    seed: int = 0
    n_readings: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def __repr__(self) -> str:
        return (
            f"Comparison({self.model}, {len(self.strategies)} strategies against "
            f"{self.reference}, {self.n_readings} readings"
            + (f", {self.n_trials} trials" if self.trials is not None else "")
            + ")"
        )

    @property
    def n_trials(self) -> int:
        return 0 if self.trials is None else int(self.trials["trial"].nunique())

    @property
    def success(self) -> bool:
        """Did every strategy's solver succeed?"""
        return all(r.success for r in self.runs.values())

    @property
    def reference_result(self) -> IdentificationResult | None:
        return self.runs[self.reference].result


# --------------------------------------------------------------------------------------
# the gauge


def _centred(points: np.ndarray) -> np.ndarray:
    # a rigid motion about the centroid spans the same space; centring keeps the
    # design matrix well conditioned (mm against 1)
    p = np.asarray(points, float)
    return p - p.mean(axis=0) if len(p) else p


def modulo_gauge(points: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``d`` (N, 3) at nominal points (N, 3) mm with the least-squares small rigid motion
    ``a + w x p`` removed (the motion no multilateration sees; the fit is
    :func:`volcal.analysis.identify.rigid_fit`); same units as ``d``."""
    d = np.asarray(d, float)
    if len(d) == 0:
        return d.reshape(0, 3)
    return rigid_fit(_centred(points), d)[1]


def _u_modulo_gauge(G: np.ndarray, points: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Per point the standard uncertainty (mm; root sum of squares of the components) of
    the first-order field G theta with the rigid motion fitted over ``points`` removed:
    the projection P = I - A A^+ acts on G, so cov(P G theta) = (P G) C (P G)^T."""
    n, _, k = G.shape
    G2 = G.reshape(3 * n, k)
    A = rigid_columns(_centred(points))
    PG = G2 - A @ np.linalg.lstsq(A, G2, rcond=None)[0]
    # held variables (NaN rows) contribute nothing, as in predict_volumetric
    var = np.sum((PG @ np.nan_to_num(cov)) * PG, axis=1).reshape(n, 3)
    return np.sqrt(np.clip(var, 0.0, None).sum(axis=1))


def _norm_stats(r: np.ndarray) -> tuple[float, float]:
    """RMS and max over the points of the norm of r (N, 3)."""
    if len(r) == 0:
        return float("nan"), float("nan")
    n = np.linalg.norm(r, axis=1)
    return float(np.sqrt(np.mean(n**2))), float(np.max(n))


# --------------------------------------------------------------------------------------
# one comparison


def _run(strategy: str, machine, meas, stations, opts: Mapping[str, Any]) -> StrategyRun:
    t0 = time.perf_counter()
    try:
        res = identify(machine, meas, stations, strategy=strategy, **opts)
    except SolverError as exc:
        status = exc.status or str(exc)
        return StrategyRun(strategy, None, status, False, time.perf_counter() - t0, str(exc))
    return StrategyRun(strategy, res, res.status, res.success, res.seconds)


def _unidentifiable(res: IdentificationResult) -> list[str]:
    return [n for n, ok in zip(res.error_model.param_names, res.identifiable) if not ok]


def _field(res: IdentificationResult, Q: np.ndarray, T: np.ndarray):
    """(field (N, 3) um, determined (N,) bool) of a result at poses Q and tools T."""
    pred = res.predict(Q, T, with_uncertainty=False)
    det = (
        pred["determined"].to_numpy(bool)
        if "determined" in pred
        else np.ones(len(pred), dtype=bool)
    )
    return pred[["dx_um", "dy_um", "dz_um"]].to_numpy(float), det


def _parameter_differences(ref: IdentificationResult, res: IdentificationResult) -> pd.DataFrame:
    pr, ps = ref.parameters(), res.parameters()
    both = pr["identifiable"].to_numpy(bool) & ps["identifiable"].to_numpy(bool)
    u = pr["u"].to_numpy(float)
    ok = both & np.isfinite(u) & (u > 0)
    diff = ps["value"].to_numpy(float) - pr["value"].to_numpy(float)
    out = pd.DataFrame(
        {
            "strategy": res.strategy,
            "name": pr["name"],
            "unit": pr["unit"],
            "reference_value": pr["value"],
            "value": ps["value"],
            "difference": diff,
            "u_reference": u,
            "difference_in_u": np.where(ok, diff / np.where(ok, u, 1.0), np.nan),
        }
    )
    return out.loc[ok].reset_index(drop=True)


def _top(pdiff: pd.DataFrame, n: int = TOP_PARAMETERS) -> str:
    if pdiff.empty:
        return ""
    z = pdiff["difference_in_u"].to_numpy(float)
    order = np.argsort(-np.abs(z))[:n]
    return ", ".join(f"{pdiff['name'].iloc[i]} {z[i]:+.3g} u" for i in order)


def _true_field(
    machine: Machine, em: ErrorModel, truth: np.ndarray | TruthField, Q, T
) -> np.ndarray:
    """The true volumetric error (N, 3) um: the exact model at the true parameters, or the
    function given."""
    if callable(truth):
        out = np.asarray(truth(Q, T), float)
        if out.shape != (len(Q), 3):
            raise InputError(
                f"the truth function returned shape {out.shape}; expected ({len(Q)}, 3) in um"
            )
        return out
    _, dp, _ = machine.evaluate(Q, T, em.values(Q, truth), exact=True)
    return dp * 1e3


def _load_truth(truth, em: ErrorModel) -> tuple[np.ndarray | TruthField | None, str]:
    """(true parameters (mm / rad) or a field function, a description)."""
    if truth is None:
        return None, ""
    if callable(truth):
        return truth, "a true field function"
    if isinstance(truth, (str, Path)):
        from volcal.measurement.simulate import load_true_parameters

        return load_true_parameters(truth, em), str(truth)
    theta = np.asarray(truth, float)
    if theta.shape != (em.n_params,) or not np.all(np.isfinite(theta)):
        raise InputError(
            f"expected {em.n_params} finite true parameters (mm / rad) for model "
            f"'{em.spec.name}', got shape {theta.shape}"
        )
    return theta, "true parameters given"


def compare(
    model: str | Path | MachineSpec | Machine,
    data: str | Path | pd.DataFrame | Measurements,
    stations: str | Path | pd.DataFrame | None = None,
    *,
    strategies: Sequence[str] = DEFAULT_STRATEGIES,
    reference: str | None = None,
    degree: int = 3,
    datum: Datum = "iso230",
    forms: dict[str, ErrorForm] | None = None,
    error_model: ErrorModel | None = None,
    budget: str | Path | Budget = "paper002",
    solver: str = "ipopt",
    truth: str | Path | np.ndarray | TruthField | None = None,
    trials: int = 0,
    seed: int = 0,
    workers: int | None = 1,
    scheduler: Any = None,
    eval_poses: int = EVAL_POSES,
    columns: Mapping[str, str] | str | None = None,
    true_stations: pd.DataFrame | None = None,
    truth_name: str | None = None,
) -> Comparison:
    """Identify the same data with several strategies and compare them (module docstring).

    model, data, stations, degree, datum, forms, error_model, budget, solver, columns: as
    :func:`volcal.workflow.identify` (one error model for every strategy);
    strategies: registered strategy names; reference: the strategy the others are compared
    with (default joint when listed, else the first); truth: true parameters (a
    ``name, value, unit`` file as ``volcal simulate --true-parameters`` reads, or theta in
    mm / rad in the error model's order) or a function (q internal, tools mm) -> true
    volumetric error (N, 3) um; trials: repeat on that many simulated data sets (the
    truth's parameters, else the reference's estimate; true stations ``true_stations``,
    else the reference's identified stations); seed: of the trials' noise; workers,
    scheduler: where the trials run (:func:`volcal.analysis.uncertainty.parallel.run_chunks`;
    ``workers=1``: this process); eval_poses: Halton poses of the workspace sample;
    truth_name: how the tables name the truth (default: its file).

    A strategy whose solver fails is reported (status, no figures) and the others go on;
    bad input raises :class:`InputError`.
    """
    t_start = time.perf_counter()
    strategies = [str(s) for s in strategies]
    known = list(registered_strategies())
    bad = [s for s in strategies if s not in known]
    if bad or not strategies:
        raise InputError(
            f"unknown strategy {', '.join(map(repr, bad)) or '(none given)'}; expected "
            f"names among {', '.join(known)}",
            source="strategies",
        )
    if len(set(strategies)) != len(strategies):
        raise InputError("a strategy is listed twice", source="strategies")
    if reference is None:
        reference = "joint" if "joint" in strategies else strategies[0]
    if reference not in strategies:
        raise InputError(
            f"the reference strategy {reference!r} is not among the strategies compared "
            f"({', '.join(strategies)})",
            source="reference",
        )
    if isinstance(trials, bool) or int(trials) != trials or trials < 0:
        raise InputError(f"expected a number of trials >= 0, got {trials!r}", source="trials")
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise InputError(f"expected a non-negative integer seed, got {seed!r}", source="seed")
    if eval_poses < 1:
        raise InputError(f"expected eval_poses >= 1, got {eval_poses}", source="eval_poses")

    machine = model if isinstance(model, Machine) else Machine.from_model(model)
    spec = machine.spec
    st_table = None if stations is None else load_stations(stations)
    meas = (
        data
        if isinstance(data, Measurements)
        else load_measurements(data, spec, stations=st_table, columns=columns)
    )
    em = error_model or build_error_model(spec, degree=degree, datum=datum, forms=forms)
    bud = budget if isinstance(budget, Budget) else load_budget(budget)
    # said here, once per run: the trials draw every axis' scatter from the budget (their
    # processes keep quiet about it)
    bud.warn_uncovered(spec)
    truth_value, truth_source = _load_truth(truth, em)
    truth_source = truth_name or truth_source
    opts = {"error_model": em, "budget": bud, "solver": solver}

    runs: dict[str, StrategyRun] = {}
    for s in strategies:
        with report_stage(f"identifying ({s})"):
            runs[s] = _run(s, machine, meas, st_table, opts)

    # the workspace sample at every measured tool offset
    tools = np.unique(np.asarray(meas.tool, float), axis=0)
    q = declared_poses(spec, eval_poses)
    Q = np.repeat(q, len(tools), axis=0)
    T = np.tile(tools, (len(q), 1))
    p0 = machine.nominal_points(Q, T)
    q_file = Q.copy()
    for k, a in enumerate(spec.axes):
        if a.is_rotary:
            q_file[:, k] = np.rad2deg(q_file[:, k])
    points = pd.DataFrame(q_file, columns=list(spec.axis_names))
    points[["tool_x", "tool_y", "tool_z"]] = T
    points[["x_mm", "y_mm", "z_mm"]] = p0

    ref = runs[reference].result
    fields: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for s, r in runs.items():
        if r.result is not None:
            fields[s] = _field(r.result, Q, T)
    u_ref = np.full(len(Q), np.nan)
    G = None
    if ref is not None:
        _, _, G = field_jacobian(machine, em, ref.theta, Q, T)
        det_ref = fields[reference][1]
        u_ref[det_ref] = _u_modulo_gauge(G[det_ref], p0[det_ref], ref.cov_theta) * 1e3
    points["u_reference_um"] = u_ref

    true_um = None
    if truth_value is not None:
        true_um = _true_field(machine, em, truth_value, Q, T)

    rows, pdiffs = [], []
    differences: dict[str, np.ndarray] = {}
    truth_errors: dict[str, np.ndarray] | None = {} if true_um is not None else None
    for s in strategies:
        r = runs[s]
        res = r.result
        row: dict[str, Any] = {
            "strategy": s,
            "status": r.status,
            "success": r.success,
            "chi2_per_dof": np.nan,
            "verdict": "not solved",
            "causes": "",
            "residual_rms_um": np.nan,
            "field_diff_rms_um": np.nan,
            "field_diff_max_um": np.nan,
            "field_diff_rms_in_u": np.nan,
            "field_diff_max_in_u": np.nan,
            "points_compared": 0,
            "largest_parameter_differences": "",
            "n_unidentifiable": np.nan,
            "unidentifiable": "",
            "time_s": r.seconds,
        }
        if true_um is not None:
            row["truth_error_rms_um"] = np.nan
            row["truth_error_max_um"] = np.nan
        if res is not None:
            un = _unidentifiable(res)
            row.update(
                chi2_per_dof=float(res.conditions.get("chi2_per_dof", np.nan)),
                verdict=adequacy_verdict(res),
                # the likely causes' kinds, most likely first (Adequacy.cause_kinds)
                causes=" ".join(res.adequacy.cause_kinds),
                residual_rms_um=res.residual_rms_um,
                n_unidentifiable=len(un),
                unidentifiable=" ".join(un),
            )
            f_s, det_s = fields[s]
            # a fit without its own null space (classic) is compared where the reference
            # determines the field
            det_s = det_s & fields[reference][1] if ref is not None else det_s
            if ref is not None:
                f_r, det_r = fields[reference]
                m = det_s & det_r
                d = np.full((len(Q), 3), np.nan)
                d[m] = modulo_gauge(p0[m], f_s[m] - f_r[m])
                differences[s] = d
                rms, mx = _norm_stats(d[m])
                # the uncertainty in the gauge of the difference: fitted over the same
                # points m (module docstring)
                u_m = u_ref[m]
                if G is not None and not np.array_equal(m, det_r):
                    u_m = _u_modulo_gauge(G[m], p0[m], ref.cov_theta) * 1e3
                with np.errstate(divide="ignore", invalid="ignore"):
                    z = np.linalg.norm(d[m], axis=1) / u_m
                z = z[np.isfinite(z)]
                row.update(
                    field_diff_rms_um=rms,
                    field_diff_max_um=mx,
                    field_diff_rms_in_u=float(np.sqrt(np.mean(z**2))) if len(z) else np.nan,
                    field_diff_max_in_u=float(np.max(z)) if len(z) else np.nan,
                    points_compared=int(m.sum()),
                )
                pd_s = _parameter_differences(ref, res)
                if s != reference:
                    pdiffs.append(pd_s)
                    row["largest_parameter_differences"] = _top(pd_s)
            if true_um is not None and truth_errors is not None:
                e = np.full((len(Q), 3), np.nan)
                e[det_s] = modulo_gauge(p0[det_s], f_s[det_s] - true_um[det_s])
                truth_errors[s] = e
                row["truth_error_rms_um"], row["truth_error_max_um"] = _norm_stats(e[det_s])
        rows.append(row)
    table = pd.DataFrame(rows)
    pdiff = (
        pd.concat(pdiffs, ignore_index=True)
        if pdiffs
        else pd.DataFrame(
            columns=[
                "strategy",
                "name",
                "unit",
                "reference_value",
                "value",
                "difference",
                "u_reference",
                "difference_in_u",
            ]
        )
    )
    notes: list[str] = []
    if ref is None:
        notes.append(
            f"the reference strategy {reference} did not solve: no field or parameter differences"
        )

    cmp = Comparison(
        model=spec.name,
        reference=reference,
        strategies=strategies,
        runs=runs,
        table=table,
        parameter_differences=pdiff,
        points=points,
        differences=differences,
        truth_errors=truth_errors,
        truth_source=truth_source,
        seed=int(seed),
        n_readings=len(meas.table),
        notes=notes,
    )
    if trials and ref is None:
        # the table of the strategies that did solve is still worth writing
        cmp.notes.append(
            f"trials skipped: the reference strategy {reference} did not solve "
            f"({runs[reference].status}); the trials need its stations (and, without a "
            "truth, its estimate) to simulate from"
        )
    elif trials and ref is not None:
        if callable(truth_value) or truth_value is None:
            theta_t, cmp.trials_truth = ref.theta, f"the {reference} estimate of the data"
        else:
            theta_t, cmp.trials_truth = truth_value, truth_source
        st_true = true_stations if true_stations is not None else ref.stations
        st_true = st_true[[c for c in _STATION_COLUMNS if c in st_true]]
        kernel = TrialKernel.from_data(
            machine,
            em,
            bud,
            meas,
            st_table,
            load_stations(st_true),
            theta_t,
            strategies,
            Q,
            T,
            fields[reference][1],
            seed=int(seed),
            solver=solver,
        )
        cmp.trial_kernel = kernel
        cmp.trials = run_trials(kernel, int(trials), workers=workers, scheduler=scheduler)
        summary = _trial_summary(cmp.trials)
        table = table.merge(summary, on="strategy", how="left")
        cmp.table = table
    cmp.seconds = time.perf_counter() - t_start
    return cmp


# --------------------------------------------------------------------------------------
# trials on simulated data


def trial_seed(seed: int, trial: int) -> int:
    """The simulation seed of trial ``trial`` of a run seeded ``seed`` (independent
    streams: ``SeedSequence(seed, spawn_key=(trial,))``)."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(int(trial),))
    return int(ss.generate_state(1, dtype=np.uint32)[0])


@dataclass
class TrialKernel:
    """What every worker needs to run trials (picklable): the model, the error model, the
    budget, the true parameters and stations, the poses, tools and readings kept (the
    data's layout), the start stations given to identify, the strategies, the workspace
    sample and where the reference determines it, the seed."""

    machine: Machine
    error_model: ErrorModel
    budget: Budget
    theta: np.ndarray
    stations: pd.DataFrame
    plan: pd.DataFrame
    tools: np.ndarray
    keep: np.ndarray | None
    start_stations: pd.DataFrame | None
    strategies: list[str]
    Q: np.ndarray
    T: np.ndarray
    mask: np.ndarray
    seed: int
    solver: str = "ipopt"
    _true: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def from_data(
        cls,
        machine: Machine,
        em: ErrorModel,
        budget: Budget,
        meas: Measurements,
        start_stations: pd.DataFrame | None,
        true_stations: pd.DataFrame,
        theta: np.ndarray,
        strategies: Sequence[str],
        Q: np.ndarray,
        T: np.ndarray,
        mask: np.ndarray,
        *,
        seed: int,
        solver: str = "ipopt",
    ) -> TrialKernel:
        """The kernel simulating the layout of ``meas``: its poses and tool offsets,
        measured by the true stations; readings the data do not have are dropped after
        the simulation.  A reading the data repeat (the same station, tool offset and
        pose more than once) is simulated as often, each repeat with its own noise: the
        plan holds a pose as many times as its most repeated reading."""
        names = list(machine.spec.axis_names)
        tab = meas.table
        plan = tab[names].drop_duplicates().reset_index(drop=True)
        tools = np.unique(np.asarray(meas.tool, float), axis=0)
        missing = sorted(set(meas.station_ids) - set(true_stations["station"]))
        if missing:
            raise InputError(
                f"the true stations lack station(s) {', '.join(missing)} of the data",
                source="true_stations",
            )
        st = true_stations.set_index("station").loc[list(meas.station_ids)].reset_index()
        pose_idx = pd.MultiIndex.from_frame(plan).get_indexer(pd.MultiIndex.from_frame(tab[names]))
        tool_idx = np.array([np.flatnonzero((tools == t).all(axis=1))[0] for t in meas.tool])
        # the k-th repeat of a reading goes to the k-th copy of its pose in the plan
        occ = (
            pd.DataFrame({"s": meas.station_index, "k": tool_idx, "p": pose_idx})
            .groupby(["s", "k", "p"])
            .cumcount()
            .to_numpy()
        )
        copies = np.zeros(len(plan), dtype=int)
        np.maximum.at(copies, pose_idx, occ + 1)
        first = np.concatenate([[0], np.cumsum(copies)[:-1]])
        plan = plan.loc[np.repeat(np.arange(len(plan)), copies)].reset_index(drop=True)
        # the simulator's reading order: station-major, then tool, then pose
        S, K, N = len(st), len(tools), len(plan)
        r = (meas.station_index * K + tool_idx) * N + first[pose_idx] + occ
        keep = np.zeros(S * K * N, dtype=bool)
        keep[r] = True
        return cls(
            machine,
            em,
            budget,
            np.asarray(theta, float).copy(),
            st[["station", "x_mm", "y_mm", "z_mm", "dead_length_mm"]],
            plan,
            tools,
            None if keep.all() else keep,
            start_stations,
            list(strategies),
            Q,
            T,
            np.asarray(mask, bool),
            int(seed),
            solver,
        )

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_true"] = None
        return d

    def true_field(self) -> np.ndarray:
        if self._true is None:
            self._true = _true_field(self.machine, self.error_model, self.theta, self.Q, self.T)
        return self._true

    def simulated(self, trial: int) -> pd.DataFrame:
        """The readings of trial ``trial``: the data's layout simulated from the true
        parameters and stations with the budget's noise (seed :func:`trial_seed`)."""
        from volcal.measurement.simulate import simulate

        sim = simulate(
            self.machine,
            self.error_model,
            self.theta,
            self.stations,
            self.plan,
            self.tools,
            self.budget,
            trial_seed(self.seed, trial),
        )
        data = sim.measurements
        if self.keep is not None:
            data = data.loc[self.keep].reset_index(drop=True)
        return data

    def run_chunk(self, chunk: tuple[int, int]) -> np.ndarray:
        """Trials ``range(*chunk)``: (n, n_strategies, 3) of field error RMS and max (um,
        modulo the gauge, over the points the reference determines) and 1.0 / 0.0 for a
        solver that succeeded / failed."""
        from volcal.base import progress

        # one bar for the trials (run_trials); the stages of each identification inside a
        # trial would only interleave with it
        was = progress.enabled()
        progress.enable(False)
        try:
            return self._run(chunk)
        finally:
            progress.enable(was)

    def _run(self, chunk: tuple[int, int]) -> np.ndarray:
        true_um = self.true_field()
        m = self.mask
        p0 = self.machine.nominal_points(self.Q[m], self.T[m])
        out = np.full((chunk[1] - chunk[0], len(self.strategies), 3), np.nan)
        with warnings.catch_warnings():
            # the run said it once (compare); a trial, maybe in its own process, not
            warnings.simplefilter("ignore", BudgetWarning)
            for i, trial in enumerate(range(*chunk)):
                data = self.simulated(trial)
                for j, s in enumerate(self.strategies):
                    try:
                        res = identify(
                            self.machine,
                            data,
                            self.start_stations,
                            strategy=s,
                            error_model=self.error_model,
                            budget=self.budget,
                            solver=self.solver,
                        )
                    except SolverError:
                        out[i, j, 2] = 0.0
                        continue
                    f, _ = _field(res, self.Q[m], self.T[m])
                    out[i, j, :2] = _norm_stats(modulo_gauge(p0, f - true_um[m]))
                    out[i, j, 2] = 1.0 if res.success else 0.0
        return out


def run_trials(
    kernel: TrialKernel,
    trials: int,
    *,
    workers: int | None = 1,
    scheduler: Any = None,
    progress: bool | None = None,
) -> pd.DataFrame:
    """Run ``trials`` trials of ``kernel`` (one chunk each; serially, in local processes
    or on Dask, see :func:`volcal.analysis.uncertainty.parallel.run_chunks`) and return
    one row per trial and strategy: ``trial, seed, strategy, field_error_rms_um,
    field_error_max_um, success``.  The same seed gives the same table wherever it runs.
    progress: a bar on a terminal, plain lines with the time left otherwise
    (:func:`volcal.base.progress.counter`; None: when :mod:`volcal.base.progress` is on)."""
    from volcal.analysis.uncertainty.parallel import run_chunks
    from volcal.base.progress import counter

    chunks = [(i, i + 1) for i in range(int(trials))]
    got: dict[int, np.ndarray] = {}
    with counter(len(chunks), "trials", "trial", on=progress) as bar:
        for chunk, res in run_chunks(kernel, chunks, workers=workers, scheduler=scheduler):
            got[chunk[0]] = res
            bar.update(1)
    rows = []
    for i in range(int(trials)):
        for j, s in enumerate(kernel.strategies):
            rms, mx, ok = got[i][0, j]
            rows.append(
                {
                    "trial": i,
                    "seed": trial_seed(kernel.seed, i),
                    "strategy": s,
                    "field_error_rms_um": rms,
                    "field_error_max_um": mx,
                    "success": bool(ok == 1.0),
                }
            )
    return pd.DataFrame(rows)


def _trial_summary(trials: pd.DataFrame) -> pd.DataFrame:
    """Per strategy: mean and standard deviation over the successful trials of the field
    error RMS and max (um), and the number of failed trials."""
    out = []
    for s, g in trials.groupby("strategy", sort=False):
        ok = g.loc[g["success"]]
        rms, mx = ok["field_error_rms_um"], ok["field_error_max_um"]
        out.append(
            {
                "strategy": s,
                "trials_error_rms_mean_um": float(rms.mean()) if len(ok) else np.nan,
                "trials_error_rms_sd_um": float(rms.std(ddof=1)) if len(ok) > 1 else np.nan,
                "trials_error_max_mean_um": float(mx.mean()) if len(ok) else np.nan,
                "trials_error_max_sd_um": float(mx.std(ddof=1)) if len(ok) > 1 else np.nan,
                "trials_failed": int((~g["success"]).sum()),
            }
        )
    return pd.DataFrame(out)
