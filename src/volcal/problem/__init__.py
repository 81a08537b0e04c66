"""volcal.problem.residuals layer."""
