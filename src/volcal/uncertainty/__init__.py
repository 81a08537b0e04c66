"""Uncertainty: budgets of measurement and positioning uncertainty (as data).

See :mod:`volcal.uncertainty.budget` and docs/budget.md.
"""
from volcal.uncertainty.budget import (ANGLE_UNITS, LENGTH_UNITS, PAPER001_DRIFT, RATE_UNITS,
                                       Budget, DriftModel, Source, budget_from_dict,
                                       bundled_budgets, default_budget, load_budget)

__all__ = [
    "Source", "DriftModel", "Budget", "PAPER001_DRIFT", "LENGTH_UNITS", "ANGLE_UNITS",
    "RATE_UNITS", "load_budget", "budget_from_dict", "bundled_budgets", "default_budget",
]
