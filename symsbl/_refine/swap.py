"""Swaps: a selected term exchanged for a library term that does its work better.

The selection removes terms from one extended fit; terms proposed for a law that none of them is stay when
their sum is what fits (``tan(v)`` beside ``v`` for the drag ``v + v|v|`` at ``|v| < 0.75``), and the term
that is the law is never a candidate: its score at their fit is nil, as they already explain what it would.

A swap asks the quadratic model of the output error, at the selected fit, what exchanging terms ``out`` of an
equation (one, or two that together stand in for one) for a library term ``j`` would gain: with ``d =
-theta_out`` the move that removes them and ``F`` the remaining terms and ``j``,

    gain = 1/2 b_F' P_FF^-1 b_F + p_out' d - 1/2 d' P_out,out d - 1/2 p_A' P_AA^-1 p_A,   b_F = p_F - S_F,out d,

with ``S`` and ``g`` the data's information and gradient (initial states eliminated, as in :mod:`.screen`),
``p = g - alpha theta`` the log posterior's gradient, ``P = S + diag(alpha)`` and ``A`` the terms held: the
maximum of the log posterior's quadratic model with ``out`` gone (their priors with them) less its maximum
with them held; two for one also saves a term's penalty. Two structures that give the same trajectory give the
same sensitivities along it, so the model holds for swaps between look-alikes however far their coefficients
move. The terms tried are those the equation's selected terms nearly span (:data:`SPANNED`): a term they can
reproduce can take the place of one or two of them. The :data:`REFITS` best swaps predicted to gain more than
the rule's ``margin_nats`` are refitted; of those whose refit beats the structure by that margin the best is
kept, every kept term must then clear the penalty again, and another round starts from there.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._base.errors import SimulationError
from .._base.rule import SelectionRule
from .candidates import Rebased, prior
from .engine import Engine
from .rows import design_rows, term_values
from .screen import blocks_info
from .selection import _every_term_clears, objective

__all__ = ["swap_terms", "swap_gains", "SPANNED", "MAX_POOL", "POOL_PER_EQUATION", "REFITS", "ROUNDS", "ROWS"]

#: A library term is tried in a selected term's place when the equation's selected terms span it this closely
#: (the cosine of its angle to their span): a term they nearly reproduce can take the place of one of them.
SPANNED = 0.95
#: Library terms added to the compiled structure for the swaps at most, over all equations, but at least
#: :data:`POOL_PER_EQUATION` per equation.
MAX_POOL = 24
POOL_PER_EQUATION = 3
#: Predicted swaps refitted per round at most (the largest gains first).
REFITS = 2
#: Rounds of swaps at most (each keeps one).
ROUNDS = 2
#: Rows of the model's states and inputs the library terms are compared on (evenly thinned).
ROWS = 4000


def swap_gains(S: np.ndarray, g: np.ndarray, theta: np.ndarray, alpha: np.ndarray, active, moves):
    """The quadratic model's gain of each move (see the module text).

    Parameters
    ----------
    S, g : ndarray, shapes (n, n) and (n,)
        The data's information and gradient of every coefficient at the fit (initial states eliminated).
    theta, alpha : ndarray, shape (n,)
        The fit's coefficients and prior precisions.
    active : array of int
        The coefficients held.
    moves : list of (tuple of int, int)
        Each ``(out, j)``: the held coefficients ``out`` removed and ``j`` added.

    Returns
    -------
    gains : ndarray, shape (len(moves),)
        Nats (``-inf`` where the quadratic model is singular).
    moved : list of ndarray, shape (n,)
        The coefficients the quadratic model predicts after each move.
    """
    active = np.asarray(active, dtype=int)
    post = g - alpha * theta  # the log posterior's gradient (zero on ``active`` at its optimum)
    P = S + np.diag(alpha)
    here = 0.5 * post[active] @ np.linalg.solve(P[np.ix_(active, active)], post[active])
    gains, moved = np.full(len(moves), -np.inf), []
    for n, (out, j) in enumerate(moves):
        out = list(out)
        free = np.append(active[~np.isin(active, out)], j)
        d = -theta[out]
        b = post[free] - S[np.ix_(free, out)] @ d
        theta_n = theta.copy()
        theta_n[out] = 0.0
        moved.append(theta_n)
        try:
            step = np.linalg.solve(P[np.ix_(free, free)], b)
        except np.linalg.LinAlgError:
            continue
        theta_n[free] += step
        gains[n] = 0.5 * b @ step + post[out] @ d - 0.5 * d @ P[np.ix_(out, out)] @ d - here
    return gains, moved


def _pool(engine: Engine, sol, library: Rebased, Z: np.ndarray, values: np.ndarray) -> tuple[dict, dict]:
    """Per fitted equation, the library terms to try in the place of its selected terms (``{state: [name]}``)
    and, per name, the selected terms it may replace (``{(state, name): {term}}``): those the selected terms
    span, closest first (see :data:`SPANNED`); ``values``: the library's terms on the rows ``Z``."""
    finite = np.all(np.isfinite(values), axis=0)
    chosen = set(int(k) for k in sol.active)
    fitted = [i for i, eq in enumerate(engine.full.equations) if not eq.fixed]
    share = max(POOL_PER_EQUATION, MAX_POOL // max(len(fitted), 1))
    pool: dict[str, list[str]] = {}
    replaces: dict[tuple[str, str], set] = {}
    for i in fitted:
        eq = engine.full.equations[i]
        own = [eq.terms[j] for k, (ii, j) in enumerate(engine.positions) if ii == i and k in chosen]
        names = {t.name for t in own}
        usable = [m for m, t in enumerate(library.terms) if finite[m] and t.name not in names]
        with np.errstate(all="ignore"):
            A = term_values([t.expr for t in own], engine.model, Z)
        if not own or not usable or not np.all(np.isfinite(A)):
            continue
        V = values[:, usable]
        Q = np.linalg.qr(A)[0]
        size = np.linalg.norm(V, axis=0)
        spanned = np.linalg.norm(Q.T @ V, axis=0) / np.where(size > 0, size, np.inf)
        for m in [m for m in np.argsort(-spanned) if spanned[m] >= SPANNED][:share]:
            name = library.terms[usable[m]].name
            pool.setdefault(eq.lhs, []).append(name)
            replaces[(eq.lhs, name)] = names
    return pool, replaces


def _widened(engine: Engine, sol, alpha: np.ndarray, pool: dict, library: Rebased, jit=None, lean=False):
    """``engine`` compiled with the terms of ``pool`` added to those it tries (``lean``: of those, only the ones
    ``sol`` holds; ``jit`` overrides its setting): the new engine, ``sol`` carried over to it by term (the new
    terms at zero, its prior precisions where it has them, else :func:`prior`'s) and the prior precisions
    ``alpha`` carried over the same way."""
    held = {engine.names[k] for k in sol.active} if lean else set(engine.names)
    merged: dict[str, list] = {}
    for eq, full in zip(engine.model.equations, engine.full.equations):
        extra = [(t.expr, 0.0) for t in full.terms[len(eq.terms) :] if (eq.lhs, t.name) in held]
        if extra:
            merged[eq.lhs] = extra
    # by name, as every mapping between the engines goes: a term already compiled is not added twice
    have = held | {engine.names[k] for k in engine.base}
    for lhs, names in pool.items():
        merged.setdefault(lhs, []).extend((library[n].expr, 0.0) for n in names if (lhs, n) not in have)
    settings = dataclasses.replace(engine.settings, noise=engine.noise)  # the noise model the fit chose
    if jit is not None:
        settings = dataclasses.replace(settings, jit=jit)
    wider = Engine(engine.model, engine.records, engine.measured, settings, merged, guess=engine.guess)
    wider.longest = engine.longest  # segments held short stay short: the evidences compare
    where = _where(engine, wider)
    kept = where >= 0
    fresh = prior(wider)
    walpha, fitted, theta = fresh.copy(), fresh, np.zeros(len(wider.positions))
    walpha[kept], theta[kept], fitted[kept] = alpha[where[kept]], sol.theta[where[kept]], sol.alpha[where[kept]]
    active = np.flatnonzero(np.isin(where, sol.active) & kept)
    wide = dataclasses.replace(sol, theta=theta, alpha=fitted, active=active)
    return wider, wide, walpha


def _where(source: Engine, target: Engine) -> np.ndarray:
    """Per position of ``target``, the position of the same term in ``source`` (-1 where it has none)."""
    return np.array([source.index.get(name, -1) for name in target.names], dtype=int)


def _moves(engine: Engine, sol, replaces: dict) -> list[tuple[tuple, int]]:
    """The moves ``(out, j)`` of compiled positions: each term :func:`_pool` proposed in the place of one of
    the terms it may replace, or of two (a pair of look-alikes that together stand in for it)."""
    index = engine.index
    active = set(int(k) for k in sol.active)
    out: list[tuple[tuple, int]] = []
    for (lhs, name), terms in replaces.items():
        j = index.get((lhs, name))
        if j is None or j in active:
            continue
        held = [index[(lhs, t)] for t in sorted(terms) if index.get((lhs, t)) in active]
        out += [((k,), j) for k in held]
        out += [((k, m), j) for a, k in enumerate(held) for m in held[a + 1 :]]
    return out


def _carried(source: Engine, target: Engine, values: np.ndarray) -> np.ndarray:
    """``values`` of ``source``'s coefficients at ``target``'s positions, by term (zero where it has none)."""
    where = _where(source, target)
    return np.where(where >= 0, values[where], 0.0)


def swap_terms(engine: Engine, sol, alpha: np.ndarray, library: Rebased, rule: SelectionRule):
    """The selected fit ``sol`` of ``engine`` with its terms swapped for library terms while a refit's objective
    says so (see the module text).

    Returns
    -------
    engine, sol, alpha
        The engine, the fit and the prior precisions it ends with.
    swaps : list of dict
        Each swap made: ``{"state", "out": [term, ...], "in": term}``.
    """
    cost = float(sol.penalty) if sol.penalty is not None else 0.0
    swaps: list[dict] = []
    Z = design_rows(engine.model, engine.records, engine.guess, most=ROWS)  # every round's engine: the same rows
    with np.errstate(all="ignore"):
        values = term_values([t.expr for t in library.terms], engine.model, Z)
    for _ in range(ROUNDS):
        pool, replaces = _pool(engine, sol, library, Z, values)
        if not replaces:
            break
        # one pass of the terms held and tried: compiling it would cost more than it saves
        once, at, _ = _widened(engine, sol, alpha, pool, library, jit=False, lean=True)
        moves = _moves(once, at, replaces)
        info = blocks_info(once.passes, at) if moves else None
        if info is None:
            break
        gains, moved = swap_gains(*info, at.theta, at.alpha, at.active, moves)
        gains += cost * np.array([len(out) - 1 for out, _ in moves])  # two for one saves a term's penalty
        if not np.any(gains > rule.margin_nats):
            break
        wider, wide, walpha = _widened(engine, sol, alpha, pool, library)
        index = wider.index
        best: tuple | None = None  # (objective, refit, move)
        for n in np.argsort(-gains)[:REFITS]:
            if not gains[n] > rule.margin_nats:
                break
            out, j = moves[n]
            move = (tuple(index[once.names[k]] for k in out), index[once.names[j]])
            trial = _refit(wider, wide, walpha, move, _carried(once, wider, moved[n]))
            if trial is None or objective(trial, cost) <= objective(wide, cost) + rule.margin_nats:
                continue
            if best is None or objective(trial, cost) > best[0]:
                best = (objective(trial, cost), trial, move)
        if best is None:
            break
        _, trial, (out, j) = best
        lhs, term = wider.names[j]
        swaps.append({"state": lhs, "out": [wider.names[k][1] for k in out], "in": term})
        engine, sol, alpha = wider, _every_term_clears(wider, trial, cost), walpha
    return engine, sol, alpha, swaps


def _refit(engine: Engine, sol, alpha: np.ndarray, move: tuple[tuple, int], start: np.ndarray):
    """The refit of ``sol`` with the terms ``move[0]`` exchanged for ``move[1]`` from the coefficients ``start``
    (None if it runs away or ends on shorter segments, where its evidence does not compare)."""
    out, j = move
    active = sorted(set(int(a) for a in sol.active) - set(out) | {j})
    prior = sol.alpha.copy()
    prior[j] = alpha[j]
    try:
        trial = engine.fit(active, start, prior)
    except (SimulationError, np.linalg.LinAlgError):
        return None
    if trial.length < sol.length or not np.isfinite(trial.posterior.log_evidence):
        return None
    return trial
