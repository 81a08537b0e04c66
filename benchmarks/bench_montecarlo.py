"""Benchmark: 10,000 full nonlinear Monte Carlo trials of the bundled example.

The bundled example (MCV 754, 6 stations, 149 poses, 4 tool offsets: 3,576 readings;
75 error parameters + 24 station parameters + 6 frame parameters) is simulated with its
seed and identified; then every trial samples the paper002 budget's inputs and re-solves
the constrained nonlinear least-squares problem:

* volcal ``run_trials`` (structured Gauss-Newton re-solver, one factorisation, exact
  gradient per iteration, batched over the trials of a chunk), 2 local worker processes
  and 1, including the pool start-up and the shipping of the kernel;
* volcal ``mode="linear"`` (one factorisation, many right-hand sides);
* a plain loop of ``scipy.optimize.least_squares`` solves of the same problem (the datum
  constraints eliminated by the null-space parametrisation x = x_hat + Z y, the held frame
  variables left out, start at the identification), timed on a few hundred trials and
  extrapolated linearly to 10,000: (a) with the problem's own CasADi residual and Jacobian
  functions, (b) with volcal's numpy structured residual and Jacobian (scipy's best case);
* one IPOPT solve (the identification's solver) for reference.

Run by hand (it takes a few minutes):

    python benchmarks/bench_montecarlo.py [--trials 10000] [--scipy-trials 200]

Prints a markdown table and writes benchmarks/results/montecarlo.md.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import scipy
from scipy.optimize import least_squares

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=10_000)
    ap.add_argument("--scipy-trials", type=int, default=200)
    ap.add_argument("--casadi-scipy-trials", type=int, default=50)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "montecarlo.md")
    ap.add_argument("--json", type=Path, default=None,
                    help="also write the table's rows (name, trials, seconds, seconds for "
                    "--trials trials) to this JSON file (benchmarks/bench_guarded.py)")
    args = ap.parse_args(argv)

    import casadi as ca

    from volcal.measurement.simulate import example
    from volcal.base.threads import set_blas_threads
    from volcal.analysis.uncertainty.montecarlo import monte_carlo, run_trials

    set_blas_threads(1)
    load0 = os.getloadavg()
    ex = example("mcv754")
    sim = ex.simulate()
    t = time.perf_counter()
    out = monte_carlo(ex.machine, sim.measurements, budget=ex.budget,
                      error_model=ex.error_model, trials=2, seed=0, workers=1)
    t_setup = time.perf_counter() - t
    k, ider, p = out["kernel"], out["identifier"], out["p"]
    eng = k.engine
    T = args.trials
    rows = []

    # volcal nonlinear, 2 workers and 1
    res = {}
    for w in (2, 1):
        t = time.perf_counter()
        s = run_trials(k, T, 1, workers=w)
        res[w] = (time.perf_counter() - t, s)
    same = np.array_equal(res[1][1].x, res[2][1].x)
    s2 = res[2][1]
    rows.append(("volcal nonlinear, 2 worker processes", T, res[2][0], res[2][0]))
    rows.append(("volcal nonlinear, 1 process", T, res[1][0], res[1][0]))
    lin = {}
    for w in (2, 1):
        t = time.perf_counter()
        sl = run_trials(k, T, 1, workers=w, mode="linear", chunk_size=500)
        lin[w] = (time.perf_counter() - t, sl)
    rows.append(("volcal linearised mode, 2 worker processes", T, lin[2][0], lin[2][0]))
    rows.append(("volcal linearised mode, 1 process", T, lin[1][0], lin[1][0]))
    lin_dev = float(np.max(np.abs(lin[1][1].x - s2.x) / eng.scale))

    # the scipy loop: same inputs (trial draws), same problem, null-space parametrisation
    free = ~eng.fixed
    Z = eng.Z
    sc = eng.scale
    x0 = eng.x_hat

    def x_of(y):
        x = x0.copy()
        x[free] += sc[free] * (Z @ y)
        return x

    def run_scipy(n, fun_jac):
        t = time.perf_counter()
        dM, _ = k.sampler.draw(1, range(n))
        X = []
        for b in range(n):
            m = eng.m + dM[b]
            f, j = fun_jac(m)
            r = least_squares(f, np.zeros(Z.shape[1]), jac=j, method="trf",
                              x_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-10)
            X.append(x_of(r.x))
        return time.perf_counter() - t, np.array(X)

    def numpy_fj(m):
        def f(y):
            return eng.residuals(x_of(y)[None, :], m[None, :])[0]

        def j(y):
            return eng.jacobian(x_of(y))[:, free] @ Z
        return f, j

    pr = ider.problem
    from volcal.analysis.uncertainty.engine import unpack_data
    qq, tool, _, w = unpack_data(pr.machine.n_axes, p)

    def casadi_fj(m):
        pp = pr.pack_data(qq, tool, m, w)

        def f(y):
            return pr.residual(pr.to_scaled(x_of(y)), pp).full().ravel()

        def j(y):
            return pr.jacobian(pr.to_scaled(x_of(y)), pp)[1].full()[:, free] @ Z
        return f, j

    n_np = args.scipy_trials
    t_np, X_np = run_scipy(n_np, numpy_fj)
    n_ca = args.casadi_scipy_trials
    t_ca, X_ca = run_scipy(n_ca, casadi_fj)
    dev_np = float(np.max(np.abs(X_np - s2.x[:n_np]) / sc))
    dev_ca = float(np.max(np.abs(X_ca - s2.x[:n_ca]) / sc))
    rows.append(("scipy least_squares loop, CasADi residual + Jacobian", n_ca, t_ca,
                 t_ca / n_ca * T))
    rows.append(("scipy least_squares loop, numpy structured residual + Jacobian", n_np,
                 t_np, t_np / n_np * T))

    # one IPOPT solve of a trial (the identification's solver)
    dM, _ = k.sampler.draw(1, [0])
    ts = []
    for _ in range(3):
        pp = pr.pack_data(qq, tool, eng.m + dM[0], w)
        o = ider.solver.solve(x0, pp, fixed=eng.fixed)
        ts.append(o.seconds)
    t_ipopt = float(np.median(ts))
    rows.append(("IPOPT (the identification's solver), 1 solve", 1, t_ipopt, t_ipopt * T))

    load1 = os.getloadavg()
    base = rows[0][3]
    lines = ["# Monte Carlo benchmark (10,000 full nonlinear trials of the bundled example)",
             "",
             f"Bundled example mcv754: {eng.n_readings} readings, {eng.n} variables "
             f"({k.n_theta} error parameters; {int(eng.fixed.sum())} held), "
             f"{Z.shape[1]} free directions after the datum constraints; budget paper002 "
             f"({len(k.source_names)} input sources).  Every trial draws its inputs and "
             "re-solves the constrained nonlinear least-squares problem.  Times are wall "
             "clock, single-threaded BLAS in every process, including pool start-up and "
             "kernel shipping for the volcal rows; loops timed on the trials shown and "
             "extrapolated linearly.", "",
             "| solver | trials timed | time measured (s) | time for 10,000 trials (s) | "
             "ratio to volcal (2 workers) |",
             "|---|---:|---:|---:|---:|"]
    for name, n, tm, t10 in rows:
        ext = " (extrapolated)" if n != T else ""
        lines.append(f"| {name} | {n} | {tm:.3f} | {t10:.2f}{ext} | {t10 / base:.1f} |")
    it = np.unique(s2.iterations, return_counts=True)
    lines += ["",
              f"- volcal nonlinear: iterations per trial {dict(zip(it[0].tolist(), it[1].tolist()))}, "
              f"not converged {int((~s2.converged).sum())}; same numbers with 1 and 2 workers: "
              f"{same}",
              f"- max |scipy - volcal| over the timed trials: {dev_np:.2g} (numpy variant), "
              f"{dev_ca:.2g} (CasADi variant) in um / urad (scipy at xtol = ftol = 1e-12)",
              f"- max |linearised - nonlinear| over the trials: {lin_dev:.2g} um / urad",
              f"- set-up (simulate + identify + Identifier + kernel): {t_setup:.1f} s, not in "
              "the table",
              f"- machine: {platform.machine()}, {os.cpu_count()} CPUs, Python "
              f"{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__},"
              f" casadi {ca.__version__}; load average {load0[0]:.1f} before, "
              f"{load1[0]:.1f} after (other jobs share this machine)"]
    t_nl, t_lin = rows[0][3], rows[2][3]
    best_scipy = min(rows[4][3], rows[5][3])
    lines += ["",
              "## Goals",
              "",
              f"- 10,000 full nonlinear trials in under 60 s: {t_nl:.1f} s "
              f"({'met' if t_nl < 60 else 'NOT met'})",
              f"- at least 20x faster than the scipy loop: {best_scipy / t_nl:.0f}x against "
              f"scipy's best case (numpy residual and Jacobian), "
              f"{rows[4][3] / t_nl:.0f}x against scipy on the problem's CasADi functions "
              f"({'met' if best_scipy / t_nl >= 20 else 'NOT met'})",
              f"- linearised mode in under 2 s: {t_lin:.2f} s "
              f"({'met' if t_lin < 2 else 'NOT met'})",
              "",
              "## Why it is fast",
              "",
              "- the first-order tool point is exactly linear in the error parameters "
              "(P = P0 + G theta); G (readings x 3 x parameters) is computed once, so a "
              "residual evaluation for a chunk of trials is two dense matrix products and a "
              "few passes over the readings;",
              "- the constrained Gauss-Newton matrix is factorised once (R of J0 Z); each "
              "iteration uses the exact gradient J(x)^T r(x), so the fixed point is the "
              "exact nonlinear minimiser (checked against IPOPT: 1e-10 um / urad); 3-4 "
              "iterations per trial here;",
              "- chunks of 200 trials per call, one kernel per worker process (shipped "
              "once), single-threaded BLAS per process: on this 2-core machine OpenBLAS "
              "threads made small factorisations 20-150x slower (a 3,576 x 99 QR: 0.18-1.4 s "
              "threaded, 0.009 s single-threaded).",
              "- the linearised mode spends most of its time drawing the 7 x 3,576 random "
              "inputs per trial; the map itself is one (trials x readings) x (readings x "
              "variables) product."]
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    if args.json is not None:
        import json

        args.json.write_text(json.dumps(
            [{"name": name, "trials": n, "s": tm, "s_all_trials": t10}
             for name, n, tm, t10 in rows]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
