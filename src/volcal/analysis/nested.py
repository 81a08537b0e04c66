"""Fits of nested error models on one problem: the candidate fits of the order selection.

Legendre polynomials of degree n are the first n + 1 of degree n + 1, Fourier series of n
harmonics the first 2n + 1 functions of n + 1 harmonics: an error model with lower orders
is the largest one with the parameters of the higher orders held at zero.  So the problem
is built once, for the largest orders, and each candidate is a set of held columns:

* one Jacobian at the structural point (errors zero, stations at their start values;
  :meth:`~volcal.analysis.identify.Identifier.structural`) and one QR of it.  Its R factor
  has the same J^T J as the tall Jacobian, restricted to any set of columns, so each
  candidate's datum selection and rank (the ``k`` of BIC) are decided on the small R, with
  the tall Jacobian's rank tolerance (``n_rows``): the same decisions as a fit of that model
  alone, without a tall factorisation per candidate;
* the solve is a chord Gauss-Newton iteration: the steps of the reduced normal equations
  (datum and held unknowns eliminated, as :mod:`volcal.solve.gauss_newton`) with a Gram
  matrix J^T J kept from an earlier point (at first the structural one, from the same R;
  taken again at the current iterate when the iteration slows down) and the gradient
  J^T r evaluated at every iterate.  The gradient is a fraction of the Gram matrix's cost,
  and near-linear residuals (errors of micrometres) make the kept matrix almost exact, so
  a candidate converges in a few gradients.  It stops where Gauss-Newton stops (largest
  step 1e-9 in solver units): the fixed point has zero reduced gradient, the minimiser
  IPOPT and the polish reach.  A candidate that does not converge so is solved by
  Levenberg-Marquardt from where it stopped.  Warm start: the solved candidate with the
  nearest set of columns, its first step from that candidate's last gradient carried over
  by the kept matrix (no evaluation).  It also stops where the step promises less than the rounding
  level of the sum of squares (Gauss-Newton's other test);
* no covariance, null space of the field, adequacy or result tables: the caller identifies
  the chosen model in full.

B-spline bases are not nested (the knots move with the number of segments): the caller
keeps them on full fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from volcal.analysis.identifiability import _r_factor, analyse_jacobian
from volcal.analysis.identify import Identifier
from volcal.base.exceptions import InputError
from volcal.model.datum import select_conditions
from volcal.model.errors import ErrorModel
from volcal.solve.gauss_newton import feasible_basis, project_feasible

__all__ = ["NestedFit", "NestedFits"]


@dataclass
class NestedFit:
    """One candidate: chi2 (sum of squared whitened residuals), rank k (independent
    combinations of the unknowns the data determine), number of readings n, solver status
    and iterations, and the unknowns x (physical units, the largest model's order)."""

    chi2: float
    k: int
    n: int
    status: str
    success: bool
    iterations: int
    x: np.ndarray


class NestedFits:
    """Candidate error models nested in ``identifier.error_model`` (module docstring).

    identifier: built for the largest orders (its solver is not used: every candidate is
    solved by its Gauss-Newton solver); x0: start values (physical units, errors zero);
    p: the data (:meth:`~volcal.problem.residuals.IdentificationProblem.pack_data`, weights
    1 / sigma with sigma in mm); user_fixed: the held unknowns (given stations, the
    instrument's own convention)."""

    def __init__(
        self, identifier: Identifier, x0: np.ndarray, p: np.ndarray, user_fixed: np.ndarray
    ):
        if identifier.datum_mode != "minimal":
            raise InputError("nested fits decide the datum per candidate (datum_mode minimal)")
        self.identifier = identifier
        pr = identifier.problem
        self.x0 = np.array(x0, float)
        self.p = np.asarray(p, float)
        self.user_fixed = np.asarray(user_fixed, bool)
        # the one factorisation: R of the scaled Jacobian at the structural point
        _, J0 = identifier.jacobian(identifier.structural(self.x0), self.p)
        self.rows = int(J0.shape[0])
        self.R0 = _r_factor(np.array(J0, float))
        self.C_all = np.zeros((pr.C_all.shape[0], pr.n_x))
        self.C_all[:, : pr.n_theta] = pr.C_all * pr.scale[None, : pr.n_theta]
        #: solved candidates: (free columns, x physical, x scaled, gradient J^T r there)
        self._solved: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        #: the kept Gram matrix J^T J (scaled unknowns) of the chord iteration
        self.gram = self.R0.T @ self.R0
        #: gradient and Gram evaluations so far (the cost of the candidates)
        self.gradients = 0
        self.grams = 1

    def columns(self, em: ErrorModel) -> np.ndarray:
        """The mask over the unknowns of the largest model that ``em`` keeps free: its
        error parameters (by name), every station and global unknown.  Raises
        InputError when ``em`` is not nested in the largest model."""
        pr = self.identifier.problem
        big = self.identifier.error_model
        names = list(big.param_names)
        missing = [n for n in em.param_names if n not in names]
        # only Legendre and Fourier orders nest (B-spline knots move with the segments)
        other = [
            s.name
            for s, f, g in zip(em.errors, em.forms, big.forms)
            if f != g and not (f.kind == g.kind and f.kind in ("poly", "fourier"))
        ]
        if missing or other or em.datum != big.datum or len(em.errors) != len(big.errors):
            raise InputError(
                f"error model not nested in the largest one ({', '.join((missing + other)[:4])})"
            )
        keep = np.ones(pr.n_x, bool)
        keep[: pr.n_theta] = np.isin(names, list(em.param_names))
        return keep

    def fit(self, em: ErrorModel) -> NestedFit:
        """Fit the candidate ``em`` (nested in the largest model)."""
        ider = self.identifier
        pr = ider.problem
        free_cols = self.columns(em)
        held = self.user_fixed | ~free_cols
        # datum and rank on the R factor, as Identifier.run decides them on the tall
        # Jacobian at the structural point (the joint strategy's one phase)
        if self.C_all.shape[0]:
            pr.set_datum(select_conditions(self.R0, self.C_all, held, n_rows=self.rows))
        else:
            pr.set_datum(np.zeros(0, bool))
        ident = analyse_jacobian(
            self.R0,
            pr.names,
            ider._scaled_constraints(),
            fixed=held,
            prefer=ider.prefer,
            n_rows=self.rows,
        )
        pivot = np.zeros(pr.n_x, bool)
        pivot[list(ident.pivots)] = True
        fixed = held | pivot
        # warm start: the solved candidate with the fewest columns of difference; the
        # columns this one holds at zero, its pivots at their start values
        x = self.x0.copy()
        warm = None
        if self._solved:
            near = min(self._solved, key=lambda s: int(np.sum(s[0] != free_cols)))
            x, warm = near[1].copy(), (near[2], near[3])
        x[~free_cols] = 0.0
        x[pivot] = np.where(ider.is_theta[pivot], 0.0, self.x0[pivot])
        x, chi2, status, iterations, g = self._chord(x, fixed, warm)
        ok = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
        if ok and g is not None:
            self._solved.append((free_cols, x, pr.to_scaled(x), g))
        return NestedFit(
            chi2,
            int(ident.rank),
            int(np.sum(self.p[-ider.layout.n_readings :] > 0)),  # weights: the last N
            status,
            ok,
            iterations,
            x,
        )

    def _chord(
        self,
        x: np.ndarray,
        fixed: np.ndarray,
        warm: tuple[np.ndarray, np.ndarray] | None = None,
        *,
        max_iter: int = 30,
    ) -> tuple[np.ndarray, float, str, int, np.ndarray | None]:
        """Minimise from x (physical) with ``fixed`` held (module docstring); returns (x,
        chi2, status, iterations, the gradient J^T r at x (scaled; None after the
        fallback)).  warm: (x scaled, gradient) of the solved candidate x comes from: the
        first step takes the gradient there carried to x by the kept matrix (a linear
        prediction, no evaluation); convergence is judged on evaluated gradients only."""
        ider = self.identifier
        pr, gn = ider.problem, ider.gauss_newton
        Z = feasible_basis(pr, fixed)
        xs = project_feasible(pr, pr.to_scaled(x), fixed)
        last = np.inf
        try:
            factor = sla.cho_factor(Z.T @ self.gram @ Z, check_finite=False)
            if warm is not None:
                g_pred = warm[1] + self.gram @ (xs - warm[0])
                xs = xs - Z @ sla.cho_solve(factor, Z.T @ g_pred, check_finite=False)
            for it in range(1, max_iter + 1):
                f, g = (v.full().ravel() for v in pr.grad_f(xs, self.p))
                self.gradients += 1
                if not np.all(np.isfinite(g)):
                    break
                dx = -Z @ sla.cho_solve(factor, Z.T @ g, check_finite=False)
                size = float(np.max(np.abs(dx))) if dx.size else 0.0
                gz = Z.T @ g
                pred = 0.5 * float(gz @ sla.cho_solve(factor, gz, check_finite=False))
                if pred < 1e-13 * max(float(f[0]), 1.0):
                    # the step promises less than the rounding level of f: converged
                    # (Gauss-Newton's own test, volcal.solve.gauss_newton)
                    return pr.from_scaled(xs), 2.0 * float(f[0]), "Solve_Succeeded", it, g
                if size > 0.25 * last:
                    # slow or diverging: the kept matrix is far from this point; take
                    # J^T J here and redo the step
                    _, J = ider.jacobian(pr.from_scaled(xs), self.p)
                    self.gram = J.T @ J
                    self.grams += 1
                    factor = sla.cho_factor(Z.T @ self.gram @ Z, check_finite=False)
                    dx = -Z @ sla.cho_solve(factor, Z.T @ g, check_finite=False)
                    size = float(np.max(np.abs(dx))) if dx.size else 0.0
                if size <= gn.step_tol:
                    return pr.from_scaled(xs), 2.0 * float(f[0]), "Solve_Succeeded", it, g
                last = size
                xs = xs + dx
        except (sla.LinAlgError, ValueError):
            pass  # the reduced Gram matrix is not positive definite: Levenberg-Marquardt
        out = gn.solve(pr.from_scaled(xs), self.p, fixed=fixed)
        f = 2.0 * out.f if np.isfinite(out.f) else float("nan")
        return np.array(out.x, float), f, out.status, max_iter + out.iterations, None
