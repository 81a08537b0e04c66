"""Paper 001 study: multilateration with the simultaneous three-laser instrument (HPTI).

Monte Carlo of section 5 of Aguado et al. 2021 (IOP Conf. Ser. Mater. Sci. Eng. 1193
012061): the 60-point mesh, the instrument's own inter-laser distances, the drift /
vibration f(t) of eq. (2), and the multilateration strategies of Table 1 (sphere
intersection, points-only, two-phase, joint) at initial accuracies 100 / 95 / 90 %, plus
our variants.  Everything is configured in config.toml; the model and the solvers are in
:mod:`volcal.analysis.multilaser`.

    python studies/paper001/run.py [--smoke] [--trials N] [--workers K] [--out DIR]
                                   [--config FILE] [--scenarios NAME ...]

Trial k of every scenario uses the generator SeedSequence(seed, spawn_key=(k,)), and one
solver is built per worker process (not per trial), so the results for a seed are the same
whatever the number of workers.

Output (DIR, default studies/paper001/results, or results_smoke with --smoke):
  table_<scenario>.csv / .md   point error (um) per case: mean, std, max, min, ...
  jacobian.csv / .md           unknowns, readings, rank, redundancy, condition per step
  trials_<scenario>.csv.gz     per trial and case: mean / max error (um), success
  errors_<scenario>.png        error distributions per strategy and initial accuracy
  summary.md, meta.json        all tables; trials, workers, wall time, versions
"""
from __future__ import annotations

import os

# small matrices: one BLAS thread per process (set before numpy is imported; the worker
# processes inherit it)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from concurrent.futures import ProcessPoolExecutor, as_completed  # noqa: E402
from multiprocessing import get_context  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from volcal.analysis import multilaser as ml  # noqa: E402

HERE = Path(__file__).resolve().parent


def load_config(path: str | Path | None = None) -> dict:
    with open(path or HERE / "config.toml", "rb") as fh:
        return tomllib.load(fh)


def _chunks(n: int, size: int) -> list[list[int]]:
    return [list(range(i, min(n, i + size))) for i in range(0, n, size)]


def run_scenario(cfg: dict, scenario: str, trials: int, workers: int = 1, *,
                 progress: bool = True) -> dict:
    """Run trials 0..trials-1 of one scenario; returns stacked arrays (trial order).

    workers = 1 runs in this process; more use a ProcessPoolExecutor (spawn) whose
    initializer builds one :class:`volcal.analysis.multilaser.StudyRunner` (one IPOPT build) per
    worker."""
    from tqdm import tqdm

    results: list[dict | None] = [None] * trials
    bar = tqdm(total=trials, desc=scenario, unit="trial", disable=not progress,
               file=sys.stderr, dynamic_ncols=True)
    if workers <= 1:
        runner = ml.StudyRunner(cfg, scenario)
        labels = runner.case_labels()
        for k in range(trials):
            results[k] = runner.trial(k)
            bar.update(1)
    else:
        labels = [c.label for c in ml.cases_from_config(cfg)]
        size = max(1, min(25, trials // (workers * 8) or 1))
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                                 initializer=ml._worker_init,
                                 initargs=(cfg, scenario)) as pool:
            futs = [pool.submit(ml._worker_trials, ch) for ch in _chunks(trials, size)]
            for f in as_completed(futs):
                for r in f.result():
                    results[r["index"]] = r
                    bar.update(1)
    bar.close()
    out = {key: np.stack([r[key] for r in results]) for key in
           ("errors_um", "success", "iterations", "geometry_mm")}
    out["labels"] = labels
    return out


def summary_table(res: dict, cases: list) -> list[dict]:
    """Per case: statistics of the point error (um) pooled over all points of all trials,
    the largest per-trial mean, the success rate and the mean iterations."""
    rows = []
    E = res["errors_um"]
    for c, case in enumerate(cases):
        e = E[:, c, :]
        rows.append({
            "case": case.name, "strategy": case.strategy,
            "initial_accuracy_pct": "" if case.accuracy is None else round(100 * case.accuracy),
            "mean_um": float(np.nanmean(e)), "std_um": float(np.nanstd(e)),
            "max_um": float(np.nanmax(e)), "min_um": float(np.nanmin(e)),
            "max_trial_mean_um": float(np.nanmax(np.nanmean(e, axis=1))),
            "success_pct": 100.0 * float(np.mean(res["success"][:, c])),
            "iterations_mean": float(np.mean(res["iterations"][:, c])),
        })
    return rows


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(v)
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-2:
        return f"{v:.3g}"
    return f"{v:.3g}" if abs(v) < 10 else f"{v:.1f}"


def markdown(rows: list[dict], cols: list[str], heads: list[str] | None = None) -> str:
    heads = heads or cols
    out = ["| " + " | ".join(heads) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        out.append("| " + " | ".join(_fmt(r[c]) for c in cols) + " |")
    return "\n".join(out)


def write_csv(path: Path, rows: list[dict]) -> None:
    import pandas as pd

    pd.DataFrame(rows).to_csv(path, index=False)


def plot_errors(path: Path, res: dict, cases: list, scenario: str, trials: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    accs = sorted({c.accuracy for c in cases if c.accuracy is not None}, reverse=True)
    names = list(dict.fromkeys(c.name for c in cases))
    colors = dict(zip(names, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 3))
    E = res["errors_um"]
    finite = E[np.isfinite(E) & (E > 0)]
    lo = max(np.floor(np.log10(finite.min())) if finite.size else -3, -4)
    hi = np.ceil(np.log10(finite.max())) if finite.size else 6
    bins = np.logspace(lo, hi, int(8 * (hi - lo)) + 1)
    fig, axes = plt.subplots(len(accs), 1, figsize=(9, 2.8 * len(accs)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, a in zip(axes, accs):
        for c, case in enumerate(cases):
            if case.accuracy not in (a, None):
                continue
            e = E[:, c, :].ravel()
            e = np.clip(e[np.isfinite(e)], bins[0], bins[-1])
            ax.hist(e, bins=bins, histtype="step", lw=1.4, color=colors[case.name],
                    ls="--" if case.strategy == "sphere" else "-",
                    label=case.name, weights=np.full(e.size, 1.0 / max(e.size, 1)))
        ax.set_xscale("log")
        ax.set_ylabel("fraction of points")
        ax.set_title(f"initial accuracy {100 * a:g} %", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, ncol=2)
    axes[-1].set_xlabel("point error |P_est - P_true| in the instrument frame (um); errors "
                        "below the left edge are piled into the first bin;\nsphere (dashed) "
                        "and points-only give the same errors and overlap")
    fig.suptitle(f"paper 001 study, scenario '{scenario}', {trials} trials x 60 points",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def jacobian_rows(cfg: dict, scenario: str) -> list[dict]:
    runner = ml.StudyRunner(cfg, scenario)
    rows = []
    for case, rep in runner.jacobian_reports():
        d = rep.as_dict()
        d.pop("gauge")
        rows.append({"case": case.label, **d})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="a handful of trials (config "
                    "study.smoke_trials), output to results_smoke unless --out is given")
    ap.add_argument("--trials", type=int, default=None, help="trials per scenario "
                    "(default: config study.trials)")
    ap.add_argument("--workers", type=int, default=1, help="local worker processes")
    ap.add_argument("--out", type=Path, default=None, help="output folder")
    ap.add_argument("--config", type=Path, default=HERE / "config.toml")
    ap.add_argument("--scenarios", nargs="+", default=None,
                    help="scenario names (default: config study.scenarios)")
    ap.add_argument("--initial-accuracy-applies-to", choices=("points", "points+instrument"),
                    default=None, help="override study.initial_accuracy_applies_to")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)

    cfg = load_config(args.config)
    st = cfg.setdefault("study", {})
    if args.initial_accuracy_applies_to:
        st["initial_accuracy_applies_to"] = args.initial_accuracy_applies_to
    trials = args.trials or (int(st.get("smoke_trials", 4)) if args.smoke
                             else int(st.get("trials", 10000)))
    out = args.out or HERE / ("results_smoke" if args.smoke else "results")
    out.mkdir(parents=True, exist_ok=True)
    scenarios = args.scenarios or list(st.get("scenarios", cfg.get("scenario", {}).keys()))
    cases = ml.cases_from_config(cfg)
    meta = {"trials": trials, "workers": args.workers, "seed": int(st.get("seed", 1)),
            "initial_accuracy_applies_to": st.get("initial_accuracy_applies_to", "points"),
            "scenarios": {}, "python": platform.python_version(),
            "platform": platform.platform(), "cpu_count": os.cpu_count()}
    try:
        import casadi

        meta["casadi"] = casadi.__version__
    except Exception:  # pragma: no cover
        pass
    meta["numpy"] = np.__version__
    md = [f"# paper 001 study results\n\n{trials} trials per scenario, {args.workers} "
          f"worker(s), seed {meta['seed']}, initial accuracy applied to "
          f"{meta['initial_accuracy_applies_to']}.\n"]
    t_all = time.perf_counter()
    for sc in scenarios:
        t0 = time.perf_counter()
        res = run_scenario(cfg, sc, trials, args.workers, progress=not args.no_progress)
        dt = time.perf_counter() - t0
        rows = summary_table(res, cases)
        write_csv(out / f"table_{sc}.csv", rows)
        cols = ["case", "initial_accuracy_pct", "mean_um", "std_um", "max_um", "min_um",
                "max_trial_mean_um", "success_pct", "iterations_mean"]
        heads = ["case", "initial accuracy %", "mean um", "std um", "max um", "min um",
                 "max trial mean um", "success %", "iterations"]
        table = markdown(rows, cols, heads)
        (out / f"table_{sc}.md").write_text(table + "\n", encoding="utf-8")
        per_trial = []
        for k in range(trials):
            for c, case in enumerate(cases):
                e = res["errors_um"][k, c]
                per_trial.append({"trial": k, "case": case.label,
                                  "mean_um": float(np.mean(e)), "max_um": float(np.max(e)),
                                  "success": bool(res["success"][k, c])})
        write_csv(out / f"trials_{sc}.csv.gz", per_trial)
        plot_errors(out / f"errors_{sc}.png", res, cases, sc, trials)
        desc = cfg.get("scenario", {}).get(sc, {}).get("description", "")
        meta["scenarios"][sc] = {"seconds": dt, "description": desc}
        md += [f"## scenario `{sc}`\n\n{desc}\n\n{trials} trials in {dt:.1f} s.\n\n{table}\n"]
        print(f"{sc}: {trials} trials in {dt:.1f} s -> {out}/table_{sc}.md", file=sys.stderr)
    jrows = jacobian_rows(cfg, scenarios[0] if scenarios else None)
    write_csv(out / "jacobian.csv", jrows)
    jcols = ["case", "step", "unknowns", "readings", "rank", "redundancy", "null",
             "condition", "gauge_fixed", "unidentifiable"]
    jtable = markdown(jrows, jcols)
    (out / "jacobian.md").write_text(jtable + "\n", encoding="utf-8")
    md += ["## Jacobian at the start values (noise-free data)\n\n" + jtable + "\n"]
    meta["seconds_total"] = time.perf_counter() - t_all
    (out / "summary.md").write_text("\n".join(md), encoding="utf-8")
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
