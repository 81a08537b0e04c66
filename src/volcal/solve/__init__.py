"""volcal.solve.ipopt layer."""
