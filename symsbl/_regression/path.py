"""The equation error's model path: each equation's structure chosen by a validation it did not fit.

Where output error's likelihood does not hold (process or input noise, a closed loop), the equation error is the
consistent estimator, but its evidence still assumes independent rows, and a measured record's equation error
is seldom white: a term that captures a real but minor effect (the velocity dependence of a real friction
beyond its viscous and Coulomb parts) gains evidence the physics' size cannot match. So each equation's terms
are removed one at a time from the equation error's support (the one whose removal costs least evidence,
refitted), and every structure on that path is scored by the cross-validated error of its equation on
contiguous folds of the records: the coefficients fitted on the other folds (their statistics are sums:
the fold's are subtracted) predict the fold's regression targets. The :class:`~symsbl.SelectionRule` chooses.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._base.rule import SelectionRule, mean_errors, paired_se
from .._model import Equation, IdentifiedModel, ModelPath, PathEntry
from .gram import GramStats
from .rows import RegressionStats
from .rvm import RVM
from .support import subset_stats

__all__ = ["validated_equations", "fold_errors"]


def _fit(template: RVM, stats: GramStats, cols: list[int], target: int) -> RVM:
    """The RVM on ``cols`` with every column kept."""
    params = dict(template.get_params(), free=list(range(len(cols))))
    return RVM(**params).fit_stats(subset_stats(stats, cols, target), target=0)


def _minus(a: GramStats, b: GramStats) -> GramStats:
    return GramStats(a.gram - b.gram, a.dty - b.dty, a.yty - b.yty, a.y_sum - b.y_sum, a.n_samples - b.n_samples)


def fold_errors(folds: list[GramStats], cols: list[int], target: int, template: RVM) -> np.ndarray:
    """Each fold's relative RMS error of the equation on ``cols`` fitted on the other folds."""
    total = folds[0]
    for f in folds[1:]:
        total = total + f
    out = []
    for f in folds:
        try:
            fit = _fit(template, _minus(total, f), cols, target)
        except (ValueError, np.linalg.LinAlgError):
            out.append(np.inf)
            continue
        yy = float(f.yty[target])
        out.append(float(np.sqrt(max(_sse(f, cols, target, fit.coef_), 0.0) / yy)) if yy > 0 else np.inf)
    return np.array(out)


def _sse(st: GramStats, cols: list[int], target: int, theta: np.ndarray) -> float:
    """The squared residual of the equation on ``cols`` with coefficients ``theta``, from the statistics alone."""
    G, b = st.gram[np.ix_(cols, cols)], st.dty[cols, target]
    return float(st.yty[target]) - 2.0 * float(theta @ b) + float(theta @ G @ theta)


def noise_floor(clean: GramStats, again: GramStats, cols: list[int], target: int, theta: np.ndarray) -> float:
    """The relative error the noise alone leaves in an equation: what the records' noise, added once more
    (``again``: the statistics of the records with their noise doubled), adds to the residual of the equation
    on ``cols`` with coefficients ``theta``, relative to the target."""
    extra = max(_sse(again, cols, target, theta) - _sse(clean, cols, target, theta), 0.0)
    return float(np.sqrt(extra / clean.yty[target])) if clean.yty[target] > 0 else 0.0


def validated_equations(
    model: IdentifiedModel,
    problem: RegressionStats,
    folds: list[GramStats],
    template: RVM,
    rule: SelectionRule,
    again: GramStats | None = None,
) -> tuple[IdentifiedModel, ModelPath]:
    """``model`` (the equation error's) with each equation's structure chosen from its backward-elimination path
    by cross-validation over ``folds`` (statistics of contiguous stretches of the records), and the path.
    ``again``: the statistics of the records with their noise added once more, which set each equation's noise
    floor (:func:`noise_floor`; 0 without them)."""
    names = problem.library.names
    n_obs, n_candidates = problem.stats.n_samples, len(names)
    cost = rule.nats_per_term(n_obs, n_candidates)
    equations, entries, reasons = [], [], []
    for eq in model.equations:
        if eq.fixed or len(eq.terms) < 2:
            equations.append(eq)
            continue
        target = problem.state_names.index(eq.lhs)
        cols = [names.index(t.name) for t in eq.terms]
        path = []
        while cols:
            fit = _fit(template, problem.stats, cols, target)
            path.append((list(cols), fit, fold_errors(folds, cols, target, template)))
            if len(cols) == 1:
                break
            cols = [c for k, c in enumerate(cols) if k != int(np.argmin(fit.evidence_contribution_))]
        sizes = [len(c) for c, _, _ in path]
        objectives = [float(f.log_evidence_) - cost * n for (_, f, _), n in zip(path, sizes)]
        E = np.array([e for _, _, e in path])
        full_cols, full_fit, _ = path[0]
        floor = (
            0.0
            if again is None
            else noise_floor(problem.stats, again, full_cols, target, full_fit.coef_[np.arange(len(full_cols))])
        )
        chosen, reason = rule.choose(sizes, objectives, E, floor=floor)
        reasons.append(reason)
        best = int(np.argmin(mean_errors(E)))
        for k, (c, f, e) in enumerate(path):
            entries.append(
                PathEntry(
                    ((eq.lhs, tuple(names[i] for i in c)),),
                    sizes[k],
                    float(f.log_evidence_),
                    objectives[k],
                    float(np.mean(e)),
                    paired_se(e, E[best]),
                    "equation error" if k == 0 else "path",
                    k == chosen,
                )
            )
        c, fit, _ = path[chosen]
        by_name = {t.name: t for t in eq.terms}
        equations.append(
            Equation.from_fit(
                eq.lhs,
                [problem.library.terms[i].expr for i in c],
                fit,
                int(n_obs),
                alternatives=[by_name[names[i]].alternatives for i in c],
                runners_up=eq.runners_up,
            )
        )
    entries.sort(key=lambda e: (e.terms[0][0], e.n_terms))
    chosen_path = ModelPath(tuple(entries), reasons[0] if reasons else "")
    return dataclasses.replace(model, equations=tuple(equations)), chosen_path
