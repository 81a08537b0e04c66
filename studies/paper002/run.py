"""Paper 002 study: Monte Carlo uncertainty of a 17-error sequential multilateration.

Liu, Xia, Rui, Metrol. Meas. Syst. 30 (2023) 49-63: four laser tracker stations at the
Table 2 positions, the Table 1 budget (volcal's bundled ``paper002``), a 17-error model of
a 3-axis machine (chain W-X-Y-Z-T), 10,000 Monte Carlo trials.  The true error motions are
set to the paper's identified values (Table 3; see config.toml), one measurement is
simulated, identified, and its uncertainty evaluated by Monte Carlo (GUM S1) and by the
linearised covariance; the source contributions are evaluated one source at a time and
in the paper's Fig. 5 variants (all sources; without the machine's repeatability; laser
length error only).

    python studies/paper002/run.py --update-readme   # full run (10,000 trials per run)
    python studies/paper002/run.py --smoke           # a few hundred trials, for the tests

Writes studies/paper002/results/ (or --out): table3_<variant>.csv, volumetric_<variant>.csv,
contributions_<variant>.csv, fig5_<variant>.csv|png, volumetric_U_<variant>.png,
analysis_plan.txt, analysis_21_errors.txt, summary.json, tables.md|json (the README's
tables; ``--update-readme`` copies them into README.md between its markers).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent
# the studies' shared table helper, next to this folder
sys.path.insert(0, str(HERE.parent))
import readme_tables as rt


def load_config(path: Path = HERE / "config.toml") -> dict:
    return tomllib.loads(path.read_text())


def build(cfg: dict):
    """(machine, spec, stations, plan, tools, budget, truth functions)."""
    from volcal.model.machine import Machine
    from volcal.model.spec import machine_from_dict
    from volcal.measurement.budget import load_budget

    spec = machine_from_dict(cfg["model"], where="config.toml [model]")
    machine = Machine.from_model(spec)
    st = pd.DataFrame(cfg["station"])
    st["dead_length_given"] = True
    st["fixed"] = False
    grids = {a: np.linspace(*v[:2], int(v[2])) for a, v in cfg["plan"].items()
             if a in spec.axis_names}
    import itertools
    plan = pd.DataFrame(list(itertools.product(*[grids[a] for a in spec.axis_names])),
                        columns=spec.axis_names)
    tools = np.array(cfg["plan"]["tools_mm"], float)
    budget = load_budget("paper002")
    return machine, spec, st, plan, tools, budget, grids


def truth_functions(spec, truth: dict) -> dict:
    """Error functions of the internal axis position (mm, rad): see config.toml [truth]."""
    from volcal.model.spec import error_symbols

    funcs = {}
    for s in error_symbols(spec):
        # the tool's zero position and orientation are not part of paper 002's truth: zero
        v = truth.get(s.name, 0.0) * (1e-3 if s.quantity == "translation" else 1e-6)
        if s.kind in ("location", "tool"):
            funcs[s.name] = (lambda x, v=v: np.full(np.shape(x), v))
            continue
        a = spec.axis(s.axis)
        lo, hi = a.travel
        if s.kind == "location":
            funcs[s.name] = (lambda x, v=v: np.full(np.shape(x), v))
            continue
        straight = s.quantity == "translation" and s.component != a.dir_index
        if straight:
            funcs[s.name] = (lambda x, v=v, lo=lo, hi=hi:
                             v * 4 * ((np.asarray(x) - lo) / (hi - lo)) *
                             (1 - (np.asarray(x) - lo) / (hi - lo)))
        else:
            far = hi if abs(hi - a.reference) >= abs(lo - a.reference) else lo
            funcs[s.name] = (lambda x, v=v, r=a.reference, far=far:
                             v * (0.7 * (np.asarray(x) - r) / (far - r) +
                                  0.3 * ((np.asarray(x) - r) / (far - r)) ** 2))
    return funcs


def error_model(spec, variant: str, grids: dict):
    from volcal.model.errors import ErrorForm, ErrorModel

    if variant == "poly3":
        return ErrorModel(spec, default=ErrorForm("poly", 3), datum="iso230")
    if variant == "table":
        forms = {a: ErrorForm("table", knots=tuple(float(v) for v in sorted(g)))
                 for a, g in grids.items()}
        return ErrorModel(spec, forms, datum="iso230")
    raise ValueError(variant)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--smoke", action="store_true", help="a few hundred trials")
    ap.add_argument("--out", type=Path, default=None,
                    help="results folder (default results/; --smoke: a temporary folder)")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the printed tables into README.md (full runs only)")
    args = ap.parse_args(argv)
    if args.update_readme and args.smoke:
        ap.error("--update-readme with --smoke would put smoke figures in the README")

    from volcal.outputs.analysis_report import analyze_plan
    from volcal.measurement.tables import load_measurements
    from volcal.model.errors import ErrorForm, ErrorModel
    from volcal.measurement.simulate import simulate
    from volcal.base.threads import set_blas_threads
    from volcal.analysis.uncertainty.evaluation import evaluation_factor
    from volcal.outputs.mc_report import default_quantities, plot_contributions
    from volcal.analysis.uncertainty.montecarlo import (MCResult, contributions, monte_carlo,
                                               quantity_table, run_trials)

    set_blas_threads(1)
    cfg = load_config()
    S = cfg["study"]
    trials = S["smoke_trials"] if args.smoke else S["trials"]
    ctrials = S["smoke_contribution_trials"] if args.smoke else S["contribution_trials"]
    workers = args.workers if args.workers is not None else S["workers"]
    # a smoke run without --out writes into a new temporary folder, never into the repository
    out = rt.output_folder(args.out, args.smoke, HERE / "results", "paper002")
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    machine, spec, stations, plan, tools, budget, grids = build(cfg)
    funcs = truth_functions(spec, cfg["truth"])
    em_true = error_model(spec, "poly3", grids)
    theta_true = em_true.fit_functions(funcs)
    C, _ = em_true.constraints()
    assert np.abs(C @ theta_true).max() < 1e-15, "the truth must satisfy the datum"
    sim = simulate(machine, em_true, theta_true, stations, plan, tools, budget, S["data_seed"])
    import warnings
    with warnings.catch_warnings():
        # "single tool offset": expected, the 17-error model leaves out what it cannot see
        warnings.simplefilter("ignore")
        meas = load_measurements(sim.measurements, spec)
    vmax_true = sim.max_volumetric_um
    log = {"readings": len(meas), "poses": len(plan), "stations": len(stations),
           "true_max_volumetric_um_measured_poses": float(vmax_true)}

    # what the plan can identify: the 17-error model, and the full 21-error model
    # linearised at the true errors and at zero errors: gauge, datum and identifiability
    # are decided at zero errors either way, so the two agree to second order
    rep = analyze_plan(machine, plan, stations, tools, budget, error_model=em_true,
                       theta=theta_true, eval_points=plan)
    rep0 = analyze_plan(machine, plan, stations, tools, budget, error_model=em_true,
                        eval_points=plan)
    (out / "analysis_plan.txt").write_text(rep.summary(top=6) + "\n")
    from volcal.model.machine import Machine
    from volcal.model.spec import machine_from_dict
    full = dict(cfg["model"])
    full["name"] = "paper002_xyz21"
    full["axis"] = [{k: v for k, v in a.items() if k != "exclude"} for a in full["axis"]]
    m21 = Machine.from_model(machine_from_dict(full))
    rep21 = analyze_plan(m21, plan, stations, tools, budget, eval_points=plan,
                         error_model=ErrorModel(m21.spec, default=ErrorForm("poly", 3)))
    (out / "analysis_21_errors.txt").write_text(rep21.summary(top=4) + "\n")
    tables = {"plan_analysis": plan_table(rep, rep0, rep21)}
    log["plan_analysis"] = {"rank": rep.rank, "condition_scaled": rep.condition,
                            "condition_unscaled": rep.condition_unscaled,
                            "unidentifiable_17": [d.line() for d in rep.unidentifiable_errors],
                            "unidentifiable_21": [d.line() for d in rep21.unidentifiable_errors]}
    print(rep.summary(top=4))
    print(rep21.summary(top=2))

    paper_U = cfg["paper_U"]
    summary = {"config": {"trials": trials, "contribution_trials": ctrials,
                          "seed": S["seed"], "data_seed": S["data_seed"]}, **log,
               "variants": {}}
    variants = cfg["identification"]["variants"]
    tabs: dict[str, pd.DataFrame] = {}
    for variant in variants:
        em = error_model(spec, variant, grids)
        t0 = time.perf_counter()
        res = monte_carlo(machine, meas, budget=budget, error_model=em, trials=trials,
                          seed=S["seed"], workers=workers, eval_points=plan, verify=2,
                          progress=not args.smoke)
        mc, k = res["mc"], res["kernel"]
        t_mc = mc.samples.seconds
        # Table 3 equivalent: every error at the end of its travel (straightness: middle)
        # paper 002's Table 3 has no tool zero position / orientation: leave them out
        tool = {s.name for s in em.errors if s.kind == "tool"}
        qs = [q for q in default_quantities(em) if q.split("(")[0] not in tool]
        tab = quantity_table(mc, em, qs)
        err_names = [q.split("(")[0] for q in qs]
        truth_vals = []
        for q, e in zip(qs, err_names):
            s_ = next(s for s in em.errors if s.name == e)
            f = 1e3 if s_.quantity == "translation" else 1e6
            pos = float(q.split("(")[1][:-1]) if "(" in q else 0.0
            truth_vals.append(float(funcs[e](pos)) * f)
        tab.insert(1, "error", err_names)
        tab["truth"] = truth_vals
        tab["E_n_vs_truth"] = evaluation_factor(tab["value"], tab["U"], tab["truth"], 0.0)
        # the tool zero position / orientation are not part of paper 002: no paper figures
        tab["paper_value"] = [cfg["truth"].get(e, np.nan) for e in err_names]
        tab["paper_U"] = [paper_U.get(e, np.nan) for e in err_names]
        tab["U_over_paper_U"] = tab["U"] / tab["paper_U"]
        tab["U_linear"] = 2 * tab["u_linear"]
        tab.to_csv(out / f"table3_{variant}.csv", index=False)
        # volumetric error over the measured poses (tool offset 0)
        vol = mc.volumetric()
        mv = mc.max_volumetric()
        vol.to_csv(out / f"volumetric_{variant}.csv", index=False)
        # contributions: one source at a time, and the paper's Fig. 5 variants
        contrib, runs = contributions(k, ctrials, S["seed"], workers=workers)
        lengths = [s.name for s in budget.length_sources]
        fig5 = {"all sources": mc.samples}
        fig5["without repeatability"] = run_trials(k, ctrials, S["seed"], enabled=lengths,
                                                   workers=workers)
        fig5["laser length only"] = runs["laser_length"]
        rows = []
        for label, smp in fig5.items():
            r = MCResult.from_samples(k, smp)
            qt = quantity_table(r, em, qs)
            vv = r.volumetric()
            for nm, U in zip(err_names, qt["U"]):
                rows.append({"quantity": nm, "variant": label, "U": U})
            rows.append({"quantity": "|d| at max", "variant": label,
                         "U": float(vv["U_norm_um"].iloc[mv["pose_index"]])})
        fig5_tab = pd.DataFrame(rows).pivot_table(index="quantity", columns="variant",
                                                  values="U", sort=False)
        fig5_tab.to_csv(out / f"fig5_{variant}.csv")
        # per single source (U at the Table 3 quantities and |d| at max)
        per = []
        for nm, smp in runs.items():
            r = MCResult.from_samples(k, smp)
            qt = quantity_table(r, em, qs)
            vv = r.volumetric()
            d = dict(zip(err_names, qt["U"]))
            d["|d| at max"] = float(vv["U_norm_um"].iloc[mv["pose_index"]])
            d["source"] = nm
            per.append(d)
        per_tab = pd.DataFrame(per).set_index("source").T
        per_tab.to_csv(out / f"contributions_{variant}.csv")
        if not args.no_plots:
            long = pd.DataFrame([{"quantity": q, "unit": u, "source": lab, "u": U / 2}
                                 for q, u in zip(err_names, tab["unit"])
                                 for lab in ("without repeatability", "laser length only")
                                 for U in [fig5_tab.loc[q, lab]]])
            total = pd.DataFrame({"name": err_names, "unit": tab["unit"], "U": tab["U"]})
            plot_contributions(long, total, out / f"fig5_{variant}.png",
                               f"paper 002 Fig. 5 equivalent ({variant}): U (k = 2) of the "
                               "errors by input sources", label="{}")
            from volcal.outputs.mc_plots import _plot_volumetric_U
            _plot_volumetric_U(vol["U_norm_um"].to_numpy(), mv["max_norm_um"],
                               k.volmap.points, out / f"volumetric_U_{variant}.png")
        ag = mc.agreement()
        summary["variants"][variant] = {
            "n_params": em.n_params, "mc_seconds": t_mc,
            "variant_seconds": time.perf_counter() - t0,
            "verify_against_ipopt": res["verify"], "not_converged": int((~mc.samples.converged).sum()),
            "identification": {"status": res["result"].status,
                               "chi2_per_dof": res["result"].conditions["chi2_per_dof"]},
            "agreement_with_linearised": ag, "max_volumetric": mv,
            "table3_E_n_vs_truth_max": float(tab["E_n_vs_truth"].max()),
            "table3_within_U_of_truth": int((tab["E_n_vs_truth"] <= 1).sum()),
            "U_over_paper_U_median": float(tab["U_over_paper_U"].median()),
            "fig5_U_at_max": {c: float(fig5_tab.loc["|d| at max", c]) for c in fig5_tab.columns},
        }
        print(f"\n== variant {variant}: {trials} trials in {t_mc:.1f} s; max |d| "
              f"{mv['max_norm_um']:.2f} um, U(|d|) there {mv['U_norm_at_max_um']:.2f} um "
              f"(k = 2); largest U(|d|) {mv['U_norm_largest_um']:.2f} um")
        print(tab[["name", "unit", "value", "truth", "U", "U_linear", "paper_value",
                   "paper_U"]].round(2).to_string(index=False))
        print(fig5_tab.round(2).to_string())
        tabs[variant] = tab
        if variant == "poly3":
            tables["plan_vs_mc"] = plan_vs_mc_table(rep, mc, mv)
            tables["fig5"] = fig5_table(fig5_tab, tab)
            tables["sources"] = sources_table(per_tab, fig5_tab)
    tables["table3"] = table3_table(tabs["poly3"], tabs.get("table"))
    tables["volumetric"] = volumetric_table(summary["variants"], cfg["paper_volumetric"])
    tables["agreement"] = agreement_table(summary["variants"], tabs)
    summary["paper"] = cfg["paper_volumetric"]
    summary["seconds_total"] = time.perf_counter() - t_start
    tables["runinfo"] = rt.markdown(
        [{"study": "paper002", "mode": "smoke" if args.smoke else "full", "trials": trials,
          "contribution_trials": ctrials, "seed": S["seed"], "data_seed": S["data_seed"]}])
    rt.write_tables(out, tables)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    if args.update_readme:
        done = rt.update_readme(HERE / "README.md", tables)
        print(f"README.md: updated {', '.join(done)}")
    print(f"\nwrote {out} in {summary['seconds_total']:.0f} s")
    print(f"results in {out}")
    return 0


# ---- the README's tables ----------------------------------------------------------------
def _f(v, nd: int = 2) -> str:
    """A figure as the README prints it: nd decimals ('-' for NaN)."""
    v = float(v)
    return "-" if v != v else f"{v:.{nd}f}"


def plan_table(rep, rep0, rep21) -> str:
    """The plan analysis (17-error model at the true and at zero errors; 21 errors)."""
    rows = []
    for label, r in (("17 errors, at the true errors", rep), ("17 errors, at zero errors", rep0),
                     ("21 errors, at zero errors", rep21)):
        ident = r.identifiability
        n_free = len(ident.singular_values)
        gauge = sum(d.dimension for d in r.null if d.kind == "gauge")
        unid = sum(d.dimension for d in r.unidentifiable_errors)
        v = r.volumetric
        rows.append({"analysis": label, "rank": f"{r.rank} of {n_free}", "gauge": gauge,
                     "unidentifiable": unid, "cond": f"{r.condition:.0f}",
                     "cond_u": f"{r.condition_unscaled:.0f}",
                     "smin": f"{ident.singular_values[r.rank - 1]:.3g}",
                     "U": _f(2 * max(v[f"u_{c}_um"].max() for c in ("dx", "dy", "dz")))})
    return rt.markdown(rows, ["analysis", "rank", "gauge", "unidentifiable", "cond", "cond_u",
                              "smin", "U"],
                       ["plan analysis", "rank (free directions)", "gauge directions",
                        "unidentifiable directions", "condition (scaled)",
                        "condition (unscaled)", "smallest identifiable s (scaled)",
                        "largest linearised U of a component, k = 2 (um)"])


def plan_vs_mc_table(rep, mc, mv) -> str:
    """The plan analysis (linearised at the true errors, before measuring) against the
    Monte Carlo of the identification (full nonlinear re-solves) at the measured poses."""
    v = rep.volumetric
    i = int(mv["pose_index"])
    mcv = mc.volumetric()
    rows = []
    for label, a, b in (
        ("U(\\|d\\|) at the largest error (um)", 2 * v["u_norm_um"].iloc[i],
         mv["U_norm_at_max_um"]),
        ("largest U(\\|d\\|) over the measured poses (um)", 2 * np.nanmax(v["u_norm_um"]),
         mv["U_norm_largest_um"]),
        ("largest U of a component (um)",
         2 * max(v[f"u_{c}_um"].max() for c in ("dx", "dy", "dz")),
         mv["U_component_largest_um"]),
        ("median U of a component (um)",
         2 * np.median(v[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy()),
         2 * np.median(mcv[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy())),
    ):
        rows.append({"q": label, "plan": _f(a), "mc": _f(b), "ratio": _f(b / a, 3)})
    return rt.markdown(rows, ["q", "plan", "mc", "ratio"],
                       ["quantity (k = 2)", "plan analysis at the true errors", "Monte Carlo",
                        "MC / plan"])


def table3_table(tab: pd.DataFrame, tab_table: pd.DataFrame | None) -> str:
    u_table = {} if tab_table is None else dict(zip(tab_table["error"], tab_table["U"]))
    rows = []
    for _, r in tab.iterrows():
        u_t = float(u_table.get(r["error"], float("nan")))
        rows.append({
            "name": r["name"], "unit": r["unit"], "truth": _f(r["truth"], 1),
            "value": _f(r["value"]), "U": _f(r["U"]), "U_linear": _f(r["U_linear"]),
            "ci": f"[{r['ci95_low']:.1f}, {r['ci95_high']:.1f}]",
            "En": _f(r["E_n_vs_truth"]), "pv": _f(r["paper_value"], 1),
            "pU": _f(r["paper_U"], 1), "ratio": _f(r["U_over_paper_U"]),
            "Ut": _f(u_t), "tr": _f(u_t / r["U"], 3)})
    return rt.markdown(rows, ["name", "unit", "truth", "value", "U", "U_linear", "ci", "En",
                              "pv", "pU", "ratio", "Ut", "tr"],
                       ["error", "unit", "truth", "identified", "U (k=2) MC", "U linearised",
                        "95 % interval", "E_n vs truth", "paper value", "paper U",
                        "U / paper U", "U table form", "table / poly3"])


def volumetric_table(variants: dict, paper: dict) -> str:
    p, t = variants["poly3"]["max_volumetric"], variants.get("table", {}).get("max_volumetric")
    t = t or {k: float("nan") for k in p}

    def ci(m):
        return f"[{m['max_ci95_low_um']:.1f}, {m['max_ci95_high_um']:.1f}]"

    rows = [
        {"q": "largest volumetric error over the measured poses (um)",
         "a": _f(p["max_norm_um"], 1), "b": _f(t["max_norm_um"], 1),
         "c": _f(paper.get("max_um", float("nan")), 1)},
        {"q": "U(\\|d\\|), k = 2, at that pose (MC, um)", "a": _f(p["U_norm_at_max_um"]),
         "b": _f(t["U_norm_at_max_um"]), "c": _f(paper.get("U_um", float("nan")), 1)},
        {"q": "95 % interval of the largest error (um)", "a": ci(p), "b": ci(t), "c": "-"},
        {"q": "largest U(\\|d\\|) over the measured poses (um)",
         "a": _f(p["U_norm_largest_um"]), "b": _f(t["U_norm_largest_um"]), "c": "-"},
    ]
    return rt.markdown(rows, ["q", "a", "b", "c"], ["", "here (poly3)", "here (table)", "paper"])


def fig5_table(fig5_tab: pd.DataFrame, tab: pd.DataFrame) -> str:
    cols = ["all sources", "without repeatability", "laser length only"]
    units = dict(zip(tab["error"], tab["unit"]))
    rows = []
    for q in fig5_tab.index:
        label = f"{q} ({units[q]})" if q in units else "\\|d\\| at the largest error (um)"
        rows.append({"q": label, **{c: _f(fig5_tab.loc[q, c]) for c in cols}})
    return rt.markdown(rows, ["q"] + cols, ["quantity"] + cols)


def sources_table(per_tab: pd.DataFrame, fig5_tab: pd.DataFrame) -> str:
    row = per_tab.loc["|d| at max"]  # in the budget's order (a fixed order of the keys)
    rows = [{"s": str(k), "U": _f(v)} for k, v in row.items()]
    rows.append({"s": "root sum of squares", "U": _f(np.sqrt(np.sum(row.to_numpy() ** 2)))})
    rows.append({"s": "all sources together", "U": _f(fig5_tab.loc["|d| at max", "all sources"])})
    return rt.markdown(rows, ["s", "U"], ["source", "U(\\|d\\|) at the largest error, k = 2 (um)"])


def _ratio_range(tab: pd.DataFrame, ref: pd.DataFrame) -> str:
    """'lo .. hi; more than 5 % apart: ERR, ...': the range of U / U_ref over the errors
    and the errors where the two differ by more than 5 %."""
    r = tab.set_index("error")["U"] / ref.set_index("error")["U"]
    far = ", ".join(r.index[(r - 1).abs() > 0.05]) or "none"
    return f"{_f(r.min(), 3)} .. {_f(r.max(), 3)}; more than 5 % apart: {far}"


def agreement_table(variants: dict, tabs: dict) -> str:
    rows = []
    for name, v in variants.items():
        ag = v["agreement_with_linearised"]
        rows.append({"variant": name,
                     "p": _f(100 * ag["parameters_max_rel_diff"], 1),
                     "v": _f(100 * ag["volumetric_max_rel_diff"], 1),
                     "tr": "-" if name == "poly3" else _ratio_range(tabs[name], tabs["poly3"])})
    return rt.markdown(rows, ["variant", "p", "v", "tr"],
                       ["variant", "MC vs linearised u, parameters: largest difference (%)",
                        "volumetric components: largest difference (%)",
                        "U of the 17 Table 3 errors / poly3's"])


if __name__ == "__main__":
    sys.exit(main())
