"""Regression rows from sampled states: the differentiator contract and its stencils (point, central,
Savitzky-Golay), the weak form, the registry of names, and position-velocity pairs (kinematics)."""
