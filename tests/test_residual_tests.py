"""Residual statistics against textbook formulas written out by hand, scipy's distributions, closed forms for
autoregressive processes and their levels over many seeds."""

import numpy as np
import pytest
import scipy.signal
from scipy import stats

from symsbl._base.blas import one_blas_thread
from symsbl._data.residuals import (
    LEVEL,
    MODEL_ERROR,
    SPLINE_LAGS,
    cross_correlation,
    effective_fraction,
    explained_out_of_sample,
    ljung_box,
    predictable,
    prewhitening,
    residual_test,
)


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """Every test in one BLAS thread: the many small least squares here cost up to 20 times more when a threaded
    BLAS splits them over busy cores."""
    with one_blas_thread():
        yield


def _ar1(a: float, w: np.ndarray) -> np.ndarray:
    """``x_t = a x_{t-1} + w_t`` from rest."""
    return scipy.signal.lfilter([1.0], [1.0, -a], w)


def _delayed(x: np.ndarray, lag: int) -> np.ndarray:
    """``x_{t - lag}`` (zero before the start)."""
    return np.concatenate([np.zeros(lag), x[: x.size - lag]])


def _autocovariance(x: np.ndarray, k: int) -> float:
    """``1/N sum_t (x_t - mean)(x_{t-k} - mean)`` by a plain loop."""
    x = x - x.mean()
    return sum(x[t] * x[t - k] for t in range(k, x.size)) / x.size


def test_ljung_box_equals_the_textbook_statistic_and_chi2_p_value():
    """``Q = N (N + 2) sum_k rho_k^2 / (N - k)`` with ``rho_k`` the sample autocorrelation written out by
    hand, and p = ``scipy.stats.chi2.sf(Q, lags - n_params)``, for white and AR(1) series."""
    rng = np.random.default_rng(0)
    for e in (rng.standard_normal(300), _ar1(0.3, rng.standard_normal(300))):
        n, lags = e.size, 12
        rho = [_autocovariance(e, k) / _autocovariance(e, 0) for k in range(1, lags + 1)]
        q = n * (n + 2) * sum(rho[k - 1] ** 2 / (n - k) for k in range(1, lags + 1))
        for n_params in (0, 2):
            got_q, got_p = ljung_box(e, lags, n_params)
            assert got_q == pytest.approx(q, rel=1e-10)
            assert got_p == pytest.approx(stats.chi2.sf(q, lags - n_params), rel=1e-10)


def test_ljung_box_level_on_white_noise_and_power_on_ar1():
    """200 white series of 200 samples, 10 lags: rejections at 5 % inside the 99.9 % binomial interval of
    Binomial(200, 0.05); an AR(1) with a = 0.5 over 500 samples is rejected (p < 1e-6)."""
    rejected = sum(ljung_box(np.random.default_rng(seed).standard_normal(200), 10)[1] < 0.05 for seed in range(200))
    low, high = stats.binom.interval(0.999, 200, 0.05)
    assert low <= rejected <= high, rejected
    assert ljung_box(_ar1(0.5, np.random.default_rng(1).standard_normal(500)))[1] < 1e-6


def test_cross_correlation_equals_hand_formula_and_bartlett_band():
    """Coloured ``e`` and ``u``: ``rho(tau) = 1/N sum_t e_t u_{t - tau} / sqrt(R_e(0) R_u(0))`` (centred) written
    out by hand at lags -7, -1, 0, 2, 5, and the band ``sqrt(P / (N R_e(0) R_u(0)))`` with
    ``P = sum_{|k| <= lags} (1 - |k| / (lags + 1)) R_e(k) R_u(k)`` likewise."""
    rng = np.random.default_rng(2)
    n, lags = 400, 10
    e, u = _ar1(0.6, rng.standard_normal(n)), _ar1(-0.4, rng.standard_normal(n)) + 0.3
    rho, band = cross_correlation(e, u, lags)
    ec, uc = e - e.mean(), u - u.mean()
    scale = np.sqrt(_autocovariance(e, 0) * _autocovariance(u, 0))
    for tau in (-7, -1, 0, 2, 5):
        hand = sum(ec[t] * uc[t - tau] for t in range(max(tau, 0), n + min(tau, 0))) / n / scale
        assert rho[lags + tau] == pytest.approx(hand, rel=1e-10)
    p = sum(
        (1 - abs(k) / (lags + 1)) * _autocovariance(e, abs(k)) * _autocovariance(u, abs(k))
        for k in range(-lags, lags + 1)
    )
    np.testing.assert_allclose(band, np.sqrt(p / (n * scale**2)), rtol=1e-10)


def test_cross_correlation_band_is_the_spread_of_rho_under_independence():
    """Independent series: for white ``e`` and ``u`` the band times sqrt(N) is within 10 % of 1 at N = 1000
    and N = 16 000 (it scales like 1 / sqrt(N)); for two independent AR(1) with a = 0.8 (Bartlett: twice
    1 / sqrt(N)) it is within 15 % of the standard deviation of ``rho`` over 100 seeds (pooled over lags)."""
    rng = np.random.default_rng(3)
    for n in (1000, 16000):
        _, band = cross_correlation(rng.standard_normal(n), rng.standard_normal(n))
        assert band[0] * np.sqrt(n) == pytest.approx(1.0, rel=0.1)
    n, rhos, bands = 1000, [], []
    for seed in range(100):
        rng = np.random.default_rng(100 + seed)
        rho, band = cross_correlation(_ar1(0.8, rng.standard_normal(n)), _ar1(0.8, rng.standard_normal(n)))
        rhos.append(rho)
        bands.append(band[0])
    spread = np.sqrt(np.mean(np.array(rhos) ** 2))
    assert np.mean(bands) == pytest.approx(spread, rel=0.15)
    assert spread * np.sqrt(n) > 1.5  # the uncorrected 1 / sqrt(N) band would be half as wide


def test_prewhitening_recovers_the_filter_of_an_ar1_input():
    """An AR(1) input with a = 0.8 over 2000 samples: the filter is ``[1, -a]`` within 4 standard errors
    (``sqrt((1 - a^2) / N)``), and the filtered input passes Ljung-Box at 1 %; a white input is left
    unfiltered (``[1]``)."""
    n, a = 2000, 0.8
    rng = np.random.default_rng(4)
    u = _ar1(a, rng.standard_normal(n))
    f = prewhitening(u)
    assert f.size == 2 and f[0] == 1.0
    assert abs(f[1] + a) < 4 * np.sqrt((1 - a**2) / n), f
    assert ljung_box(scipy.signal.lfilter(f, [1.0], u)[f.size :])[1] > 0.01
    np.testing.assert_array_equal(prewhitening(rng.standard_normal(n)), [1.0])


def test_residual_depending_on_past_input_peaks_at_positive_lag():
    """``e_t = 0.3 u_{t-3} + w_t`` (white ``u``, ``w``, 1000 samples, 3 seeds): ``|rho|`` peaks at
    ``tau = +3`` (the docstring: ``tau > 0``, the residual depends on past inputs), the input ratio
    exceeds 1 (not independent) and the feedback ratio stays below 1 (open loop)."""
    n, lags = 1000, 25
    for seed in range(3):
        rng = np.random.default_rng(20 + seed)
        u = rng.standard_normal(n)
        e = 0.3 * _delayed(u, 3) + rng.standard_normal(n)
        rho, _ = cross_correlation(e, u, lags)
        assert np.argmax(np.abs(rho)) - lags == 3
        test = residual_test("y", e, {"u": u}, lags)
        assert test.input_ratio["u"] > 1 and not test.independent, test
        assert test.feedback_ratio["u"] < 1 and test.open_loop, test


def test_feedback_from_past_residuals_peaks_at_negative_lag():
    """``u_t = 0.5 e_{t-5} + w_t`` (white ``e``, ``w``, 1000 samples, 3 seeds): ``|rho|`` peaks at
    ``tau = -5`` (``tau < 0``: the input depends on past residuals), the feedback ratio exceeds 1 (not open
    loop) while the input ratio stays below 1; the same loop at ``tau = -1 .. -SPLINE_LAGS`` is outside the
    documented feedback lags ``-lags .. -3`` and at ``-SPLINE_LAGS - 1`` inside them."""
    n, lags = 1000, 25
    for seed in range(3):
        rng = np.random.default_rng(30 + seed)
        e, w = rng.standard_normal(n), rng.standard_normal(n)
        u = 0.5 * _delayed(e, 5) + w
        rho, _ = cross_correlation(e, u, lags)
        assert np.argmax(np.abs(rho)) - lags == -5
        test = residual_test("y", e, {"u": u}, lags)
        assert test.feedback_ratio["u"] > 1 and not test.open_loop, test
        assert test.input_ratio["u"] < 1 and test.independent, test
    for delay in range(1, SPLINE_LAGS + 1):
        assert residual_test("y", e, {"u": 0.5 * _delayed(e, delay) + w}, lags).open_loop
    assert not residual_test("y", e, {"u": 0.5 * _delayed(e, SPLINE_LAGS + 1) + w}, lags).open_loop


@pytest.mark.parametrize("a_e, a_u, n_seeds", [(0.0, 0.0, 100), (0.7, 0.9, 100)], ids=["white", "coloured"])
def test_residual_test_false_alarms_at_most_the_family_wise_level(a_e, a_u, n_seeds):
    """Independent ``e`` and ``u`` (500 samples; white, or AR(1) with a = 0.7 and 0.9 so that prewhitening
    and the band's colour correction are exercised): the input test and the feedback test each raise an
    alarm on no more seeds than the 99.9 % quantile of Binomial(n_seeds, LEVEL) (family-wise level LEVEL
    over each test's lags)."""
    input_alarms = feedback_alarms = 0
    for seed in range(n_seeds):
        rng = np.random.default_rng(200 + seed)
        e, u = _ar1(a_e, rng.standard_normal(500)), _ar1(a_u, rng.standard_normal(500))
        test = residual_test("y", e, {"u": u})
        input_alarms += not test.independent
        feedback_alarms += not test.open_loop
    bound = stats.binom.ppf(0.999, n_seeds, LEVEL)
    assert input_alarms <= bound, input_alarms
    assert feedback_alarms <= bound, feedback_alarms


def test_residual_test_whiteness_and_family_threshold():
    """The whiteness verdict is Ljung-Box's p-value against LEVEL (an AR(1) residual with a = 0.5 is not
    white, p equal to ``ljung_box`` with the noise model's ``n_params``); ``family = 4`` divides every ratio
    by the Sidak quantile ``z = Phi^-1(1 - (1 - (1 - LEVEL)^(1 / ((lags + 1) family))) / 2)`` relative to
    ``family = 1``."""
    rng = np.random.default_rng(5)
    e, u = _ar1(0.5, rng.standard_normal(800)), rng.standard_normal(800)
    one = residual_test("y", e, {"u": u}, 20, n_params=1)
    assert one.whiteness_p == ljung_box(e, 20, 1)[1]
    assert not one.white and one.whiteness_p < LEVEL
    four = residual_test("y", e, {"u": u}, 20, n_params=1, family=4)
    z1, z4 = (stats.norm.isf((1 - (1 - LEVEL) ** (1 / (21 * k))) / 2) for k in (1, 4))
    assert four.input_ratio["u"] == pytest.approx(one.input_ratio["u"] * z1 / z4, rel=1e-12)
    assert four.feedback_ratio["u"] == pytest.approx(one.feedback_ratio["u"] * z1 / z4, rel=1e-12)


def test_predictable_share_of_white_noise_and_ar1():
    """White noise (2000 samples, 25 lags, mean over 5 seeds): within a factor 2 of ``lags / (N - lags)``,
    the expected R^2 of a regression on unrelated regressors. AR(1) with a = 0.8 (5000 samples): within
    0.03 of the one-step predictable share ``1 - sigma_w^2 / var(x) = a^2 = 0.64``."""
    n, lags = 2000, 25
    share = np.mean([predictable(np.random.default_rng(40 + s).standard_normal(n), lags) for s in range(5)])
    assert 0.5 < share / (lags / (n - lags)) < 2.0, share
    assert predictable(_ar1(0.8, np.random.default_rng(6).standard_normal(5000)), lags) == pytest.approx(0.64, abs=0.03)


def test_effective_fraction_of_white_noise_and_ar1():
    """White noise (20 000 samples): above 0.95. AR(1) with a = 0.5 and 0.9: within 20 % of the closed form
    ``(1 - a) / (1 + a)`` the docstring gives (the sum truncated at ``|rho| < 0.05`` overestimates slightly)."""
    rng = np.random.default_rng(7)
    assert effective_fraction(rng.standard_normal(20000)) > 0.95
    for a in (0.5, 0.9):
        got = effective_fraction(_ar1(a, rng.standard_normal(20000)))
        assert got == pytest.approx((1 - a) / (1 + a), rel=0.2), (a, got)


def test_explained_out_of_sample_is_the_signal_share_and_nothing_for_a_stranger():
    """``e = A b + w`` (4000 samples, 6 columns, unit-variance w, var(A b) = 3): within 0.03 of the signal's share
    3 / 4. White innovations against 6 independent AR(1) columns with a = 0.98 (the narrow-band trajectory of a
    lightly damped system), 10 seeds: the share is about ``-k / n_train`` (estimation error on the held-out fold,
    -6 / 2000 = -0.003): mean within 0.002 of it, every seed below 0.01 (:data:`MODEL_ERROR` is 0.05)."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((4000, 6))
    b = np.array([1.0, -1.0, 0.5, 0.5, 0.5, 0.5])
    assert explained_out_of_sample(A @ b + rng.standard_normal(4000), A) == pytest.approx(0.75, abs=0.03)
    shares = []
    for seed in range(10):
        g = np.random.default_rng(100 + seed)
        C = np.column_stack([_ar1(0.98, g.standard_normal(4000)) for _ in range(6)])
        shares.append(explained_out_of_sample(g.standard_normal(4000), C))
    assert np.mean(shares) == pytest.approx(-0.003, abs=0.002), shares
    assert max(shares) < 0.01 < MODEL_ERROR, shares


def _servo(seed: int, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """An integrating plant ``q'' = u + d - 2 q'`` (Euler, 1 kHz, 20000 samples) driven by a random force ``d``
    the record lacks, under a slow random reference: in a loop, a PD controller acting on the position and
    velocity of 5 samples before; in the open, the reference itself. The free-run residual of the exact model
    (the plant without ``d``, driven by the measured ``u``) and ``u``."""
    rng = np.random.default_rng(seed)
    n, h, delay = 20000, 1e-3, 5
    b, a = scipy.signal.butter(2, 0.01)
    r = 20.0 * scipy.signal.lfilter(b, a, rng.standard_normal(n))
    d = 200.0 * rng.standard_normal(n)
    s, sim, past = np.zeros(2), np.zeros(2), [np.zeros(2)] * delay
    e, u = np.empty(n), np.empty(n)
    for t in range(n):
        measured = past[-delay]
        past.append(s.copy())
        u[t] = 400.0 * (r[t] - measured[0]) - 40.0 * measured[1] if closed else 20.0 * r[t]
        e[t] = s[0] - sim[0]
        s = s + h * np.array([s[1], u[t] + d[t] - 2.0 * s[1]])
        sim = sim + h * np.array([sim[1], u[t] - 2.0 * sim[1]])
    return e, u


def test_feedback_is_found_under_a_free_run_residual_that_drifts():
    """An integrating plant in a delayed PD loop with a random force the record lacks (:func:`_servo`): the exact
    model's free-run residual drifts (its past predicts it almost wholly), and only once whitened by its own
    filter does the loop show (28 x the threshold; 0.16-0.50 with the input's filter alone); in the open loop,
    the same residual raises no alarm (3 seeds each)."""
    for seed in range(3):
        e, u = _servo(seed, closed=True)
        assert predictable(e) > 0.99
        closed = residual_test("q", e, {"u": u})
        assert closed.feedback_ratio["u"] > 5 and not closed.open_loop, closed
        e, u = _servo(seed, closed=False)
        assert residual_test("q", e, {"u": u}).open_loop
