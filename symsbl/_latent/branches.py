"""The three explanations of a record with a latent state, as starting models, and the verdict between them.

- *linear*: ``m y'' + c y' + k y = u``;
- *memoryless*: ``m y'' + c y' + k y + sum eta phi(y, y') = u`` (a nonlinear spring or damper);
- *hidden*: ``m y'' + c y' + k y + z = u`` with ``z' = sum xi theta(y', z)``.

Each is written in the states ``(y, v, z)`` as ``v' = u/m - k/m y - c/m v - ... - z/m``; the
coefficient of ``z`` is held at the split's ``-1/m`` (the scale convention: ``z`` is a force in the
units of ``u``). On several degrees of freedom the host's ``u`` is its drive ``d`` (see :mod:`.hosts`),
every other velocity equation starts from its least-squares fit, and ``z`` is in the input's units where
the input acts on the host, else per unit mass.

The verdict takes the branch of highest output-error log evidence; the hidden one must beat the others
by the per-term penalty ``1/2 log N + log M`` and have a law that is not ``z' = v g(z)``, which
integrates to ``z = G(y)``, an elastic force that the memoryless branch names directly.
"""

from __future__ import annotations

import dataclasses
import math
import re

import casadi as ca
import numpy as np
import sympy as sp

from .._base.rule import DEFAULT as DEFAULT_RULE
from .._base.rule import SelectionRule
from .._model import Equation, IdentifiedModel, TermEstimate
from .._regression.rvm import RVM
from .._symbolic.library import Library
from .hosts import Drive
from .periodic import Spectra
from .skeleton import Skeleton

__all__ = ["Screened", "Branches", "unused", "rivals", "margin"]


@dataclasses.dataclass(frozen=True)
class Screened:
    """What stages 1-3 found.

    Attributes
    ----------
    spectra : Spectra
    linear, skeleton : Skeleton
        The linear fit and its split from the hidden force.
    law_terms : list of Term
        Candidates of the hidden law; ``law`` the RVM screen on them.
    force_terms : list of Term
        Candidates of the memoryless force; ``memory`` the RVM screen on ``[y'', y', y, *force_terms]``.
    """

    spectra: Spectra
    linear: Skeleton
    skeleton: Skeleton
    law_terms: list
    law: RVM
    force_terms: list
    memory: RVM

    @property
    def n_candidates(self) -> int:
        return len(self.law_terms) + len(self.force_terms)

    def candidates(self, variables) -> dict:
        """The library the output-error selection of the hidden branch screens for law terms the weak-form
        screen missed: at 2 % noise a Bouc-Wen law of exponent 2 lost its ``v z^2`` to three look-alikes that
        fit the record as well, and the output-error score finds it (+270 nats). The memoryless branch is not
        screened: its equation-error screen regresses measured quantities only and was complete in every case
        measured, and screening multiplied that branch's time by 3-5."""
        return {"hidden": Library(list(self.law_terms), list(variables))}


class Branches:
    """Models of the three branches in the states ``(y, v, z)``, or of a structure whose host is ``(y, v)``.

    Parameters
    ----------
    states : tuple of casadi.SX
        The model's states in its order: ``(y, v, z)`` on one degree of freedom.
    u : casadi.SX
        The input.
    y, v, z : str
        Names of the host's position, its velocity and the latent state.
    drive : Drive, optional
        On several degrees of freedom, the host's drive and the other velocity equations (see
        :func:`.hosts.drives`); by default the input alone drives the one degree of freedom.
    """

    def __init__(self, states, u, y: str, v: str, z: str, drive: Drive | None = None):
        self.states, self.u, self.y, self.v, self.z = states, u, y, v, z
        self.sym = {s.name(): s for s in states}
        self.variables = {**self.sym, u.name(): u}
        self.drive = drive.terms if drive is not None else ((u.name(), 1.0),)
        self.others = drive.others if drive is not None else {}
        self.pairs = drive.pairs if drive is not None else ((y, v),)

    def starts(self, s: Screened) -> dict:
        """The starting model of each branch."""
        memory = s.memory
        return {
            "linear": self.model(s.linear, [], []),
            "memoryless": self.model(
                _memoryless_skeleton(memory, s.linear),
                [(s.force_terms[i - 3], memory, i) for i in memory.active_ if i >= 3],
                [],
            ),
            "hidden": self.model(s.skeleton, [], [(s.law_terms[i], s.law, i) for i in s.law.active_]),
        }

    def model(self, skeleton: Skeleton, forces, laws) -> IdentifiedModel:
        """``v' = (u - c v - k y - sum eta phi - z) / m`` and ``z' = sum xi theta`` from screened columns."""
        m, sv = skeleton.m, self.sym
        terms = [_estimate(self.variables[n], kappa / m) for n, kappa in self.drive]
        terms += [_estimate(sv[self.y], -skeleton.k / m), _estimate(sv[self.v], -skeleton.c / m)]
        terms += [_estimate(t.expr, -fit.coef_[i] / m, fit, i) for t, fit, i in forces]
        hidden = bool(laws)
        if hidden:
            terms.append(TermEstimate(expr=sv[self.z], coef=-1 / m, std=0.0, fixed=True))
        by_state = {x: Equation.kinematic(x, sv[w]) for x, w in self.pairs}
        by_state[self.v] = _equation(self.v, terms)
        for w, fitted in self.others.items():
            by_state[w] = _equation(w, [_estimate(self.variables[n], c) for n, c in fitted])
        if hidden:
            by_state[self.z] = _equation(self.z, [_estimate(t.expr, fit.coef_[i], fit, i) for t, fit, i in laws])
        states = self.states if hidden else tuple(s for s in self.states if s.name() != self.z)
        return IdentifiedModel(
            states=states,
            inputs=(self.u,),
            equations=tuple(by_state[s.name()] for s in states),
            kinematics=tuple(self.pairs),
            measured=tuple(x for x, _ in self.pairs),
        )

    def with_latent(self, model: IdentifiedModel, keep: bool) -> IdentifiedModel:
        """The chosen branch in the states asked for: without a hidden law, ``z' = 0`` and ``z`` used nowhere."""
        return model if keep else unused(model, self.states, self.z)

    def forces(self, model: IdentifiedModel) -> list:
        """The terms of the host's equation beyond its drive and skeleton (a memoryless force, a latent state)."""
        skeleton = {*dict(self.drive), self.y, self.v}
        return [t for t in model.equation(self.v).terms if t.name not in skeleton]

    def integrable(self, terms) -> bool:
        """Every term is ``v g(z)``: the law integrates to ``z = G(y)``, an elastic force."""
        for term in terms:
            symbols = {s.name: s for s in term.sympy.free_symbols}
            if self.v not in symbols:
                return False
            rest = sp.simplify(term.sympy / symbols[self.v])
            if self.v in {s.name for s in rest.free_symbols}:
                return False
        return True

    def verdict(self, fits: dict, n_samples: int, n_candidates: int, rule: SelectionRule = DEFAULT_RULE):
        """``(verdict, best branch, log evidence by branch)`` of the refined branches (a branch whose refinement
        diverged is absent from ``fits``)."""
        scores = {k: float(f.metadata["refine"]["log_evidence"]) for k, f in fits.items()}
        penalty = margin(n_samples, n_candidates, rule)
        visible = max((k for k in ("linear", "memoryless") if k in fits), key=scores.__getitem__, default=None)
        if visible == "memoryless" and "linear" in fits and not self.forces(fits["memoryless"]):
            visible = "linear"  # its selection removed every force term
        law = fits["hidden"].equation(self.z).terms if "hidden" in fits else ()
        if visible is None:  # only the hidden branch could be simulated
            return "hidden", "hidden", scores
        if law and not self.integrable(law) and scores["hidden"] > scores[visible] + penalty:
            return "hidden", "hidden", scores
        return f"nothing hidden ({'memoryless force' if visible == 'memoryless' else 'linear'})", visible, scores


def margin(n_samples: int, n_candidates: int, rule: SelectionRule = DEFAULT_RULE) -> float:
    """The nats by which a hidden branch must beat the others: the rule's per-term penalty."""
    return rule.nats_per_term(n_samples, n_candidates)


def rivals(branches: dict, chosen: str, nats: float, latent: str) -> dict:
    """The refined branches of another structure whose log evidence lies within ``nats`` of the chosen
    one's, by name: their log evidence minus the chosen one's.

    The verdict needs a hidden branch to win by its :func:`margin`; within it the record does not tell the two apart
    (measured: a Maxwell element's hidden state driven by the velocity or by the position, one transfer
    function realized twice, 1.1 nats apart on 10000 samples). Branches that reached the chosen structure from
    other starts are the same model, not rivals; so is a branch whose latent state no other equation uses (its
    law is then idle, and the branch is "nothing hidden").

    Parameters
    ----------
    branches : dict
        ``metadata["latent"]["branches"]``: per branch, its ``log_evidence`` and its ``terms`` by equation.
    chosen : str
        The branch the verdict took.
    nats : float
        The verdict's :func:`margin`.
    latent : str
        The latent state: its law counts only where another equation uses it.
    """
    best = branches[chosen]
    state = re.compile(rf"(?<![\w.]){re.escape(latent)}(?![\w(])")  # the state in a term's name

    def structure(branch: dict) -> dict:
        terms = {lhs: sorted(names) for lhs, names in branch["terms"].items() if names}
        used = any(state.search(t) for lhs, names in terms.items() if lhs != latent for t in names)
        return {lhs: names for lhs, names in terms.items() if lhs != latent or used}

    return {
        name: b["log_evidence"] - best["log_evidence"]
        for name, b in branches.items()
        if name != chosen and abs(b["log_evidence"] - best["log_evidence"]) <= nats and structure(b) != structure(best)
    }


def unused(model: IdentifiedModel, states, z: str) -> IdentifiedModel:
    """``model`` in the ``states`` asked for (casadi symbols), with ``z' = 0`` and ``z`` used nowhere."""
    by_state = {eq.lhs: eq for eq in model.equations}
    by_state[z] = Equation(z, (), np.zeros((0, 0)), math.nan, math.nan, 0)
    return dataclasses.replace(model, states=tuple(states), equations=tuple(by_state[s.name()] for s in states))


def _memoryless_skeleton(fit, linear: Skeleton) -> Skeleton:
    m, c, k = (float(fit.coef_[i]) for i in range(3))
    return Skeleton(m if m > 0 else linear.m, c, k)


def _estimate(expr, coef, fit=None, i=None) -> TermEstimate:
    """A starting term. The screen's prior precisions are not carried over: its residual is systematic
    (see :mod:`.law`), and a precision that pins a spurious term at zero would keep it out of reach of
    the output-error selection; the refinement starts from its own default prior."""
    if fit is None:
        return TermEstimate(expr=ca.SX(expr), coef=float(coef), std=abs(float(coef)) * 1e-2)
    pos = list(fit.active_).index(i)
    scale = abs(float(coef) / float(fit.coef_[i])) if fit.coef_[i] else 1.0
    return TermEstimate(expr=ca.SX(expr), coef=float(coef), std=float(math.sqrt(fit.sigma_[pos, pos])) * scale)


def _equation(lhs: str, terms) -> Equation:
    cov = np.diag([t.std**2 for t in terms]) if terms else np.zeros((0, 0))
    return Equation(lhs, tuple(terms), cov, math.nan, math.nan, 0)
