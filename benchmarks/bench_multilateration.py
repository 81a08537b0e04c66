"""Benchmark: batched sqrt multilateration vs a per-point loop of scipy.optimize.least_squares.

10,000 points from the six stations of paper 000 Table 5 (mm), readings with 0.5 um noise.
The batched solver runs on all 10,000 points; the scipy loop is timed on the first 300 points
and extrapolated linearly to 10,000 (said so in the table). Both start from the nominal
points. Run by hand:

    python benchmarks/bench_multilateration.py

Prints a markdown table and writes benchmarks/results/multilateration.md.
"""
from __future__ import annotations

import os
import platform
import time
from pathlib import Path

from importlib import resources

import numpy as np
import scipy
from scipy.optimize import least_squares

from volcal.measurement.tables import load_stations
from volcal.measurement.multilateration import multilaterate

# paper 000 Table 5 (the stations of the bundled example), mm
STATIONS = load_stations(resources.files("volcal").joinpath("data", "mcv754_stations.csv")
                         )[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
DEAD = np.array([3.1, -2.4, 5.0, 1.2, -4.4, 2.2])  # mm
N_POINTS = 10_000
N_LOOP = 300
REPEATS = 5


def data(seed=0):
    rng = np.random.default_rng(seed)
    nominal = rng.uniform([0.0, 0.0, -550.0], [754.0, 500.0, 0.0], (N_POINTS, 3))
    actual = nominal + rng.normal(0.0, 0.010, nominal.shape)  # 10 um machine errors
    L = np.linalg.norm(actual[:, None] - STATIONS, axis=-1) - DEAD
    L += rng.normal(0.0, 0.5e-3, L.shape)
    return nominal, actual, L


def best_of(fn, repeats=REPEATS):
    times = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def scipy_loop(nominal, L, n, analytic):
    out = np.empty((n, 3))
    for i in range(n):
        rho = DEAD + L[i]

        def fun(p, rho=rho):
            return np.linalg.norm(p - STATIONS, axis=1) - rho

        def jac(p):
            d = p - STATIONS
            return d / np.linalg.norm(d, axis=1)[:, None]

        kw = {"jac": jac} if analytic else {}
        out[i] = least_squares(fun, nominal[i], **kw).x
    return out


def main():
    nominal, actual, L = data()
    t_batch, res = best_of(lambda: multilaterate(STATIONS, DEAD, L, "sqrt", initial=nominal))
    t_batch_lin, res_lin = best_of(lambda: multilaterate(STATIONS, DEAD, L, "sqrt"))
    assert res.converged.all() and res_lin.converged.all()
    t_fd, p_fd = best_of(lambda: scipy_loop(nominal, L, N_LOOP, False), 2)
    t_an, p_an = best_of(lambda: scipy_loop(nominal, L, N_LOOP, True), 2)
    scale = N_POINTS / N_LOOP
    err = np.linalg.norm(res.points - actual, axis=1)
    d_fd = np.abs(p_fd - res.points[:N_LOOP]).max()
    d_an = np.abs(p_an - res.points[:N_LOOP]).max()
    rows = [
        ("batched LM (volcal, start: nominal points)", N_POINTS, t_batch, t_batch, 1.0),
        ("batched LM (volcal, start: linear Case B)", N_POINTS, t_batch_lin, t_batch_lin,
         t_batch_lin / t_batch),
        ("scipy least_squares loop, 2-point Jacobian", N_LOOP, t_fd, t_fd * scale,
         t_fd * scale / t_batch),
        ("scipy least_squares loop, analytic Jacobian", N_LOOP, t_an, t_an * scale,
         t_an * scale / t_batch),
    ]
    lines = [
        "# Multilateration benchmark (batched sqrt vs scipy loop)",
        "",
        f"{N_POINTS} points, 6 stations (paper 000 Table 5), noise 0.5 um, machine errors "
        "10 um; method `sqrt`. The scipy loop (default `trf`, tolerances default) ran on the "
        f"first {N_LOOP} points and its time is extrapolated linearly to {N_POINTS} points. "
        f"Times are the best of {REPEATS} (batched) or 2 (loops) runs.",
        "",
        "| solver | points timed | time measured (s) | time for 10,000 points (s) "
        "| ratio to batched |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, n, t, t10k, ratio in rows:
        ext = " (extrapolated)" if n != N_POINTS else ""
        lines.append(f"| {name} | {n} | {t:.4f} | {t10k:.4f}{ext} | {ratio:.1f} |")
    lines += [
        "",
        f"- batched: iterations max {res.iterations.max()}, mean {res.iterations.mean():.2f}; "
        f"point error vs truth rms {1e3 * np.sqrt(np.mean(err ** 2)):.3f} um, "
        f"max {1e3 * err.max():.3f} um",
        f"- max |scipy - batched| on the {N_LOOP} points: {d_fd:.2e} mm (2-point Jacobian), "
        f"{d_an:.2e} mm (analytic Jacobian); scipy stops at its default tolerances",
        f"- machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(__file__).resolve().parent / "results" / "multilateration.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(out)
    print(f"written {out}")


if __name__ == "__main__":
    main()
