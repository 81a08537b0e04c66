"""Identification: from a machine model and length readings to its geometric errors.

:class:`Identifier` holds what depends only on the model and the layout of the data (the
NLP, the IPOPT solver, the error model): build it once, then :meth:`Identifier.run` any
number of data sets of that layout (Monte Carlo, studies).  :func:`identify` is the
one-call front end used by the CLI.

Strategies (all on the same problem and solver, differing only in which variables are
free and which constraints are active):

``joint``       error parameters, stations, dead lengths together (one-step);
``two-phase``   stations and dead lengths on nominal points first (errors held at zero),
                then the errors with the stations fixed; a rigid motion of the station set
                is free in phase two so that the frame mismatch of phase one is absorbed;
``points-only`` stations fixed at known positions (stations table) or at the analytical
                linear solution (paper 002 eq. 12-20), only errors (+ frame motion) solved;
``classic``     the calibrate -> multilaterate -> fit pipeline of :mod:`volcal.analysis.classic`.

Unidentifiable directions are found from the Jacobian at the start point (names in
:attr:`IdentificationResult.identifiability`), held at zero, and reported; their standard
uncertainties are NaN and ``identifiable`` is False in the parameter table.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.analysis import (
    FieldNullSpace,
    Identifiability,
    analyse_jacobian,
    constrained_covariance,
    field_null_space,
    split_gauge,
)
from volcal.analysis.covariance import gram_covariance
from volcal.analysis.identifiability import FieldSets, rigid_columns
from volcal.base.exceptions import InputError, SolverError
from volcal.base.linalg import unique_rows
from volcal.base.memory import check_memory
from volcal.base.progress import stage as report_stage
from volcal.base.units import report_factors, report_unit
from volcal.measurement.budget import Budget, load_budget
from volcal.measurement.instruments import Instrument, get_instrument
from volcal.measurement.tables import (
    Measurements,
    load_instrument_stations,
    load_measurements,
    load_stations,
)
from volcal.model.datum import (
    condition_table,
    imposed_parameters,
    null_space,
    select_conditions,
)
from volcal.model.errors import Datum, ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.model.spec import MachineSpec, resolve_model
from volcal.problem.residuals import DenseJacobian, IdentificationProblem, Layout
from volcal.problem.strategies import (
    ClassicPipeline,
    PhasedStrategy,
    Strategy,
    get_strategy,
    strategies,
)
from volcal.solve.gauss_newton import GaussNewtonSolver, polish
from volcal.solve.ipopt import NLPSolver
from volcal.solve.outcome import SolveOutcome

log = logging.getLogger(__name__)

STRATEGIES: tuple[str, ...] = tuple(strategies())
SOLVERS: tuple[str, ...] = ("auto", "ipopt", "gauss-newton")
#: ``solver="auto"``: IPOPT below this many readings, Gauss-Newton on the chunked
#: evaluation from it.  IPOPT needs the CasADi graph of every reading (about 3.4 kB a
#: reading to build and hold); the chunked Gauss-Newton path needs none.  Measured whole
#: processes (`volcal identify --no-plots`, paired runs): equal at 2,976 readings
#: (1.96-2.15 s IPOPT, 2.04-2.67 s Gauss-Newton), Gauss-Newton faster from 10,296
#: (2.28-3.14 s against 3.11-3.30 s, 160 against 198 MB)
AUTO_GAUSS_NEWTON_READINGS = 10_000


def resolve_solver(solver: str, n_readings: int) -> str:
    """The solver that runs: ``solver`` itself, or for ``"auto"`` IPOPT below
    :data:`AUTO_GAUSS_NEWTON_READINGS` readings and Gauss-Newton from there."""
    if solver not in SOLVERS:
        raise InputError(f"unknown solver {solver!r}; expected one of {', '.join(SOLVERS)}")
    if solver != "auto":
        return solver
    return "gauss-newton" if n_readings >= AUTO_GAUSS_NEWTON_READINGS else "ipopt"


@dataclass(frozen=True)
class Solved:
    """What a single fit knows once its solve has ended, before its uncertainty stage
    (``on_solved`` of :func:`_identify`): the machine, the error model, the error
    parameters ``theta`` (the model's units) and the residuals: a table of every
    reading's ``station``, ``residual_um``, ``normalised_residual`` (residual / sigma) and
    ``rejected``, the values of those columns of the result's residual table (which is
    made after the uncertainty stage, not to hold a copy of the whole measurement table
    through it).  A caller draws the figures that need no covariance from it while the
    covariance is computed (``volcal identify``: the residual and volumetric plots)."""

    machine: Machine
    error_model: ErrorModel
    theta: np.ndarray
    residuals: pd.DataFrame


@dataclass
class SolverState:
    """What downstream steps (analyze, Monte Carlo, predict, the C export) need to continue
    from an identification without rebuilding guesses: the unknowns x (physical units, the
    order of :class:`~volcal.problem.residuals.IdentificationProblem`), the held variables,
    the weights 1/sigma of every reading (0: rejected), the datum conditions in force, the
    solver and instrument names, and the fingerprint of the problem they belong to."""

    x: np.ndarray
    fixed: np.ndarray
    weights: np.ndarray
    datum_active: np.ndarray
    names: list[str]
    solver: str
    instrument: str
    fingerprint: str

    def matches(self, problem: IdentificationProblem) -> bool:
        """Does this state belong to ``problem`` (same structure)?"""
        return self.fingerprint == problem.fingerprint()


@dataclass(repr=False)
class IdentificationResult:
    """Everything an identification produced (values in mm / rad unless a name says)."""

    machine: Machine
    error_model: ErrorModel
    strategy: str
    theta: np.ndarray
    cov_theta: np.ndarray
    identifiable: np.ndarray
    stations: pd.DataFrame
    frame: np.ndarray
    residuals: pd.DataFrame
    identifiability: Identifiability | None
    outcomes: list[SolveOutcome]
    conditions: dict[str, float]
    rejected: pd.DataFrame
    seconds: float
    sigma_source: str
    notes: list[str] = field(default_factory=list)
    #: every candidate datum condition, whether it was imposed, and its value (um / urad)
    datum: pd.DataFrame | None = None
    #: how the null directions of the data act on the volumetric error (see ``predict``)
    null_space: FieldNullSpace | None = None
    #: the solver state (unknowns, held set, weights, datum, fingerprint)
    state: SolverState | None = None
    #: the :class:`Identifier` that solved it (problem and solvers), for analyses of the
    #: same data that would otherwise build it again (Monte Carlo); not pickled
    identifier: Identifier | None = field(default=None, repr=False, compare=False)
    #: parameters the imposed datum conditions alone set to zero (a convention, not a
    #: measurement: u = 0); None: none known
    imposed: np.ndarray | None = field(default=None, repr=False)
    #: several instruments' tables (:mod:`volcal.analysis.fusion`): one row per table
    #: with its readings, degrees of freedom, chi2/dof and verdict (and its variance
    #: component when estimated); None for a single table
    instruments: pd.DataFrame | None = None

    def __getstate__(self):
        d = dict(self.__dict__)
        d["identifier"] = None
        return d

    def __repr__(self) -> str:
        n = int(len(self.residuals))
        return (
            f"IdentificationResult({self.machine.spec.name}, {self.strategy}, {n} readings: "
            f"{self.status}, residual RMS {self.residual_rms_um:.3g} um, chi2/dof "
            f"{self.conditions.get('chi2_per_dof', float('nan')):.3g}, "
            f"{int((~np.asarray(self.identifiable)).sum())} unidentifiable)"
        )

    def _repr_html_(self) -> str:
        """A summary for Jupyter: status, fit, adequacy, unidentifiable, largest values."""
        from html import escape

        adq = self.adequacy
        colour = "#1a7f37" if adq.adequate else "#b42318"
        par = self.parameters()
        top = par.reindex(par["value"].abs().sort_values(ascending=False).index).head(8)
        rows = "".join(
            f"<tr><td>{escape(str(r['name']))}</td><td>{r['value']:.6g}</td>"
            f"<td>{escape(str(r['unit']))}</td><td>{r['u']:.3g}</td></tr>"
            for _, r in top.iterrows()
        )
        un = [n for n, ok in zip(self.error_model.param_names, self.identifiable) if not ok]
        return (
            f"<b>Identification of {escape(self.machine.spec.name)}</b> ({escape(self.strategy)}"
            f", {len(self.residuals)} readings, {self.seconds:.1f} s)<br>"
            f"solver: {escape(self.status)}<br>residual RMS {self.residual_rms_um:.3g} um; "
            f"<span style='color:{colour}'>{escape(adq.message)}</span><br>"
            f"unidentifiable: {escape(', '.join(un) or 'none')}"
            f"<table><tr><th>largest parameters</th><th>value</th><th>unit</th><th>u</th></tr>"
            f"{rows}</table>"
        )

    @property
    def success(self) -> bool:
        return all(o.success for o in self.outcomes)

    @property
    def status(self) -> str:
        return "; ".join(o.status for o in self.outcomes)

    @property
    def adequacy(self):
        """Does the model fit the data? chi2/dof against its 99.9 % interval and, when
        outside, the likely cause (:func:`volcal.analysis.adequacy.assess`)."""
        from volcal.analysis.adequacy import assess

        return assess(self)

    def unidentifiable_explanation(self) -> dict[str, Any] | None:
        """Why parameters are left out and what to measure, when the data explain it:
        ``{"cause", "parameters", "text"}`` (None when every parameter is identifiable or
        no cause is known).

        Known cause: a single tool offset.  Lengths to one reflector position see an
        angular error of the tool-side axes only through that offset's lever arm, so
        rotations and translations that move the one point alike cannot be told apart;
        more offsets (not on one line) or more spindle orientations separate them."""
        names = [n for n, ok in zip(self.error_model.param_names, self.identifiable) if not ok]
        if not names:
            return None
        res = self.residuals
        cols = [c for c in ("tool_x", "tool_y", "tool_z") if c in res.columns]
        used = ~np.asarray(res["rejected"], bool) if "rejected" in res else slice(None)
        tools = np.unique(res.loc[used, cols].to_numpy(float), axis=0) if cols else np.zeros((1, 3))
        if len(tools) != 1:
            return None
        errors = sorted({n.split("_")[0].split("@")[0] for n in names})
        # the cause holds only when angular error motions (EA*, EB*, EC* of an axis, not
        # location errors) are among those left out: other gaps (one station, too few
        # positions for a degree) have other causes, which this does not name
        if not any(re.fullmatch(r"E[ABC][A-Z]", e) for e in errors):
            return None
        t = ", ".join(f"{v:g}" for v in tools[0])
        return {
            "cause": "single_tool_offset",
            "parameters": names,
            "text": (
                f"every reading has the same tool offset ({t}) mm: lengths to one reflector "
                "position see an angular error of the tool-side axes only through that "
                "offset's lever arm, so rotations and translations that move the one point "
                f"alike cannot be told apart. Left out: {len(names)} parameter(s) of "
                f"{', '.join(errors)} ({', '.join(names)}). To determine them, measure at "
                "three or more tool offsets not on one line (e.g. 0,0,0; 0,0,100; 80,0,60 "
                "mm: `volcal simulate --tools`, `volcal plan --tools`) or, on a machine with a "
                "swivelling head, in more spindle orientations"
            ),
        }

    @property
    def residual_rms_um(self) -> float:
        r = self.residuals.loc[~self.residuals["rejected"], "residual_um"]
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")

    def parameters(self) -> pd.DataFrame:
        """name, value, unit, u (standard uncertainty), identifiable, imposed (values and u
        in um / urad; imposed: set to zero by the datum, a convention with u = 0, not a
        measurement)."""
        units = self.error_model.param_units
        f = report_factors(units)
        std = np.sqrt(np.clip(np.diag(self.cov_theta), 0, None)) * f
        std[~self.identifiable] = np.nan
        return pd.DataFrame(
            {
                "name": self.error_model.param_names,
                "value": self.theta * f,
                "unit": [report_unit(u) for u in units],
                "u": std,
                "identifiable": self.identifiable,
                "imposed": (
                    np.zeros(len(self.theta), bool)
                    if self.imposed is None
                    else np.asarray(self.imposed, bool)
                ),
            }
        )

    def predict(
        self,
        q_internal: np.ndarray,
        tool: np.ndarray | None = None,
        *,
        with_uncertainty: bool = True,
    ) -> pd.DataFrame:
        """Volumetric error (um) at poses q (N, n_axes; mm, rad) with tool offsets (N, 3)."""
        return predict_volumetric(
            self.machine,
            self.error_model,
            self.theta,
            self.cov_theta if with_uncertainty else None,
            q_internal,
            tool,
            null_space=self.null_space,
        )


def field_jacobian(
    machine: Machine,
    em: ErrorModel,
    theta: np.ndarray,
    q: np.ndarray,
    tool: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(nominal points (N, 3) mm, volumetric errors (N, 3) mm, G (N, 3, n_params) their
    derivative wrt the error parameters) of the first-order model at poses q (N, n_axes;
    mm, rad) and tool offsets (N, 3) mm."""
    q = np.atleast_2d(np.asarray(q, float))
    tool = np.zeros((len(q), 3)) if tool is None else np.broadcast_to(tool, (len(q), 3))
    e = em.values(q, theta)
    p0, dp, Je = machine.evaluate(q, tool, e)
    return p0, dp, em.apply_basis(Je, q)  # (N, 3, n_errors) @ (N, n_errors, n_params)


def predict_volumetric(
    machine: Machine,
    em: ErrorModel,
    theta: np.ndarray,
    cov_theta: np.ndarray | None,
    q: np.ndarray,
    tool: np.ndarray | None = None,
    *,
    null_space: FieldNullSpace | None = None,
) -> pd.DataFrame:
    """dx_um, dy_um, dz_um (and u_dx_um ... standard uncertainties when a covariance is
    given) of the first-order model at poses q (N, n_axes; mm, rad) and tools (N, 3) mm.

    With the fit's ``null_space``, a column ``determined`` says per pose whether its error
    follows from the data (up to the rigid motion no multilateration sees); where it does
    not (it depends on a combination the data cannot see, e.g. at a tool offset far from
    those measured), the value is the datum's choice and the uncertainties are NaN."""
    p0, dp, G = field_jacobian(machine, em, theta, q, tool)
    out = pd.DataFrame(dp * 1e3, columns=["dx_um", "dy_um", "dz_um"])
    det = null_space.determined(G, p0) if null_space is not None else np.ones(len(out), bool)
    if cov_theta is not None:
        # held variables (NaN rows) contribute nothing where the pose is determined: their
        # value is a convention there; elsewhere the uncertainty is unknown, never zero
        cov = np.nan_to_num(cov_theta)
        var = np.sum((G @ cov) * G, axis=2)
        u = np.sqrt(np.clip(var, 0, None)) * 1e3
        u[~det] = np.nan
        out[["u_dx_um", "u_dy_um", "u_dz_um"]] = u
    if null_space is not None:
        out["determined"] = det
    return out


def _halton(n: int, d: int) -> np.ndarray:
    """The first n points (after 0) of the d-dimensional Halton sequence in [0, 1)^d (radical
    inverses in the first d primes): deterministic and low-discrepancy."""
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71]
    if d > len(primes):
        raise ValueError(f"at most {len(primes)} dimensions")
    out = np.zeros((n, d))
    idx = np.arange(1, n + 1)
    for j in range(d):
        b, k, f = primes[j], idx.copy(), np.ones(n)
        while np.any(k > 0):
            f /= b
            out[:, j] += f * (k % b)
            k //= b
    return out


def declared_poses(spec: MachineSpec, n_poses: int = 256) -> np.ndarray:
    """Poses (N, n_axes; mm, rad) spanning the declared travel of every axis: the corners of
    the travel box (up to 64) and a Halton sequence inside it.  A low-discrepancy sequence
    rather than a grid, so that it never aliases with a regular measurement plan (a grid of
    4 angles over a full turn sees sin(t) - sin(2t) as zero, a Halton sample does not)."""
    n_ax = len(spec.axes)
    lo = np.array([np.deg2rad(a.travel[0]) if a.is_rotary else a.travel[0] for a in spec.axes])
    hi = np.array([np.deg2rad(a.travel[1]) if a.is_rotary else a.travel[1] for a in spec.axes])
    u = _halton(n_poses, n_ax)
    if n_ax <= 6:
        u = np.vstack([np.array(list(np.ndindex(*([2] * n_ax))), float), u])
    return lo + u * (hi - lo)


def field_sets(
    machine: Machine, em: ErrorModel, theta: np.ndarray, q_meas: np.ndarray, tools_meas: np.ndarray
) -> FieldSets:
    """The measured set (the data's poses and tool offsets) and the declared set (a Halton
    sample of the travel at every measured tool offset) with their nominal points (mm) and
    d(volumetric error)/d(theta) (see :class:`volcal.analysis.identifiability.FieldSets`)."""
    q = declared_poses(machine.spec)
    tools = np.unique(np.atleast_2d(np.asarray(tools_meas, float)), axis=0)
    Q = np.repeat(q, len(tools), axis=0)
    T = np.tile(tools, (len(q), 1))
    p_d, _, G_d = field_jacobian(machine, em, theta, Q, T)
    p_m, _, G_m = field_jacobian(machine, em, theta, q_meas, tools_meas)
    return FieldSets(G_m, p_m, G_d, p_d)


def rigid_fit(points: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best-fit small rigid motion (a, w) with d ~ a + w x points, least squares.
    Returns (params (6,), residual d - fit). Multilateration cannot see this motion."""
    A = rigid_columns(points)
    d = np.asarray(d, float).ravel()
    sol = np.linalg.lstsq(A, d, rcond=None)[0]
    return sol, (d - A @ sol).reshape(-1, 3)


# ---------------------------------------------------------------------------------------


class Identifier:
    """Model + error model + layout -> a reusable solver (see the module docstring)."""

    def __init__(
        self,
        machine: Machine,
        error_model: ErrorModel,
        layout: Layout,
        *,
        exact: bool = False,
        hessian: str = "gauss-newton",
        verbose: bool = False,
        datum_mode: str = "minimal",
        instrument: str | Instrument | None = None,
        solver: str = "ipopt",
    ):
        self.machine = machine
        self.error_model = error_model
        if datum_mode not in ("minimal", "impose-all"):
            raise InputError(f"datum_mode must be 'minimal' or 'impose-all', got {datum_mode!r}")
        #: "minimal": impose only candidate conditions that remove a null direction;
        #: "impose-all": every ISO 230 condition (comparison only, see select_datum)
        self.datum_mode = datum_mode
        self.instrument = get_instrument(instrument)
        self.layout = layout
        t0 = time.perf_counter()
        self.problem = IdentificationProblem(
            machine, error_model, self.instrument, layout, exact=exact
        )
        solver = resolve_solver(solver, layout.n_readings)
        #: "ipopt" (default): IPOPT then a few Gauss-Newton polish steps; "gauss-newton":
        #: Levenberg-Marquardt with the datum eliminated on the chunked evaluation
        #: (volcal.solve.gauss_newton; the whole-problem graph is then never built);
        #: "auto" is resolved here (:func:`resolve_solver`)
        self.solver_name = solver
        self.gauss_newton = GaussNewtonSolver(self.problem)
        self._hessian, self._verbose = hessian, verbose
        #: the solver of :meth:`run`; None once released (:meth:`release_graph`): built
        #: again for the next solve
        self.solver: NLPSolver | GaussNewtonSolver | None = (
            self._ipopt() if solver == "ipopt" else self.gauss_newton
        )
        self.build_seconds = time.perf_counter() - t0
        n = self.problem.n_x
        nt, ss = self.problem.n_theta, self.problem.station_slice()
        self.is_theta = np.zeros(n, bool)
        self.is_theta[:nt] = True
        self.is_station = np.zeros(n, bool)
        self.is_station[ss] = True
        self.is_frame = ~(self.is_theta | self.is_station)
        # which variable to hold when a direction is unidentifiable: the frame motion first
        # (it duplicates the stations), then error parameters, highest polynomial order
        # first (holding it keeps the identified curves smooth), stations last
        order = np.zeros(n)
        for k in range(len(error_model.param_names)):
            order[k] = error_model.param_order[k]  # Legendre degree / harmonic number
        self.prefer = np.where(self.is_frame, 4.0, np.where(self.is_theta, 1.0 + 0.1 * order, 0.0))

    def station_fixed(self, station_fixed: np.ndarray) -> np.ndarray:
        """The mask over x of the held station parameters: every parameter of the stations
        where ``station_fixed`` (K,) is True, and those the instrument's own convention
        holds (e.g. the frame of a multi-laser head)."""
        pr, ins = self.problem, self.instrument
        nps = ins.n_station_params
        fixed = np.zeros(pr.n_x, bool)
        ids = self.layout.station_ids or tuple(f"station{k}" for k in range(self.layout.n_stations))
        for k, sid in enumerate(ids):
            base = pr.n_theta + nps * k
            if k < len(station_fixed) and station_fixed[k]:
                fixed[base : base + nps] = True
            for name in ins.held_station_params(sid):
                fixed[base + ins.station_param_names.index(name)] = True
        return fixed

    # ---- pieces ---------------------------------------------------------------------
    def jacobian(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals and the dense Jacobian (N, n_x) wrt the scaled variables at
        physical x, for analyses that need J's rows (``volcal analyze``).  The last two
        evaluations are kept (that command asks for the structural point and x in turn);
        identify, the datum, covariance and identifiability use :meth:`factor`, which
        never holds J."""
        key = self._key(x, p)
        cache: dict = self.__dict__.setdefault("_jac_cache", {})
        if key not in cache:
            r, J = self._dense_jacobian()(self.problem.to_scaled(x), p)
            r = r.ravel()
            r.flags.writeable = J.flags.writeable = False  # shared: read-only
            if len(cache) >= 2:
                cache.pop(next(iter(cache)))
            cache[key] = (r, J)
        return cache[key]

    def factor(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, int]:
        """(R, m): the R factor (n_x, n_x) of the Jacobian wrt the scaled variables at
        physical x (``J = Q R``) and J's number of rows m.  R carries all that the datum
        selection, null space, identifiability and covariance take from J (its J^T J, with
        J's conditioning), and is computed in blocks of readings without forming J
        (:meth:`volcal.problem.chunked.ChunkedEvaluator.r_factor`): one evaluation per
        point, shared by all of them (a few n_x^2 arrays are kept, not N n_x ones)."""
        key = self._key(x, p)
        cache: dict = self.__dict__.setdefault("_r_cache", {})
        if key not in cache:
            dense = self.__dict__.get("_jac_cache", {}).get(key)
            if dense is not None:  # already evaluated densely: its R, no second evaluation
                from volcal.analysis.identifiability import _r_factor

                R = _r_factor(np.array(dense[1]))
            else:  # in chunks of poses, without J or the whole-problem graph
                R = self.problem.chunked.r_factor(self.problem.to_scaled(x), p)[1]
            R.flags.writeable = False  # shared: read-only
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[key] = (R, self.layout.n_readings)
        return cache[key]

    @staticmethod
    def _key(x: np.ndarray, p: np.ndarray) -> tuple[bytes, bytes]:
        return (np.asarray(x, float).tobytes(), np.asarray(p, float).tobytes())

    def _dense_jacobian(self) -> DenseJacobian:
        if getattr(self, "_jac_call", None) is None:
            self._jac_call = DenseJacobian(self.problem)
        return self._jac_call

    def structural(self, x: np.ndarray) -> np.ndarray:
        """x (physical) with the error parameters at zero: where gauge, datum and
        identifiability are decided.  There the first-order model's gauge (a rigid motion
        of the point cloud expressed through the error parameters) is exact; at non-zero
        errors it is broken by second-order terms, which turn null directions into
        directions with singular values near 1e-6 that a rank tolerance near 1e-13 counts as
        determined (and the datum then leaves free).  Deciding here makes the decision the
        same whatever the linearisation point (analyze, identify, mc, plan)."""
        x0 = np.array(x, float)
        x0[: self.problem.n_theta] = 0.0
        return x0

    def analyse(
        self, x: np.ndarray, p: np.ndarray, fixed: np.ndarray, constrained: bool = True
    ) -> Identifiability:
        """Identifiability at x (physical): rank, null space and pivots decided at the
        structural point (:meth:`structural`), singular values, condition numbers and weak
        directions of the identifiable part at x."""
        R, m = self.factor(x, p)
        R0, _ = self.factor(self.structural(x), p)
        C = self._scaled_constraints() if constrained else None
        return analyse_jacobian(
            R, self.problem.names, C, fixed=fixed, prefer=self.prefer, decide_on=R0, n_rows=m
        )

    def select_datum(self, x: np.ndarray, p: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """Put in force the candidate datum conditions that remove a null direction of the
        Jacobian at the structural point of x (physical; :meth:`structural`) with ``fixed``
        held (:func:`volcal.model.datum.select_conditions`); returns the mask over the
        candidates."""
        pr = self.problem
        Call = np.zeros((pr.C_all.shape[0], pr.n_x))
        Call[:, : pr.n_theta] = pr.C_all * pr.scale[None, : pr.n_theta]
        if Call.shape[0] == 0:
            pr.set_datum(np.zeros(0, bool))
            return pr.datum_active
        if self.datum_mode == "impose-all":
            # every ISO 230 condition on the component error motions plus the tool's zero
            # position and orientation held at zero, dependent rows dropped: what an
            # ISO 230 datum imposed regardless of the data does (kept for comparison,
            # studies/datum; it can constrain what the data determine)
            from volcal.model.errors import _independent_rows

            keep = np.array([c.klass != "location" for c in pr.conditions])
            rows = np.flatnonzero(keep)
            act = np.zeros(len(keep), bool)
            act[rows[_independent_rows(pr.C_all[rows])]] = True
            pr.set_datum(act)
            return pr.datum_active
        R, m = self.factor(self.structural(x), p)
        pr.set_datum(select_conditions(R, Call, fixed, n_rows=m))
        return pr.datum_active

    def field_null_space(
        self,
        x: np.ndarray,
        p: np.ndarray,
        fixed: np.ndarray,
        q_meas: np.ndarray,
        tools_meas: np.ndarray,
    ) -> tuple[FieldNullSpace, FieldSets]:
        """How the null directions of the full Jacobian (no datum; ``fixed`` held) act on
        the volumetric error.

        The null space is taken at the structural point of x (:meth:`structural`), as
        every other decision of gauge and datum.  The measured set is the data's distinct
        (pose, tool offset) pairs q_meas (N, n_axes; mm, rad), tools_meas (N, 3) mm; the
        declared set a Halton sample of the travel of every axis at each measured tool
        offset."""
        pr = self.problem
        nt = pr.n_theta
        R, m = self.factor(self.structural(x), p)
        free, d, N = null_space(R, fixed, n_rows=m)
        dirs = np.zeros((pr.n_x, N.shape[1]))
        dirs[free] = N * d[:, None]
        theta_dirs = dirs[:nt] * pr.scale[:nt, None]
        sets = field_sets(self.machine, self.error_model, x[:nt], q_meas, tools_meas)
        return field_null_space(theta_dirs, sets), sets

    def _ipopt(self) -> NLPSolver:
        return NLPSolver(self.problem, hessian=self._hessian, verbose=self._verbose)

    def release_graph(self) -> None:
        """Free the IPOPT solver and the CasADi graph of every reading it solves on (about
        3.4 kB a reading: 3 MiB of the peak of a 960-reading run, 133 MiB) when no solve is
        to come: the command line does once its fit has converged, before the uncertainty
        stage (which evaluates the problem in chunks, or takes a Jacobian evaluated
        already).  A later solve or whole-graph Function builds them again (the same
        numbers)."""
        if self.solver is not self.gauss_newton:
            self.solver = None
        self.problem.release_graph()

    def _scaled_constraints(self) -> np.ndarray:
        pr = self.problem
        C = np.zeros((pr.C.shape[0], pr.n_x))
        C[:, : pr.n_theta] = pr.C * pr.scale[None, : pr.n_theta]
        return C

    def covariance(self, x: np.ndarray, p: np.ndarray, fixed: np.ndarray) -> np.ndarray:
        """Linearised covariance of x (physical units) under the datum constraints, with
        fixed variables NaN.

        At the answer of a Gauss-Newton solve (or IPOPT's polish) the solver's last
        iteration has evaluated J^T J there; while the reduced system is well conditioned
        the covariance is taken from it (:func:`volcal.analysis.covariance.gram_covariance`)
        instead of from an R factor, which costs a second pass over the readings."""
        cov_s = None
        final = self.gauss_newton.final_gram
        if final is not None and final.matches(x, p):
            cov_s = gram_covariance(final.H, self._scaled_constraints(), fixed=fixed)
        if cov_s is None:
            R, m = self.factor(x, p)
            cov_s = constrained_covariance(R, self._scaled_constraints(), fixed=fixed, n_rows=m)
        s = self.problem.scale
        return cov_s * s[:, None] * s[None, :]

    # ---- strategies -----------------------------------------------------------------
    def group_mask(self, groups) -> np.ndarray:
        """The mask over x of variable groups (``"errors"``, ``"stations"``, ``"frame"``)."""
        masks = {"errors": self.is_theta, "stations": self.is_station, "frame": self.is_frame}
        out = np.zeros(self.problem.n_x, bool)
        for g in groups:
            out |= masks[g]
        return out

    def run(
        self,
        strategy: str | Strategy | StrategyPlan,
        x0: np.ndarray,
        p: np.ndarray,
        *,
        user_fixed: np.ndarray | None = None,
        solve: bool = True,
    ) -> tuple[np.ndarray, list[SolveOutcome], np.ndarray, Identifiability]:
        """Solve with a strategy (:mod:`volcal.problem.strategies`) from x0 (physical), phase
        by phase on the one problem and solver.  Returns (x, outcomes, held mask of the last
        phase, identifiability of the last phase that analysed it).

        ``strategy`` may be a :class:`StrategyPlan` from :meth:`plan`: its decisions (datum,
        held pivots) are then taken as they are, with no analysis of the data at hand, and
        the identifiability returned is the plan's; ``user_fixed`` is then the plan's (a
        different one is refused)."""
        x, outcomes, plan = self._run(strategy, x0, p, user_fixed, solve)
        return x, outcomes, plan.held[-1] if plan.held else plan.user_fixed, plan.identifiability

    def plan(
        self,
        strategy: str | Strategy,
        x0: np.ndarray,
        p: np.ndarray,
        *,
        user_fixed: np.ndarray | None = None,
        solve: bool = True,
    ) -> StrategyPlan:
        """The decisions :meth:`run` takes for a strategy, from x0 (physical units) and
        data p, kept for reuse: per phase the datum conditions in force and the held
        variables (the user's, the phase's groups and one pivot per null direction).

        Gauge, datum and pivots are decided at the structural point (:meth:`structural`)
        from the layout, the weights and the held set, not from the readings, so a Monte
        Carlo over one layout (new readings, new start values) decides them once, here,
        and solves every trial with ``run(plan, x0, p)``: the same answers as ``run``
        without the analyses (two R factors and an SVD per phase).  ``solve=False``
        decides every phase at x0 instead of at the previous phase's answer (the
        structural point of a phase depends on the station and frame values only)."""
        return self._run(strategy, x0, p, user_fixed, solve)[2]

    def _run(
        self,
        strategy: str | Strategy | StrategyPlan,
        x0: np.ndarray,
        p: np.ndarray,
        user_fixed: np.ndarray | None,
        solve: bool,
    ) -> tuple[np.ndarray, list[SolveOutcome], StrategyPlan]:
        given = strategy if isinstance(strategy, StrategyPlan) else None
        strat = strategy.strategy if isinstance(strategy, StrategyPlan) else get_strategy(strategy)
        if not isinstance(strat, PhasedStrategy):
            raise InputError(
                f"the {strat.name} strategy does not solve the joint problem; "
                "run it through identify()"
            )
        n = self.problem.n_x
        if given is not None:
            if given.user_fixed.shape != (n,):
                raise InputError(
                    f"the plan was made for {given.user_fixed.shape[0]} variables, "
                    f"this problem has {n}"
                )
            if user_fixed is not None and not np.array_equal(user_fixed, given.user_fixed):
                raise InputError("user_fixed differs from the one the plan was made with")
            user_fixed = given.user_fixed
        user_fixed = np.zeros(n, bool) if user_fixed is None else np.asarray(user_fixed, bool)
        outcomes: list[SolveOutcome] = []

        def step(x, fixed) -> SolveOutcome:
            if solve:
                if self.solver is None:  # released after an earlier solve: built again
                    self.solver = self._ipopt()
                out = self.solver.solve(x, p, fixed=fixed)
                if out.success and self.solver is not self.gauss_newton:
                    out.x, out.polish_steps, out.polish_f = polish(
                        self.gauss_newton, out.x, p, fixed
                    )
                return out
            # a plan without data (export-time analysis): keep the start point
            return SolveOutcome(np.array(x, float), float("nan"), "not solved", True, 0, 0.0)

        self.phase_conditions: dict[str, float] = {}
        x = np.array(x0, float)
        fixed, ident = user_fixed, None
        held_all: list[np.ndarray] = []
        datum_all: list[np.ndarray] = []
        pivots_all: list[np.ndarray] = []
        for i, ph in enumerate(strat.phases):
            held = user_fixed | self.group_mask(ph.hold)
            x = np.where(self.group_mask(ph.zero), 0.0, x)
            if given is not None:
                self.problem.set_datum(given.datum[i])
            elif ph.datum:
                self.select_datum(x, p, held)
            else:
                # the error parameters are held: no datum condition is needed (rows on held
                # variables only would over-determine the NLP for IPOPT)
                self.problem.set_datum(np.zeros(len(self.problem.conditions), bool))
            fixed = held.copy()
            pivot = np.zeros(n, bool)
            if given is not None:
                pivot = given.pivots[i]
            elif ph.pivots:
                ident = self.analyse(x, p, held)
                # hold one variable per null direction (the pivot): an error parameter at
                # zero, a station or frame parameter at its start value (an instrument's
                # own frame need not start at zero); the others involved stay free and are
                # reported as not individually identifiable
                pivot[list(ident.pivots)] = True
            fixed |= pivot
            x = np.where(pivot & ~held & self.is_theta, 0.0, x)
            held_all.append(fixed.copy())
            datum_all.append(np.array(self.problem.datum_active, bool))
            pivots_all.append(pivot)
            out = step(x, fixed)
            outcomes.append(out)
            x = out.x
            if ph.report:
                # the conditioning of the system this phase solved
                rep = self.analyse(x, p, held, constrained=False)
                self.phase_conditions.update(
                    {
                        f"{ph.report}_jacobian_scaled": rep.condition,
                        f"{ph.report}_jacobian_unscaled": rep.condition_unscaled,
                    }
                )
        if given is not None:
            return x, outcomes, given
        if ident is None:
            ident = self.analyse(x, p, fixed)
        plan = StrategyPlan(
            strat, user_fixed.copy(), tuple(held_all), tuple(datum_all), tuple(pivots_all), ident
        )
        return x, outcomes, plan


@dataclass(frozen=True)
class StrategyPlan:
    """The decisions of a :class:`~volcal.problem.strategies.PhasedStrategy` for one
    layout and held set (:meth:`Identifier.plan`), reused by ``Identifier.run(plan, x0,
    p)`` for any readings and start values of that layout (a Monte Carlo over one
    instrument layout).

    Per phase: ``held`` the mask over x held in the solve (the user's, the phase's groups
    and the pivots), ``datum`` the mask over the problem's candidate datum conditions in
    force, ``pivots`` the mask of the variables held for a null direction (error
    parameters among them start the phase at zero).  ``identifiability``: of the last
    phase that analysed it (or of the answer when none did), at the data the plan was
    made with."""

    strategy: PhasedStrategy
    user_fixed: np.ndarray
    held: tuple[np.ndarray, ...]
    datum: tuple[np.ndarray, ...]
    pivots: tuple[np.ndarray, ...]
    identifiability: Identifiability


# ---------------------------------------------------------------------------------------


def axis_sensitivity(
    machine: Machine, q: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(nominal points (N, 3) mm, d(point)/d(axis) (n_axes, N, 3) in mm per mm or per rad)
    at poses q (N, n_axes; mm, rad) and tool offsets t (N, 3) mm, by forward differences
    of the nominal chain (step 1e-6 mm or rad)."""
    q = np.atleast_2d(np.asarray(q, float))
    t = np.broadcast_to(np.asarray(t, float), (q.shape[0], 3))
    # once per distinct pose (a measurement repeats each pose once per station): one
    # search for the distinct rows, not one per axis inside nominal_points
    uniq, inv = unique_rows(np.hstack([q, t]))
    qu, tu = uniq[:, : machine.n_axes], uniq[:, machine.n_axes :]
    p0 = machine.nominal_points(qu, tu)
    out = np.zeros((machine.n_axes,) + p0.shape)
    h = 1e-6
    for k in range(machine.n_axes):
        dq = np.zeros_like(qu)
        dq[:, k] = h
        out[k] = (machine.nominal_points(qu + dq, tu) - p0) / h
    return p0[inv], out[:, inv]


def combined_variance(
    axis_names: Sequence[str],
    budget: Budget,
    length: np.ndarray,
    grad: np.ndarray,
    dpdq: np.ndarray,
) -> np.ndarray:
    """Variance (mm^2) of each reading: the budget's length part at ``length`` (N,) mm plus
    every axis' (``axis_names`` in model order) repeatability carried through
    d(point)/d(axis) ``dpdq`` (n_axes, N, 3) and d(reading)/d(point) ``grad`` (N, 3)."""
    var = budget.length_sigma(length) ** 2
    for k, name in enumerate(axis_names):
        sig = budget.axis_sigma(name)
        if sig:
            var = var + (np.einsum("ni,ni->n", grad, dpdq[k]) * sig) ** 2
    return var


def reading_sigma(
    machine: Machine,
    budget: Budget,
    meas: Measurements,
    stations: np.ndarray,
    instrument: str | Instrument | None = None,
) -> np.ndarray:
    """Standard uncertainty (mm) of each reading from the budget: the length part combined
    with the axis repeatabilities carried to the reading through d(reading)/d(point) of the
    instrument (for a tracker, the beam direction) and d(point)/d(axis) of the machine.

    stations: the station parameters (K, n_station_params) (for the tracker (K, 3)
    positions suffice: the gradient does not depend on the dead length)."""
    ins = get_instrument(instrument)
    p0, dpdq = axis_sensitivity(machine, meas.q_internal, meas.tool)
    S = np.zeros((len(stations), ins.n_station_params))
    given = np.asarray(stations, float)
    S[:, : given.shape[1]] = given
    _, grad = ins.evaluate(p0, S[meas.station_index])  # (N, 3) d reading / d point
    var = combined_variance(machine.axis_names, budget, meas.length, grad, dpdq)
    sigma = np.sqrt(var)
    bad = ~np.isfinite(sigma)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"the reading uncertainty of row {int(meas.rows[r])} (station "
            f"{meas.station_ids[meas.station_index[r]]}) is not defined: the {ins.name} "
            "instrument's reading has no derivative there (the nominal point coincides with "
            "the station's start position?); check the instrument and the stations",
            source="measurements",
        )
    return sigma


def initial_stations(
    machine: Machine,
    meas: Measurements,
    stations: pd.DataFrame | None,
    instrument: str | Instrument | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Start values of the stations: (K, n_station_params) in the order of
    ``meas.station_ids`` (for the tracker x, y, z, dead length in mm), the mask of stations
    held fixed (K,), and notes (:func:`initial_instrument` without the globals)."""
    est, _, fixed, notes = initial_instrument(machine, meas, stations, instrument)
    return est, fixed, notes


def initial_instrument(
    machine: Machine,
    meas: Measurements,
    stations: pd.DataFrame | None,
    instrument: str | Instrument | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Start values of the instrument: stations (K, n_station_params) in the order of
    ``meas.station_ids``, global parameters, the mask of stations held fixed (K,), and
    notes.  From the stations table where given (its columns are the instrument's station
    parameter names), else the instrument's own start values from the nominal points (with
    its matching globals when no station comes from the table)."""
    ins = get_instrument(instrument)
    glob = np.zeros(ins.n_global_params)
    notes = []
    K = len(meas.station_ids)
    est = np.full((K, ins.n_station_params), np.nan)
    fixed = np.zeros(K, bool)
    if stations is not None:
        tab = stations.set_index("station")
        cols = list(ins.station_param_names)
        missing_cols = [c for c in cols if c not in tab.columns]
        if missing_cols:
            raise InputError(
                f"the stations table has no column {', '.join(missing_cols)} "
                f"(the {ins.name} instrument's station parameters are "
                f"{', '.join(cols)})",
                source="stations table",
            )
        for k, sid in enumerate(meas.station_ids):
            if sid in tab.index:
                row = tab.loc[sid]
                est[k] = [row[c] for c in cols]
                fixed[k] = bool(row["fixed"]) if "fixed" in tab.columns else False
        # ids that do not match are never silently ignored (load_measurements warns)
        described = [str(s) for s in tab.index]
        if not set(described) & set(meas.station_ids):
            raise InputError(
                f"no station of the data ({', '.join(meas.station_ids[:8])}) is "
                f"described in the stations table ({', '.join(described[:8])}); "
                "station ids must match exactly",
                source="stations table",
            )
        unused = [s for s in described if s not in meas.station_ids]
        if unused:
            notes.append(f"stations table entries without readings ignored: {', '.join(unused)}")
    missing = np.isnan(est[:, 0])
    if missing.any():
        p0 = machine.nominal_points(meas.q_internal, meas.tool)
        sel = np.isin(meas.station_index, np.flatnonzero(missing))
        ids = [meas.station_ids[k] for k in np.flatnonzero(missing)]
        # each selected reading's station among the missing ones (cumsum - 1 of the mask:
        # the rank of its station in it), without a Python loop over the readings
        idx = (np.cumsum(missing) - 1)[meas.station_index[sel]].astype(int)
        est[missing], glob_start = ins.start(ids, idx, p0[sel], meas.length[sel])
        if missing.all():  # globals only match stations that all come from the instrument
            glob = glob_start
        notes.append(ins.start_note())
    return est, glob, fixed, notes


def build_error_model(
    spec: MachineSpec,
    *,
    degree: int = 3,
    datum: Datum = "iso230",
    forms: dict[str, ErrorForm] | None = None,
) -> ErrorModel:
    """The error model of ``spec``: ``forms`` ({error or axis name: ErrorForm}), then the
    model file's bases, then Legendre of ``degree`` (Fourier of ``degree`` on full-turn
    rotary axes); see :class:`volcal.model.errors.ErrorModel`."""
    return ErrorModel(spec, forms, default=ErrorForm("poly", degree), datum=datum)


def identify(*args, **kwargs) -> IdentificationResult:
    """Identify the geometric errors of a machine (see :func:`_identify` for the
    arguments); runs with one BLAS thread (see :mod:`volcal.base.threads`)."""
    from volcal.base.threads import blas_threads

    with blas_threads(1):
        return _identify(*args, **kwargs)


def _identify(
    model: str | Path | MachineSpec | Machine,
    data: str | Path | pd.DataFrame | Measurements,
    stations: str | Path | pd.DataFrame | None = None,
    *,
    strategy: str = "joint",
    degree: int = 3,
    datum: Datum = "iso230",
    error_model: ErrorModel | None = None,
    budget: str | Path | Budget = "paper002",
    robust: bool = False,
    reject_k: float = 4.0,
    exact: bool = False,
    hessian: str = "gauss-newton",
    scale_covariance: bool = False,
    station_method: str = "sqrt",
    point_method: str = "sqrt",
    verbose: bool = False,
    forms: dict[str, ErrorForm] | None = None,
    order_criterion: str = "bic",
    cv_folds: int = 5,
    datum_mode: str = "minimal",
    progress: bool = False,
    instrument: str | Instrument | None = None,
    solver: str = "auto",
    columns: Mapping[str, str] | str | None = None,
    max_memory_gb: float | None = None,
    variance_components: bool = False,
    reject_groups: np.ndarray | None = None,
    on_solved: Callable[[Solved], None] | None = None,
    release_graph: bool = False,
) -> IdentificationResult:
    """Identify the geometric errors of a machine from length readings.

    model: bundled model name, model file, spec or Machine; data: measurement table (CSV,
    DataFrame or validated Measurements); stations: optional stations table (start values,
    or known positions where ``fixed``). Readings without ``sigma`` are weighted by the
    budget. ``robust`` rejects readings whose normalised residual exceeds ``reject_k``
    robust standard deviations and re-solves (the rejected readings are listed);
    ``reject_groups`` (one label per reading, e.g. its table): the robust standard
    deviation of each group's own readings.  Raises SolverError when IPOPT does not succeed.

    forms: error bases {error or axis name: ErrorForm} (:mod:`volcal.model.errors`).
    This is the single fit; ``degree="auto"`` (``order_criterion``, ``cv_folds``,
    ``progress``) and the classic strategy are orchestrated by
    :func:`volcal.workflow.identify` (``volcal.identify``), which calls it.

    solver: ``"auto"`` (default: IPOPT below :data:`AUTO_GAUSS_NEWTON_READINGS` readings,
    Gauss-Newton from there, said in the notes), ``"ipopt"`` or ``"gauss-newton"``
    (:mod:`volcal.solve`); both reach the same minimiser.  Gauss-Newton evaluates the
    problem in chunks of poses and never builds the CasADi graph of every reading that
    IPOPT needs (:mod:`volcal.problem.chunked`).

    instrument: the observation model (:mod:`volcal.measurement.instruments`; a name such
    as ``"tracker"`` (default) or ``"multilaser"``, or an :class:`Instrument` object).

    columns: a column mapping for an instrument's export (``"length=L[m],station=Tracker"``,
    see :func:`volcal.measurement.tables.parse_column_map`).

    max_memory_gb: the memory (GB, 1e9 bytes) the identification may take; a table whose
    estimated peak (:func:`volcal.base.memory.estimate_peak_bytes`, readings x unknowns)
    exceeds it is refused with :class:`InputError` before the solve.  None (default): the
    memory available now; ``float("inf")``: no check.

    Several instruments' tables (issue 32; ``data`` a list, ``variance_components``) are
    joined by :func:`volcal.workflow.identify` (``volcal.identify``) through
    :func:`volcal.analysis.fusion.identify_datasets`, which calls this fit.

    on_solved: called once with a :class:`Solved` (the estimates and the residual table)
    when the solve has converged, before the uncertainty stage; a plain call between
    stages (``volcal identify`` sends its plots of the residuals and of the volumetric
    error to its plotting processes there).  release_graph: the IPOPT solver and the
    CasADi graph of every reading freed at that point (:meth:`Identifier.release_graph`:
    the result's identifier builds them again if it solves again); ``volcal identify``,
    which does not, lowers its peak memory so.
    """
    several = isinstance(data, (list, tuple)) or variance_components
    if (
        several
        or degree == "auto"
        or isinstance(
            get_strategy(strategy, station_method=station_method, point_method=point_method),
            ClassicPipeline,
        )
    ):
        # orchestration, not a single fit: volcal.workflow joins several tables, chooses
        # the orders or runs the classic pipeline, and calls this fit; analysis does not
        # import upward
        raise InputError(
            "several tables, variance components, degree='auto' and the classic strategy "
            "are run by volcal.identify (volcal.workflow.identify), not by the single fit "
            "of volcal.analysis.identify",
            source="data" if several else ("degree" if degree == "auto" else "strategy"),
        )
    t_start = time.perf_counter()
    from volcal.base.progress import reset_timings

    reset_timings()  # the stage timings recorded with the result are this run's
    prep = prepare(
        model,
        data,
        stations,
        strategy=strategy,
        degree=degree,
        datum=datum,
        error_model=error_model,
        budget=budget,
        station_method=station_method,
        point_method=point_method,
        forms=forms,
        instrument=instrument,
        columns=columns,
        max_memory_gb=max_memory_gb,
        solver=solver,
    )
    machine, em, meas, ins, strat = prep.machine, prep.error_model, prep.meas, prep.ins, prep.strat
    st0, glob0, st_fixed, sigma = prep.st0, prep.glob0, prep.st_fixed, prep.sigma
    notes, sigma_source, strategy = prep.notes, prep.sigma_source, strat.name

    layout = Layout.from_measurements(meas)
    with report_stage(f"building the problem ({layout.n_readings} readings)"):
        ider = Identifier(
            machine,
            em,
            layout,
            exact=exact,
            hessian=hessian,
            verbose=verbose,
            datum_mode=datum_mode,
            instrument=ins,
            solver=solver,
        )
    pr = ider.problem
    if solver == "auto":
        notes.append(
            f"solver auto: {ider.solver_name} ({layout.n_readings} readings; Gauss-Newton on "
            f"chunks of poses from {AUTO_GAUSS_NEWTON_READINGS} readings, IPOPT below)"
        )
    weights = 1.0 / sigma
    x0 = pr.pack_x(np.zeros(em.n_params), st0, glob0)
    user_fixed = ider.station_fixed(st_fixed)
    if isinstance(strat, PhasedStrategy) and strat.hold_stations and not st_fixed.all():
        user_fixed[ider.is_station] = True
        notes.append(
            f"{strat.name}: stations held at their start values "
            "(given table or analytical solution)"
        )

    rejected = np.zeros(len(meas), bool)
    groups = (
        [np.ones(len(meas), bool)]
        if reject_groups is None
        else [np.asarray(reject_groups) == g for g in np.unique(reject_groups)]
    )
    for round_ in range(12 if robust else 1):
        p = pr.pack_data(meas.q_internal, meas.tool, meas.length, np.where(rejected, 0.0, weights))
        with report_stage(f"solving ({strategy}, {ider.solver_name})"):
            x, outcomes, fixed, ident = ider.run(strat, x0, p, user_fixed=user_fixed)
        p_all = pr.pack_data(meas.q_internal, meas.tool, meas.length, weights)
        final = ider.gauss_newton.final_gram
        if final is not None and final.matches(x, p_all):
            r = final.r  # the solver's last evaluation was there: the same numbers
        else:
            r = pr.chunked.residuals(pr.to_scaled(x), p_all)
        if not robust:
            break
        # data snooping with re-admission: a blunder spreads into its neighbours' residuals
        # while it is in the fit, so reject only the clearly worst ones per round and take
        # back readings that fit again once the blunders are out
        # (per table with several tables, ``reject_groups``: each on its own scale, so a
        # table whose budget is off neither hides another's blunders nor loses its own
        # good readings to another's scale)
        ok = ~rejected
        new = np.zeros(len(r), bool)
        back = np.zeros(len(r), bool)
        for g in groups:
            okg = ok & g
            if not okg.any():
                continue
            scale = max(1.4826 * np.median(np.abs(r[okg] - np.median(r[okg]))), 1.0)
            limit = reject_k * scale
            worst = np.max(np.abs(r[okg]))
            new |= okg & (np.abs(r) > limit) & (np.abs(r) >= 0.5 * worst)
            back |= rejected & g & (np.abs(r) <= limit)
        if not new.any() and not back.any():
            break
        rejected = (rejected | new) & ~back
        log.info(
            "robust round %d: rejected %d, re-admitted %d readings",
            round_ + 1,
            int(new.sum()),
            int(back.sum()),
        )

    for o in outcomes:
        if not o.success:
            raise SolverError(
                f"identification ({strategy}) did not converge after {o.iterations} iterations",
                status=o.status,
            )

    # the estimates and the residuals before the uncertainty stage: what needs no
    # covariance can be used meanwhile (on_solved)
    theta, st, frame = pr.unpack_x(x)
    if on_solved is not None:
        solved = pd.DataFrame(
            {
                "station": meas.table["station"],
                "residual_um": r * sigma * 1e3,
                "normalised_residual": r,
                "rejected": rejected,
            }
        )
        on_solved(Solved(machine, em, theta, solved))
        del solved
    if release_graph:  # no solve is to come (the caller says): the peak memory lower
        ider.release_graph()
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, np.where(rejected, 0.0, weights))
    with report_stage("uncertainty and identifiability"):
        cov = ider.covariance(x, p, fixed)
        # taken: the result keeps the identifier, which need not keep the data vector
        ider.gauss_newton.final_gram = None
        resid_w = r
        dof = max(int((~rejected).sum()) - int((~fixed).sum()) + pr.C.shape[0], 1)
        chi2 = float(np.sum(resid_w[~rejected] ** 2) / dof)
        if scale_covariance:
            cov = cov * chi2
            notes.append(f"covariance scaled by the residual variance factor {chi2:.3g}")
        nt = pr.n_theta
        cov_theta = cov[:nt, :nt]
        # The null space of the final phase without datum or pivots: which directions only move
        # the field rigidly (gauge) and which change it (unidentifiable), over the declared
        # travel at the measured tool offsets.
        base_fixed = fixed.copy()
        base_fixed[list(ident.pivots)] = False
        _, first = layout.poses  # one reading of every distinct pose
        null_field, sets = ider.field_null_space(
            x, p, base_fixed, meas.q_internal[first], meas.tool[first]
        )
        split_gauge(ident, nt, sets, pr.scale[:nt])
        # the passes kept for the solve and the uncertainty are not the result's to hold
        chunked = pr.__dict__.get("chunked")
        if chunked is not None:
            chunked.forget()
    # a parameter taking part in an unidentifiable direction has no value of its own: its
    # value depends on which variable was held (reported), so it gets no uncertainty
    identifiable = ~ident.unidentifiable[:nt]
    datum_table = condition_table(pr.conditions, pr.datum_active, theta)
    imposed = imposed_parameters(pr.conditions, pr.datum_active, nt) & identifiable
    # a parameter the datum alone sets to zero has no variance: exactly 0, not the
    # rounding (1e-17) of the null-space basis the constrained covariance is taken in
    cov_theta[imposed, :] = 0.0
    cov_theta[:, imposed] = 0.0
    n_not = int((~datum_table["imposed"]).sum())
    if n_not:
        notes.append(
            f"datum `{em.datum}`: {int(datum_table['imposed'].sum())} of "
            f"{len(datum_table)} conditions imposed; the other {n_not} would have "
            "constrained what the data determine and take the values the data give "
            "(datum.csv)"
        )
    nps = ins.n_station_params
    var_st = np.abs(np.diag(cov)[ider.is_station]).reshape(-1, max(nps, 1))
    stations_out = pd.DataFrame({"station": meas.station_ids})
    for j, name in enumerate(ins.station_param_names):
        stations_out[name] = st[:, j]
    for j, name in enumerate(ins.station_param_names):
        unit = ins.station_param_units[j]
        f, rep = (1e3, "um") if unit == "mm" else ((1e6, "urad") if unit == "rad" else (1.0, ""))
        base = name[: -len(unit) - 1] if name.endswith("_" + unit) else name
        col = f"u_{base}_{rep}" if rep else f"u_{base}"
        stations_out[col] = np.sqrt(var_st[:, j]) * f
    stations_out["fixed"] = True if getattr(strat, "hold_stations", False) else st_fixed
    residuals = meas.table.copy()
    residuals["residual_um"] = resid_w * sigma * 1e3
    residuals["normalised_residual"] = resid_w
    residuals["rejected"] = rejected
    rej = residuals.loc[rejected].assign(row=meas.rows[rejected])
    conditions = {
        **ider.phase_conditions,
        "jacobian_scaled": ident.condition,
        "jacobian_unscaled": ident.condition_unscaled,
        "chi2_per_dof": chi2,
    }
    state = SolverState(
        np.array(x, float),
        fixed.copy(),
        np.where(rejected, 0.0, weights),
        pr.datum_active.copy(),
        list(pr.names),
        ider.solver_name,
        ins.name,
        pr.fingerprint(),
    )
    return IdentificationResult(
        machine,
        em,
        strategy,
        theta,
        cov_theta,
        identifiable,
        stations_out,
        frame,
        residuals,
        ident,
        outcomes,
        conditions,
        rej,
        time.perf_counter() - t_start,
        sigma_source,
        notes,
        datum_table,
        null_field,
        state,
        identifier=ider,
        imposed=imposed,
    )


@dataclass
class Prepared:
    """The checked inputs of one identification, before any problem is built: the model,
    the readings, the error model, the strategy, the instrument's start values (stations
    (K, n_station_params), globals; mm / rad) and the standard uncertainty of every
    reading (mm).  :func:`prepare` makes it; the single fit and the workflow's other
    strategies (volcal.workflow) start from it."""

    spec: MachineSpec
    machine: Machine
    meas: Measurements
    st_table: pd.DataFrame | None
    ins: Instrument
    error_model: ErrorModel
    budget: Budget
    strat: Strategy
    st0: np.ndarray
    glob0: np.ndarray
    st_fixed: np.ndarray
    sigma: np.ndarray
    sigma_source: str
    notes: list[str]


def prepare(
    model: str | Path | MachineSpec | Machine,
    data: str | Path | pd.DataFrame | Measurements,
    stations: str | Path | pd.DataFrame | None = None,
    *,
    strategy: str = "joint",
    degree: int = 3,
    datum: Datum = "iso230",
    error_model: ErrorModel | None = None,
    budget: str | Path | Budget = "paper002",
    station_method: str = "sqrt",
    point_method: str = "sqrt",
    forms: dict[str, ErrorForm] | None = None,
    instrument: str | Instrument | None = None,
    columns: Mapping[str, str] | str | None = None,
    max_memory_gb: float | None = None,
    solver: str = "ipopt",
) -> Prepared:
    """Read and check the inputs of an identification (arguments as :func:`_identify`):
    tables, model, error model, budget, strategy, memory (estimated for the path
    ``solver`` takes), start values and reading uncertainties."""
    # the tables are read and checked before the model is built: a bad input is reported
    # at once, not after the build
    spec = model.spec if isinstance(model, Machine) else resolve_model(model)
    ins = get_instrument(instrument)
    st_table = None
    if stations is not None:
        # the tracker's stations table is validated by its reader; another instrument's
        # table is a DataFrame whose columns are its station parameters
        # (a combined instrument of one tracker table is named "tracker" too; its table
        # has the combined columns, volcal.analysis.fusion)
        if ins.name == "tracker" and "instrument_index" not in ins.station_param_names:
            given = isinstance(stations, pd.DataFrame) and (
                "x_mm" in stations and "dead_length_given" in stations
            )
            st_table = stations if given else load_stations(stations)
        else:
            st_table = load_instrument_stations(stations, ins.station_param_names)
    with report_stage("reading the data"):
        meas = (
            data
            if isinstance(data, Measurements)
            else load_measurements(
                data,
                spec,
                stations=st_table,
                relative_lengths=not ins.positive_readings,
                columns=columns,
            )
        )
    if isinstance(model, Machine):
        machine = model
    else:
        with report_stage("building the model"):
            machine = Machine.from_model(spec)
    em = error_model or build_error_model(spec, degree=degree, datum=datum, forms=forms)
    bud = budget if isinstance(budget, Budget) else load_budget(budget)
    strat = get_strategy(strategy, station_method=station_method, point_method=point_method)
    # before anything of the table's size is built: a table too large for the memory is
    # refused with the estimate and the limit, not ended by the kernel's OOM killer
    check_memory(
        len(meas),
        em.n_params
        + len(meas.station_ids) * len(ins.station_param_names)
        + len(ins.global_param_names),
        limit_gb=max_memory_gb,
        what=meas.source,
        # Gauss-Newton never builds the per-reading graph (problem.chunked)
        chunked=resolve_solver(solver, len(meas)) == "gauss-newton",
    )

    with report_stage("start values and reading uncertainties"):
        st0, glob0, st_fixed, notes = initial_instrument(machine, meas, st_table, ins)
        sigma = meas.sigma.copy()
        no_sigma = ~np.isfinite(sigma)
        if no_sigma.any():  # the budget only where the table gives no sigma
            sigma[no_sigma] = reading_sigma(machine, bud, meas, st0, ins)[no_sigma]
            uncovered = bud.warn_uncovered(spec)
            if uncovered:
                notes.append(uncovered)
    sigma_source = (
        "table"
        if not no_sigma.any()
        else (f"budget {bud.name}" if no_sigma.all() else f"table and budget {bud.name}")
    )

    return Prepared(
        spec,
        machine,
        meas,
        st_table,
        ins,
        em,
        bud,
        strat,
        st0,
        glob0,
        st_fixed,
        sigma,
        sigma_source,
        notes,
    )
