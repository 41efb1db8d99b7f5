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

import numpy as np

from .._model import Equation, IdentifiedModel, TermEstimate
from .laplace import reduce_model

__all__ = ["penalty", "backward", "with_terms", "without_terms", "free_positions"]


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
