"""From scaled-out statistics to a model: ``identify``'s rule, options and kinematics for every front end.

:func:`symsbl.identify_stream` and :func:`symsbl.identify_dask` build the regression's sufficient statistics
their own way (blocks read from files, slices on a cluster) and hand them here: the equation-error fit and the
output-error refinement then run as in :func:`symsbl.identify`, with the same selection rule, refinement
options and declared kinematics, on evenly spaced windows of the records when they exceed the refinement's
sample budget.
"""

from __future__ import annotations

from collections.abc import Callable

from .._base.errors import DataError, expected
from .._derivatives.kinematics import kinematic_triples
from .._model import IdentifiedModel
from .._refine import refine_or_keep
from .._refine.options import requested
from .._refine.problem import window_plan
from .._regression.fit import fit_stats, selection_rule
from .._regression.rows import RegressionStats

__all__ = ["model_from_stats"]


def model_from_stats(
    problem: RegressionStats,
    counts,
    windows: Callable,
    *,
    library,
    rvm,
    equivalence_nats,
    selection,
    kinematics,
    refine,
    refine_options,
) -> IdentifiedModel:
    """The model of the statistics ``problem`` of records of ``counts`` samples each; ``windows(plan)`` reads the
    windows of :func:`~symsbl._refine.problem.window_plan` as trajectories. The keywords are ``identify``'s."""
    rule = selection_rule(selection, rvm, equivalence_nats)
    options = requested(refine, refine_options)
    pairs = measured_pairs(kinematics, problem.state_names)
    model = fit_stats(problem, rvm=rvm, kinematics=pairs, selection=rule)
    if options is None:
        return model
    plan, note = window_plan(counts, options.max_samples)
    return refine_or_keep(model, windows(plan), library=library, options=options, note=note, selection=rule)


def measured_pairs(kinematics, states) -> tuple[tuple[str, str], ...]:
    """The declared position-velocity pairs, both members columns of the records (streamed statistics hold no
    reconstructed state and no accelerometer)."""
    if not kinematics:
        return ()
    triples = kinematic_triples(kinematics, states)
    absent = [f"{x}:{v}" + (f":{a}" if a else "") for x, v, a in triples if a or x not in states or v not in states]
    if absent:
        raise DataError(
            expected(
                "kinematics",
                "position:velocity pairs of measured states in a scaled-out identification",
                ", ".join(absent),
                "identify records with unmeasured states or accelerometers with symsbl.identify",
                raw=True,
            )
        )
    return tuple((x, v) for x, v, _ in triples)
