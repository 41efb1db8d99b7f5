"""Identification: trajectories x library -> :class:`~symsbl._model.IdentifiedModel`.

1. :func:`~symsbl._regression.regression_stats` reduces the records to the sufficient statistics of
   the regression of the state derivatives on the library (one Gram shared by every equation);
2. one :class:`~symsbl._rvm.RVM` per state equation is fitted from the shared statistics;
3. an evidence-guided search improves each support and near-equivalent candidates are resolved
   by parsimony (:mod:`symsbl._selection`): the equation-error model;
4. by default the output-error refinement (:func:`symsbl.refine`) re-estimates every coefficient
   from the simulation error of the measured states and selects terms on its evidence.

The model is expressed in the data's physical units: a term ``sin(x1)`` is the sine of the
measured ``x1``. Columns are normalised only inside the RVM.
"""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np

from ._checks import number
from ._errors import ParameterError, expected
from ._library import Library
from ._model import Equation, IdentifiedModel
from ._progress import Progress
from ._kinematics import complete_states, latent_states, parse_kinematics
from ._latent import identify_latent
from ._regression import RegressionStats, as_trajectories, regression_stats
from ._rvm import RVM
from ._selection import complexity, fit_rvm, search_support

__all__ = ["identify", "fit_stats"]


def identify(
    data,
    library: Library,
    *,
    derivative="weak",
    rvm: RVM | None = None,
    chunk_size: int = 4096,
    jit="auto",
    equivalence_nats: float = 2.0,
    states=None,
    kinematics=None,
    refine: bool = True,
    refine_options: dict | None = None,
) -> IdentifiedModel:
    """Identify one sparse ODE per state from sampled trajectories.

    Parameters
    ----------
    data : Trajectory or list of Trajectory
        Measured or simulated states and inputs. Every state gets an equation; kinematic ones
        (``x1' = x2``) are found, not assumed, unless declared in ``kinematics``.
    library : Library
        Candidate terms, e.g. :func:`symsbl.paper`.
    derivative : str or derivative strategy
        How the targets are built: ``"weak"`` (default; integral form on non-overlapping
        windows), ``"central"``, ``"point"`` (the paper's), ``"savgol"``.
    rvm : RVM, optional
        Template estimator (options are copied; it is not modified). Default ``RVM()``.
    chunk_size : int
        Rows per chunk in the dictionary evaluation.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.
    equivalence_nats : float
        Near-equivalent candidates: a kept term is swapped for a simpler candidate (see
        :func:`complexity`) when the swap costs less than this many nats of log evidence, and
        every candidate within this margin is reported as indistinguishable. At 16 mm of
        displacement ``x1``, ``sin(x1)`` and ``tan(x1)`` differ by parts in 10^4 and the
        evidence cannot separate them; parsimony then keeps ``x1``.
    states : sequence of str, optional
        The model's states, in order (default: the data's). A state absent from the data is
        unmeasured: the velocity of a pair in ``kinematics``, or else *latent*, a state with its own
        law that no record holds (the hysteretic force of a Bouc-Wen oscillator). A latent state is
        identified for one position-velocity pair, one input and one record, best of whole periods
        of a periodic input (see :mod:`symsbl._latent`): ``metadata["latent"]`` then gives the verdict
        ("hidden" or "nothing hidden"), and the model is always refined by output error.
    kinematics : mapping or str, optional
        Position-velocity pairs, ``{"x1": "x2"}`` or ``"x1:x2,x3:x4"``: ``x1' = x2`` holds exactly,
        the equation is fixed and ``x2`` may be unmeasured (estimated for the regression by a
        smoothing derivative of ``x1``, :func:`symsbl._kinematics.estimate_velocity`).
    refine : bool
        Re-estimate every coefficient by output error (:func:`symsbl.refine`) after the
        equation-error fit, and select terms on the output-error evidence (default). ``False``
        returns the equation-error model.
    refine_options : dict, optional
        Keyword arguments for :func:`symsbl.refine`.

    Returns
    -------
    IdentifiedModel

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> print(symsbl.identify(train, library, refine=False))   # equation error only
    x1' = 1.0002(5e-4) x2
    x2' = -9990(23) x1 - 20.07(0.06) x2 - 9.999e8(8e5) x1^3 + 0.9992(7e-4) F
    >>> model = symsbl.identify(train, library)                 # refined by output error
    >>> print(model)
    x1' = 0.99997(6e-5) x2
    x2' = -1.0004e4(3) x1 - 19.999(0.002) x2 - 1.000e9(2e5) x1^3 + 1.00002(7e-5) F
    >>> model.equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    trajectories = as_trajectories(data)
    names = tuple(trajectories[0].state_names) if states is None else tuple(states)
    pairs = parse_kinematics(kinematics, names)
    latent = latent_states(names, trajectories[0].state_names, pairs)
    if latent:
        return identify_latent(trajectories, library, names, pairs, latent, refine_options=refine_options)
    completed, unmeasured = complete_states(trajectories, names, pairs)
    problem = regression_stats(completed, library, derivative=derivative, chunk_size=chunk_size, jit=jit)
    model = fit_stats(problem, rvm=rvm, equivalence_nats=equivalence_nats, kinematics=pairs)
    if unmeasured:
        measured = tuple(n for n in names if n not in unmeasured)
        model = dataclasses.replace(model, measured=measured,
                                    metadata=dict(model.metadata, unmeasured_estimate="smoothing derivative"))
    if not refine:
        return model
    from ._refine import refine_or_keep

    return refine_or_keep(model, trajectories, library=library, options=refine_options)


def fit_stats(problem: RegressionStats, *, rvm: RVM | None = None, equivalence_nats: float = 2.0,
              kinematics=()) -> IdentifiedModel:
    """Fit one sparse equation per state from accumulated regression statistics.

    This is the second half of :func:`identify`, for statistics built elsewhere (streamed
    chunks, several machines): the same model comes out of the same statistics.

    Parameters
    ----------
    problem : RegressionStats
        From :func:`regression_stats` or accumulated by other means.
    rvm, equivalence_nats
        As in :func:`identify`.
    kinematics : sequence of (str, str)
        Position-velocity pairs whose equations are fixed (``x' = v``), not fitted.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> problem = symsbl.regression_stats(train, library)
    >>> symsbl.fit_stats(problem).equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    if not isinstance(problem, RegressionStats):
        raise ParameterError(expected("problem", "a RegressionStats (from symsbl.regression_stats)",
                                      type(problem).__name__, raw=True))
    if rvm is not None and not isinstance(rvm, RVM):
        raise ParameterError(expected("rvm", "an RVM (or None)", type(rvm).__name__, raw=True))
    equivalence_nats = number("equivalence_nats", equivalence_nats, low=0.0)
    template = RVM() if rvm is None else rvm
    library = problem.library
    stats = problem.stats
    keys = [complexity(t.sympy) for t in library.terms]
    variables = {v.name(): v for v in library.variables}
    states = tuple(variables[n] if n in variables else _symbol(n) for n in problem.state_names)
    inputs = tuple(variables[n] if n in variables else _symbol(n) for n in problem.input_names)
    velocity_of = dict(kinematics)
    symbol = dict(zip(problem.state_names, states))
    equations = []
    with Progress("fit", total=len(problem.state_names), unit="equations") as bar:
        for k, lhs in enumerate(problem.state_names):
            if lhs in velocity_of:
                equations.append(Equation.kinematic(lhs, symbol[velocity_of[lhs]]))
            else:
                equations.append(_fit_equation(library, stats, k, lhs, template, keys, equivalence_nats))
            bar.update()
    return IdentifiedModel(
        states=states,
        inputs=inputs,
        equations=tuple(equations),
        metadata={
            "derivative": type(problem.derivative).__name__,
            "n_candidates": len(library),
            "n_rows": int(stats.n_samples),
        },
        kinematics=tuple(kinematics),
    )


def _fit_equation(library: Library, stats, k, lhs, template, keys, equivalence_nats) -> Equation:
    """The sparse equation of state ``k``: RVM, support search, parsimony."""
    first = fit_rvm(template, stats, k)
    if len(first.active_) == 0:
        return Equation(lhs, (), np.zeros((0, 0)), float(first.noise_var_), float(first.log_evidence_),
                        int(stats.n_samples))
    active, alternatives, search = search_support(first, stats, k, keys, template, equivalence_nats)
    _, kept, final = search.score(active)
    names = {col: tuple(library.terms[i].name for i in alternatives.get(col, ())) for col in kept}
    runners = [library.terms[c].name for c in search.runners_up(kept, final)]
    return Equation.from_fit(lhs, [library.terms[c].expr for c in kept], final, int(stats.n_samples),
                             alternatives=[names[c] for c in kept], runners_up=runners)


def _symbol(name: str):
    return ca.SX.sym(name)
