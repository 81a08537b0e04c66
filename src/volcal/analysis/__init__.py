"""Identifiability and covariance of an identification problem."""
from volcal.analysis.identifiability import Identifiability, analyse_jacobian
from volcal.analysis.covariance import constrained_covariance

__all__ = ["Identifiability", "analyse_jacobian", "constrained_covariance"]
