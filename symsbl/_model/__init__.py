"""The identified model: the posterior of each term and equation, the symbolic ODE they form, and its file."""

from .estimates import Equation, FitMethod, TermEstimate
from .model import IdentifiedModel
from .outputs import AccelerationOutput, AlgebraicOutput, Output, StateOutput
from .path import ModelPath, PathEntry

__all__ = [
    "Equation",
    "FitMethod",
    "IdentifiedModel",
    "ModelPath",
    "PathEntry",
    "TermEstimate",
    "Output",
    "StateOutput",
    "AccelerationOutput",
    "AlgebraicOutput",
]
