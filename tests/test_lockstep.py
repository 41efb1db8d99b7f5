"""The solver on many subsets at once (``symsbl/_regression/lockstep.py``) against the reference: ``solve`` on each
subset alone, and the support search's outcome with each support fitted one by one."""

from __future__ import annotations

import numpy as np
import pytest
from test_rvm import MONOMIALS, monomial_problem

import symsbl._regression.support as support
from symsbl import RVM, GramStats
from symsbl._regression.lockstep import solve_subsets
from symsbl._regression.sbl import solve


def _problem(seed):
    """A unit-normalised Gram problem with a near-collinear pair, an exact and a negated duplicate of a true column
    (ties), a zero column and 40 random subsets."""
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(80, 400)), int(rng.integers(12, 50))
    X = rng.standard_normal((n, m)) * rng.uniform(0.1, 10.0, m)
    X[:, 1] = X[:, 0] * 2.0 + 1e-3 * X[:, 0].std() * rng.standard_normal(n)
    true = np.array([2, 4, 5, 7])
    w = np.zeros(m)
    w[true] = rng.standard_normal(4) * 3 / X[:, true].std(axis=0)
    y = X @ w + rng.uniform(0.01, 1.0) * (X @ w).std() * rng.standard_normal(n)
    X[:, 3], X[:, 6] = X[:, 2], -X[:, 5]
    X[:, -1] = 0.0
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    gram = X.T @ X / np.outer(scale, scale)
    unit = y.std()
    subsets = [np.sort(rng.choice(m, int(rng.integers(1, 16)), replace=False)) for _ in range(40)]
    return gram, X.T @ y / scale / unit, float(y @ y) / unit**2, n, subsets


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("prune", [0.0, 4.0])
@pytest.mark.parametrize("noise", [{}, {"beta_fixed": 30.0}, {"beta_max": 2.0}])
def test_every_subset_gets_the_solution_of_its_own_call(seed, prune, noise):
    gram, b, tt, n, subsets = _problem(seed)
    many = solve_subsets(gram, b, tt, n, 1.0, subsets, prune=np.full(len(subsets), prune), **noise)
    for cols, got in zip(subsets, many, strict=True):
        own = solve(gram[np.ix_(cols, cols)], b[cols], tt, n, 1.0, prune=prune, **noise)
        assert own.converged and got is not None
        # the same path: the same kept columns after the same number of steps
        assert list(got.active) == list(own.active) and got.n_iter == own.n_iter
        assert got.log_evidence == pytest.approx(own.log_evidence, abs=1e-8)
        assert got.beta == pytest.approx(own.beta, rel=1e-10)
        np.testing.assert_allclose(got.mu, own.mu, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(got.alpha, own.alpha, rtol=1e-6)
        np.testing.assert_allclose(got.sigma, own.sigma, rtol=1e-8, atol=1e-14)
        np.testing.assert_allclose(got.contribution, own.contribution, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(got.s_out, own.s_out, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(got.q_out, own.q_out, rtol=1e-7, atol=1e-9)


def test_a_subset_that_does_not_converge_in_its_budget_gets_none():
    gram, b, tt, n, subsets = _problem(1)
    many = solve_subsets(gram, b, tt, n, 1.0, subsets, prune=np.full(len(subsets), 4.0), max_iter=12)
    own = [solve(gram[np.ix_(c, c)], b[c], tt, n, 1.0, prune=4.0, max_iter=12) for c in subsets]
    assert [got is None for got in many] == [not o.converged for o in own]
    assert 0 < sum(got is None for got in many) < len(subsets)


def test_subsets_factored_one_by_one_where_the_batch_fails_give_their_own_calls_answer(monkeypatch):
    """A stack of posteriors that cannot be factored is factored subset by subset, as ``solve`` does, with its
    jitter: here every stack fails, and every factorisation of 3 or more columns fails once, then succeeds."""
    gram, b, tt, n, subsets = _problem(2)
    cholesky, refused = np.linalg.cholesky, {"stacks": 0, "single": 0, "last": False}

    def failing(a, *args, **kwargs):
        if np.ndim(a) > 2:
            refused["stacks"] += 1
            raise np.linalg.LinAlgError("refused")
        if np.shape(a)[-1] >= 3 and not refused["last"]:
            refused["single"] += 1
            refused["last"] = True
            raise np.linalg.LinAlgError("refused")
        refused["last"] = False
        return cholesky(a, *args, **kwargs)

    monkeypatch.setattr(np.linalg, "cholesky", failing)
    many = solve_subsets(gram, b, tt, n, 1.0, subsets, prune=4.0)
    own = [solve(gram[np.ix_(c, c)], b[c], tt, n, 1.0, prune=4.0) for c in subsets]
    assert refused["stacks"] > 0 and refused["single"] > 0
    for one, other in zip(many, own, strict=True):
        assert list(one.active) == list(other.active) and one.n_iter == other.n_iter
        assert one.log_evidence == pytest.approx(other.log_evidence, abs=1e-8)


@pytest.mark.parametrize("options", [{"prune_nats": 5.0}, {}, {"noise_var": 0.01}])
def test_rvm_fits_of_subsets_equal_fit_stats_on_each_subsets_statistics(options):
    D, y, _ = monomial_problem(300, seed=3, noise=0.1)
    stats = GramStats.from_arrays(D, y)
    rng = np.random.default_rng(0)
    # sizes differ: the default penalty ("ebic") depends on the number of candidates
    subsets = [sorted(rng.choice(len(MONOMIALS), int(rng.integers(3, 20)), replace=False)) for _ in range(30)]
    fits = RVM(**options)._fit_subsets(stats, subsets)
    for cols, fit in zip(subsets, fits, strict=True):
        own = RVM(**options).fit_stats(support.subset_stats(stats, cols, 0))
        assert list(fit.active_) == list(own.active_)
        np.testing.assert_allclose(fit.coef_, own.coef_, rtol=1e-8, atol=1e-12)
        assert fit.log_evidence_ == pytest.approx(own.log_evidence_, abs=1e-8)
        assert fit.noise_var_ == pytest.approx(own.noise_var_, rel=1e-10)
        assert fit.prune_nats_ == own.prune_nats_


def _search(stats):
    template = RVM()
    first = support.fit_rvm(template, stats, 0)
    keys = [(len(mono), i) for i, mono in enumerate(MONOMIALS)]
    active, alternatives, search = support.search_support(first, stats, 0, keys, template, 2.0)
    _, kept, fit = search.score(active, own=True)  # the support's own fit, past the budget too
    return active, alternatives, kept, fit.coef_.copy(), list(search.cache), len(search.batched)


@pytest.mark.parametrize(("noise", "budget"), [(0.05, None), (0.5, None), (0.5, 17), (0.5, 40)])
def test_the_support_search_ends_where_fitting_each_support_alone_ends(monkeypatch, noise, budget):
    if budget is not None:
        monkeypatch.setattr(support, "MAX_SCORED", budget)
    outcomes = []
    for seed in range(8):
        D, y, _ = monomial_problem(150, seed=seed, noise=noise)
        stats = GramStats.from_arrays(D, y)
        lockstep = _search(stats)
        with monkeypatch.context() as patch:
            patch.setattr(support.SupportSearch, "score_all", lambda self, trials: None)
            alone = _search(stats)
        assert lockstep[5] > 0 and alone[5] == 0  # the moves were scored in lockstep, and then one by one
        # the same supports scored, in the same order, within the budget (and the final support's own fit); the
        # same outcome
        assert lockstep[4] == alone[4] and len(alone[4]) <= (budget or support.MAX_SCORED) + 1
        assert lockstep[:3] == alone[:3]
        # the reported fit is the support's own in both
        np.testing.assert_array_equal(lockstep[3], alone[3])
        outcomes.append(len(lockstep[0]))
    assert sum(k >= 3 for k in outcomes) >= 4  # real searches: most keep several terms
