"""volcal.measurement layer."""
