"""Term selection on the output-error evidence.

The objective is the relevance vector machine's, the :class:`~symsbl.SelectionRule`'s: log evidence minus
``T`` nats per free term (``T = 1/2 log N + log M`` by default, the extended BIC with ``N`` the measured
samples and ``M`` the candidate terms). From one fit of the current structure extended by the candidates (the
equation-error runners-up and the terms it found indistinguishable; of a staged structure, those whose score gain
at the fitted structure clears a share of the penalty), Bayesian model reduction scores removing each
term without refitting; terms are removed one by one while that raises the objective. The structure
it settles on is then refitted, and kept only if the refit confirms the gain.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from .._base.errors import SimulationError
from .._base.rule import DEFAULT as DEFAULT_RULE
from .._base.rule import SelectionRule
from .laplace import reduce_model, reprior
from .rows import design_rows, term_values
from .screen import score_gains

if TYPE_CHECKING:  # the engine builds on this module
    from .engine import Engine

__all__ = ["backward", "select", "objective"]


def backward(post, alpha: np.ndarray, cost_per_term: float, keys, equivalence_nats: float) -> list[int]:
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
        gains = {
            k: reduce_model(post, alpha, removed + [k])[0] - base + cost_per_term for k in range(n) if k not in removed
        }
        best = max(gains.values())
        if best <= 0:
            break
        near = [k for k, g in gains.items() if g > 0 and g >= best - equivalence_nats]
        removed.append(max(near, key=lambda k: (keys[k], -gains[k])))
    return removed


def objective(sol, cost_per_term: float) -> float:
    return sol.posterior.log_evidence - cost_per_term * sol.active.size


def select(
    engine: Engine, first, alpha: np.ndarray, cost_of, twins: dict | None = None, rule: SelectionRule = DEFAULT_RULE
):
    """The sub-structure with the best penalised output-error evidence: model reduction from one fit of
    the model extended by its candidates, confirmed by a refit. ``cost_of(fit)`` gives the nats per term
    from the extended fit (whose residual says how much structure no candidate explains). ``twins``
    (``{state: {look-alike: term}}``) names candidates tried in a term's place: when model reduction keeps
    both, the one whose removal costs less evidence goes (a look-alike added beside its term would soak up
    a misfit the structure has, such as an input interpolated across its steps); when it keeps the more
    complex of a pair alone, the simpler is refitted in its place (see :func:`_simpler_twins`). ``rule`` sets
    the margin within which structures are equivalent."""
    pairs = {lhs: dict(d) for lhs, d in (twins or {}).items()}
    for eq in engine.model.equations:  # and the equation error's indistinguishable alternatives
        for t in eq.terms:
            for a in t.alternatives:
                pairs.setdefault(eq.lhs, {}).setdefault(a, t.name)
    best, cost = _select(engine, first, alpha, cost_of, twins, rule)
    return _every_term_clears(engine, _simpler_twins(engine, best, alpha, pairs, rule), cost)


def _every_term_clears(engine: Engine, best, cost: float):
    """``best`` with every free term's evidence at least the penalty ``cost``, as the model reports it.

    The selection scores changes to a structure, and a structure a change did not beat stays whole: look-alikes
    sharing one role (a damping split over ``v``, ``sin(v)``, ``v^3``, ``v|v|``) can each be worth less than
    the penalty. While a term's evidence from the posterior falls short, the weakest (of equals, the most
    complex) is refitted without; the refit is kept when the objective does not drop, else the term stays with
    the evidence the refit measured, which clears the penalty. The solution carries the penalty and those
    measured evidences (``confirmed``, by structure index), which the model reports.
    """
    confirmed: dict = {}
    while True:  # each round removes a term or confirms one: it ends
        active = [int(k) for k in best.active]
        prior = best.alpha[best.active]
        evidence = {k: confirmed.get(k, -reduce_model(best.posterior, prior, [n])[0]) for n, k in enumerate(active)}
        short = [k for k in active if k not in confirmed and evidence[k] < cost]
        if not short or len(active) < 2:
            break
        k = min(short, key=lambda j: (evidence[j], [-key for key in engine.keys[j]]))
        n = active.index(k)
        _, mean, _ = reduce_model(best.posterior, prior, [n])
        chosen = [j for j in active if j != k]
        start = best.theta.copy()
        start[k], start[chosen] = 0.0, mean
        try:
            refit = engine.fit(chosen, start, best.alpha, warm=best)
        except (SimulationError, np.linalg.LinAlgError):
            refit = None
        if (
            refit is not None
            and np.isfinite(refit.posterior.log_evidence)
            and objective(refit, cost) >= objective(best, cost)
        ):
            best, confirmed = refit, {}
        else:
            confirmed[k] = (
                (best.posterior.log_evidence - refit.posterior.log_evidence)
                if refit is not None and np.isfinite(refit.posterior.log_evidence)
                else np.inf
            )
    return dataclasses.replace(best, confirmed=confirmed, penalty=float(cost))


def _simpler_twins(engine: Engine, best, alpha: np.ndarray, twins: dict, rule: SelectionRule):
    """``best`` with each kept term whose simpler look-alike or alternative was left out replaced by it when
    the refit's evidence is at most ``rule.equivalence_nats`` below (parsimony, as in the equation-error
    selection); ``twins``: ``{state: {look-alike or alternative: term}}``.

    Model reduction scores removals from one posterior, an approximation far from it: on a drag
    oscillator (velocities below 1.3 m/s) it kept ``sin(v)``, with the drag 12 % off, over ``v`` with the true
    drag, which a refit put 1.6 nats higher; on a hardening oscillator it kept ``sin(x)`` for ``x`` (the
    refit 5e-4 nats higher: the same model, since ``x^3`` takes up the difference). One refit per such pair.
    """
    index = engine.index
    rows = None
    for lhs, pairs in twins.items():
        for alike, term in pairs.items():
            a, b = index.get((lhs, alike)), index.get((lhs, term))
            active = set(best.active.tolist())
            if a is None or b is None or (a in active) == (b in active):
                continue
            kept, other = (a, b) if a in active else (b, a)
            if engine.keys[other] >= engine.keys[kept]:
                continue
            if rows is None:
                rows = design_rows(engine.model, engine.records, engine.guess)
            with np.errstate(all="ignore"):
                T = term_values(
                    [
                        engine.full.equations[engine.positions[k][0]].terms[engine.positions[k][1]].expr
                        for k in (kept, other)
                    ],
                    engine.model,
                    rows,
                )
            if not np.all(np.isfinite(T)) or not T[:, 1] @ T[:, 1] > 0:
                continue
            start = best.theta.copy()
            start[other], start[kept] = start[kept] * (T[:, 0] @ T[:, 1]) / (T[:, 1] @ T[:, 1]), 0.0
            prior = best.alpha.copy()
            prior[other] = alpha[other]
            try:
                trial = engine.fit(sorted(active - {kept} | {other}), start, prior)
            except (SimulationError, np.linalg.LinAlgError):
                continue
            if (
                trial.length >= best.length
                and np.isfinite(trial.posterior.log_evidence)
                and trial.posterior.log_evidence >= best.posterior.log_evidence - rule.equivalence_nats
            ):
                best = trial
    return best


#: A staged structure's extended fit takes the candidates whose score gain at the fitted structure is at least
#: this share of the penalty per term (a pair that only together explains something scores less apiece).
PROMISING_SHARE = 0.25


def _promising(engine: Engine, first, cost_of) -> np.ndarray:
    """The coefficients of the extended fit: every one; of a staged structure (see
    :class:`~symsbl._refine.sensitivity.Passes`), whose passes cost in proportion to the coefficients they carry,
    ``first``'s and the candidates whose score gain at ``first`` (one pass, :func:`score_gains`) is at least
    :data:`PROMISING_SHARE` of the penalty ``cost_of(first)``."""
    every = np.arange(len(engine.positions))
    passes = engine.passes
    if not passes.staged:
        return every
    cost = cost_of(first)
    others = np.setdiff1d(every, first.active)
    with np.errstate(all="ignore"):
        blocks = passes.sensitivities(first.theta, first.X0, passes.segments(first.starts), first.w, first.ar)
        found = score_gains(blocks, first.theta.size, first.active, first.alpha[first.active], others)
    if found is None:  # the pass ran away: no candidate is scored
        return first.active
    return np.union1d(first.active, others[found >= PROMISING_SHARE * cost])


def _select(engine: Engine, first, alpha: np.ndarray, cost_of, twins: dict | None, rule: SelectionRule):
    every = _promising(engine, first, cost_of)
    sol = first
    if np.setdiff1d(every, first.active).size:  # candidates to try beyond the fitted structure
        sol = _extended(engine, first, every, alpha)
        if sol is None:  # a candidate that makes the model run away: keep the fitted structure
            return first, cost_of(first)
    cost = cost_of(sol)
    removed, post = _removals(engine, sol, alpha, cost, twins or {}, rule)
    chosen = np.array([k for n, k in enumerate(sol.active) if n not in removed], dtype=int)
    best = first
    if set(chosen) != set(engine.base):
        refit = _reduced(engine, sol, post, alpha, removed)
        if refit is not None and objective(refit, cost) > objective(first, cost):
            best = refit
    if sol is not first and objective(sol, cost) > objective(best, cost) + rule.equivalence_nats:
        pruned = _prune(engine, sol, alpha, cost, twins or {}, rule, tried=removed)
        if objective(pruned, cost) > objective(best, cost):
            best = pruned
    return best, cost


def _removals(engine: Engine, sol, alpha: np.ndarray, cost: float, twins: dict, rule: SelectionRule):
    """Positions in ``sol.active`` that model reduction removes (then one of each look-alike pair), and the
    posterior under the structure's priors they were scored on."""
    keys = [engine.keys[k] for k in sol.active]
    # compared under the structure's own priors: MacKay's, tuned to the extended fit, split a pair of
    # near-equivalent terms unevenly and would decide between them by that split
    post = reprior(sol.posterior, sol.alpha[sol.active], alpha[sol.active])
    removed = backward(post, alpha[sol.active], cost, keys, rule.equivalence_nats)
    return _one_of_each_pair(
        engine, sol.active, post, alpha[sol.active], removed, twins, keys, rule.equivalence_nats
    ), post


def _reduced(engine: Engine, sol, post, alpha: np.ndarray, removed: list):
    """The refit of ``sol`` without the positions ``removed`` of its active set, started at the mean of the
    reduced posterior ``post`` (``None`` if it runs away)."""
    chosen = np.array([k for n, k in enumerate(sol.active) if n not in removed], dtype=int)
    _, mean, _ = reduce_model(post, alpha[sol.active], removed) if removed else (0, post.mean, 0)
    start = np.zeros_like(sol.theta)
    start[chosen] = mean if removed else sol.theta[chosen]
    try:
        refit = engine.fit(chosen, start, sol.alpha, warm=sol)
    except (SimulationError, np.linalg.LinAlgError):
        return None
    return refit if np.isfinite(refit.posterior.log_evidence) else None


#: Refits :func:`_prune` makes at most.
PRUNE_REFITS = 12


def _prune(
    engine: Engine, sol, alpha: np.ndarray, cost: float, twins: dict, rule: SelectionRule, tried: list | None = None
):
    """Backward elimination from the extended fit in confirmed steps, when one reduction of it fell short of
    the extended fit itself: model reduction extrapolates from one posterior, and far from it (many
    candidates removed at once) it can err by thousands of nats (measured: a 2-DOF oscillator recorded by
    displacement only, 16 of 30 terms removed, predicted +29 nats, the refit 2880 nats below). The
    removals are refitted in halving batches, each batch kept when its refit raises the objective, and model
    reduction is redone from every accepted refit, so that it extrapolates over ever shorter distances.
    ``tried``: the removals from ``sol`` already refitted, which start at half the batch.
    """
    current, refits = sol, 0
    while refits < PRUNE_REFITS:
        removed, post = _removals(engine, current, alpha, cost, twins, rule)
        batch, accepted = len(removed), False
        if current is sol and tried is not None and list(tried) == list(removed):
            batch //= 2
        while batch >= 1 and refits < PRUNE_REFITS:
            refit = _reduced(engine, current, post, alpha, removed[:batch])
            refits += 1
            if refit is not None and objective(refit, cost) > objective(current, cost):
                current, accepted = refit, True
                break
            batch //= 2
        if not accepted:
            break
    return current


def _extended(engine: Engine, first, every: np.ndarray, alpha: np.ndarray):
    """The fit of the structure with the candidates ``every`` (see :func:`_promising`), on ``first``'s segments (so
    that the evidences compare).

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
    if (
        cold is not None
        and np.array_equal(cold.starts, first.starts)
        and (0.5 * np.sum(cold.ssr * first.w) <= 0.5 * np.sum(first.ssr * first.w) + 1.0)
    ):
        return cold
    try:
        return engine.fit(every, first.theta, alpha, warm=first)
    except SimulationError:
        return None


def _one_of_each_pair(
    engine: Engine,
    active: np.ndarray,
    post,
    alpha: np.ndarray,
    removed: list,
    twins: dict,
    keys,
    equivalence_nats: float,
):
    """``removed`` extended so that no look-alike stays beside its term: of each such pair, the one whose
    removal lowers the evidence less goes (Bayesian model reduction); within ``equivalence_nats`` of each
    other, the more complex goes (``keys``: parsimony keys), as in :func:`backward`. (A drag oscillator
    driven at velocities below 1.3 m/s: ``sin(v)`` with ``v|v|`` 12 % off fitted within 1.6 nats of ``v``
    with the true drag, and model reduction, a posterior approximation, ranked them the other way.)"""
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
            after = {n: reduce_model(post, alpha, removed + [n])[0] for n in (a, b)}
            if abs(after[a] - after[b]) < equivalence_nats:
                removed.append(max((a, b), key=lambda n: keys[n]))
            else:
                removed.append(max((a, b), key=after.__getitem__))
    return removed
