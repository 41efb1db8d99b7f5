"""The design of a discrepancy run: one library holding every base and candidate term, the statistics
of each record (computed once, shared by every fit of every iteration), fits and held-out errors."""

from __future__ import annotations

import math
from typing import cast

import numpy as np

from .._data.trajectory import Trajectory
from .._model import Equation, IdentifiedModel
from .._regression.gram import GramStats
from .._regression.rows import regression_stats
from .._regression.rvm import RVM
from .._regression.support import subset_stats
from .._symbolic.library import Library
from .._validate.validate import validate_model

__all__ = ["Design", "heldout_error", "ERROR_MEASURES"]

#: Held-out error measures: re-simulation of the states, or the one-step equation error.
ERROR_MEASURES = ("simulation", "equation")


class Design:
    """One library holding every base and candidate term, its columns, and the statistics of each
    record (computed once per record, shared by every fit of every iteration)."""

    def __init__(self, base, candidates, states, inputs, derivative):
        self.states, self.inputs = states, inputs
        variables = tuple(states) + tuple(inputs)
        self.variables = variables
        exprs = [e for terms in base.values() for e in terms] + [e for v in candidates for e in v.exprs]
        self.library = Library(exprs, variables)
        self.derivative = derivative
        self._stats: dict[int, tuple[Trajectory, GramStats]] = {}
        #: Effective-sample fraction of the rows (1 for independent residuals), see
        #: :func:`~symsbl._data.residuals.effective_fraction`.
        self.weight = 1.0

    def column(self, expr) -> int | None:
        """Column of ``expr`` (None when the library merged it into an equal term)."""
        name = Library([expr], self.variables).names
        if not name or name[0] not in self.library:
            return None
        return self.library.index(name[0])

    def stats(self, traj: Trajectory):
        key = id(traj)
        if key not in self._stats:
            self._stats[key] = (traj, regression_stats(traj, self.library, derivative=self.derivative).stats)
        return self._stats[key][1]

    def forget(self, traj: Trajectory) -> None:
        """Drop the statistics of a record no longer needed (a bootstrap replicate)."""
        self._stats.pop(id(traj), None)

    def fit(self, traj, k, cols) -> RVM:
        rvm = RVM(free=tuple(range(len(cols))), prune_nats=None)
        stats = subset_stats(self.stats(traj), cols, k)
        return rvm.fit_stats(stats if self.weight == 1.0 else stats.scaled(self.weight))

    def equation(self, lhs, cols, fit, n_rows) -> Equation:
        return Equation.from_fit(lhs, [self.library.terms[c].expr for c in cols], fit, n_rows)

    def model(self, structure, traj) -> IdentifiedModel:
        equations = []
        names = list(traj.state_names)
        for lhs, cols in structure.items():
            fit = self.fit(traj, names.index(lhs), cols)
            equations.append(self.equation(lhs, cols, fit, self.stats(traj).n_samples))
        return IdentifiedModel(
            tuple(self.states),
            tuple(self.inputs),
            tuple(equations),
            metadata={"derivative": type(self.derivative).__name__},
        )


def heldout_error(
    model: IdentifiedModel, traj: Trajectory, measure: str, design: Design, velocity: str, measured=None
) -> float:
    """Held-out error of ``model`` on ``traj``: mean simulation NRMSE of the ``measured`` states (default all),
    or the NRMSE of the velocity equation on the record's rows (``measure="equation"``)."""
    if measure == "simulation":
        result = validate_model(model, traj, method="rk4")
        keep = result.nrmse if measured is None else {k: v for k, v in result.nrmse.items() if k in measured}
        return math.inf if result.status != "ok" else float(np.mean(list(keep.values())))
    stats = design.stats(traj)
    k = list(traj.state_names).index(velocity)
    eq = model.equation(velocity)
    cols = cast("list[int]", [design.column(t.expr) for t in eq.terms])  # the model's terms are design columns
    theta = eq.coefs
    rss = stats.yty[k] - 2 * theta @ stats.dty[cols, k] + theta @ stats.gram[np.ix_(cols, cols)] @ theta
    n = stats.n_samples
    var = stats.yty[k] / n - (stats.y_sum[k] / n) ** 2
    return float(math.sqrt(max(rss, 0.0) / n / var))
