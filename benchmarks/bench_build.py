"""Benchmark: building each bundled machine model cold and loading it from the build cache.

Every measurement runs in a fresh Python process, so that module imports are paid (and
reported) separately:

* cold: an empty cache folder; the process imports volcal.model.machine (CasADi, NumPy), then
  SymPy with volcal's symbolic layer and lowering, then calls ``Machine.from_model`` (SymPy
  chain + lowering to CasADi + function creation + writing the cache entry);
* cached: the cache folder the cold run filled; the process imports volcal.model.machine and calls
  ``Machine.from_model``, which must load the entry without importing SymPy.

"process" is the wall time of the whole child process seen from the parent (interpreter
start-up included). Figures are medians over the repeats, with the minimum and maximum.
Run by hand:

    python benchmarks/bench_build.py [--repeats N]

Prints a markdown table and writes benchmarks/results/build.md.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median

HERE = Path(__file__).resolve().parent

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import volcal.model.machine
t1 = time.perf_counter()
out = {"import_core": t1 - t0}
if sys.argv[2] == "cold":
    import sympy, volcal.model.symbolic, volcal.model.lowering
    t2 = time.perf_counter()
    out["import_sympy"] = t2 - t1
    t1 = t2
m = volcal.model.machine.Machine.from_model(sys.argv[1])
t3 = time.perf_counter()
out.update(build=t3 - t1, from_cache=m.from_cache, n_axes=m.n_axes, n_errors=m.n_errors,
           sympy_loaded="sympy" in sys.modules)
print(json.dumps(out))
"""


def child(model: str, mode: str, cache: str) -> dict:
    env = dict(os.environ, VOLCAL_CACHE_DIR=cache)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", CHILD, model, mode], env=env,
                       capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["process"] = wall
    return out


def stat(values: list[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{median(values):.3f} ({min(values):.3f}-{max(values):.3f})"


def run(repeats: int) -> str:
    from volcal.model.spec import bundled_models

    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    rows = []
    checks = []
    for name in bundled_models():
        cold: list[dict] = []
        warm: list[dict] = []
        for _ in range(repeats):
            with tempfile.TemporaryDirectory(prefix="volcal-bench-") as cache:
                c = child(name, "cold", cache)
                w = child(name, "cached", cache)
            if c["from_cache"] or not w["from_cache"]:
                raise RuntimeError(f"{name}: cache did not behave: cold {c}, cached {w}")
            if w["sympy_loaded"]:
                raise RuntimeError(f"{name}: loading from the cache imported SymPy")
            cold.append(c)
            warm.append(w)
        col = lambda runs, key: [r[key] for r in runs]  # noqa: E731
        rows.append([name, str(cold[0]["n_axes"]), str(cold[0]["n_errors"]),
                     stat(col(cold, "import_core")), stat(col(cold, "import_sympy")),
                     stat(col(cold, "build")), stat(col(cold, "process")),
                     stat(col(warm, "import_core")), stat(col(warm, "build")),
                     stat(col(warm, "process"))])
        if cold[0]["n_axes"] == 5:
            b = median(col(cold, "build"))
            bi = median([r["import_sympy"] + r["build"] for r in cold])
            load = median(col(warm, "build"))
            checks.append(
                f"- {name}: cold build {b:.3f} s (with the SymPy import {bi:.3f} s) "
                f"{'<' if bi < 1 else '>='} 1 s goal; cached load {load:.3f} s "
                f"{'<' if load < 0.1 else '>='} 0.1 s goal")

    header = ["model", "axes", "errors", "cold: import volcal.model.machine", "cold: import SymPy",
              "cold: build", "cold: process", "cached: import volcal.model.machine",
              "cached: load", "cached: process"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    load_after = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    import casadi
    import sympy
    env = (f"Python {platform.python_version()}, CasADi {casadi.__version__}, SymPy "
           f"{sympy.__version__}, {platform.machine()} {platform.system()}, "
           f"{os.cpu_count()} CPUs, {repeats} repeats; seconds, median (min-max). "
           f"1-min load average {load_before:.1f} before and {load_after:.1f} after the run "
           "(other work on the machine inflates the figures).")
    text = "\n".join([
        "# Model build times: cold vs cached", "",
        "Measured by `python benchmarks/bench_build.py`; every figure comes from a fresh "
        "process (see the script's docstring). \"build\" is `Machine.from_model` alone: "
        "SymPy chain, lowering, CasADi functions and cache write when cold; reading the "
        "cache entry when cached. \"process\" is the child's whole wall time, interpreter "
        "start-up included.", "", env, "", *lines, "", "Goals (5-axis models; cold: SymPy import and build):", *checks, ""])
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "build.md")
    args = ap.parse_args()
    text = run(args.repeats)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text, encoding="utf-8")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
