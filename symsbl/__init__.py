"""symsbl: sparse Bayesian identification of nonlinear dynamical systems.

Candidate terms are CasADi expressions; the dictionary is compiled once and evaluated in chunks;
a relevance vector machine selects the terms and returns their posterior; the result is a
symbolic ODE that can be printed, saved and re-simulated. See the README for a tour.
"""

from . import systems
from .batch import identify_many
from .catalogue import Effect, catalogue
from .data import Trajectory, noise_levels, read_trajectory, write_trajectory
from .discrepancy import DiscrepancyReport, discrepancy
from .derivatives import CentralDifference, PointDifference, SavitzkyGolay, WeakForm
from .errors import DataError, LibraryError, MissingExtraError, SimulationError, SymsblError
from .evaluator import Evaluator
from .identify import fit_stats, identify, regression_stats
from .library import Library, custom, elementwise, inputs, paper, polynomial
from .model import Equation, IdentifiedModel, TermEstimate
from .progress import progress_enabled, set_progress
from .rvm import RVM, GramStats
from .signals import Chirp, FreeDecay, Multisine, Sampled, Sine
from .distributed import dask_stats, from_delayed, identify_dask
from .records import ChunkedRecord, chunked, open_npz
from .stream import identify_stream, stream_stats
from .simulate import simulate, time_grid
from .symbolic import casadi_to_sympy, symbols, sympy_to_casadi
from .system import OdeSystem
from .validate import Validation, compare_to_truth, nrmse, validate_model

__version__ = "0.1.0"

__all__ = [
    "casadi_to_sympy",
    "catalogue",
    "CentralDifference",
    "Chirp",
    "chunked",
    "ChunkedRecord",
    "compare_to_truth",
    "custom",
    "dask_stats",
    "DataError",
    "discrepancy",
    "DiscrepancyReport",
    "Effect",
    "elementwise",
    "Equation",
    "Evaluator",
    "fit_stats",
    "FreeDecay",
    "from_delayed",
    "GramStats",
    "IdentifiedModel",
    "identify",
    "identify_dask",
    "identify_many",
    "identify_stream",
    "inputs",
    "Library",
    "LibraryError",
    "MissingExtraError",
    "Multisine",
    "noise_levels",
    "nrmse",
    "OdeSystem",
    "open_npz",
    "paper",
    "PointDifference",
    "polynomial",
    "progress_enabled",
    "read_trajectory",
    "regression_stats",
    "RVM",
    "Sampled",
    "set_progress",
    "SavitzkyGolay",
    "simulate",
    "SimulationError",
    "Sine",
    "stream_stats",
    "symbols",
    "sympy_to_casadi",
    "SymsblError",
    "systems",
    "TermEstimate",
    "time_grid",
    "Trajectory",
    "validate_model",
    "Validation",
    "WeakForm",
    "write_trajectory",
    "__version__",
]
