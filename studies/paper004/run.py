"""Paper 004 study: where to put the laser tracker (station placement) and how good the
predicted uncertainty of a plan is.

Paper 004 places four tracker stations with a genetic algorithm whose fitness is the Monte
Carlo RMSE of the identified coordinates, under the reflector's viewing-angle condition and
the feasible area on the floor; the optimised arrangement gives 4.5 um RMS against 5.2 um
and 6.4 um when one station is replaced (Cases 1 and 2).  The study runs volcal's planner
(:mod:`volcal.analysis.planning`) on a stand-in of the paper's setting (config.toml):

* ``comparison``: the predicted volumetric uncertainty (I-criterion, modulo the rigid motion
  no multilateration sees) of the optimised layout, of a hand-made one, of the optimised
  layout with one station replaced (the paper's Cases 1 and 2) and of random feasible
  layouts, each next to the RMS error *achieved* when simulated measurements of the plan
  are identified with ``volcal.identify`` (volcal's simulator, the budget's noise, a random
  truth of about 50 um, drawn from the model's own basis);
* ``outside``: the same for a truth *outside* the model's basis, drawn and measured by the
  independent rigid-body simulator of the test suite (tests/indep_sim.py: sines of
  non-integer periods, smooth steps and tables, not satisfying the datum), with the part
  of that truth no parameter set of the model can represent (the representation floor);
* ``search``: paper 004's GA (Monte Carlo fitness), the same GA on the I-criterion and
  gradient-based placement (IPOPT with CasADi derivatives): criterion reached, evaluations
  and time, the time as the median of ``timing_repeats`` repeated runs of every search with
  the machine's load average at the start of each.

    python studies/paper004/run.py [--smoke] [--out DIR] [--update-readme] [--workers N]

``--smoke`` without ``--out`` writes into a new temporary folder.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import tomllib
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import readme_tables as rt  # noqa: E402

# the independent simulator lives with the tests (as for studies/datum and paper000)
sys.path.insert(0, str(HERE.parents[1] / "tests"))
import indep_sim as ind  # noqa: E402

PAPER_UM = {"optimised": 4.5, "Case 1": 5.2, "Case 2": 6.4}


def setup(cfg: dict):
    from volcal.analysis.planning import constraints_from_dict
    from volcal.analysis.planning.evaluator import PlanEvaluator
    from volcal.analysis.planning.plan import _tool_axes, candidate_poses
    from volcal.analysis.planning.search import StationSampler
    from volcal.model.errors import ErrorModel
    from volcal.model.machine import Machine

    st = cfg["setting"]
    machine = Machine.from_model(HERE / st["model"])
    em = ErrorModel(machine.spec)
    cons = constraints_from_dict(cfg["constraints"])
    cand = candidate_poses(machine, int(st["grid"]))
    q = machine.axis_to_internal(cand[machine.axis_names].to_numpy(float))
    tools = np.asarray(st["tools"], float)
    K = int(st["stations"])
    ev = PlanEvaluator(machine, em, q, tools, K, st["budget"])
    n_poses = int(st["readings"]) // (K * len(tools))
    sel = np.zeros(len(cand), bool)
    sel[:n_poses] = True  # the grid, every pose (the paper places stations, not poses)
    centre = 0.5 * (ev.points.min(0) + ev.points.max(0))
    use = sel[ev.pose_of] & (ev.station_of == 0)
    axes = _tool_axes(machine, ev.q[use], ev.t[use], cons.reflector.axis)
    sampler = StationSampler(cons, ev.points[use], axes, centre)
    manual = np.asarray(cfg["manual"]["stations"], float)
    ok = sampler.ok(manual)
    if not ok.all():
        raise SystemExit(f"config: manual station(s) {np.flatnonzero(~ok) + 1} break a constraint")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ev.freeze(manual, sel)
    return machine, em, cons, cand, ev, sel, sampler, manual


def repeated_searches(cfg, ev, sel, sampler, manual, size: dict, workers: int):
    """Every search run ``size["timing_repeats"]`` times (the same seeds, so the same
    results): {label: (result of the first run, [seconds of each run])}, [gradient result
    of each run] and the 1, 5 and 15 min load averages at the start of each run."""
    runs, loads = [], []
    for _ in range(int(size["timing_repeats"])):
        loads.append(os.getloadavg())
        runs.append(searches(cfg, ev, sel, sampler, manual, size, workers))
    out = {k: (r, [run[k][1] for run in runs]) for k, (r, _) in runs[0].items()}
    grads = [run[GRADIENT][0] for run in runs]
    return out, grads, loads


GRADIENT = "gradient (IPOPT, CasADi derivatives of I)"


def searches(cfg, ev, sel, sampler, manual, size: dict, workers: int):
    import copy

    from volcal.analysis.planning.search import genetic_placement, gradient_placement

    seed = int(cfg["search"]["seed"])
    out = {}
    t = time.perf_counter()
    g = gradient_placement(ev, sampler, selected=sel, starts=int(size["gradient_starts"]),
                           seed=seed)
    out[GRADIENT] = (g, time.perf_counter() - t)
    sc_i = ev.scorer
    sc_nl = copy.copy(ev.scorer)
    sc_nl.criterion_name = "MC-nonlinear"
    sc_nl.mc_trials = int(size["mc_trials_nonlinear"])
    sc_mc = copy.copy(ev.scorer)
    sc_mc.criterion_name = "MC"
    sc_mc.mc_trials = int(size["mc_trials_fitness"])
    variants = (
        ("GA, Monte Carlo fitness, every trial identified (paper 004)", sc_nl, "ga_nl"),
        ("GA, Monte Carlo fitness, trials linearised", sc_mc, "ga"),
        ("GA, I-criterion fitness", sc_i, "ga"),
    )
    for label, sc, key in variants:
        t = time.perf_counter()
        r = genetic_placement(
            sc,
            sampler,
            ev.n_stations,
            selected=sel,
            population=int(size[f"{key}_population"]),
            generations=int(size[f"{key}_generations"]),
            seed=seed,
            workers=workers,
        )
        out[label] = (r, time.perf_counter() - t)
    return out


def _median_range(v, fmt: str) -> str:
    """'median (min .. max)' of a list of figures, each formatted by ``fmt``."""
    v = [float(x) for x in v]
    med = fmt.format(statistics.median(v))
    return med if len(v) == 1 else f"{med} ({fmt.format(min(v))} .. {fmt.format(max(v))})"


def time_to_reach(res, target: float) -> float | None:
    """Seconds the search took until its best criterion was <= target (None: never)."""
    for h in res.history:
        if h["best"] <= target * (1 + 1e-12):
            return float(h["seconds"])
    return None


def achieved(machine, em, ev, sel, S, tools, budget, trials: int, seed: int
             ) -> tuple[float, float, float, float]:
    """RMS error (um) of the identified volumetric error at the evaluation poses, modulo the
    rigid motion no multilateration sees, over ``trials`` simulated measurements of the
    plan (volcal's simulator, the budget's noise, a random truth) identified by volcal, and
    its standard error (um) over the trials (delta method: se(mean square) / (2 RMS)); then
    paper 004's own measure, the RMSE of the identified coordinates of the measured points
    (per coordinate, modulo the same rigid motion, um), and its standard error."""
    import pandas as pd

    from volcal.analysis.identify import field_jacobian, identify, rigid_fit
    from volcal.measurement.simulate import draw_true_parameters, simulate

    plan = pd.DataFrame(ev.poses[sel], columns=machine.axis_names)
    st = pd.DataFrame(S, columns=["x_mm", "y_mm", "z_mm"])
    st.insert(0, "station", [f"S{k + 1}" for k in range(len(S))])
    st["dead_length_mm"] = 0.3
    Q, T = ev.eval_q, ev.eval_t
    p0, _, _ = machine.evaluate(Q, T, np.zeros(machine.n_errors))
    use = sel[ev.pose_of] & (ev.station_of == 0)      # each measured point once
    Qm, Tm = ev.q[use], ev.t[use]
    p0m, _, _ = machine.evaluate(Qm, Tm, np.zeros(machine.n_errors))
    sq, sqm = [], []
    for k in range(trials):
        theta = draw_true_parameters(machine, em, np.random.default_rng(seed + 1000 + k), 50.0)
        _, true_mm, _ = field_jacobian(machine, em, theta, Q, T)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim = simulate(machine, em, theta, st, plan, tools, budget, seed + k)
            start = sim.stations[["station", "x_mm", "y_mm", "z_mm"]].copy()
            start[["x_mm", "y_mm", "z_mm"]] += np.random.default_rng(k).normal(0, 2.0, (len(S), 3))
            fit = identify(machine, sim.measurements, start, error_model=em)
        pred = fit.predict(Q, T, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
        _, resid = rigid_fit(p0, (pred - true_mm * 1e3).ravel())
        sq.append(np.mean(np.sum(resid**2, axis=1)))
        _, true_m, _ = field_jacobian(machine, em, theta, Qm, Tm)
        pm = fit.predict(Qm, Tm, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]]
        _, rm = rigid_fit(p0m, (pm.to_numpy() - true_m * 1e3).ravel())
        sqm.append(np.mean(rm**2))

    return (*_rms_se(sq), *_rms_se(sqm))


def _rms_se(v) -> tuple[float, float]:
    """RMS of per-trial mean squares ``v`` and its standard error over the trials (delta
    method: se(mean square) / (2 RMS))."""
    v = np.asarray(v, float)
    r = float(np.sqrt(np.mean(v)))
    return r, float(np.std(v, ddof=1) / np.sqrt(len(v)) / (2 * r)) if len(v) > 1 else np.nan


def achieved_outside(machine, em, ev, sel, S, tools, trials: int, seed: int, max_um: float,
                     family: str = "nonrep") -> dict[str, float]:
    """The achieved RMS error (um) as in :func:`achieved`, but for a truth outside the
    model's basis, drawn and measured by the independent simulator (tests/indep_sim.py:
    the ``nonrep`` family, sines of non-integer periods, smooth steps and tables that do not
    satisfy the datum, scaled to ``max_um`` largest volumetric error at the evaluation
    poses; exact rigid-body chain; paper 002's budget; the plan's stations with random dead
    lengths; start values 2 mm off), identified by volcal.  Also the representation floor:
    the RMS (um) at the evaluation poses of what no parameter set of the model represents
    of the truth (least-squares residual of the true field by the first-order model field
    G theta plus a rigid motion).  The same ``trials`` truths for every plan (seeded).
    ``family="representable"`` draws cubic motions instead (inside the basis, still not
    satisfying the datum): the control that the independent pipeline itself agrees with
    the prediction.
    Returns {"ach", "ach_se", "floor", "floor_se", "rest", "rest_se", "chi2", "misfit"}, rest
    being the RMS of the achieved error's part above the floor, sqrt(mean(ach^2 -
    floor^2)), chi2 the median chi2/dof of the identifications and misfit how many of them
    volcal's adequacy check calls "does not fit"."""
    from volcal.analysis.identifiability import rigid_columns
    from volcal.analysis.identify import field_jacobian, identify, rigid_fit

    geom = ind.load_geometry(HERE / "boring_mill.toml")
    assert geom.axis_names == list(machine.axis_names)
    Q, T = ev.eval_q, ev.eval_t
    p0, _, G = field_jacobian(machine, em, np.zeros(em.n_params), Q, T)
    A = np.hstack([G.reshape(-1, em.n_params), rigid_columns(p0)])
    A = A / np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    q_eval = geom.to_internal(geom.to_file(Q))  # the simulator's own units (here the same)
    poses = geom.to_file(ev.poses[sel])
    sq, fl, chi2, misfit = [], [], [], 0
    for k in range(trials):
        rng = np.random.default_rng([seed, 7, k])
        tr = ind.draw_truth(geom, rng, family, tool_orientation=False)
        e = ind.true_error_um(geom, tr, q_eval, T)
        tr = tr.scaled(max_um / float(np.max(np.linalg.norm(e, axis=1))))
        true_um = ind.true_error_um(geom, tr, q_eval, T)
        sim = ind.simulate(geom, tr, poses, tools, np.random.default_rng([seed, 8, k]),
                           stations=S)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = identify(machine, sim.measurements, sim.stations_start, error_model=em)
            misfit += fit.adequacy.verdict == "does_not_fit"
        chi2.append(fit.conditions["chi2_per_dof"])
        pred = fit.predict(Q, T, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
        _, resid = rigid_fit(p0, (pred - true_um).ravel())
        sq.append(np.mean(np.sum(resid**2, axis=1)))
        r = true_um.ravel() - A @ np.linalg.lstsq(A, true_um.ravel(), rcond=None)[0]
        fl.append(np.mean(np.sum(r.reshape(-1, 3) ** 2, axis=1)))
    ach, ach_se = _rms_se(sq)
    floor, floor_se = _rms_se(fl)
    rest, rest_se = _rms_se(np.asarray(sq) - np.asarray(fl))
    return {"ach": ach, "ach_se": ach_se, "floor": floor, "floor_se": floor_se,
            "rest": rest, "rest_se": rest_se, "chi2": float(np.median(chi2)),
            "misfit": f"{misfit} of {trials}"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true",
                    help="small searches and few trials, into a temporary folder unless --out")
    ap.add_argument("--out", type=Path, default=None,
                    help="results folder (default studies/paper004/results)")
    ap.add_argument("--config", type=Path, default=HERE / "config.toml")
    ap.add_argument("--workers", type=int, default=1, help="GA: local scoring processes")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the printed tables into README.md's marked tables")
    args = ap.parse_args(argv)
    cfg = tomllib.loads(args.config.read_text(encoding="utf-8"))
    size = dict(cfg["search"])
    if args.smoke:
        size.update(cfg["smoke"])
    out = rt.output_folder(args.out, args.smoke, HERE / "results", "paper004")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    machine, em, cons, cand, ev, sel, sampler, manual = setup(cfg)
    sc = ev.scorer
    res, grads, loads = repeated_searches(cfg, ev, sel, sampler, manual, size, args.workers)
    S_opt = min((r for r, _ in res.values()), key=lambda r: sc.score(r.stations, sel)).stations
    seed = int(cfg["search"]["seed"])
    rng = np.random.default_rng(seed)
    layouts = {"optimised": S_opt, "manual": manual}
    for case, k in (("Case 1", 0), ("Case 2", 1)):  # one optimised station replaced
        S = S_opt.copy()
        S[k] = manual[k]
        layouts[case] = S
    rand = [sampler.draw(rng, ev.n_stations) for _ in range(int(size["random_layouts"]))]
    tools = np.asarray(cfg["setting"]["tools"], float)
    budget = cfg["setting"]["budget"]
    trials = int(size["validation_trials"])
    out_trials = int(size["outside_trials"])
    rows, orows = [], []

    def outside(name, S, pred):
        o = achieved_outside(machine, em, ev, sel, S, tools, out_trials, seed, 50.0)
        c = achieved_outside(machine, em, ev, sel, S, tools, out_trials, seed, 50.0,
                             "representable")
        orows.append({
            "plan": name, "pred": f"{pred:.3g}",
            "ctrl": f"{c['ach'] / pred:.2f} ± {c['ach_se'] / pred:.2f}",
            "ach": f"{o['ach']:.3g} ± {o['ach_se']:.2g}",
            "ratio": f"{o['ach'] / pred:.2f} ± {o['ach_se'] / pred:.2f}",
            "floor": f"{o['floor']:.3g} ± {o['floor_se']:.2g}",
            "rest": f"{o['rest'] / pred:.2f} ± {o['rest_se'] / pred:.2f}",
            "chi2": f"{o['chi2']:.3g} (control {c['chi2']:.3g})",
            "misfit": f"{o['misfit']} (control {c['misfit']})"})

    for name, S in layouts.items():
        pred = sc.score(S, sel)
        ach, se, crd, crd_se = achieved(machine, em, ev, sel, S, tools, budget, trials, seed)
        rows.append({"plan": name, "pred": pred, "ach": ach, "se": se, "ratio": ach / pred,
                     "coord": f"{crd:.3g} ± {crd_se:.2g}", "paper": PAPER_UM.get(name)})
        outside(name, S, pred)
    # random feasible layouts: the first is simulated, all are scored
    rv = np.array([sc.score(S, sel) for S in rand])
    ach_r, se_r, crd, crd_se = achieved(machine, em, ev, sel, rand[0], tools, budget, trials,
                                        seed)
    rows.append({"plan": "random feasible layout", "coord": f"{crd:.3g} ± {crd_se:.2g}",
                 "pred": float(rv[0]), "ach": ach_r, "se": se_r, "ratio": ach_r / rv[0],
                 "paper": None,
                 "spread": f"{rv.min():.3g} .. {rv.max():.3g} (mean {rv.mean():.3g}, "
                           f"{len(rand)} layouts)"})
    outside("random feasible layout", rand[0], float(rv[0]))
    tables = {}
    tables["comparison"] = rt.markdown(
        [{**r, "pred": f"{r['pred']:.3g}", "ach": f"{r['ach']:.3g} ± {r['se']:.2g}",
          "ratio": f"{r['ratio']:.2f} ± {r['se'] / r['pred']:.2f}",
          "paper": "-" if r["paper"] is None else f"{r['paper']:.1f}",
          "spread": r.get("spread", "-")} for r in rows],
        ["plan", "pred", "spread", "ach", "ratio", "coord", "paper"],
        ["plan", "predicted volumetric u, RMS, um", "range over random layouts, um",
         "achieved RMS error ± its standard error over the simulated measurements, um",
         "achieved / predicted ± standard error",
         "paper 004's measure: coordinate RMSE of the measured points ± SE, um",
         "paper 004, um"])
    srows = []
    for k, (r, times) in res.items():
        reached = sc.score(r.stations, sel)
        # per run: this search's seconds over the seconds the same run's gradient search
        # took to reach the criterion this search reached
        tgs = [time_to_reach(g, reached) for g in grads]
        ratios = [t / tg for t, tg in zip(times, tgs) if tg]
        srows.append({
            "method": k, "I": f"{reached:.4g}", "fit": f"{r.value:.4g}",
            "n": r.evaluations, "s": _median_range(times, "{:.1f}"),
            "tg": "not reached" if None in tgs else _median_range(tgs, "{:.2f}"),
            "x": "-" if len(ratios) < len(times) else _median_range(ratios, "{:.0f}")})
    tables["search"] = rt.markdown(
        srows, ["method", "I", "fit", "n", "s", "tg", "x"],
        ["search", "criterion I reached, um", "its own fitness, um",
         "fitness evaluations (IPOPT: iterations)",
         "seconds, median of the runs (range)",
         "gradient's seconds to reach the same I, median (range)",
         "ratio of the two, median of the runs' ratios (range)"])
    tables["outside"] = rt.markdown(
        orows, ["plan", "pred", "ctrl", "ach", "ratio", "floor", "rest", "chi2", "misfit"],
        ["plan", "predicted volumetric u, RMS, um",
         "control, cubic truth (inside the basis) from the independent simulator: "
         "achieved / predicted ± SE",
         "achieved RMS error ± SE, truth outside the basis (independent simulator), um",
         "achieved / predicted ± SE",
         "representation floor ± SE: RMS of the truth no parameter set represents, um",
         "sqrt(achieved² - floor²) / predicted ± SE",
         "chi2/dof of the fits, median",
         "fits volcal's adequacy check calls 'does not fit'"])
    tables["runinfo"] = rt.markdown(
        [{"part": "candidate poses x tool offsets x stations", "n":
          f"{int(sel.sum())} x {len(tools)} x {ev.n_stations}"},
         {"part": "simulated measurements identified per plan", "n": trials},
         {"part": "GA population x generations (linearised and I fitness)", "n":
          f"{size['ga_population']} x {size['ga_generations']}"},
         {"part": "GA population x generations, trials per fitness (paper 004's fitness)",
          "n": f"{size['ga_nl_population']} x {size['ga_nl_generations']}, "
               f"{size['mc_trials_nonlinear']}"},
         {"part": "simulated measurements per plan, truth outside the basis", "n": out_trials},
         {"part": "runs of every search (timing)", "n": len(grads)},
         {"part": "load average, 1 min, at the start of each run (2 cores)",
          "n": ", ".join(f"{la[0]:.1f}" for la in loads)},
         {"part": "seconds", "n": f"{time.perf_counter() - t0:.1f}"}],
        ["part", "n"], ["part", "n"])
    rt.write_tables(out, tables)
    np.savetxt(out / "stations_optimised.csv", S_opt, delimiter=",", header="x_mm,y_mm,z_mm",
               comments="")
    rt.print_and_publish(
        tables, f"\nresults in {out}", HERE / "README.md", args.update_readme, args.smoke
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
