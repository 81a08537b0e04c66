"""Searches for a better plan: station placement (genetic algorithm, gradient-based
multi-start) and pose selection (exchange).

Every search minimises a :class:`~volcal.analysis.planning.evaluator.Scorer` criterion over
designs that satisfy the constraints (:mod:`volcal.analysis.planning.geometry`).  A station
may stand where it can read every selected point; stations are independent of each other,
so feasibility is checked (and repaired) station by station.

* :func:`genetic_placement`: paper 004's algorithm: a population of station sets,
  tournament selection, crossover at station level and blend, Gaussian mutation, then the
  constraint check after crossover and mutation (an infeasible station is drawn again
  inside the regions), elitism.  The population is scored in parallel (local processes or
  Dask, :func:`volcal.analysis.uncertainty.parallel.run_chunks`); the search saves a
  checkpoint after every generation and resumes from it.
* :func:`gradient_placement`: IPOPT on the station coordinates with exact derivatives of the
  criterion (CasADi through the problem's Jacobian; the gradient written out, see
  :meth:`~volcal.analysis.planning.evaluator.PlanEvaluator.criterion_functions`), the
  regions, distance, range and acceptance-angle constraints written as smooth
  inequalities (those the station's region cannot break left out: the region implies
  them), from several feasible starts, all drawn first and then solved in parallel like
  the GA's scores (each process builds the solvers it needs); line of sight is checked on
  each result (a start whose optimum a beam of which is blocked is discarded).
  Checkpointed after every start.
* :func:`exchange_poses`: a Fedorov-type exchange of poses between the plan and a candidate
  grid for the I-criterion, with rank-K updates of the information matrix.

Randomness comes from one seeded numpy Generator per search; the same seed gives the same
result wherever the scoring runs (scores are exact functions of the design).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from volcal.analysis.planning.evaluator import PlanEvaluator, Scorer
from volcal.analysis.planning.geometry import Constraints, stations_ok
from volcal.base.exceptions import InputError
from volcal.base.interrupts import raise_if_signalled

__all__ = [
    "SearchResult",
    "StationSampler",
    "genetic_placement",
    "gradient_placement",
    "exchange_poses",
]


@dataclass
class SearchResult:
    """Best stations (K, 3) mm, its criterion, the history (one row per generation or
    start: ``step``, ``best``, ``seconds``), evaluations and wall time (s)."""

    method: str
    stations: np.ndarray
    value: float
    history: list[dict[str, float]] = field(default_factory=list)
    evaluations: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


class StationSampler:
    """Feasible station positions for the readings of a plan (points (n, 3) mm, reflector
    axes turned with the tool (n, 3), workspace centre (3,) mm)."""

    def __init__(
        self,
        constraints: Constraints,
        points: np.ndarray,
        tool_axes: np.ndarray,
        centre: np.ndarray,
        *,
        bounds: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.constraints, self.points, self.tool_axes = constraints, points, tool_axes
        self.centre = np.asarray(centre, float)
        if not constraints.regions:
            if bounds is None:
                raise InputError("planning needs at least one region where stations may stand")
        self.bounds = bounds

    def ok(self, S: np.ndarray) -> np.ndarray:
        return stations_ok(S, self.points, self.tool_axes, self.constraints, self.centre)

    def draw(self, rng: np.random.Generator, n: int, max_tries: int = 200) -> np.ndarray:
        """n feasible positions (n, 3) mm, regions chosen in proportion to their volume."""
        regs = self.constraints.regions
        out = np.empty((0, 3))
        for _ in range(max_tries):
            m = max(4 * (n - len(out)), 16)
            if regs:
                vol = np.array([r.volume for r in regs])
                which = rng.choice(len(regs), size=m, p=vol / vol.sum())
                cand = np.vstack(
                    [regs[k].sample(rng, int(np.sum(which == k))) for k in range(len(regs))]
                )
            else:
                lo, hi = self.bounds  # type: ignore[misc]
                cand = rng.uniform(lo, hi, (m, 3))
            cand = cand[rng.permutation(len(cand))]
            out = np.vstack([out, cand[self.ok(cand)]])
            if len(out) >= n:
                return out[:n]
        raise InputError(
            f"found only {len(out)} of {n} feasible station positions in {max_tries} rounds: "
            f"{self._why(cand)}; widen a region, relax a constraint or cover less travel"
        )

    def _why(self, cand: np.ndarray) -> str:
        """Which constraint rules out how many of the candidate positions (a diagnosis)."""
        from volcal.analysis.planning.geometry import reading_violations

        cand = cand[:40]
        n = len(self.points)
        bad = reading_violations(
            np.tile(self.points, (len(cand), 1)),
            np.tile(self.tool_axes, (len(cand), 1)),
            np.repeat(np.arange(len(cand)), n),
            cand,
            self.constraints,
            self.centre,
        )
        counts = bad.groupby("constraint")["station"].nunique()
        parts = [f"{k} rules out {v} of {len(cand)}" for k, v in counts.items()]
        return "of the positions tried, " + (", ".join(parts) or "none is ruled out")


# ---- scoring in parallel ---------------------------------------------------------------


def _score_all(
    scorer: Scorer,
    designs: list[tuple[np.ndarray, np.ndarray | None]],
    workers: int | None,
    scheduler: Any,
) -> np.ndarray:
    from volcal.analysis.uncertainty.parallel import run_chunks

    # serial scoring also goes through run_chunks: one BLAS thread everywhere, so a
    # design scores bit-identically in this process, in a worker and on Dask
    n_chunks = min(len(designs), 4 * (workers or 2))
    bounds = np.linspace(0, len(designs), n_chunks + 1).astype(int)
    chunks = [(int(a), designs[a:b]) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    out = np.empty(len(designs))
    for (start, part), vals in run_chunks(scorer, chunks, workers=workers, scheduler=scheduler):
        out[start : start + len(part)] = vals
    return out


# ---- checkpoints -------------------------------------------------------------------------


def _save(path: Path | None, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    if path is None:
        return
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, meta=np.array(json.dumps(meta)), **arrays)  # type: ignore[arg-type]
    tmp.replace(path)  # atomic: a stopped search never leaves half a checkpoint


def _load(path: Path | None, kind: str, key: dict[str, Any]) -> dict[str, Any] | None:
    if path is None or not Path(path).exists():
        return None
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        if meta.get("kind") != kind or meta.get("key") != key:
            raise InputError(
                f"the checkpoint {path} belongs to another search "
                f"({meta.get('kind')}, {meta.get('key')}); expected {kind}, {key}",
                source=str(path),
            )
        out = {k: z[k] for k in z.files if k != "meta"}
    out["meta"] = meta
    return out


# ---- genetic algorithm (paper 004) ------------------------------------------------------


def genetic_placement(
    scorer: Scorer,
    sampler: StationSampler,
    n_stations: int,
    *,
    selected: np.ndarray | None = None,
    population: int = 40,
    generations: int = 30,
    crossover: float = 0.8,
    mutation: float = 0.2,
    elite: int = 2,
    seed: int = 0,
    initial: np.ndarray | None = None,
    workers: int | None = 1,
    scheduler: Any = None,
    checkpoint: Path | None = None,
    progress: Callable[[int, float], None] | None = None,
    fingerprint: str = "",
) -> SearchResult:
    """Paper 004's genetic algorithm on the station coordinates (see the module doc).
    ``initial``: a design (K, 3) put into the first population; ``checkpoint``: a file
    written after every generation and read at the start when it exists (the search
    continues from its last generation with the same random stream)."""
    t0 = time.perf_counter()
    K = int(n_stations)
    # a checkpoint of another problem (poses, tools, constraints: ``fingerprint``) is refused
    key = {
        "K": K,
        "population": population,
        "seed": seed,
        "criterion": scorer.criterion_name,
        "problem": fingerprint,
    }
    rng = np.random.default_rng(seed)
    state = _load(checkpoint, "ga", key)
    extent = _extent(sampler)
    if state is not None:
        pop, fit = state["population"], state["fitness"]
        gen0 = int(state["meta"]["generation"]) + 1
        rng.bit_generator.state = state["meta"]["rng"]
        history = state["meta"]["history"]
        n_eval = int(state["meta"]["evaluations"])
    else:
        pop = sampler.draw(rng, population * K).reshape(population, K, 3)
        if initial is not None:
            pop[0] = np.asarray(initial, float).reshape(K, 3)
        fit = _score_all(scorer, [(S, selected) for S in pop], workers, scheduler)
        gen0, history, n_eval = 0, [], population
    for gen in range(gen0, generations):
        order = np.argsort(fit)
        children = [pop[i].copy() for i in order[:elite]]
        while len(children) < population:
            a, b = _tournament(rng, fit), _tournament(rng, fit)
            c1, c2 = pop[a].copy(), pop[b].copy()
            if rng.random() < crossover:
                swap = rng.random(K) < 0.5  # station-level uniform crossover
                c1[swap], c2[swap] = pop[b][swap], pop[a][swap]
                lam = rng.random()  # and a blend of one station
                k = rng.integers(K)
                c1[k] = lam * pop[a][k] + (1 - lam) * pop[b][k]
            for c in (c1, c2):
                mut = rng.random((K, 3)) < mutation
                c += mut * rng.normal(0.0, 0.1, (K, 3)) * extent
                bad = ~sampler.ok(c)  # constraints after crossover and mutation
                if bad.any():
                    c[bad] = sampler.draw(rng, int(bad.sum()))
                children.append(c)
        pop = np.array(children[:population])
        fit = np.concatenate(
            [
                fit[order[:elite]],
                _score_all(scorer, [(S, selected) for S in pop[elite:]], workers, scheduler),
            ]
        )
        n_eval += population - elite
        best = float(fit.min())
        history.append({"step": gen, "best": best, "seconds": time.perf_counter() - t0})
        _save(
            checkpoint,
            {"population": pop, "fitness": fit},
            {
                "kind": "ga",
                "key": key,
                "generation": gen,
                "rng": rng.bit_generator.state,
                "history": history,
                "evaluations": n_eval,
            },
        )
        if progress is not None:
            progress(gen, best)
    i = int(np.argmin(fit))
    return SearchResult("ga", pop[i], float(fit[i]), history, n_eval, time.perf_counter() - t0)


def _tournament(rng: np.random.Generator, fit: np.ndarray, size: int = 3) -> int:
    idx = rng.choice(len(fit), size=size, replace=False)
    return int(idx[np.argmin(fit[idx])])


def _extent(sampler: StationSampler) -> np.ndarray:
    if sampler.constraints.regions:
        pts = np.vstack(
            [r.sample(np.random.default_rng(0), 64) for r in sampler.constraints.regions]
        )
        return np.ptp(pts, axis=0) + 1.0
    lo, hi = sampler.bounds  # type: ignore[misc]
    return np.asarray(hi, float) - np.asarray(lo, float)


# ---- gradient-based placement -----------------------------------------------------------


def _region_of(sampler: StationSampler, s: np.ndarray) -> int:
    for k, r in enumerate(sampler.constraints.regions):
        if r.contains(s)[0]:
            return k
    return 0


def gradient_placement(
    ev: PlanEvaluator,
    sampler: StationSampler,
    *,
    selected: np.ndarray | None = None,
    starts: int = 6,
    seed: int = 0,
    initial: np.ndarray | None = None,
    criterion: str = "I",
    max_iter: int = 60,
    workers: int | None = 1,
    scheduler: Any = None,
    checkpoint: Path | None = None,
    progress: Callable[[int, float], None] | None = None,
    fingerprint: str = "",
) -> SearchResult:
    """Multi-start IPOPT on the station coordinates (see the module doc).  The reading
    weights are those of each start's stations (the budget's distance dependence is weak);
    the result is scored again with its own weights.

    The starts are independent: every start design is drawn here first (the random stream
    and what the checkpoint records are those of drawing them one after the other), then
    the starts are solved where ``workers`` / ``scheduler`` say
    (:func:`volcal.analysis.uncertainty.parallel.run_chunks`: 1 this process, None every
    core with this one, a Dask address or Client), each by the same solver with one BLAS
    thread, so the result does not depend on where they ran.  The best start is the one
    of least criterion, the first of equal ones.  ``progress(n - 1, best)`` after the n-th
    start to finish, with the best criterion of the finished ones."""
    from volcal.analysis.uncertainty.parallel import default_workers, run_chunks

    t0 = time.perf_counter()
    if ev.frozen is None:
        raise RuntimeError("freeze the evaluator first")
    K = ev.n_stations
    scorer = ev.scorer
    cons = sampler.constraints
    rng = np.random.default_rng(seed)
    # the number of starts is not part of it: a search resumed with more starts goes on
    # with the same random stream
    key = {
        "K": K,
        "seed": seed,
        "criterion": criterion,
        "problem": fingerprint,
    }
    f_sym, fg_sym = ev.criterion_functions(criterion, selected)
    sel = np.ones(len(ev.poses), bool) if selected is None else np.asarray(selected, bool)
    use = sel[ev.pose_of] & (ev.station_of == 0)  # the points of one station's readings
    P = ev.points[use]
    Ax = sampler.tool_axes
    s = ca.MX.sym("s", 3 * K)
    pp = ca.MX.sym("w", f_sym.size1_in(1))
    f0 = float(scorer.score(initial if initial is not None else sampler.draw(rng, K), selected))
    fscale = 1.0 / max(f0 * f0, 1e-12)
    cos_h = np.cos(np.radians(cons.reflector.half_angle_deg))
    # the reading constraints of each station: (expression, lower, upper, kind) with one
    # row per point; kind "distance" rows may be dropped where the station's region
    # cannot break them (_reading_rows)
    rows_of: list[list[tuple[ca.MX, np.ndarray, np.ndarray, str]]] = []
    for k in range(K):
        sk = s[3 * k : 3 * k + 3]
        D = ca.repmat(sk.T, len(P), 1) - ca.DM(P)  # beams, point -> station
        d2 = ca.sum2(D * D)
        mine = []
        if cons.min_distance_mm > 0 or np.isfinite(cons.max_range_mm):
            # in metres: constraint values of order one (IPOPT's scaling is gradient based
            # and a squared range of 3.6e7 mm^2 stalls it)
            mine.append(
                (
                    ca.sqrt(d2) / 1000.0,
                    # small margins inside every limit: IPOPT may end a hair outside (1e-8
                    # scale)
                    np.full(len(P), cons.min_distance_mm / 1000.0 + 1e-6),
                    np.full(len(P), cons.max_range_mm / 1000.0 - 1e-6),
                    "distance",
                )
            )
        if cons.reflector.limited:
            ax: ca.MX | ca.DM
            if cons.reflector.axis is not None:
                ax = ca.DM(Ax)
            else:
                a = sk - ca.DM(sampler.centre)
                ax = ca.repmat((a / ca.norm_2(a)).T, len(P), 1)
            mine.append(
                (
                    ca.sum2(D * ax) / ca.sqrt(d2) - cos_h - 1e-7,
                    np.zeros(len(P)),
                    np.full(len(P), np.inf),
                    "angle" if cons.reflector.axis is not None else "aimed",
                )
            )
        rows_of.append(mine)
    results: list[tuple[float, np.ndarray]] = []
    history: list[dict[str, float]] = []
    n_eval = 0
    state = _load(checkpoint, "gradient", key)
    if state is not None:
        results = [(float(v), S) for v, S in zip(state["values"], state["stations"])]
        history = state["meta"]["history"]
        rng.bit_generator.state = state["meta"]["rng"]
    n_done = len(results)
    # every start design first, with the random stream's state after drawing it (what a
    # checkpoint after that start records): the draws are those of a search that solves
    # each start before drawing the next, wherever the starts are then solved
    drawn: list[np.ndarray] = []
    rng_after: list[Mapping[str, Any]] = []
    for j in range(n_done, starts):
        use_initial = j == 0 and initial is not None
        drawn.append(
            np.asarray(initial, float).reshape(K, 3) if use_initial else sampler.draw(rng, K)
        )
        rng_after.append(rng.bit_generator.state)
    # a start drawn where an earlier one began (the first draw of a round is the plan's
    # start design when both come from the same seed) ends where it ended: IPOPT is
    # deterministic, so it is solved once
    first_of: dict[bytes, int] = {}
    same_as: dict[int, int] = {}
    for i, S0 in enumerate(drawn):
        same_as[i] = first_of.setdefault(S0.tobytes(), i)
    problems: dict[tuple[int, ...], tuple[ca.Function, np.ndarray, np.ndarray]] = {}
    fv, gv = fg_sym(s, pp)
    grad_f = ca.Function("grad_f", [s, pp], [fscale * fv, fscale * gv])
    f = fscale * f_sym(s, pp)
    chunks = []
    for i, S0 in enumerate(drawn):
        if same_as[i] != i:
            continue
        # region of each station: fixed for this start (linear constraints); one problem
        # per assignment of stations to regions, shared by the starts
        regions = tuple(_region_of(sampler, S0[k]) for k in range(K)) if cons.regions else ()
        if regions not in problems:
            g, lbg, ubg = _reading_rows(rows_of, cons, regions, P, sampler.centre)
            problems[regions] = _placement_problem(s, pp, f, g, lbg, ubg, cons, regions)
        chunks.append((i, S0, regions, ev.weights(S0, selected)))
    side_by_side = scheduler is not None or (workers or default_workers()) > 1
    if side_by_side and n_done == 0 and initial is not None and chunks and chunks[0][0] == 0:
        # the start at ``initial`` (in a later round the plan's stations, an optimum for
        # the previous selection: the fewest iterations, 12 against 25-60 for mcv754) in
        # the middle: the workers take the starts from the front and this process from
        # the back (run_chunks), so it is among the last taken, where a short start
        # evens out the processes' ends; results are kept by start, whatever the order
        chunks.insert(len(chunks) // 2, chunks.pop(0))
    kernel = _PlacementKernel(problems, grad_f, max_iter, scorer, sampler, selected)
    base = len(results)  # starts done before (a checkpoint); drawn[i] is start base + i
    ended: dict[int, tuple[float, np.ndarray]] = {}

    def record(i: int, value: float, S: np.ndarray) -> None:
        """Drawn start i (and the later ones drawn at its start design) has ended: the
        finished starts without a gap go into the results, the history and the
        checkpoint (a resumed search draws the rest), in the order of the starts."""
        for d in range(i, len(drawn)):
            if same_as[d] == i:
                ended[d] = (value, S)
        m = len(results) - base
        if m not in ended:
            return
        while m in ended:
            results.append(ended[m])
            best = min(v for v, _ in results)
            history.append({"step": base + m, "best": best, "seconds": time.perf_counter() - t0})
            m += 1
        _save(
            checkpoint,
            {
                "values": np.array([v for v, _ in results]),
                "stations": np.array([S for _, S in results]),
            },
            {"kind": "gradient", "key": key, "rng": rng_after[m - 1], "history": history},
        )

    before = [v for v, _ in results]
    for (i, *_), (value, S, iters) in run_chunks(
        kernel, chunks, workers=workers, scheduler=scheduler
    ):
        n_eval += iters
        record(i, value, S)
        if progress is not None:
            progress(base + len(ended) - 1, min(before + [v for v, _ in ended.values()]))
    best = min(results, key=lambda r: r[0])  # the first of the least: the lowest start
    notes = []
    n_bad = sum(1 for v, _ in results if not np.isfinite(v))
    if n_bad:
        notes.append(f"{n_bad} of {starts} starts ended where a constraint (line of sight) fails")
    return SearchResult(
        "gradient",
        best[1],
        float(best[0]),
        history,
        n_eval,
        time.perf_counter() - t0,
        notes,
    )


class _PlacementKernel:
    """One start of the placement search, for :func:`run_chunks`: the NLP of every
    assignment of stations to regions (a Function of the station coordinates and the
    weights, with its constraint bounds), the objective's gradient Function, the scorer
    and the sampler's constraint check, picklable (CasADi Functions travel serialised).
    Each process builds the IPOPT solver of an assignment when a start first needs it and
    keeps it (building one is a few milliseconds, see :func:`_placement_solver`: in the
    processes that solve, not before the work is shared out).
    ``run_chunk((index, S0, regions, weights))`` solves from the start design S0 (K, 3)
    mm and returns (criterion of the result, or inf where it breaks a constraint; stations
    (K, 3) mm; IPOPT iterations + 1)."""

    def __init__(
        self,
        problems: dict[tuple[int, ...], tuple[ca.Function, np.ndarray, np.ndarray]],
        grad_f: ca.Function,
        max_iter: int,
        scorer: Scorer,
        sampler: StationSampler,
        selected: np.ndarray | None,
    ):
        self.problems, self.grad_f, self.max_iter = problems, grad_f, int(max_iter)
        self.scorer, self.sampler, self.selected = scorer, sampler, selected
        self._solvers: dict[tuple[int, ...], ca.Function] = {}

    def __getstate__(self) -> dict[str, Any]:
        # the Functions in one CasADi serialisation: the criterion graph they share (its
        # constant matrices) is written once, not once per Function; no solvers (built
        # where they run)
        d = dict(self.__dict__)
        keys = list(self.problems)
        ss = ca.StringSerializer()
        ss.pack([self.grad_f] + [self.problems[k][0] for k in keys])
        d["problems"] = (keys, ss.encode(), [self.problems[k][1:] for k in keys])
        d["grad_f"] = None
        d["_solvers"] = {}
        return d

    def __setstate__(self, d: dict[str, Any]) -> None:
        keys, packed, bounds = d["problems"]
        fs = ca.StringDeserializer(packed).unpack()
        d["grad_f"] = fs[0]
        d["problems"] = {k: (f, *b) for k, f, b in zip(keys, fs[1:], bounds)}
        self.__dict__.update(d)

    def solver(self, regions: tuple[int, ...]) -> ca.Function:
        """The IPOPT solver of an assignment of stations to regions, built at first use."""
        solver = self._solvers.get(regions)
        if solver is None:
            nlp = self.problems[regions][0]
            solver = self._solvers[regions] = _placement_solver(nlp, self.max_iter, self.grad_f)
        return solver

    def run_chunk(self, chunk: tuple[int, np.ndarray, tuple[int, ...], np.ndarray]):
        _, S0, regions, w = chunk
        _, lb_all, ub_all = self.problems[regions]
        solver = self.solver(regions)
        sol = solver(x0=S0.ravel(), p=w, lbg=lb_all, ubg=ub_all)
        raise_if_signalled()  # IPOPT ends early on Ctrl-C / SIGTERM and returns
        iters = int(solver.stats().get("iter_count", 0)) + 1
        S = np.asarray(sol["x"]).reshape(S0.shape)
        ok = self.sampler.ok(S).all()
        value = self.scorer.score(S, self.selected) if ok else float("inf")
        return float(value), S, iters


def _reading_rows(
    rows_of: list[list[tuple[Any, np.ndarray, np.ndarray, str]]],
    cons: Constraints,
    regions: tuple[int, ...],
    P: np.ndarray,
    centre: np.ndarray,
) -> tuple[Any, list[np.ndarray], list[np.ndarray]]:
    """The reading constraints of every station for one assignment of stations to
    regions (indices into ``cons.regions``; () when there are none), without those no
    position in the station's region can break: a minimum distance below the nearest
    position, a range above the farthest (1 mm to spare), and the acceptance angle of a
    reflector re-aimed at every set-up (its axis from the workspace ``centre`` to the
    station) at a point p whose beam cannot turn that far: in the triangle station,
    centre, p the angle at the station is below arcsin(|p - centre| / |station -
    centre|) when |p - centre| is the shorter side (0.5 deg to spare).  The region's
    own constraints imply it, so the feasible set is the same, and IPOPT's cost per
    iteration grows with the number of constraints (its back-solves dominate once the
    criterion is cheap).  The plan is checked against every constraint afterwards."""
    g, lbg, ubg = [], [], []
    for k, mine in enumerate(rows_of):
        lo_box = hi_box = None
        if regions:
            c = cons.regions[regions[k]].corners()
            lo_box, hi_box = c.min(0) - 1.0, c.max(0) + 1.0  # mm, with room to spare
        for expr, lb, ub, kind in mine:
            lb, ub = lb.copy(), ub.copy()
            if kind == "distance" and lo_box is not None:
                # nearest: to the region's bounding box; farthest: a corner (convex)
                near = np.linalg.norm(P - np.clip(P, lo_box, hi_box), axis=1) / 1000.0
                far = np.max(np.linalg.norm(P[:, None, :] - c[None], axis=2), axis=1) + 1.0
                lb[near > lb + 1e-3] = -np.inf
                ub[far / 1000.0 < ub] = np.inf
            elif kind == "aimed" and lo_box is not None:
                d_c = np.linalg.norm(centre - np.clip(centre, lo_box, hi_box))
                ratio = np.linalg.norm(P - centre, axis=1) / max(d_c, 1e-9)
                turn = np.degrees(np.arcsin(np.minimum(ratio, 1.0)))
                lb[(ratio < 1.0) & (turn < cons.reflector.half_angle_deg - 0.5)] = -np.inf
            keep = np.isfinite(lb) | np.isfinite(ub)
            if keep.all():
                g.append(expr)
            elif keep.any():
                g.append(expr[np.flatnonzero(keep).tolist()])
            lbg.append(lb[keep])
            ubg.append(ub[keep])
    return (ca.vertcat(*g) if g else ca.MX(0, 1)), lbg, ubg


def _placement_problem(s, pp, f, g_base, lbg, ubg, cons, regions):
    """The NLP on the station coordinates ``s`` with weights ``pp``: objective f, the
    smooth reading constraints g_base and the half-spaces of each station's region
    ``regions`` (indices into ``cons.regions``).  Returns (Function (x, p) -> (f, g), as
    ``nlpsol`` builds it from the expressions; lbg; ubg)."""
    K = s.shape[0] // 3
    gg, lb, ub = [g_base], list(lbg), list(ubg)
    if regions:
        A_rows, b_rows = [], []
        for k, r in enumerate(regions):
            A, b = cons.regions[r].halfspaces()
            Ak = np.zeros((len(A), 3 * K))
            Ak[:, 3 * k : 3 * k + 3] = A
            A_rows.append(Ak)
            b_rows.append(b)
        Aall = np.vstack(A_rows)
        gg.append(ca.mtimes(ca.DM(Aall), s))
        lb.append(np.full(len(Aall), -np.inf))
        ub.append(np.concatenate(b_rows) - 1e-4)
    nlp = ca.Function(
        "nlp", {"x": s, "p": pp, "f": f, "g": ca.vertcat(*gg)}, ["x", "p"], ["f", "g"]
    )
    cat = np.concatenate
    return nlp, (cat(lb) if lb else np.zeros(0)), (cat(ub) if ub else np.zeros(0))


def _placement_solver(nlp: ca.Function, max_iter: int, grad_f: ca.Function) -> ca.Function:
    """IPOPT on the NLP of :func:`_placement_problem`, the objective's value and gradient
    from the Function ``grad_f(s, pp)`` (written out rather than reverse AD)."""
    return ca.nlpsol("placement", "ipopt", nlp, _placement_options(max_iter, grad_f))


def _placement_options(max_iter: int, grad_f: ca.Function) -> dict[str, Any]:
    """The options of :func:`_placement_solver`."""
    from volcal.solve.ipopt import NO_PARAMETER_MULTIPLIERS

    return {
        "ipopt.print_level": 0,
        "print_time": False,
        "ipopt.hessian_approximation": "limited-memory",
        # the quasi-Newton update inside the augmented system (one solve per step)
        # instead of Sherman-Morrison's back-solves per stored pair: the same step,
        # a third less of IPOPT's own time with hundreds of reading constraints
        "ipopt.limited_memory_aug_solver": "extended",
        "ipopt.max_iter": max_iter,
        "ipopt.tol": 1e-6,
        "ipopt.acceptable_tol": 1e-4,
        "ipopt.sb": "yes",
        "ipopt.bound_relax_factor": 0.0,
        "grad_f": grad_f,
        # the weights' multipliers are never read: no reverse AD through the whole
        # criterion graph for them (0.07 s for the first solver of a graph, 0.013 s for
        # each later one); the iterates are the same (a test)
        **NO_PARAMETER_MULTIPLIERS,
    }


# ---- pose exchange ---------------------------------------------------------------------


def _exchange_effects(
    A: np.ndarray,
    blocks: list[np.ndarray],
    stacked: np.ndarray | None,
    Minv: np.ndarray,
    MWM: np.ndarray,
    sel: np.ndarray,
    allowed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(gain, loss) of the trace(W M^-1) criterion per candidate pose: what adding an
    unselected allowed pose takes off, tr((I + V)^-1 U), and what removing a selected one
    adds, tr((I - V)^-1 U), with V = A_c M^-1 A_c^T and U = A_c M^-1 W M^-1 A_c^T of the
    pose's rows A_c; -inf / inf where a pose cannot be added / removed."""
    gain = np.full(len(sel), -np.inf)
    loss = np.full(len(sel), np.inf)
    if stacked is not None:
        AM = stacked @ Minv  # (n, k, r)
        At = np.swapaxes(stacked, 1, 2)
        V, U = AM @ At, (stacked @ MWM) @ At  # (n, k, k)
        eye = np.eye(V.shape[1])
        sign = np.where(sel, -1.0, 1.0)[:, None, None]
        use = sel | allowed
        try:
            X = np.linalg.solve(eye + sign[use] * V[use], U[use])
        except np.linalg.LinAlgError:  # a singular one: pose by pose below
            pass
        else:
            tr = np.trace(X, axis1=1, axis2=2)
            idx = np.flatnonzero(use)
            loss[idx[sel[use]]] = tr[sel[use]]
            gain[idx[~sel[use]]] = tr[~sel[use]]
            return gain, loss
    for c, rows in enumerate(blocks):
        Ac = A[rows]
        V = Ac @ Minv @ Ac.T
        U = Ac @ MWM @ Ac.T
        k = len(rows)
        if sel[c]:
            try:  # removing: trace increases by tr((I - V)^-1 U)
                loss[c] = np.trace(np.linalg.solve(np.eye(k) - V, U))
            except np.linalg.LinAlgError:
                loss[c] = np.inf
        elif allowed[c]:
            gain[c] = np.trace(np.linalg.solve(np.eye(k) + V, U))
    return gain, loss


def exchange_poses(
    scorer: Scorer,
    stations: np.ndarray,
    selected: np.ndarray,
    *,
    max_exchanges: int = 200,
    allowed: np.ndarray | None = None,
) -> tuple[np.ndarray, float, int]:
    """Fedorov-type exchange of poses (the I-criterion, or the scorer's criterion when it
    is not I) with the stations fixed: repeatedly swap the selected pose whose removal
    costs least for the candidate whose addition gains most (rank-K updates of M and of
    the criterion), keeping the swap when the exact criterion improves.  Returns
    (selected mask, criterion, swaps made).  ``allowed``: candidates that may be added
    (e.g. those every station can read)."""
    sel = np.asarray(selected, bool).copy()
    allowed = np.ones(len(sel), bool) if allowed is None else np.asarray(allowed, bool)
    J = scorer.jacobian(stations, np.ones(len(sel), bool))
    A = J[:, scorer.free] @ scorer.Z  # (N, r) every reading of every candidate
    pose = scorer.pose_of
    blocks = [np.flatnonzero(pose == c) for c in range(len(sel))]
    # every candidate has the same readings (each station, each tool offset): one stack
    # (n_candidates, k, r) scored at once instead of a Python loop over candidates
    stacked = A[np.array(blocks)] if len({len(b) for b in blocks}) == 1 else None
    M = A[sel[pose]].T @ A[sel[pose]]
    best = scorer.value(M)
    swaps = 0
    W = scorer.B.T @ scorer.B  # (r, r): the I-criterion is trace(W M^-1) / n_eval
    tried: set[tuple[int, int]] = set()
    for _ in range(max_exchanges):
        Minv = np.linalg.inv(M)
        MWM = Minv @ W @ Minv
        gain, loss = _exchange_effects(A, blocks, stacked, Minv, MWM, sel, allowed)
        improved = False
        for add in np.argsort(-gain)[:5]:
            if not np.isfinite(gain[add]):
                break
            for rem in np.argsort(loss)[:5]:
                if not sel[rem] or (add, rem) in tried:
                    continue
                tried.add((int(add), int(rem)))
                M2 = M + A[blocks[add]].T @ A[blocks[add]] - A[blocks[rem]].T @ A[blocks[rem]]
                v = scorer.value(M2)
                if v < best * (1 - 1e-9):
                    sel[add], sel[rem] = True, False
                    M, best, swaps, improved = M2, v, swaps + 1, True
                    break
            if improved:
                break
        if not improved:
            break
    return sel, float(best), swaps
