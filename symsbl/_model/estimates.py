"""The posterior of one term and of one equation, and how a model's coefficients were estimated."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np
import sympy as sp

from .._base.format import format_uncertain, pretty
from .._symbolic.symbols import casadi_to_sympy

__all__ = ["FitMethod", "TermEstimate", "Equation"]


class FitMethod(str, enum.Enum):
    """How a model's coefficients were estimated (its value is the ``fit`` field of the model file)."""

    EQUATION_ERROR = "equation-error"
    OUTPUT_ERROR = "output-error"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class TermEstimate:
    """Posterior of one kept term of one equation.

    Attributes
    ----------
    expr : casadi.SX
        The candidate term, a scalar expression of the model's states and inputs.
    coef, std : float
        Posterior mean and standard deviation of its coefficient, in the data's units.
    alpha : float
        Optimised prior precision of the coefficient.
    evidence : float
        Log evidence (nats) lost if the term is removed; ``nan`` when unknown.
    alternatives : tuple of str
        Candidates the data cannot tell apart from this term (same fit within the evidence
        tolerance); the simplest of the group is the one kept.
    fixed : bool
        The coefficient is a convention, not an estimate (the scale of a latent state: see
        :attr:`IdentifiedModel.latent_names`).
    """

    expr: ca.SX
    coef: float
    std: float
    alpha: float = math.nan
    evidence: float = math.nan
    alternatives: tuple[str, ...] = ()
    fixed: bool = False

    @cached_property
    def sympy(self) -> sp.Expr:
        """The term as a sympy expression (converted once: sympy builds ``Max`` and ``Abs`` slowly)."""
        return casadi_to_sympy(self.expr)

    @property
    def name(self) -> str:
        """The term's name, its sympy print."""
        return str(self.sympy)

    @property
    def snr(self) -> float:
        """``|coef| / std``, the posterior signal-to-noise ratio of the coefficient."""
        return abs(self.coef) / self.std if self.std > 0 else math.inf


@dataclass(frozen=True)
class Equation:
    """Posterior of one state equation ``lhs' = sum_i coef_i term_i``.

    Attributes
    ----------
    lhs : str
        Name of the state whose derivative this is.
    terms : tuple of TermEstimate
        The kept terms, in library order.
    covariance : ndarray, shape (n_terms, n_terms)
        Posterior covariance of the kept coefficients.
    noise_var : float
        Estimated variance of the equation error (regression-row units).
    log_evidence : float
        Log marginal likelihood of the fitted equation (nats).
    n_rows : int
        Number of regression rows (equation error) or measured samples (output error) behind the fit.
    fixed : bool
        The equation is given, not estimated: a kinematic relation ``x' = v`` (coefficients exact).
    runners_up : tuple of str
        The candidates next in line by equation-error evidence (what an output-error refinement tries).
    algebraic : bool
        The equation of an output, ``lhs = sum_i coef_i term_i`` (a force cell), not of a state's derivative.
    """

    lhs: str
    terms: tuple[TermEstimate, ...]
    covariance: np.ndarray
    noise_var: float
    log_evidence: float
    n_rows: int = 0
    fixed: bool = False
    runners_up: tuple = field(default=(), compare=False)
    algebraic: bool = False

    @property
    def written(self) -> str:
        """The left-hand side as printed: ``x'`` for a state's derivative, ``y`` for an output."""
        return self.lhs if self.algebraic else f"{self.lhs}'"

    @classmethod
    def kinematic(cls, lhs: str, velocity) -> Equation:
        """The fixed equation ``lhs' = velocity`` of a position and its velocity (a casadi.SX symbol)."""
        term = TermEstimate(expr=velocity, coef=1.0, std=0.0)
        return cls(lhs, (term,), np.zeros((1, 1)), math.nan, math.nan, 0, fixed=True)

    @classmethod
    def from_fit(
        cls, lhs: str, exprs, fit, n_rows: int, alternatives=None, runners_up=(), algebraic: bool = False
    ) -> Equation:
        """The equation of a fitted :class:`~symsbl.RVM`: one term per kept column, in ``fit.active_`` order.

        Parameters
        ----------
        lhs : str
        exprs : sequence of casadi.SX
            The term of each kept column (``len(fit.active_)`` of them).
        fit : RVM
            Fitted on the columns the terms belong to.
        n_rows : int
            Regression rows behind the fit.
        alternatives : sequence of tuple of str, optional
            Per kept term, the candidates the data cannot tell apart from it.
        runners_up : sequence of str
            The candidates next in line.
        algebraic : bool
            The equation of an output (see :attr:`algebraic`).
        """
        active = [int(i) for i in fit.active_]
        alternatives = alternatives or [()] * len(active)
        terms = tuple(
            TermEstimate(
                expr=e,
                coef=float(fit.coef_[i]),
                std=float(math.sqrt(fit.sigma_[pos, pos])),
                alpha=float(fit.alpha_[i]),
                evidence=float(fit.evidence_contribution_[pos]),
                alternatives=tuple(alt),
            )
            for pos, (i, e, alt) in enumerate(zip(active, exprs, alternatives))
        )
        return cls(
            lhs,
            terms,
            np.array(fit.sigma_),
            float(fit.noise_var_),
            float(fit.log_evidence_),
            int(n_rows),
            runners_up=tuple(runners_up),
            algebraic=algebraic,
        )

    @property
    def coefs(self) -> np.ndarray:
        """Posterior means, shape ``(n_terms,)``."""
        return np.array([t.coef for t in self.terms])

    @property
    def stds(self) -> np.ndarray:
        """Posterior standard deviations, shape ``(n_terms,)``."""
        return np.array([t.std for t in self.terms])

    @property
    def names(self) -> list[str]:
        """Names of the kept terms."""
        return [t.name for t in self.terms]

    def coef(self, name: str) -> float:
        """Coefficient of the term called ``name`` (0.0 if the term was not kept)."""
        for t in self.terms:
            if t.name == name:
                return t.coef
        return 0.0

    def rhs_sympy(self) -> sp.Expr:
        """Right-hand side with the posterior means as coefficients."""
        return sp.Add(*[sp.Float(t.coef) * t.sympy for t in self.terms])

    def __str__(self) -> str:
        if self.fixed:
            return f"{self.lhs}' = " + " + ".join(pretty(t.name) for t in self.terms) + "  (kinematics, fixed)"
        parts: list[str] = []
        for t in self.terms:
            text = (
                format_uncertain(t.coef, t.std, signed=bool(parts))
                if not t.fixed
                else (f"{'- ' if t.coef < 0 else '+ ' if parts else ''}{abs(t.coef):g}")
            )
            label = pretty(t.name)
            label = f"({label})" if isinstance(t.sympy, sp.Add) else label  # a sum is one term: c (a - b)
            body = text if label == "1" else f"{text} {label}"
            if t.fixed:
                body += " (scale convention)"
            if t.alternatives:
                body += " (indistinguishable here from " + ", ".join(pretty(a) for a in t.alternatives) + ")"
            parts.append(body)
        return f"{self.written} = " + (" ".join(parts) if parts else "0")
