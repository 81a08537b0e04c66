"""Solver construction (once per problem layout) and the raw solve result.

IPOPT with a Gauss-Newton Hessian passed through ``hess_lag``: for nonlinear least
squares it converges in a handful of iterations and costs half of the exact Hessian
(DESIGN.md).  The exact Hessian is kept as an option.
"""

from __future__ import annotations

import time
from typing import Any

import casadi as ca
import numpy as np

from volcal.base.interrupts import raise_if_signalled
from volcal.problem.residuals import IdentificationProblem
from volcal.solve.outcome import SolveOutcome

_OK = {"Solve_Succeeded", "Solved_To_Acceptable_Level"}

#: nlpsol options for a solver whose callers never read the multipliers of the parameters
#: p (the data, the weights): without them nlpsol builds the Lagrangian's gradient with
#: respect to p by reverse AD through the whole graph (0.04 s of the 0.05 s nlpsol took
#: on the bundled example; 0.07 s for a plan's first placement solver); same iterates
NO_PARAMETER_MULTIPLIERS: dict[str, Any] = {"calc_lam_p": False, "no_nlp_grad": True}


class NLPSolver:
    """IPOPT for an :class:`IdentificationProblem`, built once and reused for any data."""

    def __init__(
        self,
        problem: IdentificationProblem,
        *,
        hessian: str = "gauss-newton",
        tol: float = 1e-8,
        max_iter: int = 100,
        verbose: bool = False,
    ):
        self.problem = problem
        opts: dict[str, Any] = {
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
            **NO_PARAMETER_MULTIPLIERS,
        }
        opts["grad_f"] = problem.grad_f
        if hessian == "gauss-newton":
            opts["hess_lag"] = problem.hess_lag
        elif hessian != "exact":
            raise ValueError(f"hessian must be 'gauss-newton' or 'exact', got {hessian!r}")
        self.hessian = hessian
        self.solver = ca.nlpsol("identify", "ipopt", problem.nlp, opts)

    def solve(
        self, x0: np.ndarray, p: np.ndarray, *, fixed: np.ndarray | None = None
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
        raise_if_signalled()  # IPOPT ends early on Ctrl-C / SIGTERM and returns
        dt = time.perf_counter() - t0
        st = self.solver.stats()
        status = st.get("return_status", "unknown")
        x = self.problem.from_scaled(sol["x"].full())
        ok = status in _OK and bool(np.all(np.isfinite(x)))
        return SolveOutcome(x, float(sol["f"]), status, ok, int(st.get("iter_count", -1)), dt)
