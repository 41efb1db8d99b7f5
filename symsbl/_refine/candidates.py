"""What the output-error selection tries, and with which prior.

- :class:`Rebased`: the candidate library written in the model's own symbols;
- :func:`candidates`: per equation, the equation-error runners-up and indistinguishable terms, the
  library's look-alikes of its terms, and its terms of one variable alone;
- :func:`prior`: prior precisions of every coefficient of a compiled structure;
- :func:`extend`: a structure widened by terms the output-error screen proposed.
"""

from __future__ import annotations

import dataclasses
import functools

import casadi as ca
import numpy as np
import sympy as sp
from sympy.calculus.singularities import singularities

from .._base.errors import ParameterError, expected
from .._base.rule import complexity
from .._model import IdentifiedModel
from .._symbolic.library import Library, Term
from .engine import Engine
from .rows import design_rows, term_values

__all__ = [
    "Rebased",
    "pole_within",
    "candidates",
    "look_alikes",
    "partial_cosines",
    "LOOK_ALIKE",
    "PER_EQUATION",
    "ALONE_EVERYWHERE",
    "neighbourhood",
    "prior",
    "extend",
]


#: Functions infinite at finite arguments: a term holding one is checked for a pole where the records run.
POLES = (sp.tan, sp.cot, sp.sec, sp.csc, sp.log)


@functools.lru_cache(maxsize=4096)
def pole_within(expr: sp.Expr, ranges: tuple[tuple[str, float, float], ...]) -> bool:
    """Whether ``expr`` is infinite somewhere in ``ranges`` (``(name, low, high)`` of each variable, one variable at
    a time): ``tan(v)`` where ``v`` spans more than ``pi``, ``log(x)`` where ``x`` crosses 0. Only terms holding a
    function of :data:`POLES` or a negative power are examined (sympy's ``singularities``)."""
    if not (expr.has(*POLES) or any(p.exp.is_negative for p in expr.atoms(sp.Pow))):
        return False
    for name, low, high in ranges:
        symbol = next((s for s in expr.free_symbols if str(s) == name), None)
        if symbol is None or not low < high:
            continue
        try:
            if singularities(expr, symbol, sp.Interval(low, high)) != sp.S.EmptySet:
                return True
        except (NotImplementedError, TypeError, ValueError):  # sympy cannot tell: the term stays a candidate
            continue
    return False


class Rebased:
    """A library's terms written in a model's own symbols (matched by name), as far as refinement reads it.

    With ``ranges`` (``{variable: (low, high)}`` over the records), a term infinite within them is left out: no
    simulation passes through its pole (``tan(v)`` of a velocity spanning +-40 once set the fixed-step integrator
    to its cap of 32 substeps, through its slope near a pole, and made every pass of the fit eight times longer).
    """

    def __init__(self, library: Library, model: IdentifiedModel, ranges: dict | None = None):
        own = {s.name(): s for s in model.states + model.inputs}
        names = library.variable_names
        missing = [n for n in names if n not in own]
        if missing:
            raise ParameterError(
                expected(
                    "library", f"terms of the model's states and inputs {list(own)}", f"terms of {missing}", raw=True
                )
            )
        box = tuple(sorted((n, float(a), float(b)) for n, (a, b) in (ranges or {}).items()))
        poles = [pole_within(t.sympy, box) for t in library.terms]
        kept = [t for t, pole in zip(library.terms, poles) if not pole]
        old, new = ca.vertcat(*library.variables), ca.vertcat(*(own[n] for n in names))
        self.terms = tuple(Term._from_parts(ca.substitute(t.expr, old, new), t.sympy) for t in kept)
        #: The library's size: the candidates the penalty counts (a term left out was offered all the same).
        self.offered = len(library.terms)
        #: The library's terms left out for a pole within the records' range.
        self.with_poles = tuple(t.name for t, pole in zip(library.terms, poles) if pole)
        self._by_name = {t.name: t for t in self.terms}
        self.keys = [complexity(t.sympy) for t in self.terms]

    def __len__(self) -> int:
        return len(self.terms)

    def __contains__(self, name) -> bool:
        return name in self._by_name

    def __getitem__(self, name: str) -> Term:
        return self._by_name[name]


#: Partial cosine with a selected term (the other terms of its equation projected out) above which a
#: library term is tried in its place: the equation error, on an estimated velocity, can rank ``sin(v)``
#: over ``v`` (partial cosine 0.99 at |v| < 2) where the output error separates them by thousands of nats.
LOOK_ALIKE = 0.95
#: Partial cosine above which a term's closest simpler look-alike (:func:`symsbl._regression.support.complexity`) is
#: tried in place of a term that is not a polynomial, when no look-alike reached :data:`LOOK_ALIKE`: the
#: equation error on noisy records can take ``sign(v)`` with a stronger ``v|v|`` for viscous damping with
#: quadratic drag (partial cosine of ``v`` with ``sign(v)`` 0.86 on a multisine record), which the output
#: error puts 267 nats below the truth.
SIMPLER_ALIKE = 0.8
#: Alternatives and look-alikes tried per equation at most (the runners-up come on top).
PER_EQUATION = 6
#: Terms of one variable tried in every equation while the library holds at most this many; beyond, an
#: equation tries those of the variables it holds, their kinematic partners and the inputs (see
#: :func:`candidates`).
ALONE_EVERYWHERE = 8


def candidates(model: IdentifiedModel, library: Rebased, Z: np.ndarray):
    """Terms to try in each equation: the equation-error indistinguishables, each term's closest look-alike
    in the library on the rows ``Z`` of states and inputs (see :data:`LOOK_ALIKE`), at most
    :data:`PER_EQUATION`, and the runners-up (two at most) whatever the count: on a record where every
    term of an equation had two indistinguishable alternatives, the cap once left out the true term
    ranked second by the equation error (x^3 of an asymmetric softening oscillator, 0.4 N of a 25 N
    spring force at the peaks), and the output error made up for it with four wrong terms (178 nats
    below the truth). On top, every term of the library that is one variable alone (``v3``, ``F``) and
    that the equation lacks: a weak linear damping or coupling is what the equation error's penalty
    leaves out under noise first, and what a free-run simulation resolves (a chain of five masses damped
    at 0.5 % of critical, 287 candidates: seven of its thirteen damping terms missing from the equation
    error's model, five from the output error's with three spurious terms in their place; all found, and
    nothing else, with them tried). Where the library holds more than :data:`ALONE_EVERYWHERE` such terms,
    an equation tries those of its neighbourhood: the variables its terms hold, its own state, their
    kinematic partners and the inputs (a chain of ten masses, positions measured, offered 21 in each of
    its ten equations: 264 coefficients compiled at once, 167 with the neighbourhoods; the chain of five
    stays exact, every state measured or the positions alone).

    Returns ``({state: [(expr, 0.0), ...]}, {state: {look-alike: term}})``: a look-alike is tried in its
    term's place, not beside it (see :func:`symsbl._refine.selection.select`).
    """
    with np.errstate(all="ignore"):
        values = term_values([t.expr for t in library.terms], model, Z)
    finite = np.all(np.isfinite(values), axis=0)
    alone = [t.name for t in library.terms if t.sympy.is_Symbol]
    out, twins = {}, {}
    for eq in model.equations:
        if eq.fixed:
            continue
        around = neighbourhood(eq, model) if len(alone) > ALONE_EVERYWHERE else set(alone)
        near = [n for n in alone if n in around]
        alike = look_alikes(eq, library, model, Z, values, finite)
        present = set(eq.names)

        def usable(names, present=present):
            return [n for n in dict.fromkeys(names) if n in library and n not in present]

        kept = usable([n for t in eq.terms for n in t.alternatives] + list(alike))[:PER_EQUATION]
        kept += [n for n in usable(eq.runners_up) if n not in kept]
        pairs = {n: alike[n] for n in kept if n in alike}  # a term of one variable added below goes beside
        kept += [n for n in usable(near) if n not in kept]
        if kept:
            out[eq.lhs] = [(library[n].expr, 0.0) for n in kept]
            twins[eq.lhs] = pairs
    return out, twins


def neighbourhood(eq, model: IdentifiedModel) -> set[str]:
    """The variables of ``eq``'s terms, its own state, their kinematic partners and the model's inputs."""
    names = {str(s) for t in eq.terms for s in t.sympy.free_symbols} | {eq.lhs}
    for pair in model.kinematics:
        if names & set(pair):
            names |= set(pair)
    return names | set(model.input_names)


def look_alikes(
    eq, library: Rebased, model: IdentifiedModel, Z: np.ndarray, values: np.ndarray, finite: np.ndarray
) -> dict:
    """Per free term of ``eq``, the library term (not in ``eq``, not already its alternative or runner-up)
    whose values on ``Z``, with the equation's other terms projected out, are closest in direction to the
    term's, when their partial cosine reaches :data:`LOOK_ALIKE`, else for a term that is not a polynomial
    its closest simpler one above :data:`SIMPLER_ALIKE`: ``{look-alike: term}``. ``values``: the
    library's terms on ``Z``; ``finite``: which of them are finite there."""
    taken = set(eq.names) | {a for t in eq.terms for a in t.alternatives} | set(eq.runners_up)
    usable = np.flatnonzero([finite[k] and t.name not in taken for k, t in enumerate(library.terms)])
    if not eq.terms or not usable.size:
        return {}
    with np.errstate(all="ignore"):
        A = term_values([t.expr for t in eq.terms], model, Z)
    if not np.all(np.isfinite(A)):
        return {}
    keys = library.keys
    keys_own = [complexity(t.sympy) for t in eq.terms]
    pairs, closest_simpler = [], {}
    cosines = partial_cosines(A, values[:, usable])
    for j, term in enumerate(eq.terms):
        if term.fixed:
            continue
        cos = cosines[j]
        pairs += [(-float(cos[k]), j, int(usable[k])) for k in np.flatnonzero(cos >= LOOK_ALIKE)]
        simpler = [k for k in np.argsort(-cos) if cos[k] >= SIMPLER_ALIKE and keys[usable[k]] < keys_own[j]]
        if keys_own[j][0] > 0 and simpler:
            closest_simpler[j] = int(usable[simpler[0]])
    # One look-alike per term and one term per look-alike, the closest pairs first: with v|v| and sin(v)
    # both in an equation, v resembles each (partial cosines 0.9968 and 0.9986 on a drag oscillator); given
    # to the first term only, v was tried in the place of v|v| and never of sin(v), which stayed (the drag
    # coefficient 12 % off, 100 posterior standard deviations).
    found, matched = {}, set()
    for _, j, k in sorted(pairs):
        name = library.terms[k].name
        if j not in matched and name not in found:
            found[name] = eq.terms[j].name
            matched.add(j)
    for j, k in closest_simpler.items():
        name = library.terms[k].name
        if j not in matched and name not in found:
            found[name] = eq.terms[j].name
    return found


#: Share of a candidate's squared norm outside ``span(A)`` below which :func:`partial_cosines` projects it (the
#: difference of squares keeps about ``log10(1 / NEAR_SPAN)`` fewer digits than the projection).
NEAR_SPAN = 1e-4


def partial_cosines(A: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``|cos|`` of the angle between each column ``j`` of ``A`` (n_rows, n_terms) and each column of ``V``
    (n_rows, n_candidates), both with ``A``'s other columns projected out: ``(n_terms, n_candidates)``.

    ``span(A)`` is the others' span plus the unit direction ``d`` of column ``j``'s part they miss, so a
    candidate ``v`` less its projection on the others is ``v_A + (d . v) d``, ``v_A`` its part outside
    ``span(A)``: one pass over the candidates serves every column (a pass per column cost seconds on a
    library of 390 terms). ``|v_A|^2 = |v|^2 - |Q^T v|^2`` needs no array of ``V``'s size (the projection did:
    1.4 s a call, mostly writing fresh memory, on a ten-mass chain's 16385 rows and 1772 candidates, against
    0.3 s); a candidate within :data:`NEAR_SPAN` of ``span(A)``, where the difference loses digits, is
    projected."""
    Q_all = np.linalg.qr(A)[0]
    total = np.einsum("ij,ij->j", V, V)
    P = Q_all.T @ V
    outside = total - np.einsum("ij,ij->j", P, P)
    near = outside <= NEAR_SPAN * total
    if near.any():
        W = V[:, near]
        outside[near] = np.linalg.norm(W - Q_all @ (Q_all.T @ W), axis=0) ** 2
    out = np.zeros((A.shape[1], V.shape[1]))
    for j in range(A.shape[1]):
        others = np.delete(A, j, axis=1)
        Q = np.linalg.qr(others)[0] if others.shape[1] else np.zeros((len(A), 0))
        rj = A[:, j] - Q @ (Q.T @ A[:, j])
        size = np.linalg.norm(rj)
        along = (rj / size) @ V if size > 0 else np.zeros(V.shape[1])
        norms = np.sqrt(outside + along**2)
        out[j] = np.abs(along) / np.where(norms > 0, norms, np.inf)
    return out


def prior(engine: Engine) -> np.ndarray:
    """Prior precisions of every coefficient of the compiled structure: the model's own (the relevance
    vector machine's, else ``1 / coef^2``); for an alternative the equation-error fit found
    indistinguishable from a term, that term's prior on the same contribution; for another candidate, and
    for a term of the model started at zero with no prior of its own, ``(s_term / s_rhs)^2``, a prior wide
    enough for it to carry the whole right-hand side (``1 / 0^2`` would hold it at zero)."""
    model = engine.model
    Z = design_rows(model, engine.records, engine.guess)
    alpha: list[float] = []
    for eq, full in zip(model.equations, engine.full.equations):
        if full.fixed:
            continue
        if len(full.terms) == len(eq.terms) and not any(_unset(t) for t in full.terms):
            alpha.extend(own_alpha(t) for t in full.terms if not t.fixed)  # the model's own: no term values needed
            continue
        D = term_values([t.expr for t in full.terms], model, Z)
        scale = float(np.std(D[:, : len(eq.terms)] @ eq.coefs)) if eq.terms else 1.0
        for k, t in enumerate(full.terms):
            if t.fixed:
                continue
            if k < len(eq.terms) and not _unset(t):
                alpha.append(own_alpha(t))
                continue
            s = float(np.std(D[:, k]))
            twin = next((j for j, u in enumerate(eq.terms) if t.name in u.alternatives), None)
            s_twin = float(np.std(D[:, twin])) if twin is not None else 0.0
            if twin is not None and s > 0 and s_twin > 0:
                # an indistinguishable alternative: the same prior on its contribution
                alpha.append(own_alpha(eq.terms[twin]) * (s / s_twin) ** 2)
            else:  # (a constant's twin has no spread to compare with)
                alpha.append((s / scale) ** 2 if s > 0 and scale > 0 else 1.0)
    return np.array(alpha)


def _unset(term) -> bool:
    """A free term started at zero with no prior precision of its own (a term for the fit to find)."""
    return not term.fixed and term.coef == 0.0 and not (np.isfinite(term.alpha) and term.alpha > 0)


def own_alpha(term) -> float:
    return term.alpha if np.isfinite(term.alpha) and term.alpha > 0 else 1.0 / max(term.coef**2, 1e-300)


def extend(engine: Engine, sol, alpha: np.ndarray, candidates: dict, screened: dict, library: Rebased):
    """The engine, solution and prior precisions with the screened terms added to the candidates (held at zero
    in the solution); unchanged when the screen found nothing new."""
    merged = {lhs: list(c) for lhs, c in candidates.items()}
    new = False
    for lhs, names in screened.items():
        have = {str(e) for e, _ in merged.get(lhs, [])}
        for name in names:
            expr = library[name].expr
            if str(expr) not in have:
                merged.setdefault(lhs, []).append((expr, 0.0))
                new = True
    if not new:
        return engine, sol, alpha
    settings = dataclasses.replace(engine.settings, noise=engine.noise)  # the noise model the fit chose
    wider = Engine(engine.model, engine.records, engine.measured, settings, merged, guess=engine.guess)
    alpha = prior(wider)
    theta = np.zeros(len(wider.positions))
    theta[wider.base] = sol.theta[engine.base]
    fitted_alpha = alpha.copy()
    fitted_alpha[wider.base] = sol.alpha[engine.base]
    return wider, dataclasses.replace(sol, theta=theta, alpha=fitted_alpha, active=wider.base), alpha
