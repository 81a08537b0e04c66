"""Benchmark: the whole ``volcal mc`` process, command line to written result.

Runs, for each mode (nonlinear, the default, and linear), ``--repeat`` times::

    volcal mc --example mcv754 --trials 10000 [--mode linear] --out <fresh folder> -v

as a subprocess (a fresh output folder every run: an existing one would be resumed),
measures its wall time from start to exit and its peak resident memory, and reads the
per-stage wall times the command prints with ``-v`` (start-up, imports, model build,
simulation, identification, Monte Carlo set-up, trials, linearised covariance, IPOPT
cross-check, tables, plots, summary and report, writing).  Prints medians (and the range)
as a table and writes it to ``benchmarks/results/mc_whole_process.txt``.

Run by hand on a quiet machine (other jobs on the cores show in the figures; the load
average before and after is printed with them)::

    python benchmarks/mc_whole_process.py [--repeat 5] [--workers default 1 2]

Goals (issue): whole process < 5 s nonlinear, < 2 s linear, on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
GOALS = {"nonlinear": 5.0, "linear": 2.0}
STAGE = re.compile(r"^\s{2}(\S.*?)\s{2,}([0-9.]+) s$")


def volcal_exe() -> list[str]:
    exe = shutil.which("volcal") or str(Path(sys.executable).parent / "volcal")
    return [exe] if Path(exe).exists() else [sys.executable, "-m", "volcal.cli.main"]


def run_measured(cmd: list[str]) -> tuple[float, float, dict[str, float], str]:
    """(wall s, peak RSS MiB of the main process (Linux: wait4), stages, stdout) of one
    run."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, text=True)
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{out}\n{err}")
    stages: dict[str, float] = {}
    on = False
    for line in out.splitlines():
        if line.startswith("stage timings"):
            on = True
            continue
        m = STAGE.match(line) if on else None
        if m:
            stages[m.group(1)] = float(m.group(2))
    return wall, ru.ru_maxrss / 1024.0, stages, out


def busy_fraction(seconds: float = 0.5) -> float:
    """Fraction of all cores busy over ``seconds`` (Linux /proc/stat; 0 elsewhere)."""
    try:
        with open("/proc/stat") as fh:
            a = [int(v) for v in fh.readline().split()[1:]]
        time.sleep(seconds)
        with open("/proc/stat") as fh:
            b = [int(v) for v in fh.readline().split()[1:]]
    except OSError:  # pragma: no cover
        return 0.0
    d = [y - x for x, y in zip(a, b)]
    idle = d[3] + d[4]  # idle, iowait
    total = sum(d[:8])
    return 1.0 - idle / total if total else 0.0


def wait_quiet(limit: float, threshold: float = 0.15) -> bool:
    """Wait (at most ``limit`` s) until other jobs leave the cores idle; True if they do."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < limit:
        if busy_fraction() < threshold:
            return True
    return False


def fmt(values: list[float], digits: int = 2) -> str:
    med = statistics.median(values)
    if len(values) == 1:
        return f"{med:.{digits}f}"
    return f"{med:.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--trials", type=int, default=10_000)
    ap.add_argument("--modes", nargs="+", default=["nonlinear", "linear"])
    ap.add_argument(
        "--workers",
        nargs="+",
        default=["default"],
        help="worker settings to compare: default (the command's own), or numbers",
    )
    ap.add_argument(
        "--quiet-wait",
        type=float,
        default=0.0,
        metavar="S",
        help="before each run wait up to S seconds for the cores to be idle (other jobs)",
    )
    ap.add_argument(
        "--exe",
        default=None,
        help="the command to time instead of this environment's volcal (e.g. another "
        "checkout's: 'python /other/src/volcal/cli/main.py'), split on spaces",
    )
    ap.add_argument("--label", default="", help="a title line for the table")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "mc_whole_process.txt")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    # byte-compiled modules, as an installed copy has them (see compare_scipy.compile_volcal)
    import compileall

    import volcal

    compileall.compile_dir(Path(volcal.__file__).parent, quiet=1)

    exe = args.exe.split() if args.exe else volcal_exe()
    configs = [(m, w) for w in args.workers for m in args.modes]
    load0 = os.getloadavg()
    results: dict[tuple[str, str], dict] = {}
    quiet = 0
    with tempfile.TemporaryDirectory(prefix="mc_bench_") as tmp:
        # one warm-up run (file cache, model cache), not counted
        run_measured(
            exe + ["mc", "--example", "mcv754", "--trials", "200", "--out", f"{tmp}/warm", "-q"]
        )
        for r in range(args.repeat):
            # interleaved, so that a change of load affects every configuration alike
            for mode, w in configs:
                cmd = exe + ["mc", "--example", "mcv754", "--trials", str(args.trials)]
                if mode != "nonlinear":
                    cmd += ["--mode", mode]
                if w != "default":
                    cmd += ["--workers", w]
                cmd += ["--out", f"{tmp}/{mode}-{w}-{r}", "-v"]
                if args.quiet_wait > 0:
                    quiet += wait_quiet(args.quiet_wait)
                busy = busy_fraction(0.2)
                wall, rss, stages, _ = run_measured(cmd)
                res = results.setdefault(
                    (mode, w), {"wall": [], "rss": [], "stages": {}, "busy": []}
                )
                res["busy"].append(busy)
                res["wall"].append(wall)
                res["rss"].append(rss)
                for k, v in stages.items():
                    res["stages"].setdefault(k, []).append(v)
                print(
                    f"  run {r + 1}/{args.repeat} {mode:9s} workers={w:7s} {wall:6.2f} s",
                    file=sys.stderr,
                    flush=True,
                )
    load1 = os.getloadavg()
    busy_median = statistics.median([b for r in results.values() for b in r["busy"]])

    names: list[str] = []
    for res in results.values():
        for k in res["stages"]:
            if k not in names and k != "total":
                names.append(k)
    head = [f"{m}" + ("" if w == "default" else f", --workers {w}") for m, w in configs]
    lines = [
        f"# volcal mc, whole process: {args.trials:,} trials of the bundled example (mcv754)",
        "",
        *([args.label, ""] if args.label else []),
        "command: volcal mc --example mcv754 --trials "
        f"{args.trials} [--mode linear] [--workers W] --out <fresh folder> -v",
        f"median of {args.repeat} runs per column (min-max); seconds of wall clock",
        "",
        "| stage | " + " | ".join(head) + " |",
        "|---|" + "---:|" * len(configs),
    ]
    for k in names:
        row = [fmt(results[c]["stages"].get(k, [0.0]), 3) for c in configs]
        lines.append(f"| {k} | " + " | ".join(row) + " |")
    lines.append(
        "| other (not in a stage: argument parsing, exit, ...) | "
        + " | ".join(
            fmt(
                [
                    w - sum(v[i] for k, v in results[c]["stages"].items() if k != "total")
                    for i, w in enumerate(results[c]["wall"])
                ],
                3,
            )
            for c in configs
        )
        + " |"
    )
    lines.append(
        "| the command's own total (process start to the end of its work) | "
        + " | ".join(fmt(results[c]["stages"].get("total", [0.0]), 3) for c in configs)
        + " |"
    )
    lines.append(
        "| **whole process** (wall, start to exit, measured outside) | "
        + " | ".join("**" + fmt(results[c]["wall"]) + "**" for c in configs)
        + " |"
    )
    lines.append(
        "| peak RSS of the main process (MiB) | "
        + " | ".join(fmt(results[c]["rss"], 0) for c in configs)
        + " |"
    )
    lines.append("")
    for m, w in configs:
        goal = GOALS.get(m)
        if goal is None:
            continue
        med = statistics.median(results[(m, w)]["wall"])
        label = m + ("" if w == "default" else f" --workers {w}")
        lines.append(
            f"- goal {m} < {goal:g} s: {med:.2f} s ({label}): "
            + ("met" if med < goal else "NOT met")
        )
    lines += [
        "",
        f"machine: {platform.machine()}, {os.cpu_count()} CPUs (usable "
        f"{len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'}), "
        f"Python {platform.python_version()}; load average {load0[0]:.2f} before, "
        f"{load1[0]:.2f} after (other jobs share this machine); cores busy just before "
        f"a run: median {100 * busy_median:.0f} %"
        + (
            f"; {quiet} of {args.repeat * len(configs)} runs started on idle cores "
            f"(waited up to {args.quiet_wait:g} s)"
            if args.quiet_wait > 0
            else ""
        ),
        f"date: {time.strftime('%Y-%m-%d %H:%M')}",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
