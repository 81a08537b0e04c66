"""Invariant: every solver gives the same minimiser.

IPOPT (the default of ``identify``, followed by its Gauss-Newton polish) and the
Gauss-Newton / Levenberg-Marquardt solver with the datum eliminated
(:mod:`volcal.solve.gauss_newton`) solve the same problem from the same residual Function;
on every bundled model their estimates agree to 1e-9 relative.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_identify import simulated
from volcal.analysis.identify import Identifier, identify
from volcal.measurement.tables import load_measurements
from volcal.problem.residuals import Layout
from volcal.solve.gauss_newton import feasible_basis, project_feasible

MODELS = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "models").glob("*.toml"))


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(a)), 1e-300))


@pytest.mark.parametrize("model", MODELS)
def test_ipopt_and_gauss_newton_reach_the_same_minimiser(model):
    five = model in ("trunnion_ac", "head_bc")
    machine, em, _, sim = simulated(model, grid=2 if five else 3)
    strategies = ["joint"] if five else ["joint", "two-phase"]
    for strategy in strategies:
        a = identify(machine, sim.measurements, error_model=em, strategy=strategy)
        b = identify(machine, sim.measurements, error_model=em, strategy=strategy,
                     solver="gauss-newton")
        assert a.success and b.success, (a.status, b.status)
        assert b.outcomes[-1].status == "Solve_Succeeded", b.outcomes[-1].status
        assert _rel(a.theta, b.theta) < 1e-9, (model, strategy, _rel(a.theta, b.theta))
        st = ["x_mm", "y_mm", "z_mm", "dead_length_mm"]
        assert _rel(a.stations[st].to_numpy(), b.stations[st].to_numpy()) < 1e-9
        ca_, cb = a.conditions["chi2_per_dof"], b.conditions["chi2_per_dof"]
        assert abs(ca_ / cb - 1) < 1e-9


def test_gauss_newton_steps_keep_the_datum_and_the_held_variables():
    machine, em, _, sim = simulated("mcv754_wxyzt", grid=3)
    meas = load_measurements(sim.measurements, machine.spec)
    ider = Identifier(machine, em, Layout.from_measurements(meas), solver="gauss-newton")
    pr = ider.problem
    rng = np.random.default_rng(0)
    fixed = np.zeros(pr.n_x, bool)
    fixed[rng.choice(pr.n_theta, 5, replace=False)] = True
    Z = feasible_basis(pr, fixed)
    assert np.all(Z[fixed] == 0)
    C = pr.C * pr.scale[None, :pr.n_theta]
    assert np.max(np.abs(C @ Z[:pr.n_theta])) < 1e-12
    xs = project_feasible(pr, rng.normal(size=pr.n_x), fixed)
    assert np.max(np.abs(C @ xs[:pr.n_theta])) < 1e-10


@pytest.mark.parametrize(
    "model,instrument",
    [(m, "tracker") for m in MODELS] + [("mcv754_wxyzt", "multilaser")],
)
def test_dense_jacobian_is_the_problems_jacobian(model, instrument):
    """The identification assembles J in numpy from its factors (d(point)/d(theta) per pose,
    d(r)/d(point, station, globals) per reading) instead of through CasADi's sparse product:
    it must equal the CasADi Function's J and the central differences of the residual."""
    from volcal.measurement.instruments import get_instrument
    from volcal.problem.residuals import DenseJacobian

    five = model in ("trunnion_ac", "head_bc")
    machine, em, _, sim = simulated(model, grid=2 if five else 3)
    meas = load_measurements(sim.measurements, machine.spec)
    ider = Identifier(machine, em, Layout.from_measurements(meas),
                      instrument=get_instrument(instrument))
    pr = ider.problem
    rng = np.random.default_rng(3)
    xs = rng.normal(size=pr.n_x)
    # stations about 1.5 m away (scaled units of 1 um) so that every length is well defined
    n_ps = pr.instrument.n_station_params
    for k in range(len(meas.station_ids)):
        xs[pr.n_theta + n_ps * k: pr.n_theta + n_ps * k + 3] += 1.5e6 * rng.uniform(-1, 1, 3)
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, 1.0 / meas.sigma
                     if np.isfinite(meas.sigma).all() else np.ones(len(meas)))
    r_np, J_np = DenseJacobian(pr)(xs, p)
    r_ca, J_ca = (np.asarray(v.full()) for v in pr.jacobian(xs, p))
    assert np.allclose(r_np, r_ca.ravel(), rtol=0, atol=1e-12 * max(1.0, np.abs(r_ca).max()))
    scale = np.abs(J_ca).max()
    assert np.max(np.abs(J_np - J_ca)) <= 1e-12 * scale
    # and against central differences of the residual Function, 12 random columns
    cols = rng.choice(pr.n_x, 12, replace=False)
    for j in cols:
        h = np.zeros(pr.n_x)
        h[j] = 1e-3
        fd = (np.asarray(pr.residual(xs + h, p)) - np.asarray(pr.residual(xs - h, p))).ravel()
        assert np.max(np.abs(fd / 2e-3 - J_np[:, j])) <= 1e-6 * max(scale, 1.0), (model, j)
    # the R factor the analyses use, accumulated station by station in blocks of a few
    # readings without forming J: the same J^T J and singular values as CasADi's J
    r_f, R = DenseJacobian(pr).r_factor(xs, p, block_rows=7)
    assert R.shape == (pr.n_x, pr.n_x) and np.all(np.tril(R, -1) == 0)
    assert np.array_equal(r_f, r_np)
    gram = J_ca.T @ J_ca
    assert np.max(np.abs(R.T @ R - gram)) <= 1e-12 * np.abs(gram).max()
    s_ref = np.linalg.svd(J_ca, compute_uv=False)
    assert np.max(np.abs(np.linalg.svd(R, compute_uv=False) - s_ref)) <= 1e-12 * s_ref[0]


def test_gauss_newton_stops_where_the_sum_of_squares_is_at_its_rounding_level(monkeypatch):
    """At the minimum the polish's steps are at the rounding level of f, and a second
    evaluation of f (summed in another order) can judge such a step worse by more than
    that level.  That is convergence, not a reason to raise the damping: the polish stops
    after its first useful step.  (It used to raise the damping until its step limit, a
    Jacobian each: 0.45 s of a 5-axis identification with 7,896 readings.)  The estimate
    is the one of an exact evaluation of f, to 1e-9."""
    from volcal.solve.gauss_newton import GaussNewtonSolver

    machine, em, _, sim = simulated("mcv754_wxyzt", grid=3)
    exact = identify(machine, sim.measurements, error_model=em)
    trial = GaussNewtonSolver.trial

    def rounded(self, xs, p, **kwargs):  # f as another summation order may give it: 1e-11 above
        f, system = trial(self, xs, p, **kwargs)
        return f * (1 + 1e-11), system

    init = GaussNewtonSolver.__init__

    def rounding_level_steps(self, *args, **kwargs):
        # as on the 5-axis example: steps at the rounding level above the step tolerance
        init(self, *args, **kwargs)
        self.step_tol = 0.0

    monkeypatch.setattr(GaussNewtonSolver, "trial", rounded)
    monkeypatch.setattr(GaussNewtonSolver, "__init__", rounding_level_steps)
    res = identify(machine, sim.measurements, error_model=em)
    out = res.outcomes[-1]
    assert res.success and out.polish_steps <= 2, out.polish_steps
    assert _rel(exact.theta, res.theta) < 1e-9


def test_gauss_newton_never_calls_a_step_it_cannot_take_convergence(monkeypatch):
    """From the start values, far from the minimum, with every trial step judged worse
    (here: f cannot be evaluated there), the damping grows until the steps are tiny and
    promise almost nothing; that is a failure to say, neither convergence at the rounding
    level of f nor a solution "to an acceptable level" (both were reported before)."""
    from volcal.base.exceptions import SolverError
    from volcal.solve.gauss_newton import GaussNewtonSolver

    machine, em, _, sim = simulated("mcv754_wxyzt", grid=3)
    monkeypatch.setattr(GaussNewtonSolver, "trial", lambda self, xs, p, **kw: (float("nan"), None))
    with pytest.raises(SolverError, match="Search_Direction|Maximum_Iterations"):
        identify(machine, sim.measurements, error_model=em, solver="gauss-newton")
