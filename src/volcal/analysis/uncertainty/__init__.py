"""Uncertainty of an identification: the structured least-squares engine, Monte Carlo
(GUM Supplement 1), its sampling, parallel execution and coverage studies."""
