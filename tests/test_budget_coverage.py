"""A budget that does not cover the model's axes is said once per run.

The bundled ``paper002`` budget is a 3-axis machine's: on a 5-axis model its rotary axes
have no positioning repeatability.  ``simulate``, ``identify`` and the Monte Carlo each
use the budget; together they warn once, naming the axes, and not at all with a budget
that has a term for every axis (rotary ones in arcsec).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from volcal.analysis.identify import identify
from volcal.analysis.uncertainty.montecarlo import monte_carlo
from volcal.measurement.budget import Budget, BudgetWarning, Source, load_budget
from volcal.measurement.plans import default_stations, grid_plan
from volcal.measurement.simulate import draw_true_parameters, simulate
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine

TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0]])


def _covering() -> Budget:
    """paper002 with a repeatability for A and C (half-widths in arcsec)."""
    b = load_budget("paper002")
    rot = tuple(
        Source(f"repeatability_{a}", 2.0, "arcsec", "rectangular", f"axis:{a}") for a in "AC"
    )
    return Budget("covering", b.sources + rot)


def _run(budget):
    """simulate -> identify -> a small Monte Carlo, with every warning recorded."""
    machine = Machine.from_model("trunnion_ac")
    em = ErrorModel(machine.spec, default=None)
    theta = draw_true_parameters(machine, em, np.random.default_rng(3), 20.0)
    plan = grid_plan(machine.spec, {"C": 4, "A": 2, "X": 2, "Y": 2, "Z": 2})
    stations = default_stations(machine.spec, 4, seed=3, tools=TOOLS)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")  # Python's own: each warning once per place
        sim = simulate(machine, em, theta, stations, plan, TOOLS, budget, 3)
        meas = sim.measurements.drop(columns=["sigma"], errors="ignore")
        identify(machine, meas, error_model=em, budget=budget)
        monte_carlo(machine, meas, error_model=em, budget=budget, trials=4, workers=1)
    return [str(w.message) for w in caught if issubclass(w.category, BudgetWarning)]


def test_the_default_budget_on_a_5_axis_model_warns_once_naming_the_rotary_axes():
    said = _run("paper002")
    assert len(said) == 1, said
    assert "axes C, A (rotary)" in said[0] and "'paper002'" in said[0]
    assert "arcsec" in said[0] and "--budget" in said[0]


def test_a_budget_with_every_axis_says_nothing():
    assert _run(_covering()) == []
    spec = Machine.from_model("trunnion_ac").spec
    assert _covering().axes_without_term(spec) == []
    assert load_budget("paper002").axes_without_term(spec) == ["C", "A"]


@pytest.mark.parametrize("model", ["mcv754_wxyzt", "xfyz"])
def test_the_default_budget_covers_the_3_axis_models(model):
    spec = Machine.from_model(model).spec
    assert load_budget("paper002").coverage_message(spec) is None
