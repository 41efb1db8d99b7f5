"""The faster ways of computing what the refinement and its diagnostics need, each against the direct computation
it replaces: the same numbers (bit for bit where the shortcut falls back to it, to rounding elsewhere)."""

import casadi as ca
import numpy as np
import pytest

import symsbl
from symsbl import Multisine, paper, simulate, systems, time_grid
from symsbl._base.blas import one_blas_thread
from symsbl._base.lsq import GRAM_COND, Gram, lstsq
from symsbl._data.residuals import PREWHITEN_ORDER, innovations, past_removed, prewhitening
from symsbl._refine.candidates import partial_cosines
from symsbl._refine.rows import CHUNK, term_values


@pytest.fixture(autouse=True)
def _one_blas_thread():
    with one_blas_thread():
        yield


def _lags(x: np.ndarray, first: int, count: int, top: int) -> np.ndarray:
    n = x.size
    return np.column_stack([x[top - i : n - i] for i in range(first, first + count)])


def _prewhitening_by_order(u: np.ndarray, max_order: int = PREWHITEN_ORDER) -> np.ndarray:
    """The filter chosen by BIC, each order fitted on its own by numpy's least squares."""
    x = u - u.mean()
    n = x.size
    best, best_bic = np.ones(1), n * np.log(max(float(x @ x) / n, 1e-300))
    y = x[max_order:]
    for p in range(1, min(max_order, n // 10) + 1):
        X = _lags(x, 1, p, max_order)
        coef = np.linalg.lstsq(X, y, rcond=None)[0]
        var = float(np.mean((y - X @ coef) ** 2))
        bic = y.size * np.log(max(var, 1e-300)) + p * np.log(y.size)
        if bic < best_bic:
            best, best_bic = np.concatenate([[1.0], -coef]), bic
    return best


def test_the_normal_equations_agree_with_the_svd_where_well_conditioned():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((5000, 12)) * np.arange(1, 13)  # cond(X) about 12
    y = X @ rng.standard_normal(12) + rng.standard_normal(5000)
    gram = Gram(X, y)
    w = np.linalg.eigvalsh(gram.G)
    assert w[-1] < GRAM_COND * w[0]
    np.testing.assert_allclose(lstsq(X, y), np.linalg.lstsq(X, y, rcond=None)[0], rtol=1e-11, atol=0)
    for p in (1, 5, 12):
        np.testing.assert_allclose(gram.coef(p), np.linalg.lstsq(X[:, :p], y, rcond=None)[0], rtol=1e-11, atol=0)


def test_collinear_columns_are_truncated_as_the_svd_truncates_them():
    t = np.arange(20000) / 32768
    x = np.sin(2 * np.pi * 10 * t)  # the lags of a sine span two dimensions
    X, y = _lags(x, 1, 6, 6), x[6:]
    gram = Gram(X, y)
    for p in (3, 6):  # the minimum-norm solution of the rank-2 design, from its QR factor
        want = np.linalg.lstsq(X[:, :p], y, rcond=None)[0]
        np.testing.assert_allclose(gram.coef(p), want, rtol=0, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("kind", ["sine", "multisine", "ar2", "white"])
def test_prewhitening_chooses_the_filter_each_order_fitted_alone_chooses(kind):
    rng = np.random.default_rng(1)
    n = 20000
    t = np.arange(n) / 32768
    u = {
        "sine": 100 * np.sin(2 * np.pi * 10 * t),
        "multisine": Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)(t),
        "ar2": np.convolve(rng.standard_normal(n), [1.0, 0.9, 0.5], "same"),
        "white": rng.standard_normal(n),
    }[kind]
    got, want = prewhitening(u), _prewhitening_by_order(u)
    assert got.shape == want.shape
    # a multisine's lags are rank-deficient to rounding (cond 4e15): two solvers' filters whiten it alike to
    # rounding, not coefficient by coefficient
    whitened = innovations(u, want[1:])
    np.testing.assert_allclose(innovations(u, got[1:]), whitened, rtol=0, atol=1e-10 * np.std(u))
    if kind != "multisine":
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)
    kept = got.copy()
    got[:] = 0.0  # the filter kept for the next call of the same input is a copy
    np.testing.assert_array_equal(prewhitening(u), kept)


def test_the_past_input_is_removed_as_numpy_least_squares_removes_it():
    rng = np.random.default_rng(2)
    u = np.convolve(rng.standard_normal(30000), [1.0, 0.6], "same")
    uf = innovations(u, prewhitening(u)[1:])
    e = rng.standard_normal(uf.size) + 0.3 * np.roll(uf, 3)
    order = 100
    X = _lags(uf, 0, order + 1, order)
    want = e[order:] - X @ np.linalg.lstsq(X, e[order:], rcond=None)[0]
    got = past_removed(e, uf, order)
    np.testing.assert_allclose(got[order:], want, rtol=0, atol=1e-10 * np.abs(e).max())
    np.testing.assert_array_equal(got[:order], np.mean(e))


def _projected_cosine(A: np.ndarray, j: int, v: np.ndarray) -> float:
    """Column ``j`` of ``A`` and ``v``, each less its least-squares fit on ``A``'s other columns."""
    others = np.delete(A, j, axis=1)

    def rest(x):
        return x - others @ np.linalg.lstsq(others, x, rcond=None)[0] if others.shape[1] else x

    a, b = rest(A[:, j]), rest(v)
    return float(abs(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b)))


def test_partial_cosines_are_those_of_each_column_projected_alone():
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, 4000)
    v = rng.uniform(-1, 1, 4000)
    A = np.column_stack([x, v, x**3])
    near = x**3 - 0.5 * v + 1e-4 * np.sin(7 * x)  # nearly in span(A): a difference of squares would lose digits
    V = np.column_stack([np.sin(x), np.tan(x), x * np.abs(x), v**2, np.sign(v), x**5, np.exp(x), near])
    got = partial_cosines(A, V)
    for j in range(A.shape[1]):
        for k in range(V.shape[1]):
            assert got[j, k] == pytest.approx(_projected_cosine(A, j, V[:, k]), rel=1e-9, abs=1e-12)
    assert got[0, 0] > 0.99  # sin(x) looks like x once x^3 is accounted for


@pytest.mark.parametrize("n", [1, 700, CHUNK, 2 * CHUNK + 37])
def test_term_values_are_casadis_evaluation_of_every_row(n):
    duffing = systems.duffing()
    library = paper(duffing.states, duffing.inputs, degree=3)
    train = simulate(duffing, time_grid(1.5, 8192), inputs=Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1))
    Z = np.column_stack([train.states, train.inputs])[:n]

    class Model:  # term_values reads the symbols only
        states, inputs = duffing.states, duffing.inputs

    exprs = [t.expr for t in library.terms]
    f = ca.Function("terms", [ca.vertcat(*duffing.states, *duffing.inputs)], [ca.vertcat(*exprs)])
    want = np.asarray(f.map(n)(Z.T)).T
    np.testing.assert_array_equal(term_values(exprs, Model, Z), want)


def _duffing_case(seconds: float, fs: float, seed: int = 0):
    duffing = systems.duffing()
    train = simulate(
        duffing, time_grid(seconds, fs), inputs=Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)
    ).with_noise(0.01, seed=seed)
    x1, x2, F = duffing.states[0], duffing.states[1], duffing.inputs[0]
    library = symsbl.custom([x2, x1, x1**3, x2**3, x1**2, F], [x1, x2, F])
    return train, library


def test_a_trial_step_stopped_once_refused_leaves_every_fit_as_it_was(monkeypatch):
    """A Levenberg-Marquardt trial ends its pass once the cost summed so far refuses it (the cost only grows); the
    refinement is the same, bit for bit, as when every trial runs to the end of the record, in fewer samples
    simulated."""
    from symsbl._refine.sensitivity import Passes

    train, library = _duffing_case(1.0, 4096)
    start = symsbl.identify(train, library, refine=False)
    original = Passes._chunks
    counts = {"stopped": 0, "whole": 0, "unstopped": 0}

    def counted(self, *args):
        done = original(self, *args)
        counts["stopped" if not done else "whole"] += 1
        return done

    monkeypatch.setattr(Passes, "_chunks", counted)
    fast = symsbl.refine(start, train, library=library)
    assert counts["stopped"] > 0, counts

    def whole(self, buf, call, seg, ar, sw, z0, outs, sums, residual, stop=None, rows=None, pick=None):
        done = original(self, buf, call, seg, ar, sw, z0, outs, sums, residual, None, rows, pick)
        assert done  # no stop: every pass runs to the end of the record
        counts["unstopped"] += 1
        return done

    monkeypatch.setattr(Passes, "_chunks", whole)
    slow = symsbl.refine(start, train, library=library)
    assert counts["unstopped"] > counts["whole"], counts  # the trials stopped before run whole now
    assert str(fast) == str(slow)
    for a, b in zip(fast.equations, slow.equations):
        np.testing.assert_array_equal(a.coefs, b.coefs)
    assert fast.metadata["refine"]["log_evidence"] == slow.metadata["refine"]["log_evidence"]


def test_the_model_path_of_long_data_scores_first_stretches_and_keeps_a_fit_on_every_sample(monkeypatch):
    """Data longer than PATH_SAMPLES: the path fits and cross-validates each record's first stretch, and chooses
    the same structure here; a structure other than the evidence's is refitted on every sample, to the optimum
    the refinement of that structure on every sample reaches."""
    from symsbl._refine import path
    from symsbl._refine.engine import Settings

    train, library = _duffing_case(2.0, 4096)
    start = symsbl.identify(train, library, refine=False)
    whole = symsbl.refine(start, train, library=library)
    half = train.n_samples // 2
    monkeypatch.setattr(path, "PATH_SAMPLES", half)
    seen = []
    original = path._union

    def union(start, refined, records, measured, settings):
        seen.append([r.n_samples for r in records])
        return original(start, refined, records, measured, settings)

    monkeypatch.setattr(path, "_union", union)
    short = symsbl.refine(start, train, library=library)
    assert seen == [[half]]
    assert [eq.names for eq in short.equations] == [eq.names for eq in whole.equations]
    assert all(eq.n_rows == train.n_samples for eq in short.equations if not eq.fixed)

    measured = ("x1", "x2")
    engine, alpha, theta0, _ = original(start, whole, [train.slice(0, half)], measured, Settings())
    sol = engine.fit(engine.base, theta0, alpha)
    full, refit = path._refitted(engine, sol, [train], measured, cost=0.0)
    assert full.records[0].n_samples == train.n_samples
    reference = symsbl.refine(start, train, select=False)
    got = path.to_model(full, refit, {})
    for a, b in zip(got.equations, reference.equations):
        assert a.names == b.names
        stds = np.array([t.std for t in b.terms])
        assert np.all(np.abs(a.coefs - b.coefs) < 0.05 * stds), (a.coefs, b.coefs, stds)


def test_a_structure_that_runs_away_on_every_sample_leaves_the_evidences(monkeypatch):
    """Data longer than PATH_SAMPLES: a structure chosen on the first stretches and refitted on every sample is
    dropped when that refit runs away, and the evidence's structure (fitted on every sample) is kept, the path
    saying so."""
    from symsbl._refine import path

    train, library = _duffing_case(2.0, 4096)
    start = symsbl.identify(train, library, refine=False)
    monkeypatch.setattr(path, "PATH_SAMPLES", train.n_samples // 2)
    calls = []

    def runs_away(engine, sol, records, measured, cost, seed=None):
        calls.append([r.n_samples for r in records])
        return None

    evidence = symsbl.refine(start, train, library=library, selection=symsbl.SelectionRule(model_choice="evidence"))
    monkeypatch.setattr(path, "_refitted", runs_away)
    # a rule that takes the path's simplest structure, which is not the evidence's
    monkeypatch.setattr(symsbl.SelectionRule, "choose", lambda self, sizes, *_, **__: (int(np.argmin(sizes)), "least"))
    model = symsbl.refine(start, train, library=library)
    assert calls == [[train.n_samples]]
    assert model.path.chosen.source == "evidence"
    assert "ran away on every sample" in model.path.rule
    assert [eq.names for eq in model.equations] == [eq.names for eq in evidence.equations]


def test_the_model_path_scores_records_a_little_past_its_bound_whole():
    """Up to PATH_MARGIN times PATH_SAMPLES the records are scored whole (1 s at 32768 Hz is 32769 samples: cut
    by one sample, its chosen structure would be refitted whole for nothing); past it, first stretches."""
    from symsbl._refine.path import PATH_MARGIN, PATH_SAMPLES, _shortened

    train, _ = _duffing_case(1.0, 32768)
    assert train.n_samples == PATH_SAMPLES + 1
    assert _shortened([train], PATH_SAMPLES) == [train]
    longer = int(PATH_MARGIN * PATH_SAMPLES) + 2
    cut = _shortened([train, train.slice(0, longer - train.n_samples)], PATH_SAMPLES)
    assert sum(r.n_samples for r in cut) <= PATH_SAMPLES + 1


def test_the_residual_tests_of_long_data_read_each_segments_first_stretch():
    """Up to TEST_SAMPLES every segment is tested whole; past it, each segment's first stretch, in proportion to
    its length and long enough for the tests' lags, about TEST_SAMPLES samples in all."""
    from symsbl._refine.diagnostics import LAGS, TEST_SAMPLES, _tested_ends

    starts = np.array([0, 1000, 5000])
    np.testing.assert_array_equal(_tested_ends(starts, 9000), [1000, 5000, 9000])
    n = 4 * TEST_SAMPLES
    starts = np.array([0, 120, n // 4, n // 2])
    ends = _tested_ends(starts, n)
    whole = np.append(starts[1:], n) - starts
    assert np.all(ends > starts) and np.all(ends - starts <= whole)
    assert ends[0] - starts[0] == min(whole[0], 4 * LAGS)
    np.testing.assert_array_equal(ends[2:] - starts[2:], whole[2:] // 4)
    assert abs(int(np.sum(ends - starts)) - TEST_SAMPLES) <= 4 * LAGS


def test_a_warm_start_from_whole_records_holds_only_where_the_continuation_would_reach_them():
    """The refined fit starts the path's fits only when it held one segment per record, its model amplifies no
    state error PHI_STOP-fold within them and no shorter segments are asked for; it then starts each record (or
    its first stretch) as one segment from the fitted initial state, with the fit's noise."""
    from types import SimpleNamespace as Stub

    from symsbl._refine.solver import PHI_STOP, restarted

    prefixes = Stub(records=Stub(starts=np.array([0, 100]), lengths=np.array([100, 60])))
    seed = Stub(
        starts=np.array([0, 200]),
        X0=np.arange(6.0).reshape(2, 3),
        w=np.ones((2, 1)),
        ar=None,
        stages=[{"length": 200, "growth": 1.0}],
    )
    warm = restarted(seed, prefixes)
    assert warm is not None and warm.length == 100 and list(warm.starts) == [0, 100]
    assert np.array_equal(warm.X0, seed.X0) and warm.X0 is not seed.X0
    assert restarted(Stub(**{**vars(seed), "starts": np.array([0, 50, 200])}), prefixes) is None
    # growth PHI_STOP^4 over 200 samples: PHI_STOP-fold within 50, shorter than the 100-sample record
    assert restarted(Stub(**{**vars(seed), "stages": [{"length": 200, "growth": PHI_STOP**4}]}), prefixes) is None
    assert restarted(seed, prefixes, longest=64) is None
