"""symsbl: sparse Bayesian identification of nonlinear dynamical systems.

Candidate terms are CasADi expressions; the dictionary is compiled once and evaluated in chunks;
a relevance vector machine selects the terms and returns their posterior; the result is a
symbolic ODE that can be printed, saved and re-simulated. See the README for a tour.

This module is the package's one public surface, listed in the order data flows through it.
Everything lives in private modules (``symsbl._name``) or private subpackages behind it; the
only public modules are :mod:`symsbl.systems` (ready-made systems) and :mod:`symsbl.plots`
(figures, optional matplotlib).
"""

from ._base import interrupt as _interrupt  # noqa: F401  first: Ctrl-C while the symsbl command imports is one line, not a traceback

from importlib import metadata as _metadata
from . import systems

# -- errors ----------------------------------------------------------------------------------
from ._base.errors import (
    DataError,
    DivergenceError,
    ExpressionError,
    LibraryError,
    MissingExtraError,
    ParameterError,
    RefineWarning,
    SimulationError,
    SymsblError,
)

# -- the selection rule: which terms are kept, at every stage ------------------------------------
from ._base.rule import SelectionRule

# -- symbolic terms and candidate libraries ----------------------------------------------------
from ._symbolic.symbols import casadi_to_sympy, symbols, sympy_to_casadi
from ._symbolic.library import Library, Term
from ._symbolic.terms import custom, elementwise, inputs, paper, polynomial

# -- compiled evaluation of a library ----------------------------------------------------------
from ._symbolic.evaluator import Evaluator

# -- data: trajectories, files, noise ---------------------------------------------------------
from ._data.trajectory import Trajectory, noise_levels
from ._data.io import read_trajectory, write_trajectory

# -- systems, forcing signals and simulation ---------------------------------------------------
from ._simulation.ode import OdeSystem
from ._simulation.signals import Chirp, FreeDecay, Multisine, Sampled, Signal, Sine
from ._simulation.simulate import simulate, time_grid

# -- derivatives: regression rows from sampled states -------------------------------------------
from ._derivatives.differentiator import Differentiator, Stencil
from ._derivatives.differences import CentralDifference, PointDifference, SavitzkyGolay
from ._derivatives.weakform import WeakForm

# -- the identified model and its observation model (what each measured channel is) -------------
from ._model import Equation, FitMethod, IdentifiedModel, ModelPath, PathEntry, TermEstimate
from ._model import AccelerationOutput, AlgebraicOutput, Output, StateOutput

# -- sparse Bayesian regression (equation error) -----------------------------------------------
from ._regression.gram import GramStats
from ._regression.rvm import RVM
from ._regression.rows import RegressionStats, regression_stats
from ._regression.fit import fit_stats

# -- output-error refinement: fit the trajectories -----------------------------------------------
from ._refine import RefineOptions, refine

# -- re-simulation and validation ----------------------------------------------------------
from ._validate.validate import Validation, nrmse, validate_model
from ._validate.truth import TruthComparison, compare_to_truth

# -- identification: equation error, then output error (the main entry point) ------------------
from ._identify import identify

# -- discrepancy workflow: what is the model missing? ------------------------------------------
from ._discrepancy import (
    CATALOGUE,
    Decision,
    DecisionRule,
    Disagreement,
    DiscrepancyReport,
    DiscrepancyStep,
    Effect,
    EffectScore,
    Variant,
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
from ._base.progress import progress_enabled, set_progress

try:  # the one version source is the installed distribution's metadata (pyproject.toml)
    __version__ = _metadata.version("symsbl")
except _metadata.PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = [
    # errors
    "SymsblError",
    "DataError",
    "LibraryError",
    "ExpressionError",
    "SimulationError",
    "DivergenceError",
    "ParameterError",
    "MissingExtraError",
    "RefineWarning",
    # symbolic terms and libraries
    "symbols",
    "casadi_to_sympy",
    "sympy_to_casadi",
    "Term",
    "Library",
    "polynomial",
    "elementwise",
    "inputs",
    "custom",
    "paper",
    # evaluation
    "Evaluator",
    # systems and simulation
    "systems",
    "OdeSystem",
    "Signal",
    "Sine",
    "Multisine",
    "Chirp",
    "FreeDecay",
    "Sampled",
    "simulate",
    "time_grid",
    # data
    "Trajectory",
    "noise_levels",
    "read_trajectory",
    "write_trajectory",
    # derivatives
    "Differentiator",
    "Stencil",
    "PointDifference",
    "CentralDifference",
    "SavitzkyGolay",
    "WeakForm",
    # the selection rule
    "SelectionRule",
    # regression and identification
    "GramStats",
    "RVM",
    "RegressionStats",
    "regression_stats",
    "fit_stats",
    "identify",
    "RefineOptions",
    "refine",
    # the model
    "TermEstimate",
    "Equation",
    "IdentifiedModel",
    "FitMethod",
    "ModelPath",
    "PathEntry",
    "Output",
    "StateOutput",
    "AccelerationOutput",
    "AlgebraicOutput",
    # validation
    "Validation",
    "validate_model",
    "nrmse",
    "TruthComparison",
    "compare_to_truth",
    # discrepancy
    "Effect",
    "Variant",
    "CATALOGUE",
    "catalogue",
    "parse_base",
    "position_record",
    "Decision",
    "DecisionRule",
    "Disagreement",
    "EffectScore",
    "DiscrepancyStep",
    "DiscrepancyReport",
    "discrepancy",
    # scale-out
    "ChunkedRecord",
    "chunked",
    "open_npz",
    "stream_stats",
    "identify_stream",
    "identify_many",
    "dask_stats",
    "identify_dask",
    "from_delayed",
    # demo
    "run_demo",
    "DemoResult",
    # progress
    "set_progress",
    "progress_enabled",
    "__version__",
]
