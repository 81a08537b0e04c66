"""Input quantities of the Monte Carlo method (GUM Supplement 1) and their sampling.

The measurand (error parameters, stations, volumetric errors) is a function of the input
quantities through the identification.  The inputs and their PDFs, centred on the values
the identification used:

* every length source of the budget (``applies_to = "length"``): an independent draw per
  reading, at the reading's length (``magnitude + per_metre * L``);
* every axis source (``axis:<NAME>``, positioning repeatability): an independent draw per
  reading (every station visit repositions the machine), acting on the reading through
  ``dL/dq = u . dP/dq`` (u the beam direction);
* the drift of the budget (drift model and drift sources), one realisation per station
  over the readings' time stamps (needs a ``time`` column; otherwise reported as absent);
* optionally the tool (reflector) offsets: one draw per distinct offset per trial, normal
  with standard uncertainty ``tool_sigma_mm`` per component, acting through ``u . dP/dt``;
* optionally the positions of stations held fixed in the identification: one draw per
  coordinate per trial, normal with standard uncertainty ``station_sigma_mm``.

Axis and tool offset changes act on the readings through the first-order (in the change)
sensitivity: the neglected term is of order ``dq^2 / L`` (0.8 um over 600 mm:
1e-9 um), far below anything reported.

Randomness: trial ``i`` draws from ``Generator(PCG64(SeedSequence(seed, spawn_key=(i,))))``,
every source in a fixed order and always (a source switched off is drawn and discarded),
so a trial's draws of a source are the same in every run with that seed - whatever the
number of workers, the chunking, or which other sources are on.  The one-source-at-a-time
contributions therefore use the same draws as the full run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from volcal.measurement.budget import Budget

__all__ = ["InputSource", "InputSampler", "trial_rng"]


def trial_rng(seed: int, trial: int) -> np.random.Generator:
    """The random stream of one trial (independent of chunking and workers)."""
    return np.random.Generator(
        np.random.PCG64(np.random.SeedSequence(int(seed), spawn_key=(int(trial),)))
    )


@dataclass(frozen=True)
class InputSource:
    """One input of the Monte Carlo method: ``name`` (the budget source name, ``drift``,
    ``tool_offsets`` or ``stations``), ``kind`` and a description."""

    name: str
    kind: str
    description: str


@dataclass
class InputSampler:
    """Draws reading changes dm (mm) and changes of held variables for trials (numpy only,
    picklable).  Build it with :meth:`build`."""

    sources: list[InputSource]
    budget: Budget
    length_mm: np.ndarray  # (N,) reading lengths for per-metre sources
    axis_names: list[str]
    axis_sens: np.ndarray  # (N, n_axes) dL/dq (mm/mm or mm/rad)
    time_s: np.ndarray  # (N,) NaN where unknown
    station_rows: list[np.ndarray]  # readings of each station
    tool_group: np.ndarray  # (N,) index of each reading's tool offset
    tool_sens: np.ndarray  # (N, 3) dL/dt
    tool_sigma_mm: float
    fixed_station_vars: np.ndarray  # indices (into the held-variable vector) of station xyz
    station_sigma_mm: float
    n_fixed: int
    notes: list[str] = field(default_factory=list)

    @classmethod
    def build(
        cls,
        machine,
        q: np.ndarray,
        tool: np.ndarray,
        station_index: np.ndarray,
        beam_unit: np.ndarray,
        length_mm: np.ndarray,
        budget,
        *,
        time_s: np.ndarray | None = None,
        fixed: np.ndarray | None = None,
        station_slice: slice | None = None,
        tool_sigma_mm: float = 0.0,
        station_sigma_mm: float = 0.0,
    ) -> InputSampler:
        """Sensitivities from the machine (nominal model) at the readings' poses q (N,
        n_axes; mm, rad) and tools (N, 3); beam_unit (N, 3) unit vectors station ->
        point; length_mm (N,) the readings' lengths; budget: a Budget."""
        q = np.asarray(q, float)
        tool = np.asarray(tool, float)
        N = len(q)
        zeros = np.zeros(machine.n_errors)
        # the machine is evaluated once per distinct pose and tool offset (every station
        # sees the same poses): the same numbers as per reading, in a fraction of the time
        _, first, pose = np.unique(
            np.hstack([q, tool]), axis=0, return_index=True, return_inverse=True
        )
        pose = pose.ravel()
        qd, td = q[first], tool[first]

        def point(qq: np.ndarray, tt: np.ndarray) -> np.ndarray:
            return machine.evaluate(qq, tt, zeros)[0][pose]

        p0 = point(qd, td)
        names = list(machine.axis_names)
        sens = np.zeros((N, len(names)))
        h = 1e-6
        for k, a in enumerate(names):
            if budget.axis_sigma(a) == 0.0:
                continue
            dq = np.zeros_like(qd)
            dq[:, k] = h
            p1 = point(qd + dq, td)
            pm = point(qd - dq, td)
            sens[:, k] = np.einsum("ni,ni->n", beam_unit, (p1 - pm) / (2 * h))
        # tool offsets: P is affine in t (the tool frame's rotation), so differences are exact
        tsens = np.zeros((N, 3))
        groups, tool_group = np.unique(np.round(tool, 9), axis=0, return_inverse=True)
        if tool_sigma_mm > 0:
            for k in range(3):
                dt = np.zeros(3)
                dt[k] = 1.0
                p1 = point(qd, td + dt)
                tsens[:, k] = np.einsum("ni,ni->n", beam_unit, p1 - p0)
        st_idx = np.asarray(station_index, int)
        rows = [np.flatnonzero(st_idx == s) for s in range(int(st_idx.max()) + 1)]
        time_s = np.full(N, np.nan) if time_s is None else np.asarray(time_s, float)
        fixed = np.zeros(0, bool) if fixed is None else np.asarray(fixed, bool)
        fixed_idx = np.flatnonzero(fixed)
        fsv = np.zeros(0, int)
        if station_slice is not None and station_sigma_mm > 0:
            sl = np.arange(station_slice.start, station_slice.stop)
            xyz = sl[(sl - station_slice.start) % 4 < 3]
            pos = {v: i for i, v in enumerate(fixed_idx)}
            fsv = np.array([pos[v] for v in xyz if v in pos], int)

        sources: list[InputSource] = []
        notes: list[str] = []
        for s in budget.length_sources:
            sources.append(
                InputSource(
                    s.name,
                    "length",
                    f"{s.distribution} length error "
                    f"({s.magnitude:g} + {s.per_metre:g} L/m {s.unit})",
                )
            )
        for a in names:
            s = budget.axis_sources.get(a)
            if s is not None:
                sources.append(
                    InputSource(
                        s.name,
                        "axis",
                        f"{s.distribution} positioning "
                        f"repeatability of {a} ({s.magnitude:g} {s.unit})",
                    )
                )
        has_drift = budget.drift is not None or bool(budget.drift_sources)
        if has_drift:
            if np.all(np.isfinite(time_s)):
                sources.append(
                    InputSource(
                        "drift",
                        "drift",
                        "drift of the length readings, one realisation per station",
                    )
                )
            else:
                notes.append(
                    "the budget has drift but the data have no time stamps: drift left out"
                )
        if tool_sigma_mm > 0:
            sources.append(
                InputSource(
                    "tool_offsets",
                    "tool",
                    f"normal, u = {tool_sigma_mm * 1e3:g} um per component and offset",
                )
            )
        if fsv.size:
            sources.append(
                InputSource(
                    "stations",
                    "station",
                    f"normal, u = "
                    f"{station_sigma_mm * 1e3:g} um per coordinate of the "
                    "fixed stations",
                )
            )
        elif station_sigma_mm > 0:
            notes.append(
                "station uncertainty given but no station is held fixed: the "
                "stations are estimated, their uncertainty is an output"
            )
        return cls(
            sources,
            budget,
            np.asarray(length_mm, float),
            names,
            sens,
            time_s,
            rows,
            tool_group,
            tsens,
            float(tool_sigma_mm),
            fsv,
            float(station_sigma_mm),
            int(fixed.sum()),
            notes,
        )

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.sources]

    def _mask(self, enabled) -> list[bool]:
        if enabled is None:
            return [True] * len(self.sources)
        enabled = set(enabled)
        unknown = enabled - set(self.names)
        if unknown:
            raise ValueError(f"unknown input source(s) {sorted(unknown)}; sources: {self.names}")
        return [s.name in enabled for s in self.sources]

    def draw(self, seed: int, trials, enabled=None) -> tuple[np.ndarray, np.ndarray]:
        """(dm (B, N) mm, dx_fixed (B, n_fixed)) for the given trial indices."""
        trials = list(trials)
        on = self._mask(enabled)
        N = self.length_mm.size
        dM = np.zeros((len(trials), N))
        dX = np.zeros((len(trials), self.n_fixed))
        plan = self._plan()
        bud = self.budget
        # a rectangular draw is (2 u - 1) s with u uniform on [0, 1) (u = k 2^-53): u - 0.5
        # and 2 s are exact, so (u - 0.5) (2 s) is the same double as (2 u - 1) s, in one
        # pass less
        steps = [
            (kind, dist, None if scale is None else (scale if dist == "normal" else 2.0 * scale))
            for kind, dist, scale in plan
        ]
        buf = np.empty(N)
        for b, i in enumerate(trials):
            g = trial_rng(seed, i)
            row = dM[b]
            for k, (kind, dist, f) in enumerate(steps):
                if kind == "reading":
                    # the distributions of Source.sample, drawn without its per-call overhead
                    if dist == "normal":
                        g.standard_normal(out=buf)
                    else:
                        g.random(out=buf)
                        buf -= 0.5
                    if on[k]:
                        assert f is not None  # a reading source always has its factor
                        buf *= f
                        row += buf
                elif kind == "drift":
                    for rows in self.station_rows:
                        v = bud.sample_drift(self.time_s[rows], g)
                        if on[k]:
                            row[rows] += v
                elif kind == "tool":
                    n_g = int(self.tool_group.max()) + 1
                    dt = g.normal(0.0, self.tool_sigma_mm, (n_g, 3))
                    if on[k]:
                        row += np.einsum("ni,ni->n", self.tool_sens, dt[self.tool_group])
                elif kind == "station":
                    v = g.normal(0.0, self.station_sigma_mm, self.fixed_station_vars.size)
                    if on[k]:
                        dX[b, self.fixed_station_vars] += v
        return dM, dX

    def _plan(self) -> list[tuple[str, str, np.ndarray | None]]:
        """Per source (in order): (kind, distribution, per-reading factor on a standard
        draw: the standard deviation for normal, the half-width for rectangular, times the
        sensitivity for axis sources)."""
        plan = getattr(self, "_plan_cache", None)
        if plan is not None:
            return plan
        bud = self.budget
        plan = []
        for s in self.sources:
            if s.kind == "length":
                src = next(x for x in bud.length_sources if x.name == s.name)
                if src.distribution == "normal":
                    f = np.asarray(src.standard_uncertainty(self.length_mm), float)
                else:
                    f = np.asarray(src.half_width(self.length_mm), float)
                plan.append(("reading", src.distribution, f * np.ones(self.length_mm.size)))
            elif s.kind == "axis":
                j = next(
                    j
                    for j, a in enumerate(self.axis_names)
                    if bud.axis_sources.get(a) is not None and bud.axis_sources[a].name == s.name
                )
                src = bud.axis_sources[self.axis_names[j]]
                v = (
                    float(src.standard_uncertainty())
                    if src.distribution == "normal"
                    else float(src.half_width())
                )
                plan.append(("reading", src.distribution, v * self.axis_sens[:, j]))
            else:
                plan.append((s.kind, "", None))
        self._plan_cache = plan
        return plan

    def __getstate__(self):
        d = dict(self.__dict__)
        d.pop("_plan_cache", None)
        return d

    # ---- linearised covariance of the inputs --------------------------------------------
    def reading_variance(self, name: str) -> np.ndarray | None:
        """Per-reading variance (N,) of an independent-per-reading source, else None."""
        bud = self.budget
        for s in bud.length_sources:
            if s.name == name:
                return np.asarray(s.standard_uncertainty(self.length_mm), float) ** 2 * np.ones(
                    self.length_mm.size
                )
        for j, a in enumerate(self.axis_names):
            src = bud.axis_sources.get(a)
            if src is not None and src.name == name:
                return (float(src.standard_uncertainty()) * self.axis_sens[:, j]) ** 2
        return None

    def propagate(self, Km: np.ndarray, Kx: np.ndarray, name: str) -> np.ndarray:
        """Linearised covariance (n, n) of the estimate from one input source, through
        dx = Km dm + Kx dx_fixed."""
        var = self.reading_variance(name)
        if var is not None:
            A = Km * np.sqrt(var)[None, :]
            return A @ A.T
        src = next(s for s in self.sources if s.name == name)
        n = Km.shape[0]
        if src.kind == "tool":
            out = np.zeros((n, n))
            for gidx in range(int(self.tool_group.max()) + 1):
                rows = self.tool_group == gidx
                A = Km[:, rows] @ self.tool_sens[rows] * self.tool_sigma_mm
                out += A @ A.T
            return out
        if src.kind == "station":
            A = Kx[:, self.fixed_station_vars] * self.station_sigma_mm
            return A @ A.T
        if src.kind == "drift":
            out = np.zeros((n, n))
            bud = self.budget
            for rows in self.station_rows:
                t = self.time_s[rows]
                C = np.zeros((t.size, t.size))
                if bud.drift is not None:
                    A_ = np.asarray(bud.drift.amplitude_mm)
                    w_ = np.asarray(bud.drift.omega_rad_s)
                    dt = t[:, None] - t[None, :]
                    if bud.drift.random_phase:
                        C += sum(a * a / 2 * np.cos(w * dt) for a, w in zip(A_, w_))
                    # fixed phases: deterministic, no variance
                tau = t - t.min()
                for s in bud.drift_sources:
                    C += float(s.standard_uncertainty()) ** 2 * np.outer(tau, tau)
                Ks = Km[:, rows]
                out += Ks @ C @ Ks.T
            return out
        raise ValueError(name)  # pragma: no cover
