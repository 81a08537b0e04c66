"""The candidate fits of ``degree="auto"`` on one problem (volcal.analysis.nested) against
full identifications of each candidate model built alone.

Data from the independent simulator (tests/indep_sim.py: exact transforms, a truth of sums
of sines, steps and tables, not volcal's bases, that violates the datum).  The reference of
each candidate is ``volcal.identify`` with that error model: its own problem, IPOPT and
the polish, its own datum selection and rank on the tall Jacobian.  The candidate path must
give the same chi2 (the same minimum) and the same rank k (the same BIC), and so the same
choice."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import indep_sim as ind
from volcal.model.machine import Machine
from volcal.workflow import identify
from volcal.workflow.orders import _nested_fits, axis_orders, select_orders, with_orders


@functools.cache
def _case():
    geom = ind.load_geometry("xfyz")
    rng = np.random.default_rng(12)
    truth = ind.draw_truth(geom, rng, "nonrep")
    plan = np.vstack([ind.grid(geom, {"X": 9, "Y": 3, "Z": 2}), ind.diagonals(geom, 6)])
    sim = ind.simulate(geom, truth, plan, np.zeros((1, 3)), rng, n_stations=4)
    machine = Machine.from_model("xfyz")
    res = select_orders(
        machine, sim.measurements, sim.stations_start, candidates={"poly": (1, 3, 5)}
    )
    return machine, sim, res


@pytest.mark.filterwarnings("ignore:.*tool offset")
def test_candidates_on_one_problem_match_full_fits():
    machine, sim, res = _case()
    sel = res.order_selection
    assert any("one problem of the largest orders" in n for n in res.notes), res.notes
    assert (sel["status"] == "Solve_Succeeded").all()
    # the selection is not trivial: the orders change the fit
    assert sel["chi2"].max() > 1.05 * sel["chi2"].min()
    em0 = res.error_model
    kinds = axis_orders(em0)
    rows = sel.drop_duplicates("orders")
    # the lowest X order and the model of the most parameters (with a direction the data
    # hardly see: its rank is the subtle one); the chosen model below
    picked = [rows[rows["axis"] == "X"].iloc[0], rows.loc[rows["n_params"].idxmax()]]
    for row in picked:
        orders = {a: int(t.split(":")[1]) for a, t in zip(kinds, row["orders"].split())}
        full = identify(
            machine, sim.measurements, sim.stations_start, error_model=with_orders(em0, orders)
        )
        chi2 = float(np.sum(full.residuals["normalised_residual"].to_numpy(float) ** 2))
        assert row["chi2"] == pytest.approx(chi2, rel=1e-7), row["orders"]
        assert row["k"] == full.identifiability.rank, row["orders"]
    # the chosen model was identified in full (IPOPT, its own problem): the result is that
    # fit, with its own rank
    chosen = rows[rows["chosen"]].iloc[0]
    got = float(np.sum(res.residuals["normalised_residual"].to_numpy(float) ** 2))
    assert got == pytest.approx(chosen["chi2"], rel=1e-7)
    assert chosen["k"] == res.identifiability.rank
    assert res.success
    ok = res.identifiable
    assert np.isfinite(res.cov_theta[np.ix_(ok, ok)]).all()  # with its covariance


def test_candidates_that_are_not_nested_keep_full_fits():
    """B-splines (not nested), phased strategies, robust rejection, the impose-all datum
    and other instruments: no shared problem (nothing is built)."""
    for kinds, opts in (
        ({"X": "bspline"}, {}),
        ({"X": "poly"}, {"strategy": "two-phase"}),
        ({"X": "poly"}, {"robust": True}),
        ({"X": "poly"}, {"datum_mode": "impose-all"}),
        ({"X": "poly"}, {"instrument": "multilaser"}),
    ):
        assert _nested_fits(None, None, None, None, {}, kinds, "iso230", opts) is None, opts


@pytest.mark.filterwarnings("ignore:.*tool offset")
def test_a_model_that_is_not_nested_is_refused():
    from volcal.base.exceptions import InputError
    from volcal.measurement.tables import load_measurements, load_stations
    from volcal.model.errors import ErrorForm, ErrorModel

    machine, sim, _ = _case()
    st = load_stations(sim.stations_start)
    meas = load_measurements(sim.measurements, machine.spec, stations=st)
    em0 = ErrorModel(machine.spec, default=ErrorForm("poly", 3))
    kinds = {a: "poly" for a in axis_orders(em0)}
    nested = _nested_fits(
        machine, meas, st, em0, {a: [1, 3] for a in kinds}, kinds, "iso230", {}
    )
    lower = nested.columns(with_orders(em0, {"X": 1}))
    assert (~lower).sum() == 2 * 6  # Legendre P2, P3 of X's six motions held
    spline = ErrorModel(
        machine.spec, {"X": ErrorForm("bspline", segments=1)}, default=ErrorForm("poly", 3)
    )
    for em in (spline, with_orders(em0, {"X": 5})):  # not nested / above the largest
        with pytest.raises(InputError, match="not nested"):
            nested.columns(em)
