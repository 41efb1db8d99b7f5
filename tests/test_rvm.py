"""symsbl.rvm against closed forms, invariances and sparse-recovery benchmarks."""

import itertools

import numpy as np
import pytest
from helpers import exactly
from hypothesis import given, settings
from hypothesis import strategies as st

from symsbl import RVM, DataError, GramStats, ParameterError
from symsbl._regression.sbl import DenseGram, posterior, solve

MONOMIALS = [c for deg in range(7) for c in itertools.combinations_with_replacement(range(3), deg)]
TRUE = {(0,): 1.0, (1,): -0.5, (0, 2): 2.0, (0, 0, 0): -1.5, (1, 2, 2): 0.8}
SUPPORT = sorted(MONOMIALS.index(k) for k in TRUE)


def monomial_problem(n, seed, noise=0.01, extra=None, out=None):
    """All 84 monomials of degree <= 6 in 3 uniform variables; 5 true terms (+ ``extra``).
    ``out``: a reusable (n, 84) Fortran-ordered buffer for the dictionary."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.0, 1.0, (n, 3))
    D = np.empty((n, len(MONOMIALS)), order="F") if out is None else out
    D[:, 0] = 1.0
    for j, mono in enumerate(MONOMIALS[1:], start=1):  # each monomial extends a shorter one
        np.multiply(D[:, MONOMIALS.index(mono[:-1])], x[:, mono[-1]], out=D[:, j])
    w = np.zeros(len(MONOMIALS))
    for mono, value in {**TRUE, **dict([extra] if extra else [])}.items():
        w[MONOMIALS.index(mono)] = value
    signal = D @ w
    return D, signal + noise * signal.std() * rng.standard_normal(n), w


def small_problem(seed=0, n=300, m=10):
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, m)) * rng.uniform(0.1, 10.0, m)
    w = np.zeros(m)
    w[[1, 4, 7]] = [2.0 / X[:, 1].std(), -1.0 / X[:, 4].std(), 0.5 / X[:, 7].std()]
    return X, X @ w + 0.3 * rng.standard_normal(n)


def direct_log_evidence(X, y, alpha_u, noise_var, active):
    C = noise_var * np.eye(len(y)) + (X[:, active] / alpha_u) @ X[:, active].T
    _, logdet = np.linalg.slogdet(C)
    return -0.5 * (len(y) * np.log(2 * np.pi) + logdet + y @ np.linalg.solve(C, y))


@pytest.mark.parametrize("prune", [None, "bic", "ebic"])
def test_log_evidence_equals_direct_formula(prune):
    X, y = small_problem()
    model = RVM(prune_nats=prune).fit(X, y)
    u = model.active_
    expected = direct_log_evidence(X, y, model.alpha_[u], model.noise_var_, u)
    assert model.log_evidence_ == pytest.approx(expected, rel=1e-10, abs=1e-8)


def test_evidence_contribution_is_exact_drop_from_deleting_each_term():
    X, y = small_problem(1)
    model = RVM(prune_nats=None).fit(X, y)
    u = model.active_
    for k, j in enumerate(u):
        keep = u != j
        reduced = direct_log_evidence(X, y, model.alpha_[u][keep], model.noise_var_, u[keep])
        assert model.evidence_contribution_[k] == pytest.approx(model.log_evidence_ - reduced, abs=1e-7)
    np.testing.assert_allclose(model.snr_, np.abs(model.coef_[u]) / np.sqrt(np.diag(model.sigma_)))


def test_equal_fixed_precisions_give_ridge_regression():
    X, y = small_problem(2)
    alpha, beta = 3.0, 1.0 / 0.09
    mu, sigma, _, _ = posterior(X.T @ X, X.T @ y, np.full(X.shape[1], alpha), beta)
    ridge = np.linalg.solve(X.T @ X + (alpha / beta) * np.eye(X.shape[1]), X.T @ y)
    np.testing.assert_allclose(mu, ridge, rtol=1e-10)
    np.testing.assert_allclose(sigma, np.linalg.inv(beta * X.T @ X + alpha * np.eye(X.shape[1])), rtol=1e-10)


def test_fitted_posterior_is_weighted_ridge_at_returned_hyperparameters():
    X, y = small_problem(3)
    model = RVM().fit(X, y)
    Xu, a = X[:, model.active_], model.alpha_[model.active_]
    ridge = np.linalg.solve(Xu.T @ Xu + model.noise_var_ * np.diag(a), Xu.T @ y)
    np.testing.assert_allclose(model.coef_[model.active_], ridge, rtol=1e-9)
    np.testing.assert_allclose(model.sigma_, np.linalg.inv(Xu.T @ Xu / model.noise_var_ + np.diag(a)), rtol=1e-9)
    assert np.all(model.coef_[np.setdiff1d(np.arange(X.shape[1]), model.active_)] == 0)
    assert np.all(np.isinf(np.delete(model.alpha_, model.active_)))


def test_predictive_variance_equals_direct_formula():
    X, y = small_problem(4)
    model = RVM().fit(X[:200], y[:200])
    mean, std = model.predict(X[200:], return_std=True)
    Xu = X[200:, model.active_]
    cov = model.noise_var_ * np.eye(len(Xu)) + Xu @ model.sigma_ @ Xu.T
    np.testing.assert_allclose(std**2, np.diag(cov), rtol=1e-12)
    np.testing.assert_allclose(mean, X[200:] @ model.coef_, rtol=1e-12)
    np.testing.assert_array_equal(model.predict(X[200:]), mean)


def direct_factors(X, y, model, i):
    """Sparsity and quality factors of column i with i left out of C."""
    u = [j for j in model.active_ if j != i]
    C = model.noise_var_ * np.eye(len(y)) + (X[:, u] / model.alpha_[u]) @ X[:, u].T
    phi = X[:, i]
    return phi @ np.linalg.solve(C, phi), phi @ np.linalg.solve(C, y)


def test_plain_sb2_stationarity_q2_vs_s():
    X, y = small_problem(5)
    model = RVM(prune_nats=None).fit(X, y)
    for i in range(X.shape[1]):
        s, q = direct_factors(X, y, model, i)
        if i in model.active_:
            assert q**2 > s
            # and alpha is at its stationary point s^2 / (q^2 - s), to the convergence tolerance
            assert np.log(model.alpha_[i]) == pytest.approx(np.log(s**2 / (q**2 - s)), abs=2e-3)
        else:
            assert q**2 <= s


def test_penalised_stationarity_every_kept_term_is_worth_the_penalty():
    X, y = small_problem(6)
    model = RVM(prune_nats=3.0).fit(X, y)
    assert np.all(model.evidence_contribution_ >= 3.0)
    for i in np.setdiff1d(np.arange(X.shape[1]), model.active_):
        s, q = direct_factors(X, y, model, i)
        rho = q**2 / s
        assert rho <= 1 or 0.5 * (rho - 1 - np.log(rho)) <= 3.0


@settings(max_examples=15, deadline=None)
@given(
    scales=st.lists(st.floats(1e-3, 1e3), min_size=10, max_size=10),
    perm_seed=st.integers(0, 10_000),
)
def test_invariant_to_column_scaling_and_order(scales, perm_seed):
    X, y = small_problem(7)
    ref = RVM().fit(X, y)
    scales = np.asarray(scales)
    perm = np.random.default_rng(perm_seed).permutation(X.shape[1])
    model = RVM().fit((X * scales)[:, perm], y)
    np.testing.assert_array_equal(np.sort(perm[model.active_]), ref.active_)
    np.testing.assert_allclose((model.coef_ * scales[perm])[np.argsort(perm)], ref.coef_, rtol=1e-7, atol=1e-12)
    assert model.log_evidence_ == pytest.approx(ref.log_evidence_, rel=1e-10)
    assert model.noise_var_ == pytest.approx(ref.noise_var_, rel=1e-8)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000))
def test_deterministic(seed):
    X, y = small_problem(seed)
    a, b = RVM(prune_nats=None).fit(X, y), RVM(prune_nats=None).fit(X, y)
    np.testing.assert_array_equal(a.coef_, b.coef_)
    np.testing.assert_array_equal(a.sigma_, b.sigma_)
    assert (a.log_evidence_, a.n_iter_) == (b.log_evidence_, b.n_iter_)


def test_from_chunks_equals_from_arrays_and_serves_several_targets():
    D, y, _ = monomial_problem(5000, 0)
    Y = np.column_stack([y, D[:, 3] - 2.0 * D[:, 9]])
    whole = GramStats.from_arrays(D, Y)
    chunked = GramStats.from_chunks((D[s : s + 777], Y[s : s + 777]) for s in range(0, 5000, 777))
    for name in ("gram", "dty", "yty", "y_sum"):
        np.testing.assert_allclose(getattr(chunked, name), getattr(whole, name), rtol=1e-12, atol=1e-9)
    assert chunked.n_samples == 5000
    for k in range(2):
        ref = RVM().fit(D, Y[:, k])
        for stats in (whole, chunked, whole.target(k)):
            model = RVM().fit_stats(stats, target=0 if stats.n_targets == 1 else k)
            np.testing.assert_array_equal(model.active_, ref.active_)
            np.testing.assert_allclose(model.coef_, ref.coef_, rtol=1e-8, atol=1e-12)


def test_scaled_stats_equal_repeated_data():
    X, y = small_problem(8)
    stats = GramStats.from_arrays(X, y)
    doubled = RVM().fit(np.vstack([X, X]), np.concatenate([y, y]))
    model = RVM().fit_stats(stats.scaled(2.0))
    np.testing.assert_allclose(model.coef_, doubled.coef_, rtol=1e-8, atol=1e-12)
    assert model.log_evidence_ == pytest.approx(doubled.log_evidence_, rel=1e-9)


def test_qr_statistics_resolve_a_residual_of_1e9_of_the_signal():
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (20000, 3))
    D = np.column_stack([np.ones(20000), x, x**2, x[:, 0] * x[:, 1], x**3])
    signal = D[:, [1, 2, 5, 8]] @ [1.0, -2.0, 0.5, 3.0]
    noise = 1e-9 * signal.std()
    y = signal + noise * rng.standard_normal(20000)
    chunks = [(D[s : s + 3000], y[s : s + 3000]) for s in range(0, 20000, 3000)]
    for stats in (GramStats.from_arrays(D, y, qr=True), GramStats.from_chunks(chunks, qr=True)):
        model = RVM(noise_floor=0).fit_stats(stats)
        assert model.noise_var_ == pytest.approx(noise**2, rel=0.05)
        np.testing.assert_array_equal(model.active_, [1, 2, 5, 8])
    # The Gram identity cannot see below its rounding-error bound: the estimate stays finite.
    gram_only = RVM(noise_floor=0).fit(D, y)
    assert noise**2 < gram_only.noise_var_ < 1e-10 * signal.var()
    assert RVM().fit(D, y).noise_var_ == pytest.approx(1e-6 * y.var())  # the default floor


def _rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


@pytest.mark.parametrize("layout", ["C", "F", "strided"])
def test_blocked_rank_k_gram_equals_the_general_product(layout):
    """``from_arrays`` builds D^T D by symmetric rank-k updates block by block, with D^T Y from the
    same blocks: the same numbers as a general matrix product to 1e-12, exactly symmetric."""
    D, y, _ = monomial_problem(20_000, 0)
    D = {"C": np.ascontiguousarray(D), "F": np.asfortranarray(D), "strided": np.asfortranarray(D)[::2]}[layout]
    Y = np.column_stack([y[: len(D)], D[:, 3] - 2.0 * D[:, 9]])
    stats = GramStats.from_arrays(D, Y)
    plain_gram = np.einsum("ni,nj->ij", D, D)  # a general product, no symmetric kernel
    assert _rel(stats.gram, plain_gram) < 1e-12
    assert _rel(stats.dty, np.einsum("ni,nk->ik", D, Y)) < 1e-12
    np.testing.assert_array_equal(stats.gram, stats.gram.T)


def test_fit_gives_the_model_of_the_plain_statistics():
    D, y, _ = monomial_problem(50_000, 3)
    plain = GramStats(
        np.einsum("ni,nj->ij", D, D),
        np.einsum("ni,n->i", D, y)[:, None],
        np.array([y @ y]),
        np.array([y.sum()]),
        len(y),
    )
    for prune in (None, "ebic"):
        fast, ref = RVM(prune_nats=prune).fit(D, y), RVM(prune_nats=prune).fit_stats(plain)
        np.testing.assert_array_equal(fast.active_, ref.active_)
        assert fast.n_iter_ == ref.n_iter_
        assert _rel(fast.coef_, ref.coef_) < 1e-10  # relative to the largest coefficient
        assert _rel(fast.sigma_, ref.sigma_) < 1e-9
        # The Gram-identity residual turns 1e-16 perturbations of G into ~beta t^T t 1e-16 nats.
        assert fast.log_evidence_ == pytest.approx(ref.log_evidence_, abs=1e-5)
        assert fast.noise_var_ == pytest.approx(ref.noise_var_, rel=1e-9)


class _OnDemand:
    """A column source computing each Gram column from the design when first asked, recording which."""

    def __init__(self, D):
        self.D, self.diag, self.read = D, np.einsum("ni,ni->i", D, D), []

    def columns(self, idx, priority=None):
        self.read += [int(i) for i in idx if int(i) not in self.read]
        return self.D.T @ self.D[:, idx]


def test_solver_reads_only_the_gram_columns_of_terms_that_enter():
    """The sequential algorithm needs the diagonal of G and the columns of the terms that enter,
    nothing else: a source that computes those on demand gives the same solution."""
    D, y, _ = monomial_problem(20_000, 1)
    D = D / np.linalg.norm(D, axis=0)
    G, b = D.T @ D, D.T @ y
    args = (b, float(y @ y), float(len(y)), float(y.var()))
    source = _OnDemand(D)
    for prune in (0.0, 9.0):
        ref = solve(DenseGram(G), *args, beta_max=1e6 / y.var(), prune=prune)
        lazy = solve(source, *args, beta_max=1e6 / y.var(), prune=prune)
        np.testing.assert_array_equal(lazy.active, ref.active)
        assert lazy.n_iter == ref.n_iter
        for name in ("mu", "alpha", "sigma", "q_out", "s_out"):
            assert _rel(getattr(lazy, name), getattr(ref, name)) < 1e-9, name
        assert lazy.log_evidence == pytest.approx(ref.log_evidence, rel=1e-12)
    assert set(ref.active) <= set(source.read) and len(source.read) < D.shape[1] // 3


def test_scikit_learn_takes_it_as_a_regressor():
    """``clone`` and ``MultiOutputRegressor`` (what pysindy's ``WrappedOptimizer`` uses) accept an RVM."""
    pytest.importorskip("sklearn", reason="scikit-learn is not installed; nothing to be compatible with")
    from sklearn.base import clone, is_regressor
    from sklearn.multioutput import MultiOutputRegressor

    X, y = small_problem(11)
    rvm = RVM(prune_nats=3.0)
    assert is_regressor(rvm) and clone(rvm).get_params() == rvm.get_params()
    both = MultiOutputRegressor(rvm).fit(X, np.column_stack([y, 2.0 * y]))
    single = RVM(prune_nats=3.0).fit(X, y)
    np.testing.assert_allclose(both.estimators_[1].coef_, 2.0 * single.coef_, rtol=1e-8)
    np.testing.assert_allclose(both.predict(X)[:, 0], single.predict(X), rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("n", [20_000, 200_000])
def test_exact_support_over_20_seeds_where_plain_sb2_over_selects(n):
    spurious_plain = 0
    buffer = np.empty((n, len(MONOMIALS)), order="F")
    for seed in range(20):
        D, y, w = monomial_problem(n, seed, out=buffer)
        stats = GramStats.from_arrays(D, y)
        model = RVM().fit_stats(stats)
        np.testing.assert_array_equal(model.active_, SUPPORT)
        np.testing.assert_allclose(model.coef_, w, atol=5e-3)
        if seed < 3:
            spurious_plain += len(RVM(prune_nats=None).fit_stats(stats).active_) - 5
    assert spurious_plain >= 3  # what the penalty removes


def test_small_genuine_term_is_kept():
    """A sixth term with 1 % of the signal variance, N = 3e4 and 0.5 % noise stays."""
    D, y0, w0 = monomial_problem(30000, 0, noise=0.0)
    j = MONOMIALS.index((0, 0, 1))
    weight = np.sqrt(0.01 * y0.var()) / D[:, j].std()
    for seed in range(3):
        D, y, w = monomial_problem(30000, seed, noise=0.005, extra=((0, 0, 1), weight))
        model = RVM().fit(D, y)
        np.testing.assert_array_equal(model.active_, sorted(SUPPORT + [j]))
        assert model.coef_[j] == pytest.approx(weight, rel=0.05)


def test_near_duplicate_columns_are_not_both_admitted():
    rng = np.random.default_rng(9)
    x = rng.standard_normal((2000, 4))
    X = np.column_stack([x, x[:, 0] + 1e-6 * rng.standard_normal(2000)])
    y = x @ [1.0, 0.5, 0.0, -2.0] + 0.01 * rng.standard_normal(2000)
    model = RVM(prune_nats=None).fit(X, y)
    assert len({0, 4} & set(model.active_)) == 1
    assert np.all(np.isfinite(model.sigma_)) and np.isfinite(model.log_evidence_)


def test_options_free_fixed_noise_floor_and_verbose(capsys):
    X, y = small_problem(10)
    model = RVM(free=[0], noise_var=0.09, verbose=True).fit(X, y)
    assert 0 in model.active_ and model.noise_var_ == 0.09
    assert "add" in capsys.readouterr().out
    clean = RVM(prune_nats=2.5).fit(X, X[:, 1] - X[:, 4])
    assert clean.noise_var_ == pytest.approx(1e-6 * np.var(X[:, 1] - X[:, 4]))
    assert clean.prune_nats_ == 2.5
    assert RVM().fit(X, y).prune_nats_ == pytest.approx(0.5 * np.log(300) + np.log(10))
    assert RVM(prune_nats="bic").fit(X, y).prune_nats_ == pytest.approx(0.5 * np.log(300))
    with pytest.warns(RuntimeWarning, match="did not converge in max_iter = 1"):
        RVM(max_iter=1).fit(X, y)


@pytest.mark.parametrize(
    "X, y, match",
    [
        (
            np.ones(10),
            np.ones(10),
            exactly("X: expected a 2-D array, received shape (10,); reshape it (e.g. X.reshape(-1, 1) for one column)"),
        ),
        (
            np.ones((10, 2)),
            np.ones((10, 2)),
            exactly(
                "y: expected a 1-D array, received shape (10, 2); reshape it (e.g. y.reshape(-1, 1) for one column)"
            ),
        ),
        (np.ones((10, 2)), np.ones(9), exactly("y: expected as many rows as X (10), received 9 rows")),
        (
            np.where(np.eye(10, 2) > 0, np.nan, 1.0),
            np.ones(10),
            exactly(
                "X: expected finite values, received a "
                "non-finite value at index (0, 0); remove or "
                "impute NaN/inf rows first"
            ),
        ),
        (
            np.ones((10, 2)),
            np.r_[np.ones(9), np.inf],
            exactly(
                "y: expected finite values, received a non-finite value "
                "at index (9, 0); remove or impute NaN/inf rows first"
            ),
        ),
        (
            np.ones((1, 2)),
            np.ones(1),
            exactly(
                "rows: expected more regression rows than candidate terms (2), received "
                "1 rows from X; use longer records, fewer candidate terms (a lower "
                "degree) or a derivative strategy with more rows"
            ),
        ),
        (np.ones((10, 0)), np.ones(10), exactly("stats: expected at least one dictionary column, received none")),
        (
            np.ones((10, 2)),
            np.zeros(10),
            exactly("y: expected a target that is not identically zero, received all zeros; there is nothing to fit"),
        ),
    ],
)
def test_fit_rejects_bad_data(X, y, match):
    with pytest.raises(DataError, match=match):
        RVM().fit(X, y)


@pytest.mark.parametrize(
    "params, match",
    [
        ({"prune_nats": "aic"}, exactly("prune_nats: expected one of 'bic', 'ebic', received 'aic'")),
        (
            {"prune_nats": -1.0},
            exactly("prune_nats: expected a finite number >= 0.0, None, 'bic', 'ebic', received -1.0"),
        ),
        ({"noise_var": 0.0}, exactly("noise_var: expected a finite number > 0.0, None, received 0.0")),
        ({"noise_floor": np.nan}, exactly("noise_floor: expected a finite number >= 0.0, received nan")),
        ({"tol": -1}, exactly("tol: expected a finite number > 0.0, received -1")),
        ({"max_iter": 0}, exactly("max_iter: expected an integer >= 1, received 0")),
        ({"verbose": "yes"}, exactly("verbose: expected True or False, received 'yes'")),
        ({"free": [12]}, exactly("free: expected an integer in [0, 9], received 12")),
        ({"free": [1, 1]}, exactly("free: expected distinct column indices, received [1, 1]")),
    ],
)
def test_fit_rejects_bad_options(params, match):
    X, y = small_problem()
    with pytest.raises(ValueError, match=match):
        RVM(**params).fit(X, y)


def test_other_user_errors():
    X, y = small_problem()
    stats = GramStats.from_arrays(X, y)
    with pytest.raises(ValueError, match=exactly("target: expected an integer in [0, 0], received 1")):
        RVM().fit_stats(stats, target=1)
    with pytest.raises(ParameterError, match=exactly("stats: expected a GramStats, received tuple")):
        RVM().fit_stats((X.T @ X, X.T @ y))
    with pytest.raises(
        ParameterError,
        match=exactly(
            "RVM: expected a fitted estimator, received one not fitted yet; call fit(X, y) or fit_stats(stats) first"
        ),
    ):
        RVM().predict(X)
    with pytest.raises(DataError, match=exactly("X: expected 10 columns (as in fit), received 3")):
        RVM().fit(X, y).predict(X[:, :3])
    with pytest.raises(
        DataError, match=exactly("chunks: expected at least one (D_chunk, Y_chunk) pair, received none")
    ):
        GramStats.from_chunks([])
    with pytest.raises(ParameterError, match=exactly("factor: expected a finite number > 0.0, received -1")):
        stats.scaled(-1)
    with pytest.raises(
        DataError, match=exactly("other: expected GramStats of (10, 1) (n_terms, n_targets), received (3, 1)")
    ):
        stats + GramStats.from_arrays(X[:, :3], y)
    with pytest.raises(ParameterError, match=r"^set_params: expected parameter names among \[.*\], received 'alpha'$"):
        RVM().set_params(alpha=1.0)
    assert RVM().set_params(tol=0.1).get_params()["tol"] == 0.1


def test_a_budget_the_plain_optimum_would_spend_still_reaches_the_penalised_one():
    """The penalised fit starts from the plain optimum (a continuation); given no more iterations than the plain
    optimum alone takes, it still ends converged at the support it reaches with the default budget (the plain
    stage gets half the budget: with all of it, the penalty never acted and 33 terms came back, not 3)."""
    rng = np.random.default_rng(3)
    X = rng.standard_normal((300, 120))
    X[:, 1:] += 0.95 * X[:, :-1]  # neighbouring columns correlated: the plain stage takes 163 iterations
    w = np.zeros(120)
    w[[5, 40, 90]] = [2.0, -1.5, 1.0]
    y = X @ w + 0.5 * rng.standard_normal(300)
    plain = RVM(prune_nats=None).fit(X, y)
    assert len(plain.active_) > 20
    reference = RVM(prune_nats=3.0).fit(X, y)
    tight = RVM(prune_nats=3.0, max_iter=plain.n_iter_).fit(X, y)  # a RuntimeWarning (an error here) if not converged
    assert tight.converged_ and list(tight.active_) == list(reference.active_) == [5, 40, 90]
    assert np.all(tight.evidence_contribution_ >= 3.0)
