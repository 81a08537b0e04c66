"""volcal.base layer."""
