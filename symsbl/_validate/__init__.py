"""Re-simulation and validation of an identified model, and comparison with a known system."""
