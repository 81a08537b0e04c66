"""volcal identify against the fastest plain scipy script, whole process and per stage.

    python benchmarks/compare_scipy.py                  # 1e3 .. 2e5 readings, 1 and 2 threads
    python benchmarks/compare_scipy.py --million        # and 10^6 readings
    python benchmarks/compare_scipy.py --sizes 1000 10000 --threads 1 --repeat 3
    python benchmarks/compare_scipy.py --smoke          # tiny, for the tests

Both sides run as separate processes on the same simulated data (the bundled MCV 754
example: paper 002's budget, four tool offsets, its six stations, a grid sized to the
number of readings), with the same number of BLAS threads in the environment
(OPENBLAS_NUM_THREADS, OMP_NUM_THREADS, MKL_NUM_THREADS).  volcal's command line runs BLAS
on one thread whatever the environment says (its dense blocks are small: one thread is
faster than a contended pool) and uses the other core for its plotting children; the
script follows the environment.  So with two threads the script has two BLAS threads and
volcal one, and, as the script is not always faster with two, the printout also compares
each side's best over the thread counts run:

* volcal: ``volcal identify --model mcv754_wxyzt --data DATA.csv --out DIR`` with default
  outputs (tables, report and plots) and with ``--no-plots``;
* scipy: ``benchmarks/scipy_reference.py`` (read it: the script a competent user writes
  with the analytic Jacobian, covariance, a CSV) in every configuration of its
  ``CONFIGS``: dense exact TRF (scipy's default), Levenberg-Marquardt and sparse TRF +
  LSMR, each with scipy's default and with tight tolerances, given start stations 1 mm
  from the truth (volcal computes its own start values from the data).  A configuration
  counts only when it reached the minimum (its cost within 1e-6 relative of the lowest
  cost of all configurations at that size); the fastest of those is the reference of
  the ratios.  A configuration whose time, extrapolated linearly from the previous size,
  would exceed ``--max-seconds`` is not run at the larger sizes (printed as skipped).

Measured from outside: whole-process wall time, CPU time of the process tree, and peak
memory two ways: the largest process's resident set (``os.wait4``) and the sum over the
process and its children (volcal draws its plots in two child processes) of their
proportional set sizes, sampled every 20 ms in one more, untimed run (volcal and the
fastest configuration; up to ``--tree-max`` readings).  The stages come from each side's
own timings (scipy: the script's JSON; volcal: the stage record in result.json,
``timings_s``, of the run without plots; volcal's plots are the difference of its two
whole-process times, its start-up the rest).  The best of ``--repeat`` runs is kept
(``--repeat-large`` runs from 50,000 readings).  Prints every configuration's time and
memory, side-by-side tables against the fastest with the fitted scaling exponent of each
column and stage (log-log slope over the sizes), writes benchmarks/results/
compare_scipy.csv (one row per size and thread count), compare_scipy_configs.csv (one
row per scipy run) and compare_scipy.png (log-log).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent


def compile_volcal() -> None:
    """Byte-compile volcal's modules, as installing it does (``pip install`` compiles; an
    editable install under PYTHONDONTWRITEBYTECODE would recompile every module in every
    run, 0.1 s that no installed copy pays).  Both sides import volcal's modules."""
    import compileall

    import volcal

    compileall.compile_dir(Path(volcal.__file__).parent, quiet=1)


def make_data(n_readings: int, folder: Path, seed: int = 0) -> tuple[Path, Path, int]:
    """A simulated measurement of about n_readings readings; returns (data CSV, stations
    CSV for the scipy script, actual number of readings)."""
    from volcal.measurement.plans import grid_plan
    from volcal.measurement.simulate import _clear_plan, example, simulate

    ex = example("mcv754")
    per_pose = len(ex.tools) * len(ex.stations)
    target = max(n_readings / per_pose, 8)
    # the grid (about as many positions per axis as the travels are long) whose poses
    # clear of the stations come closest to the number asked for
    best = None
    for nz in range(2, 40):
        for ny in range(nz, nz + 3):
            for nx in range(ny, ny + 3):
                if nx * ny * nz > 2.5 * target + 8:
                    continue
                g = grid_plan(ex.machine.spec, {"X": nx, "Y": ny, "Z": nz})
                g = _clear_plan(ex.machine, g, ex.tools, ex.stations, 50.0)
                err = abs(np.log(max(len(g), 1) / target))
                if best is None or err < best[0]:
                    best = (err, g)
    plan = best[1]
    sim = simulate(ex.machine, ex.error_model, ex.theta_true, ex.stations, plan, ex.tools,
                   ex.budget, seed)
    data = folder / "data.csv"
    sim.measurements.to_csv(data, index=False)
    rng = np.random.default_rng(seed)
    st = ex.stations.copy()
    for c in ("x_mm", "y_mm", "z_mm"):
        st[c] = st[c] + rng.normal(0.0, 1.0, len(st))
    stations = folder / "stations_start.csv"
    st.to_csv(stations, index=False)
    return data, stations, len(sim.measurements)


def _tree_pss_mib(root: int) -> float:
    """Proportional set size (MiB) of a process and all its descendants: shared pages
    (a forked child's inherited libraries) counted once, split between their users."""
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        kids.setdefault(ppid, []).append(int(d))
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        todo += kids.get(pid, [])
        try:
            with open(f"/proc/{pid}/smaps_rollup") as fh:
                for line in fh:
                    if line.startswith("Pss:"):
                        total += int(line.split()[1]) / 1024.0
                        break
        except OSError:
            continue
    return total


#: a minimal launcher (python -S: no site, no imports but os/time/json/sys) that runs the
#: measured command and reports its wall time and resources.  Measuring from the benchmark
#: process itself would be wrong: a child's peak resident set starts at its parent's size
#: at fork (before exec), and this process holds numpy, pandas and the simulated data.
_LAUNCHER = """
import json, os, sys, time
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    fd = os.open(os.devnull, os.O_WRONLY)
    os.dup2(fd, 1)
    os.execvp(sys.argv[1], sys.argv[1:])
_, status, ru = os.wait4(pid, 0)
wall = time.perf_counter() - t0
print(json.dumps({"wall": wall, "cpu": ru.ru_utime + ru.ru_stime, "rss": ru.ru_maxrss / 1024.0,
                  "code": os.waitstatus_to_exitcode(status)}))
"""


def _run(cmd: list[str], threads: int, sample: bool = False) -> dict:
    """Wall time (s), CPU time of the process and its children (s), peak resident memory
    of the largest process (MiB, ``os.wait4``) and, with ``sample``, the peak total PSS
    of the process tree sampled every 20 ms (MiB; sampling takes CPU, so it runs in a
    separate, untimed repetition) of a whole process."""
    import threading

    env = dict(os.environ)
    for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[v] = str(threads)
    proc = subprocess.Popen([sys.executable, "-S", "-c", _LAUNCHER, *cmd], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    peak = [0.0]
    done = threading.Event()

    def sampler() -> None:
        while not done.wait(0.02):
            peak[0] = max(peak[0], _tree_pss_mib(proc.pid))

    th = threading.Thread(target=sampler, daemon=True) if sample else None
    if th is not None:
        th.start()
    out, err = proc.communicate()
    done.set()
    if th is not None:
        th.join()
    try:
        m = json.loads(out.decode().strip().splitlines()[-1])
    except (IndexError, ValueError):
        raise RuntimeError(f"{cmd[0]}: the launcher failed: {err.decode()[-2000:]}") from None
    if m["code"] != 0:
        raise RuntimeError(f"{cmd[0]} failed ({m['code']}): {err.decode()[-2000:]}")
    m["pss"] = peak[0] if sample else float("nan")
    return m


def _scipy_cmd(data: Path, stations: Path, folder: Path, config: str) -> list[str]:
    return [sys.executable, str(HERE / "scipy_reference.py"), str(data), str(stations),
            "--model", "mcv754_wxyzt", "--out", str(folder / f"scipy_{config}.csv"),
            "--timings", str(folder / f"timings_{config}.json"), "--config", config]


def measure(n: int, threads: int, repeat: int, work: Path, configs: list[str],
            tree: bool, runs: list[dict]) -> dict:
    """One size and thread count: every volcal and scipy command ``repeat`` times (the
    best kept); appends one record per scipy configuration to ``runs``."""
    folder = work / f"n{n}"
    folder.mkdir(parents=True, exist_ok=True)
    data, stations, N = make_data(n, folder)
    volcal_exe = str(Path(sys.executable).parent / "volcal")
    row: dict = {"readings": N, "threads": threads}
    best: dict[str, tuple] = {}
    pss: dict[str, float] = {}
    cmds = {}
    for label, extra in (("volcal", []), ("volcal_no_plots", ["--no-plots"])):
        out = folder / f"out_{label}"
        cmds[label] = (
            [volcal_exe, "-q", "identify", "--model", "mcv754_wxyzt", "--data", str(data),
             "--out", str(out), "--force", *extra],
            out,
        )
    for c in configs:
        cmds[f"scipy:{c}"] = (_scipy_cmd(data, stations, folder, c), None)
    for _ in range(repeat):
        for label, (cmd, out) in cmds.items():
            m = _run(cmd, threads)
            if out is not None:
                doc = json.loads((out / "result.json").read_text())
                solve, st = sum(ph["seconds"] for ph in doc["phases"]), doc.get("timings_s", {})
            else:
                t = json.loads((folder / f"timings_{label[6:]}.json").read_text())
                solve, st = t["solve"], t
            if label not in best or m["wall"] < best[label][0]["wall"]:
                best[label] = (m, solve, st)
    # which configurations reached the minimum; the fastest of them is the reference
    costs = {c: best[f"scipy:{c}"][2]["cost"] for c in configs}
    low = min(costs.values())
    ok = {c: costs[c] <= low * (1 + 1e-6) + 1e-12 for c in configs}
    fastest = min((c for c in configs if ok[c]), key=lambda c: best[f"scipy:{c}"][0]["wall"])
    for c in configs:
        m, solve, t = best[f"scipy:{c}"]
        runs.append({"readings": N, "threads": threads, "config": c, "wall_s": m["wall"],
                     "cpu_s": m["cpu"], "MiB": m["rss"], "solve_s": solve,
                     "nfev": t["nfev"], "cost_rel": t["cost"] / low - 1.0,
                     "status": t["status"], "reached_minimum": ok[c],
                     "fastest": c == fastest})
    # the whole process tree's memory, in one more (untimed) run each
    for label in ("volcal", "volcal_no_plots", f"scipy:{fastest}"):
        pss[label] = _run(cmds[label][0], threads, sample=True)["pss"] if tree else float("nan")
    for label in ("volcal", "volcal_no_plots"):
        m, solve, _ = best[label]
        row[f"{label}_s"] = m["wall"]
        row[f"{label}_cpu_s"] = m["cpu"]
        row[f"{label}_MiB"] = m["rss"]
        row[f"{label}_tree_MiB"] = pss[label]
        row[f"{label}_solve_s"] = solve
    # volcal's stages (its own record in result.json, run without plots); the plots are
    # the difference of the two whole-process times; start-up and imports the rest
    st = best["volcal_no_plots"][2]
    for key, name in VOLCAL_STAGES.items():
        row[f"volcal_{key}_s"] = sum(v for k, v in st.items() if k in name)
    row["volcal_plots_s"] = max(row["volcal_s"] - row["volcal_no_plots_s"], 0.0)
    row["volcal_startup_s"] = max(
        row["volcal_no_plots_s"] - sum(row[f"volcal_{k}_s"] for k in VOLCAL_STAGES), 0.0
    )
    m, solve, t = best[f"scipy:{fastest}"]
    row["scipy_config"] = fastest
    row["scipy_s"], row["scipy_cpu_s"], row["scipy_MiB"] = m["wall"], m["cpu"], m["rss"]
    row["scipy_tree_MiB"], row["scipy_solve_s"] = pss[f"scipy:{fastest}"], solve
    for k in ("imports", "read", "model", "setup", "covariance", "write"):
        row[f"scipy_{k}_s"] = t[k]
    row["ratio_whole"] = row["volcal_s"] / row["scipy_s"]
    row["ratio_whole_no_plots"] = row["volcal_no_plots_s"] / row["scipy_s"]
    row["ratio_solve"] = row["volcal_solve_s"] / row["scipy_solve_s"]
    row["ratio_MiB_no_plots"] = row["volcal_no_plots_MiB"] / row["scipy_MiB"]
    return row


#: volcal's stage names (volcal.base.progress) grouped as the table shows them
VOLCAL_STAGES = {
    "read": ("reading the data",),
    "model": ("building the model",),
    "setup": ("start values and reading uncertainties", "building the problem"),
    # the whole solving stage: datum selection, every phase, pivots, polish (the
    # ``volcal_solve_s`` column is the optimiser's phases alone)
    "solving": ("solving",),
    "covariance": ("uncertainty and identifiability",),
    "write": ("writing the tables",),
    "adequacy": ("testing the model's adequacy",),
}


def stage_table(df: pd.DataFrame) -> str:
    """Per-stage seconds side by side (volcal / scipy) for every size, one thread count."""
    stages = ["startup", "read", "model", "setup", "solving", "covariance", "adequacy", "write",
              "plots"]
    lines = ["readings | " + " | ".join(f"{s} v/s" for s in stages)]
    for _, r in df.iterrows():
        cells = []
        for s in stages:
            v = r.get(f"volcal_{s}_s", float("nan"))
            key = {"startup": "imports", "plots": None, "solving": "solve"}.get(s, s)
            sc = r.get(f"scipy_{key}_s", float("nan")) if key else float("nan")
            cells.append(f"{v:.3g}/{sc:.3g}" if sc == sc else f"{v:.3g}/-")
        lines.append(f"{int(r['readings'])} | " + " | ".join(cells))
    return "\n".join(lines)


def best_over_threads(df: pd.DataFrame) -> pd.DataFrame:
    """Per size, the script's fastest run over the thread counts (config, threads) and
    volcal's fastest with and without plots, with the ratios."""
    rows = []
    for n, part in df.groupby("readings"):
        s = part.loc[part["scipy_s"].idxmin()]
        v = part["volcal_s"].min()
        vn = part["volcal_no_plots_s"].min()
        rows.append({
            "readings": n, "scipy_s": s["scipy_s"], "scipy_config": s["scipy_config"],
            "scipy_threads": s["threads"], "volcal_s": v, "volcal_no_plots_s": vn,
            "ratio_whole": v / s["scipy_s"], "ratio_whole_no_plots": vn / s["scipy_s"],
        })  # fmt: skip
    return pd.DataFrame(rows)


def exponents(df: pd.DataFrame, cols: list[str]) -> dict[str, float]:
    """Log-log slope of each column against the number of readings (per thread count)."""
    out = {}
    if df["readings"].nunique() < 2:
        return out
    x = np.log(df["readings"].to_numpy(float))
    for c in cols:
        v = df[c].to_numpy(float)
        # a column measured at some sizes only (tree memory), or a difference clamped at 0
        # (the plots, when the run with them was the faster): those sizes left out
        y = np.log(np.where(v > 0, v, np.nan))
        ok = np.isfinite(y)
        if ok.sum() >= 2:
            out[c] = float(np.polyfit(x[ok], y[ok], 1)[0])
    return out


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(HERE))
    from scipy_reference import CONFIGS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000, 200000])
    ap.add_argument("--million", action="store_true", help="also 10^6 readings")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--repeat-large", type=int, default=1,
                    help="runs per command from 50,000 readings (default 1)")
    ap.add_argument("--configs", nargs="+", choices=list(CONFIGS), default=list(CONFIGS),
                    help="scipy configurations (default: all)")
    ap.add_argument("--max-seconds", type=float, default=150.0,
                    help="skip a scipy configuration at the sizes where its time, "
                    "extrapolated linearly from the previous size, exceeds this")
    ap.add_argument("--tree-max", type=int, default=100000,
                    help="sample the process tree's memory up to this many readings")
    ap.add_argument("--smoke", action="store_true",
                    help="100 readings, 1 thread, 1 run, two configurations")
    ap.add_argument("--out", type=Path, default=HERE / "results",
                    help="folder for compare_scipy.csv / .png")
    ap.add_argument("--summarize", type=Path, nargs="+", metavar="CSV",
                    help="print each side at its best over the thread counts from "
                    "compare_scipy.csv files written before (several runs: their rows "
                    "together), and stop (nothing is run)")
    a = ap.parse_args(argv)
    if a.summarize is not None:
        with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
            rows = pd.concat([pd.read_csv(f) for f in a.summarize], ignore_index=True)
            print(best_over_threads(rows).to_string(index=False))
        return 0
    if a.million:
        a.sizes = sorted({*a.sizes, 1_000_000})
    if a.smoke:
        a.sizes, a.threads, a.repeat, a.configs = [100], [1], 1, ["trf_exact", "trf_lsmr"]
    compile_volcal()
    rows: list[dict] = []
    runs: list[dict] = []
    skipped: list[str] = []
    with tempfile.TemporaryDirectory(prefix="volcal-bench-") as tmp:
        for th in a.threads:
            last: dict[str, tuple[int, float]] = {}
            for n in a.sizes:
                configs = []
                for c in a.configs:
                    if c in last and last[c][1] * n / last[c][0] > a.max_seconds:
                        skipped.append(f"{c} at {n} readings, {th} thread(s) (about "
                                       f"{last[c][1] * n / last[c][0]:.0f} s expected)")
                    else:
                        configs.append(c)
                print(f"  {n} readings, {th} BLAS thread(s) ...", file=sys.stderr, flush=True)
                rows.append(measure(n, th, a.repeat if n < 50000 else a.repeat_large,
                                    Path(tmp), configs, n <= a.tree_max, runs))
                for r in runs:
                    if r["threads"] == th and r["readings"] == rows[-1]["readings"]:
                        last[r["config"]] = (n, r["wall_s"])
    df = pd.DataFrame(rows)
    lines: list[str] = []

    def say(text: str = "") -> None:
        print(text)
        lines.append(text)

    cols = ["volcal_s", "volcal_no_plots_s", "scipy_s", "volcal_solve_s", "scipy_solve_s",
            "volcal_MiB", "volcal_no_plots_MiB", "scipy_MiB", "volcal_tree_MiB"]
    show = ["readings", "threads", "scipy_config", "volcal_s", "volcal_no_plots_s", "scipy_s",
            "ratio_whole", "ratio_whole_no_plots", "volcal_solve_s", "scipy_solve_s",
            "ratio_solve"]
    mem = ["readings", "threads", "volcal_MiB", "volcal_tree_MiB", "volcal_no_plots_MiB",
           "scipy_MiB", "scipy_tree_MiB", "ratio_MiB_no_plots", "volcal_cpu_s",
           "volcal_no_plots_cpu_s", "scipy_cpu_s"]
    rf = pd.DataFrame(runs)
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        say("every scipy configuration, whole process (wall and CPU seconds, peak MiB of the "
            "process), its solve, evaluations, cost above the lowest (relative) and whether "
            "it reached the minimum:")
        say(rf.to_string(index=False))
        if skipped:
            say("not run (--max-seconds): " + "; ".join(skipped))
        say("\nwhole process, wall seconds (best of the repeats); scipy_s is the fastest "
            "configuration that reached the minimum (scipy_config):")
        say(df[show].to_string(index=False))
        if df["threads"].nunique() > 1:
            say("\nevery side at its best over the thread counts run (wall seconds; the "
                "script's fastest configuration that reached the minimum, at its threads):")
            say(best_over_threads(df).to_string(index=False))
        say("\npeak memory, MiB: *_MiB the largest process (wait4 maxrss), *_tree_MiB the "
              "sum over the process and its children\n(PSS, sampled every 20 ms; volcal's "
              "plotting children included); CPU seconds of the whole process tree:")
        say(df[mem].to_string(index=False))
    for th, part in df.groupby("threads"):
        ex = exponents(part, cols)
        if ex:
            say(f"scaling exponents ({th} thread(s)): "
                  + ", ".join(f"{k} {v:.2f}" for k, v in ex.items()))
    stage_cols = [c for c in df.columns if c.endswith("_s") and (
        c.startswith("volcal_") and c[7:-2] in (*VOLCAL_STAGES, "solve", "plots", "startup")
        or c.startswith("scipy_") and c[6:-2] in ("imports", "read", "model", "setup",
                                                   "solve", "covariance", "write"))]
    for th, part in df.groupby("threads"):
        say(f"\nper stage, seconds, volcal / scipy script ({th} thread(s)); volcal's "
              "start-up includes the interpreter and imports:")
        say(stage_table(part))
        ex = exponents(part, stage_cols)
        if ex:
            say(f"stage scaling exponents ({th} thread(s)): "
                  + ", ".join(f"{k[:-2]} {v:.2f}" for k, v in ex.items()))
    a.out.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out / "compare_scipy.csv", index=False)
    rf.to_csv(a.out / "compare_scipy_configs.csv", index=False)
    (a.out / "compare_scipy.txt").write_text(
        f"python benchmarks/compare_scipy.py {' '.join(argv or sys.argv[1:])}".rstrip()
        + f"\n{platform.platform()}, {os.cpu_count()} CPUs, Python {platform.python_version()}"
        + "\n\n" + "\n".join(lines) + "\n"
    )
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4.5))
        for th, part in df.groupby("threads"):
            for c, style in (("volcal_s", "-o"), ("volcal_no_plots_s", "--o"),
                             ("scipy_s", "-s")):
                name = "fastest scipy" if c == "scipy_s" else c[:-2]
                ax.loglog(part["readings"], part[c], style, label=f"{name} ({th} thr)")
        for (th, c), part in rf.groupby(["threads", "config"]):
            ax.loglog(part["readings"], part["wall_s"], ":", lw=0.8, alpha=0.6,
                      label=f"scipy {c} ({th} thr)")
        ax.set_xlabel("readings")
        ax.set_ylabel("whole process (s)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=5, ncol=2)
        fig.tight_layout()
        fig.savefig(a.out / "compare_scipy.png", dpi=120)
    except ImportError:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
