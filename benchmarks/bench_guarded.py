"""Benchmark: what met its goal stays met — this version against a baseline, in one run.

    python benchmarks/bench_guarded.py --baseline-ref 71a2c17 [--repeat 3]

Issue 27 asks that the speed work does not regress what already met its goal, "shown in
the same benchmark run before and after".  Each measurement runs this version and the
baseline revision in turn (this, baseline, this, baseline, ...), so that a change of the
machine's load affects both alike; the ratio this / baseline is taken pair by pair and
its median printed.  The baseline is the ``src/`` of git revision REF (``git archive``
into a temporary folder, first on PYTHONPATH); both sides are byte-compiled first.

* ``volcal --help``, whole process (wall s);
* ``volcal mc --example mcv754 --trials 10000`` and the same with ``--mode linear``,
  whole processes (simulation, identification, the trials, tables, plots; wall s);
* the Monte Carlo trials against a loop of plain ``scipy.optimize.least_squares`` solves
  of the same trials (``benchmarks/bench_montecarlo.py --json``, run under each version:
  volcal's 10,000 trials with 2 workers and scipy's loop on ``--scipy-trials`` trials of
  the same draws, extrapolated linearly; the ratio scipy / volcal is the speed-up, and the
  whole ``volcal mc`` process is also given as a fraction of the scipy loop's 10,000
  trials);
* the cold build of the 5-axis model trunnion_ac (an empty cache folder; SymPy's import
  and ``Machine.from_model``, as ``benchmarks/bench_build.py`` times them; s);
* the exported C solver's speed-up per solve over the Python IPOPT path on the bundled
  example (``benchmarks/bench_codegen.py``'s ``bench``, median of ``--codegen-repeat``
  solves each).

Writes the printout to ``benchmarks/results/guarded.txt``.
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

from bench_build import CHILD as BUILD_CHILD  # noqa: E402
from bench_startup import _load, _time, baseline_src, write_printout  # noqa: E402

#: the C solver's speed-up, run under one version's PYTHONPATH (bench_codegen's bench)
CODEGEN_CHILD = r"""
import json, sys, tempfile
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import bench_codegen as b
label, machine, df = next(b.problems(True))
with tempfile.TemporaryDirectory() as d:
    row = b.bench(label, machine, df, int(sys.argv[2]), Path(d))
print(json.dumps({"python_s": row["py_solve"][0], "c_s": row["c_solve"][0],
                  "params_rel": row["par_normrel"]}))
"""


def _env(src: Path | None, **extra: str) -> dict[str, str]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", **extra)
    if src is not None:
        env["PYTHONPATH"] = str(src) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _json_child(code: list[str], env: dict[str, str]) -> dict:
    r = subprocess.run(code, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{code[:3]}: exit {r.returncode}: {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _cold_build(src: Path | None, work: Path) -> float:
    """SymPy's import and the cold build of trunnion_ac in a fresh process (s)."""
    with tempfile.TemporaryDirectory(dir=work) as cache:
        out = _json_child(
            [sys.executable, "-c", BUILD_CHILD, "trunnion_ac", "cold"],
            _env(src, VOLCAL_CACHE_DIR=cache),
        )
    if out["from_cache"]:
        raise RuntimeError("the cold build read a cache entry")
    return float(out["import_sympy"] + out["build"])


def _mc_vs_scipy(src: Path | None, work: Path, scipy_trials: int) -> dict[str, float]:
    """bench_montecarlo's rows under one version: volcal's 10,000 trials (2 workers) and
    the scipy loop's time extrapolated to 10,000 trials (s)."""
    js = work / "mc.json"
    subprocess.run(
        [sys.executable, str(HERE / "bench_montecarlo.py"), "--trials", "10000",
         "--scipy-trials", str(scipy_trials), "--casadi-scipy-trials", "5",
         "--out", str(work / "mc.md"), "--json", str(js)],
        env=_env(src), check=True, capture_output=True, text=True,
    )  # fmt: skip
    rows = {r["name"]: r["s_all_trials"] for r in json.loads(js.read_text())}
    scipy = min(v for k, v in rows.items() if k.startswith("scipy least_squares loop"))
    return {
        "volcal_trials_s": rows["volcal nonlinear, 2 worker processes"],
        "volcal_linear_trials_s": rows["volcal linearised mode, 2 worker processes"],
        "scipy_loop_s": scipy,
    }


def _median(v: list[float]) -> float:
    return float(statistics.median(v))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline-ref", metavar="REF", required=True,
                    help="git revision to compare with (the version before the change)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per measurement and version")
    ap.add_argument("--scipy-trials", type=int, default=100,
                    help="trials of the scipy loop per run (extrapolated to 10,000)")
    ap.add_argument("--codegen-repeat", type=int, default=10)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "guarded.txt")
    a = ap.parse_args(argv)
    import volcal

    compileall.compile_dir(Path(volcal.__file__).parent, quiet=1)
    lines = [
        f"python benchmarks/bench_guarded.py --baseline-ref {a.baseline_ref} --repeat {a.repeat}"
        f" --scipy-trials {a.scipy_trials} --codegen-repeat {a.codegen_repeat}",
        f"{platform.platform()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; "
        "one BLAS thread per process",
        f"load average before: {_load()}",
    ]
    times: dict[tuple[str, str], list[float]] = {}

    def add(name: str, side: str, value: float) -> None:
        times.setdefault((name, side), []).append(value)

    with tempfile.TemporaryDirectory(prefix="volcal-guarded-") as tmp:
        work = Path(tmp)
        sides: dict[str, Path | None] = {"this": None,
                                         "baseline": baseline_src(a.baseline_ref, work)}
        for side, src in sides.items():  # warm-up: the file cache, the model caches
            _time(["--help"], src, 0)
            _time(["mc", "--example", "mcv754", "--trials", "100", "--out",
                   str(work / f"warm-{side}")], src, 0)  # fmt: skip
        for i in range(a.repeat):
            for side, src in sides.items():
                print(f"  run {i + 1} of {a.repeat}, {side} ...", file=sys.stderr, flush=True)
                add("volcal --help (s)", side, _time(["--help"], src, 0))
                for mode in ("nonlinear", "linear"):
                    out = work / f"mc-{side}-{mode}-{i}"
                    add(
                        f"volcal mc --example mcv754 --trials 10000, {mode} (s)",
                        side,
                        _time(["mc", "--example", "mcv754", "--trials", "10000", "--mode",
                               mode, "--out", str(out)], src, 0),
                    )  # fmt: skip
                mc = _mc_vs_scipy(src, work, a.scipy_trials)
                add("Monte Carlo trials: scipy loop / volcal, nonlinear (x)", side,
                    mc["scipy_loop_s"] / mc["volcal_trials_s"])
                add("Monte Carlo trials: scipy loop / volcal, linear (x)", side,
                    mc["scipy_loop_s"] / mc["volcal_linear_trials_s"])
                whole = times[("volcal mc --example mcv754 --trials 10000, nonlinear (s)",
                               side)][-1]
                add("whole volcal mc nonlinear / scipy loop's trials alone", side,
                    whole / mc["scipy_loop_s"])
                add("cold build of trunnion_ac with SymPy's import (s)", side,
                    _cold_build(src, work))
                cg = _json_child(
                    [sys.executable, "-c", CODEGEN_CHILD, str(HERE), str(a.codegen_repeat)],
                    _env(src),
                )
                add("C solver speed-up over the Python IPOPT solve (x)", side,
                    cg["python_s"] / cg["c_s"])
    lines.append(f"load average after: {_load()}")
    lines.append("")
    names = list(dict.fromkeys(n for n, _ in times))
    width = max(len(n) for n in names)
    lines.append(f"{'measurement':{width}s}  {'this':>9s}  {'baseline':>9s}  this / baseline")
    for n in names:
        t, b = times[(n, "this")], times[(n, "baseline")]
        pairs = [x / y for x, y in zip(t, b)]
        lines.append(f"{n:{width}s}  {_median(t):9.3f}  {_median(b):9.3f}  "
                     f"{_median(pairs):.3f} ({min(pairs):.3f}-{max(pairs):.3f})")
    lines += ["", "medians of the runs; this / baseline: median (range) of the run pairs; "
              "for (x) figures larger is faster"]
    write_printout(lines, a.out)
    return 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    code = main()
    print(f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    raise SystemExit(code)
