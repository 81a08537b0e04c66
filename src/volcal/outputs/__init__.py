"""volcal.base.folders layer."""
