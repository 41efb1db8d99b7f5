"""The autoregressive noise model of output-error residuals against least squares, scipy's filters, the
asymptotic covariance of the AR estimate and the variance of a long simulation."""

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from symsbl._base.blas import one_blas_thread
from symsbl._refine.noise import MAX_ORDER, NoiseModel, choose_order, fit_ar, innovations

#: A clearly coloured, stable AR(2): ``A(q) = 1 - 1.5 q^-1 + 0.7 q^-2``, poles of radius sqrt(0.7) = 0.84.
AR2 = np.array([-1.5, 0.7])


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """Every test in one BLAS thread: the many small least squares here cost up to 20 times more when a threaded
    BLAS splits them over busy cores."""
    with one_blas_thread():
        yield


def _ar(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``A(q) r = w`` from rest: the residual whose innovations are ``w``."""
    return scipy.signal.lfilter([1.0], np.concatenate([[1.0], a]), w)


def _one_segment(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``since`` and ``run`` of one contiguous, fully measured segment."""
    return np.arange(n), np.arange(1, n + 1)


def _segments(lengths: list[int], valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``since`` (samples since the segment start) and ``run`` (consecutive valid samples ending at each row),
    built by a plain loop as the refinement builds them from its segment starts and validity mask."""
    since, run = np.zeros(valid.size, dtype=np.int64), np.zeros(valid.size, dtype=np.int64)
    row = 0
    for length in lengths:
        for k in range(length):
            since[row] = k
            run[row] = (run[row - 1] + 1 if row > 0 else 1) if valid[row] else 0
            row += 1
    return since, run


def test_fit_ar_recovers_ar2_within_asymptotic_standard_errors():
    """20 000 samples of an AR(2) (sigma = 0.3): each coefficient within 4 standard errors of the truth,
    with the covariance ``sigma^2 R^-1 / N`` (``R`` the 2 x 2 Toeplitz matrix of the exact autocovariance,
    from the impulse response of ``1 / A(q)``), and the innovation variance within 4 of its own standard
    errors (``sigma^2 sqrt(2 / N)``) of ``sigma^2``."""
    n, sigma = 20000, 0.3
    r = _ar(AR2, sigma * np.random.default_rng(0).standard_normal(n))
    a, var, rows = fit_ar(r, *_one_segment(n), order=2)

    impulse = np.zeros(4000)
    impulse[0] = 1.0
    psi = _ar(AR2, impulse)
    gamma = [sigma**2 * float(psi[: psi.size - k] @ psi[k:]) for k in range(2)]
    se = np.sqrt(np.diag(sigma**2 * np.linalg.inv(scipy.linalg.toeplitz(gamma)) / n))
    assert rows == n - 2
    assert np.all(np.abs(a - AR2) < 4 * se), (a, se)
    assert abs(var - sigma**2) < 4 * sigma**2 * np.sqrt(2 / n), var


@pytest.mark.parametrize("order, hold", [(0, None), (2, None), (3, None), (2, 6)])
def test_fit_ar_over_segments_equals_brute_force_least_squares(order, hold):
    """Three segments with unmeasured (NaN) samples and one finite sample flagged invalid: coefficients,
    innovation variance and row count equal a least squares built row by row from every sample at least
    ``hold`` after its segment start whose ``hold`` predecessors and itself are all measured."""
    lengths = [120, 200, 90]
    rng = np.random.default_rng(1)
    r = np.concatenate([_ar(AR2, rng.standard_normal(m)) for m in lengths])
    r[[150, 151, 230, 380]] = np.nan
    valid = np.isfinite(r)
    valid[60] = False  # a finite sample the record marks as not measured
    since, run = _segments(lengths, valid)
    h = order if hold is None else hold

    ys, xs, start = [], [], 0
    for length in lengths:
        for t in range(start + h, start + length):
            window = slice(t - h, t + 1)
            if np.all(valid[window]) and np.all(np.isfinite(r[window])):
                ys.append(r[t])
                xs.append([r[t - i] for i in range(1, order + 1)])
        start += length
    y, X = np.array(ys), np.array(xs).reshape(len(ys), order)
    if order:
        coef = np.linalg.lstsq(X, y, rcond=None)[0]
        expected_a, expected_var = -coef, float(np.mean((y - X @ coef) ** 2))
    else:
        expected_a, expected_var = np.zeros(0), float(np.mean(y**2))

    a, var, n = fit_ar(r, since, run, order, hold=hold)
    assert n == y.size
    np.testing.assert_allclose(a, expected_a, rtol=1e-10, atol=1e-12)
    assert var == pytest.approx(expected_var, rel=1e-10)


def test_innovations_equal_scipy_fir_filter_and_undo_the_ar_filter():
    """``innovations(r, a)`` equals ``scipy.signal.lfilter([1, a_1 .. a_p], [1], r)`` past the first ``p``
    samples, and applied to ``r = lfilter([1], [1, a], w)`` from rest it gives back ``w``."""
    rng = np.random.default_rng(2)
    r = rng.standard_normal(500)
    for a in (np.array([0.4]), AR2, np.array([0.3, -0.2, 0.1, 0.05])):
        np.testing.assert_allclose(
            innovations(r, a), scipy.signal.lfilter(np.concatenate([[1.0], a]), [1.0], r)[a.size :], rtol=0, atol=1e-12
        )
    w = rng.standard_normal(500)
    np.testing.assert_allclose(innovations(_ar(AR2, w), AR2), w[2:], rtol=0, atol=1e-10)
    np.testing.assert_array_equal(innovations(r, np.zeros(0)), r)


def test_choose_order_is_zero_on_white_noise_and_two_on_ar2():
    """BIC over orders 0 .. MAX_ORDER on 2000 samples in two segments, over 10 seeds: order 0 for white
    noise and order 2 for the AR(2) on at least 9 seeds each (BIC is consistent)."""
    lengths = [1200, 800]
    since, run = _segments(lengths, np.ones(sum(lengths), dtype=bool))
    white, ar2 = 0, 0
    for seed in range(10):
        rng = np.random.default_rng(10 + seed)
        white += choose_order(rng.standard_normal(sum(lengths)), since, run) == 0
        r = np.concatenate([_ar(AR2, rng.standard_normal(m)) for m in lengths])
        ar2 += choose_order(r, since, run, MAX_ORDER) == 2
    assert white >= 9, white
    assert ar2 >= 9, ar2


def test_spectrum_gain_equals_impulse_response_energy_and_simulated_variance_ratio():
    """Per channel of a zero-padded model (AR(2), AR(1) a = 0.5, white): the gain equals the sum of squared
    impulse-response coefficients of ``1 / A(q)`` from ``scipy.signal.lfilter`` (and ``1 / (1 - a^2)`` for
    the AR(1), 1 for white noise), and var(noise) / var(innovations) of a 200 000-sample simulation
    within 3 %; each channel's own order is its last nonzero coefficient."""
    model = NoiseModel(np.array([AR2, [0.5, 0.0], [0.0, 0.0]]))
    assert model.order == 2
    assert model.orders() == [2, 1, 0]
    gain = model.spectrum_gain()

    impulse = np.zeros(20000)
    impulse[0] = 1.0
    energy = [float(np.sum(_ar(row, impulse) ** 2)) for row in model.ar]
    np.testing.assert_allclose(gain, energy, rtol=1e-10)
    assert gain[1] == pytest.approx(1 / (1 - 0.5**2), rel=1e-12)
    assert gain[2] == 1.0
    np.testing.assert_array_equal(NoiseModel.white(3).spectrum_gain(), np.ones(3))

    w = np.random.default_rng(3).standard_normal(200000)
    for row, g in zip(model.ar, gain):
        v = _ar(row, w)[1000:]  # past the start-up transient
        assert np.var(v) / np.var(w[1000:]) == pytest.approx(g, rel=0.03)


def test_spectrum_gain_near_the_unit_circle_and_beyond():
    """A pole at 0.998 (stable, slow): ``1 / (1 - a^2)`` = 250.25, not cut short; a pole outside the unit circle:
    inf, without an overflow warning."""
    gain = NoiseModel(np.array([[-0.998], [-1.1]])).spectrum_gain()
    assert gain[0] == pytest.approx(1 / (1 - 0.998**2), rel=1e-9)
    assert gain[1] == np.inf
