"""Sparse Bayesian regression (equation error): sufficient statistics, the Tipping-Faul core, the
:class:`~symsbl.RVM` estimator, the regression rows of a library on records, and the support search."""
