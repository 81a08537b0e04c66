"""volcal identify against the plain scipy script, whole process and per stage.

    python benchmarks/compare_scipy.py                  # 1e2 .. 3e4 readings, 1 and 2 threads
    python benchmarks/compare_scipy.py --sizes 100 1000 --threads 1 --repeat 3
    python benchmarks/compare_scipy.py --smoke          # tiny, for the tests

Both sides run as separate processes on the same simulated data (the bundled MCV 754
example: paper 002's budget, four tool offsets, its six stations, a grid sized to the
number of readings), with the same number of BLAS threads (OPENBLAS_NUM_THREADS,
OMP_NUM_THREADS, MKL_NUM_THREADS):

* volcal: ``volcal identify --model mcv754_wxyzt --data DATA.csv --out DIR`` with default
  outputs (tables, report and plots) and with ``--no-plots``;
* scipy: ``benchmarks/scipy_reference.py`` (read it: the script a competent user writes,
  sparse analytic Jacobian, trf + LSMR, covariance, a CSV), given start stations 1 mm from
  the truth (volcal computes its own start values from the data).

Measured from outside: whole-process wall time, CPU time of the process tree, and peak
memory two ways: the largest process's resident set (``os.wait4``) and the sum over the
process and its children (volcal draws its plots in two child processes) of their
proportional set sizes, sampled every 20 ms in one more, untimed run.  The stages come
from each side's own timings (scipy: the script's JSON; volcal: the stage record in
result.json, ``timings_s``, of the run without plots; volcal's plots are the difference of
its two whole-process times, its start-up the rest).  The best of ``--repeat`` runs is
kept.  Prints side-by-side tables with the fitted scaling exponent of each column
(log-log slope over the sizes), writes benchmarks/results/compare_scipy.csv and
compare_scipy.png.
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


def measure(n: int, threads: int, repeat: int, work: Path) -> dict:
    folder = work / f"n{n}"
    folder.mkdir(parents=True, exist_ok=True)
    data, stations, N = make_data(n, folder)
    volcal_exe = str(Path(sys.executable).parent / "volcal")
    row: dict = {"readings": N, "threads": threads}
    best: dict[str, tuple] = {}
    pss: dict[str, float] = {}
    tim = folder / "timings.json"
    cmds = {}
    for label, extra in (("volcal", []), ("volcal_no_plots", ["--no-plots"])):
        out = folder / f"out_{label}"
        cmds[label] = (
            [volcal_exe, "-q", "identify", "--model", "mcv754_wxyzt", "--data", str(data),
             "--out", str(out), "--force", *extra],
            out,
        )
    cmds["scipy"] = (
        [sys.executable, str(HERE / "scipy_reference.py"), str(data), str(stations),
         "--model", "mcv754_wxyzt", "--out", str(folder / "scipy.csv"), "--timings", str(tim)],
        None,
    )
    for _ in range(repeat):
        for label, (cmd, out) in cmds.items():
            m = _run(cmd, threads)
            if out is not None:
                doc = json.loads((out / "result.json").read_text())
                solve, st = sum(ph["seconds"] for ph in doc["phases"]), doc.get("timings_s", {})
            else:
                t = json.loads(tim.read_text())
                solve, st = t["solve"], t
            if label not in best or m["wall"] < best[label][0]["wall"]:
                best[label] = (m, solve, st)
    # the whole process tree's memory, in one more (untimed) run each
    for label, (cmd, _) in cmds.items():
        pss[label] = _run(cmd, threads, sample=True)["pss"]
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
    m, solve, t = best["scipy"]
    row["scipy_s"], row["scipy_cpu_s"], row["scipy_MiB"] = m["wall"], m["cpu"], m["rss"]
    row["scipy_tree_MiB"], row["scipy_solve_s"] = pss["scipy"], solve
    for k in ("imports", "read", "model", "setup", "covariance", "write"):
        row[f"scipy_{k}_s"] = t[k]
    row["ratio_whole"] = row["volcal_s"] / row["scipy_s"]
    row["ratio_whole_no_plots"] = row["volcal_no_plots_s"] / row["scipy_s"]
    row["ratio_solve"] = row["volcal_solve_s"] / row["scipy_solve_s"]
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
}


def stage_table(df: pd.DataFrame) -> str:
    """Per-stage seconds side by side (volcal / scipy) for every size, one thread count."""
    stages = ["startup", "read", "model", "setup", "solving", "covariance", "write", "plots"]
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


def exponents(df: pd.DataFrame, cols: list[str]) -> dict[str, float]:
    """Log-log slope of each column against the number of readings (per thread count)."""
    out = {}
    if df["readings"].nunique() < 2:
        return out
    x = np.log(df["readings"].to_numpy(float))
    for c in cols:
        y = np.log(np.maximum(df[c].to_numpy(float), 1e-9))
        out[c] = float(np.polyfit(x, y, 1)[0])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 10000, 30000])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--smoke", action="store_true", help="100 readings, 1 thread, 1 run")
    ap.add_argument("--out", type=Path, default=HERE / "results",
                    help="folder for compare_scipy.csv / .png")
    a = ap.parse_args(argv)
    if a.smoke:
        a.sizes, a.threads, a.repeat = [100], [1], 1
    compile_volcal()
    rows = []
    with tempfile.TemporaryDirectory(prefix="volcal-bench-") as tmp:
        for th in a.threads:
            for n in a.sizes:
                print(f"  {n} readings, {th} BLAS thread(s) ...", file=sys.stderr, flush=True)
                rows.append(measure(n, th, a.repeat, Path(tmp)))
    df = pd.DataFrame(rows)
    lines: list[str] = []

    def say(text: str = "") -> None:
        print(text)
        lines.append(text)

    cols = ["volcal_s", "volcal_no_plots_s", "scipy_s", "volcal_solve_s", "scipy_solve_s",
            "volcal_MiB", "scipy_MiB", "volcal_tree_MiB"]
    show = ["readings", "threads", "volcal_s", "volcal_no_plots_s", "scipy_s", "ratio_whole",
            "ratio_whole_no_plots", "volcal_solve_s", "scipy_solve_s", "ratio_solve"]
    mem = ["readings", "threads", "volcal_MiB", "volcal_tree_MiB", "volcal_no_plots_MiB",
           "scipy_MiB", "scipy_tree_MiB", "volcal_cpu_s", "volcal_no_plots_cpu_s",
           "scipy_cpu_s"]
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        say("whole process, wall seconds (best of the repeats):")
        say(df[show].to_string(index=False))
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
    (a.out / "compare_scipy.txt").write_text(
        f"python benchmarks/compare_scipy.py {' '.join(argv or sys.argv[1:])}".rstrip()
        + f"\n{platform.platform()}, {os.cpu_count()} CPUs, Python {platform.python_version()}"
        + "\n\n" + "\n".join(lines) + "\n"
    )
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for th, part in df.groupby("threads"):
            for c, style in (("volcal_s", "-o"), ("volcal_no_plots_s", "--o"), ("scipy_s", "-s")):
                ax.loglog(part["readings"], part[c], style, label=f"{c[:-2]} ({th} thr)")
        ax.set_xlabel("readings")
        ax.set_ylabel("whole process (s)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(a.out / "compare_scipy.png", dpi=120)
    except ImportError:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
