"""volcal.cli.main layer."""
