"""Measurement planning: station placement and pose selection that minimise the predicted
uncertainty (paper 004 and beyond).  See :func:`volcal.analysis.planning.plan.plan`."""

from volcal.analysis.planning.evaluator import CRITERIA, PlanEvaluator
from volcal.analysis.planning.geometry import (
    Constraints,
    Obstacle,
    Reflector,
    Region,
    constraints_from_dict,
    reading_violations,
)
from volcal.analysis.planning.plan import OPTIMIZERS, PlanResult, plan

__all__ = [
    "plan",
    "PlanResult",
    "PlanEvaluator",
    "CRITERIA",
    "OPTIMIZERS",
    "Constraints",
    "Region",
    "Obstacle",
    "Reflector",
    "constraints_from_dict",
    "reading_violations",
]
