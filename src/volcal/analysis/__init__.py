"""Identifiability and covariance of an identification problem."""

from volcal.analysis.covariance import constrained_covariance
from volcal.analysis.identifiability import (
    FieldNullSpace,
    FieldSets,
    Identifiability,
    analyse_jacobian,
    field_null_space,
    rigid_columns,
    split_gauge,
)

__all__ = [
    "FieldNullSpace",
    "FieldSets",
    "Identifiability",
    "analyse_jacobian",
    "constrained_covariance",
    "field_null_space",
    "rigid_columns",
    "split_gauge",
]
