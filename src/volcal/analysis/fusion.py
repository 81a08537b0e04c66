"""Several instruments' tables identified as one problem (one NLP, one datum, one
covariance): a tracker, a multi-laser head, laser interferometer lines and ballbar circles
measured on the same machine.

Each table is read by its instrument (:meth:`Instrument.read_table`: the interferometer's
CSV or ISO 230-2 file, the ballbar's circles) and validated alone (messages name its file
and rows); its readings are weighted by their own ``sigma`` or by the table's budget
(paper 002's for the tracker by default; an interferometer or ballbar table without sigma
needs its own budget).  The tables are then joined into one measurement table read by a
:class:`~volcal.measurement.instruments.CombinedInstrument` and identified by
:func:`volcal.analysis.identify.identify`.

What each instrument says about the fit (:func:`instrument_fit`): its share of the degrees
of freedom (the sum of its readings' redundancy numbers 1 - h_ii, h the hat matrix of the
whitened, datum-constrained problem), its chi2/dof and whether that lies in its 99.9 %
interval.  Variance component estimation (``variance_components=True``, Helmert's method
in Foerstner's iterative form) re-weights each instrument by the factor its chi2/dof
gives until the factors settle, and reports each budget's scale factor (on the standard
uncertainties) with its standard uncertainty and 95 % interval (chi2 with Satterthwaite's
degrees of freedom from REML's information, see :func:`identify_datasets`; coverage
measured by studies/vce).

The single table's options, per table: ``robust`` rejects each table's outliers on that
table's own robust scale; ``stations`` (a tracker's stations table) and ``columns`` (an
export's column mapping) apply to the tracker tables (``columns`` also to a multi-laser
head's).  Refused, with why: ``degree="auto"`` (its criteria depend on the budgets'
relative scale) and the classic strategy (it multilaterates points from tracker stations).
"""

from __future__ import annotations

import dataclasses
import logging
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError
from volcal.measurement.budget import Budget, load_budget
from volcal.measurement.datasets import DataSet, parse_data_argument
from volcal.measurement.instruments import CombinedInstrument, Instrument, get_instrument
from volcal.measurement.tables import DataWarning, Measurements, load_measurements
from volcal.model.machine import Machine
from volcal.model.spec import MachineSpec

if TYPE_CHECKING:
    from volcal.analysis.identify import IdentificationResult

log = logging.getLogger(__name__)

#: instruments whose readings the default budget (a tracker's) describes
_LENGTH_INSTRUMENTS = ("tracker", "multilaser")


def as_datasets(data: Any, instrument: str | Instrument | None = None) -> list[DataSet]:
    """The ``data`` argument of :func:`identify` as data sets: a list whose items are a
    :class:`DataSet`, an ``(instrument, table[, budget[, name]])`` tuple,
    a text ``"instrument=path"``, or a bare table (read by ``instrument``)."""
    default = instrument if instrument is not None else "tracker"
    out = []
    for k, item in enumerate(data):
        if isinstance(item, DataSet):
            out.append(item)
        elif isinstance(item, tuple) and len(item) in (2, 3, 4):
            out.append(DataSet(*item))
        elif isinstance(item, str) and not isinstance(default, Instrument):
            out.append(parse_data_argument(item, default))
        elif isinstance(item, (str, Path, pd.DataFrame)):
            out.append(DataSet(default, item))
        else:
            raise InputError(
                f"data item {k + 1}: expected a table (path or DataFrame), an (instrument, "
                f"table[, budget[, name]]) tuple or a DataSet, got {type(item).__name__}",
                source="data",
            )
    if not out:
        raise InputError("no data: expected at least one table", source="data")
    return out


@dataclass(frozen=True, eq=False)
class JoinedData:
    """Several tables as one: the joined measurements (every reading's sigma filled in),
    the combined instrument, the data set of every reading (N,) and the data sets' names
    and instrument names."""

    meas: Measurements
    instrument: CombinedInstrument
    group: np.ndarray
    names: list[str]
    instruments: list[str]
    sigma_sources: list[str]
    #: every reading's row in its own table (spreadsheet numbering, header = row 1)
    rows: np.ndarray | None = None


def join_datasets(
    model: Machine | str | Path | MachineSpec,
    datasets: Sequence[DataSet],
    budget: str | Path | Budget = "paper002",
    *,
    columns: Any = None,
) -> tuple[Machine, JoinedData]:
    """Read and validate every table with its instrument (before the model is built: a
    bad table is reported at once), weight its readings, and join them (see the module
    docstring).  Station ids must differ between tables.  ``columns``: the column mapping
    of a tracker's or multi-laser head's export (:func:`volcal.measurement.tables.
    parse_column_map`), applied to those instruments' tables (the other instruments read
    their own formats).  Returns (the machine, the joined data)."""
    from volcal.analysis.identify import reading_sigma
    from volcal.base.progress import stage as report_stage
    from volcal.model.spec import resolve_model

    spec = model.spec if isinstance(model, Machine) else resolve_model(model)
    default_budget = budget if isinstance(budget, Budget) else load_budget(budget)
    parts: list[Instrument] = []
    kinds: list[tuple[str, int]] = []
    held: dict[str, tuple[str, ...]] = {}
    frames, groups, sigma_sources, rows = [], [], [], []
    owner: dict[str, str] = {}
    seen_points: set[str] = set()
    neutral: list[tuple[float, ...]] = []
    loaded = []
    for ds in datasets:
        ins = get_instrument(ds.instrument)
        table = ins.read_table(ds.source, spec)
        with warnings.catch_warnings():
            if ins.name not in _LENGTH_INSTRUMENTS:
                # the table's warnings are about locating a tracker from its points (a
                # ballbar's circle or an interferometer's line is flat by design) and about
                # one table alone (one tool offset): not about this instrument's data
                warnings.simplefilter("ignore", DataWarning)
            meas = load_measurements(
                table,
                spec,
                name=ds.label,
                relative_lengths=not ins.positive_readings,
                columns=columns if ins.name in _LENGTH_INSTRUMENTS else None,
            )
        for sid in meas.station_ids:
            if sid in owner:
                raise InputError(
                    f"station (set-up) {sid!r} also appears in {owner[sid]}; station ids "
                    "must differ between tables (rename one)",
                    source=ds.label,
                    column="station",
                )
            owner[sid] = ds.label
        loaded.append((ds, ins, meas))
    if isinstance(model, Machine):
        machine = model
    else:
        with report_stage("building the model"):
            machine = Machine.from_model(spec)
    for i, (ds, ins, meas) in enumerate(loaded):
        if ins not in parts:
            parts.append(ins)
        k = parts.index(ins)
        kinds += [(sid, k) for sid in meas.station_ids]
        p0 = machine.nominal_points(meas.q_internal, meas.tool)
        held.update(ins.held_from_points(meas.station_ids, meas.station_index, p0))
        st0, _ = ins.start(meas.station_ids, meas.station_index, p0, meas.length)
        if len(parts) > len(neutral):
            neutral.append(tuple(float(v) for v in st0[0]))
        sigma = meas.sigma.copy()
        missing = ~np.isfinite(sigma)
        if missing.any():
            bud = ds.budget
            if bud is None and ins.name not in _LENGTH_INSTRUMENTS:
                raise InputError(
                    f"the {ins.name} readings have no sigma_mm (or sigma_um) and the table "
                    "has no budget; give either (the default budget describes a tracker)",
                    source=ds.label,
                    column="sigma_mm",
                )
            bud = default_budget if bud is None else bud
            bud = bud if isinstance(bud, Budget) else load_budget(bud)
            sigma[missing] = reading_sigma(machine, bud, meas, st0, ins)[missing]
            sigma_sources.append(f"budget {bud.name}" if missing.all() else f"table and {bud.name}")
        else:
            sigma_sources.append("table")
        t = meas.table
        points = t["point"].astype(str).to_numpy(dtype=object)
        if seen_points & set(points):  # a point id names one pose: keep the tables' apart
            points = np.array([f"{i + 1}:{q}" for q in points], dtype=object)
        seen_points |= set(points)
        frame = pd.DataFrame({"station": t["station"].to_numpy(dtype=object), "point": points})
        for a in spec.axes:
            frame[f"{a.name}_{'deg' if a.is_rotary else 'mm'}"] = t[a.name].to_numpy(float)
        for c in "xyz":
            frame[f"tool_{c}_mm"] = meas.tool[:, "xyz".index(c)]
        frame["length_mm"] = meas.length
        frame["sigma_mm"] = sigma
        frames.append(frame)
        groups.append(np.full(len(meas), i))
        rows.append(np.asarray(meas.rows, int))
    joined = pd.concat(frames, ignore_index=True)
    with warnings.catch_warnings():  # every table was checked (and warned about) alone
        warnings.simplefilter("ignore", DataWarning)
        meas = load_measurements(
            joined,
            spec,
            name="<joined tables: " + ", ".join(d.label for d in datasets) + ">",
            relative_lengths=True,
        )
    combined = CombinedInstrument(
        parts=tuple(parts),
        kinds=tuple(kinds),
        held=tuple(sorted(held.items())),
        neutral=tuple(neutral),
    )
    return machine, JoinedData(
        meas,
        combined,
        np.concatenate(groups),
        [d.label for d in datasets],
        [get_instrument(d.instrument).name for d in datasets],
        sigma_sources,
        np.concatenate(rows),
    )


def _solved(result: IdentificationResult):
    """(identifier, solver state) of a result that was just solved (both are kept then)."""
    if result.identifier is None or result.state is None:
        raise ValueError("the result carries no identifier or solver state (a loaded result?)")
    return result.identifier, result.state


def redundancy_traces(
    J: np.ndarray, cov: np.ndarray, group: np.ndarray, used: np.ndarray, n_groups: int
) -> tuple[np.ndarray, np.ndarray]:
    """Each table's redundancy number r_i = tr(R_ii) and the matrix T_ij = tr(R_ij R_ji)
    of the residual projector R = I - J cov J' of the whitened, datum-constrained
    problem (J: whitened Jacobian (N, n), cov: its constrained covariance, NaN where
    fixed; ``used``: readings in the fit).  Formed from the tables' normal matrices
    N_i = J_i' J_i (n x n, never N x N): tr(R_ii) = n_i - tr(cov N_i), T_ii = n_i -
    2 tr(cov N_i) + tr(cov N_i cov N_i), T_ij = tr(cov N_i cov N_j) (i != j)."""
    C = np.nan_to_num(cov)
    n_i = np.zeros(n_groups)
    CN = []
    for i in range(n_groups):
        Ji = J[(group == i) & used]
        n_i[i] = len(Ji)
        CN.append(C @ (Ji.T @ Ji))
    tr1 = np.array([np.trace(a) for a in CN])
    T = np.array([[np.sum(a * b.T) for b in CN] for a in CN])  # tr(A B)
    T[np.diag_indices(n_groups)] += n_i - 2.0 * tr1
    return n_i - tr1, T


def instrument_fit(result: IdentificationResult, joined: JoinedData) -> pd.DataFrame:
    """Per data set: readings, degrees of freedom (sum of the redundancy numbers of its
    readings that were not rejected), chi2/dof, its 99.9 % interval and the verdict
    (``fits``, ``too large``: the data scatter more than its budget or the model misses
    what it sees, ``too small``: the budget is pessimistic).

    The interval: with the budget right, a table's sum of squared normalised residuals
    is the quadratic form e' R S_i R e (e standard normal, S_i selecting the table) of
    mean r_i = tr(R_ii) and variance 2 T_ii (:func:`redundancy_traces`); T_ii < r_i
    where the other tables share the table's redundancy, so it is taken as a scaled
    chi2, (T_ii / r_i) chi2 with r_i^2 / T_ii degrees of freedom (``dof_check``;
    Satterthwaite's two-moment approximation, Biometrics Bulletin 2 (1946) 110-114),
    not chi2 with r_i (too wide an interval: fewer detections and fewer false alarms
    than stated).  Also returns T (``redundancy_t``) for the variance components."""
    from scipy.stats import chi2 as chi2_dist

    from volcal.analysis.covariance import constrained_covariance

    ider, state = _solved(result)
    pr = ider.problem
    m = joined.meas
    p = pr.pack_data(m.q_internal, m.tool, m.length, state.weights)
    r, J = ider.jacobian(state.x, p)
    cov = constrained_covariance(J, ider._scaled_constraints(), fixed=state.fixed)
    used = state.weights > 0
    k = len(joined.names)
    red, T = redundancy_traces(J, cov, joined.group, used, k)
    rows = []
    for i, name in enumerate(joined.names):
        sel = (joined.group == i) & used
        dof = float(red[i])
        ss = float(np.sum(r[sel] ** 2))
        chi = ss / dof if dof > 0 else float("nan")
        nu = dof**2 / T[i, i] if dof > 0 and T[i, i] > 0 else float("nan")
        lo, hi = (
            (chi2_dist.ppf(0.0005, nu) / nu, chi2_dist.ppf(0.9995, nu) / nu)
            if nu > 0
            else (float("nan"), float("nan"))
        )
        verdict = "fits" if lo <= chi <= hi else ("too large" if chi > hi else "too small")
        rows.append(
            {
                "data": name,
                "instrument": joined.instruments[i],
                "n_readings": int((joined.group == i).sum()),
                "dof": dof,
                "dof_check": nu,
                "chi2_per_dof": chi,
                "chi2_low": lo,
                "chi2_high": hi,
                "verdict": verdict,
                "sigma_source": joined.sigma_sources[i],
            }
        )
    out = pd.DataFrame(rows)
    out.attrs["redundancy_t"] = T
    return out


def identify_datasets(
    model: Machine | str | Path | MachineSpec,
    data: Sequence[Any],
    *,
    instrument: str | Instrument | None = None,
    variance_components: bool = False,
    budget: str | Path | Budget = "paper002",
    max_vce_iterations: int = 20,
    **options: Any,
) -> IdentificationResult:
    """Identify from several instruments' tables as one problem (module docstring).

    data: see :func:`as_datasets`; instrument: the instrument of bare tables;
    variance_components: estimate each instrument's budget scale factor (Helmert) and
    weight by it; the other options are :func:`volcal.analysis.identify.identify`'s
    (``robust``: per table; ``stations``, ``columns``: the tracker tables'; see the module
    docstring).  Returns the :class:`IdentificationResult` with ``instruments`` (one row
    per table: :func:`instrument_fit`, with ``chi2_per_dof_given`` and ``verdict_given``
    (the check with the budgets as given), ``scale_factor``, ``dof_vce``,
    ``u_scale_factor``, ``scale_low_95``, ``scale_high_95`` when variance components were
    estimated), a ``data`` column in its residuals and, in ``rejected``, each rejected
    reading's table (``data``) and its row there."""
    from scipy.stats import chi2 as chi2_dist

    from volcal.analysis.identify import _identify
    from volcal.base.progress import stage as report_stage
    from volcal.measurement.tables import load_stations

    stations = options.pop("stations", None)
    columns = options.pop("columns", None)
    if options.get("degree") == "auto":
        raise InputError(
            "degree 'auto' is not available with several tables: its criteria (BIC, "
            "cross-validation) weigh every reading by its budget, so with several tables "
            "the chosen orders would depend on the budgets' relative scale, which is what "
            "the variance components estimate; choose the orders on the tracker's table "
            "alone (--degree auto with that table) and give them here (--degree, --basis)",
            source="degree",
        )
    if options.get("strategy") == "classic":
        raise InputError(
            "the classic pipeline multilaterates every pose's point from the tracker's "
            "stations before fitting the errors; an interferometer or ballbar reading is not "
            "a distance from a station and has no point of its own, so it has no place in "
            "that pipeline; with several tables use joint, two-phase or points-only",
            source="strategy",
        )
    t_start = time.perf_counter()
    datasets = as_datasets(data, instrument)
    # the stations table is read and checked before the model is built, as the tables are
    st_table = None
    if stations is not None:
        st_table = load_stations(
            stations, name=None if isinstance(stations, (str, Path)) else "<stations DataFrame>"
        )
    machine, joined = join_datasets(model, datasets, budget, columns=columns)
    if st_table is not None:
        options["stations"] = _combined_stations(st_table, joined)
    if options.get("robust"):
        # each table's outliers on its own robust scale (volcal.analysis.identify)
        options["reject_groups"] = joined.group
    factor = np.ones(len(datasets))
    iterations = 0
    given = None  # each table's check against the budgets as given (the first round)
    while True:
        sigma = joined.meas.sigma * factor[joined.group]
        meas = dataclasses.replace(joined.meas, sigma=sigma)
        res = _identify(machine, meas, instrument=joined.instrument, budget=budget, **options)
        fit = instrument_fit(res, dataclasses.replace(joined, meas=meas))
        if not variance_components:
            break
        if given is None:
            given = fit[["chi2_per_dof", "verdict"]].copy()
        s2 = fit["chi2_per_dof"].to_numpy(float)
        poor = fit.loc[~(fit["dof"] > 1.0), "data"].tolist()
        if poor:
            raise InputError(
                f"{', '.join(map(str, poor))}: too few redundant readings (degrees of "
                "freedom <= 1) to estimate a variance component; identify without "
                "--variance-components or measure more",
                source="variance components",
            )
        iterations += 1
        factor = factor * np.sqrt(s2)
        log.info("variance components, round %d: scale factors %s", iterations, factor)
        if np.max(np.abs(s2 - 1.0)) < 1e-4 or iterations >= max_vce_iterations:
            break
    if variance_components:
        assert given is not None
        fit.insert(fit.columns.get_loc("verdict") + 1, "verdict_given", given["verdict"])
        fit.insert(fit.columns.get_loc("verdict"), "chi2_per_dof_given", given["chi2_per_dof"])
        # The spread of the estimates: at convergence (every table's chi2/dof 1 with the
        # scaled budgets) the covariance of the variance factors is REML's inverse
        # information, 2 T^-1 with T_ij = tr(R_ij R_ji) (Koch, Parameter Estimation and
        # Hypothesis Testing in Linear Models, 2nd ed. 1999, sec. 3.6.3; Searle, Casella
        # & McCulloch, Variance Components 1992, sec. 6.3).  A table sharing its
        # redundancy with the others has T_ii < r_i and the other components' estimates
        # in its own (off-diagonal T), so its factor is less certain than chi2 with r_i
        # says: the interval is chi2 with Satterthwaite's degrees of freedom
        # nu_i = 2 / var(s_i^2) = 1 / (T^-1)_ii (Biometrics Bulletin 2 (1946) 110-114).
        T = fit.attrs["redundancy_t"]
        try:
            nu = 1.0 / np.diag(np.linalg.inv(T))
        except np.linalg.LinAlgError:
            nu = np.full(len(factor), np.nan)
        nu = np.where(nu > 0, nu, np.nan)
        fit["scale_factor"] = factor
        fit["dof_vce"] = nu
        fit["u_scale_factor"] = factor / np.sqrt(2.0 * nu)
        fit["scale_low_95"] = factor * np.sqrt(nu / chi2_dist.ppf(0.975, nu))
        fit["scale_high_95"] = factor * np.sqrt(nu / chi2_dist.ppf(0.025, nu))
        res.notes.append(
            f"variance components (Helmert, {iterations} rounds): standard uncertainties "
            "scaled per table by "
            + ", ".join(f"{n} x{f:.3g}" for n, f in zip(joined.names, factor))
        )
        converged = iterations < max_vce_iterations
        if not converged:
            res.notes.append(f"variance components did not settle in {max_vce_iterations} rounds")
    with report_stage("what each table determines"):
        fit = fit.join(contributions(res, dataclasses.replace(joined, meas=meas)))
    res.instruments = fit
    res.seconds = time.perf_counter() - t_start  # every round of the variance components
    res.stations = _stations_by_instrument(res.stations, joined.instrument)
    res.residuals.insert(0, "data", np.asarray(joined.names, dtype=object)[joined.group])
    if len(res.rejected) and joined.rows is not None:
        # the rows of the joined table as each reading's table and its own row there
        rej = res.residuals["rejected"].to_numpy(bool)
        res.rejected = res.rejected.assign(row=joined.rows[rej])
        res.rejected.insert(0, "data", res.residuals.loc[rej, "data"].to_numpy())
    res.sigma_source = "; ".join(f"{n}: {s}" for n, s in zip(joined.names, joined.sigma_sources))
    return res


def _combined_stations(table: pd.DataFrame, joined: JoinedData) -> pd.DataFrame:
    """A tracker's stations table (:func:`volcal.measurement.tables.load_stations` form:
    start values, or known positions where ``fixed``) as the combined instrument's
    stations table: its rows whose station reads in a tracker table, the other parts'
    columns at zero (held at a tracker's station).  A station of another instrument's
    table is refused (its set-up parameters are not a position and a dead length); ids
    without readings are left out (noted by the identification as for one table)."""
    from volcal.measurement.instruments.combined import INDEX

    ins = joined.instrument
    ids = list(joined.meas.station_ids)
    trackers = [k for k, part in enumerate(ins.parts) if part.name == "tracker"]
    if not trackers:
        raise InputError(
            "the stations table gives tracker station positions, but no table is a "
            "tracker's ("
            + ", ".join(f"{n}: {i}" for n, i in zip(joined.names, joined.instruments))
            + ")",
            source="stations table",
        )
    rows = []
    for _, r in table.iterrows():
        sid = str(r["station"])
        if sid not in ids:
            continue
        k = ins.part_of(sid)
        if k not in trackers:
            first = np.flatnonzero(np.asarray(joined.meas.station_index) == ids.index(sid))[0]
            owner = joined.names[int(joined.group[first])]
            raise InputError(
                f"station {sid!r} of the stations table is a set-up of {owner} "
                f"({ins.parts[k].name}); the stations table gives tracker stations only",
                source="stations table",
                column="station",
            )
        row = {"station": sid, INDEX: float(k)}
        for n in ins.station_param_names[1:]:
            row[n] = float(r[n]) if n in ins.parts[k].station_param_names else 0.0
        row["fixed"] = bool(r["fixed"])
        rows.append(row)
    if not rows:
        tracker_ids = [s for s in ids if ins.part_of(s) in trackers]
        raise InputError(
            "no tracker station of the data ("
            + ", ".join(tracker_ids[:8])
            + ") is described in the stations table ("
            + ", ".join(map(str, table["station"][:8]))
            + "); station ids must match exactly",
            source="stations table",
        )
    return pd.DataFrame(rows, columns=["station", *ins.station_param_names, "fixed"])


def _stations_by_instrument(st: pd.DataFrame, ins: CombinedInstrument) -> pd.DataFrame:
    """The stations table with an ``instrument`` column instead of the index, and the
    parameters a station's instrument does not have (and their uncertainties) empty."""
    from volcal.measurement.instruments.combined import INDEX

    st = st.copy()
    kinds = [ins.part_of(s) for s in st["station"]]
    st.insert(1, "instrument", [ins.parts[k].name for k in kinds])
    ucols = [c for c in st.columns if c.startswith("u_")]
    for n in ins.station_param_names[1:]:
        unit = ins._unit(n)
        base = n[: -len(unit) - 1] if n.endswith("_" + unit) else n
        ucol = next((c for c in ucols if c == f"u_{base}" or c.startswith(f"u_{base}_")), None)
        absent = np.array([n not in ins.parts[k].station_param_names for k in kinds])
        st.loc[absent, n] = np.nan
        if ucol is not None:
            st.loc[absent, ucol] = np.nan
    return st.drop(columns=[c for c in (INDEX, f"u_{INDEX}") if c in st.columns])


def contributions(result: IdentificationResult, joined: JoinedData) -> pd.DataFrame:
    """What each table contributes, at the solution and with the datum in force: the
    error parameters it determines alone (``determined_alone``, and by name those it
    leaves undetermined, ``undetermined_alone``), and the field uncertainty with the
    tables up to it (``field_u_cumulative_um``: RMS over the measured poses of the
    standard uncertainty |u| of the volumetric error, um; NaN while parameters are
    undetermined).  Another table's readings are dropped by a zero weight and its set-up
    parameters held."""
    from volcal.analysis.covariance import constrained_covariance
    from volcal.analysis.identify import field_jacobian

    ider, state = _solved(result)
    pr = ider.problem
    m = joined.meas
    nt = pr.n_theta
    nps = pr.instrument.n_station_params
    station_of = np.asarray(m.station_index, int)
    own = [np.unique(station_of[joined.group == i]) for i in range(len(joined.names))]
    _, first = pr.layout.poses
    _, _, G = field_jacobian(
        result.machine, result.error_model, result.theta, m.q_internal[first], m.tool[first]
    )
    names = np.asarray(result.error_model.param_names)
    rows = []
    for i in range(len(joined.names)):
        out: dict[str, Any] = {}
        for label, tables in (("alone", [i]), ("cumulative", list(range(i + 1)))):
            keep = np.isin(joined.group, tables)
            p = pr.pack_data(m.q_internal, m.tool, m.length, np.where(keep, state.weights, 0.0))
            fixed = state.fixed.copy()
            for k in range(len(joined.names)):
                if k not in tables:
                    for st in own[k]:
                        fixed[nt + nps * st : nt + nps * (st + 1)] = True
            # global (frame) parameters of an instrument without readings here: held
            used = {joined.instruments[k] for k in tables}
            for j, g in enumerate(pr.instrument.global_param_names):
                if g.split(".")[0] not in used:
                    fixed[pr.n_x - pr.instrument.n_global_params + j] = True
            ident = ider.analyse(state.x, p, fixed)
            undetermined = np.asarray(ident.unidentifiable[:nt], bool)
            if label == "alone":
                out["determined_alone"] = int((~undetermined).sum())
                out["undetermined_alone"] = " ".join(names[undetermined])
            else:
                u = float("nan")
                if not undetermined.any():
                    fixed[list(ident.pivots)] = True
                    _, J = ider.jacobian(state.x, p)
                    cov = constrained_covariance(J, ider._scaled_constraints(), fixed=fixed)
                    C = np.nan_to_num(cov[:nt, :nt]) * np.outer(pr.scale[:nt], pr.scale[:nt])
                    var = np.einsum("nij,jk,nik->n", G, C, G)
                    u = float(np.sqrt(np.mean(var))) * 1e3
                out["field_u_cumulative_um"] = u
        rows.append(out)
    return pd.DataFrame(rows)
