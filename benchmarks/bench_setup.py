"""Benchmark: the problem set-up of ``identify`` (IdentificationProblem and the IPOPT solver
built on it) against the number of readings, time and resident memory.

Each size runs in a fresh Python process (so that resident memory is that size's): the
bundled MCV 754 example (its stations and tool offsets) on a synthetic layout of N readings,
every pose seen by every station.  Only the layout enters the set-up, not the numbers, so no
data are simulated.  Reported per size: seconds and resident-memory growth (MB, from
/proc/self/statm, Linux) of building the IdentificationProblem and of building the IPOPT
solver, median over the repeats; then the exponent of a log-log fit of each stage's time and
memory against N.  Timings on a shared machine are noisy: compare runs made together.

    python benchmarks/bench_setup.py [--sizes 20000 200000] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from statistics import median

import numpy as np

CHILD = r"""
import json, sys, time
import numpy as np
from volcal.measurement.instruments import get_instrument
from volcal.measurement.simulate import example
from volcal.problem.residuals import IdentificationProblem, Layout
from volcal.solve.ipopt import NLPSolver

def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 1e6

n = int(sys.argv[1])
ex = example("mcv754")
n_st = len(ex.stations)
n_poses = max(n // n_st, 1)
layout = Layout(np.tile(np.arange(n_st), n_poses), n_st, None,
                np.repeat(np.arange(n_poses), n_st))
ins = get_instrument(None)
# a small build first: CasADi's one-time initialisation is not the set-up's cost
IdentificationProblem(ex.machine, ex.error_model, ins,
                      Layout(layout.station_index[:n_st], n_st, None,
                             layout.pose_index[:n_st]))
m0, t0 = rss_mb(), time.perf_counter()
problem = IdentificationProblem(ex.machine, ex.error_model, ins, layout)
m1, t1 = rss_mb(), time.perf_counter()
NLPSolver(problem)
m2, t2 = rss_mb(), time.perf_counter()
print(json.dumps({"readings": layout.n_readings, "problem_s": t1 - t0,
                  "problem_mb": m1 - m0, "solver_s": t2 - t1, "solver_mb": m2 - m1}))
"""

STAGES = ("problem_s", "problem_mb", "solver_s", "solver_mb")


def measure(n: int, repeats: int) -> dict[str, float]:
    """Median over ``repeats`` fresh processes of the set-up figures at about n readings."""
    runs = []
    for _ in range(repeats):
        out = subprocess.run(
            [sys.executable, "-c", CHILD, str(n)], capture_output=True, text=True, check=True
        )
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return {k: median(r[k] for r in runs) for k in ("readings",) + STAGES}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[20000, 200000])
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args(argv)
    rows = [measure(n, args.repeats) for n in args.sizes]
    print("| readings | problem s | problem MB | solver s | solver MB | bytes/reading |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        per = (r["problem_mb"] + r["solver_mb"]) * 1e6 / r["readings"]
        print(
            f"| {r['readings']:,} | {r['problem_s']:.2f} | {r['problem_mb']:.0f} | "
            f"{r['solver_s']:.2f} | {r['solver_mb']:.0f} | {per:.0f} |"
        )
    if len(rows) > 1:
        n = np.log([r["readings"] for r in rows])
        for k in STAGES:
            v = np.array([max(r[k], 1e-9) for r in rows])
            print(f"exponent of {k} vs readings: {np.polyfit(n, np.log(v), 1)[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
