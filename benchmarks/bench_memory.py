"""Peak memory of ``volcal identify`` against readings x unknowns: the factors of
``volcal.base.memory`` (the check that refuses a table too large for the memory).

Simulates mcv754_wxyzt tables on grids of 8, 14 and 18 positions per axis (12,288 to
139,968 readings) and identifies them with ``--no-plots`` at degree 3, and the middle one
also at degrees 1 and 5 (75 to 147 unknowns); each identification runs under a minimal
launcher (``python -S``) that reports the command's own peak resident set.  Fits
``peak = base + readings x (a + b x unknowns)`` by least squares and prints the factors
next to the ones volcal uses.

With ``--solver ipopt`` every identification goes through the whole CasADi graph (the
factors ``volcal.base.memory`` uses for IPOPT); ``--solver gauss-newton`` (and ``auto``,
the default, at these sizes) through the chunked evaluation (``CHUNKED_FACTORS``).

Run:  python benchmarks/bench_memory.py [--grids 8 14 18] [--degrees 1 5] [--solver S]
(about two minutes on a quiet machine; memory is not timing: load does not change it.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from volcal.analysis.identify import resolve_solver
from volcal.base import memory

LAUNCH = (
    "import resource, subprocess, sys\n"
    "r = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL)\n"
    "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
)


def volcal(*args: str) -> list[str]:
    return [sys.executable, "-m", "volcal.cli.main", *args]


def peak_kib(cmd: list[str]) -> int:
    out = subprocess.run(
        [sys.executable, "-S", "-c", LAUNCH, *cmd], capture_output=True, text=True, check=True
    ).stdout.split()
    if out[0] != "0":
        raise SystemExit(f"failed: {' '.join(cmd)}")
    return int(out[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grids", type=int, nargs="+", default=[8, 14, 18])
    ap.add_argument("--degrees", type=int, nargs="+", default=[1, 5])
    ap.add_argument("--solver", choices=["auto", "ipopt", "gauss-newton"], default="auto")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        mid = a.grids[len(a.grids) // 2]
        for g in a.grids:
            sim = t / f"sim{g}"
            subprocess.run(
                volcal(
                    "simulate",
                    "--model",
                    "mcv754_wxyzt",
                    "--grid",
                    str(g),
                    "--seed",
                    "1",
                    "--out",
                    str(sim),
                    "-q",
                ),
                check=True,
            )
            for d in [3] + (a.degrees if g == mid else []):
                res = t / f"res{g}_{d}"
                kib = peak_kib(
                    volcal(
                        "identify",
                        "--model",
                        "mcv754_wxyzt",
                        "--data",
                        str(sim / "measurements.csv"),
                        "--degree",
                        str(d),
                        "--out",
                        str(res),
                        "--no-plots",
                        "-q",
                        "--max-memory-gb",
                        "inf",
                        "--solver",
                        a.solver,
                    )
                )
                doc = json.loads((res / "result.json").read_text())
                n = int(doc["n_readings"])
                # unknowns as the check counts them: error parameters, 4 per station, frame 6
                unknowns = len(doc["param_names"]) + 4 * len(doc["stations"]) + 6
                # the path the run took (identify's own rule for --solver auto)
                chunked = resolve_solver(a.solver, n) == "gauss-newton"
                rows.append((n, unknowns, kib * 1024, chunked))
                print(f"{n:>8} readings {unknowns:>4} unknowns  peak {kib / 1024:8.1f} MiB")
    d = np.array([r[:3] for r in rows], float)
    A = np.c_[np.ones(len(d)), d[:, 0], d[:, 0] * d[:, 1]]
    c, *_ = np.linalg.lstsq(A, d[:, 2], rcond=None)
    res = A @ c - d[:, 2]
    print(
        f"fit: base {c[0] / 1e6:.0f} MB, {c[1] / 1e3:.2f} kB per reading, "
        f"{c[2]:.1f} B per reading and unknown (largest residual {abs(res).max() / 1e6:.1f} MB)"
    )
    chunked_all = all(r[3] for r in rows)
    base, per_reading, per_cell = (
        memory.CHUNKED_FACTORS
        if chunked_all
        else (memory.BASE_BYTES, memory.BYTES_PER_READING, memory.BYTES_PER_READING_UNKNOWN)
    )
    print(
        f"volcal.base.memory uses ({'chunked' if chunked_all else 'whole graph'}): "
        f"base {base / 1e6:.0f} MB, {per_reading / 1e3:.2f} kB per reading, "
        f"{per_cell:.1f} B per reading and unknown"
    )
    for n, u, peak, chunked in rows:
        est = memory.estimate_peak_bytes(int(n), int(u), chunked=chunked)
        print(
            f"  {int(n):>8} x {int(u):>4}: measured {peak / 1e6:7.0f} MB, "
            f"estimate {est / 1e6:7.0f} MB"
        )


if __name__ == "__main__":
    main()
