"""volcal.model layer."""
