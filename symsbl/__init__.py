"""symsbl: sparse Bayesian identification of nonlinear dynamical systems.

Candidate terms are CasADi expressions; the dictionary is compiled once and evaluated in chunks;
a relevance vector machine selects the terms and returns their posterior; the result is a
symbolic ODE that can be printed, saved and re-simulated. See the README for a tour.
"""

from . import systems
from .data import Trajectory, read_trajectory, write_trajectory
from .derivatives import CentralDifference, PointDifference, SavitzkyGolay, WeakForm
from .errors import DataError, LibraryError, SimulationError, SymsblError
from .evaluator import Evaluator
from .identify import identify, regression_stats
from .library import Library, custom, elementwise, inputs, paper, polynomial
from .model import Equation, IdentifiedModel, TermEstimate
from .rvm import RVM, GramStats
from .signals import Chirp, FreeDecay, Multisine, Sampled, Sine
from .simulate import simulate, time_grid
from .symbolic import casadi_to_sympy, symbols, sympy_to_casadi
from .system import OdeSystem
from .validate import Validation, compare_to_truth, nrmse, validate_model

__version__ = "0.1.0"

__all__ = [
    "CentralDifference",
    "Chirp",
    "DataError",
    "Equation",
    "Evaluator",
    "FreeDecay",
    "GramStats",
    "IdentifiedModel",
    "Library",
    "LibraryError",
    "Multisine",
    "OdeSystem",
    "PointDifference",
    "RVM",
    "Sampled",
    "SavitzkyGolay",
    "SimulationError",
    "Sine",
    "SymsblError",
    "TermEstimate",
    "Trajectory",
    "Validation",
    "WeakForm",
    "__version__",
    "casadi_to_sympy",
    "compare_to_truth",
    "custom",
    "elementwise",
    "identify",
    "inputs",
    "nrmse",
    "paper",
    "polynomial",
    "read_trajectory",
    "regression_stats",
    "simulate",
    "symbols",
    "sympy_to_casadi",
    "systems",
    "time_grid",
    "validate_model",
    "write_trajectory",
]
