"""Solver construction (once per problem layout) and the raw solve result.

IPOPT with a Gauss-Newton Hessian passed through ``hess_lag``: for nonlinear least
squares it converges in a handful of iterations and costs half of the exact Hessian
(DESIGN.md).  The exact Hessian is kept as an option.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from volcal.problem.residuals import IdentificationProblem

_OK = {"Solve_Succeeded", "Solved_To_Acceptable_Level"}


@dataclass
class SolveOutcome:
    """What one IPOPT solve returned: x, the objective 0.5 ||r||^2, status and effort."""

    x: np.ndarray
    f: float
    status: str
    success: bool
    iterations: int
    seconds: float
    #: Gauss-Newton steps :func:`polish` took after IPOPT, and the objective it reached
    polish_steps: int = 0
    polish_f: float = float("nan")


class NLPSolver:
    """IPOPT for an :class:`IdentificationProblem`, built once and reused for any data."""

    def __init__(self, problem: IdentificationProblem, *, hessian: str = "gauss-newton",
                 tol: float = 1e-8, max_iter: int = 100, verbose: bool = False):
        self.problem = problem
        opts = {
            "ipopt.print_level": 5 if verbose else 0,
            "print_time": False,
            "ipopt.sb": "yes",
            "ipopt.tol": tol,
            "ipopt.max_iter": max_iter,
            # at the optimum the gradient of a whitened sum of squares is at rounding level,
            # not zero (about 1e-6 for 2e4 readings and 150 unknowns): stop as soon as the
            # objective stalls at a relaxed tolerance; :func:`polish` then takes the
            # Gauss-Newton steps that end at the minimiser to working precision
            "ipopt.acceptable_tol": 1e-4,
            "ipopt.acceptable_iter": 1,
            "ipopt.acceptable_obj_change_tol": 1e-10,
            # the data are whitened: residual norm ~ sqrt(N), tolerance relative to that
            "ipopt.nlp_scaling_method": "none",
            "error_on_fail": False,
        }
        opts["grad_f"] = problem.grad_f
        if hessian == "gauss-newton":
            opts["hess_lag"] = problem.hess_lag
        elif hessian != "exact":
            raise ValueError(f"hessian must be 'gauss-newton' or 'exact', got {hessian!r}")
        self.hessian = hessian
        self.solver = ca.nlpsol("identify", "ipopt", problem.nlp, opts)

    def solve(self, x0: np.ndarray, p: np.ndarray, *, fixed: np.ndarray | None = None
              ) -> SolveOutcome:
        """Solve from x0 (physical units) with data p; variables where ``fixed`` is True
        stay at x0.  Returns x in physical units."""
        n = self.problem.n_x
        x0 = self.problem.to_scaled(x0)
        lbx, ubx = np.full(n, -np.inf), np.full(n, np.inf)
        if fixed is not None:
            lbx[fixed] = ubx[fixed] = x0[fixed]
        lbg, ubg = self.problem.g_bounds()
        t0 = time.perf_counter()
        sol = self.solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        dt = time.perf_counter() - t0
        st = self.solver.stats()
        status = st.get("return_status", "unknown")
        x = self.problem.from_scaled(sol["x"].full())
        ok = status in _OK and bool(np.all(np.isfinite(x)))
        return SolveOutcome(x, float(sol["f"]), status, ok, int(st.get("iter_count", -1)), dt)


def polish(problem: IdentificationProblem, x: np.ndarray, p: np.ndarray,
           fixed: np.ndarray | None = None, *, steps: int = 3
           ) -> tuple[np.ndarray, int, float]:
    """A few Gauss-Newton steps from IPOPT's answer x (physical units) under the datum in
    force, with ``fixed`` variables held.

    IPOPT stops once the gradient of the whitened sum of squares is at rounding level, which
    leaves the sum of squares about 1e-7 relative above its minimum; the minimiser is then
    datum-dependent at that level.  Near the minimum Gauss-Newton converges fast, so a few
    steps bring every datum and strategy to the same minimum (1e-10 relative) for the price
    of a Jacobian each.  A step is kept only when it lowers the sum of squares.  Returns
    (x, steps kept, objective 0.5 ||r||^2 at x)."""
    import scipy.linalg as sla

    n = problem.n_x
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    nt = problem.n_theta
    C = np.zeros((problem.C.shape[0], n))
    C[:, :nt] = problem.C * problem.scale[None, :nt]
    Cf = C[:, free]
    Cf = Cf[np.linalg.norm(Cf, axis=1) > 0]
    Z = sla.null_space(Cf) if Cf.shape[0] else np.eye(len(free))
    xs = problem.to_scaled(x)
    r, J = problem.jacobian(xs, p)
    r, J = r.full().ravel(), J.full()
    f = float(r @ r)
    kept = 0
    for _ in range(steps):
        A = J[:, free] @ Z
        y = np.linalg.lstsq(A, -r, rcond=None)[0]
        trial = xs.copy()
        trial[free] += Z @ y
        r1, J1 = problem.jacobian(trial, p)
        r1 = r1.full().ravel()
        f1 = float(r1 @ r1)
        if not np.isfinite(f1) or f1 >= f:
            break
        xs, r, J, f = trial, r1, J1.full(), f1
        kept += 1
    return problem.from_scaled(xs), kept, 0.5 * f
