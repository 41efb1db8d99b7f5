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
    """A unit-normalised Gram problem with a near-collinear pair, a zero column and 40 random subsets."""
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(80, 400)), int(rng.integers(12, 50))
    X = rng.standard_normal((n, m)) * rng.uniform(0.1, 10.0, m)
    X[:, 1] = X[:, 0] * 2.0 + 1e-3 * X[:, 0].std() * rng.standard_normal(n)
    w = np.zeros(m)
    w[rng.choice(m, 4, replace=False)] = rng.standard_normal(4) * 3 / X.std(axis=0)[:4]
    y = X @ w + rng.uniform(0.01, 1.0) * (X @ w).std() * rng.standard_normal(n)
    X[:, -1] = 0.0
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    gram = X.T @ X / np.outer(scale, scale)
    unit = y.std()
    subsets = [np.sort(rng.choice(m, int(rng.integers(1, 16)), replace=False)) for _ in range(40)]
    return gram, X.T @ y / scale / unit, float(y @ y) / unit**2, n, subsets


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("prune", [0.0, 4.0])
@pytest.mark.parametrize("beta_fixed", [None, 30.0])
def test_every_subset_gets_the_solution_of_its_own_call(seed, prune, beta_fixed):
    gram, b, tt, n, subsets = _problem(seed)
    many = solve_subsets(gram, b, tt, n, 1.0, subsets, prune=np.full(len(subsets), prune), beta_fixed=beta_fixed)
    for cols, got in zip(subsets, many, strict=True):
        own = solve(gram[np.ix_(cols, cols)], b[cols], tt, n, 1.0, prune=prune, beta_fixed=beta_fixed)
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


def test_subsets_factored_one_by_one_where_the_batch_fails_give_the_batched_answer(monkeypatch):
    gram, b, tt, n, subsets = _problem(2)
    prune = np.full(len(subsets), 4.0)
    batched = solve_subsets(gram, b, tt, n, 1.0, subsets, prune=prune)
    cholesky = np.linalg.cholesky

    def refuse_stacks(a, *args, **kwargs):
        if np.ndim(a) > 2:
            raise np.linalg.LinAlgError("refused")
        return cholesky(a, *args, **kwargs)

    monkeypatch.setattr(np.linalg, "cholesky", refuse_stacks)
    single = solve_subsets(gram, b, tt, n, 1.0, subsets, prune=prune)
    for one, other in zip(batched, single, strict=True):
        assert list(one.active) == list(other.active)
        assert one.log_evidence == pytest.approx(other.log_evidence, abs=1e-8)


def test_rvm_fits_of_subsets_equal_fit_stats_on_each_subsets_statistics():
    D, y, _ = monomial_problem(300, seed=3, noise=0.1)
    stats = GramStats.from_arrays(D, y)
    rng = np.random.default_rng(0)
    subsets = [sorted(rng.choice(len(MONOMIALS), 10, replace=False).tolist()) for _ in range(30)]
    template = RVM(prune_nats=5.0)
    fits = template._fit_subsets(stats, subsets)
    for cols, fit in zip(subsets, fits, strict=True):
        own = RVM(prune_nats=5.0).fit_stats(support.subset_stats(stats, cols, 0))
        assert list(fit.active_) == list(own.active_)
        np.testing.assert_allclose(fit.coef_, own.coef_, rtol=1e-8, atol=1e-12)
        assert fit.log_evidence_ == pytest.approx(own.log_evidence_, abs=1e-8)
        assert fit.noise_var_ == pytest.approx(own.noise_var_, rel=1e-10)


def _search(stats, noise):
    template = RVM()
    first = support.fit_rvm(template, stats, 0)
    keys = [(len(mono), i) for i, mono in enumerate(MONOMIALS)]
    active, alternatives, search = support.search_support(first, stats, 0, keys, template, 2.0)
    _, kept, fit = search.score(active, own=True)
    return active, alternatives, kept, fit.coef_.copy(), len(search.cache), len(search.batched)


@pytest.mark.parametrize("noise", [0.05, 0.5])
def test_the_support_search_ends_where_fitting_each_support_alone_ends(monkeypatch, noise):
    outcomes = []
    for seed in range(8):
        D, y, _ = monomial_problem(150, seed=seed, noise=noise)
        stats = GramStats.from_arrays(D, y)
        lockstep = _search(stats, noise)
        with monkeypatch.context() as patch:
            patch.setattr(support.SupportSearch, "score_all", lambda self, trials: None)
            alone = _search(stats, noise)
        assert lockstep[5] > 0 and alone[5] == 0  # the moves were scored in lockstep, and then one by one
        assert lockstep[:3] == alone[:3] and lockstep[4] == alone[4]
        # the reported fit is the support's own in both
        np.testing.assert_array_equal(lockstep[3], alone[3])
        outcomes.append(len(lockstep[0]))
    assert sum(k >= 3 for k in outcomes) >= 4  # real searches: most keep several terms
