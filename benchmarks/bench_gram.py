"""Cost of the Gauss-Newton Hessian J^T J of the identification Jacobian: numpy's BLAS on
one thread (what the solver's callback uses today) against CasADi's own sparse product
(what a pure CasADi Hessian would use).  The 5-axis trunnion_ac on a 4-position grid with
four tool offsets and six stations (18,432 readings).

    python benchmarks/bench_gram.py
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_identify import simulated  # noqa: E402  (the tests' simulation setup)

from volcal.measurement.tables import load_measurements  # noqa: E402
from volcal.analysis.identify import Identifier, initial_stations  # noqa: E402
from volcal.problem.residuals import Layout  # noqa: E402


def main() -> None:
    machine, em, _, sim = simulated("trunnion_ac", grid=4)
    meas = load_measurements(sim.measurements, machine.spec)
    pr = Identifier(machine, em, Layout.from_measurements(meas)).problem
    st0, _, _ = initial_stations(machine, meas, None)
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, 1 / meas.sigma)
    _, J = pr.jacobian(pr.to_scaled(pr.pack_x(np.zeros(pr.n_theta), st0)), p)
    Jd = np.asarray(J.full())
    with threadpool_limits(1):
        t0 = time.perf_counter()
        for _ in range(5):
            Jd.T @ Jd
        t_np = (time.perf_counter() - t0) / 5
    sym = ca.MX.sym("J", J.sparsity())
    f = ca.Function("gram", [sym], [ca.mtimes(sym.T, sym)])
    t0 = time.perf_counter()
    for _ in range(3):
        f(J)
    t_ca = (time.perf_counter() - t0) / 3
    print(f"J {J.shape[0]} x {J.shape[1]} ({J.nnz()} nonzeros): numpy J^T J on 1 BLAS "
          f"thread {t_np:.3f} s; CasADi MX Function {t_ca:.3f} s ({t_ca / t_np:.0f}x)")


if __name__ == "__main__":
    main()
