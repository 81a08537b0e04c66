"""Benchmark: the whole ``volcal plan`` process for the bundled settings.

Runs, for each setting, ``--repeat`` times::

    volcal plan --setting <setting> --out <fresh folder> [--no-plots]

as a subprocess, measures its wall time from start to exit and its CPU time (user +
system of the finished child), and reads the plan's criterion, its search time and the
evaluations from the folder's ``summary.json`` (so a faster run that finds a worse plan
shows).  Prints medians (and the range) as a table.

Run by hand (other jobs on the cores show in the wall times, less in the CPU times; the
load average before and after is printed with them)::

    python benchmarks/bench_plan.py [--repeat 3] [--settings mcv754 trunnion_ac] [--no-plots]

Goals (issue 27): mcv754 < 5 s, trunnion_ac < 15 s, the same plans or a better criterion.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(setting: str, no_plots: bool) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "plan"
        cmd = [sys.executable, "-m", "volcal", "plan", "--setting", setting, "--out", str(out)]
        if no_plots:
            cmd.append("--no-plots")
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        summary = json.loads((out / "summary.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "plan_s": float(summary["seconds"]),
        "criterion_um": float(summary["criterion_value"]),
        "evaluations": float(sum(s["evaluations"] for s in summary["searches"])),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs per setting (default 3)")
    ap.add_argument("--settings", nargs="+", default=["mcv754", "trunnion_ac"])
    ap.add_argument("--no-plots", action="store_true", help="pass --no-plots")
    args = ap.parse_args(argv)
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    print("| setting | wall (s) | CPU (s) | planning (s) | criterion I (um) | evaluations |")
    print("|---|---|---|---|---|---|")
    for setting in args.settings:
        runs = [_run(setting, args.no_plots) for _ in range(args.repeat)]

        def cell(key: str, fmt: str = ".1f", runs: list[dict[str, float]] = runs) -> str:
            v = [r[key] for r in runs]
            med = statistics.median(v)
            return f"{med:{fmt}}" if len(v) == 1 else f"{med:{fmt}} ({min(v):{fmt}}-{max(v):{fmt}})"

        print(
            f"| {setting} | {cell('wall_s')} | {cell('cpu_s')} | {cell('plan_s')} | "
            f"{cell('criterion_um', '.4f')} | {cell('evaluations', '.0f')} |"
        )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
