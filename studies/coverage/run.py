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
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


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
    args = ap.parse_args(argv)
    here = Path(__file__).resolve().parent
    sys.path.insert(0, str(here.parent))
    from readme_tables import output_folder

    # a smoke run without --out writes into a new temporary folder, never into the repository
    args.out = output_folder(args.out, args.smoke, here / "results", "coverage")
    if args.smoke:
        args.n, args.mc_trials = 4, 200

    from volcal.analysis.uncertainty.coverage import CoverageSetup, run_coverage, summarise_coverage

    setup = CoverageSetup.from_example("mcv754", mc_trials=args.mc_trials)
    t0 = time.perf_counter()
    res = run_coverage(setup, args.n, seed=args.seed, workers=args.workers, progress=True)
    summ = summarise_coverage(res)
    summ.update({"n": args.n, "mc_trials": args.mc_trials, "seed": args.seed,
                 "seconds_total": time.perf_counter() - t0,
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
    print(json.dumps(summ, indent=2))
    print(f"results in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
