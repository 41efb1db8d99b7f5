"""The identified model: the posterior of each term and equation, the symbolic ODE they form, and its file."""

from .estimates import Equation, FitMethod, TermEstimate
from .model import IdentifiedModel

__all__ = ["Equation", "FitMethod", "IdentifiedModel", "TermEstimate"]
