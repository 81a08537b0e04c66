"""Coverage of volcal's 95 % intervals over independent simulated experiments.

For each experiment k = 0 .. n-1: a new true error set (drawn, 60 um maximum volumetric
error), a new noise realisation of the bundled example's measurement (MCV 754, 6 stations,
149 poses, 4 tool offsets, paper 002 budget), identify(), then check whether the truth
lies inside the linearised 95 % interval (estimate +- 1.96 u) and the Monte Carlo 95 %
coverage interval of the volumetric error at 27 fixed poses (3 x 3 x 3 grid over the
travel, tool offset 0), and inside estimate +- 1.96 u for the 75 error parameters.
See volcal.analysis.uncertainty.coverage.

    python studies/coverage/run.py                 # 200 experiments, 1000 MC trials each
    python studies/coverage/run.py --smoke         # 4 experiments, 200 MC trials
    python studies/coverage/run.py -n 300 --workers 2 --out studies/coverage/results
    python studies/coverage/run.py --table-from studies/coverage/results/coverage_full.json

The README's results table is :func:`results_table` of the run's summary (``--update-readme``
copies it; ``--table-from`` prints it from a finished run's JSON without computing).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import readme_tables as rt  # noqa: E402


def results_table(summ: dict) -> str:
    """The README's results table (markdown) from a run's summary (coverage_*.json)."""
    n = int(summ["n"])
    rows = []
    for key, label in (("linear_inside", "linearised, volumetric error"),
                       ("mc_inside", f"Monte Carlo ({summ['mc_trials']} trials), volumetric error"),
                       ("parameters", "linearised, error parameters")):
        d = summ[key]
        per = (f"{100 * d['per_check_min']:.1f} % .. {100 * d['per_check_max']:.1f} %"
               if "per_check_min" in d else "-")
        sd = f"{d['experiment_rate_std']:.3f}" if "experiment_rate_std" in d else "-"
        rows.append({"interval": label, "inside": f"{d['inside']} / {d['checks']}",
                     "rate": f"{100 * d['rate']:.2f} %", "per": per, "sd": sd})
    return rt.markdown(rows, ["interval", "inside", "rate", "per", "sd"],
                       ["interval", "inside / checks", "coverage",
                        f"per checked quantity ({n} each)", "between-experiment sd"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-n", type=int, default=200, help="experiments (default 200)")
    ap.add_argument("--mc-trials", type=int, default=1000, help="MC trials per experiment")
    ap.add_argument("--seed", type=int, default=2023)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--smoke", action="store_true", help="4 experiments, 200 trials")
    ap.add_argument("--out", type=Path, default=None,
                    help="results folder (default results/ here; --smoke: a temporary folder)")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the results table into README.md (not with --smoke)")
    ap.add_argument("--table-from", type=Path, default=None, metavar="JSON",
                    help="print (with --update-readme: write) the results table of a finished "
                         "run's coverage_*.json; compute nothing")
    args = ap.parse_args(argv)
    here = Path(__file__).resolve().parent
    from readme_tables import output_folder

    if args.table_from is not None:
        tab = results_table(json.loads(args.table_from.read_text(encoding="utf-8")))
        print(tab)
        if args.update_readme:
            rt.update_readme(here / "README.md", {"results": tab})
        return 0
    if args.update_readme and args.smoke:
        raise SystemExit("--update-readme with --smoke would put smoke figures in the README")

    # a smoke run without --out writes into a new temporary folder, never into the repository
    args.out = output_folder(args.out, args.smoke, here / "results", "coverage")
    if args.smoke:
        args.n, args.mc_trials = 4, 200

    from volcal.analysis.uncertainty.coverage import CoverageSetup, run_coverage, summarise_coverage

    setup = CoverageSetup.from_example("mcv754", mc_trials=args.mc_trials)
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    res = run_coverage(setup, args.n, seed=args.seed, workers=args.workers, progress=True)
    summ = summarise_coverage(res)
    summ.update({"n": args.n, "mc_trials": args.mc_trials, "seed": args.seed,
                 "seconds_total": time.perf_counter() - t0,
                 # one timing on a shared machine: its load (1, 5, 15 min) at start and end
                 "load_average_start": load0, "load_average_end": os.getloadavg(),
                 "readings": int(len(setup.plan) * len(setup.tools) * len(setup.stations)),
                 "check_poses": int(len(setup.check_poses))})
    args.out.mkdir(parents=True, exist_ok=True)
    tag = "smoke" if args.smoke else "full"
    (args.out / f"coverage_{tag}.json").write_text(json.dumps(summ, indent=2) + "\n")
    np.savez_compressed(args.out / f"coverage_{tag}.npz",
                        linear_inside=np.array([r["linear_inside"] for r in res]),
                        mc_inside=np.array([r["mc_inside"] for r in res]),
                        z_parameters=np.array([r["z_parameters"] for r in res]),
                        u_linear=np.array([r["u_linear"] for r in res]),
                        u_mc=np.array([r["u_mc"] for r in res]))
    tab = results_table(summ)
    rt.write_tables(args.out, {"results": tab})
    print(json.dumps(summ, indent=2))
    print(f"\n{tab}\nresults in {args.out}")
    if args.update_readme:
        rt.update_readme(here / "README.md", {"results": tab})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
