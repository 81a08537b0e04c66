"""Exported C solver vs the Python IPOPT path: solve time, export + compile time, agreement.

Problems:
* ``mcv754``: the bundled 3-axis example (MCV 754, 3576 readings, 6 stations, 4 tool
  offsets, 105 unknowns), joint strategy;
* ``trunnion_ac``: a 5-axis trunnion table (4^5 grid x 4 tools x 6 stations = 18432
  readings, 165 unknowns), joint strategy.

Per problem:
* export + compile: ``export_solver(..., force=True)`` into a fresh folder (CasADi functions,
  C generation, the export-time analysis, which runs Python's Identifier once) and
  ``make`` (gcc -O2 -Wall -Werror); separately and together;
* Python solve: ``NLPSolver.solve`` (IPOPT, Gauss-Newton Hessian) from the same start point
  with the same fixed set, solver built once (what a repeated identification costs);
  also the whole ``identify()`` call for context;
* C solve: ``<name>_identify`` through the ctypes loader (start stations computed in C,
  budget weights not needed: the data carry sigma), and the example program in a
  subprocess (process start, CSV parsing and writing included);
* agreement: C example vs ``identify()``, parameters (max |diff| over max |value|, and
  max |diff| / max(|value|, std)), stations (mm), volumetric errors at the measured points.

Run:  python benchmarks/bench_codegen.py [--repeat 20] [--skip-5axis]
Writes benchmarks/results/codegen.md.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pandas as pd

from volcal.outputs.codegen import export_solver, load
from volcal.measurement.tables import load_measurements
from volcal.model.errors import ErrorModel
from volcal.analysis.identify import initial_stations, identify
from volcal.model.machine import Machine
from volcal.measurement.plans import default_stations, grid_plan
from volcal.measurement.simulate import draw_true_parameters, example, simulate

HERE = Path(__file__).parent
TOOLS = np.array([[0, 0, 0], [0, 0, -100.0], [80, 0, -100.0], [0, 80, -100.0]])
ST = ["x_mm", "y_mm", "z_mm", "dead_length_mm"]


def problems(skip_5axis: bool):
    ex = example()
    yield "mcv754 (3-axis example)", ex.machine, ex.simulate().measurements
    if not skip_5axis:
        m = Machine.from_model("trunnion_ac")
        em = ErrorModel(m.spec)
        theta = draw_true_parameters(m, em, np.random.default_rng(1), 60.0)
        sim = simulate(m, em, theta, default_stations(m.spec, 6, seed=1, tools=TOOLS),
                       grid_plan(m.spec, 4), TOOLS, "paper002", 1)
        yield "trunnion_ac (5-axis)", m, sim.measurements


def stats(t):
    t = np.asarray(t)
    return float(np.median(t)), float(t.min()), float(t.max())


def bench(label, machine, df, repeat, workdir):
    row = {"problem": label, "readings": len(df)}
    # ---- export + compile
    out = workdir / label.split()[0]
    t0 = time.perf_counter()
    info = export_solver(machine, df, out, force=True, build_it=False)
    t_exp = time.perf_counter() - t0
    t0 = time.perf_counter()
    subprocess.run(["make", "-C", str(out), "-j2", "CFLAGS=-O2 -Wall -Werror"], check=True,
                   capture_output=True)
    t_build = time.perf_counter() - t0
    row.update(export_s=t_exp, build_s=t_build,
               c_lines=sum(1 for _ in open(out / f"{info.name}_generated.c")),
               unknowns=info.manifest["sizes"]["n_x"],
               free=info.manifest["phases"][-1]["n_reduced"])

    # ---- Python path
    t0 = time.perf_counter()
    res = identify(machine, df)
    row["identify_s"] = time.perf_counter() - t0
    from volcal.outputs.codegen import define_solver
    dfn = define_solver(machine, df)
    ider, pr = dfn.identifier, dfn.problem
    meas = load_measurements(df, machine.spec)
    st0, _, _ = initial_stations(machine, meas, None)
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, 1.0 / meas.sigma)
    ph = dfn.phases[-1]
    x0 = np.where(ph.zero, 0.0, pr.pack_x(np.zeros(pr.n_theta), st0))
    ider.solver.solve(x0, p, fixed=ph.fixed)  # warm-up
    tp = []
    for _ in range(max(3, repeat // 4)):
        o = ider.solver.solve(x0, p, fixed=ph.fixed)
        tp.append(o.seconds)
    row["py_solve"] = stats(tp)
    row["py_iter"] = o.iterations

    # ---- C path
    solver = load(out)
    a = solver.arrays_from_table(df)
    tc = []
    for _ in range(repeat):
        r = solver.identify(a["q"], a["tool"], a["length"], a["sigma"])
        tc.append(r.seconds)
    assert r.converged, r.status_text
    row["c_solve"] = stats(tc)
    row["c_iter"] = r.iterations
    csv = workdir / f"{out.name}.csv"
    df.to_csv(csv, index=False)
    te = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run([str(out / f"{info.name}_example"), str(csv), str(workdir / "o")],
                       check=True, capture_output=True)
        te.append(time.perf_counter() - t0)
    row["c_process"] = stats(te)

    # ---- agreement (example program output vs identify())
    pc = pd.read_csv(workdir / "o" / "parameters.csv")["value"].to_numpy()
    pp = res.parameters()
    vp, sd = pp["value"].to_numpy(), pp["u"].to_numpy()
    ok = pp["identifiable"].to_numpy() & (vp != 0)  # held or unidentifiable: no own scale
    row["par_normrel"] = float(np.abs(pc - vp).max() / np.abs(vp).max())
    row["par_rel_std"] = float(np.max((np.abs(pc - vp) / np.fmax(np.abs(vp), sd))[ok]))
    row["par_rel_elem"] = float(np.max((np.abs(pc - vp) / np.abs(vp))[ok]))
    stc = pd.read_csv(workdir / "o" / "stations.csv")[ST].to_numpy()
    row["st_mm"] = float(np.abs(stc - res.stations[ST].to_numpy()).max())
    vol = pd.read_csv(workdir / "o" / "volumetric.csv")
    q = machine.axis_to_internal(vol[machine.axis_names].to_numpy())
    pv = res.predict(q, vol[["tool_x", "tool_y", "tool_z"]].to_numpy(),
                     with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    row["vol_um"] = float(np.abs(vol[["dx_um", "dy_um", "dz_um"]].to_numpy() - pv).max())
    row["vol_max_um"] = float(np.abs(pv).max())
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--skip-5axis", action="store_true")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for label, machine, df in problems(args.skip_5axis):
            rows.append(bench(label, machine, df, args.repeat, Path(d)))
            print(rows[-1])
    load1 = os.getloadavg()[0]
    gcc = subprocess.run(["gcc", "--version"], capture_output=True,
                         text=True).stdout.splitlines()[0]
    f = lambda s: f"{s[0]:.4f} ({s[1]:.4f}-{s[2]:.4f})"  # noqa: E731
    lines = [
        "# Exported C solver vs the Python IPOPT path",
        "",
        "Measured by `python benchmarks/bench_codegen.py` (see its docstring for what each "
        "column times).",
        "",
        f"Python {platform.python_version()}, CasADi {ca.__version__}, "
        f"{gcc}, "
        f"{platform.machine()} Linux, {os.cpu_count()} CPUs; 1-min load average "
        f"{load0:.1f} before and {load1:.1f} after the run (other work on the machine "
        "inflates the figures).  Seconds, median (min-max).",
        "",
        "## Solve time",
        "",
        "| problem | readings | unknowns (free) | Python IPOPT solve | iter | C solve | iter | "
        "speed-up (median) | C example process | Python identify() |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['problem']} | {r['readings']} | {r['unknowns']} ({r['free']}) | "
            f"{f(r['py_solve'])} | {r['py_iter']} | {f(r['c_solve'])} | {r['c_iter']} | "
            f"{r['py_solve'][0] / r['c_solve'][0]:.1f}x | {f(r['c_process'])} | "
            f"{r['identify_s']:.2f} |")
    lines += [
        "",
        "The C solve includes what the Python solve does not: the start stations (computed "
        "in C from the readings) and the final convergence check (one more Gauss-Newton "
        "step evaluation at the returned point).",
        "",
        "## Export and compile",
        "",
        "| problem | export (s) | compile (s) | total (s) | generated C lines |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['problem']} | {r['export_s']:.2f} | {r['build_s']:.2f} | "
                     f"{r['export_s'] + r['build_s']:.2f} | {r['c_lines']} |")
    lines += [
        "",
        "Export includes the export-time identifiability analysis, which runs Python's "
        "`Identifier` (with its IPOPT solve when the plan carries lengths) so that the "
        "fixed set is exactly Python's.",
        "",
        "## Agreement (C example program vs `identify()`, default options on both sides)",
        "",
        "| problem | params: max diff / max value | params: max diff / max(value, std) | "
        "params: max elementwise relative | stations (mm) | volumetric (um) | "
        "max volumetric (um) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['problem']} | {r['par_normrel']:.1e} | {r['par_rel_std']:.1e} | "
                     f"{r['par_rel_elem']:.1e} | {r['st_mm']:.1e} | {r['vol_um']:.1e} | "
                     f"{r['vol_max_um']:.1f} |")
    lines += [
        "",
        "The last two parameter columns are over the identifiable parameters (the "
        "unidentifiable ones, held or not, have no scale of their own).  "
        "The elementwise relative difference is dominated by parameters whose value is "
        "far below their uncertainty (e.g. 0.006 urad with a standard uncertainty of "
        "0.1 urad): both solvers stop within about 1e-8 um/urad of the minimiser, the "
        "floor set by rounding in the residuals (lengths of ~1000 mm, readings whitened by "
        "sigma of ~0.5 um).",
        "",
    ]
    targets = []
    for r in rows:
        sp = r["py_solve"][0] / r["c_solve"][0]
        tot = r["export_s"] + r["build_s"]
        targets.append(f"- {r['problem']}: C solve {sp:.1f}x faster than the Python IPOPT "
                       f"solve (goal >= 5x: {'met' if sp >= 5 else 'NOT met'}); export + "
                       f"compile {tot:.1f} s (goal < 30 s: {'met' if tot < 30 else 'NOT met'})")
    lines += ["## Goals", ""] + targets + [""]
    text = "\n".join(lines)
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "codegen.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
