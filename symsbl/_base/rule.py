"""The one rule by which symsbl keeps a term: evidence minus a penalty per term, the simpler among equals.

Every selection in symsbl (the relevance vector machine's, the support search's, the output-error
refinement's, the latent-state branches' and the discrepancy workflow's) maximises the same objective,

    log evidence - T * (number of free terms),    T = 1/2 log N + log M    (the extended BIC),

with ``N`` the observations and ``M`` the candidates the terms were chosen from (Chen and Chen 2008 with
gamma = 1: the unit-information Occam factor the adaptive prior removes, ``1/2 log N``, plus the
multiplicity of choosing among ``M``, ``log M``). Two structures whose objectives differ by less than
:attr:`SelectionRule.equivalence_nats` are equivalent and the simpler is kept, simplicity ordered by
:func:`complexity`; a named winner must beat its runner-up by :attr:`SelectionRule.margin_nats`.

References
----------
J. Chen, Z. Chen, "Extended Bayesian information criteria for model selection with large model spaces",
Biometrika 95 (2008) 759-771.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sympy as sp

from .checks import choice, number
from .errors import ParameterError, expected

__all__ = [
    "SelectionRule",
    "PENALTIES",
    "MODEL_CHOICES",
    "complexity",
    "nats_per_term",
    "multiplicity",
    "paired_se",
    "mean_errors",
]


def _ebic(n_obs: float, n_candidates: float) -> float:
    return 0.5 * math.log(max(n_obs, 2)) + math.log(max(n_candidates, 2))


def _bic(n_obs: float, n_candidates: float) -> float:
    return 0.5 * math.log(max(n_obs, 2))


#: Named penalties: nats per term as a function of (observations, candidates).
PENALTIES = {"bic": _bic, "ebic": _ebic}


def nats_per_term(penalty, n_obs: float, n_candidates: float) -> float:
    """The penalty ``penalty`` (a name in :data:`PENALTIES`, a number of nats, or None for no penalty) for
    ``n_obs`` observations and ``n_candidates`` candidates."""
    if penalty is None:
        return 0.0
    if isinstance(penalty, str):
        if penalty not in PENALTIES:
            raise ParameterError(expected("penalty", f"one of {sorted(PENALTIES)} or a number of nats >= 0", penalty))
        return float(PENALTIES[penalty](n_obs, n_candidates))
    return float(penalty)


def multiplicity(n_choices: int) -> float:
    """Nats a choice among ``n_choices`` equally likely alternatives costs, ``log n`` (0 for one)."""
    return math.log(n_choices) if n_choices > 1 else 0.0


#: A cross-validated error (RMS over each channel's spread) above this is a simulation that ran away.
RAN_AWAY = 10.0

#: How a structure is chosen from the model path (see :attr:`SelectionRule.model_choice`).
MODEL_CHOICES = ("validated", "evidence")


def paired_se(a: np.ndarray, b: np.ndarray) -> float:
    """Standard error of the mean of the fold-by-fold differences ``a - b`` (0 when ``a`` is ``b``)."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    if not np.all(np.isfinite(d)):
        return math.inf
    if not np.any(d):
        return 0.0
    return float(np.std(d, ddof=1) / math.sqrt(d.size)) if d.size > 1 else math.inf


def mean_errors(fold_errors) -> np.ndarray:
    """Each candidate's mean cross-validated error over its folds; ``inf`` where a fold diverged."""
    E = np.asarray(fold_errors, dtype=float)
    return np.where(np.all(np.isfinite(E), axis=1), E.mean(axis=1), np.inf)


def complexity(expr: sp.Expr) -> tuple[int, int, int]:
    """Parsimony key of a candidate term: smaller is simpler.

    Terms are ranked first by function class (polynomial < with ``Abs`` < with ``sign`` < ``sin``/``cos`` <
    anything else, e.g. ``tan``), then by polynomial degree, then by the number of operations.

    Examples
    --------
    >>> import sympy as sp
    >>> x = sp.Symbol("x")
    >>> sorted([sp.tan(x), sp.sin(x), x**3, x, sp.sign(x), x * sp.Abs(x)], key=complexity)
    [x, x**3, x*Abs(x), sign(x), sin(x), tan(x)]
    """
    funcs = {type(f).__name__ for f in expr.atoms(sp.Function)}
    if not funcs:
        rank = 0
    elif funcs <= {"Abs"}:
        rank = 1
    elif funcs <= {"Abs", "sign"}:
        rank = 2
    elif funcs <= {"Abs", "sign", "sin", "cos"}:
        rank = 3
    else:
        rank = 4
    try:
        free = expr.free_symbols
        degree = int(sp.Poly(expr.replace(sp.Abs, lambda a: a), *free).total_degree()) if free else 0
    except (sp.PolynomialError, sp.GeneratorsNeeded):
        degree = 99
    return rank, degree, int(sp.count_ops(expr))


#: The share of the noise floor within which a structure's distance to it is not resolved: the floor is an
#: estimate, a few per cent off (:func:`symsbl._data.excitation.relative_noise` reads 1 % noise on a sine as
#: 0.98 %), so at the floor a richer structure must still close its share of this much.
FLOOR_RESOLUTION = 0.05


@dataclass(frozen=True)
class SelectionRule:
    """How symsbl chooses terms: one rule for the equation error, the output error, latent states and the
    discrepancy workflow.

    Attributes
    ----------
    penalty : {"ebic", "bic"} or float
        Nats each free term must earn: ``"ebic"`` (default) ``1/2 log N + log M``, ``"bic"`` ``1/2 log N``, or a
        fixed number of nats.
    equivalence_nats : float
        Structures whose penalised evidences differ by less than this are equivalent, and the simpler
        (:func:`complexity`) is kept; candidates within it of a kept term are reported as indistinguishable
        (2 nats: at 16 mm of displacement, ``x``, ``sin(x)`` and ``tan(x)`` differ by parts in 10^4).
    margin_nats : float
        Log Bayes factor by which a named choice must beat its runner-up (3 nats: odds of 20 to 1); below it,
        the choice is reported as ambiguous.
    model_choice : {"validated", "evidence"}
        How the identified structure is chosen from the model path (the structures between the equation
        error's and the output error's, each with its evidence and cross-validated error): ``"validated"``
        (default) from the simplest, a richer structure is taken only when it lowers the cross-validated error
        by more than one standard error of the fold-by-fold difference (every fold agrees) and by more than
        ``min_gain`` of the distance to the noise floor for each term it adds (it matters); ``"evidence"`` the
        evidence's own choice.
    min_gain : float
        The share of the gap between a structure's cross-validated error and the noise floor that a richer
        structure must close for each term it adds to be taken (0.1: a term that brings a model a tenth closer
        to what the noise allows; two terms, 19 %), the gap taken as at least 5 % of the floor (an estimate:
        nearer is not resolved). Measured on EMPS (a real axis with friction): a cubic
        velocity term lowers the held-out force error by 1.9 %, every fold agreeing, and moves the viscous
        coefficient by 14 %; the physics' four terms are kept. From its encoder alone, two terms (v|v|,
        q v^2) closed about 14 % of the gap together and are left out.

    Examples
    --------
    >>> import symsbl
    >>> rule = symsbl.SelectionRule()
    >>> round(rule.nats_per_term(n_obs=10000, n_candidates=94), 2)   # 1/2 log 1e4 + log 94
    9.15
    >>> symsbl.SelectionRule(penalty="bic").nats_per_term(10000, 94) == 0.5 * __import__("math").log(10000)
    True
    >>> rule.objective(log_evidence=120.0, n_terms=2, n_obs=10000, n_candidates=94) > 100
    True
    """

    penalty: str | float = "ebic"
    equivalence_nats: float = 2.0
    margin_nats: float = 3.0
    model_choice: str = "validated"
    min_gain: float = 0.1

    def check(self) -> SelectionRule:
        """``self``, after checking every field (called where a rule enters a computation)."""
        if isinstance(self.penalty, str):
            if self.penalty not in PENALTIES:
                raise ParameterError(
                    expected("selection.penalty", f"one of {sorted(PENALTIES)} or a number of nats >= 0", self.penalty)
                )
        else:
            number("selection.penalty", self.penalty, low=0.0)
        number("selection.equivalence_nats", self.equivalence_nats, low=0.0)
        number("selection.margin_nats", self.margin_nats, low=0.0)
        choice("selection.model_choice", self.model_choice, MODEL_CHOICES)
        number("selection.min_gain", self.min_gain, low=0.0, high=1.0)
        return self

    def nats_per_term(self, n_obs: float, n_candidates: float) -> float:
        """The penalty of one free term for ``n_obs`` observations and ``n_candidates`` candidates."""
        return nats_per_term(self.penalty, n_obs, n_candidates)

    def objective(self, log_evidence: float, n_terms: int, n_obs: float, n_candidates: float) -> float:
        """Penalised log evidence of a structure with ``n_terms`` free terms."""
        return float(log_evidence) - n_terms * self.nats_per_term(n_obs, n_candidates)

    def equivalent(self, a: float, b: float) -> bool:
        """Whether two penalised evidences are within :attr:`equivalence_nats` of each other."""
        return abs(float(a) - float(b)) < self.equivalence_nats

    def decisive(self, log_bayes_factor: float) -> bool:
        """Whether a choice beats its runner-up by at least :attr:`margin_nats`."""
        return float(log_bayes_factor) >= self.margin_nats

    def choose(self, sizes, objectives, fold_errors, floor: float = 0.0) -> tuple[int, str]:
        """The chosen candidate of a model path and the reason, in one line.

        Parameters
        ----------
        sizes : sequence of int
            Free terms of each candidate.
        objectives : sequence of float
            Penalised log evidence of each.
        fold_errors : ndarray, shape (n_candidates, n_folds)
            Cross-validated error of each candidate on each fold (``inf``: diverged).
        floor : float
            The error the noise alone leaves (0 when unknown).
        """
        sizes, objectives = np.asarray(sizes), np.asarray(objectives, dtype=float)
        by_evidence = int(np.argmax(np.where(np.isfinite(objectives), objectives, -np.inf)))
        E = np.asarray(fold_errors, dtype=float)
        E = np.where(E > RAN_AWAY, np.inf, E)  # a fold simulated past ten spreads ran away: the structure fails it
        finite = np.all(np.isfinite(E), axis=1) if E.size else np.zeros(0, bool)
        if self.model_choice == "evidence" or not np.any(finite):
            return by_evidence, "the best penalised evidence"
        mean = mean_errors(E)
        order = sorted(np.flatnonzero(finite), key=lambda k: (sizes[k], -objectives[k]))
        current = order[0]
        for k in order[1:]:
            gain = mean[current] - mean[k]
            # each added term closes its share of what is left: two terms that together close a tenth earn none
            share = 1.0 - (1.0 - self.min_gain) ** max(int(sizes[k] - sizes[current]), 1)
            if gain > paired_se(E[k], E[current]) and gain > share * max(
                mean[current] - floor, FLOOR_RESOLUTION * floor
            ):
                current = k
        return int(current), (
            f"from the simplest, a richer structure only when it lowers the cross-validated "
            f"error beyond one standard error and each added term by {100 * self.min_gain:g} % of the "
            f"gap to the noise floor (at least {100 * FLOOR_RESOLUTION:g} % of the floor)"
        )

    @staticmethod
    def complexity(expr: sp.Expr) -> tuple[int, int, int]:
        """Parsimony key of a term (see :func:`complexity`)."""
        return complexity(expr)


#: The rule used where none is given.
DEFAULT = SelectionRule()
