"""Support selection around the RVM: evidence-guided local search and parsimony.

The fast RVM (:class:`symsbl.RVM`) is a greedy optimiser of the penalised evidence. This module
refines its answer for one state equation:

- :class:`SupportSearch` tries single additions, deletions and swaps, each scored by the RVM's own
  objective (log evidence minus the per-term penalty) refitted on the candidate support (a move's
  supports side by side, :mod:`symsbl._regression.lockstep`, each along its own fit's path);
- :func:`search_support` then applies parsimony among near-equivalent candidates: a kept term is
  replaced by a simpler one (:func:`complexity`) when the evidence cannot tell them apart, and the
  alternatives are reported.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .gram import GramStats
from .rvm import RVM

__all__ = ["fit_rvm", "search_support", "subset_stats", "SupportSearch", "EQUIVALENCE_COSINE"]

#: Candidates whose columns, normalised, have a cosine above this with a kept term are tested
#: for equivalence by an exact refit (a cheap pre-filter; the decision is by evidence).
EQUIVALENCE_COSINE = 0.99


def subset_stats(stats: GramStats, cols: Sequence[int], target: int) -> GramStats:
    """Statistics of columns ``cols`` and target ``target`` only."""
    cols = list(cols)
    return GramStats(
        stats.gram[np.ix_(cols, cols)],
        stats.dty[cols][:, [target]],
        stats.yty[[target]],
        stats.y_sum[[target]],
        stats.n_samples,
    )


def _subset_template(template: RVM, prune_nats=None) -> RVM:
    """``template``'s options without free columns; a given ``prune_nats`` overrides the template's, so
    subsets are scored with the full problem's penalty."""
    params = template.get_params()
    params["free"] = ()
    if prune_nats is not None:
        params["prune_nats"] = prune_nats
    return RVM(**params)


def fit_rvm(template: RVM, stats: GramStats, target: int, prune_nats=None) -> RVM:
    """Fit a fresh RVM with ``template``'s options (no free columns) to one target; a given
    ``prune_nats`` overrides the template's, so subsets are scored with the full problem's
    penalty."""
    return _subset_template(template, prune_nats).fit_stats(stats, target=target)


#: Distinct supports the local search scores per equation at most: a deterministic budget. The most any
#: test, example or demo needed was 616; a record whose equation residual is far from white (Bouc-Wen of
#: order 3 under a multisine) needed thousands of refits of about 80 terms each, minutes per equation.
MAX_SCORED = 2000


class SupportSearch:
    """Evidence-guided local search over supports around the RVM's answer.

    The fast RVM is a greedy optimiser: a term admitted early (``sin(x2)`` before ``x2``) can
    leave it in a local optimum that needs two moves to escape (``sin(x2) + 1107 x2**3``
    mimicking ``x2``). The search scores a support by the RVM's own objective, the log
    evidence minus the per-term penalty, refitting the RVM on the support's columns only, and
    tries single additions, deletions and swaps. Candidates are pre-filtered by their correlation
    with the residual (for additions) or with the residual plus the swapped term's
    contribution (for swaps), ``n_candidates`` each, plus every column nearly collinear with
    the swapped term.
    """

    def __init__(self, stats, target, template, prune_nats, n_candidates=8):
        self.stats, self.target, self.template = stats, target, template
        self.prune_nats, self.k = prune_nats, n_candidates
        G = stats.gram
        self.norms = np.sqrt(np.maximum(np.diag(G), 1e-300))
        self.cache: dict[tuple, tuple[float, list[int], RVM]] = {}
        self.batched: set[tuple] = set()  # supports scored in lockstep, not by their own fit

    def _entry(self, key, fit) -> tuple[float, list[int], RVM]:
        kept = [key[i] for i in fit.active_]
        return fit.log_evidence_ - self.prune_nats * len(kept), kept, fit

    def score(self, cols, own: bool = False) -> tuple[float, list[int], RVM] | None:
        """Penalised log evidence of the RVM refitted on ``cols``, the columns it keeps
        (sorted), and the fit itself; None once :data:`MAX_SCORED` supports have been scored
        (the search then keeps the best found so far). ``own`` asks for the support's own fit, past the
        budget too, where the cached one was scored in lockstep (they agree to rounding) or none was."""
        key = tuple(sorted(cols))
        if key not in self.cache or (own and key in self.batched):
            if key not in self.cache and len(self.cache) >= MAX_SCORED and not own:
                return None
            fit = fit_rvm(self.template, subset_stats(self.stats, key, self.target), 0, self.prune_nats)
            self.cache[key] = self._entry(key, fit)
            self.batched.discard(key)
        return self.cache[key]

    def score_all(self, trials) -> None:
        """Score the supports among ``trials`` not scored yet, in order and within :data:`MAX_SCORED`, in one
        lockstep fit (:func:`symsbl._regression.lockstep.solve_subsets`): a move's dozens of refits at the cost
        of a few. A support whose lockstep fit did not converge gets its own fit, which says so."""
        keys = [key for key in dict.fromkeys(tuple(sorted(cols)) for cols in trials) if key not in self.cache]
        keys = keys[: max(MAX_SCORED - len(self.cache), 0)]
        if len(keys) < 2 or self.template.verbose:
            return
        fits = _subset_template(self.template, self.prune_nats)._fit_subsets(self.stats, keys, self.target)
        for key, fit in zip(keys, fits, strict=True):
            if fit is None:
                self.score(key)
            else:
                self.cache[key] = self._entry(key, fit)
                self.batched.add(key)

    def coefficients(self, kept, fit) -> np.ndarray:
        """Full-length coefficient vector of a fit returned by :meth:`score`."""
        mu = np.zeros(self.stats.n_terms)
        mu[kept] = fit.coef_[fit.active_]
        return mu

    def _top(self, scores, exclude):
        order = np.argsort(-np.abs(scores) / self.norms, kind="stable")
        allowed = np.ones(len(order), dtype=bool)
        allowed[list(exclude)] = False
        return [int(i) for i in order[allowed[order]][: self.k]]

    def runners_up(self, kept, fit, k: int = 2) -> list[int]:
        """Up to ``k`` candidates whose addition to the fit on ``kept`` would raise its log evidence by more
        than a nat (before the per-term penalty), best first: the relevance vector machine's exact one-term
        gain ``1/2 (rho - 1 - log rho)`` with ``rho = q^2 / s`` (Tipping and Faul 2003)."""
        G, b = self.stats.gram, self.stats.dty[:, self.target]
        beta = 1.0 / fit.noise_var_
        cross = G[:, kept]  # (M, m)
        sigma = np.asarray(fit.sigma_)
        s = beta * np.diag(G) - beta**2 * np.einsum("im,mn,in->i", cross, sigma, cross)
        q = beta * (b - G @ self.coefficients(kept, fit))
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(s > 0, q**2 / np.where(s > 0, s, 1.0), 0.0)
            gain = np.where(rho > 1.0, 0.5 * (rho - 1.0 - np.log(np.where(rho > 1.0, rho, 1.0))), 0.0)
        gain[list(kept)] = 0.0
        order = np.argsort(-gain, kind="stable")
        return [int(i) for i in order[:k] if gain[i] > 1.0]

    def collinear(self, j, exclude):
        G = self.stats.gram
        cos = np.abs(G[j]) / (self.norms * self.norms[j])
        return [int(i) for i in np.flatnonzero(cos > EQUIVALENCE_COSINE) if i != j and i not in exclude]

    def run(self, active, max_moves=20):
        best, active, fit = self.score(active)
        G, b = self.stats.gram, self.stats.dty[:, self.target]
        for _ in range(max_moves):
            mu = self.coefficients(active, fit)
            corr = b - G @ mu
            trials = [active + [i] for i in self._top(corr, active)]
            for pos, j in enumerate(active):
                others = active[:pos] + active[pos + 1 :]
                if others:
                    trials.append(others)
                pool = self._top(corr + mu[j] * G[:, j], active) + self.collinear(j, active)
                trials += [others + [i] for i in dict.fromkeys(pool)]
            improved, spent = None, False
            self.score_all(trials)
            for cols in trials:
                scored = self.score(cols)
                if scored is None:  # out of budget: keep the best support found, this move's included
                    spent = True
                    break
                if scored[0] > best + 1e-6 and (improved is None or scored[0] > improved[0]):
                    improved = scored
            if improved is not None:
                best, active, fit = improved
            if improved is None or spent:
                break
        return best, active, fit


def search_support(first: RVM, stats, target, keys, template, tol):
    """Local search from the RVM's support (and from its supports on parsimony-ordered subsets of
    the library), then parsimony among near-equivalents.

    Returns the support and, per kept column, the near-equivalent columns whose swap costs
    less than ``tol`` nats (the simplest of each group is the one kept)."""
    search = SupportSearch(stats, target, template, first.prune_nats_)
    best, active, _ = search.run([int(i) for i in first.active_])
    # Multi-start: the same search from the RVM's answer on nested candidate sets ordered by
    # parsimony (polynomials only, then with |.|, sign, sin/cos, everything). A first pass over
    # the whole library can settle in a basin of look-alike terms (x1|x1|, x1^3|x1|, sign(x1)
    # for x1 and x1^3) that single moves cannot leave.
    ranks = np.array([k[0] for k in keys])
    for rank in np.unique(ranks)[:-1]:
        cols = [int(i) for i in np.flatnonzero(ranks <= rank)]
        if not cols:
            continue
        start = fit_rvm(template, subset_stats(stats, cols, target), 0, first.prune_nats_)
        if len(start.active_) == 0:
            continue
        if len(search.cache) >= MAX_SCORED:  # the budget is spent
            break
        value, kept, _ = search.run([cols[i] for i in start.active_])
        if value > best + 1e-6:
            best, active = value, kept
    alternatives: dict[int, list[int]] = {}
    for _ in range(len(active) + 1):
        changed = False
        for pos, j in enumerate(active):
            others = active[:pos] + active[pos + 1 :]
            equal = []
            for i in search.collinear(j, active):
                scored = search.score(others + [i])
                if scored is None:
                    break
                value, kept, _ = scored
                if value >= best - tol and i in kept and set(kept) - {i} == set(others):
                    equal.append((i, value))
            if not equal:
                continue
            group = [j] + [i for i, _ in equal]
            simplest = min(group, key=lambda i: (keys[i], i))
            alternatives[simplest] = sorted(set(group) - {simplest}, key=lambda i: (keys[i], i))
            if simplest != j:
                alternatives.pop(j, None)
                active = sorted(others + [simplest])
                best = dict(equal)[simplest]
                changed = True
                break
        if not changed:
            break
    return sorted(active), alternatives, search
