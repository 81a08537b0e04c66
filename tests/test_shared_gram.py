"""Invariant: the covariance at the answer taken from the solver's last Gauss-Newton system
is the covariance of the Jacobian there.

The last iteration of a Gauss-Newton solve (``solver="gauss-newton"``, or IPOPT's polish)
evaluates J^T J at the answer to find that the step is at its tolerance; identify takes the
covariance from that matrix (:func:`volcal.analysis.covariance.gram_covariance`) instead of
a second pass over the readings for an R factor.  The reference is computed here from
scratch: the whole-graph CasADi Jacobian at the answer (not the chunked sums the solver
used), a plain numpy QR of it and the constrained inverse written out with numpy, on
readings of the independent rigid-body simulator (tests/indep_sim.py).
"""

from __future__ import annotations

import numpy as np
import pytest

import indep_sim as ind
import volcal.analysis.identify as idf
from volcal.analysis.covariance import constrained_covariance, gram_covariance
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine


def _data():
    geom = ind.load_geometry("mcv754_wxyzt")
    plan = ind.grid(geom, {a.name: 3 for a in geom.axes})
    tools = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0]])
    truth = ind.draw_truth(geom, np.random.default_rng(2), "nonrep")
    sim = ind.simulate(geom, truth, plan, tools, np.random.default_rng(4), n_stations=4)
    machine = Machine.from_model("mcv754_wxyzt")
    return machine, ErrorModel(machine.spec, default=ErrorForm("poly", 2)), sim.measurements


def _reference(ider, x, p, fixed):
    """Z (Z^T R^T R Z)^-1 Z^T in physical units from a numpy QR of the whole-graph J."""
    pr = ider.problem
    _, J = ider.jacobian(x, p)
    R = np.linalg.qr(np.array(J), mode="r")
    free = np.flatnonzero(~fixed)
    C = ider._scaled_constraints()[:, free]
    C = C[np.linalg.norm(C, axis=1) > 0]
    _, s, Vt = np.linalg.svd(C)
    Z = Vt[int(np.sum(s > 1e-12 * s[0])) :].T if len(C) else np.eye(len(free))
    Rz = R[:, free] @ Z
    cov_s = Z @ np.linalg.inv(Rz.T @ Rz) @ Z.T
    cov = np.full((pr.n_x, pr.n_x), np.nan)
    cov[np.ix_(free, free)] = cov_s
    return cov * pr.scale[:, None] * pr.scale[None, :]


@pytest.mark.parametrize("solver", ["gauss-newton", "ipopt"])
def test_covariance_from_the_last_gauss_newton_system_is_the_jacobians(monkeypatch, solver):
    machine, em, meas = _data()
    seen = []
    covariance = idf.Identifier.covariance

    def spy(self, x, p, fixed):
        final = self.gauss_newton.final_gram
        seen.append((self, x.copy(), p, fixed.copy(), final is not None and final.matches(x, p)))
        return covariance(self, x, p, fixed)

    monkeypatch.setattr(idf.Identifier, "covariance", spy)
    res = idf.identify(machine, meas, error_model=em, solver=solver)
    assert res.success
    ((ider, x, p, fixed, shared),) = seen
    assert shared  # the solver's last system was at the answer: no second pass was made
    nt = ider.problem.n_theta
    ref = _reference(ider, x, p, fixed)[:nt, :nt]
    imposed = np.all(res.cov_theta == 0, axis=0)  # set to exactly 0 by the datum
    ref[imposed] = ref[:, imposed] = 0.0
    scale = np.nanmax(np.abs(ref))
    assert np.array_equal(np.isnan(ref), np.isnan(res.cov_theta))
    assert np.nanmax(np.abs(res.cov_theta - ref)) <= 1e-9 * scale

    # without the shared system (the R factor of the chunked evaluation): the same
    monkeypatch.setattr(idf, "gram_covariance", lambda *a, **k: None)
    seen.clear()
    again = idf.identify(machine, meas, error_model=em, solver=solver)
    assert np.nanmax(np.abs(again.cov_theta - res.cov_theta)) <= 1e-9 * scale


def test_the_gram_is_inverted_only_while_it_is_well_conditioned():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(200, 8)) * np.logspace(-2, 3, 8)  # badly scaled columns
    C = np.zeros((1, 8))
    C[0, [1, 4]] = 1.0, -2.0
    fixed = np.zeros(8, bool)
    fixed[6] = True
    ref = constrained_covariance(J, C, fixed=fixed)
    got = gram_covariance(J.T @ J, C, fixed=fixed)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    assert np.nanmax(np.abs(got - ref)) <= 1e-12 * np.nanmax(np.abs(ref))
    # a nearly dependent column: the Gram's rounding would show, the caller takes R
    J[:, 3] = J[:, 2] * (1e-3 / 1e-2) + 1e-5 * rng.normal(size=200)
    assert gram_covariance(J.T @ J, C, fixed=fixed) is None
    # an exactly null direction left free
    assert gram_covariance(np.diag([1.0, 2.0, 0.0])) is None
