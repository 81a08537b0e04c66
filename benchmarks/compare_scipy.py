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

Whole-process wall time and peak resident memory (``os.wait4``) are measured from outside;
the stages come from each side's own timings (scipy: the script's JSON; volcal: the stage
record in result.json, ``timings_s``, of the run without plots; volcal's plots are the
difference of its two whole-process times, its start-up the rest).  The best of ``--repeat`` runs is kept.  Prints a
side-by-side table with the fitted scaling exponent of each column (log-log slope over the
sizes), writes benchmarks/results/compare_scipy.csv and compare_scipy.png.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent


def make_data(n_readings: int, folder: Path, seed: int = 0) -> tuple[Path, Path, int]:
    """A simulated measurement of about n_readings readings; returns (data CSV, stations
    CSV for the scipy script, actual number of readings)."""
    from volcal.measurement.plans import grid_plan
    from volcal.measurement.simulate import _clear_plan, example, simulate

    ex = example("mcv754")
    per_pose = len(ex.tools) * len(ex.stations)
    n_poses = max(n_readings // per_pose, 8)
    k = max(2, round(n_poses ** (1 / 3)))
    plan = grid_plan(ex.machine.spec, {"X": k + 1, "Y": k, "Z": max(k - 1, 2)})
    plan = _clear_plan(ex.machine, plan, ex.tools, ex.stations, 50.0)
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


def _run(cmd: list[str], threads: int) -> tuple[float, float, int]:
    """(wall s, peak RSS MiB, exit code) of a whole process."""
    env = dict(os.environ)
    for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[v] = str(threads)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode() if proc.stderr else ""
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd[0]} failed ({proc.returncode}): {err[-2000:]}")
    return wall, ru.ru_maxrss / 1024.0, proc.returncode


def measure(n: int, threads: int, repeat: int, work: Path) -> dict:
    folder = work / f"n{n}"
    folder.mkdir(parents=True, exist_ok=True)
    data, stations, N = make_data(n, folder)
    volcal_exe = str(Path(sys.executable).parent / "volcal")
    row: dict = {"readings": N, "threads": threads}
    best: dict[str, tuple] = {}
    for _ in range(repeat):
        for label, extra in (("volcal", []), ("volcal_no_plots", ["--no-plots"])):
            out = folder / f"out_{label}"
            cmd = [volcal_exe, "-q", "identify", "--model", "mcv754_wxyzt", "--data",
                   str(data), "--out", str(out), "--force", *extra]
            wall, rss, _ = _run(cmd, threads)
            doc = json.loads((out / "result.json").read_text())
            solve = sum(ph["seconds"] for ph in doc["phases"])
            if label not in best or wall < best[label][0]:
                best[label] = (wall, rss, solve, doc.get("timings_s", {}))
        tim = folder / "timings.json"
        cmd = [sys.executable, str(HERE / "scipy_reference.py"), str(data), str(stations),
               "--model", "mcv754_wxyzt", "--out", str(folder / "scipy.csv"),
               "--timings", str(tim)]
        wall, rss, _ = _run(cmd, threads)
        t = json.loads(tim.read_text())
        if "scipy" not in best or wall < best["scipy"][0]:
            best["scipy"] = (wall, rss, t["solve"], t)
    for label in ("volcal", "volcal_no_plots"):
        wall, rss, solve, _ = best[label]
        row[f"{label}_s"] = wall
        row[f"{label}_MiB"] = rss
        row[f"{label}_solve_s"] = solve
    # volcal's stages (its own record in result.json, run without plots); the plots are
    # the difference of the two whole-process times; start-up and imports the rest
    st = best["volcal_no_plots"][3]
    for key, name in VOLCAL_STAGES.items():
        row[f"volcal_{key}_s"] = sum(v for k, v in st.items() if k in name)
    row["volcal_plots_s"] = max(row["volcal_s"] - row["volcal_no_plots_s"], 0.0)
    row["volcal_startup_s"] = max(
        row["volcal_no_plots_s"] - sum(row[f"volcal_{k}_s"] for k in VOLCAL_STAGES), 0.0
    )
    wall, rss, solve, t = best["scipy"]
    row["scipy_s"], row["scipy_MiB"], row["scipy_solve_s"] = wall, rss, solve
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
    rows = []
    with tempfile.TemporaryDirectory(prefix="volcal-bench-") as tmp:
        for th in a.threads:
            for n in a.sizes:
                print(f"  {n} readings, {th} BLAS thread(s) ...", file=sys.stderr, flush=True)
                rows.append(measure(n, th, a.repeat, Path(tmp)))
    df = pd.DataFrame(rows)
    cols = ["volcal_s", "volcal_no_plots_s", "scipy_s", "volcal_solve_s", "scipy_solve_s",
            "volcal_MiB", "scipy_MiB"]
    show = ["readings", "threads", "volcal_s", "volcal_no_plots_s", "scipy_s", "ratio_whole",
            "volcal_solve_s", "scipy_solve_s", "ratio_solve", "volcal_MiB", "scipy_MiB"]
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        print(df[show].to_string(index=False))
    for th, part in df.groupby("threads"):
        ex = exponents(part, cols)
        if ex:
            print(f"scaling exponents ({th} thread(s)): "
                  + ", ".join(f"{k} {v:.2f}" for k, v in ex.items()))
    stage_cols = [c for c in df.columns if c.endswith("_s") and (
        c.startswith("volcal_") and c[7:-2] in (*VOLCAL_STAGES, "solve", "plots", "startup")
        or c.startswith("scipy_") and c[6:-2] in ("imports", "read", "model", "setup",
                                                   "solve", "covariance", "write"))]
    for th, part in df.groupby("threads"):
        print(f"\nper stage, seconds, volcal / scipy script ({th} thread(s)); volcal's "
              "start-up includes the interpreter and imports:")
        print(stage_table(part))
        ex = exponents(part, stage_cols)
        if ex:
            print(f"stage scaling exponents ({th} thread(s)): "
                  + ", ".join(f"{k[:-2]} {v:.2f}" for k, v in ex.items()))
    a.out.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out / "compare_scipy.csv", index=False)
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
