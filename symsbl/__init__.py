"""symsbl: sparse Bayesian identification of nonlinear dynamical systems.

The public API is re-exported here; see ``__all__``.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
