"""The equation-error model from regression statistics: one sparse equation per state.

Each equation gets one :class:`~symsbl.RVM` fitted from the statistics shared by every equation, then an
evidence-guided support search and parsimony among near-equivalent candidates
(:mod:`symsbl._regression.support`); kinematic equations ``x' = v`` are fixed, not fitted.
"""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np

from .._base.checks import number
from .._base.errors import ParameterError, expected
from .._base.progress import Progress
from .._base.rule import DEFAULT as DEFAULT_RULE
from .._base.rule import SelectionRule, complexity
from .._model import Equation, IdentifiedModel
from .._model.outputs import AccelerationOutput, AlgebraicOutput, state_outputs
from .._symbolic.library import Library
from .rows import RegressionStats
from .rvm import RVM
from .support import fit_rvm, search_support

__all__ = ["fit_stats", "selection_rule"]


def fit_stats(
    problem: RegressionStats,
    *,
    rvm: RVM | None = None,
    equivalence_nats: float | None = None,
    kinematics=(),
    selection: SelectionRule | None = None,
) -> IdentifiedModel:
    """Fit one sparse equation per state from accumulated regression statistics.

    This is the second half of :func:`identify`, for statistics built elsewhere (streamed
    chunks, several machines): the same model comes out of the same statistics.

    Parameters
    ----------
    problem : RegressionStats
        From :func:`regression_stats` or accumulated by other means.
    rvm, equivalence_nats, selection
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
        raise ParameterError(
            expected("problem", "a RegressionStats (from symsbl.regression_stats)", type(problem).__name__, raw=True)
        )
    rule = selection_rule(selection, rvm, equivalence_nats)
    equivalence_nats = rule.equivalence_nats
    template = RVM(**dict((RVM() if rvm is None else rvm).get_params(), prune_nats=rule.penalty))
    library = problem.library
    stats = problem.stats
    keys = [complexity(t.sympy) for t in library.terms]
    variables = {v.name(): v for v in library.variables}
    states = tuple(variables[n] if n in variables else _symbol(n) for n in problem.state_names)
    inputs = tuple(variables[n] if n in variables else _symbol(n) for n in problem.input_names)
    velocity_of = dict(kinematics)
    symbol = dict(zip(problem.state_names, states))
    equations = []
    with Progress("fit", total=len(problem.target_names), unit="equations") as bar:
        for k, lhs in enumerate(problem.target_names):
            if lhs in velocity_of:
                equations.append(Equation.kinematic(lhs, symbol[velocity_of[lhs]]))
            else:
                equations.append(
                    _fit_equation(
                        library, stats, k, lhs, template, keys, equivalence_nats, algebraic=lhs in problem.output_names
                    )
                )
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
        outputs=_outputs(problem),
    )


def _outputs(problem: RegressionStats) -> tuple:
    """The outputs the statistics' targets read: none beyond the states (then the states are), or the states,
    the measured derivatives as accelerations and the algebraic outputs."""
    if not problem.output_names and not problem.derivatives:
        return ()
    return (
        state_outputs([n for n in problem.state_names if n not in dict(problem.derivatives)])
        + tuple(AccelerationOutput(column, state) for state, column in problem.derivatives)
        + tuple(AlgebraicOutput(n) for n in problem.output_names)
    )


def selection_rule(selection: SelectionRule | None, rvm: RVM | None, equivalence_nats: float | None) -> SelectionRule:
    """The selection rule of an identification: ``selection`` (default :class:`~symsbl.SelectionRule`) with the
    parts given on their own, the template ``rvm``'s penalty and ``equivalence_nats``; a part given twice
    with two values is an error."""
    if selection is not None and not isinstance(selection, SelectionRule):
        raise ParameterError(expected("selection", "a SelectionRule (or None)", type(selection).__name__, raw=True))
    if rvm is not None and not isinstance(rvm, RVM):
        raise ParameterError(expected("rvm", "an RVM (or None)", type(rvm).__name__, raw=True))
    rule = (selection or DEFAULT_RULE).check()
    if rvm is not None and rvm.prune_nats != RVM().prune_nats:
        penalty = 0.0 if rvm.prune_nats is None else rvm.prune_nats
        if selection is not None and selection.penalty != penalty:
            raise ParameterError(
                expected(
                    "rvm.prune_nats",
                    "the penalty per term given once",
                    "both "
                    f"rvm=RVM(prune_nats={rvm.prune_nats!r}) and selection=SelectionRule("
                    f"penalty={selection.penalty!r})",
                    "set it in the SelectionRule only",
                    raw=True,
                )
            )
        rule = dataclasses.replace(rule, penalty=penalty).check()
    if equivalence_nats is not None:
        equivalence_nats = number("equivalence_nats", equivalence_nats, low=0.0)
        if selection is not None and selection.equivalence_nats != equivalence_nats:
            raise ParameterError(
                expected(
                    "equivalence_nats",
                    "the parsimony margin given once",
                    "both "
                    f"equivalence_nats={equivalence_nats:g} and selection=SelectionRule("
                    f"equivalence_nats={selection.equivalence_nats:g})",
                    "set it in the SelectionRule only",
                    raw=True,
                )
            )
        rule = dataclasses.replace(rule, equivalence_nats=equivalence_nats)
    return rule


def _fit_equation(
    library: Library, stats, k, lhs, template, keys, equivalence_nats, algebraic: bool = False
) -> Equation:
    """The sparse equation of target ``k`` (a state's derivative or an algebraic output): RVM, support search,
    parsimony."""
    first = fit_rvm(template, stats, k)
    if len(first.active_) == 0:
        return Equation(
            lhs,
            (),
            np.zeros((0, 0)),
            float(first.noise_var_),
            float(first.log_evidence_),
            int(stats.n_samples),
            algebraic=algebraic,
        )
    active, alternatives, search = search_support(first, stats, k, keys, template, equivalence_nats)
    _, kept, final = search.score(active, own=True)
    names = {col: tuple(library.terms[i].name for i in alternatives.get(col, ())) for col in kept}
    runners = [library.terms[c].name for c in search.runners_up(kept, final)]
    return Equation.from_fit(
        lhs,
        [library.terms[c].expr for c in kept],
        final,
        int(stats.n_samples),
        alternatives=[names[c] for c in kept],
        runners_up=runners,
        algebraic=algebraic,
    )


def _symbol(name: str):
    return ca.SX.sym(name)
