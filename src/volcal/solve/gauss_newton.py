"""Gauss-Newton / Levenberg-Marquardt on the identification problem, with the datum
eliminated, on the problem's chunked evaluation (no whole-problem graph).

The NLP of :class:`volcal.problem.residuals.IdentificationProblem` is a nonlinear least-
squares problem with *linear* equality constraints (the datum, C theta = 0) and held
variables.  Both are eliminated exactly: with Z an orthonormal basis of the null space of
the constraints restricted to the free variables (zero rows for held ones), every step is
dx = Z dz and a feasible start stays feasible.  The step solves the reduced normal
equations

    (Z^T H Z + mu diag(Z^T H Z)) dz = -Z^T J^T r,      H = J^T J

from r, J^T r and J^T J evaluated in fixed-size chunks of poses through the problem's
per-pose and per-reading CasADi Functions, mapped once
(:class:`volcal.problem.chunked.ChunkedEvaluator`): the residual model IPOPT sees, without
the graph of every reading that IPOPT's NLP needs, so a problem of 10^6 readings is solved
in O(N) memory.  ``mu`` is the
Levenberg-Marquardt damping (Marquardt's diagonal scaling), 0 for a pure Gauss-Newton
step; it is raised when a step does not lower the sum of squares and lowered when it does.

:meth:`GaussNewtonSolver.solve_levenberg` is the other use of a damping: a *fixed* metric
for a problem that stays rank deficient after its gauge is held (paper 001's joint
estimation, studies/paper001).  Every step solves ``Z^T (H + diag(d)) Z dz = -Z^T J^T r``
with d fixed and is taken whole, so the iteration converges to the exact fit its start and
d select (nearly the minimum-norm correction in the metric d), not to a point set by
rounding.

The sums over the readings are CasADi and BLAS; the reduced system (n_z x n_z), the
accept/reject loop and the stopping test are numpy.  (The exported C solver,
:mod:`volcal.outputs.codegen`, builds its own CasADi step from the problem's Jacobian.)
At the fixed point the reduced gradient Z^T J^T r is zero, which
is the KKT condition of the constrained problem: the minimiser is the one IPOPT finds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from volcal.base import progress
from volcal.base.linalg import cholesky_solve, cholesky_upper, null_space, solve_triangular
from volcal.problem.residuals import IdentificationProblem
from volcal.solve.outcome import SolveOutcome


def _qr_solve(A: np.ndarray, b: np.ndarray, *, rank_check: bool = False) -> np.ndarray:
    """A^-1 b through a QR of A (a square system that may be badly conditioned; raises
    LinAlgError when exactly singular, and with ``rank_check`` when numerically singular:
    a diagonal of R below n eps times the largest, the tolerance
    ``numpy.linalg.matrix_rank`` applies to singular values, here on R's diagonal, which
    an unpivoted QR makes a cheap indicator rather than a rank-revealing one).  Q^T b is
    formed by numpy (LAPACK orgqr; the systems are n_z x n_z, a few hundred at most)."""
    if A.shape[0] == 0:
        return np.zeros(0)
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        return np.full(len(b), np.nan)  # the caller reports the invalid number
    Q, R = np.linalg.qr(A)
    qtb = Q.T @ b
    d = np.abs(np.diag(R))
    if d.min() == 0.0 or (rank_check and d.min() <= len(d) * np.finfo(float).eps * d.max()):
        raise np.linalg.LinAlgError(
            "singular system" if d.min() == 0.0 else "numerically singular system"
        )
    return solve_triangular(R, qtb)


def _spd_solve(A: np.ndarray, b: np.ndarray, *, rank_check: bool = False) -> np.ndarray:
    """A^-1 b for a symmetric Gauss-Newton matrix A: by Cholesky (a third of a QR's work)
    when its pivots show A well conditioned (the smallest squared diagonal of the factor
    above sqrt(eps) times the largest), else by :func:`_qr_solve` with ``rank_check``, so
    that a nearly singular system is solved, or refused, exactly as before."""
    if A.shape[0] and np.all(np.isfinite(A)) and np.all(np.isfinite(b)):
        try:
            U = cholesky_upper(A)
        except np.linalg.LinAlgError:
            pass
        else:
            d = np.diag(U) ** 2
            if d.min() > np.sqrt(np.finfo(float).eps) * d.max():
                return cholesky_solve(U, b)
    return _qr_solve(A, b, rank_check=rank_check)


def _selection(Z: np.ndarray) -> np.ndarray | None:
    """The indices of the variables Z (n_x, n_z) selects when it is a selection (no datum
    condition on the free variables: Z's columns are unit vectors in increasing order),
    else None; the reduced system is then a sub-matrix, not two products with Z."""
    n_z = Z.shape[1]
    if np.count_nonzero(Z) != n_z:
        return None
    rows, cols = np.nonzero(Z)
    if not (np.array_equal(cols, np.arange(n_z)) and np.all(Z[rows, cols] == 1.0)):
        return None
    return rows


def _expand(Z: np.ndarray, sel: np.ndarray | None, dz: np.ndarray) -> np.ndarray:
    """dx = Z dz (n_x,), by placing dz at the selected variables when Z is a selection."""
    if sel is None:
        return Z @ dz
    dx = np.zeros(Z.shape[0])
    dx[sel] = dz
    return dx


def feasible_basis(problem: IdentificationProblem, fixed: np.ndarray | None) -> np.ndarray:
    """Z (n_x, n_z): orthonormal basis of the steps that keep the datum in force and the
    held variables where they are (scaled variables)."""
    n, nt = problem.n_x, problem.n_theta
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    C = np.zeros((problem.C.shape[0], n))
    C[:, :nt] = problem.C * problem.scale[None, :nt]
    Cf = C[:, free]
    Cf = Cf[np.linalg.norm(Cf, axis=1) > 0]
    Zf = null_space(Cf) if Cf.shape[0] else np.eye(len(free))
    Z = np.zeros((n, Zf.shape[1]))
    Z[free] = Zf
    return Z


def project_feasible(
    problem: IdentificationProblem, xs: np.ndarray, fixed: np.ndarray | None
) -> np.ndarray:
    """The closest point to xs (scaled) that satisfies the datum in force, moving free
    variables only."""
    n, nt = problem.n_x, problem.n_theta
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    C = np.zeros((problem.C.shape[0], n))
    C[:, :nt] = problem.C * problem.scale[None, :nt]
    if C.shape[0] == 0:
        return np.array(xs, float)
    Cf = C[:, ~fixed]
    viol = C @ xs
    out = np.array(xs, float)
    out[~fixed] -= np.linalg.lstsq(Cf, viol, rcond=None)[0]
    return out


@dataclass(frozen=True)
class FinalGram:
    """The Gauss-Newton system at the answer of a solve: r (N,), J^T r (n_x,) and J^T J
    (n_x, n_x) wrt the scaled variables at physical x with data p (held, not copied).  The
    last iteration of :meth:`GaussNewtonSolver.solve` evaluates it there to find that the
    step is at its tolerance; the covariance at the answer takes it instead of evaluating
    the Jacobian again (:meth:`matches` says whether it is for a given x and p)."""

    x: np.ndarray
    p: np.ndarray
    r: np.ndarray
    g: np.ndarray
    H: np.ndarray

    def matches(self, x: np.ndarray, p: np.ndarray) -> bool:
        """Whether this is the system at physical x (n_x,) with data p, exactly."""
        x, p = np.asarray(x, float), np.asarray(p, float)
        return bool(
            x.shape == self.x.shape
            and np.array_equal(x, self.x)
            and (p is self.p or (p.shape == self.p.shape and np.array_equal(p, self.p)))
        )


class GaussNewtonSolver:
    """Gauss-Newton / Levenberg-Marquardt for an :class:`IdentificationProblem`, built once
    per problem and reused for any data of its layout (see the module docstring)."""

    def __init__(
        self,
        problem: IdentificationProblem,
        *,
        max_iter: int = 50,
        step_tol: float = 1e-9,
        damping: float = 0.0,
    ):
        self.problem = problem
        self.max_iter = max_iter
        #: stop once the largest step is below this (scaled units: 1 = 1 um or 1 urad)
        self.step_tol = step_tol
        #: initial Levenberg-Marquardt damping (0: start with pure Gauss-Newton steps)
        self.damping = damping
        #: the steps the last :meth:`solve` took (an iteration may end without one)
        self.steps_taken = 0
        #: the Gauss-Newton system at the answer of the last :meth:`solve` when its last
        #: iteration evaluated it there (see :class:`FinalGram`), else None
        self.final_gram: FinalGram | None = None

    def _basis_kind(self, Z: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """(the selection Z makes or None (:func:`_selection`), whether Z moves any error
        parameter: a step that holds them all needs no d(point)/d(theta)), kept for the
        last Z (one per solve, not modified)."""
        last = self.__dict__.get("_basis_last")
        if last is None or last[0] is not Z:
            last = self._basis_last = (Z, _selection(Z), bool(np.any(Z[: self.problem.n_theta])))
        return last[1], last[2]

    def step(
        self, xs: np.ndarray, p: np.ndarray, Z: np.ndarray, mu: float
    ) -> tuple[float, np.ndarray, float, float, float]:
        """``(f, dx, kkt, pred, level)`` at scaled x for a null-space basis Z (n_x, n_z): f =
        0.5 ||r||^2, the damped step dx = Z dz, kkt = ||Z^T J^T r||_inf, the reduction
        of f the local model predicts for dx and the rounding level of f (below it two
        evaluations of f cannot rank two points).  A singular system gives a NaN step."""
        return self._step(xs, p, Z, mu)[0]

    def _step(
        self, xs: np.ndarray, p: np.ndarray, Z: np.ndarray, mu: float, system: tuple | None = None
    ) -> tuple[tuple[float, np.ndarray, float, float, float], tuple]:
        """:meth:`step` from the system (r, J^T r, J^T J) at xs when it is given (already
        evaluated there), and that system."""
        sel, theta = self._basis_kind(Z)
        if system is None:
            system = self.problem.chunked.gram(xs, p, theta=theta)
        r, g, H = system
        f = 0.5 * float(r @ r)
        # each residual w (reading - m) carries the rounding of a reading of size |m| (or
        # |m + r / w|), eps |w m| + eps |r|; f = 0.5 sum r^2 then moves by up to their sum
        # weighted by |r| between two evaluations at points a rounding apart (1e-7 of
        # f = 4e4 on 648 readings with residuals of 150 sigma, far above 1e-13 f)
        m, w = self.problem.chunked.readings(p)
        level = float(np.finfo(float).eps * (np.abs(r) @ (np.abs(w * m) + np.abs(r))))
        if Z.shape[1] == 0:
            return (f, np.zeros(self.problem.n_x), 0.0, 0.0, level), system
        Hz = H[np.ix_(sel, sel)] if sel is not None else Z.T @ H @ Z
        gz = g[sel] if sel is not None else Z.T @ g
        A = Hz + mu * np.diag(np.fmax(np.diag(Hz), 1e-12))
        try:
            dz = -_spd_solve(A, gz)
        except np.linalg.LinAlgError:
            dz = np.full(len(gz), np.nan)
        pred = -(float(gz @ dz) + 0.5 * float(dz @ (Hz @ dz)))
        return (f, _expand(Z, sel, dz), float(np.max(np.abs(gz))), pred, level), system

    def solve_levenberg(
        self,
        x0: np.ndarray,
        p: np.ndarray,
        damping: np.ndarray,
        *,
        fixed: np.ndarray | None = None,
        max_iter: int | None = None,
    ) -> SolveOutcome:
        """Gauss-Newton with a fixed Levenberg damping: from x0 (physical units), with data
        p and ``fixed`` variables held, every step solves ``(H + diag(damping)) dx = -J^T r``
        on the free variables (under the datum in force) and is taken whole, until the
        largest step is below ``step_tol``.

        damping: (n_x,) >= 0, per scaled variable (units of J^T J: a scaled unit is 1 um or
        1 urad).  For a problem whose Jacobian keeps null directions after the gauge is
        held, the answer is then the exact fit that the start and this metric select (a
        constant times the identity: nearly the minimum-norm correction in scaled units;
        ``c * diag(J0^T J0)`` of the start: Marquardt's metric), reproducibly, where an
        undamped or adaptively damped iteration ends wherever rounding sends it along the
        null directions.  Well-posed problems should use :meth:`solve`."""
        pr = self.problem
        d = np.asarray(damping, float).ravel()
        if d.shape != (pr.n_x,) or not np.all(np.isfinite(d)) or np.any(d < 0):
            raise ValueError(f"damping: expected {pr.n_x} finite values >= 0, got {d.shape}")
        t0 = time.perf_counter()
        Z = feasible_basis(pr, fixed)
        sel, theta = self._basis_kind(Z)
        xs = project_feasible(pr, pr.to_scaled(x0), fixed)
        max_iter = self.max_iter if max_iter is None else max_iter
        status, it, f = "Maximum_Iterations_Exceeded", 0, float("nan")
        for it in range(1, max_iter + 1):  # noqa: B007  (the count is reported)
            r, g, H = pr.chunked.gram(xs, p, theta=theta)
            f = 0.5 * float(r @ r)
            try:
                Hd = H + np.diag(d)
                A = Hd[np.ix_(sel, sel)] if sel is not None else Z.T @ Hd @ Z
                gz = g[sel] if sel is not None else Z.T @ g
                # an undamped null direction would otherwise give a step of rounding
                # divided by rounding (the whole-graph solver refused it the same way)
                dx = -_expand(Z, sel, _spd_solve(A, gz, rank_check=True))
            except np.linalg.LinAlgError:  # a singular system: no damping on a null direction
                status = "Singular_Step"
                break
            progress.update(f"Levenberg iteration {it}, cost {f:.6g}")
            if not np.all(np.isfinite(dx)):
                status = "Invalid_Number_Detected"
                break
            xs = xs + dx
            if (float(np.max(np.abs(dx))) if dx.size else 0.0) <= self.step_tol:
                status = "Solve_Succeeded"
                break
        x = pr.from_scaled(xs)
        ok = status == "Solve_Succeeded" and bool(np.all(np.isfinite(x)))
        return SolveOutcome(x, self.objective(xs, p), status, ok, it, time.perf_counter() - t0)

    def objective(self, xs: np.ndarray, p: np.ndarray) -> float:
        return self.problem.chunked.objective(xs, p)

    def trial(
        self, xs: np.ndarray, p: np.ndarray, *, theta: bool, system: bool
    ) -> tuple[float, tuple | None]:
        """f = 0.5 ||r||^2 at a trial point xs (scaled) and, with ``system``, the
        Gauss-Newton system there (r, J^T r, J^T J; the error parameters' rows with
        ``theta``): the next iteration's when the step is taken, in the same pass over
        the readings (the residuals are the same numbers as :meth:`objective`'s)."""
        if not system:
            return self.objective(xs, p), None
        r, g, H = self.problem.chunked.gram(xs, p, theta=theta)
        return 0.5 * float(r @ r), (r, g, H)

    def solve(
        self,
        x0: np.ndarray,
        p: np.ndarray,
        *,
        fixed: np.ndarray | None = None,
        max_iter: int | None = None,
        damping: float | None = None,
    ) -> SolveOutcome:
        """Solve from x0 (physical units) with data p, ``fixed`` variables held at x0.
        x0 is first projected onto the datum.  Returns x in physical units."""
        pr = self.problem
        t0 = time.perf_counter()
        Z = feasible_basis(pr, fixed)
        xs = project_feasible(pr, pr.to_scaled(x0), fixed)
        mu = self.damping if damping is None else damping
        max_iter = self.max_iter if max_iter is None else max_iter
        status, it = "Maximum_Iterations_Exceeded", 0
        f, size = float("nan"), float("inf")
        accepted = False  # whether the last trial step was taken
        taken = 0  # steps taken
        floor: float | None = None  # size of the last step f could not rank, if it was
        self.final_gram = None
        theta = self._basis_kind(Z)[1]
        # the system (r, J^T r, J^T J) at xs once evaluated there, kept while xs does not
        # move (a rejected step, a damping dropped) and taken from the trial point when
        # an undamped step (nearly always accepted) moves xs there
        system = None
        for it in range(1, max_iter + 1):  # noqa: B007  (the count is reported)
            (f, dx, _, pred, level), system = self._step(xs, p, Z, mu, system)
            progress.update(f"Gauss-Newton iteration {it}, cost {f:.6g}")
            if not np.all(np.isfinite(dx)):
                status = "Invalid_Number_Detected"
                break
            size = float(np.max(np.abs(dx))) if dx.size else 0.0
            if size <= self.step_tol:
                if mu == 0:
                    status = "Solve_Succeeded"  # the Gauss-Newton step is at rounding level
                    break
                # a damped step is small also because of its damping: judge convergence
                # on the undamped step (a stuck iteration then keeps failing, and says so)
                mu = 0.0
                continue
            xt = xs + dx
            f_new, trial = self.trial(xt, p, theta=theta, system=mu == 0)
            # below the rounding level of f (flat directions of a large-residual fit) the
            # sum of squares cannot judge a step; the gradient-based model still can
            flat = max(1e-13 * max(f, 1.0), level)
            accepted = bool(
                np.isfinite(f_new) and (f_new < f or (pred < flat and f_new <= f + flat))
            )
            # an undamped step that promises less than the rounding level of f: f cannot
            # rank it (lower or higher is rounding), the model still can.  It is taken
            # unless f finds it clearly worse (the model's correction: every solver then
            # ends at the same Gauss-Newton fixed point whatever the rounding of its
            # evaluations); once two such steps in a row no longer shrink, the steps are
            # the rounding of x itself: converged.
            unrankable = mu == 0 and pred < flat
            if accepted and unrankable and floor is not None and size >= 0.5 * floor:
                status = "Solve_Succeeded"
                break
            if accepted:
                xs, system = xt, trial
                taken += 1
                floor = size if unrankable else None
                # Nielsen's rule: relax the damping when the model predicted well
                rho = (f - f_new) / pred if pred > 0 else 0.0
                mu = mu * max(1 / 3, 1 - (2 * rho - 1) ** 3) if mu else 0.0
                f = f_new
            elif mu == 0 and pred < flat:
                # the undamped Gauss-Newton model promises less than the rounding level of
                # f: the step only measures the rounding of the residuals (their sum
                # differs in the last digits between evaluations); damping cannot help,
                # the iteration has converged.  Without this test a fit at its minimum with
                # steps just above step_tol raised the damping until max_iter, a Jacobian
                # each.  (A damped step's small promise says nothing: a large damping
                # shrinks any step, so the test is for mu = 0 only.)
                status = "Solve_Succeeded"
                break
            else:
                mu = max(2 * mu, 1e-6) if mu else 1e-6
                if mu > 1e12:
                    status = "Search_Direction_Becomes_Too_Small"
                    break
        else:
            # 1e-6 um: far below any uncertainty, not at rounding level; only for a step
            # that was taken (a rejected step can be tiny merely because it is damped)
            if size <= 1e-6 and accepted:
                status = "Solved_To_Acceptable_Level"
        x = pr.from_scaled(xs)
        ok = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level") and bool(
            np.all(np.isfinite(x))
        )
        self.steps_taken = taken
        if system is not None and theta and status == "Solve_Succeeded":
            self.final_gram = FinalGram(x, p, *system)  # the system at xs (see above)
        return SolveOutcome(x, f, status, ok, it, time.perf_counter() - t0)


def polish(
    solver: GaussNewtonSolver,
    x: np.ndarray,
    p: np.ndarray,
    fixed: np.ndarray | None = None,
    *,
    steps: int = 10,
) -> tuple[np.ndarray, int, float]:
    """A few Gauss-Newton steps from IPOPT's answer x (physical units) under the datum in
    force, with ``fixed`` variables held.

    IPOPT stops once the gradient of the whitened sum of squares is at rounding level, which
    leaves the sum of squares about 1e-7 relative above its minimum; the minimiser is then
    datum-dependent at that level.  Near the minimum Gauss-Newton converges fast, so a few
    steps bring every datum and strategy to the same minimum (1e-10 relative) for the price
    of a Jacobian each.  A step is kept only when it lowers the sum of squares.  Returns
    (x, steps taken, objective 0.5 ||r||^2 at x)."""
    out = solver.solve(x, p, fixed=fixed, max_iter=steps + 1, damping=0.0)
    if not np.all(np.isfinite(out.x)):
        return np.array(x, float), 0, float("nan")
    return out.x, solver.steps_taken, out.f
