"""Term selection on the output-error evidence.

The objective is the relevance vector machine's: log evidence minus ``T`` nats per free term
(``T = 1/2 log N + log M``, the extended BIC with ``N`` the measured samples and ``M`` the candidate
terms). From one fit of the current structure extended by the candidates (the equation-error
runners-up and the terms it found indistinguishable), Bayesian model reduction scores removing each
term without refitting; terms are removed one by one while that raises the objective. The structure
it settles on is then refitted, and kept only if the refit confirms the gain.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from .._errors import SimulationError
from .._model import Equation, IdentifiedModel, TermEstimate
from .laplace import reduce_model, reprior

if TYPE_CHECKING:  # the engine builds on this module
    from .engine import Engine

__all__ = ["penalty", "backward", "select", "objective", "with_terms", "without_terms", "free_positions"]


def penalty(n_obs: int, n_candidates: int) -> float:
    """Nats per free term: ``1/2 log N + log M``."""
    return 0.5 * float(np.log(max(n_obs, 2))) + float(np.log(max(n_candidates, 2)))


def free_positions(model: IdentifiedModel) -> list[tuple[int, int]]:
    """``(equation, term)`` of every free coefficient, in the order of the fit's ``theta``."""
    return [(i, j) for i, eq in enumerate(model.equations) if not eq.fixed
            for j, term in enumerate(eq.terms) if not term.fixed]


def backward(post, alpha: np.ndarray, cost_per_term: float, keys, equivalence_nats: float = 2.0) -> list[int]:
    """Free coefficients to remove, chosen greedily by model reduction from one posterior.

    Each round removes a coefficient whose removal gains (evidence change plus the penalty it saves)
    a positive amount; among the removals within ``equivalence_nats`` of the best, the most complex
    term goes (``keys``: parsimony keys, larger is more complex), so that of near-equivalent terms
    (``x`` and ``tan(x)`` at small ``x``) the simpler one stays, as in the equation-error selection.
    """
    removed: list[int] = []
    n = post.mean.size
    while len(removed) < n - 1:
        base = reduce_model(post, alpha, removed)[0] if removed else 0.0
        gains = {k: reduce_model(post, alpha, removed + [k])[0] - base + cost_per_term
                 for k in range(n) if k not in removed}
        best = max(gains.values())
        if best <= 0:
            break
        near = [k for k, g in gains.items() if g > 0 and g >= best - equivalence_nats]
        removed.append(max(near, key=lambda k: (keys[k], -gains[k])))
    return removed


def without_terms(model: IdentifiedModel, positions) -> IdentifiedModel:
    """The model without the terms at ``(equation, term)`` positions."""
    drop = set(positions)
    equations = []
    for i, eq in enumerate(model.equations):
        keep = [j for j in range(len(eq.terms)) if (i, j) not in drop]
        if len(keep) == len(eq.terms):
            equations.append(eq)
            continue
        equations.append(dataclasses.replace(eq, terms=tuple(eq.terms[j] for j in keep),
                                             covariance=np.asarray(eq.covariance)[np.ix_(keep, keep)]))
    return dataclasses.replace(model, equations=tuple(equations), joint_covariance=None)


def with_terms(model: IdentifiedModel, additions: dict) -> IdentifiedModel:
    """The model with ``additions`` ``{state: [(expr, coef), ...]}`` appended to its equations."""
    equations = []
    for eq in model.equations:
        extra = additions.get(eq.lhs, [])
        if not extra or eq.fixed:
            equations.append(eq)
            continue
        terms = eq.terms + tuple(TermEstimate(expr=e, coef=c, std=np.nan) for e, c in extra)
        n = len(terms)
        cov = np.zeros((n, n))
        cov[:len(eq.terms), :len(eq.terms)] = eq.covariance
        equations.append(Equation(eq.lhs, terms, cov, eq.noise_var, eq.log_evidence, eq.n_rows,
                                  runners_up=eq.runners_up))
    return dataclasses.replace(model, equations=tuple(equations), joint_covariance=None)


def objective(sol, cost_per_term: float) -> float:
    return sol.posterior.log_evidence - cost_per_term * sol.active.size


def select(engine: Engine, first, alpha: np.ndarray, cost_of, twins: dict | None = None):
    """The sub-structure with the best penalised output-error evidence: model reduction from one fit of
    the model extended by its candidates, confirmed by a refit. ``cost_of(fit)`` gives the nats per term
    from the extended fit (whose residual says how much structure no candidate explains). ``twins``
    (``{state: {look-alike: term}}``) names candidates tried in a term's place: when model reduction keeps
    both, the one whose removal costs less evidence goes (a look-alike added beside its term would soak up
    a misfit the structure has, such as an input interpolated across its steps)."""
    every = np.arange(len(engine.positions))
    sol = first
    if every.size > engine.base.size:
        sol = _extended(engine, first, every, alpha)
        if sol is None:  # a candidate that makes the model run away: keep the fitted structure
            return first
    cost = cost_of(sol)
    keys = [engine.keys[k] for k in sol.active]
    # compared under the structure's own priors: MacKay's, tuned to the extended fit, split a pair of
    # near-equivalent terms unevenly and would decide between them by that split
    post = reprior(sol.posterior, sol.alpha[sol.active], alpha[sol.active])
    removed = backward(post, alpha[sol.active], cost, keys)
    removed = _one_of_each_pair(engine, sol.active, post, alpha[sol.active], removed, twins or {})
    chosen = np.array([k for n, k in enumerate(sol.active) if n not in removed], dtype=int)
    if set(chosen) == set(engine.base):
        return first
    _, mean, _ = reduce_model(post, alpha[sol.active], removed) if removed else (0, post.mean, 0)
    start = np.zeros_like(sol.theta)
    start[chosen] = mean if removed else sol.theta[chosen]
    try:
        refit = engine.fit(chosen, start, sol.alpha, warm=sol)
    except SimulationError:
        return first
    return refit if objective(refit, cost) > objective(first, cost) else first


def _extended(engine: Engine, first, every: np.ndarray, alpha: np.ndarray):
    """The fit of the structure with every candidate, on ``first``'s segments (so that the evidences compare).

    By continuation from short segments: started at ``first``'s optimum on its long segments, a candidate
    that should take over a term's role (``v`` for ``sin(v)``) needs a large move of every coefficient
    that the long horizon makes non-convex (measured: 52177 nats against 80161 from short segments). When
    the continuation stops at other segments, or fits worse than ``first`` (by more than a nat at ``first``'s
    noise levels; a nested model cannot), the fit warm-started at ``first`` is taken instead. ``None`` when
    both run away.

    When ``first`` itself stopped short of whole records (a structure that cannot follow them: a term is
    missing), its coefficients have drifted to make up for what is missing, and the candidates start from
    that drift. The extended structure is then also fitted from the structure's own starting coefficients
    (the equation error's) up to whole records, and taken when it reaches longer segments with a higher
    evidence (measured on a 2-DOF chain with a cubic coupling spring, displacement only, the coupling's
    damping missing: 46892 nats on 4 segments from ``first``, 88879 on the whole record from the start).
    """
    fitted = _extended_from_first(engine, first, every, alpha)
    if first.length >= int(engine.passes.records.lengths.max()):
        return fitted
    start = np.zeros_like(first.theta)
    start[engine.base] = engine.param.theta0[engine.base]
    try:
        fresh = engine.fit(every, start, alpha)
    except SimulationError:
        return fitted
    longer = fresh.length > first.length
    if longer and (fitted is None or fresh.posterior.log_evidence > fitted.posterior.log_evidence):
        return fresh
    return fitted


def _extended_from_first(engine: Engine, first, every: np.ndarray, alpha: np.ndarray):
    """:func:`_extended` started at ``first``'s optimum."""
    cold = None
    try:
        cold = engine.fit(every, first.theta, alpha, longest=int(first.length))
    except SimulationError:
        pass
    same = cold is not None and np.array_equal(cold.starts, first.starts)
    if same and 0.5 * np.sum(cold.ssr * first.w) <= 0.5 * np.sum(first.ssr * first.w) + 1.0:
        return cold
    try:
        return engine.fit(every, first.theta, alpha, warm=first)
    except SimulationError:
        return None


def _one_of_each_pair(engine: Engine, active: np.ndarray, post, alpha: np.ndarray, removed: list, twins: dict):
    """``removed`` extended so that no look-alike stays beside its term: of each such pair, the one whose
    removal lowers the evidence less goes (Bayesian model reduction)."""
    where = {}
    for n, k in enumerate(active):
        i, j = engine.positions[k]
        eq = engine.full.equations[i]
        where[(eq.lhs, eq.terms[j].name)] = n
    removed = list(removed)
    for lhs, pairs in twins.items():
        for alike, term in pairs.items():
            a, b = where.get((lhs, alike)), where.get((lhs, term))
            if a is None or b is None or a in removed or b in removed:
                continue
            removed.append(max((a, b), key=lambda n: reduce_model(post, alpha, removed + [n])[0]))
    return removed
