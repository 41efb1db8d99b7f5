"""symsbl: sparse Bayesian identification of nonlinear dynamical systems.

Candidate terms are CasADi expressions; the dictionary is compiled once and evaluated in chunks;
a relevance vector machine selects the terms and returns their posterior; the result is a
symbolic ODE that can be printed, saved and re-simulated. See the README for a tour.

This module is the package's one public surface, listed in the order data flows through it.
Everything lives in private modules (``symsbl._name``) or private subpackages behind it; the
only public modules are :mod:`symsbl.systems` (ready-made systems) and :mod:`symsbl.plots`
(figures, optional matplotlib).
"""

from . import _interrupt  # first: Ctrl-C while the symsbl command is still importing is one line, not a traceback
from . import systems

# -- errors ----------------------------------------------------------------------------------
from ._errors import (
    DataError,
    DivergenceError,
    ExpressionError,
    LibraryError,
    MissingExtraError,
    RefineWarning,
    ParameterError,
    SimulationError,
    SymsblError,
)

# -- symbolic terms and candidate libraries ----------------------------------------------------
from ._symbolic import casadi_to_sympy, symbols, sympy_to_casadi
from ._library import Library, Term
from ._terms import custom, elementwise, inputs, paper, polynomial

# -- compiled evaluation of a library ----------------------------------------------------------
from ._evaluator import Evaluator

# -- systems, forcing signals and simulation ---------------------------------------------------
from ._ode import OdeSystem
from ._signals import Chirp, FreeDecay, Multisine, Sampled, Signal, Sine
from ._simulate import simulate, time_grid

# -- data: trajectories, files, noise ---------------------------------------------------------
from ._trajectory import Trajectory, noise_levels
from ._io import read_trajectory, write_trajectory

# -- derivatives: regression rows from sampled states -------------------------------------------
from ._differentiator import Differentiator, Stencil
from ._differences import CentralDifference, PointDifference, SavitzkyGolay
from ._weakform import WeakForm

# -- sparse Bayesian regression (equation error) -----------------------------------------------
from ._gram import GramStats
from ._rvm import RVM
from ._regression import RegressionStats, regression_stats
from ._identify import fit_stats, identify

# -- output-error refinement: fit the trajectories -----------------------------------------------
from ._refine import refine

# -- the identified model --------------------------------------------------------------------
from ._model import Equation, FitMethod, IdentifiedModel, TermEstimate

# -- re-simulation and validation ----------------------------------------------------------
from ._validate import Validation, nrmse, validate_model
from ._truth import TruthComparison, compare_to_truth

# -- discrepancy workflow: what is the model missing? ------------------------------------------
from ._discrepancy import (
    CATALOGUE,
    Variant,
    Decision,
    DecisionRule,
    Disagreement,
    DiscrepancyReport,
    DiscrepancyStep,
    Effect,
    EffectScore,
    catalogue,
    discrepancy,
    parse_base,
    position_record,
)

# -- scale-out: long records, batches, Dask ----------------------------------------------------
from ._scale import (
    ChunkedRecord,
    chunked,
    dask_stats,
    from_delayed,
    identify_dask,
    identify_many,
    identify_stream,
    open_npz,
    stream_stats,
)

# -- the paper's five systems end to end (``symsbl demo``) --------------------------------------
from ._demo import DemoResult, run_demo

# -- progress lines --------------------------------------------------------------------------
from ._progress import progress_enabled, set_progress

__version__ = "0.2.0"

__all__ = [
    # errors
    "SymsblError", "DataError", "LibraryError", "ExpressionError", "SimulationError", "DivergenceError",
    "ParameterError", "MissingExtraError", "RefineWarning",
    # symbolic terms and libraries
    "symbols", "casadi_to_sympy", "sympy_to_casadi", "Term", "Library", "polynomial", "elementwise", "inputs",
    "custom", "paper",
    # evaluation
    "Evaluator",
    # systems and simulation
    "systems", "OdeSystem", "Signal", "Sine", "Multisine", "Chirp", "FreeDecay", "Sampled", "simulate", "time_grid",
    # data
    "Trajectory", "noise_levels", "read_trajectory", "write_trajectory",
    # derivatives
    "Differentiator", "Stencil", "PointDifference", "CentralDifference", "SavitzkyGolay", "WeakForm",
    # regression and identification
    "GramStats", "RVM", "RegressionStats", "regression_stats", "fit_stats", "identify", "refine",
    # the model
    "TermEstimate", "Equation", "IdentifiedModel", "FitMethod",
    # validation
    "Validation", "validate_model", "nrmse", "TruthComparison", "compare_to_truth",
    # discrepancy
    "Effect", "Variant", "CATALOGUE", "catalogue", "parse_base", "position_record", "Decision", "DecisionRule",
    "Disagreement", "EffectScore", "DiscrepancyStep", "DiscrepancyReport", "discrepancy",
    # scale-out
    "ChunkedRecord", "chunked", "open_npz", "stream_stats", "identify_stream", "identify_many", "dask_stats",
    "identify_dask", "from_delayed",
    # demo
    "run_demo", "DemoResult",
    # progress
    "set_progress", "progress_enabled",
    "__version__",
]
