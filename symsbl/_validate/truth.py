"""How an identified model compares with the system that generated the data: support and coefficients."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import sympy as sp

from .._data.trajectory import Trajectory
from .._model import IdentifiedModel
from .._symbolic.evaluator import Evaluator
from .._symbolic.library import Library

__all__ = ["TruthComparison", "compare_to_truth"]


@dataclass(frozen=True)
class TruthComparison:
    """How an identified model compares with the system that generated the data.

    Attributes
    ----------
    exact_support : bool
        Every equation has exactly the true terms: none missing, none spurious.
    missing, spurious : dict[str, list[str]]
        Per state, true terms not found and found terms not in the truth.
    relative_error : dict[str, dict[str, float]]
        Per state and true term, ``|coef - true| / |true|`` (``inf`` if missing).
    variance_share : dict[str, dict[str, float]]
        Per state and true term, ``var(coef * term)`` divided by the sum of these variances over
        the equation's true terms, on the given data (to judge small terms such as Coulomb
        friction); 1.0 when no data is given.
    """

    exact_support: bool
    missing: dict
    spurious: dict
    relative_error: dict
    variance_share: dict

    def max_error(self, min_share: float = 0.0) -> float:
        """Largest relative coefficient error over terms with at least ``min_share`` of their
        equation's variance."""
        errs = [
            e
            for state, terms in self.relative_error.items()
            for name, e in terms.items()
            if self.variance_share[state][name] >= min_share
        ]
        return max(errs) if errs else 0.0


def _true_terms(system) -> list[dict]:
    """Per equation, ``{term name: (coefficient, sympy term)}`` of the expanded right-hand side."""
    out = []
    for rhs in system.to_sympy():
        terms: dict = {}
        for part in sp.Add.make_args(sp.expand(rhs.rhs)):
            coef, term = part.as_coeff_Mul()
            old = terms.get(str(term), (0.0, term))[0]
            terms[str(term)] = (old + float(coef), term)
        out.append(terms)
    return out


def compare_to_truth(model: IdentifiedModel, system, data: Trajectory | None = None) -> TruthComparison:
    """Compare ``model`` term by term with the true ``system`` (an OdeSystem).

    Terms are matched by their canonical sympy form, so ``Abs(x2)*x3*Abs(x3)`` in the truth
    matches the library term of the same function. A found term that the truth does not
    contain but that is reported indistinguishable from a true term (e.g. ``tan(x1)`` for
    ``x1``) still counts as spurious: parsimony should have kept the true one.

    Parameters
    ----------
    model : IdentifiedModel
    system : OdeSystem
        The system that generated the data.
    data : Trajectory, optional
        Used to compute each true term's variance share.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify(train, library)
    >>> truth = symsbl.compare_to_truth(model, duffing, train)
    >>> truth.exact_support, truth.max_error() < 0.005
    (True, True)
    """
    truth = _true_terms(system)
    missing, spurious, rel, share = {}, {}, {}, {}
    for eq, true_terms in zip(model.equations, truth):
        true = {n: c for n, (c, _) in true_terms.items()}
        found = {t.name: t.coef for t in eq.terms}
        missing[eq.lhs] = sorted(set(true) - set(found))
        spurious[eq.lhs] = sorted(set(found) - set(true))
        rel[eq.lhs] = {n: abs(found.get(n, math.inf) - c) / abs(c) if n in found else math.inf for n, c in true.items()}
        share[eq.lhs] = {n: 1.0 for n in true}
        if data is not None and true:
            variables = list(system.states) + list(system.inputs)
            lib = Library([term for _, term in true_terms.values()], variables)
            Z = np.column_stack([data.column(v.name()) for v in variables])
            D = Evaluator(lib, jit=False).evaluate(Z)
            contrib = {n: np.var(D[:, lib.index(n)] * c) if n in lib else 0.0 for n, c in true.items()}
            total = sum(contrib.values()) or 1.0
            share[eq.lhs] = {n: float(v / total) for n, v in contrib.items()}
    exact = not any(missing.values()) and not any(spurious.values())
    return TruthComparison(exact, missing, spurious, rel, share)
