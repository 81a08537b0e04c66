"""``volcal.plan``: where to put the tracker and which poses to measure.

:func:`plan` puts the pieces together:

1. candidate poses: a grid over the travel to cover (a sub-range per axis if given), every
   pose measured with every available tool offset from every station;
2. the readings budget (a number, or minutes at seconds per reading) fixes how many poses
   the plan holds: readings / (stations x tool offsets);
3. a start: the given stations or feasible random ones, and an even spread of poses
   (farthest-point sampling over the normalised axis positions);
4. station placement (``"gradient"``, ``"ga"`` or ``"none"``), then a pose exchange
   (``poses="exchange"``) among the poses every station can read, then placement again;
5. the result: every reading checked against every constraint (a plan that breaks one is
   never returned), the predicted uncertainties (error motions, volumetric error over the
   workspace, error parameters) and what would stay unidentifiable.

The search runs in constraints made stricter by margins (``margin_deg`` off the
reflector's acceptance angle, ``margin_mm`` inside the regions, on the distance, range and
obstacles; defaults :data:`DEFAULT_MARGIN_DEG`, :data:`DEFAULT_MARGIN_MM`), so that the
planned worst case is not on a declared limit: a tracker set up ``margin_mm`` off its
planned spot, or a reflector aimed a few degrees off, still keeps every declared limit.
:meth:`PlanResult.slack` reports how much room the plan leaves on each declared limit, and
:meth:`PlanResult.setup_sheet` what the operator does at each station (where the tracker
stands, where the reflector points and how it is mounted, the order of the readings and
the time they take).

Units: mm and degrees at the interface (poses in file units as in
:mod:`volcal.measurement.plans`), mm and rad inside.
"""

from __future__ import annotations

import functools
import hashlib
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.analysis.planning.evaluator import CRITERIA, PlanEvaluator
from volcal.analysis.planning.geometry import (
    Constraints,
    beam_angles_deg,
    constraint_slack,
    constraints_from_dict,
    reading_violations,
)
from volcal.analysis.planning.search import (
    SearchResult,
    StationSampler,
    exchange_poses,
    genetic_placement,
    gradient_placement,
)
from volcal.base.exceptions import InputError
from volcal.base.progress import stage as progress_stage
from volcal.base.threads import blas_threads
from volcal.measurement.budget import Budget, load_budget
from volcal.measurement.plans import grid_plan
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine

__all__ = [
    "plan",
    "PlanResult",
    "OPTIMIZERS",
    "DEFAULT_MARGIN_DEG",
    "DEFAULT_MARGIN_MM",
    "candidate_poses",
    "spread_poses",
]

#: station placement methods
OPTIMIZERS = ("gradient", "ga", "none")

#: default margins (deg off the acceptance half-angle; mm inside regions and on distances
#: and obstacles): a tracker tripod set up by tape measure lands within a couple of cm of
#: its mark, and 20 mm sideways at 250 mm or more from the reflector turns a beam by less
#: than 5 deg
DEFAULT_MARGIN_DEG = 5.0
DEFAULT_MARGIN_MM = 20.0


def candidate_poses(
    machine: Machine,
    n: int,
    travel: Mapping[str, Sequence[float]] | None = None,
    n_sample: int = 0,
) -> pd.DataFrame:
    """Candidate poses over the travel, or over ``travel`` ({axis: (lo, hi)} in mm / deg,
    inside the axis travel) where given: a grid of ``n`` positions per axis for a machine
    without rotary axes; with rotary axes the corners of the travel box and a Halton
    sample of ``n_sample`` poses, so that every rotary axis is seen at many distinct angles
    (a grid of 4 angles cannot determine a third-order Fourier series)."""
    from volcal.analysis.identify import _halton

    spec = machine.spec
    rotary = any(a.is_rotary for a in spec.axes)
    lo = np.array([a.travel[0] for a in spec.axes], float)
    hi = np.array([a.travel[1] for a in spec.axes], float)
    for k, a in enumerate(spec.axes):
        if travel and a.name in travel:
            t0, t1 = (float(v) for v in travel[a.name])
            if not (a.travel[0] - 1e-9 <= t0 < t1 <= a.travel[1] + 1e-9):
                raise InputError(
                    f"travel to cover on {a.name}: {t0:g} .. {t1:g} must lie inside the "
                    f"axis travel {a.travel[0]:g} .. {a.travel[1]:g} with lo < hi"
                )
            lo[k], hi[k] = t0, t1
    unknown = sorted(set(travel or {}) - set(spec.axis_names))
    if unknown:
        raise InputError(f"travel given for unknown axes {unknown}; axes: {spec.axis_names}")
    if not rotary:
        g = grid_plan(spec, n)
        for k, a in enumerate(spec.axes):
            t0, t1 = a.travel
            g[a.name] = lo[k] + (g[a.name] - t0) * (hi[k] - lo[k]) / (t1 - t0)
        return g.drop_duplicates().reset_index(drop=True)
    d = len(spec.axes)
    u = _halton(max(int(n_sample), 16), d)
    if d <= 6:
        u = np.vstack([np.array(list(np.ndindex(*([2] * d))), float), u])
    q = lo + u * (hi - lo)
    return pd.DataFrame(q, columns=spec.axis_names).drop_duplicates().reset_index(drop=True)


def spread_poses(machine: Machine, poses: pd.DataFrame, n: int) -> np.ndarray:
    """Mask selecting ``n`` poses spread evenly (greedy farthest-point sampling over the
    axis positions normalised by their travel, from the pose nearest the centre)."""
    if n >= len(poses):
        return np.ones(len(poses), bool)
    spec = machine.spec
    span = np.array([max(a.travel[1] - a.travel[0], 1e-9) for a in spec.axes])
    X = poses[spec.axis_names].to_numpy(float) / span
    first = int(np.argmin(np.linalg.norm(X - X.mean(0), axis=1)))
    chosen = [first]
    d = np.linalg.norm(X - X[first], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(X - X[k], axis=1))
    sel = np.zeros(len(poses), bool)
    sel[chosen] = True
    return sel


def _tool_axes(machine: Machine, q: np.ndarray, t: np.ndarray, axis) -> np.ndarray:
    """The reflector axis (tool frame) turned into the machine frame at each reading: the
    difference of the nominal points at tool offsets t + axis and t (the tool offset is
    affine in the tool frame)."""
    if axis is None:
        return np.zeros_like(t)
    z = np.zeros(machine.n_errors)
    p1, _, _ = machine.evaluate(q, t + np.asarray(axis, float), z)
    p0, _, _ = machine.evaluate(q, t, z)
    d = p1 - p0
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(repr=False)
class PlanResult:
    """A measurement plan and its prediction (see :func:`plan`)."""

    machine: Machine
    error_model: ErrorModel
    evaluator: PlanEvaluator
    stations_mm: np.ndarray
    selected: np.ndarray
    criterion: str
    value: float
    start_value: float
    searches: list[SearchResult]
    constraints: Constraints
    settings: dict[str, Any]
    seconds: float
    notes: list[str] = field(default_factory=list)
    #: the workspace centre (mm) a re-aimed reflector points from
    centre_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: the margins the search kept from the declared limits: (deg, mm)
    margins: tuple[float, float] = (0.0, 0.0)
    #: interferometer lines / ballbar circles added within a time budget
    #: (:func:`volcal.analysis.planning.additions.add_instruments`), or None
    additions: Any = None

    @property
    def planning_constraints(self) -> Constraints:
        """The declared constraints made stricter by the margins (what the search kept)."""
        return self.constraints.with_margins(*self.margins)

    def _planned(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nominal points (n, 3) mm, reflector axes turned with the tool (n, 3) and station
        index (n,) of every planned reading in :meth:`measurement_plan` order."""
        ev = self.evaluator
        keep = self.selected[ev.pose_of]
        axes = _tool_axes(self.machine, ev.q[keep], ev.t[keep], self.constraints.reflector.axis)
        return ev.points[keep], axes, ev.station_of[keep]

    # ---- tables ----------------------------------------------------------------------
    @property
    def stations(self) -> pd.DataFrame:
        """station, x_mm, y_mm, z_mm (the tracker set-ups, in measuring order)."""
        ids = [f"S{k + 1}" for k in range(len(self.stations_mm))]
        df = pd.DataFrame(self.stations_mm, columns=["x_mm", "y_mm", "z_mm"])
        df.insert(0, "station", ids)
        return df

    @property
    def poses(self) -> pd.DataFrame:
        """The selected poses, one column per axis (mm / deg), in measuring order."""
        m = self.machine
        q = self.evaluator.poses[self.selected]
        out = q.copy()
        for k, a in enumerate(m.spec.axes):
            if a.is_rotary:
                out[:, k] = np.rad2deg(out[:, k])
        return pd.DataFrame(out, columns=m.axis_names)

    @property
    def tools(self) -> np.ndarray:
        return self.evaluator.tools

    def measurement_plan(self, *, with_tool_index: bool = False) -> pd.DataFrame:
        """Every planned reading in measuring order (station, then tool offset, then pose)
        in the columns ``identify`` reads: ``station, point, <axes>, tool_x_mm,
        tool_y_mm, tool_z_mm`` and an empty ``length_mm`` to fill with the readings
        (``with_tool_index``: also ``tool``, the tool offset's index, for the NC
        program)."""
        ev, m = self.evaluator, self.machine
        keep = self.selected[ev.pose_of]
        q = ev.q[keep].copy()
        for k, a in enumerate(m.spec.axes):
            if a.is_rotary:
                q[:, k] = np.rad2deg(q[:, k])
        st = ev.station_of[keep]
        # point ids: one per (pose, tool), the same at every station
        sel_idx = np.cumsum(self.selected) - 1
        point = ev.tool_of[keep] * int(self.selected.sum()) + sel_idx[ev.pose_of[keep]] + 1
        df = pd.DataFrame({"station": [f"S{k + 1}" for k in st], "point": point})
        for k, name in enumerate(m.axis_names):
            df[name] = q[:, k]
        if with_tool_index:
            df["tool"] = ev.tool_of[keep]
        df[["tool_x_mm", "tool_y_mm", "tool_z_mm"]] = ev.t[keep]
        df["length_mm"] = np.nan
        return df

    def violations(self, *, with_margins: bool = False) -> pd.DataFrame:
        """Every planned reading that breaks a declared constraint (``with_margins``: the
        constraints the search kept, :attr:`planning_constraints`); empty for a returned
        plan.  Columns as :func:`volcal.analysis.planning.geometry.reading_violations`."""
        P, axes, st = self._planned()
        cons = self.planning_constraints if with_margins else self.constraints
        return reading_violations(P, axes, st, self.stations_mm, cons, self.centre_mm)

    def slack(self) -> pd.DataFrame:
        """How much room the plan leaves on each declared limit, worst case over its
        readings: constraint, worst, limit, slack, unit, station, reading (see
        :func:`volcal.analysis.planning.geometry.constraint_slack`); ``station`` as its id
        (S1, ...)."""
        P, axes, st = self._planned()
        df = constraint_slack(P, axes, st, self.stations_mm, self.constraints, self.centre_mm)
        df["station"] = [f"S{k + 1}" for k in df["station"]]
        return df

    def aim(self) -> pd.DataFrame:
        """Where the reflector points at each station: station, mode (``re-aimed``: the
        axis points from the workspace centre at the tracker, fixed in the machine frame
        for the whole set-up; ``tool frame``: a fixed axis in the tool frame that turns
        with the rotary axes; ``any``: no acceptance limit), from_x_mm, from_y_mm,
        from_z_mm (the point the axis is aimed from, the workspace centre; NaN unless
        re-aimed), dir_x, dir_y, dir_z (unit vector: machine frame when re-aimed, tool
        frame otherwise), azimuth_deg (from +x towards +y), elevation_deg (from the x-y
        plane towards +z) and max_beam_angle_deg (the largest angle between the axis and
        a beam of the station, over its planned readings; limit: the declared
        half-angle)."""
        ref = self.constraints.reflector
        P, axes, st = self._planned()
        ang = beam_angles_deg(P, axes, self.stations_mm[st], ref, self.centre_mm)
        rows = []
        for k, s in enumerate(self.stations_mm):
            if not ref.limited:
                mode, frm, u = "any", np.full(3, np.nan), np.full(3, np.nan)
            elif ref.axis is None:
                mode, frm = "re-aimed", np.asarray(self.centre_mm, float)
                u = (s - frm) / np.linalg.norm(s - frm)
            else:
                mode, frm, u = "tool frame", np.full(3, np.nan), np.asarray(ref.axis, float)
            rows.append(
                {
                    "station": f"S{k + 1}",
                    "mode": mode,
                    "from_x_mm": frm[0],
                    "from_y_mm": frm[1],
                    "from_z_mm": frm[2],
                    "dir_x": u[0],
                    "dir_y": u[1],
                    "dir_z": u[2],
                    "azimuth_deg": float(np.degrees(np.arctan2(u[1], u[0]))),
                    "elevation_deg": float(np.degrees(np.arcsin(np.clip(u[2], -1, 1)))),
                    "max_beam_angle_deg": float(ang[st == k].max()) if (st == k).any() else np.nan,
                }
            )
        return pd.DataFrame(rows)

    def setup_sheet(self, seconds_per_reading: float | None = None) -> list[dict[str, Any]]:
        """What the operator does at each station, in measuring order: one dict per
        station with ``station``, ``position_mm`` (x, y, z), ``region`` (the declared
        region it stands in), ``aim`` (a row of :meth:`aim` as a dict), ``blocks`` (one per
        tool offset in measuring order: ``tool_offset_mm`` (x, y, z in the tool frame),
        ``first_row`` and ``last_row`` (1-based rows of :meth:`measurement_plan`),
        ``points`` (the point ids, in order) and ``readings``), ``readings`` and
        ``minutes`` (readings x ``seconds_per_reading``, default the plan's setting, 4 s;
        setting up the tracker and changing the reflector come on top)."""
        spr = float(
            self.settings.get("seconds_per_reading", 4.0)
            if seconds_per_reading is None
            else seconds_per_reading
        )
        mp = self.measurement_plan(with_tool_index=True)
        aim = self.aim()
        regs = self.constraints.regions
        sheet = []
        for k, s in enumerate(self.stations_mm):
            sid = f"S{k + 1}"
            rows = np.flatnonzero(mp["station"].to_numpy() == sid)
            blocks = []
            for t in pd.unique(mp["tool"].to_numpy()[rows]):
                r = rows[mp["tool"].to_numpy()[rows] == t]
                blocks.append(
                    {
                        "tool_offset_mm": [float(v) for v in self.tools[int(t)]],
                        "first_row": int(r[0]) + 1,
                        "last_row": int(r[-1]) + 1,
                        "points": [int(p) for p in mp["point"].to_numpy()[r]],
                        "readings": int(len(r)),
                    }
                )
            region = ""
            if regs:
                depth = [float(g.clearance(s[None])[0]) for g in regs]
                region = regs[int(np.argmax(depth))].name
            sheet.append(
                {
                    "station": sid,
                    "position_mm": [float(v) for v in s],
                    "region": region,
                    "aim": {
                        key: (None if isinstance(v, float) and np.isnan(v) else v)
                        for key, v in aim.iloc[k].to_dict().items()
                    },
                    "blocks": blocks,
                    "readings": int(len(rows)),
                    "minutes": len(rows) * spr / 60.0,
                }
            )
        return sheet

    # ---- prediction --------------------------------------------------------------------
    def covariance(self) -> np.ndarray:
        """Linearised covariance of the unknowns (mm, rad; held variables NaN)."""
        return self.evaluator.covariance(self.stations_mm, self.selected)

    def parameter_uncertainty(self) -> pd.DataFrame:
        """parameter, unit, u (standard uncertainty, um or urad; NaN where held)."""
        pr = self.evaluator.problem
        cov = self.covariance()
        u = np.sqrt(np.clip(np.diag(cov), 0, None))
        factor = np.array([1e3 if un == "mm" else 1e6 if un == "rad" else 1.0 for un in pr.units])
        unit = ["um" if un == "mm" else "urad" if un == "rad" else un for un in pr.units]
        return pd.DataFrame({"parameter": pr.names, "unit": unit, "u": u * factor})

    def error_motion_uncertainty(self, n: int = 21) -> pd.DataFrame:
        """Standard uncertainty of every error motion along its axis (the other axes at
        their reference): error, axis, position (mm or deg), u_um or u_urad in
        ``u_value`` with ``unit``."""
        m, em = self.machine, self.error_model
        cov = np.nan_to_num(self.covariance()[: em.n_params, : em.n_params])
        rows = []
        ref = np.array([a.reference for a in m.spec.axes], float)
        ref = m.axis_to_internal(ref[None])[0]
        for k, s in enumerate(em.errors):
            if s.kind == "component":
                a = m.spec.axis(s.axis)
                j = m.axis_names.index(s.axis)
                pos = np.linspace(a.travel[0], a.travel[1], n)
                q = np.repeat(ref[None], n, axis=0)
                q[:, j] = np.deg2rad(pos) if a.is_rotary else pos
            else:
                pos, q = np.array([np.nan]), ref[None]
            b = em.basis(q, [k])[:, 0, :]  # (n, n_params)
            var = np.einsum("np,pq,nq->n", b, cov, b)
            f, unit = (1e3, "um") if s.quantity == "translation" else (1e6, "urad")
            for x, v in zip(pos, var):
                rows.append(
                    {
                        "error": s.name,
                        "axis": s.axis,
                        "position": x,
                        "u_value": float(np.sqrt(max(v, 0.0)) * f),
                        "unit": unit,
                    }
                )
        return pd.DataFrame(rows)

    def volumetric_uncertainty(self) -> pd.DataFrame:
        """Standard uncertainty of the volumetric error at the evaluation poses: the axes
        (mm / deg), tool offset (mm), nominal point (mm), u_dx_um, u_dy_um, u_dz_um,
        u_total_um."""
        ev, m = self.evaluator, self.machine
        u = ev.volumetric_u(self.stations_mm, self.selected)
        q = ev.eval_q.copy()
        for k, a in enumerate(m.spec.axes):
            if a.is_rotary:
                q[:, k] = np.rad2deg(q[:, k])
        df = pd.DataFrame(q, columns=m.axis_names)
        df[["tool_x_mm", "tool_y_mm", "tool_z_mm"]] = ev.eval_t
        p0, _, _ = m.evaluate(ev.eval_q, ev.eval_t, np.zeros(m.n_errors))
        df[["x_mm", "y_mm", "z_mm"]] = p0
        df[["u_dx_um", "u_dy_um", "u_dz_um"]] = u
        df["u_total_um"] = np.linalg.norm(u, axis=1)
        return df

    def unidentifiable(self) -> list[str]:
        """Error parameters in a direction the plan's data cannot see (the gauge of the
        stations and the tracker frame is left out: no data can see it)."""
        nt = self.error_model.n_params
        names = set(self.error_model.param_names)
        return [
            n
            for n in (self.evaluator.frozen.unidentifiable if self.evaluator.frozen else [])
            if n in names
        ][:nt]

    def field_determined(self) -> np.ndarray:
        """Per evaluation pose: whether its volumetric error follows from the data (up to
        the rigid motion no multilateration sees)."""
        ev = self.evaluator
        ider = ev.identifier
        x, p = ev.x(self.stations_mm), ev.p(self.stations_mm, self.selected)
        user_fixed = ider.station_fixed(np.zeros(ev.n_stations, bool))
        keep = self.selected[ev.pose_of]
        fns, _ = ider.field_null_space(x, p, user_fixed, ev.q[keep], ev.t[keep])
        p0, _, _ = self.machine.evaluate(ev.eval_q, ev.eval_t, np.zeros(self.machine.n_errors))
        return np.asarray(fns.determined(ev.G_eval, p0), bool)

    def summary(self, *, vol: pd.DataFrame | None = None) -> dict[str, Any]:
        """The plan's figures, searches, margins and slack as plain data; ``vol``: its
        :meth:`volumetric_uncertainty` where the caller has it already."""
        if vol is None:
            vol = self.volumetric_uncertainty()
        return {
            "model": self.machine.spec.name,
            "stations": int(len(self.stations_mm)),
            "tool_offsets": int(len(self.tools)),
            "poses": int(self.selected.sum()),
            "readings": int(self.selected.sum() * len(self.tools) * len(self.stations_mm)),
            "criterion": self.criterion,
            "criterion_value": self.value,
            "start_value": self.start_value,
            "volumetric_u_rms_um": float(np.sqrt(np.mean(vol["u_total_um"] ** 2))),
            "volumetric_u_max_um": float(vol["u_total_um"].max()),
            "unidentifiable_error_parameters": self.unidentifiable(),
            "searches": [
                {
                    "method": s.method,
                    "value": s.value,
                    "evaluations": s.evaluations,
                    "seconds": round(s.seconds, 3),
                }
                for s in self.searches
            ],
            "seconds": round(self.seconds, 3),
            "notes": self.notes,
            "margins": {"deg": self.margins[0], "mm": self.margins[1]},
            "slack": self.slack().to_dict(orient="records"),
        }

    def _repr_html_(self) -> str:
        """The plan's summary and stations for Jupyter."""
        from html import escape

        s = self.summary()
        return (
            f"<b>Measurement plan for {escape(s['model'])}</b>: {s['stations']} stations, "
            f"{s['poses']} poses x {s['tool_offsets']} tool offset(s) = {s['readings']} "
            f"readings<br>criterion {s['criterion']} {s['criterion_value']:.4g} (start "
            f"{s['start_value']:.4g}); predicted volumetric u RMS "
            f"{s['volumetric_u_rms_um']:.3g} um, max {s['volumetric_u_max_um']:.3g} um<br>"
            + self.stations.round(1).to_html(index=False)
        )

    def __repr__(self) -> str:
        return (
            f"PlanResult({self.machine.spec.name}: {len(self.stations_mm)} stations, "
            f"{int(self.selected.sum())} poses x {len(self.tools)} tools, "
            f"{self.criterion} = {self.value:.4g} (start {self.start_value:.4g}))"
        )


def _readings_budget(
    readings: int | None, minutes: float | None, seconds_per_reading: float
) -> int | None:
    if readings is not None and minutes is not None:
        raise InputError("give the budget as readings or as minutes, not both")
    if minutes is not None:
        if not minutes > 0 or not seconds_per_reading > 0:
            raise InputError("minutes and seconds per reading must be > 0")
        return int(minutes * 60.0 / seconds_per_reading)
    if readings is not None and readings <= 0:
        raise InputError(f"the readings budget must be > 0, got {readings}")
    return readings


def _one_blas_thread(fn: Callable[..., PlanResult]) -> Callable[..., PlanResult]:
    """Run ``fn`` with one BLAS thread, as the command line runs: the planner's dense
    problems are small (r x r solves, stacks of k x k), and a pool of BLAS threads made
    the pose exchange 5x slower on a shared 2-core machine."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> PlanResult:
        with blas_threads(1):
            return fn(*args, **kwargs)

    return wrapper


@_one_blas_thread
def plan(
    model: str | Path | Machine,
    *,
    n_stations: int = 4,
    tools: np.ndarray | Sequence[Sequence[float]] | None = None,
    readings: int | None = None,
    minutes: float | None = None,
    seconds_per_reading: float = 4.0,
    constraints: Constraints | Mapping[str, Any] | None = None,
    travel: Mapping[str, Sequence[float]] | None = None,
    budget: str | Path | Budget = "paper002",
    degree: int = 3,
    error_model: ErrorModel | None = None,
    criterion: str = "I",
    optimizer: str = "gradient",
    poses: str = "exchange",
    stations: np.ndarray | pd.DataFrame | None = None,
    grid: int = 6,
    seed: int = 0,
    starts: int = 6,
    population: int = 40,
    generations: int = 30,
    rounds: int = 2,
    margin_deg: float = DEFAULT_MARGIN_DEG,
    margin_mm: float = DEFAULT_MARGIN_MM,
    workers: int | None = None,
    scheduler: Any = None,
    checkpoint_dir: str | Path | None = None,
    progress: Callable[[str, int, int, float], None] | None = None,
    add_instruments: Sequence[str] | None = None,
    add_minutes: float | None = None,
    instrument_costs: Mapping[str, Any] | Any = None,
) -> PlanResult:
    """Plan a sequential multilateration measurement (see the module docstring).

    model: bundled name, model file or Machine; n_stations: tracker set-ups; tools: the
    available tool (reflector) offsets (T, 3) mm, every one measured (default (0, 0, 0));
    readings / minutes + seconds_per_reading: the time budget (default: every candidate
    pose once); constraints: :class:`Constraints` or its TOML mapping
    (:func:`volcal.analysis.planning.geometry.constraints_from_dict`), regions required;
    travel: {axis: (lo, hi)} mm / deg to cover (default the whole travel); budget: reading
    uncertainties; criterion: I (default), A, D or E; optimizer: gradient (default), ga
    or none (keep ``stations``); poses: exchange (default) or spread (keep the even
    spread); stations: start or given stations (K, 3) mm or a table with x_mm, y_mm,
    z_mm; grid: candidate positions per linear axis; seed: every random draw;
    starts / population / generations: search sizes; rounds: placement / exchange
    alternations; margin_deg / margin_mm: how far the plan keeps from the declared limits
    (deg off the acceptance half-angle; mm inside the regions, on the distance, range and
    obstacles; see the module docstring); workers / scheduler: where the gradient search's
    starts are solved and the GA's designs scored (None, the default: every core, this
    process's included; 1: this process only; W: W local processes; a Dask address or
    Client), the same plan wherever; checkpoint_dir: searches
    save there after every generation or start and resume from what they find;
    progress(stage, step, total, best): called after every generation, start and
    exchange, e.g. ("GA round 1 of 2: generation", 5, 30, 0.29) (step 1-based, 0 when a
    search round begins; best: the criterion reached, um for I and MC, the solver's
    scaled units for A, D and E); add_minutes: a time budget (minutes, on top of the
    tracker plan, which stays as planned) for interferometer lines and ballbar circles
    chosen to improve the criterion further, add_instruments: which (default both),
    instrument_costs: their time costs and uncertainties
    (:class:`volcal.analysis.planning.additions.InstrumentCosts` or a mapping of its
    keys); the result's ``additions`` (see
    :func:`volcal.analysis.planning.additions.add_instruments`)."""
    t0 = time.perf_counter()
    from volcal.analysis.planning import additions as adds

    if add_instruments is not None and add_minutes is None:
        raise InputError(
            "instruments to add given without a time budget for them: give add_minutes "
            "(--add-minutes, or minutes in the setting's [instruments])",
            source="add_minutes",
        )
    if add_minutes is not None:
        adds.check_minutes(add_minutes, "add_minutes")
        adds.check_instruments(
            list(adds.ADDABLE if add_instruments is None else add_instruments),
            "add_instruments",
        )
        if not isinstance(instrument_costs, adds.InstrumentCosts):
            instrument_costs = adds.InstrumentCosts.from_mapping(
                instrument_costs or {}, "instrument costs"
            )
    if criterion not in CRITERIA:
        raise InputError(f"unknown criterion {criterion!r}; expected one of {', '.join(CRITERIA)}")
    if optimizer not in OPTIMIZERS:
        raise InputError(
            f"unknown optimizer {optimizer!r}; expected one of {', '.join(OPTIMIZERS)}"
        )
    if poses not in ("exchange", "spread"):
        raise InputError(f"poses must be 'exchange' or 'spread', got {poses!r}")
    if n_stations < 3:
        raise InputError(f"multilateration needs at least 3 stations, got {n_stations}")
    machine = model if isinstance(model, Machine) else Machine.from_model(model)
    em = error_model or ErrorModel(machine.spec, default=ErrorForm("poly", degree))
    bud = budget if isinstance(budget, Budget) else load_budget(budget)
    T = np.zeros((1, 3)) if tools is None else np.atleast_2d(np.asarray(tools, float))
    if T.shape[1] != 3 or not np.isfinite(T).all():
        raise InputError("tool offsets must be finite (T, 3) mm")
    declared = (
        constraints
        if isinstance(constraints, Constraints)
        else constraints_from_dict(constraints or {})
    )
    # every search and check below works in the stricter constraints
    cons = declared.with_margins(margin_deg, margin_mm)
    rounds = max(1, int(rounds))
    if not cons.regions and (optimizer != "none" or stations is None):
        raise InputError(
            "declare at least one region where the tracker may stand ([[constraints.region]] "
            "with a box or polygon)"
        )
    n_total = _readings_budget(readings, minutes, seconds_per_reading)
    per_pose = n_stations * len(T)
    want = None if n_total is None else n_total // per_pose
    # with rotary axes: three candidates per planned pose (a sample, not a grid)
    cand = candidate_poses(machine, grid, travel, n_sample=min(max(3 * (want or 64), 128), 900))
    q_cand = machine.axis_to_internal(cand[machine.axis_names].to_numpy(float))
    n_poses = len(cand) if want is None else want
    notes: list[str] = []
    if n_poses > len(cand):
        notes.append(
            f"the budget allows {n_poses} poses but the grid has {len(cand)}: all measured "
            "(raise grid for more candidates)"
        )
        n_poses = len(cand)
    n_min = 4
    if n_poses < n_min:
        raise InputError(
            f"the budget gives {n_poses} pose(s) per station and tool offset "
            f"({n_total} readings / ({n_stations} stations x {len(T)} tool offsets)); "
            f"at least {n_min} are needed"
        )
    with progress_stage(f"building the prediction for {len(q_cand)} candidate poses"):
        ev = PlanEvaluator(machine, em, q_cand, T, n_stations, bud)
    rng = np.random.default_rng(seed)
    sel = spread_poses(machine, cand, n_poses)
    # the workspace centre the re-aimed reflector points from: the middle of the bounding
    # box of every candidate reading's nominal point
    centre = 0.5 * (ev.points.min(0) + ev.points.max(0))
    ckpt = Path(checkpoint_dir) if checkpoint_dir is not None else None
    if ckpt is not None:
        ckpt.mkdir(parents=True, exist_ok=True)

    def sampler_for(selected: np.ndarray) -> StationSampler:
        use = selected[ev.pose_of] & (ev.station_of == 0)
        axes = _tool_axes(machine, ev.q[use], ev.t[use], cons.reflector.axis)
        return StationSampler(cons, ev.points[use], axes, centre)

    sampler = sampler_for(sel)
    if stations is not None:
        S0 = (
            stations[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
            if isinstance(stations, pd.DataFrame)
            else np.asarray(stations, float)
        ).reshape(-1, 3)
        if len(S0) != n_stations:
            raise InputError(f"{len(S0)} stations given for n_stations = {n_stations}")
        bad = ~sampler.ok(S0)
        if bad.any() and optimizer == "none":
            raise InputError(
                f"given station(s) {', '.join(f'S{k + 1}' for k in np.flatnonzero(bad))} "
                f"cannot read every planned point: {sampler._why(S0[bad])} (the limits "
                f"less the margins of {margin_deg:g} deg and {margin_mm:g} mm); move them, "
                "lower the margins or let a search place them (optimizer gradient or ga)",
                source="stations",
            )
        if bad.any():
            notes.append(
                f"given station(s) {', '.join(f'S{k + 1}' for k in np.flatnonzero(bad))} "
                "break a constraint; the search starts from feasible draws for them"
            )
            S0[bad] = sampler.draw(rng, int(bad.sum()))
    else:
        S0 = sampler.draw(rng, n_stations)
    with warnings.catch_warnings(), progress_stage("choosing the datum at the start design"):
        warnings.simplefilter("ignore")
        ev.freeze(S0, sel)
    scorer = ev.scorer
    scorer.criterion_name = criterion
    start_value = scorer.score(S0, sel)
    S, searches = S0, []
    current = start_value  # the criterion of (S, sel), kept to score each design once
    for rnd in range(rounds):
        # what the search counts: GA generations or gradient starts
        unit, total = ("generation", generations) if optimizer == "ga" else ("start", starts)
        name = "GA" if optimizer == "ga" else optimizer

        def report(
            step: int,
            best: float,
            _what: str = f"{name} round {rnd + 1} of {rounds}: {unit}",
            _n: int = total,
        ) -> None:
            if progress is not None:
                progress(_what, step + 1, _n, best)

        if optimizer != "none":
            report(-1, current)  # step 0: the round begins

        # what a checkpoint must belong to: the readings to place stations for, the
        # constraints and the criterion
        h = hashlib.sha256(ev.points[sel[ev.pose_of]].tobytes())
        h.update(repr((cons, criterion, bud.name, em.param_names)).encode())
        fp = h.hexdigest()[:16]
        if optimizer == "ga":
            res = genetic_placement(
                scorer,
                sampler,
                n_stations,
                selected=sel,
                population=population,
                generations=generations,
                seed=seed + rnd,
                initial=S,
                workers=workers,
                scheduler=scheduler,
                checkpoint=ckpt / f"ga_round{rnd + 1}.npz" if ckpt else None,
                progress=report,
                fingerprint=fp,
            )
            searches.append(res)
        elif optimizer == "gradient":
            res = gradient_placement(
                ev,
                sampler,
                selected=sel,
                starts=starts,
                seed=seed + rnd,
                initial=S,
                criterion=criterion if criterion in ("I", "A", "D") else "I",
                workers=workers,
                scheduler=scheduler,
                checkpoint=ckpt / f"gradient_round{rnd + 1}.npz" if ckpt else None,
                progress=report,
                fingerprint=fp,
            )
            searches.append(res)
        if searches and searches[-1].value < current:
            S, current = searches[-1].stations, searches[-1].value
        if poses == "exchange":
            allowed = _readable(ev, machine, cons, S, centre)
            sel, _, swaps = exchange_poses(scorer, S, sel, allowed=allowed)
            current = scorer.score(S, sel)
            if progress is not None:
                progress("pose exchange: round", rnd + 1, rounds, current)
            sampler = sampler_for(sel)
            if swaps == 0 and rnd > 0:
                break
        else:
            break
    value = scorer.score(S, sel)
    result = PlanResult(
        machine,
        em,
        ev,
        np.asarray(S, float),
        sel,
        criterion,
        value,
        start_value,
        searches,
        declared,
        {
            "n_stations": n_stations,
            "tools_mm": T.tolist(),
            "readings": n_total,
            "criterion": criterion,
            "optimizer": optimizer,
            "poses": poses,
            "grid": grid,
            "seed": seed,
            "starts": starts,
            "population": population,
            "generations": generations,
            "rounds": rounds,
            "budget": bud.name,
            "degree": degree,
            "travel": {k: list(map(float, v)) for k, v in (travel or {}).items()},
            "centre_mm": centre.tolist(),
            "seconds_per_reading": float(seconds_per_reading),
            "margin_deg": float(margin_deg),
            "margin_mm": float(margin_mm),
        },
        time.perf_counter() - t0,
        notes,
        centre,
        (float(margin_deg), float(margin_mm)),
    )
    bad = result.violations(with_margins=True)
    if len(bad):
        raise RuntimeError(  # never returned: the searches only keep feasible designs
            f"internal error: the plan breaks {len(bad)} reading constraint(s):\n{bad.head()}"
        )
    if add_minutes is not None:
        with progress_stage("choosing interferometer lines / ballbar circles to add"):
            adds.add_instruments(
                result,
                adds.ADDABLE if add_instruments is None else add_instruments,
                add_minutes,
                instrument_costs,
            )
        result.seconds = time.perf_counter() - t0
    return result


def _readable(
    ev: PlanEvaluator, machine: Machine, cons: Constraints, S: np.ndarray, centre: np.ndarray
) -> np.ndarray:
    """Candidate poses every station can read with every tool offset."""
    axes = _tool_axes(machine, ev.q, ev.t, cons.reflector.axis)
    bad = reading_violations(ev.points, axes, ev.station_of, S, cons, centre)
    ok = np.ones(len(ev.poses), bool)
    ok[np.unique(ev.pose_of[bad["reading"].to_numpy(int)])] = False
    return ok
