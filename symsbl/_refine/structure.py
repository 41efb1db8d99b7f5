"""Which coefficients a refinement fits: a model's free terms, and the model with terms added or removed."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._model import Equation, IdentifiedModel, TermEstimate

__all__ = ["free_positions", "with_terms", "without_terms"]


def free_positions(model: IdentifiedModel) -> list[tuple[int, int]]:
    """``(equation, term)`` of every free coefficient, in the order of the fit's ``theta``."""
    return [
        (i, j)
        for i, eq in enumerate(model.equations)
        if not eq.fixed
        for j, term in enumerate(eq.terms)
        if not term.fixed
    ]


def without_terms(model: IdentifiedModel, positions) -> IdentifiedModel:
    """The model without the terms at ``(equation, term)`` positions."""
    drop = set(positions)
    equations = []
    for i, eq in enumerate(model.equations):
        keep = [j for j in range(len(eq.terms)) if (i, j) not in drop]
        if len(keep) == len(eq.terms):
            equations.append(eq)
            continue
        equations.append(
            dataclasses.replace(
                eq, terms=tuple(eq.terms[j] for j in keep), covariance=np.asarray(eq.covariance)[np.ix_(keep, keep)]
            )
        )
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
        cov[: len(eq.terms), : len(eq.terms)] = eq.covariance
        equations.append(
            Equation(
                eq.lhs,
                terms,
                cov,
                eq.noise_var,
                eq.log_evidence,
                eq.n_rows,
                runners_up=eq.runners_up,
                algebraic=eq.algebraic,
            )
        )
    return dataclasses.replace(model, equations=tuple(equations), joint_covariance=None)
