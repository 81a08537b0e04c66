"""Benchmark: the whole ``volcal plan`` process for the bundled settings.

Runs, for each setting, ``--repeat`` times::

    volcal plan --setting <setting> --out <fresh folder> [--no-plots]

as a subprocess, measures its wall time from start to exit and its CPU time (user +
system of the finished child and its plotting child), and reads the plan's criterion,
its search time and the evaluations from the folder's ``summary.json`` (so a faster run
that finds a worse plan shows).  Prints medians (and the range) as a table.

With ``--baseline-python PY`` (the interpreter of another installation, e.g. the main
branch's virtual environment) the two versions run in turn, run by run (this one, then
the baseline), the ratio of each pair is printed (median and range: pairs taken close in
time cancel most of a shared machine's drift), and the plans are compared: whether the
stations and the criterion are identical to the bit, which of the written stations.csv,
poses.csv, measurement_plan.csv and prediction_volumetric.csv differ byte for byte, the
largest station difference (mm), whether the selected poses are the same (a rotary axis
at -180 and +180 deg is one pose), and the difference of the criterion (negative: this
version's plan is better).

With ``--baseline-args='--workers 1'`` (and no baseline interpreter) this version runs in
turn with and without those flags: the placement starts solved side by side (the default)
against one after the other in the program itself.

Before the runs, each version's modules are byte-compiled, as installing volcal does
(``pip install`` compiles them; an editable install under PYTHONDONTWRITEBYTECODE, as on
the project's machine, compiled its 50-odd modules again in every run: 0.2-0.3 s of CPU
in every figure before this was done).

Run by hand (other jobs on the cores show in the wall times, less in the CPU times; the
load average before and after is printed with them)::

    python benchmarks/bench_plan.py [--repeat 3] [--settings mcv754 trunnion_ac] [--no-plots]
        [--baseline-python ../main/.venv/bin/python] [--baseline-args='--workers 1']
        [--out benchmarks/results/plan.txt]

Goals (issue 27): mcv754 < 5 s, trunnion_ac < 15 s, the same plans or a better criterion.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd


def _run(
    python: str, setting: str, no_plots: bool, keep: Path, extra: list[str] | None = None
) -> dict[str, float]:
    out = keep / "plan"
    cmd = [python, "-m", "volcal", "-q", "plan", "--setting", setting, "--out", str(out)]
    cmd += ["--force", *(extra or [])]
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


def _compile(python: str) -> None:
    """Byte-compile the volcal that ``python`` imports, as installing it does (see the
    module docstring): both versions are timed as installed copies run."""
    code = (
        "import compileall, pathlib, volcal; "
        "compileall.compile_dir(pathlib.Path(volcal.__file__).parent, quiet=1)"
    )
    subprocess.run([python, "-c", code], check=True, capture_output=True)


def _poses(folder: Path) -> Counter:
    """The selected poses as a multiset; a rotary axis at +-180 deg counted as 180."""
    p = pd.read_csv(folder / "poses.csv")
    for c in p.columns:
        v = p[c].to_numpy(float)
        if np.any(np.isclose(np.abs(v), 180.0)):
            p[c] = np.where(np.isclose(v, -180.0), 180.0, v)
    return Counter(map(tuple, p.round(6).to_numpy()))


def _compare(new: Path, base: Path) -> str:
    cols = ["x_mm", "y_mm", "z_mm"]
    Sn = pd.read_csv(new / "stations.csv")[cols].to_numpy(float)
    Sb = pd.read_csv(base / "stations.csv")[cols].to_numpy(float)
    cn = json.loads((new / "summary.json").read_text())["criterion_value"]
    cb = json.loads((base / "summary.json").read_text())["criterion_value"]
    pn, pb = _poses(new), _poses(base)
    same = np.array_equal(Sn, Sb) and cn == cb
    tables = [
        f
        for f in ("stations.csv", "poses.csv", "measurement_plan.csv", "prediction_volumetric.csv")
        if (new / f).read_bytes() != (base / f).read_bytes()
    ]
    return (
        ("identical to the bit (stations, criterion), " if same else "")
        + (f"tables differing: {', '.join(tables)}; " if tables else "the same tables; ")
        + f"stations differ by at most {np.abs(Sn - Sb).max():.2e} mm; "
        f"selected poses {'the same' if pn == pb else 'differ'} ({sum(pn.values())} poses"
        f"{'' if pn == pb else f', {sum((pn - pb).values())} exchanged'}); "
        f"criterion {cn:.10f} um here, {cb:.10f} um baseline, difference {cn - cb:+.2e} um"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs per setting (default 3)")
    ap.add_argument("--settings", nargs="+", default=["mcv754", "trunnion_ac"])
    ap.add_argument("--no-plots", action="store_true", help="pass --no-plots")
    ap.add_argument("--baseline-python", help="interpreter of a version to run in turn")
    ap.add_argument(
        "--baseline-args",
        default="",
        help="extra flags of the baseline's runs, e.g. --baseline-args='--workers 1' (with "
        "--baseline-python or alone: this version run in turn with them)",
    )
    ap.add_argument("--out", type=Path, help="also write the printout to this file")
    args = ap.parse_args(argv)
    text = io.StringIO()

    def say(line: str) -> None:
        print(line, flush=True)
        text.write(line + "\n")

    say(f"command: python benchmarks/bench_plan.py {shlex.join(argv or sys.argv[1:])}")
    say(f"load average before: {os.getloadavg()[0]:.2f}")
    versions = [("this", sys.executable)]
    if args.baseline_python or args.baseline_args:
        versions.append(("baseline", args.baseline_python or sys.executable))
    for py in dict.fromkeys(py for _, py in versions):
        _compile(py)
    say("each version's modules byte-compiled first, as installing volcal does")
    say(
        "| setting | version | wall (s) | CPU (s) | planning (s) | criterion I (um) | evaluations |"
    )
    say("|---|---|---|---|---|---|---|")
    extra = {"this": [], "baseline": args.baseline_args.split()}
    comparisons = []
    with tempfile.TemporaryDirectory() as tmp:
        for setting in args.settings:
            runs: dict[str, list[dict[str, float]]] = {v: [] for v, _ in versions}
            for _ in range(args.repeat):
                for name, py in versions:
                    keep = Path(tmp) / setting / name
                    keep.mkdir(parents=True, exist_ok=True)
                    runs[name].append(_run(py, setting, args.no_plots, keep, extra[name]))
            for name, _ in versions:

                def cell(key: str, fmt: str = ".1f", rs: list = runs[name]) -> str:
                    v = [r[key] for r in rs]
                    med = statistics.median(v)
                    return (
                        f"{med:{fmt}}"
                        if len(v) == 1
                        else f"{med:{fmt}} ({min(v):{fmt}}-{max(v):{fmt}})"
                    )

                say(
                    f"| {setting} | {name} | {cell('wall_s', '.2f')} | {cell('cpu_s', '.2f')} "
                    f"| {cell('plan_s')} | {cell('criterion_um', '.6f')} "
                    f"| {cell('evaluations', '.0f')} |"
                )
            for name, _ in versions:
                # in run order: a first run slower than the rest is the cold start (files
                # not yet in the page cache), not the program
                comparisons.append(
                    f"{setting}: {name}: wall of each run in order (s): "
                    + " ".join(f"{r['wall_s']:.2f}" for r in runs[name])
                )
            if len(versions) > 1:
                for key in ("wall_s", "cpu_s"):
                    r = [a[key] / b[key] for a, b in zip(runs["this"], runs["baseline"])]
                    comparisons.append(
                        f"{setting}: {key[:-2]} this / baseline, pair by pair: median "
                        f"{statistics.median(r):.3f} ({min(r):.3f}-{max(r):.3f})"
                    )
                comparisons.append(
                    f"{setting}: "
                    + _compare(
                        Path(tmp) / setting / "this" / "plan",
                        Path(tmp) / setting / "baseline" / "plan",
                    )
                )
    for line in comparisons:
        say(line)
    say(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.out is not None:
        args.out.write_text(text.getvalue())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
